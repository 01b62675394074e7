"""The training loop of CVA-Net (paper section 3.3), with checkpoints, resume and DDP.

One process trains on CPU or one GPU. Launched by ``torchrun`` (``WORLD_SIZE`` > 1 in the
environment), every process trains a disjoint share of each epoch's samples and PyTorch's
DistributedDataParallel averages the gradients; rank 0 validates and writes every file.
"""

from __future__ import annotations

from collections.abc import Callable
import contextlib
from dataclasses import dataclass, fields
import datetime
from functools import partial
import gc
import hashlib
import json
import math
import os
from pathlib import Path
import shutil
import signal
import sys
import threading
import time
from typing import Any, TypeVar, cast

import numpy as np
import torch
from torch import nn

from cva_confidence_ros import strict_json
from cva_confidence_ros.datasets import (
    StereoSample,
    fit_disparity_range,
    list_scenes,
    load_scene,
    skipped_notice,
)
from cva_confidence_ros.datasets.synthetic import synthetic_pair
from cva_confidence_ros.errors import ConfigError, DataError, ModelError, reason
from cva_confidence_ros.memory import memory_left as available_memory
from cva_confidence_ros.memory import size_text
from cva_confidence_ros.model import (
    ARCHITECTURES,
    PATCH_SIZE,
    predict_confidence_at,
    resolve_device,
    save_weights,
)
from cva_confidence_ros.outputs import (
    check_output_dir,
    check_output_file,
    torch_save_atomic,
    write_text_atomic,
)
from cva_confidence_ros.training.card import card_paths, hardware_facts, write_model_card
from cva_confidence_ros.training.config import TrainConfig, parse_dataset_spec
from cva_confidence_ros.training.data import (
    LabelledScene,
    PreparedScene,
    SampleIndex,
    VolumeCache,
    batches,
    dense_crops,
    epoch_order,
    flip_draws,
    gather_crops,
    gather_extracts,
    prepare_scene,
    sample_index,
    validation_subset,
    volume_bytes,
)
from cva_confidence_ros.training.distill import (
    distillation_loss,
    load_init_weights,
    load_teacher,
    teacher_logits,
)

__all__ = [
    'CHECKPOINT_NAME',
    'VAL_SEED_OFFSET',
    'Stopped',
    'available_memory',
    'stop_on_signals',
    'train',
]

CHECKPOINT_NAME = 'checkpoint.pt'
_HISTORY_NAME = 'history.json'
#: Synthetic validation pairs use seeds from here on, disjoint from the training seeds.
VAL_SEED_OFFSET = 1_000_000
# Fields that must not change between a run and its resume: they decide the samples, the
# network or the steps of every epoch.
_RESUME_KEYS = (
    'matcher',
    'max_disparity',
    'datasets',
    'max_scenes',
    'synthetic',
    'synthetic_size',
    'synthetic_seed',
    'mode',
    'crop_size',
    'vflip',
    'batch_size',
    'samples_per_epoch',
    'seed',
    'arch',
    'teacher',
    'distill_weight',
    'init_weights',
)
# Keys added after the first checkpoints were written: those checkpoints ran with the defaults.
_RESUME_DEFAULTS = {
    field.name: field.default
    for field in fields(TrainConfig)
    if field.name in ('arch', 'teacher', 'distill_weight', 'init_weights', 'vflip')
}
# Fields that decide the learning rate (and LGC-Net's stage) of each epoch. A resume may change
# them as long as every finished epoch keeps its learning rate and stage: more epochs at the
# end, never another rate for an epoch already trained.
_SCHEDULE_KEYS = ('epochs', 'epochs_low_lr', 'lr', 'low_lr_factor')
#: (stage, learning rate) of each epoch of a run.
Schedule = list[tuple[str, float]]
#: Labelled training pixels whose logits are checked after each epoch (NaN, infinity).
_PROBE_PIXELS = 256
#: Share of the available memory the cost volumes may take without a note: matching a scene
#: needs its float32 volume on top, and the network and batches need some.
_VOLUME_SHARE = 0.8


_T = TypeVar('_T')


class Stopped(KeyboardInterrupt):
    """A run stopped by SIGTERM or SIGINT (``signum``); ``saved`` says what its checkpoint
    holds where the run wrote one on the way out ('' where it did not)."""

    def __init__(self, signum: int, saved: str = '') -> None:
        super().__init__(signal.Signals(signum).name)
        self.signum = signum
        self.saved = saved


class _Signals:
    """What :func:`stop_on_signals` caught: within the steps of a one-process run
    (``deferring``) a signal is noted in ``received`` and the run stops at the end of its
    step, after a checkpoint of it."""

    deferring = False
    received: int | None = None


_SIGNALS = _Signals()


@contextlib.contextmanager
def stop_on_signals() -> Any:
    """Turn SIGTERM (a Slurm preemption, ``kill``, torchrun ending its workers) and SIGINT
    into :class:`Stopped` meanwhile (main thread only).

    SIGTERM ended the process at once, without a word, and a run preempted in an hours-long
    epoch lost all of it. Within an epoch's steps of a one-process run the signal is noted
    and the run checkpoints the step it reached first (a second signal stops it at once);
    under torchrun the processes would stop at different steps, so they stop at once and a
    resume starts from the last checkpoint (``--checkpoint-every`` writes them within epochs).
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, _frame: object) -> None:
        if _SIGNALS.deferring and _SIGNALS.received is None:
            _SIGNALS.received = signum
            return
        raise Stopped(signum)

    previous = {sig: signal.signal(sig, handler) for sig in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        for sig, action in previous.items():
            signal.signal(sig, action)
        _SIGNALS.deferring, _SIGNALS.received = False, None


@dataclass(frozen=True)
class _Dist:
    rank: int
    world: int
    device: torch.device

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.world > 1:
            torch.distributed.barrier()

    def sum(self, values: list[float]) -> list[float]:
        """Element-wise sum of ``values`` over all processes."""
        if self.world == 1:
            return values
        tensor = torch.tensor(values, dtype=torch.float64, device=self.device)
        torch.distributed.all_reduce(tensor)
        return tensor.tolist()

    def settle(self, error: Exception | None) -> None:
        """The barrier after work of the main process alone (validation, files): every
        process learns whether that work failed, and all stop together.

        A bare barrier left the other processes waiting for the main one as long as its
        process lived after the error (a caller that catches it), then ended them with gloo's
        'Connection closed by peer'.

        Raises:
            Exception: ``error``, on the process that met it.
            ModelError: On the other processes, when the main process failed.
        """
        if self.world > 1:
            failed = self.sum([float(error is not None)])[0] > 0
            if failed:
                # The group is left as it is: ended here, DDP's reducer would hold its last
                # reference, and freeing that with the GIL held (as the error unwinds) waits
                # for a gloo thread that needs the GIL to let go of this exchange's tensor.
                if error is None:
                    raise ModelError(
                        f'process 0 of {self.world} stopped with an error (its message is in '
                        f'its output); process {self.rank} stops with it'
                    )
        if error is not None:
            raise error

    def close(self) -> None:
        """End the process group after the last collective, its gloo threads included.

        Call it with DistributedDataParallel's wrapper dropped: its reducer holds the group.
        gloo's worker threads let go of a finished work a moment after the caller saw it done;
        one that still held the last all_reduce's tensors when the interpreter shut down took
        the GIL of a finalising interpreter and aborted the process (``terminate called
        without an active exception``, SIGABRT after every file was written: about 1 run in
        100 under load). A group that nothing holds any more joins those threads as it ends.
        """
        if self.world > 1:
            gc.collect()  # the wrapper and its reducer sit in reference cycles
            torch.distributed.destroy_process_group()

    def on_main(self, work: Callable[[], _T], default: _T) -> _T:
        """``work()`` on the main process, ``default`` on the others; an error of the main
        process is raised on every process (see :meth:`settle`)."""
        result, error = default, None
        if self.main:
            try:
                result = work()
            except Exception as exc:  # raised again by settle, on every process
                error = exc
        self.settle(error)
        return result


def _setup_distributed(device: str) -> _Dist:
    world = int(os.environ.get('WORLD_SIZE', '1'))
    resolved = resolve_device(device)
    if world <= 1:
        return _Dist(0, 1, resolved)
    rank = int(os.environ['RANK'])
    local_rank = int(os.environ.get('LOCAL_RANK', '0'))
    if resolved.type == 'cuda':
        resolved = torch.device('cuda', local_rank)
        torch.cuda.set_device(resolved)
    backend = 'nccl' if resolved.type == 'cuda' else 'gloo'
    if not torch.distributed.is_initialized():
        # Imported before the group exists: its functions take ``group=group.WORLD`` as a
        # default, bound at import, and DDP imports it; imported later, those defaults held the
        # group for good and destroy_process_group left its threads running (see close).
        import torch.distributed.nn as _distributed_nn  # noqa: F401

        torch.distributed.init_process_group(backend)
    return _Dist(rank, world, resolved)


class _Logits(nn.Module):
    """Forward = logits, so that DistributedDataParallel wraps the call the loss uses."""

    def __init__(self, net: nn.Module) -> None:
        super().__init__()
        self.net = net

    def forward(self, volume: torch.Tensor) -> torch.Tensor:
        # Any registered cost-volume network (CVA-Net, -Lite, -Fast) has forward_logits.
        forward_logits = cast('Callable[[torch.Tensor], torch.Tensor]', self.net.forward_logits)
        return forward_logits(volume)


class _Log:
    """Messages to stderr and ``out/train.log`` (main process only)."""

    def __init__(self, path: Path, enabled: bool) -> None:
        self.path = path
        self.enabled = enabled

    def __call__(self, message: str) -> None:
        if not self.enabled:
            return
        stamp = datetime.datetime.now().isoformat(timespec='seconds')
        print(message, file=sys.stderr, flush=True)
        with self.path.open('a', encoding='utf-8') as handle:
            handle.write(f'{stamp} {message}\n')


def _load_samples(
    config: TrainConfig, validation: bool, log: Callable[[str], None] | None = None
) -> list[tuple[str, Callable[[], StereoSample]]]:
    """(label, loader) per scene, loaded lazily so that only one pair is in memory at a time;
    scenes left out for a missing file (a partial download) are named through ``log``."""
    specs = config.val_datasets if validation else config.datasets
    loaders: list[tuple[str, Callable[[], StereoSample]]] = []
    root = config.val_root if validation else config.data_root
    for spec in specs:
        name, split = parse_dataset_spec(spec)
        notice = skipped_notice(name, root, split) if log is not None else ''
        if notice and log is not None:
            log(notice)
        for scene in list_scenes(name, root, split)[: config.max_scenes]:
            loaders.append((f'{name}/{scene}', partial(load_scene, name, root, scene, split)))
    count = config.val_synthetic if validation else config.synthetic
    first = config.synthetic_seed + (VAL_SEED_OFFSET if validation else 0)
    height, width = config.synthetic_hw
    for seed in range(first, first + count):
        pair = partial(synthetic_pair, seed, height, width, config.max_disparity)
        loaders.append((f'synthetic/seed{seed}', pair))
    return loaders


_Scene = TypeVar('_Scene', bound=LabelledScene)


def _prepare(
    loaders: list[tuple[str, Callable[[], StereoSample]]],
    config: TrainConfig,
    validation: bool,
    log: _Log,
    prepare: Callable[[StereoSample, str, int], _Scene],
    seen: dict[str, str] | None = None,
    same: SamePairs | None = None,
    repeats: list[tuple[str, str]] | None = None,
    cache: VolumeCache | None = None,
) -> list[_Scene]:
    """The scenes of ``loaders`` (:func:`_load_samples`), each prepared by ``prepare`` (the
    cost-volume networks' :func:`prepare_scene`; the disparity-map networks'
    ``prepare_disparity_scene``), one line of log each.

    A pair met before (the same images and ground truth under another name, here or in
    ``seen``, which collects the pairs across calls: pass the training call's to the
    validation call) is taken once, and said so: data sets that ship one another's frames
    would weigh it twice, or validate on a training scene. ``same`` (a resume) checks each
    pair taken against the run's before it is matched. ``repeats`` collects (label, label of
    the pair met before) of the pairs not taken. ``cache`` (``--volume-cache``) keeps the
    cost volumes on disk, keyed by the pair's digest, instead of ``prepare``.
    """
    seen = {} if seen is None else seen
    scenes: list[_Scene] = []
    for label, loader in loaders:
        tic = time.perf_counter()
        sample = loader()
        fingerprint = _pair_fingerprint(sample)
        # Met before also under its own name: a validation root (--val-data-root) names its
        # scenes as the training root does (stereo_folder/scene0 in both).
        first = seen.get(fingerprint)
        if first is not None:
            log(
                f'{"val " if validation else ""}scene {label}: the same pair as {first} (taken '
                'once)'
            )
            if repeats is not None:
                repeats.append((label, first))
            continue
        seen[fingerprint] = label
        if same is not None:
            same.take(len(scenes), label, fingerprint)
        if cache is not None:
            scene = cast('_Scene', cache.prepare(
                sample, config.matcher, config.max_disparity, fingerprint
            ))
        else:
            scene = prepare(sample, config.matcher, config.max_disparity)
        scenes.append(scene)
        log(
            f'{"val " if validation else ""}scene {label}: {scene.shape[0]}×{scene.shape[1]} '
            f'(factor {scene.factor}), {scene.n_labelled} labelled, '
            f'{scene.n_wrong / max(1, scene.n_labelled):.1%} wrong, '
            f'{time.perf_counter() - tic:.1f} s'
        )
    if same is not None:
        same.done(len(scenes))
    return scenes


def training_pairs(seen: dict[str, str]) -> list[list[str]]:
    """[label, fingerprint] of the training pairs taken, in order: ``seen`` of
    :func:`_prepare`'s training call, kept in the checkpoint for :class:`SamePairs`."""
    return [[label, fingerprint] for fingerprint, label in seen.items()]


def _prepare_validation(
    loaders: list[tuple[str, Callable[[], StereoSample]]],
    config: TrainConfig,
    log: _Log,
    prepare: Callable[[StereoSample, str, int], _Scene],
    seen: dict[str, str],
    same: SamePairs | None = None,
    cache: VolumeCache | None = None,
) -> tuple[list[_Scene], list[list[str]]]:
    """The validation scenes (:func:`_prepare` after the training call, with its ``seen``)
    and their [label, fingerprint] pairs, kept in the checkpoint for :class:`SamePairs`.

    Raises:
        ConfigError: Every scene of the validation data sets is a training pair (the same
            images and ground truth): ``--val-data-root`` lets them share a data set name
            with the training data, so only their content tells.
    """
    before = len(seen)
    repeats: list[tuple[str, str]] = []
    scenes = _prepare(loaders, config, True, log, prepare, seen, same, repeats, cache)
    taken = training_pairs(seen)[before:]
    own = [label for label, _ in loaders if not label.startswith('synthetic/')]
    if own and not any(not label.startswith('synthetic/') for label, _ in taken):
        val, first = repeats[0]
        root = '--val-data-root' if config.val_data_root else '--data-root'
        raise ConfigError(
            f'validation data must be held apart from the training data; every scene of '
            f'--val-datasets {",".join(config.val_datasets)} in {root} {config.val_root} is a '
            f'training pair (the same images and ground truth): {val} there is {first}'
            + ('' if first.startswith('synthetic/') else f' of --data-root {config.data_root}')
            + (f' ({len(repeats)} such scenes)' if len(repeats) > 1 else '')
            + '; validate on scenes held out of training'
        )
    return scenes, taken


class SamePairs:
    """A resume's check that its training pairs are the run's (``train_pairs`` of the
    checkpoint), scene by scene before each is matched; with ``validation``, that its
    validation pairs are (``val_pairs``): the history compares the epochs on them.

    The data sets are read from ``--data-root``, which a resume may change (the data moved):
    another root of ``stereo_folder`` (or a data set whose scenes were added, removed or
    re-recorded) was taken with a note that 'the same data sets are read from the new
    place', and the run went on with other samples than its finished epochs; the card then
    listed only the new scenes. Synthetic pairs are compared by name (their seeds and size
    are settings the resume keeps): their pixels may differ by rounding between machines.
    A run that recorded no validation pairs (none, or a checkpoint from before they were
    kept) may gain them.
    """

    def __init__(self, checkpoint: Path, state: dict[str, Any], validation: bool = False) -> None:
        self.checkpoint = checkpoint
        key = 'val_pairs' if validation else 'train_pairs'
        self.recorded = [tuple(pair) for pair in state.get(key) or []]
        config = state['config']
        own_root = validation and bool(config.get('val_data_root'))
        self.option = '--val-data-root' if own_root else '--data-root'
        self.root = config.get('val_data_root' if own_root else 'data_root')
        self.what = 'validation' if validation else 'training'
        self.did = 'validated' if validation else 'trained'

    def _refuse(self, what: str) -> ConfigError:
        verb = 'were validated' if self.did == 'validated' else 'trained'
        return ConfigError(
            f"cannot resume from {self.checkpoint}: the {self.what} data differ from the run's "
            f'({what}); its finished epochs {verb} on the others: resume with those scenes '
            f'(the run read {self.option} {self.root}) or start over in another --out folder'
        )

    def take(self, position: int, label: str, fingerprint: str) -> None:
        """Refuse pair ``position`` (0-based) of this resume if the run's was another.

        Raises:
            ConfigError: Another scene there, or the same one with other pixels.
        """
        if not self.recorded:
            return  # a checkpoint from before the pairs were kept
        if position >= len(self.recorded):
            raise self._refuse(
                f'{label} is new: the run {self.did} on {len(self.recorded)} scenes'
            )
        was, digest = self.recorded[position]
        if was != label:
            raise self._refuse(f"scene {position + 1} is {label}, the run's was {was}")
        if digest != fingerprint and not label.startswith('synthetic/'):
            raise self._refuse(
                f'{label} holds other images or ground truth than when the run started'
            )

    def done(self, count: int) -> None:
        """Refuse a resume that took fewer pairs than the run.

        Raises:
            ConfigError: Naming the first pairs missing.
        """
        if self.recorded and count < len(self.recorded):
            missing = [label for label, _ in self.recorded[count:]]
            more = f' and {len(missing) - 3} more' if len(missing) > 3 else ''
            raise self._refuse(
                f'{", ".join(missing[:3])}{more} missing: the run {self.did} on '
                f'{len(self.recorded)} scenes, this one finds {count}'
            )


def _pair_fingerprint(sample: StereoSample) -> str:
    """A digest of a pair's images and ground truth (shapes and dtypes included)."""
    digest = hashlib.blake2b(digest_size=16)
    for array in (sample.left, sample.right, sample.disparity):
        array = np.ascontiguousarray(array)
        digest.update(f'{array.dtype.str}{array.shape}'.encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _plan_volumes(
    loaders: list[tuple[str, Callable[[], StereoSample]]],
    val_loaders: list[tuple[str, Callable[[], StereoSample]]],
    config: TrainConfig,
    log: Callable[[str], None],
    cache: VolumeCache | None,
    processes: int = 1,
) -> None:
    """Say before any matching what the scenes' cost volumes will take (memory, or the disk
    of ``--volume-cache``), and refuse a run whose volumes cannot fit.

    Every training scene's padded float16 volume stayed in memory (data.volume_bytes): all
    of KITTI 2012 + 2015 at D = 256 is 98 GB, and a run on a 64 GB workstation was killed by
    the system after an hour of matching, with no word. Each pair is read here (the halving
    that fits D needs its ground truth's largest disparity) but not matched; a pair met before
    is counted once, as :func:`_prepare` takes it once. Training volumes are held by each of
    the ``processes`` of a torchrun group on this machine, validation volumes by process 0.

    Raises:
        ConfigError: The volumes take more memory than is available (without a cache), or
            more disk than is free in the cache folder (what it does not hold yet).
    """
    tic = time.perf_counter()
    seen: set[str] = set()
    counts, sizes = [0, 0], [0, 0]  # training, validation
    cached = largest = 0
    for part, group in enumerate((loaders, val_loaders)):
        for _, loader in group:
            sample = loader()
            fingerprint = _pair_fingerprint(sample)
            if fingerprint in seen:
                continue
            seen.add(fingerprint)
            fitted, _ = fit_disparity_range(sample, config.max_disparity)
            height, width = fitted.left.shape[:2]
            size = volume_bytes(height, width, config.max_disparity)
            counts[part] += 1
            sizes[part] += size
            largest = max(largest, size)
            if cache is not None and cache.has(fingerprint, config.matcher, config.max_disparity):
                cached += size
    depth = config.max_disparity
    scenes = (
        f'{counts[0]} training scenes {size_text(sizes[0])}'
        # Copies in memory, not on disk: the processes map the same files.
        + (f' (× {processes} processes)' if processes > 1 and cache is None else '')
        + (f', {counts[1]} validation scenes {size_text(sizes[1])}' if counts[1] else '')
    )
    took = f'sized in {time.perf_counter() - tic:.1f} s'
    if cache is not None:
        total = sum(sizes)
        free = shutil.disk_usage(cache.folder).free
        log(
            f'cost volumes (float16, D = {depth}): {scenes}: {size_text(total)} on disk in '
            f'--volume-cache {cache.folder}, {size_text(cached)} of it there already, '
            f'{size_text(free)} free there ({took})'
        )
        if total - cached > free:
            raise ConfigError(
                f'--volume-cache {cache.folder}: the cost volumes still to write take '
                f'{size_text(total - cached)} ({scenes} at D = {depth}), more than the '
                f'{size_text(free)} free there; free space, give a folder on a larger disk, '
                'or train on fewer scenes (--max-scenes N)'
            )
        return
    need = sizes[0] * processes + sizes[1]
    available, source = available_memory()
    log(
        f'cost volumes (float16, D = {depth}): {scenes}: {size_text(need)} in memory for the '
        'whole run'
        + (f'; {size_text(available)} available ({source})' if available is not None else '')
        + f' ({took})'
    )
    if available is None:
        return
    if need > available:
        raise ConfigError(
            f'the cost volumes of this run take {size_text(need)} of memory ({scenes} at '
            f'D = {depth}, float16), more than the {size_text(available)} available '
            f'({source}): the system would end the run while it matches. Keep them on disk '
            f'with --volume-cache DIR ({size_text(sizes[0] + sizes[1])} there; epochs then '
            'read what the page cache does not hold from the disk), train on fewer scenes '
            '(--max-scenes N, fewer --datasets), or use a smaller --max-disparity'
        )
    if need + 2 * largest > _VOLUME_SHARE * available:
        log(
            f'note: the cost volumes take {need / available:.0%} of the available memory, and '
            f'matching a scene needs up to {size_text(3 * largest)} more (its float32 '
            'volume): the run may run short; --volume-cache DIR keeps the volumes on disk'
        )


def _scene_facts(scenes: list[PreparedScene]) -> list[dict[str, Any]]:
    return [
        {
            'name': s.name,
            'factor': s.factor,
            'height': s.shape[0],
            'width': s.shape[1],
            'labelled': s.n_labelled,
            'wrong': s.n_wrong,
        }
        for s in scenes
    ]


def check_finite_loss(loss: float, epoch: int, lr: float, out: Path) -> None:
    """Stop a diverged run before it overwrites the last good checkpoint with NaN weights.

    Raises:
        ModelError: ``loss`` is NaN or infinite (the same on every process: it is summed).
    """
    if not math.isfinite(loss):
        raise _diverged(f'the loss of epoch {epoch + 1} is {loss}', epoch, lr, out)


def _diverged(what: str, epoch: int, lr: float, out: Path) -> ModelError:
    """The error of a run that diverged in ``epoch`` (0-based), ``what`` saying how."""
    return ModelError(
        f'training diverged: {what} (lr {lr:g}); lower --lr. No weights were written'
        + (f'; the checkpoint in {out} still holds epoch {epoch}' if epoch else '')
    )


def _check_finite_network(
    net: nn.Module,
    scenes: list[PreparedScene],
    index: SampleIndex,
    dist: _Dist,
    epoch: int,
    lr: float,
    out: Path,
) -> str | None:
    """Stop a run whose last steps left weights that give non-finite logits: the loss of an
    epoch is that of the weights before each step, so it stays finite when only the last step
    diverged, and the checkpoint and weights file would take the broken weights.

    Returns what is wrong with a network that gives one confidence at every probed pixel,
    correct and wrong ones (a collapse, which later epochs may undo: the caller refuses the
    final weights of one), or None.

    The network runs as inference runs it (eval mode) on up to :data:`_PROBE_PIXELS` labelled
    training pixels spread over the index; the count is summed over the processes, so that
    all of them stop together.

    Raises:
        ModelError: Some logit is NaN or infinite.
    """
    count = min(_PROBE_PIXELS, len(index))
    chosen = np.linspace(0, len(index) - 1, count).round().astype(np.int64)
    volumes, targets = gather_extracts(scenes, index, chosen)
    training = net.training
    net.eval()
    try:
        with torch.no_grad():
            logits = _Logits(net)(volumes.to(dist.device)).float()
    finally:
        net.train(training)
    confidence = torch.sigmoid(logits.flatten())
    constant = one_confidence(confidence, targets, bool((volumes != volumes[0]).any()))
    bad, same = dist.sum([float((~torch.isfinite(logits)).sum()), float(constant)])
    if bad:
        raise _diverged(
            f'after epoch {epoch + 1}, {int(bad)} of {count * dist.world} logits of the network '
            'at training pixels are NaN or infinite',
            epoch,
            lr,
            out,
        )
    if same:
        return collapse_message(epoch, 'the network', float(confidence[0]), count)
    return None


def one_confidence(confidence: torch.Tensor, targets: torch.Tensor, inputs_vary: bool) -> bool:
    """Whether a network collapsed: one ``confidence`` at every probed training pixel
    although their inputs vary and their ``targets`` hold correct and wrong ones.

    A too-high --lr mostly leaves finite weights that give one confidence for any input
    (dead ReLUs: one logit; or logits of 1e5 and more: all 1.0), which the NaN checks let
    into the checkpoint and the weights file (lr 1: loss 21, val AUC that of a constant).
    Not where the probe is of one input or one class: one answer may then be right.
    """
    flat, labels = confidence.flatten(), targets.flatten()
    return (
        flat.numel() > 1
        and bool((flat == flat[0]).all())
        and inputs_vary
        and bool((labels != labels[0]).any())
    )


def collapse_message(epoch: int, name: str, value: float, count: int) -> str:
    """What :func:`one_confidence` found after ``epoch`` (0-based) in network ``name``."""
    return (
        f'after epoch {epoch + 1}, {name} gives one confidence ({value:g}) at all of {count} '
        'training pixels, correct and wrong ones: it no longer depends on its input'
    )


def _save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    """Write ``state`` beside ``path`` and move it in place.

    Raises:
        DataError: The checkpoint cannot be written (a full disk, a folder in the way); the
            one at ``path`` is left as it was.
    """
    try:
        # torch_save_atomic raises the file system's error (a full disk: ENOSPC), where torch's
        # own writer says '[enforce fail at inline_container.cc:…] unexpected pos …'.
        torch_save_atomic(path, state)
    except (OSError, RuntimeError) as exc:  # torch's writer raises RuntimeError
        kept = '; the one there was left as it was' if path.is_file() else ''
        raise DataError(f'cannot write checkpoint {path} ({reason(exc)}){kept}') from exc


def _write_history(out: Path, history: list[dict[str, Any]]) -> None:
    """``out/history.json``, replaced whole (a run stopped while writing it keeps the last)."""
    # NaN / inf as null: json.dumps wrote them as NaN / Infinity, which strict readers refuse.
    text = json.dumps(strict_json.json_ready(history), indent=2, allow_nan=False)
    write_text_atomic(out / _HISTORY_NAME, text + '\n',
                      'training history ')


def _schedule(config: TrainConfig) -> Schedule:
    """(stage, learning rate) of every epoch of a cost-volume network's run: one stage."""
    return [('single', config.lr_at(epoch)) for epoch in range(config.total_epochs)]


def _load_checkpoint(
    path: Path, config: TrainConfig, schedule: Callable[[TrainConfig], Schedule] = _schedule
) -> dict[str, Any]:
    """Read a training checkpoint and check that ``config`` may continue it.

    Args:
        path: The checkpoint (``out/checkpoint.pt``).
        config: The configuration of the resumed run.
        schedule: (stage, learning rate) of each epoch of a configuration's run.

    Raises:
        ModelError: ``path`` is not a readable cva-train checkpoint.
        ConfigError: A setting of :data:`_RESUME_KEYS` differs from the run's, or the new
            schedule gives a finished epoch another learning rate or stage, or has fewer
            epochs than are finished.
    """
    try:
        state = torch.load(path, map_location='cpu', weights_only=True)
    except Exception as exc:  # torch raises many unrelated types for a damaged file
        raise ModelError(f'cannot read checkpoint {path} ({reason(exc)})') from exc
    if isinstance(state, dict) and 'state_dict' in state and 'meta' in state:
        raise ModelError(
            f'{path} is a weights file, not a training checkpoint; to start from weights use '
            '--init-weights'
        )
    expected = {'epoch': int, 'model': dict, 'optimizer': dict, 'history': list, 'config': dict}
    wrong = (
        [name for name, kind in expected.items() if not isinstance(state.get(name), kind)]
        if isinstance(state, dict)
        else list(expected)
    )
    if wrong:
        raise ModelError(
            f'{path} is not a cva-train checkpoint: expected a dict with '
            f'{", ".join(expected)}; missing or wrong: {", ".join(wrong)}'
        )
    # Checkpoints written before ``arch`` existed are CVA-Net runs.
    saved = {**_RESUME_DEFAULTS, **state['config']}
    current = config.to_dict()
    changed = [k for k in _RESUME_KEYS if saved.get(k) != current.get(k)]
    if changed:
        detail = ', '.join(f'{k}: {saved.get(k)!r} → {current.get(k)!r}' for k in changed)
        raise ConfigError(
            f'cannot resume from {path}: the run was started with other settings ({detail}); '
            'use another --out folder or the original settings'
        )
    # An epoch stopped within keeps its learning rate too.
    within = 1 if state.get('partial') else 0
    _check_schedule(path, saved, config, int(state['epoch']) + within, schedule)
    return state


def _file_digest(path: Path) -> str:
    """The SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, 'rb') as handle:
        for block in iter(lambda: handle.read(1 << 20), b''):
            digest.update(block)
    return digest.hexdigest()


def _check_teacher(path: Path, state: dict[str, Any], teacher: str, digest: str) -> None:
    """Refuse a resume whose teacher file is not the one the run started with: the path
    alone is the same, its weights (SHA-256) are not (checkpoints from before the digest was
    kept are taken as they are)."""
    saved = state.get('teacher_sha256')
    if saved is not None and saved != digest:
        raise ConfigError(
            f'cannot resume from {path}: the teacher {teacher} is not the file the run started '
            f'with (SHA-256 {digest[:12]}…, was {saved[:12]}…); the finished epochs distilled '
            'from the other one: restore it, or start over in another --out folder'
        )


def _check_schedule(
    path: Path,
    saved: dict[str, Any],
    config: TrainConfig,
    finished: int,
    schedule: Callable[[TrainConfig], Schedule],
) -> None:
    """Refuse a resume whose schedule changes a finished epoch or ends before the finished
    ones; more epochs at the end (a longer run) are fine.

    Raises:
        ConfigError: Naming the changed settings of :data:`_SCHEDULE_KEYS`, old → new.
    """
    kept = {key: saved[key] for key in _SCHEDULE_KEYS if key in saved}
    changes = ', '.join(
        f'{key}: {value!r} → {getattr(config, key)!r}'
        for key, value in kept.items()
        if value != getattr(config, key)
    )
    changes = f' ({changes})' if changes else ''
    try:
        before = schedule(config.replace(**kept))
    except ConfigError as exc:
        raise ModelError(f'{path} holds an invalid training schedule ({exc})') from exc
    now = schedule(config)
    if finished > len(now):
        raise ConfigError(
            f'cannot resume from {path}: it holds {finished} finished epochs, this command '
            f'trains {len(now)} in all{changes}; to train on, keep or raise --epochs and '
            '--epochs-low-lr'
        )

    def rate(plan: tuple[str, float]) -> str:
        stage, lr = plan
        return f'lr {lr:g}' + ('' if stage == 'single' else f' ({stage} stage)')

    for epoch in range(min(finished, len(before))):
        (stage, lr), (new_stage, new_lr) = before[epoch], now[epoch]
        if stage != new_stage or not math.isclose(lr, new_lr, rel_tol=1e-9):
            raise ConfigError(
                f'cannot resume from {path}: finished epoch {epoch + 1} ran at '
                f'{rate(before[epoch])}, this command would run it at {rate(now[epoch])}'
                f'{changes}; a resume may only add epochs after the {finished} finished '
                'ones: use the original --lr, --low-lr-factor, --epochs and --epochs-low-lr '
                '(raised to train longer), or another --out folder'
            )


def _check_processes(path: Path, state: dict[str, Any], world: int) -> None:
    """Refuse a resume under another number of processes: each step averages the gradients
    of ``batch_size`` samples per process, so that number is part of the batch size.

    Raises:
        ConfigError: The checkpoint was written by a run of another number of processes
            (checkpoints written before it was recorded are not checked).
    """
    saved = state.get('processes')
    if saved is not None and int(saved) != world:
        raise ConfigError(
            f'cannot resume from {path}: the run trained in {saved} processes, this one in '
            f'{world} (processes: {saved} → {world}); a step learns from --batch-size samples '
            'per process, so run it with as many processes (torchrun --nproc_per_node '
            f'{saved}, or without torchrun for 1) or use another --out folder'
        )


def _validate(
    net: nn.Module,
    scenes: list[PreparedScene],
    subsets: list[tuple[np.ndarray, np.ndarray]],
    device: torch.device,
    epoch: int = 0,
    lr: float = 0.0,
    out: Path = Path(),
) -> dict[str, float | None]:
    """Validation scores of ``net`` after ``epoch`` (0-based; ``lr`` and ``out`` for the
    message of a diverged run).

    Raises:
        ModelError: A confidence is NaN or infinite (the network diverged).
    """
    from cva_confidence_ros.metrics import auc_scores

    confidences, wrongs = [], []
    for scene, (ys, xs) in zip(scenes, subsets, strict=True):
        if ys.size == 0:
            continue
        confidences.append(predict_confidence_at(net, scene.unpadded_volume(), ys, xs, device))
        wrongs.append(~scene.correct[ys, xs])
    if not confidences:
        return {'val_auc': None, 'val_auc_opt': None, 'val_error_rate': None, 'val_high': None}
    confidence = np.concatenate(confidences)
    bad = int(np.count_nonzero(~np.isfinite(confidence)))
    if bad:
        raise _diverged(
            f'after epoch {epoch + 1}, {bad} of {confidence.size} validation confidences are '
            'NaN or infinite',
            epoch,
            lr,
            out,
        )
    scores = auc_scores(confidence, np.concatenate(wrongs))
    return {
        **{f'val_{key}': float(scores[key]) for key in ('auc', 'auc_opt', 'error_rate')},
        # Share of outputs >= 0.5: near 1 means the network calls almost everything correct.
        'val_high': float(np.mean(confidence >= 0.5)),
    }


def _progress(total: int, description: str, enabled: bool) -> Any:
    from tqdm import tqdm

    return tqdm(
        total=total,
        desc=description,
        unit='sample',
        unit_scale=True,
        disable=not enabled,
        dynamic_ncols=True,
        leave=False,
    )


def _autocast(precision: str, device: torch.device) -> Any:
    """The autocast context of a training step (a no-op for float32)."""
    if precision == 'fp32':
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=torch.bfloat16)


def _share(items: np.ndarray, dist: _Dist) -> np.ndarray:
    """This process's share of ``items``: equal lengths on every process (DDP steps in lock
    step), the list wrapped around so that no item is left out."""
    if dist.world == 1:
        return items
    padded = np.resize(items, len(items) + (-len(items) % dist.world))  # np.resize cycles
    return padded[dist.rank :: dist.world]


def _steps(count: int, size: int, single_extract: bool) -> list[np.ndarray]:
    """Positions ``0 … count − 1`` of an epoch in steps of ``size`` inputs.

    Where an input is a single 13×13 extract (``single_extract``), a last step of one input
    joins the step before: batch normalisation cannot train on one extract (CVA-Net-Fast's
    fusion ends in one value per channel, which PyTorch refuses in training mode).
    """
    steps = list(batches(np.arange(count), size))
    if single_extract and len(steps) > 1 and steps[-1].size == 1:
        steps[-2:] = [np.concatenate(steps[-2:])]
    return steps


def _check_step_inputs(config: TrainConfig, world: int = 1) -> None:
    """Refuse a run whose steps would each hold a single 13×13 extract (``--batch-size 1``, or
    one sample an epoch for each of the ``world`` processes) when its network cannot train
    on one (see :func:`_steps`).

    Raises:
        ConfigError: Naming the options that make the steps that small.
    """
    samples = config.samples_per_epoch
    per_process = samples is not None and math.ceil(samples / max(world, 1)) == 1
    single = config.batch_size == 1 or per_process
    if not single or (config.mode == 'dense' and config.crop_size > 1):
        return
    net = ARCHITECTURES.get(config.arch)({'max_disparity': config.max_disparity}).train()
    probe = torch.zeros((1, 1, config.max_disparity, PATCH_SIZE, PATCH_SIZE))
    try:
        with torch.no_grad():
            _Logits(net)(probe)
    except ValueError as exc:
        causes = []
        if config.batch_size == 1:
            causes.append('--batch-size 1')
        if per_process:
            causes.append(
                f'--samples-per-epoch {samples}'
                + (f' over {world} processes' if world > 1 and samples != 1 else '')
            )
        if config.mode == 'dense' and config.crop_size == 1:
            causes.append('--crop-size 1')
        raise ConfigError(
            f'{" and ".join(causes)} make{"" if len(causes) > 1 else "s"} steps of a single '
            f'{PATCH_SIZE}×{PATCH_SIZE} extract, which --arch {config.arch} cannot train on '
            f'({reason(exc)}); use 2 or more'
            + (' samples per process' if world > 1 and per_process else '')
        ) from exc


def _run_epoch(
    config: TrainConfig,
    model: nn.Module,
    optimiser: torch.optim.Optimizer,
    scenes: list[PreparedScene],
    index: SampleIndex,
    n_samples: int,
    epoch: int,
    dist: _Dist,
    teacher: nn.Module | None = None,
    resume_at: dict[str, Any] | None = None,
    save_step: Callable[[dict[str, Any]], None] | None = None,
) -> tuple[float, int, float]:
    """One epoch; returns (mean loss over all processes, samples seen in all, seconds).

    ``resume_at`` (a checkpoint's ``partial``, see :func:`_step_state`) continues the epoch
    after its step; ``save_step`` checkpoints such a state every ``config.checkpoint_every``
    steps, and before a stop for a signal that :func:`stop_on_signals` noted.

    Raises:
        Stopped: After ``save_step``, for a noted signal.
    """
    model.train()
    device = dist.device
    tic = time.perf_counter()
    loss_sum = 0.0
    seen = 0
    first = 0
    if resume_at is not None:
        # Where the stopped epoch was: its steps done, each process's sums and dropout draws.
        first = int(resume_at['step'])
        sums = resume_at['sums'][dist.rank]
        loss_sum, seen = float(sums[0]), int(sums[1])
        torch.set_rng_state(resume_at['rng'][dist.rank])
        cuda_rng = resume_at['cuda_rng'][dist.rank]
        if device.type == 'cuda' and cuda_rng is not None:  # None: stopped on a CPU
            torch.cuda.set_rng_state(cuda_rng, device)
        tic -= float(resume_at['seconds'])
    if config.mode == 'sparse':
        order = _share(epoch_order(len(index), n_samples, config.seed, epoch), dist)
        flips = _share(flip_draws(n_samples, config.seed, epoch, config.vflip), dist)
        steps = _steps(len(order), config.batch_size, single_extract=True)
        total = len(order)
    else:
        crops = dense_crops(scenes, index, n_samples, config.crop_size, config.seed, epoch)
        order = _share(np.arange(len(crops.scene)), dist)
        flips = _share(flip_draws(len(crops.scene), config.seed, epoch, config.vflip), dist)
        side = min([config.crop_size] + [min(s.shape) for s in scenes])
        per_step = max(1, math.ceil(config.batch_size / side**2))
        steps = _steps(len(order), per_step, single_extract=side == 1)
        total = int(crops.n_labelled[order].sum())
    description = f'epoch {epoch + 1}/{config.total_epochs}'
    with _progress(total, description, config.progress and dist.main) as bar:
        bar.update(seen)
        for number, step in enumerate(steps[first:], first):
            autocast = _autocast(config.precision, device)
            if config.mode == 'sparse':
                volumes, targets = gather_extracts(scenes, index, order[step], flips[step])
                volumes, targets = volumes.to(device), targets.to(device)
                with autocast:
                    logits = model(volumes)[:, 0, 0].float()
                soft = None if teacher is None else teacher_logits(teacher, volumes)[:, 0, 0]
                loss = distillation_loss(logits, targets, soft, config.distill_weight)
                count = len(step)
            else:
                volumes, targets, mask = gather_crops(
                    scenes, crops, order[step], config.crop_size, flips[step]
                )
                volumes, targets, mask = volumes.to(device), targets.to(device), mask.to(device)
                with autocast:
                    logits = model(volumes).float()
                count = int(mask.sum())
                if count:
                    soft = None if teacher is None else teacher_logits(teacher, volumes)[mask]
                    loss = distillation_loss(
                        logits[mask], targets[mask], soft, config.distill_weight
                    )
                else:  # keep the graph (and DDP's gradient exchange) alive
                    loss = logits.sum() * 0.0
            optimiser.zero_grad(set_to_none=True)
            loss.backward()
            optimiser.step()
            loss_sum += float(loss.detach()) * count
            seen += count
            bar.update(count)
            elapsed = time.perf_counter() - tic
            bar.set_postfix(loss=f'{loss_sum / max(1, seen):.4f}', sps=f'{seen / elapsed:.0f}')
            done = number + 1
            # Only one process notes signals (stop_on_signals): every process decides alike.
            stop = _SIGNALS.received
            every = config.checkpoint_every
            if save_step is None or done == len(steps) or not (
                stop is not None or (every and done % every == 0)
            ):
                continue
            save_step(_step_state(done, loss_sum, seen, elapsed, dist))
            if stop is not None:
                raise Stopped(
                    stop, f'step {done} of {len(steps)} of epoch {epoch + 1}/{config.total_epochs}'
                )
    loss_total, seen_total = dist.sum([loss_sum, float(seen)])
    return loss_total / max(1.0, seen_total), int(seen_total), time.perf_counter() - tic


def _step_state(
    done: int, loss_sum: float, seen: int, seconds: float, dist: _Dist
) -> dict[str, Any]:
    """The ``partial`` of a checkpoint within an epoch after step ``done``: what
    :func:`_run_epoch` needs to go on from there as if it had not stopped (each process's loss
    sum, samples and random-number state: dropout draws)."""
    own: list[Any] = [
        [loss_sum, seen],
        torch.get_rng_state(),
        torch.cuda.get_rng_state(dist.device) if dist.device.type == 'cuda' else None,
    ]
    every: list[Any] = [own]
    if dist.world > 1:
        every = [None] * dist.world
        torch.distributed.all_gather_object(every, own)
    return {
        'step': done,
        'seconds': seconds,
        'sums': [part[0] for part in every],
        'rng': [part[1] for part in every],
        'cuda_rng': [part[2] for part in every],
    }


def train(config: TrainConfig, command: str = '') -> dict[str, Any]:
    """Train CVA-Net as configured; write checkpoints, log, weights and model card.

    Args:
        config: What to train on and how.
        command: The command line, recorded in the model card.

    Returns:
        The training summary (the ``meta`` stored in the weights and the model card's facts).

    Raises:
        ConfigError: Bad configuration, or ``resume`` with a checkpoint of other settings.
        DataError: Unreadable data, no labelled pixel, or a file that cannot be written.
        ModelError: Unreadable checkpoint; under torchrun, on the other processes, an error
            of process 0 in the work it does alone (validation, files).
    """
    from cva_confidence_ros.model.baselines import BASELINE_ARCHS

    if config.arch in BASELINE_ARCHS:  # CCNN, LFN, LGC-Net learn from disparity + image
        from cva_confidence_ros.training.baselines import train_baseline

        return train_baseline(config, command)
    check_run_setup(config)
    _check_step_inputs(config, int(os.environ.get('WORLD_SIZE', '1')))
    dist = _setup_distributed(config.device)
    if dist.device.type == 'cuda':
        # Fixed crop shapes: let cuDNN time its kernels once and keep the fastest.
        torch.backends.cudnn.benchmark = True
    out = Path(config.out)
    log = _Log(out / 'train.log', dist.main)

    def begin() -> None:
        out.mkdir(parents=True, exist_ok=True)
        log(f'cva-train: {command or config.to_dict()}')

    dist.on_main(begin, None)
    started = time.perf_counter()

    # The checkpoint, and the weight files named on the command line, are checked before the
    # data are prepared (minutes on the full recipe): a resume with other settings is refused
    # first. The weight files are read into throwaway copies (the run's own loads below are
    # left as they were); --init-weights not on a resume, whose weights are the checkpoint's
    # (the file may have gone since the run started).
    checkpoint = out / CHECKPOINT_NAME
    state: dict[str, Any] | None = None
    if config.resume and checkpoint.is_file():
        state = _load_checkpoint(checkpoint, config)
        _check_processes(checkpoint, state, dist.world)
    if config.init_weights and state is None:
        spare = ARCHITECTURES.get(config.arch)({'max_disparity': config.max_disparity})
        load_init_weights(spare, config.init_weights, config.arch)
    teacher_digest = None
    if config.teacher:
        load_teacher(config.teacher, config.matcher, config.max_disparity, torch.device('cpu'))
        teacher_digest = _file_digest(Path(config.teacher))
        if state is not None:
            _check_teacher(checkpoint, state, config.teacher, teacher_digest)

    # Both listed before either is prepared: a missing validation scene costs no matching.
    loaders = _load_samples(config, False, log)
    val_loaders: list[tuple[str, Callable[[], StereoSample]]] = dist.on_main(
        lambda: _load_samples(config, True, log), []
    )
    # Made on every process (each prepares the training scenes); only process 0 logs.
    cache = VolumeCache(config.volume_cache, log) if config.volume_cache else None
    # Under torchrun, every process of this machine holds the training volumes.
    processes = int(os.environ.get('LOCAL_WORLD_SIZE', dist.world)) if dist.world > 1 else 1
    dist.on_main(
        partial(_plan_volumes, loaders, val_loaders, config, log, cache, processes), None
    )
    pairs: dict[str, str] = {}  # the pairs taken, to take each once
    same = None if state is None else SamePairs(checkpoint, state)
    scenes = _prepare(loaders, config, False, log, prepare_scene, pairs, same, cache=cache)
    train_pairs = training_pairs(pairs)
    index = sample_index(scenes)
    same_val = None if state is None else SamePairs(checkpoint, state, validation=True)
    nothing: tuple[list[PreparedScene], list[list[str]]] = ([], [])  # on the other processes
    val_scenes, val_pairs = dist.on_main(
        lambda: _prepare_validation(
            val_loaders, config, log, prepare_scene, pairs, same_val, cache
        ),
        nothing,
    )
    val_subsets = validation_subset(val_scenes, config.val_pixels, config.seed)
    n_samples = config.samples_per_epoch or len(index)
    log(
        f'{len(scenes)} training scenes, {len(index)} labelled pixels, '
        f'{index.fraction_wrong:.1%} labelled wrong; {n_samples} samples per epoch '
        f'({config.mode} mode); {len(val_scenes)} validation scenes; cost volumes '
        + size_text(sum(int(s.volume.nbytes) for s in [*scenes, *val_scenes]))
        + (f' on disk in --volume-cache {config.volume_cache}' if cache else ' in memory')
    )
    if index.fraction_wrong in (0.0, 1.0):
        # Ground truth made by the matcher itself (no lidar) labels every pixel correct: the
        # run went on without a word and taught the network to trust everything.
        kind = 'wrong' if index.fraction_wrong else 'correct'
        log(f'warning: every labelled training pixel is {kind} for {config.matcher}: the '
            "network cannot learn to tell correct from wrong (is the ground truth the "
            "matcher's own disparity?)")

    torch.manual_seed(config.seed)
    net = ARCHITECTURES.get(config.arch)({'max_disparity': config.max_disparity}).to(dist.device)
    init_meta = None if state is None else state.get('init_meta')
    if config.init_weights and state is None:
        init_meta = load_init_weights(net, config.init_weights, config.arch)
        log(f'initialised from {config.init_weights} ({_weights_facts(init_meta)})')
        if init_meta.get('matcher') != config.matcher:
            log(f'note: {config.init_weights} was trained on {init_meta.get("matcher")} cost '
                f'volumes; this run trains for {config.matcher} (a transfer across matchers)')
    teacher, teacher_meta = None, None
    if config.teacher:
        teacher, teacher_meta = load_teacher(
            config.teacher, config.matcher, config.max_disparity, dist.device
        )
        log(
            f'distilling from {config.teacher} ({_weights_facts(teacher_meta)}) with weight '
            f'{config.distill_weight}'
        )
    optimiser = torch.optim.Adam(net.parameters(), lr=config.lr, betas=(0.9, 0.999))
    history: list[dict[str, Any]] = []
    start_epoch = 0
    previous_wall = 0.0
    resume_at: dict[str, Any] | None = None
    if state is not None:
        try:
            net.load_state_dict(state['model'])
            optimiser.load_state_dict(state['optimizer'])
        except (KeyError, TypeError, ValueError, RuntimeError) as exc:
            raise ModelError(
                f'checkpoint {checkpoint} does not fit this network ({reason(exc)})'
            ) from exc
        history = list(state['history'])
        start_epoch = int(state['epoch'])
        previous_wall = float(state.get('wall_time_s', 0.0))
        resume_at = state.get('partial')
        log(
            f'resumed from {checkpoint} after epoch {start_epoch}'
            + (f', within epoch {start_epoch + 1} after its step {resume_at["step"]}'
               if resume_at else '')
        )
        # A run stopped between its checkpoint and history.json left that one short; a
        # resume with no epoch left to train would never write it.
        dist.on_main(partial(_write_history, out, history), None)
        if config.init_weights:
            log(f'note: {config.init_weights} not read again: the checkpoint holds the weights')
        started_with = state['config'].get('data_root')
        if started_with != config.data_root:
            log(f'note: the run was started with --data-root {started_with}, now '
                f'{config.data_root}: the same data sets are read from the new place')
        started_in = state['config'].get('precision', 'fp32')
        if started_in != config.precision:
            log(f'note: the run was started with --precision {started_in}, now '
                f'{config.precision}: the finished epochs keep their arithmetic, the card '
                f'names {config.precision}')
    elif config.resume:
        log(f'--resume: no checkpoint in {out}, starting from scratch')
    model: nn.Module = _Logits(net)
    if dist.world > 1:
        device_ids = [dist.device.index] if dist.device.type == 'cuda' else None
        model = nn.parallel.DistributedDataParallel(model, device_ids=device_ids)

    def run_state(finished: int) -> dict[str, Any]:
        """The checkpoint after ``finished`` epochs (and a ``partial`` one, added by
        ``save_step``)."""
        return {
            'format': 1,
            'epoch': finished,
            'model': {k: v.detach().cpu() for k, v in net.state_dict().items()},
            'optimizer': optimiser.state_dict(),
            'history': history,
            'config': config.to_dict(),
            'processes': dist.world,
            'wall_time_s': previous_wall + time.perf_counter() - started,
            'init_meta': _weights_facts(init_meta) if init_meta else None,
            'teacher_sha256': teacher_digest,
            'train_pairs': train_pairs,
            'val_pairs': val_pairs,
            'weights_out_path': weights_out_path(config),
        }

    def save_step(epoch: int, part: dict[str, Any]) -> None:
        """Checkpoint within ``epoch`` (0-based) after ``part['step']`` (every process)."""
        dist.on_main(
            lambda: _save_checkpoint(checkpoint, {**run_state(epoch), 'partial': part}), None
        )

    def finish_epoch(epoch: int, record: dict[str, Any]) -> None:
        """Validate, checkpoint, history and log line of an epoch (the main process)."""
        lr = record['lr']
        record.update(_validate(net, val_scenes, val_subsets, dist.device, epoch, lr, out))
        history.append(record)
        _save_checkpoint(checkpoint, run_state(epoch + 1))
        _write_history(out, history)
        val = record.get('val_auc')
        log(
            f'epoch {epoch + 1}/{config.total_epochs}: lr {lr:.1e}, loss '
            f'{record["train_loss"]:.4f}, {record["samples"]} samples in '
            f'{record["seconds"]:.1f} s ({record["samples_per_s"]:.1f}/s)'
            + (
                f', val AUC {val:.4f} (optimal {record["val_auc_opt"]:.4f}), '
                f'{record["val_high"]:.1%} of val outputs >= 0.5'
                if val is not None
                else ''
            )
        )

    try:
        for epoch in range(start_epoch, config.total_epochs):
            lr = config.lr_at(epoch)
            for group in optimiser.param_groups:
                group['lr'] = lr
            # Dropout draws depend on (seed, epoch, rank) only: a resumed epoch repeats exactly.
            torch.manual_seed(config.seed * 1_000_003 + epoch * 7919 + dist.rank + 1)
            # One process notes a signal and stops after the step (and the checkpoint) it is in.
            _SIGNALS.deferring = dist.world == 1
            loss, seen, seconds = _run_epoch(
                config, model, optimiser, scenes, index, n_samples, epoch, dist, teacher,
                resume_at if epoch == start_epoch else None, partial(save_step, epoch),
            )
            check_finite_loss(loss, epoch, config.lr_at(epoch), out)
            collapsed = _check_finite_network(net, scenes, index, dist, epoch, lr, out)
            if collapsed and epoch + 1 == config.total_epochs:
                raise _diverged(collapsed, epoch, lr, out)  # no such weights as the final ones
            if collapsed:
                log(f'warning: {collapsed} (lr {lr:g}); lower --lr unless later epochs undo it')
            record: dict[str, Any] = {
                'epoch': epoch + 1,
                'lr': lr,
                'train_loss': loss,
                'samples': seen,
                'seconds': seconds,
                'samples_per_s': seen / max(seconds, 1e-9),
            }
            dist.on_main(partial(finish_epoch, epoch, record), None)
            if _SIGNALS.received is not None:  # in the last step, the checks or the checkpoint
                raise Stopped(_SIGNALS.received, f'epoch {epoch + 1}/{config.total_epochs}')
    finally:
        # Also when the run fails (a diverged epoch, a bad batch): left on, it made the next
        # run of this process (a notebook's, a test's) ignore a signal while it prepared its
        # scenes, until its first step was done.
        _SIGNALS.deferring = False

    wall = previous_wall + time.perf_counter() - started
    last = history[-1] if history else {}
    summary: dict[str, Any] = {
        'arch': config.arch,
        'matcher': config.matcher,
        'max_disparity': config.max_disparity,
        'mode': config.mode,
        # The side run: the smallest scene side where that is smaller (dense_crops).
        'crop_size': min([config.crop_size] + [min(scene.shape) for scene in scenes]),
        'vflip': config.vflip,
        'datasets': list(config.datasets),
        'synthetic': config.synthetic,
        'synthetic_size': list(config.synthetic_hw),
        'scenes': _scene_facts(scenes),
        'labelled_pixels': len(index),
        'fraction_wrong': index.fraction_wrong,
        'val_datasets': list(config.val_datasets),
        'val_data_root': config.val_data_root,
        'val_synthetic': config.val_synthetic,
        'val_scenes': _scene_facts(val_scenes),
        'val_pixels': int(sum(ys.size for ys, _ in val_subsets)),
        'samples_per_epoch': n_samples,
        'samples_seen': int(sum(r['samples'] for r in history)),
        'epochs': config.epochs,
        'epochs_low_lr': config.epochs_low_lr,
        'batch_size': config.batch_size,
        'precision': config.precision,
        'lr': config.lr,
        'lr_low': config.lr * config.low_lr_factor,
        'seed': config.seed,
        'teacher': config.teacher,
        'teacher_meta': _weights_facts(teacher_meta) if teacher_meta else None,
        'distill_weight': config.distill_weight,
        'init_weights': config.init_weights,
        'init_meta': _weights_facts(init_meta) if init_meta else None,
        'hardware': hardware_facts(dist.device, dist.world),
        'wall_time_s': wall,
        'command': command,
        'final_train_loss': last.get('train_loss'),
        'final_val_auc': last.get('val_auc'),
        'final_val_auc_opt': last.get('val_auc_opt'),
        'final_val_error_rate': last.get('val_error_rate'),
        'final_val_high': last.get('val_high'),
        'history': history,
        'date': datetime.date.today().isoformat(),
    }

    def write_weights() -> None:
        if config.weights_out:
            path = save_weights(net, config.weights_out, summary)
            md_path, json_path = write_model_card(path, summary)
            log(f'wrote {path}, {md_path} and {json_path}')

    dist.on_main(write_weights, None)
    del model  # DistributedDataParallel's reducer holds the process group
    dist.close()
    return summary


def _weights_facts(meta: dict[str, Any]) -> dict[str, Any]:
    """The identifying facts of a weights file's meta (not its whole history)."""
    keys = ('arch', 'matcher', 'max_disparity', 'samples_seen', 'command', 'date')
    return {key: meta.get(key) for key in keys if key in meta}


def check_run_options(config: TrainConfig) -> None:
    """The refusals of :func:`check_run_setup` that touch no path (before ``--out`` is made).

    Raises:
        ConfigError: The matcher is not registered, or ``resume`` and ``overwrite`` are both
            set.
    """
    from cva_confidence_ros.matching import MATCHERS

    if config.matcher not in MATCHERS:
        raise ConfigError(
            f'unknown matcher {config.matcher!r}; expected one of {MATCHERS.names()}'
        )
    if config.resume and config.overwrite:
        # The resume won, silently: the earlier run went on instead of a fresh one.
        raise ConfigError(
            '--resume continues the run in --out, --overwrite starts it afresh; give one'
        )


def check_run_setup(config: TrainConfig) -> None:
    """Refuse an unknown matcher or output paths that cannot be written (before hours of
    training, not after them); apply ``config.threads`` to numba and torch. With
    ``overwrite``, remove the checkpoint and history of the earlier run in ``out``: a run
    stopped before its first checkpoint would otherwise be resumed from that one.

    Raises:
        ConfigError: The matcher is not registered, ``resume`` and ``overwrite`` are both
            set, ``out`` / ``weights_out`` cannot be written, ``weights_out`` (or its card)
            is the checkpoint or history of ``out``, or exists without ``overwrite`` (or
            ``resume`` of the run in ``out`` started with that ``weights_out``).
    """
    check_run_options(config)
    # The weights file first: the check of --out makes that folder.
    if config.weights_out:
        check_output_file(config.weights_out, '--weights-out')
    out = check_output_dir(config.out, '--out')
    checkpoint = out / CHECKPOINT_NAME
    if config.weights_out:
        # The weights (or their card) over the checkpoint or the history: a resume then
        # found a weights file, or history.json a model card.
        run_files = {(out / name).resolve(): name for name in (CHECKPOINT_NAME, _HISTORY_NAME)}
        for target in (Path(config.weights_out), *card_paths(config.weights_out)):
            if target.resolve() in run_files:
                raise ConfigError(
                    f'--weights-out {config.weights_out}: {target} would replace the '
                    f'{run_files[target.resolve()]} of the run in --out {out}; write the '
                    'weights elsewhere or under another name'
                )
    if config.weights_out and not config.overwrite:
        # A run was replacing the shipped models/*.pt and their cards (or an earlier run's)
        # without a word; the node, the tools and torch.hub then loaded it. A resume replaces
        # only what its own run wrote: with a bare --resume (scripts pass it always, and with
        # no checkpoint it starts afresh) any existing weights were replaced too.
        existing = [t for t in (Path(config.weights_out), *card_paths(config.weights_out))
                    if t.exists()]
        own = config.resume and _same_path(_run_weights_out(checkpoint), config.weights_out)
        if existing and not own:
            raise ConfigError(
                f'--weights-out {config.weights_out}: {existing[0]} exists (shipped or earlier '
                'weights, or their card): --overwrite to replace them, or another path'
                + (
                    f' (--resume replaces only the weights of its own run, and the run in '
                    f'{out} was not started with this --weights-out)'
                    if config.resume
                    else ''
                )
            )
    if checkpoint.exists() and not checkpoint.is_file():
        raise ConfigError(f'--out {out}: {checkpoint} is not a file; cannot keep checkpoints')
    if checkpoint.is_file() and not (config.resume or config.overwrite):
        written = time.strftime('%Y-%m-%d %H:%M', time.localtime(checkpoint.stat().st_mtime))
        raise ConfigError(
            f'--out {out} holds the checkpoint of an earlier run ({CHECKPOINT_NAME}, written '
            f'{written}): --resume to continue it, --overwrite to start over, or another --out'
        )
    if config.overwrite:
        for stale in (checkpoint, out / _HISTORY_NAME):
            try:
                stale.unlink(missing_ok=True)
            except OSError as exc:
                raise ConfigError(
                    f'--overwrite: cannot remove {stale} of the earlier run ({reason(exc)})'
                ) from exc
    if config.threads:
        # numba's OpenMP layer resets the OpenMP thread count that torch also uses: numba first.
        _limit_numba_threads(config.threads)
        torch.set_num_threads(config.threads)


def weights_out_path(config: TrainConfig) -> str | None:
    """``weights_out`` resolved, for the checkpoint (see :func:`_run_weights_out`)."""
    return str(Path(config.weights_out).resolve()) if config.weights_out else None


def _run_weights_out(checkpoint: Path) -> list[str]:
    """The --weights-out of the run whose checkpoint is ``checkpoint``, as given and resolved
    when it was started (empty where there is none, or no readable checkpoint: its resume
    then fails with the reason)."""
    if not checkpoint.is_file():
        return []
    try:
        state = torch.load(checkpoint, map_location='cpu', weights_only=True, mmap=True)
        values = [state['config'].get('weights_out'), state.get('weights_out_path')]
    except Exception:  # torch raises many unrelated types for a damaged file
        return []
    return [value for value in values if isinstance(value, str)]


def _same_path(paths: list[str], path: str) -> bool:
    """Whether ``path`` names a file of ``paths`` (spelled alike, or alike once resolved;
    a resolved one of ``paths`` also holds from another working folder)."""
    return any(
        known == path or Path(known).resolve() == Path(path).resolve() for known in paths
    )


def _limit_numba_threads(threads: int) -> None:
    try:
        import numba
    except ImportError:
        return
    available = int(numba.config.NUMBA_NUM_THREADS)  # type: ignore[attr-defined]
    numba.set_num_threads(min(threads, available))
