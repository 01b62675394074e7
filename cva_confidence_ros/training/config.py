"""The training configuration: one frozen dataclass, validated on construction."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from cva_confidence_ros.checks import is_int, is_real
from cva_confidence_ros.errors import ConfigError

__all__ = [
    'DISJOINT_SPLITS',
    'FUSION_SPLITS',
    'MODES',
    'TRAIN_PRECISIONS',
    'TrainConfig',
    'check_training_datasets',
    'default_synthetic_size',
    'parse_dataset_spec',
]

#: ``sparse``: one 13×13×D extract per sample (the paper); ``dense``: crops with a masked loss.
MODES = ('sparse', 'dense')
_DEVICES = ('cpu', 'cuda', 'auto')
#: Arithmetic of the training steps: float32, or bfloat16 autocast (mixed precision).
TRAIN_PRECISIONS = ('fp32', 'bf16')
#: LGC-Net's split of the training scenes between its two stages: ``alternate`` (scenes sorted
#: by name, even positions train CCNN + ConfNet, odd positions the fusion) or ``none`` (both
#: stages on every scene, which lets the fusion learn the parts' over-confidence on their own
#: training scenes).
FUSION_SPLITS = ('alternate', 'none')
#: Data sets whose splits hold different scenes (FlyingThings3D: TRAIN and TEST), name →
#: its splits. Every other data set's splits (KITTI ``training``, ETH3D
#: ``two_view_training``, the Middlebury sizes ``trainingQ|H|F``, ``quarter|half|full``,
#: ``ThirdSize|HalfSize|FullSize``) are sizes or subsets of the same scenes, so training and
#: validation on one data set overlap whatever the splits.
DISJOINT_SPLITS: dict[str, tuple[str, ...]] = {'flyingthings3d': ('TRAIN', 'TEST')}
#: Data sets that are scenes of a develop data set under another name: never train on them.
_DEVELOP_SCENES: dict[str, str] = {
    'motorcycle': 'the Middlebury 2014 Motorcycle scene of middlebury2014 (MiddEval3)',
}
#: Largest run seed: the trainer seeds torch with seed · 1 000 003 + …, which
#: ``torch.manual_seed`` takes only below 2**64.
_MAX_SEED = 2**32 - 1
#: The largest learning rate taken: one float32 holds (Adam's steps are float32; 1e39 stopped
#: the first step with a raw overflow error). Far smaller ones already diverge, and say so.
_LR_MAX = 1e38


def default_synthetic_size(max_disparity: int) -> tuple[int, int]:
    """(H, W) of synthetic pairs for depth D: at least 128×256, and W ≥ 2·D."""
    return max(128, int(max_disparity)), max(256, 2 * int(max_disparity))


def parse_dataset_spec(spec: str) -> tuple[str, str | None]:
    """Split ``'name'`` or ``'name:split'`` into (name, split or None)."""
    name, _, split = spec.partition(':')
    name = name.strip()
    if not name:
        raise ConfigError(f"expected a data set as 'name' or 'name:split'; got {spec!r}")
    return name, split.strip() or None


def check_training_datasets(
    specs: Sequence[str], validation: bool = False
) -> list[tuple[str, str | None]]:
    """Parse ``name[:split]`` data set specs and refuse unknown names and, for training, the
    develop data sets and the data sets that are develop scenes (``motorcycle``).

    Raises:
        ConfigError: An unknown data set or split, a develop one (or a develop scene) to
            train on, or scenes given twice (``kitti2012,kitti2012``, or ``name`` and
            ``name:split`` of a data set whose splits are disjoint).
    """
    from cva_confidence_ros.datasets import DATASETS, DEVELOP_DATASETS

    parsed = [parse_dataset_spec(spec) for spec in specs]
    for name, _ in parsed:
        if name not in DATASETS:
            raise ConfigError(f'unknown data set {name!r}; expected one of {DATASETS.names()}')
        if not validation and name in DEVELOP_DATASETS:
            raise ConfigError(
                f'{name} is a develop data set ({", ".join(DEVELOP_DATASETS)}): never train '
                'on it, or the reported numbers mean nothing'
            )
        if not validation and name in _DEVELOP_SCENES:
            raise ConfigError(
                f'{name} is {_DEVELOP_SCENES[name]}, develop data '
                f'({", ".join(DEVELOP_DATASETS)}): never train on it, or the reported numbers '
                'mean nothing'
            )
    # A split the data set lacks is refused now, not once the training data are prepared.
    resolved = [(name, DATASETS.get(name).resolve_split(split)) for name, split in parsed]
    given = [f'{name}:{split}' if split else name for name, split in parsed]
    for index, (name, split) in enumerate(resolved):
        for before, (other, other_split) in enumerate(resolved[:index]):
            # The same scenes twice (sizes of the same scenes, e.g. trainingQ and trainingH,
            # are a choice: each size is its own sample).
            if other == name and (
                split == other_split
                or (name in DISJOINT_SPLITS and None in (split, other_split))
            ):
                twice = (
                    f'{given[index]} is given twice'
                    if given[index] == given[before]
                    else f'{given[index]} and {given[before]} hold the same scenes'
                )
                raise ConfigError(
                    f'{twice}: they would count twice; give each data set (and split) once'
                )
    return parsed


def _same_scenes(name: str, split_a: str | None, split_b: str | None) -> bool:
    """Whether ``name:split_a`` and ``name:split_b`` share scenes (None = no split given)."""
    if name not in DISJOINT_SPLITS or split_a is None or split_b is None:
        return True  # a size or subset of the same scenes, or every split
    return split_a == split_b


def _overlap(
    train: Sequence[tuple[str, str | None]], val: Sequence[tuple[str, str | None]]
) -> list[str]:
    """The data sets of ``val`` that share scenes with ``train``, each with the reason."""
    found = []
    for name, split in val:
        for other, other_split in train:
            if other != name or not _same_scenes(name, other_split, split):
                continue
            specs = [f'{name}:{s}' if s else name for s in (other_split, split)]
            if other_split == split:
                found.append(specs[0])
            elif name in DISJOINT_SPLITS:
                found.append(
                    f'{name} ({" and ".join(specs)}; {name} without a split is all of its '
                    f'splits, {", ".join(DISJOINT_SPLITS[name])})'
                )
            else:
                found.append(
                    f'{name} ({" and ".join(specs)}; the splits of {name} are sizes or '
                    'subsets of the same scenes)'
                )
            break
    return found


@dataclass(frozen=True)
class TrainConfig:
    """Everything that decides what ``cva-train`` does.

    Attributes:
        arch: Network architecture to train, a name of ``model.ARCHITECTURES``
            (``cvanet`` = CVA-Net, the paper's network).
        matcher: Registered matcher whose cost volumes the network learns from.
        max_disparity: Cost-volume depth D (paper: 256).
        data_root: Folder holding the data sets (each under its registered name, or itself one).
        datasets: Training data sets as ``name`` or ``name:split``.
        max_scenes: Use at most this many scenes per data set (None = all).
        synthetic: Number of synthetic training pairs.
        synthetic_size: (H, W) of the synthetic pairs; None = :func:`default_synthetic_size`.
        synthetic_seed: Seed of the first synthetic training pair (pair i has seed + i).
        val_datasets: Held-apart validation data sets (``name`` or ``name:split``).
        val_data_root: Folder holding the validation data sets; None = ``data_root``. Another
            root than ``data_root`` may hold data sets of the training names (your own
            ``stereo_folder`` scenes held apart): its scenes are then refused only where every
            one is a training pair (same images and ground truth).
        val_synthetic: Number of synthetic validation pairs (seeds disjoint from training).
        val_pixels: Size of the fixed pixel subset the validation AUC is computed on.
        mode: ``sparse`` or ``dense`` (see :data:`MODES`).
        crop_size: Output side of a dense-mode crop (input is crop + 12).
        vflip: Turn half of the training extracts or crops upside down (augmentation; see
            ``training.data.flip_draws``). Not in the paper.
        epochs: Epochs at learning rate ``lr`` (paper: 10).
        epochs_low_lr: Further epochs at ``lr × low_lr_factor`` (paper: 3).
        batch_size: Samples per step (paper: 256). Dense mode uses ceil(batch / crop²) crops.
        lr: Learning rate of Adam (paper: 1e-4).
        low_lr_factor: Factor of the last epochs' learning rate (paper: 0.1).
        samples_per_epoch: Labelled samples per epoch; None = as many as there are labelled
            pixels (sparse mode: each once; dense mode: crops at random places, which may hold
            a pixel more than once and another not at all).
        seed: Seed of initialisation, sampling and dropout.
        device: ``cpu``, ``cuda`` or ``auto``.
        precision: ``fp32``, or ``bf16``: forward and backward under bfloat16 autocast (CUDA;
            weights, optimiser and batch-norm statistics stay float32).
        threads: torch and numba CPU threads; None = their defaults.
        out: Folder for checkpoints, the log and the history.
        weights_out: Final weights file (+ model card beside it); None = only checkpoints.
        resume: Continue from ``out/checkpoint.pt`` if it exists.
        overwrite: Start afresh even if ``out`` holds the checkpoint of an earlier run (which
            is refused otherwise: it would be overwritten at the end of the first epoch).
        progress: Show a progress bar.
        teacher: Weights file of a trained network that the trained one learns to imitate
            (knowledge distillation, see ``training.distill``); None = labels only.
        distill_weight: A in [0, 1]: loss = (1 − A)·BCE(label) + A·BCE(teacher probability).
        init_weights: Weights file of the same architecture to start from (warm start; another D is
            transferred, see ``training.distill``).
        fusion_split: LGC-Net only: which training scenes each stage sees (see
            :data:`FUSION_SPLITS`; ``alternate``: the parts learn from one half of the scenes and
            the fusion from the other, ``none``: both stages from all scenes).
        volume_cache: Folder that keeps the scenes' cost volumes on disk, mapped into memory
            (``training.data.VolumeCache``), instead of all of them in memory; reused by later
            runs and resumes on the same pairs, matcher and D. None = in memory.
        checkpoint_every: Also checkpoint every N training steps within an epoch (0 = at the
            end of each epoch only): an hours-long epoch stopped (preempted, a lost node)
            resumes at its last such step, to the bit as if it had not stopped.
    """

    arch: str = 'cvanet'
    matcher: str = 'census_bm'
    max_disparity: int = 64
    data_root: str | None = None
    datasets: tuple[str, ...] = ()
    max_scenes: int | None = None
    synthetic: int = 0
    synthetic_size: tuple[int, int] | None = None
    synthetic_seed: int = 0
    val_datasets: tuple[str, ...] = ()
    val_data_root: str | None = None
    val_synthetic: int = 0
    val_pixels: int = 2000
    mode: str = 'sparse'
    crop_size: int = 32
    vflip: bool = False
    epochs: int = 10
    epochs_low_lr: int = 3
    batch_size: int = 256
    lr: float = 1e-4
    low_lr_factor: float = 0.1
    samples_per_epoch: int | None = None
    seed: int = 0
    device: str = 'cpu'
    precision: str = 'fp32'
    threads: int | None = None
    out: str = 'out/train'
    weights_out: str | None = None
    resume: bool = False
    overwrite: bool = False
    progress: bool = True
    teacher: str | None = None
    distill_weight: float = 0.0
    init_weights: str | None = None
    fusion_split: str = 'alternate'
    volume_cache: str | None = None
    checkpoint_every: int = 0

    def __post_init__(self) -> None:
        from cva_confidence_ros.model import ARCHITECTURES
        from cva_confidence_ros.model.baselines import BASELINE_ARCHS
        from cva_confidence_ros.training.card import card_paths

        for name in ('datasets', 'val_datasets'):
            specs = getattr(self, name)
            if isinstance(specs, str):
                # tuple('kitti2012') would be nine one-letter data sets.
                raise ConfigError(
                    f'{name} must be a sequence of data set specs; got the string {specs!r} '
                    f'(write ({specs!r},))'
                )
            # None ended in "'NoneType' object is not iterable", a number in the spec parser's
            # AttributeError.
            if not isinstance(specs, Sequence) or not all(isinstance(s, str) for s in specs):
                raise ConfigError(
                    f"{name} must be a sequence of data set specs ('name' or 'name:split'); "
                    f'got {type(specs).__name__} {specs!r}'
                )
            object.__setattr__(self, name, tuple(specs))
        for name in ('vflip', 'resume', 'overwrite', 'progress'):
            # A string such as 'false' is true; a numpy bool is neither JSON (the history and
            # card) nor loadable from a checkpoint.
            value = getattr(self, name)
            if not isinstance(value, (bool, np.bool_)):
                raise ConfigError(
                    f'{name} must be True or False; got {type(value).__name__} {value!r}'
                )
            object.__setattr__(self, name, bool(value))
        for name in ('data_root', 'val_data_root', 'out', 'weights_out', 'teacher',
                     'init_weights', 'volume_cache'):
            # A Path is kept as a str: checkpoints are read with weights_only, which refuses a
            # pickled Path (a resume would fail with 'cannot read checkpoint').
            value = getattr(self, name)
            if value is None and name != 'out':
                continue
            path = os.fspath(value) if isinstance(value, os.PathLike) else value
            if not isinstance(path, str):
                raise ConfigError(
                    f'{name} must be a path (str or os.PathLike); got {type(value).__name__} '
                    f'{value!r}'
                )
            object.__setattr__(self, name, path)
        for field in fields(self):
            # Numpy integers are integers (and plain ints keep the checkpoints and cards JSON).
            if is_int(getattr(self, field.name)):
                object.__setattr__(self, field.name, int(getattr(self, field.name)))
        for name in ('lr', 'low_lr_factor', 'distill_weight'):
            value = getattr(self, name)
            if not is_real(value):
                raise ConfigError(
                    f'{name} must be a real number; got {type(value).__name__} {value!r}'
                )
            try:
                number = float(value)
            except OverflowError:  # an int beyond float: refused below as infinite
                number = math.inf if value > 0 else -math.inf
            object.__setattr__(self, name, number)
        if self.synthetic_size is not None:
            size = self.synthetic_size
            if (
                isinstance(size, str)
                or not isinstance(size, (tuple, list))
                or len(size) != 2
                or not all(is_int(v) for v in size)
            ):
                raise ConfigError(f'synthetic_size must be two integers (H, W); got {size!r}')
            object.__setattr__(self, 'synthetic_size', (int(size[0]), int(size[1])))
        _at_least('max_disparity', self.max_disparity, 13)
        _at_least('synthetic', self.synthetic, 0)
        _at_least('val_synthetic', self.val_synthetic, 0)
        _at_least('val_pixels', self.val_pixels, 1)
        _at_least('crop_size', self.crop_size, 1)
        _at_least('epochs', self.epochs, 0)
        _at_least('epochs_low_lr', self.epochs_low_lr, 0)
        _at_least('batch_size', self.batch_size, 1)
        _at_least('synthetic_seed', self.synthetic_seed, 0)
        _at_least('seed', self.seed, 0)
        if self.seed > _MAX_SEED:
            raise ConfigError(f'seed must be an integer in [0, {_MAX_SEED}]; got {self.seed!r}')
        if self.epochs + self.epochs_low_lr < 1:
            raise ConfigError('epochs + epochs_low_lr must be >= 1; got 0')
        if self.max_scenes is not None:
            _at_least('max_scenes', self.max_scenes, 1)
        if self.samples_per_epoch is not None:
            _at_least('samples_per_epoch', self.samples_per_epoch, 1)
        if self.threads is not None:
            _at_least('threads', self.threads, 1)
        _at_least('checkpoint_every', self.checkpoint_every, 0)
        if self.arch not in ARCHITECTURES:
            raise ConfigError(
                f'unknown arch {self.arch!r}; expected one of {ARCHITECTURES.names()}'
            )
        if self.fusion_split not in FUSION_SPLITS:
            raise ConfigError(
                f'fusion_split must be one of {FUSION_SPLITS}; got {self.fusion_split!r}'
            )
        if self.mode not in MODES:
            raise ConfigError(f'mode must be one of {MODES}; got {self.mode!r}')
        device = str(self.device)
        if device not in _DEVICES and not (device.startswith('cuda:') and device[5:].isdecimal()):
            raise ConfigError(f'device must be one of {_DEVICES} or cuda:N; got {self.device!r}')
        if self.precision not in TRAIN_PRECISIONS:
            raise ConfigError(
                f'precision must be one of {TRAIN_PRECISIONS}; got {self.precision!r}'
            )
        if self.arch in BASELINE_ARCHS and (self.vflip or self.precision != 'fp32'):
            raise ConfigError(
                f'--arch {self.arch} trains in float32 without flips: --vflip and --precision '
                'bf16 are for the cost-volume networks (cvanet, cvanet_lite, cvanet_fast); got '
                f'vflip {self.vflip}, precision {self.precision!r}'
            )
        if self.arch in BASELINE_ARCHS and self.checkpoint_every:
            raise ConfigError(
                f'--arch {self.arch} checkpoints at the end of each epoch only: '
                '--checkpoint-every is for the cost-volume networks (cvanet, cvanet_lite, '
                f'cvanet_fast); got checkpoint_every {self.checkpoint_every!r}'
            )
        if self.arch in BASELINE_ARCHS and self.volume_cache:
            # Their scenes keep disparity maps, no cost volumes: the option did nothing.
            raise ConfigError(
                f'--arch {self.arch} keeps no cost volumes (it learns from disparity maps): '
                f'--volume-cache is for the cost-volume networks (cvanet, cvanet_lite, '
                f'cvanet_fast); got volume_cache {self.volume_cache!r}'
            )
        if not (math.isfinite(self.lr) and self.lr > 0 and 0 < self.low_lr_factor <= 1):
            raise ConfigError(
                f'lr must be finite and > 0, low_lr_factor in (0, 1]; got {self.lr}, '
                f'{self.low_lr_factor}'
            )
        if self.lr > _LR_MAX:
            # Adam's step in float32 overflowed: a raw RuntimeError at the first step.
            raise ConfigError(f'lr must be at most {_LR_MAX:g}; got {self.lr:g}')
        if not 0.0 <= self.distill_weight <= 1.0:
            raise ConfigError(f'distill_weight must be in [0, 1]; got {self.distill_weight}')
        if (self.distill_weight > 0) != bool(self.teacher):
            raise ConfigError(
                'distillation needs both --teacher PATH and --distill-weight A > 0; got '
                f'teacher {self.teacher!r} and distill_weight {self.distill_weight}'
            )
        if self.weights_out and Path(self.weights_out) in card_paths(self.weights_out):
            raise ConfigError(
                f'--weights-out {self.weights_out}: the model card is written beside the '
                'weights as PATH.md and PATH.json and would overwrite them; name the weights '
                'PATH.pt'
            )
        if not self.datasets and self.synthetic == 0:
            raise ConfigError('no training data: give --datasets and/or --synthetic N (N > 0)')
        if self.datasets and not self.data_root:
            raise ConfigError('--datasets need --data-root')
        if self.val_data_root and not self.val_datasets:
            raise ConfigError(
                f'--val-data-root {self.val_data_root} needs --val-datasets (the data sets to '
                'validate on there, e.g. stereo_folder)'
            )
        if self.val_datasets and not (self.val_data_root or self.data_root):
            raise ConfigError('--val-datasets need --data-root or --val-data-root')
        train = check_training_datasets(self.datasets)
        val = check_training_datasets(self.val_datasets, validation=True)
        # Data sets of one name under two roots are other scenes (or copies, which the
        # trainer refuses by content): only one root makes a name the same scenes.
        overlap = _overlap(train, val) if self.same_val_root else []
        if overlap:
            raise ConfigError(
                'validation data must be held apart from the training data; both use '
                + ', '.join(overlap)
            )
        height, width = self.synthetic_hw
        if self.synthetic or self.val_synthetic:
            if height < 16 or width < 2 * self.max_disparity:
                raise ConfigError(
                    f'synthetic pairs must be at least 16 px high and 2·D = '
                    f'{2 * self.max_disparity} px wide; got {height}×{width}'
                )

    @property
    def val_root(self) -> str | None:
        """The folder the validation data sets are read from."""
        return self.val_data_root or self.data_root

    @property
    def same_val_root(self) -> bool:
        """Whether training and validation data sets are read from one folder."""
        if not self.val_data_root or not self.data_root:
            return True
        return Path(self.val_data_root).resolve() == Path(self.data_root).resolve()

    @property
    def synthetic_hw(self) -> tuple[int, int]:
        """(H, W) of the synthetic pairs."""
        return self.synthetic_size or default_synthetic_size(self.max_disparity)

    @property
    def total_epochs(self) -> int:
        """``epochs + epochs_low_lr``."""
        return self.epochs + self.epochs_low_lr

    def lr_at(self, epoch: int) -> float:
        """Learning rate of (0-based) ``epoch``."""
        return self.lr if epoch < self.epochs else self.lr * self.low_lr_factor

    def to_dict(self) -> dict[str, Any]:
        """Plain-Python dict of the fields (for checkpoints and model cards)."""
        data = asdict(self)
        for key, value in data.items():
            if isinstance(value, tuple):
                data[key] = list(value)
        return data

    def replace(self, **changes: Any) -> TrainConfig:
        """A validated copy with ``changes`` applied."""
        names = {f.name for f in fields(self)}
        unknown = set(changes) - names
        if unknown:
            raise ConfigError(f'unknown training options {sorted(unknown)}')
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        values.update(changes)
        return TrainConfig(**values)


def _at_least(name: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f'{name} must be an integer >= {low}; got {value!r}')
