"""Training data: cost volumes and labels per scene, and the samples drawn from them.

Every scene is matched once; its cost volume is kept zero-padded by 6 px in float16 (half the
memory of float32, and costs in [0, 1] lose nothing that matters at 1e-3), and every pixel with
ground truth is labelled correct or wrong by the KITTI criterion against the matcher's
winner-takes-all disparity. Samples are then sliced out of the padded volumes:

* sparse mode: a 13×13×D extract centred on a labelled pixel (the paper's training samples);
* dense mode: a (c + 12)×(c + 12)×D crop whose c×c outputs are trained with a masked loss, so
  that neighbouring samples share one forward pass. A "sample" is a labelled output pixel.

All draws are seeded by (seed, epoch), so a resumed run sees exactly the samples of an
uninterrupted one.

Memory: every training scene's padded volume stays in memory for the whole run,
:func:`volume_bytes` = D·(H + 12)·(W + 12)·2 bytes (measured: the allocation is exactly that;
the resident size grows by that per scene, plus one scene's float32 matching buffers while it
is matched). A 1242×375 KITTI pair at D = 256 is 248 MB, all 394 KITTI 2012 + 2015 pairs
98 GB. :class:`VolumeCache` keeps them in files on disk instead, mapped into memory: the
page cache then holds what fits, and the run reads the rest from the disk.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
import contextlib
from dataclasses import dataclass
import json
import math
import os
from pathlib import Path
import re
import time
from typing import Any
import zipfile

import numpy as np
import torch

from cva_confidence_ros.datasets import StereoSample, fit_disparity_range
from cva_confidence_ros.errors import ConfigError, DataError, reason
from cva_confidence_ros.model import PAD, PATCH_SIZE, pad_cost_volume

__all__ = [
    'CropBatch',
    'LabelledScene',
    'PreparedScene',
    'SampleIndex',
    'VolumeCache',
    'dense_crops',
    'epoch_order',
    'gather_crops',
    'gather_extracts',
    'match_and_label',
    'prepare_scene',
    'sample_index',
    'validation_subset',
    'volume_bytes',
]


class LabelledScene:
    """What every training scene has (a mix-in of the scene dataclasses): a name, the
    factor it was shrunk by, and its labels."""

    name: str
    factor: int
    labelled: np.ndarray  # (H, W) bool, True where ground truth is known
    correct: np.ndarray  # (H, W) bool, True where the WTA disparity is correct

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the scene's outputs."""
        return int(self.labelled.shape[0]), int(self.labelled.shape[1])

    @property
    def n_labelled(self) -> int:
        """Pixels with ground truth."""
        return int(self.labelled.sum())

    @property
    def n_wrong(self) -> int:
        """Labelled pixels whose WTA disparity is wrong."""
        return int((self.labelled & ~self.correct).sum())


@dataclass(eq=False)
class PreparedScene(LabelledScene):
    """One matched scene at the training resolution.

    Attributes:
        name: ``dataset/scene``.
        factor: Downscaling factor applied by ``fit_disparity_range`` (1, 2, 4, ...).
        volume: (D, H + 12, W + 12) float16 cost volume, zero-padded by 6 px on each side.
        labelled: (H, W) bool, True where ground truth is known.
        correct: (H, W) bool, True where the WTA disparity is correct (KITTI criterion);
            meaningful only where ``labelled``.
    """

    name: str
    factor: int
    volume: torch.Tensor
    labelled: np.ndarray
    correct: np.ndarray

    def unpadded_volume(self) -> np.ndarray:
        """(D, H, W) float32 cost volume."""
        height, width = self.shape
        return self.volume[:, PAD : PAD + height, PAD : PAD + width].float().numpy()


def prepare_scene(sample: StereoSample, matcher: str, max_disparity: int) -> PreparedScene:
    """Shrink a sample until its ground truth fits D, match it and label its pixels.

    Args:
        sample: A stereo pair with ground truth (NaN = unknown).
        matcher: Registered matcher name.
        max_disparity: Cost-volume depth D.

    Returns:
        The :class:`PreparedScene`.

    Raises:
        DataError: No pixel with ground truth after shrinking.
    """
    matched = match_and_label(sample, matcher, max_disparity)
    padded = torch.from_numpy(pad_cost_volume(matched.volume, np.float16))
    return PreparedScene(matched.name, matched.factor, padded, matched.labelled, matched.correct)


def volume_bytes(height: int, width: int, max_disparity: int) -> int:
    """Bytes of the padded float16 volume of a :class:`PreparedScene` of ``height`` ×
    ``width`` outputs (after the halving that fits D) at depth ``max_disparity``."""
    return int(max_disparity) * (int(height) + 2 * PAD) * (int(width) + 2 * PAD) * 2


#: Temporary files of :class:`VolumeCache` entries (``outputs.temporary_sibling``).
_TEMPORARY = re.compile(r'.+\.(npy|labels\.npz)\.\d+-\d+\.tmp')
#: Seconds a temporary entry file stays unchanged before it is taken for a killed writer's.
_ABANDONED_S = 3600.0


class VolumeCache:
    """Padded float16 cost volumes of prepared scenes in a folder, one ``.npy`` file each,
    mapped into memory instead of held in it (``cva-train --volume-cache DIR``).

    An entry is keyed by the pair's content (the digest the trainer keeps for its resume
    checks), the matcher and D: it is written once, when the scene is first matched, and
    taken by every later epoch, resume or run on the same pair, matcher and D. Beside the
    volume, ``<key>.labels.npz`` holds the labels, the halving factor and what the entry was
    made from (matcher, D, package version, shape); an entry that does not match (cut short, or
    written by another version, whose matcher may compute other costs) is matched again and
    replaced, and said so.

    The volumes are mapped copy-on-write: training only reads them, so their pages are the
    page cache's, shared by the processes of a torchrun group, and dropped under memory
    pressure instead of the process being killed. Results are those of the in-memory volumes,
    bit for bit.
    """

    def __init__(
        self, folder: str | os.PathLike[str], log: Callable[[str], None] | None = None
    ) -> None:
        """
        Raises:
            ConfigError: ``folder`` cannot be made or written.
        """
        self.folder = Path(folder)
        self.log = log
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            probe = self.folder / f'.probe-{os.getpid()}'
            probe.write_bytes(b'')
            # missing_ok: a process of the same number on another machine (a shared folder)
            # may have removed it first; the write is what was to be probed.
            probe.unlink(missing_ok=True)
        except OSError as exc:
            # mkdir's own words for a file there are 'File exists'.
            why = 'it is a file, not a folder' if self.folder.is_file() else reason(exc)
            raise ConfigError(
                f'--volume-cache {folder}: cannot write cost volumes there ({why})'
            ) from exc
        self._remove_abandoned()

    def _remove_abandoned(self) -> None:
        """Remove the temporary files of entries whose writer was killed (SIGKILL, SIGTERM, a
        lost machine: an entry is written beside its name and renamed), unchanged for
        :data:`_ABANDONED_S`: a writer writes an entry in seconds. Each killed write left one,
        as large as the volume, unsaid and never removed."""
        now = time.time()
        removed, size = 0, 0
        paths: list[Path] = []
        with contextlib.suppress(OSError):  # a folder that may be written but not listed
            paths = list(self.folder.iterdir())
        for path in paths:
            if not _TEMPORARY.fullmatch(path.name):
                continue
            with contextlib.suppress(OSError):  # gone already, or not ours to remove
                stat = path.stat()
                if now - stat.st_mtime > _ABANDONED_S:
                    path.unlink()
                    removed, size = removed + 1, size + stat.st_size
        if removed and self.log is not None:
            self.log(
                f'--volume-cache: removed {removed} temporary files ({size / 1e6:.1f} MB) '
                f'in {self.folder} left by runs killed while writing an entry'
            )

    def key(self, pair: str, matcher: str, max_disparity: int) -> str:
        """The entry name of the pair of digest ``pair`` matched by ``matcher`` at D."""
        safe = re.sub(r'[^A-Za-z0-9_.-]', '_', matcher)
        return f'{pair}-{safe}-d{int(max_disparity)}'

    def paths(self, key: str) -> tuple[Path, Path]:
        """(volume, labels) files of entry ``key``."""
        return self.folder / f'{key}.npy', self.folder / f'{key}.labels.npz'

    def has(self, pair: str, matcher: str, max_disparity: int) -> bool:
        """Whether the entry's files are there (not whether they are valid)."""
        return all(path.is_file() for path in self.paths(self.key(pair, matcher, max_disparity)))

    def _meta(self, matcher: str, max_disparity: int, pair: str) -> dict[str, Any]:
        from cva_confidence_ros import __version__

        return {
            'format': 1,
            'matcher': matcher,
            'max_disparity': int(max_disparity),
            'pair': pair,
            'version': __version__,
        }

    def _read(
        self, name: str, key: str, meta: dict[str, Any]
    ) -> PreparedScene | str | None:
        """The cached scene of ``key``; None where there is none, or why it is stale."""
        volume_path, labels_path = self.paths(key)
        if not (volume_path.is_file() and labels_path.is_file()):
            return None
        try:
            with np.load(labels_path, allow_pickle=False) as stored:
                saved = json.loads(str(stored['meta']))
                labelled = np.array(stored['labelled'], dtype=bool)
                correct = np.array(stored['correct'], dtype=bool)
            dtype, shape, volume = _map_volume(volume_path)
        except (OSError, ValueError, RuntimeError, KeyError, EOFError, zipfile.BadZipFile) as exc:
            return f'unreadable ({reason(exc)})'
        factor = saved.pop('factor', None)
        if saved != meta:
            changed = [k for k in meta if saved.get(k) != meta[k]]
            return 'made with other ' + ', '.join(
                f'{k} ({saved.get(k)!r}, now {meta[k]!r})' for k in changed
            )
        height, width = labelled.shape
        depth = meta['max_disparity']
        expected = (depth, height + 2 * PAD, width + 2 * PAD)
        if volume is None or shape != expected or correct.shape != (height, width):
            return f'a {dtype} {shape} volume where {expected} float16 belongs'
        return PreparedScene(name, int(factor), volume, labelled, correct)

    def prepare(
        self, sample: StereoSample, matcher: str, max_disparity: int, pair: str
    ) -> PreparedScene:
        """:func:`prepare_scene`, the volume taken from the cache where it holds the entry,
        else matched, written there and mapped.

        Args:
            pair: The digest of ``sample``'s images and ground truth.

        Raises:
            DataError: As :func:`prepare_scene`, or the entry cannot be written (a full disk).
        """
        from cva_confidence_ros.outputs import write_atomic

        name = f'{sample.dataset}/{sample.scene}'
        key = self.key(pair, matcher, max_disparity)
        meta = self._meta(matcher, max_disparity, pair)
        found = self._read(name, key, meta)
        if isinstance(found, PreparedScene):
            return found
        if found is not None and self.log is not None:
            self.log(f'--volume-cache: the entry of {name} in {self.folder} is stale ({found}): '
                     'matched again')
        matched = match_and_label(sample, matcher, max_disparity)
        padded = pad_cost_volume(matched.volume, np.float16)
        volume_path, labels_path = self.paths(key)
        record = json.dumps({**meta, 'factor': matched.factor})
        try:
            # The volume first: the labels file, written last, completes the entry.
            write_atomic(volume_path, lambda handle: np.save(handle, padded))
            write_atomic(
                labels_path,
                lambda handle: np.savez(
                    handle,
                    meta=np.array(record),
                    labelled=matched.labelled,
                    correct=matched.correct,
                ),
            )
        except OSError as exc:
            raise DataError(
                f'--volume-cache: cannot write the cost volume of {name} to {volume_path} '
                f'({reason(exc)}; it takes {padded.nbytes / 1e9:.2f} GB)'
            ) from exc
        stored = self._read(name, key, meta)
        if not isinstance(stored, PreparedScene):
            raise DataError(
                f'--volume-cache: the cost volume of {name} just written to {volume_path} '
                f'does not read back ({stored or "gone"})'
            )
        return stored


def _map_volume(path: Path) -> tuple[np.dtype, tuple[int, ...], torch.Tensor | None]:
    """(dtype, shape, volume) of the ``.npy`` file of a cached volume, mapped into memory
    copy-on-write: a writable tensor (torch takes no read-only one) whose pages stay the
    file's as long as nothing writes them, and training only reads. None for the volume where
    the file holds no C-ordered float16 array.

    Mapped by torch, which keeps no file open: numpy's memmap keeps one descriptor per file,
    and a cache of more scenes than the open-file limit (``ulimit -n``, 1024 on many systems)
    failed with 'Too many open files' where the in-memory run trained.

    Raises:
        OSError, ValueError, EOFError, RuntimeError: The file cannot be read, is no ``.npy``
            file, or is cut short.
    """
    with open(path, 'rb') as handle:
        version = np.lib.format.read_magic(handle)
        if version not in ((1, 0), (2, 0)):
            raise ValueError(f'.npy format {version[0]}.{version[1]}')
        read = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        shape, fortran, dtype = read(handle)
        offset = handle.tell()
        size = os.fstat(handle.fileno()).st_size
    shape = tuple(int(side) for side in shape)
    if dtype != np.float16 or fortran or offset % 2:
        return dtype, shape, None
    end = offset + 2 * math.prod(shape)
    if size < end:
        raise ValueError(f'cut short: {size} bytes where {end} belong')
    raw = torch.from_file(str(path), shared=False, size=end, dtype=torch.uint8)
    return dtype, shape, raw[offset:].view(torch.float16).view(shape)


@dataclass(eq=False)
class MatchedScene:
    """A sample shrunk until its ground truth fits D, matched and labelled.

    Attributes:
        name: ``dataset/scene``.
        factor: Downscaling factor applied by ``fit_disparity_range``.
        fitted: The shrunk sample.
        volume: (D, H, W) float32 cost volume.
        estimate: (H, W) winner-takes-all disparity.
        labelled: (H, W) bool, True where ground truth is known.
        correct: (H, W) bool, True where the WTA disparity is correct (KITTI criterion).
    """

    name: str
    factor: int
    fitted: StereoSample
    volume: np.ndarray
    estimate: np.ndarray
    labelled: np.ndarray
    correct: np.ndarray


def match_and_label(sample: StereoSample, matcher: str, max_disparity: int) -> MatchedScene:
    """Shrink ``sample`` until its ground truth fits D, match it and label its pixels.

    Raises:
        DataError: No pixel with ground truth after shrinking, or the shrunk pair is not wider
            than D.
    """
    from cva_confidence_ros.matching import compute_cost_volume, wta_disparity
    from cva_confidence_ros.metrics import kitti_error

    name = f'{sample.dataset}/{sample.scene}'
    fitted, factor = fit_disparity_range(sample, max_disparity)
    height, width = fitted.left.shape[:2]
    if width <= max_disparity:
        # The matcher's own message names neither the scene nor the shrinking.
        shrunk = (
            f'its ground truth reaches {sample.max_disparity:.4g} px, which shrinks it by '
            f'{factor} to {width}×{height}'
            if factor > 1
            else f'it is {width}×{height}'
        )
        raise DataError(
            f'{name}: {shrunk}; matching needs images wider than D = {max_disparity} '
            '(check the ground truth and its scale, or use another D)'
        )
    volume = compute_cost_volume(fitted.left, fitted.right, matcher, max_disparity)
    estimate = wta_disparity(volume)
    labelled = np.isfinite(fitted.disparity)
    if not labelled.any():
        raise DataError(f'{name}: no pixel with ground truth at factor {factor}')
    correct = ~kitti_error(estimate, fitted.disparity) & labelled
    return MatchedScene(name, factor, fitted, volume, estimate, labelled, correct)


@dataclass(frozen=True)
class SampleIndex:
    """Every labelled pixel of a list of scenes.

    Attributes:
        scene: (N,) int32 scene number.
        ys: (N,) int32 rows.
        xs: (N,) int32 columns.
        target: (N,) float32, 1 = correct disparity, 0 = wrong.
    """

    scene: np.ndarray
    ys: np.ndarray
    xs: np.ndarray
    target: np.ndarray

    def __len__(self) -> int:
        return int(self.scene.size)

    @property
    def fraction_wrong(self) -> float:
        """Share of samples labelled wrong (class balance)."""
        return float(1.0 - self.target.mean()) if len(self) else 0.0


def sample_index(scenes: Sequence[LabelledScene]) -> SampleIndex:
    """The :class:`SampleIndex` of all labelled pixels, scene by scene in row-major order."""
    parts = []
    for number, scene in enumerate(scenes):
        ys, xs = np.nonzero(scene.labelled)
        target = scene.correct[ys, xs].astype(np.float32)
        parts.append(
            (np.full(ys.size, number, np.int32), ys.astype(np.int32), xs.astype(np.int32), target)
        )
    if not parts:
        empty = np.zeros(0, np.int32)
        return SampleIndex(empty, empty, empty, np.zeros(0, np.float32))
    return SampleIndex(*(np.concatenate(column) for column in zip(*parts, strict=True)))


def epoch_order(n_total: int, n_samples: int, seed: int, epoch: int) -> np.ndarray:
    """Indices of the samples of one epoch: shuffled, each used once before any repeats.

    Args:
        n_total: Number of available samples.
        n_samples: Samples wanted this epoch.
        seed: Run seed.
        epoch: 0-based epoch (each epoch gets its own order).

    Returns:
        (n_samples,) int64 indices into [0, n_total); empty if ``n_samples`` < 1 (as
        :func:`dense_crops`).
    """
    if n_total < 1:
        raise DataError('no labelled training samples')
    if n_samples < 1:
        return np.zeros(0, np.int64)  # no round to concatenate
    rng = np.random.default_rng([seed, epoch, 1])
    rounds = math.ceil(n_samples / n_total)
    order = np.concatenate([rng.permutation(n_total) for _ in range(rounds)])
    return order[:n_samples]


def gather_extracts(
    scenes: Sequence[PreparedScene],
    index: SampleIndex,
    chosen: np.ndarray,
    flip: np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """13×13×D extracts centred on the chosen samples.

    Args:
        scenes: The prepared scenes.
        index: Their :class:`SampleIndex`.
        chosen: (B,) indices into ``index``.
        flip: Optional (B,) bool: turn these extracts upside down (see :func:`flip_draws`).

    Returns:
        ``(volumes, targets)``: (B, 1, D, 13, 13) float32 and (B,) float32.
    """
    depth = scenes[0].volume.shape[0]
    out = torch.empty((len(chosen), 1, depth, PATCH_SIZE, PATCH_SIZE), dtype=torch.float32)
    scene_ids = index.scene[chosen]
    for number in np.unique(scene_ids):
        rows = np.nonzero(scene_ids == number)[0]
        picked = chosen[rows]
        # (D, H, W, 13, 13) view; advanced indexing copies only the chosen windows.
        windows = scenes[number].volume.unfold(1, PATCH_SIZE, 1).unfold(2, PATCH_SIZE, 1)
        patch = windows[:, torch.from_numpy(index.ys[picked]), torch.from_numpy(index.xs[picked])]
        out[torch.from_numpy(rows), 0] = patch.permute(1, 0, 2, 3).float()
    if flip is not None and flip.any():
        upside = torch.from_numpy(np.nonzero(flip)[0])
        out[upside] = out[upside].flip(-2)
    return out, torch.from_numpy(index.target[chosen])


def flip_draws(count: int, seed: int, epoch: int, enabled: bool) -> np.ndarray:
    """Which of ``count`` training samples of an epoch are turned upside down.

    A vertical flip is a valid augmentation of a cost volume: the pair with both images turned
    upside down is still rectified, and its cost volume is the original turned upside down
    (exactly for Census block matching, whose window and transform are symmetric). A horizontal
    flip is not: it would swap which image is the reference and where occlusions fall.

    Returns:
        (count,) bool; all False unless ``enabled``. Drawn from their own stream, so switching
        flips on changes no other draw of the run.
    """
    if not enabled:
        return np.zeros(count, dtype=bool)
    return np.random.default_rng([seed, epoch, 3]).random(count) < 0.5


@dataclass(frozen=True)
class CropBatch:
    """Dense-mode crops: top-left output corners and labelled-pixel counts.

    Attributes:
        scene: (N,) int32 scene numbers.
        y0: (N,) int32 first output row.
        x0: (N,) int32 first output column.
        n_labelled: (N,) int32 labelled outputs in each crop.
    """

    scene: np.ndarray
    y0: np.ndarray
    x0: np.ndarray
    n_labelled: np.ndarray


def _crop_side(scenes: Sequence[LabelledScene], crop_size: int) -> int:
    return min([crop_size] + [min(s.shape) for s in scenes])


def dense_crops(
    scenes: Sequence[LabelledScene],
    index: SampleIndex,
    n_samples: int,
    crop_size: int,
    seed: int,
    epoch: int,
) -> CropBatch:
    """Crops of one epoch, each placed around a random labelled pixel, until they hold at least
    ``n_samples`` labelled outputs in total.

    The crop side is ``crop_size`` or the smallest scene side if that is smaller.

    Raises:
        DataError: ``index`` is empty (no labelled pixel to place a crop around).
    """
    if len(index) < 1:
        raise DataError('no labelled training samples')
    side = _crop_side(scenes, crop_size)
    rng = np.random.default_rng([seed, epoch, 2])
    counts = [
        np.pad(s.labelled.astype(np.int32).cumsum(0).cumsum(1), ((1, 0), (1, 0))) for s in scenes
    ]
    chosen: list[tuple[int, int, int, int]] = []
    total = 0
    while total < n_samples:
        for centre in rng.permutation(len(index))[:4096]:
            number = int(index.scene[centre])
            height, width = scenes[number].shape
            y = int(index.ys[centre]) - int(rng.integers(0, side))
            x = int(index.xs[centre]) - int(rng.integers(0, side))
            y0, x0 = min(max(0, y), height - side), min(max(0, x), width - side)
            table = counts[number]
            n = int(
                table[y0 + side, x0 + side]
                - table[y0, x0 + side]
                - table[y0 + side, x0]
                + table[y0, x0]
            )
            chosen.append((number, y0, x0, n))
            total += n
            if total >= n_samples:
                break
    columns = np.array(chosen, dtype=np.int32).reshape(-1, 4).T  # (4, N), also for N = 0
    return CropBatch(*(np.ascontiguousarray(column) for column in columns))


def gather_crops(
    scenes: Sequence[PreparedScene],
    crops: CropBatch,
    rows: np.ndarray,
    crop_size: int,
    flip: np.ndarray | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Input crops, targets and loss masks of the chosen dense-mode crops.

    Args:
        scenes: The prepared scenes.
        crops: All crops of the epoch.
        rows: (B,) indices into ``crops``.
        crop_size: Requested output side (clipped as in :func:`dense_crops`).
        flip: Optional (B,) bool: turn these crops (volume, targets and mask) upside down.

    Returns:
        ``(volumes, targets, mask)``: (B, 1, D, c + 12, c + 12) float32, (B, c, c) float32
        (1 = correct) and (B, c, c) bool (True = labelled).
    """
    side = _crop_side(scenes, crop_size)
    depth = scenes[0].volume.shape[0]
    span = side + 2 * PAD
    volumes = torch.empty((len(rows), 1, depth, span, span), dtype=torch.float32)
    targets = np.empty((len(rows), side, side), dtype=np.float32)
    mask = np.empty((len(rows), side, side), dtype=bool)
    for out_row, row in enumerate(rows):
        scene = scenes[int(crops.scene[row])]
        y0, x0 = int(crops.y0[row]), int(crops.x0[row])
        volumes[out_row, 0] = scene.volume[:, y0 : y0 + span, x0 : x0 + span].float()
        targets[out_row] = scene.correct[y0 : y0 + side, x0 : x0 + side]
        mask[out_row] = scene.labelled[y0 : y0 + side, x0 : x0 + side]
        if flip is not None and flip[out_row]:
            volumes[out_row] = volumes[out_row].flip(-2)
            targets[out_row] = targets[out_row, ::-1]
            mask[out_row] = mask[out_row, ::-1]
    return volumes, torch.from_numpy(targets), torch.from_numpy(mask)


def batches(order: np.ndarray, batch_size: int) -> Iterator[np.ndarray]:
    """Consecutive slices of ``order`` of at most ``batch_size`` entries."""
    for start in range(0, len(order), batch_size):
        yield order[start : start + batch_size]


def validation_subset(
    scenes: Sequence[LabelledScene], n_pixels: int, seed: int
) -> list[tuple[np.ndarray, np.ndarray]]:
    """A fixed random subset of labelled pixels per validation scene, ``n_pixels`` in all.

    Pixels are drawn uniformly over all labelled pixels of all scenes (so larger scenes get more).

    Returns:
        Per scene, (ys, xs) int arrays (possibly empty; all empty if ``n_pixels`` < 1).
    """
    index = sample_index(scenes)
    rng = np.random.default_rng([seed, 7])
    # A negative slice end would take all but that many pixels.
    take = rng.permutation(len(index))[: max(0, min(n_pixels, len(index)))]
    take.sort()
    return [
        (index.ys[take][index.scene[take] == n], index.xs[take][index.scene[take] == n])
        for n in range(len(scenes))
    ]
