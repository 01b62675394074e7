"""Loaders of stereo data sets with ground truth, one registered object per data set.

Every loader reads the layout of the original download (and of the copies under the shared data
folder), so a user points it at their own KITTI, Middlebury, ETH3D or Scene Flow folder. All
return :class:`StereoSample` in the package conventions (``left[y, x] ≈ right[y, x - d]``,
disparity float32 with NaN where unknown, never negative).

Train / develop split (see :data:`TRAIN_DATASETS`, :data:`DEVELOP_DATASETS`): never train on the
develop sets. ``motorcycle`` is in neither: it is the Middlebury 2014 Motorcycle scene, so it
must not be trained on either. Middlebury 2014 ``ArtL`` and ``Teddy`` derive from the 2005 Art
and 2003 Teddy scenes: drop 2005 Art from training data when reporting on Middlebury 2014.
``stereo_folder`` (a user's own pairs, see :class:`StereoFolder`) is in neither: it may be
trained on and evaluated; keeping its training and evaluation scenes apart is the user's part.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from numbers import Integral
import os
from pathlib import Path
import re
from typing import Any

import numpy as np

from cva_confidence_ros.datasets.io import (
    MAX_IMAGE_PIXELS,
    Calibration,
    read_disparity_png,
    read_image,
    read_kitti_calibration,
    read_middlebury_calibration,
    read_pfm,
)
from cva_confidence_ros.errors import ConfigError, DataError, reason
from cva_confidence_ros.registry import Registry

__all__ = [
    'DATASETS',
    'DEVELOP_DATASETS',
    'TRAIN_DATASETS',
    'StereoDataset',
    'StereoFolder',
    'StereoSample',
    'list_scenes',
    'load_dataset',
    'load_scene',
    'skipped_notice',
    'skipped_scenes',
]

PathLike = str | Path


@dataclass(frozen=True, eq=False)
class StereoSample:
    """One rectified stereo pair with ground truth.

    Attributes:
        dataset: Registered data set name (``kitti2015``, ``middlebury2014``, ...).
        scene: Scene id within the data set (as listed by :func:`list_scenes`).
        left: (H, W, 3) uint8 RGB or (H, W) uint8 gray left image.
        right: Same shape and dtype as ``left``.
        disparity: (H, W) float32 left ground-truth disparity in pixels, ≥ 0, NaN = unknown;
            +inf (how Middlebury and ETH3D PFMs, and :func:`read_pfm`, mark unknown) is
            stored as NaN.
        nonocc: (H, W) bool, True where the pixel is visible in both views, or None if the data
            set has no occlusion information.
        calib: Calibration of the pair, or None.
    """

    dataset: str
    scene: str
    left: np.ndarray
    right: np.ndarray
    disparity: np.ndarray
    nonocc: np.ndarray | None = None
    calib: Calibration | None = None

    def __post_init__(self) -> None:
        where = f'{self.dataset}/{self.scene}'
        for side, image in (('left', self.left), ('right', self.right)):
            if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
                got = image.dtype if isinstance(image, np.ndarray) else type(image).__name__
                raise DataError(f'{where}: {side} image must be uint8; got {got}')
            if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
                raise DataError(f'{where}: {side} image must be H×W or H×W×3; got {image.shape}')
        if self.left.shape != self.right.shape:
            raise DataError(
                f'{where}: left and right images must have the same shape; '
                f'got {self.left.shape} and {self.right.shape}'
            )
        shape = self.left.shape[:2]
        for field in ('disparity', 'nonocc'):
            value = getattr(self, field)
            if not isinstance(value, np.ndarray) and (field == 'disparity' or value is not None):
                # A list or None failed with AttributeError on .dtype.
                raise DataError(
                    f'{where}: {field} must be a numpy array of shape {shape}; '
                    f'got {type(value).__name__}'
                )
        if self.disparity.dtype != np.float32 or self.disparity.shape != shape:
            raise DataError(
                f'{where}: disparity must be float32 of shape {shape}; '
                f'got {self.disparity.dtype} {self.disparity.shape}'
            )
        unknown = np.isposinf(self.disparity)
        if unknown.any():
            # Middlebury's inf = unknown was kept as a disparity ∞ (NaN = unknown elsewhere).
            disparity = self.disparity.copy()
            disparity[unknown] = np.nan
            object.__setattr__(self, 'disparity', disparity)
        with np.errstate(invalid='ignore'):
            negative = self.disparity < 0
        if negative.any():
            # Another sign convention (right-to-left) was scored as all wrong pixels.
            y, x = np.argwhere(negative)[0]
            raise DataError(
                f'{where}: disparity must be ≥ 0 (NaN = unknown); got '
                f'{self.disparity[y, x]:g} at (y, x) = ({y}, {x})'
            )
        if self.nonocc is not None and (
            self.nonocc.dtype != np.bool_ or self.nonocc.shape != shape
        ):
            raise DataError(
                f'{where}: nonocc must be bool of shape {shape}; '
                f'got {self.nonocc.dtype} {self.nonocc.shape}'
            )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the pair."""
        return (int(self.left.shape[0]), int(self.left.shape[1]))

    @property
    def max_disparity(self) -> float:
        """Largest finite ground-truth disparity (0 if none is known)."""
        finite = self.disparity[np.isfinite(self.disparity)]
        return float(finite.max()) if finite.size else 0.0


def _clean_disparity(disparity: np.ndarray) -> np.ndarray:
    """NaN for unknown (±inf, NaN) and negative values; float32."""
    disparity = np.asarray(disparity, dtype=np.float32).copy()
    with np.errstate(invalid='ignore'):
        disparity[~np.isfinite(disparity) | (disparity < 0)] = np.nan
    return disparity


def _sample(files: dict[str, Path | None], **fields: Any) -> StereoSample:
    """``StereoSample(**fields)``; shapes or dtypes it refuses are reported with the files read,
    so that a ground truth or mask of the wrong size names the file to look at."""
    try:
        return StereoSample(**fields)
    except DataError as exc:
        read = ', '.join(f'{role} {path}' for role, path in files.items() if path is not None)
        raise DataError(f'{exc} (files: {read})') from None


def _visible_mask(path: Path) -> np.ndarray:
    """A non-occlusion mask image as bool (H, W): True where it is 255 (every channel)."""
    nonocc = read_image(path) == 255
    return nonocc.all(axis=2) if nonocc.ndim == 3 else nonocc


def _read_npy(path: Path) -> np.ndarray:
    """An (H, W) real-valued ``.npy`` array as float32 (no pickles).

    Raises:
        DataError: The file cannot be read, or holds no (H, W) real-valued array.
    """
    try:
        # Mapped, not read: a header that declares more data than the file holds is refused
        # by its length before anything is allocated (read, a 100-byte file declaring
        # 100000 × 100000 floats raised MemoryError, or allocated gigabytes).
        raw = np.load(path, mmap_mode='r')
    except (OSError, ValueError, EOFError) as exc:  # EOFError: an empty or cut file
        why = reason(exc)
        if 'mmap length' in why:
            why = 'it holds less data than its header declares: cut short, or a corrupt header'
        raise DataError(f'cannot read {path} as a float array ({why})') from exc
    if not isinstance(raw, np.ndarray) or raw.dtype.kind not in 'fiu' or raw.ndim != 2:
        got = f'{raw.dtype} {raw.shape}' if isinstance(raw, np.ndarray) else type(raw).__name__
        raise DataError(f'{path}: expected an (H, W) real-valued array; got {got}')
    if raw.size > MAX_IMAGE_PIXELS:
        raise DataError(
            f'{path}: a {raw.shape[1]}×{raw.shape[0]} array is more than {MAX_IMAGE_PIXELS} '
            f'pixels, the most an image may have'
        )
    return np.array(raw, dtype=np.float32, order='C')


def _im0_im1_sample(
    dataset: str, scene: str, folder: Path, gt: Path, mask: Path | None
) -> StereoSample:
    """The MiddEval3 / ETH3D layout: im0.png, im1.png, a PFM ground truth, optional
    non-occlusion mask (255 = visible) and calib.txt."""
    nonocc = _visible_mask(mask) if mask is not None else None
    calib = None
    if (folder / 'calib.txt').is_file():
        calib = read_middlebury_calibration(folder / 'calib.txt')
    left, right = folder / 'im0.png', folder / 'im1.png'
    return _sample(
        {'left': left, 'right': right, 'disparity': gt, 'nonocc': mask},
        dataset=dataset,
        scene=scene,
        left=read_image(left),
        right=read_image(right),
        disparity=_clean_disparity(read_pfm(gt)),
        nonocc=nonocc,
        calib=calib,
    )


def _first_existing(folder: Path, names: tuple[str, ...]) -> Path | None:
    for name in names:
        if (folder / name).is_file():
            return folder / name
    return None


def _absent(path: Path, base: Path, also: tuple[str, ...] = ()) -> str:
    """``path`` relative to ``base`` (or the names ``also``), naming the files beside it that
    look meant for it (another case, another suffix, ``im1E.png`` beside a missing ``im1.png``):
    on a case-sensitive file system ``IM0.PNG`` or ``000005_10.jpg`` is not the file looked
    for."""
    stem = path.stem.lower()
    try:
        near = sorted(
            p.name
            for p in path.parent.iterdir()
            if p.name.lower().startswith(stem) and p.is_file()
        )
    except OSError:
        near = []
    found = f' (found {", ".join(near[:3])})' if near else ''
    alternatives = f' (or {", ".join(also)})' if also else ''
    return f'{path.relative_to(base).as_posix()}{alternatives}{found}'


def _describe(skipped: list[tuple[str, str]], limit: int = 3) -> str:
    """``'<scene> has no <file>; …'`` for the first ``limit`` of ``skipped``."""
    shown = '; '.join(f'{scene} has {why}' for scene, why in skipped[:limit])
    more = f' (and {len(skipped) - limit} more)' if len(skipped) > limit else ''
    return shown + more


def _rglob(root: Path, pattern: str) -> Iterator[Path]:
    """``root.rglob(pattern)`` that also goes into symlinked folders (rglob does not: scene
    folders linked in from another disk were not found), each real folder once."""
    seen: set[tuple[int, int]] = set()
    for folder, dirs, _ in os.walk(root, followlinks=True):
        dirs.sort()
        try:
            info = os.stat(folder)
        except OSError:
            continue
        if (info.st_dev, info.st_ino) in seen:  # a link back up the tree, or a second link
            dirs.clear()
            continue
        seen.add((info.st_dev, info.st_ino))
        yield from Path(folder).glob(pattern)


def _scale_by_width(width: int, steps: tuple[tuple[int, float], ...], last: float) -> float:
    """Divisor of stored disparities, chosen by the image width (the file name has no size)."""
    for min_width, scale in steps:
        if width >= min_width:
            return scale
    return last


class StereoDataset:
    """One data set layout: lists scenes under a root and loads them.

    Attributes:
        name: Registered name.
        layout: Human-readable description of the expected folder layout (used in errors).
        splits: Accepted ``split`` values; empty if the data set has no splits.
        default_split: Split used when ``split`` is None.
        needs_root: False only for data sets that ship with a library (``motorcycle``).
    """

    name = ''
    layout = ''
    splits: tuple[str, ...] = ()
    default_split: str | None = None
    needs_root = True
    #: What :meth:`skipped` lists, for messages.
    skipped_what = 'scenes missing a file'
    #: Scenes at any depth under the root: a root one level off is no mistake to point out.
    any_depth = False

    def resolve_split(self, split: str | None) -> str | None:
        """Validate ``split`` and apply the default.

        Raises:
            ConfigError: A split the data set does not have.
        """
        if split is None:
            return self.default_split
        if split not in self.splits:
            raise ConfigError(
                f'{self.name} has splits {list(self.splits) or "none"}; got split={split!r}'
            )
        return split

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        """Sorted scene ids under ``root`` (empty if none match the layout)."""
        raise NotImplementedError

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        """Load one scene; raise :class:`DataError` if its files are missing or unreadable."""
        raise NotImplementedError

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        """``(scene, 'no <file> …')`` of each scene under ``root`` that :meth:`list_scenes`
        leaves out for a missing file although it has ground truth (or, where a split holds
        only scenes with ground truth, an image); sorted by scene."""
        return []

    def _elsewhere(self, folder: Path, split: str | None) -> Path | None:
        """The nearest folder up to two levels above or below ``folder`` that holds pairs in
        this layout (an archive extracted with its top folder, a root one level too deep)."""
        if self.any_depth or not folder.is_dir():
            return None
        near = [folder.absolute().parent, folder.absolute().parent.parent]
        try:
            children = sorted(p for p in folder.iterdir() if p.is_dir())
            near += children[:50]
            for child in children[:50]:
                near += sorted(p for p in child.iterdir() if p.is_dir())[:50]
        except OSError:
            pass
        return next(
            (
                path
                for path in dict.fromkeys(near)
                if path.absolute() != folder.absolute() and self.list_scenes(path, split)
            ),
            None,
        )

    def no_pairs(self, folder: Path, split: str | None = None) -> DataError:
        """The error for a root without a single pair in this layout (for ``split``, named
        with the splits that do hold pairs: a default split the root lacks gave no hint; for no
        split, the splits whose subfolders hold pairs)."""
        where = ''
        if split is not None:
            others = [s for s in self.splits if s != split and self.list_scenes(folder, s)]
            held = f'; split(s) {others} hold pairs there' if others else ''
            where = f' for split {split!r}{held}'
        else:
            # <root>/ThirdSize/<scene>/ (the original Middlebury 2005 layout) without a split
            # said only 'no pairs found'.
            others = [s for s in self.splits if self.list_scenes(folder, s)]
            if others:
                where = f' without a split; split(s) {others} hold pairs there'
        message = (
            f'no {self.name} stereo pairs found under {folder}{where}; expected {self.layout}'
        )
        # A download without its ground-truth part, or without the right images, said only
        # 'no pairs found'.
        skipped = self.skipped(folder, split)
        if skipped:
            message += f'; {self.skipped_what}: {_describe(skipped)}'
        elif elsewhere := self._elsewhere(folder, split):
            message += f'; pairs found under {elsewhere}: use that as root'
        else:
            # KITTI 2015 given as kitti2012, Scene Flow samples as flyingthings3d.
            others = [
                other
                for other in DATASETS
                if other != self.name
                and DATASETS.get(other).needs_root
                and not DATASETS.get(other).any_depth
                and DATASETS.get(other).list_scenes(folder, DATASETS.get(other).default_split)
            ]
            if others:
                message += f'; pairs of data set(s) {others} found there'
        return DataError(message)

    def missing(self, root: Path, scene: str, split: str | None = None) -> DataError:
        """The error for an unknown scene: what it lacks if it misses a file, else some of
        the scenes there are."""
        for name, why in self.skipped(root, split):
            if name == scene:
                return DataError(
                    f'{self.name} scene {scene!r} not found under {root}: it has {why}'
                )
        scenes = self.list_scenes(root, split)
        there = f'{len(scenes)} scene(s) there: {", ".join(scenes[:5])}'
        if len(scenes) > 5:
            there += ', …'
        return DataError(
            f'{self.name} scene {scene!r} not found under {root}; '
            + (there if scenes else f'expected {self.layout}')
        )


class _Kitti(StereoDataset):
    splits = ('training',)
    default_split = 'training'
    occ_dir = ''
    noc_dir = ''
    image_dirs: tuple[tuple[str, str], ...] = ()
    calib_dir = ''
    calib_keys: dict[str, tuple[str, str]] = {}

    def _base(self, root: Path, split: str | None) -> Path:
        base = root / str(split)
        return base if (base / self.occ_dir).is_dir() else root

    def _images(self, base: Path, scene: str) -> tuple[str, Path, Path] | None:
        for left_dir, right_dir in self.image_dirs:
            left = base / left_dir / f'{scene}_10.png'
            right = base / right_dir / f'{scene}_10.png'
            if left.is_file() and right.is_file():
                return left_dir, left, right
        return None

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        base = self._base(root, split)
        folder = base / self.occ_dir
        if not folder.is_dir():
            return []
        scenes = []
        for path in folder.glob('*_10.png'):
            scene = path.name[: -len('_10.png')]
            if re.fullmatch(r'\d{6}', scene) and self._images(base, scene):
                scenes.append(scene)
        return sorted(scenes)

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        base = self._base(root, split)
        folder = base / self.occ_dir
        if not folder.is_dir():
            return []
        skipped = []
        for path in sorted(folder.glob('*_10.png')):
            scene = path.name[: -len('_10.png')]
            if not re.fullmatch(r'\d{6}', scene) or self._images(base, scene):
                continue
            name = f'{scene}_10.png'
            # The pair of which one image is there (KITTI 2012: colour or gray), else all.
            pairs = [p for p in self.image_dirs if any((base / d / name).is_file() for d in p)]
            if not pairs and len(self.image_dirs) > 1:
                dirs = ' or '.join(f'{left},{right}' for left, right in self.image_dirs)
                skipped.append((scene, f'no images ({{{dirs}}}/{name})'))
                continue
            absent = [
                _absent(base / d / name, base)
                for d in (pairs or self.image_dirs)[0]
                if not (base / d / name).is_file()
            ]
            skipped.append((scene, 'no ' + ' and no '.join(absent)))
        return skipped

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        base = self._base(root, split)
        gt_path = base / self.occ_dir / f'{scene}_10.png'
        found = self._images(base, scene)
        if found is None or not gt_path.is_file():
            raise self.missing(root, scene, split)
        image_dir, left_path, right_path = found
        noc_path = base / self.noc_dir / f'{scene}_10.png'
        nonocc = None
        if noc_path.is_file():
            nonocc = np.isfinite(read_disparity_png(noc_path, 256.0, bits=16))
        files = {
            'left': left_path,
            'right': right_path,
            'disparity': gt_path,
            'nonocc': noc_path if nonocc is not None else None,
        }
        calib = None
        calib_path = base / self.calib_dir / f'{scene}.txt'
        if calib_path.is_file():
            calib = read_kitti_calibration(calib_path, *self.calib_keys[image_dir])
        return _sample(
            files,
            dataset=self.name,
            scene=scene,
            left=read_image(left_path),
            right=read_image(right_path),
            disparity=_clean_disparity(read_disparity_png(gt_path, 256.0, bits=16)),
            nonocc=nonocc,
            calib=calib,
        )


class Kitti2012(_Kitti):
    """KITTI stereo 2012: ``training/{colored_0,colored_1}/<id>_10.png`` (or gray
    ``image_0/image_1``), ``disp_occ/<id>_10.png`` (uint16, d = v / 256, 0 = unknown),
    optional ``disp_noc/`` (non-occlusion) and ``calib/<id>.txt`` (P0/P1 for both pairs: the
    colour images share the gray cameras' viewpoints)."""

    name = 'kitti2012'
    layout = (
        '<root>/training/{colored_0,colored_1 or image_0,image_1}/<6 digits>_10.png and '
        'disp_occ/<6 digits>_10.png (uint16, d = v / 256)'
    )
    occ_dir, noc_dir, calib_dir = 'disp_occ', 'disp_noc', 'calib'
    image_dirs = (('colored_0', 'colored_1'), ('image_0', 'image_1'))
    # The benchmark's colour images are pixel-aligned with the gray ones (and share their
    # ground truth), so both take the gray cameras' P0/P1: P2/P3, the colour cameras' own
    # baseline (0.532 m against 0.537 m), gave depths 0.9 % short.
    calib_keys = {'colored_0': ('P0', 'P1'), 'image_0': ('P0', 'P1')}


class Kitti2015(_Kitti):
    """KITTI stereo 2015: ``training/{image_2,image_3}/<id>_10.png``, ``disp_occ_0/`` (uint16,
    d = v / 256, 0 = unknown), optional ``disp_noc_0/`` and ``calib_cam_to_cam/<id>.txt``."""

    name = 'kitti2015'
    layout = (
        '<root>/training/{image_2,image_3}/<6 digits>_10.png and disp_occ_0/<6 digits>_10.png '
        '(uint16, d = v / 256)'
    )
    occ_dir, noc_dir, calib_dir = 'disp_occ_0', 'disp_noc_0', 'calib_cam_to_cam'
    image_dirs = (('image_2', 'image_3'),)
    calib_keys = {'image_2': ('P_rect_02', 'P_rect_03')}


class Middlebury2014(StereoDataset):
    """Middlebury v3 (MiddEval3): ``<split>/<Scene>/{im0,im1}.png``, ``disp0GT.pfm`` (inf =
    unknown), ``mask0nocc.png`` (255 = visible in both views), ``calib.txt``."""

    name = 'middlebury2014'
    layout = (
        '<root>/<trainingQ|trainingH|trainingF>/<Scene>/{im0.png, im1.png, disp0GT.pfm} '
        '(+ mask0nocc.png, calib.txt)'
    )
    splits = ('trainingQ', 'trainingH', 'trainingF')
    default_split = 'trainingQ'

    def _base(self, root: Path, split: str | None) -> Path:
        for base in (root / str(split), root / 'MiddEval3' / str(split)):
            if base.is_dir():
                return base
        return root

    #: disp0.pfm: the full-size 2014 downloads (``<Scene>-perfect|-imperfect/``), which
    #: have no disp0GT.pfm.
    gt_names = ('disp0GT.pfm', 'disp0.pfm')

    def _is_scene(self, folder: Path) -> bool:
        return (folder / 'im0.png').is_file() and (folder / 'im1.png').is_file() and bool(
            _first_existing(folder, self.gt_names)
        )

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        base = self._base(root, split)
        if not base.is_dir():
            return []
        return sorted(p.name for p in base.iterdir() if p.is_dir() and self._is_scene(p))

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        base = self._base(root, split)
        if not base.is_dir():
            return []
        wanted = {'im0', 'im1', 'disp0gt', 'disp0'}
        skipped = []
        for folder in sorted(p for p in base.iterdir() if p.is_dir()):
            # Names in any case count: IM0.PNG is named as found, not left out unsaid.
            if self._is_scene(folder) or not any(
                p.stem.lower() in wanted for p in folder.iterdir()
            ):
                continue
            absent = [
                _absent(folder / name, folder)
                for name in ('im0.png', 'im1.png')
                if not (folder / name).is_file()
            ]
            if not _first_existing(folder, self.gt_names):
                absent.append(_absent(folder / 'disp0GT.pfm', folder, self.gt_names[1:]))
            skipped.append((folder.name, 'no ' + ' and no '.join(absent)))
        return skipped

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        folder = self._base(root, split) / scene
        if not self._is_scene(folder):
            raise self.missing(root, scene, split)
        mask = folder / 'mask0nocc.png'
        gt = _first_existing(folder, self.gt_names) or folder / 'disp0GT.pfm'
        return _im0_im1_sample(self.name, scene, folder, gt, mask if mask.is_file() else None)


@dataclass(frozen=True)
class _Pattern:
    """File names of one pair inside a scene folder; ``{scene}`` is replaced by its name."""

    left: tuple[str, ...]
    right: tuple[str, ...]
    gt: tuple[str, ...]
    scale: float | None  # None: chosen by the image width

    def match(self, folder: Path) -> tuple[Path, Path, Path] | None:
        names = [
            _first_existing(folder, tuple(n.format(scene=folder.name) for n in group))
            for group in (self.left, self.right, self.gt)
        ]
        if any(name is None for name in names):
            return None
        return names[0], names[1], names[2]  # type: ignore[return-value]


class _FolderPerScene(StereoDataset):
    """Older Middlebury sets: one folder per scene, 8-bit disparity PNG/PGM, 0 = unknown."""

    patterns: tuple[_Pattern, ...] = ()
    size_scales: dict[str, float] = {}
    #: Split → (min, max) image width of the data set's own files at that size: a split
    #: named for files of another size would read their disparities at the wrong scale.
    split_widths: dict[str, tuple[int, int]] = {}

    def _base(self, root: Path, split: str | None) -> Path:
        if split is not None and (root / split).is_dir():
            return root / split
        return root

    def _match(self, folder: Path) -> tuple[_Pattern, tuple[Path, Path, Path]] | None:
        for pattern in self.patterns:
            files = pattern.match(folder)
            if files is not None:
                return pattern, files
        return None

    def _width_scale(self, width: int) -> float:
        raise NotImplementedError

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        base = self._base(root, split)
        if not base.is_dir():
            return []
        return sorted(p.name for p in base.iterdir() if p.is_dir() and self._match(p))

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        base = self._base(root, split)
        if not base.is_dir():
            return []
        skipped = []
        for folder in sorted(p for p in base.iterdir() if p.is_dir() and not self._match(p)):
            # The naming of which most files are there.
            best: list[str] = []
            most = 0
            for pattern in self.patterns:
                groups = [
                    tuple(n.format(scene=folder.name) for n in group)
                    for group in (pattern.left, pattern.right, pattern.gt)
                ]
                lacking = [group for group in groups if _first_existing(folder, group) is None]
                if len(groups) - len(lacking) > most:
                    most = len(groups) - len(lacking)
                    best = [_absent(folder / group[0], folder, group[1:]) for group in lacking]
            if best:
                skipped.append((folder.name, 'no ' + ' and no '.join(best)))
        return skipped

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        folder = self._base(root, split) / scene
        found = self._match(folder) if folder.is_dir() else None
        if found is None:
            raise self.missing(root, scene, split)
        pattern, (left_path, right_path, gt_path) = found
        left = read_image(left_path)
        if pattern.scale is not None:
            scale = pattern.scale
        elif split is not None:
            scale = self.size_scales[split]
            width = left.shape[1]
            other = [
                name
                for name, (low, high) in self.split_widths.items()
                if name != split and low <= width <= high
            ]
            if other:
                raise DataError(
                    f'split {split!r} stores disparity × {scale:g}, but {left_path} is {width} px '
                    f'wide, the width of split {other[0]!r} (disparity × '
                    f'{self.size_scales[other[0]]:g}); pick that split'
                )
        else:
            scale = self._width_scale(left.shape[1])
        mask_path = folder / 'nonocc.png'
        nonocc = _visible_mask(mask_path) if mask_path.is_file() else None
        return _sample(
            {
                'left': left_path,
                'right': right_path,
                'disparity': gt_path,
                'nonocc': mask_path if nonocc is not None else None,
            },
            dataset=self.name,
            scene=scene,
            left=left,
            right=read_image(right_path),
            disparity=_clean_disparity(read_disparity_png(gt_path, scale, bits=8)),
            nonocc=nonocc,
        )


class Middlebury2001(_FolderPerScene):
    """Middlebury 2001: Tsukuba (``scene1.row3.col3/col4.ppm``, ``truedisp.row3.col3.pgm``,
    d = v / 16), Sawtooth-style scenes (``im2/im6.ppm``, ``disp2.pgm``, d = v / 8) and Map
    (``im0/im1.pgm``, ``disp0.pgm``, d = v / 8)."""

    name = 'middlebury2001'
    layout = (
        '<root>/<scene>/ with scene1.row3.col3.ppm, scene1.row3.col4.ppm, truedisp.row3.col3.pgm '
        '(v / 16), or im2 + im6 + disp2 (v / 8), or im0 + im1 + disp0 (v / 8), .ppm/.pgm/.png'
    )
    patterns = (
        _Pattern(
            ('scene1.row3.col3.ppm', 'scene1.row3.col3.png'),
            ('scene1.row3.col4.ppm', 'scene1.row3.col4.png'),
            ('truedisp.row3.col3.pgm', 'truedisp.row3.col3.png'),
            16.0,
        ),
        _Pattern(
            ('im2.ppm', 'im2.pgm', 'im2.png'),
            ('im6.ppm', 'im6.pgm', 'im6.png'),
            ('disp2.pgm', 'disp2.png'),
            8.0,
        ),
        _Pattern(
            ('im0.ppm', 'im0.pgm', 'im0.png'),
            ('im1.ppm', 'im1.pgm', 'im1.png'),
            ('disp0.pgm', 'disp0.png'),
            8.0,
        ),
    )


class Middlebury2003(_FolderPerScene):
    """Middlebury 2003 (Cones, Teddy): ``im2/im6`` and ``disp2`` (original names) or
    ``<scene>_image_02/06.png`` and ``<scene>_disp_02.png``; d = v / 4 at quarter size
    (v / 2 half, v / 1 full, chosen by the image width or by split ``quarter|half|full``)."""

    name = 'middlebury2003'
    layout = (
        '<root>/<scene>/ with im2.png + im6.png + disp2.png, or <scene>_image_02.png + '
        '<scene>_image_06.png + <scene>_disp_02.png (8 bit, 0 = unknown)'
    )
    splits = ('quarter', 'half', 'full')
    size_scales = {'quarter': 4.0, 'half': 2.0, 'full': 1.0}
    split_widths = {'quarter': (440, 460), 'half': (880, 920), 'full': (1760, 1840)}
    patterns = (
        _Pattern(
            ('{scene}_image_02.png',),
            ('{scene}_image_06.png',),
            ('{scene}_disp_02.png',),
            None,
        ),
        _Pattern(
            ('im2.png', 'im2.ppm'),
            ('im6.png', 'im6.ppm'),
            ('disp2.png', 'disp2.pgm'),
            None,
        ),
    )

    def _width_scale(self, width: int) -> float:
        # Full size is 1800 px wide, half 900, quarter 450.
        return _scale_by_width(width, ((1200, 1.0), (600, 2.0)), 4.0)


class Middlebury2005(_FolderPerScene):
    """Middlebury 2005 / 2006: ``view1/view5.png`` + ``disp1.png`` (original) or
    ``img0/img1.png`` + ``disp1.png``; d = v / 3 at third size (v / 2 half, v / 1 full, by
    image width or split ``ThirdSize|HalfSize|FullSize``, which may also be a subfolder)."""

    name = 'middlebury2005'
    layout = (
        '<root>[/<FullSize|HalfSize|ThirdSize>]/<scene>/ with view1.png + view5.png + disp1.png '
        '(or img0.png + img1.png + disp1.png), 8 bit, 0 = unknown'
    )
    splits = ('ThirdSize', 'HalfSize', 'FullSize')
    size_scales = {'ThirdSize': 3.0, 'HalfSize': 2.0, 'FullSize': 1.0}
    split_widths = {'ThirdSize': (413, 465), 'HalfSize': (620, 698), 'FullSize': (1240, 1396)}
    patterns: tuple[_Pattern, ...] = (
        _Pattern(('view1.png',), ('view5.png',), ('disp1.png',), None),
        _Pattern(('img0.png',), ('img1.png',), ('disp1.png',), None),
    )

    def _width_scale(self, width: int) -> float:
        # Full size is 1240–1396 px wide, half 620–698, third 413–465.
        return _scale_by_width(width, ((1000, 1.0), (550, 2.0)), 3.0)


class Middlebury2006(Middlebury2005):
    """Middlebury 2006: as 2005, plus the OpenCV sample naming ``<scene>L.jpg``,
    ``<scene>R.jpg``, ``<scene>GT.png``."""

    name = 'middlebury2006'
    layout = (
        '<root>[/<FullSize|HalfSize|ThirdSize>]/<scene>/ with view1.png + view5.png + disp1.png '
        'or <scene>L.(png|jpg) + <scene>R.(png|jpg) + <scene>GT.png, 8 bit, 0 = unknown'
    )
    patterns: tuple[_Pattern, ...] = Middlebury2005.patterns + (
        _Pattern(
            ('{scene}L.png', '{scene}L.jpg'),
            ('{scene}R.png', '{scene}R.jpg'),
            ('{scene}GT.png',),
            None,
        ),
    )


class Eth3d(StereoDataset):
    """ETH3D low-res two-view: ``two_view_training/<scene>/{im0,im1}.png``, ``calib.txt`` and
    ``disp0GT.pfm`` + ``mask0nocc.png`` (from ``two_view_training_gt``, in the same folder or a
    sibling one, also beside a root that is ``two_view_training`` itself) or ``disp0.pfm``;
    inf = unknown."""

    name = 'eth3d'
    layout = (
        '<root>/two_view_training/<scene>/{im0.png, im1.png} with disp0GT.pfm (here or in '
        '<root>/two_view_training_gt/<scene>/) or disp0.pfm'
    )
    splits = ('two_view_training',)
    default_split = 'two_view_training'

    def _base(self, root: Path, split: str | None) -> Path:
        base = root / str(split)
        return base if base.is_dir() else root

    def _files(
        self, root: Path, split: str | None, scene: str
    ) -> tuple[Path | None, Path | None]:
        """(ground truth, mask) of ``scene``, each None where not found."""
        base = self._base(root, split)
        folder = base / scene
        gt, mask = (
            _first_existing(folder, ('disp0GT.pfm', 'disp0.pfm')),
            _first_existing(folder, ('mask0nocc.png',)),
        )
        # The sibling of the training folder: under the root, or beside the root where the
        # root is the training folder itself (its GT was not found there).
        for gt_folder in dict.fromkeys((root / f'{split}_gt', base.parent / f'{split}_gt')):
            gt = gt or _first_existing(gt_folder / scene, ('disp0GT.pfm',))
            mask = mask or _first_existing(gt_folder / scene, ('mask0nocc.png',))
        return gt, mask

    def _lacks(self, root: Path, split: str | None, folder: Path) -> list[str]:
        """What keeps ``folder`` from being a scene (empty if it is one)."""
        absent = [
            _absent(folder / name, folder)
            for name in ('im0.png', 'im1.png')
            if not (folder / name).is_file()
        ]
        if self._files(root, split, folder.name)[0] is None:
            # two_view_training_gt is a download of its own.
            absent.append(f'disp0GT.pfm (here or in {split}_gt/{folder.name}/)')
        return absent

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        base = self._base(root, split)
        if not base.is_dir():
            return []
        return sorted(
            p.name for p in base.iterdir() if p.is_dir() and not self._lacks(root, split, p)
        )

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        base = self._base(root, split)
        if not base.is_dir():
            return []
        skipped = []
        for folder in sorted(p for p in base.iterdir() if p.is_dir()):
            lacks = self._lacks(root, split, folder)
            if lacks and len(lacks) < 3:  # a folder without any of the three is no scene
                skipped.append((folder.name, 'no ' + ' and no '.join(lacks)))
        return skipped

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        folder = self._base(root, split) / scene
        gt, mask = self._files(root, split, scene)
        if gt is None or self._lacks(root, split, folder):
            raise self.missing(root, scene, split)
        return _im0_im1_sample(self.name, scene, folder, gt, mask)


class FlyingThings3D(StereoDataset):
    """FlyingThings3D (Scene Flow): ``frames_cleanpass/<TRAIN|TEST>/<A|B|C>/<seq>/
    {left,right}/<frame>.png`` (or ``frames_finalpass``) and ``disparity/…/left/<frame>.pfm``.
    Scene ids are ``<TRAIN|TEST>/<letter>/<seq>/<frame>``."""

    name = 'flyingthings3d'
    layout = (
        '<root>/frames_cleanpass/<TRAIN|TEST>/<A|B|C>/<seq>/{left,right}/<frame>.png and '
        '<root>/disparity/<TRAIN|TEST>/<A|B|C>/<seq>/left/<frame>.pfm'
    )
    splits = ('TRAIN', 'TEST')
    image_roots = ('frames_cleanpass', 'frames_finalpass')

    def _images(self, root: Path, scene: str) -> tuple[Path, Path] | None:
        *sequence, frame = scene.split('/')
        for image_root in self.image_roots:
            folder = root.joinpath(image_root, *sequence)
            left, right = folder / 'left' / f'{frame}.png', folder / 'right' / f'{frame}.png'
            if left.is_file() and right.is_file():
                return left, right
        return None

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        scenes = []
        for part in (split,) if split else self.splits:
            folder = root / 'disparity' / part
            if not folder.is_dir():
                continue
            for pfm in folder.glob('*/*/left/*.pfm'):
                letter, sequence = pfm.parent.parent.parent.name, pfm.parent.parent.name
                scene = f'{part}/{letter}/{sequence}/{pfm.stem}'
                if self._images(root, scene):
                    scenes.append(scene)
        return sorted(scenes)

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        skipped = []
        for part in (split,) if split else self.splits:
            folder = root / 'disparity' / part
            for pfm in sorted(folder.glob('*/*/left/*.pfm')) if folder.is_dir() else ():
                letter, sequence = pfm.parent.parent.parent.name, pfm.parent.parent.name
                scene = f'{part}/{letter}/{sequence}/{pfm.stem}'
                if not self._images(root, scene):
                    where = f'{part}/{letter}/{sequence}/{{left,right}}/{pfm.stem}.png'
                    skipped.append((scene, f'no images ({"|".join(self.image_roots)})/{where}'))
        return skipped

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        parts = scene.split('/')
        if split is not None and len(parts) == 4 and parts[0] != split:
            # A TEST frame loaded under split TRAIN leaked test data into training.
            raise DataError(
                f'{self.name} scene {scene!r} is in split {parts[0]!r}, not in split {split!r}'
            )
        found = self._images(root, scene) if len(parts) == 4 else None
        gt = root.joinpath('disparity', *parts[:3], 'left', f'{parts[-1]}.pfm')
        if found is None or not gt.is_file():
            raise self.missing(root, scene, split)
        return _sample(
            {'left': found[0], 'right': found[1], 'disparity': gt},
            dataset=self.name,
            scene=scene,
            left=read_image(found[0]),
            right=read_image(found[1]),
            disparity=_clean_disparity(read_pfm(gt)),
        )


class _FramesByTruth(StereoDataset):
    """A data set of loose frames found by their ground-truth files (``_gt_files``: folder,
    frame id, its two images), each a scene when its files are all there (``_files``)."""

    def _gt_files(self, root: Path) -> Iterator[tuple[Path, str, tuple[Path, Path]]]:
        raise NotImplementedError

    @staticmethod
    def _files(folder: Path, frame: str) -> tuple[object, ...] | None:
        raise NotImplementedError

    @staticmethod
    def _scene(root: Path, folder: Path, frame: str) -> str:
        raise NotImplementedError

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        return sorted(
            {
                self._scene(root, folder, frame)
                for folder, frame, _ in self._gt_files(root)
                if self._files(folder, frame)
            }
        )

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        # A frame with ground truth but no right image was left out unsaid.
        skipped: dict[str, str] = {}
        for folder, frame, images in self._gt_files(root):
            scene = self._scene(root, folder, frame)
            if scene in skipped or self._files(folder, frame):
                continue
            absent = [_absent(path, folder) for path in images if not path.is_file()]
            skipped[scene] = 'no ' + ' and no '.join(absent)
        return sorted(skipped.items())


class SceneFlowExtra(_FramesByTruth):
    """Loose Scene Flow samples in two layouts, one folder each under the root:
    ``<dir>/{Left,Right}/<id>.png`` + ``<dir>/Disparity/<id>.pfm``, or
    ``<dir>/RGB_cleanpass/{left,right}/<id>.png`` + ``<dir>/disparity/left/<id>.pfm`` (+
    ``<dir>/occlusion/left/<id>.png``, 255 = occluded). Scene ids are ``<dir>/<id>``."""

    name = 'sceneflow_extra'
    layout = (
        '<root>/<dir>/{Left,Right}/<id>.png + <dir>/Disparity/<id>.pfm, or '
        '<root>/<dir>/RGB_cleanpass/{left,right}/<id>.png + <dir>/disparity/left/<id>.pfm'
    )

    @staticmethod
    def _files(folder: Path, stem: str) -> tuple[Path, Path, Path, Path | None] | None:
        candidates = (
            (folder / 'Left', folder / 'Right', folder / 'Disparity', None),
            (
                folder / 'RGB_cleanpass' / 'left',
                folder / 'RGB_cleanpass' / 'right',
                folder / 'disparity' / 'left',
                folder / 'occlusion' / 'left',
            ),
        )
        for left, right, gt, occlusion in candidates:
            files = (left / f'{stem}.png', right / f'{stem}.png', gt / f'{stem}.pfm')
            if all(path.is_file() for path in files):
                occ = occlusion / f'{stem}.png' if occlusion is not None else None
                return files[0], files[1], files[2], occ if occ and occ.is_file() else None
        return None

    def _gt_files(self, root: Path) -> Iterator[tuple[Path, str, tuple[Path, Path]]]:
        """(folder, frame id, its (left, right) images in the layout of its ground truth)
        of each ground-truth PFM under ``root``."""
        if not root.is_dir():
            return
        for folder in sorted(root.iterdir()):
            layouts = (
                (folder / 'Disparity', folder / 'Left', folder / 'Right'),
                (
                    folder / 'disparity' / 'left',
                    folder / 'RGB_cleanpass' / 'left',
                    folder / 'RGB_cleanpass' / 'right',
                ),
            )
            for gt_dir, left, right in layouts:
                for pfm in sorted(gt_dir.glob('*.pfm')) if gt_dir.is_dir() else ():
                    yield folder, pfm.stem, (left / f'{pfm.stem}.png', right / f'{pfm.stem}.png')

    @staticmethod
    def _scene(root: Path, folder: Path, stem: str) -> str:
        return f'{folder.name}/{stem}'

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        folder_name, _, stem = scene.partition('/')
        files = self._files(root / folder_name, stem) if stem else None
        if files is None:
            raise self.missing(root, scene, split)
        left, right, gt, occlusion = files
        nonocc = None
        if occlusion is not None:
            nonocc = read_image(occlusion) == 0
            if nonocc.ndim == 3:
                nonocc = nonocc.all(axis=2)
        return _sample(
            {'left': left, 'right': right, 'disparity': gt, 'nonocc': occlusion},
            dataset=self.name,
            scene=scene,
            left=read_image(left),
            right=read_image(right),
            disparity=_clean_disparity(read_pfm(gt)),
            nonocc=nonocc,
        )


# TartanAir's fixed rig: f = 320 px, principal point (320, 240), baseline 0.25 m.
_TARTANAIR_CALIB = Calibration(fx=320.0, fy=320.0, cx=320.0, cy=240.0, baseline=0.25)


class TartanAir(_FramesByTruth):
    """TartanAir: ``<...>/<id>_left.png``, ``<id>_right.png``, ``<id>_left_disp.npy`` (float32
    disparity), or the original ``<...>/{image_left,image_right,depth_left}/<id>_left.png``,
    ``<id>_right.png``, ``<id>_left_depth.npy`` (metric depth; d = 80 / depth). Scene ids are
    ``<relative folder>/<id>``."""

    name = 'tartanair'
    any_depth = True
    layout = (
        '<root>/<...>/<id>_left.png + <id>_right.png + <id>_left_disp.npy, or '
        '<root>/<...>/{image_left,image_right,depth_left}/<id>_left.png, <id>_right.png, '
        '<id>_left_depth.npy'
    )

    @staticmethod
    def _files(folder: Path, frame: str) -> tuple[Path, Path, Path, bool] | None:
        flat = (
            folder / f'{frame}_left.png',
            folder / f'{frame}_right.png',
            folder / f'{frame}_left_disp.npy',
        )
        if all(path.is_file() for path in flat):
            return flat[0], flat[1], flat[2], False
        nested = (
            folder / 'image_left' / f'{frame}_left.png',
            folder / 'image_right' / f'{frame}_right.png',
            folder / 'depth_left' / f'{frame}_left_depth.npy',
        )
        if all(path.is_file() for path in nested):
            return nested[0], nested[1], nested[2], True
        return None

    @staticmethod
    def _gt_files(root: Path) -> Iterator[tuple[Path, str, tuple[Path, Path]]]:
        """(scene folder, frame id, its (left, right) images in the layout of its ground
        truth) of each ground-truth file under ``root``."""
        if not root.is_dir():
            return
        for path in _rglob(root, '*_left_disp.npy'):
            frame = path.name[: -len('_left_disp.npy')]
            folder = path.parent
            yield folder, frame, (folder / f'{frame}_left.png', folder / f'{frame}_right.png')
        for path in _rglob(root, 'depth_left/*_left_depth.npy'):
            frame = path.name[: -len('_left_depth.npy')]
            folder = path.parent.parent
            yield folder, frame, (
                folder / 'image_left' / f'{frame}_left.png',
                folder / 'image_right' / f'{frame}_right.png',
            )

    @staticmethod
    def _scene(root: Path, folder: Path, frame: str) -> str:
        return f'{folder.relative_to(root).as_posix()}/{frame}'

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        folder, _, frame = scene.rpartition('/')
        files = self._files(root / folder, frame) if frame else None
        if files is None:
            raise self.missing(root, scene, split)
        left, right, gt, is_depth = files
        values = _read_npy(gt)
        if is_depth:
            with np.errstate(divide='ignore'):
                values = np.float32(_TARTANAIR_CALIB.fx * _TARTANAIR_CALIB.baseline) / values
        return _sample(
            {'left': left, 'right': right, 'disparity': gt},
            dataset=self.name,
            scene=scene,
            left=read_image(left),
            right=read_image(right),
            disparity=_clean_disparity(values),
            calib=_TARTANAIR_CALIB,
        )


class StereoFolder(StereoDataset):
    """A user's own rectified pairs with ground truth (a lidar projection, a simulator): one
    folder per scene at any depth under the root (or the root itself), scene id = the folder's
    path relative to the root (``.`` for the root), holding

    * ``left.png`` and ``right.png`` (or ``.jpg``, ``.jpeg``, ``.ppm``, ``.pgm``; 8- or 16-bit,
      grey or colour, as :func:`read_image` reads them),
    * the left image's disparity (``left[y, x] ≈ right[y, x - d]``) as exactly one of
      ``disparity.pfm`` (float; inf and NaN = unknown, 0 is a disparity: a point at infinity,
      e.g. a simulator's sky), ``disparity.npy`` (float or integer (H, W); 0, NaN and inf =
      unknown, the lidar convention) or ``disparity.png`` (16-bit, d = value / 256, 0 =
      unknown, as KITTI; an 8-bit PNG is refused: its scale is unknown). Negative values are
      unknown too (a ``-1`` marker); a map whose only known values are negative is refused
      (the other sign convention). Two disparity files in one folder are refused rather than
      one of them picked,
    * optionally ``nonocc.png`` (255 = visible in both views; one marking no pixel 255, e.g.
      a 0/1 mask, is refused) and ``calib.txt`` in Middlebury form (``cam0=[f 0 cx; 0 f cy;
      0 0 1]``, ``baseline`` in mm, ``doffs``) for metric depth.

    A folder with a left image but no right image or no disparity is not a scene (the error
    for a root without scenes names such folders)."""

    name = 'stereo_folder'
    layout = (
        '<root>/<scene, any depth, or the root itself>/ with left.png + right.png (or .jpg, '
        '.ppm, .pgm) and one of disparity.pfm (float, inf/NaN = unknown), disparity.npy '
        '(float (H, W), 0/NaN/inf = unknown) or disparity.png (16-bit, d = value / 256, '
        '0 = unknown) (+ nonocc.png, 255 = visible; calib.txt, Middlebury form)'
    )
    skipped_what = 'folders with a left image'
    any_depth = True
    image_suffixes = ('.png', '.jpg', '.jpeg', '.ppm', '.pgm')
    disparity_names = ('disparity.pfm', 'disparity.npy', 'disparity.png')

    @staticmethod
    def _existing(folder: Path, names: tuple[str, ...]) -> list[Path]:
        return [folder / name for name in names if (folder / name).is_file()]

    def _image_names(self, side: str) -> tuple[str, ...]:
        return tuple(side + suffix for suffix in self.image_suffixes)

    def _lacks(self, folder: Path) -> list[str]:
        """What keeps ``folder`` from being a scene (empty if it is one)."""
        wanted = (
            ('left image', self._image_names('left')),
            ('right image', self._image_names('right')),
            ('disparity', self.disparity_names),
        )
        return [
            f'{what} ({", ".join(names)})'
            for what, names in wanted
            if not self._existing(folder, names)
        ]

    def _candidates(self, root: Path) -> list[Path]:
        """Folders under ``root`` (and ``root``) holding a left image, sorted."""
        if not root.is_dir():
            return []
        lefts = set(self._image_names('left'))
        return sorted(
            {
                path.parent
                for path in _rglob(root, 'left.*')
                if path.name in lefts and path.is_file()
            }
        )

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        return sorted(
            folder.relative_to(root).as_posix()
            for folder in self._candidates(root)
            if not self._lacks(folder)
        )

    def skipped(self, root: Path, split: str | None) -> list[tuple[str, str]]:
        return [
            (path.relative_to(root).as_posix(), 'no ' + ' and no '.join(lacks))
            for path in self._candidates(root)
            if (lacks := self._lacks(path))
        ]

    def _one(self, folder: Path, scene: str, what: str, names: tuple[str, ...]) -> Path:
        found = self._existing(folder, names)
        if len(found) > 1:
            # Which one holds the truth (a stale conversion, another convention) is not guessed.
            raise DataError(
                f'{self.name} scene {scene!r} holds {len(found)} {what} files '
                f'({", ".join(path.name for path in found)}) in {folder}; keep one'
            )
        return found[0]

    def _disparity(self, path: Path) -> np.ndarray:
        """The ground truth of ``path`` in the package convention (NaN = unknown)."""
        if path.suffix == '.png':
            try:
                return read_disparity_png(path, 256.0, bits=16)
            except DataError as exc:
                raise DataError(
                    f'{exc}; {self.name} reads disparity.png as 16-bit d = value / 256 (0 = '
                    'unknown, as KITTI): save other maps as disparity.npy or disparity.pfm '
                    '(float, in pixels)'
                ) from None
        values = read_pfm(path) if path.suffix == '.pfm' else _read_npy(path)
        finite = values[np.isfinite(values)]
        if (finite < 0).any() and not (finite > 0).any():
            # Right-to-left disparities would be read as all unknown: no pixel scored.
            raise DataError(
                f'{path}: every known disparity is negative (min {finite.min():g}); '
                "expected the left image's disparity, d ≥ 0 with left[y, x] ≈ right[y, x - d]"
            )
        if path.suffix == '.npy':
            with np.errstate(invalid='ignore'):
                values = np.where(values > 0, values, np.float32(np.nan))
        return _clean_disparity(values)

    def _mask(self, path: Path, scene: str) -> np.ndarray:
        nonocc = _visible_mask(path)
        if nonocc.size and not nonocc.any():
            # A 0/1 mask read as 'nothing visible' would score every pixel as occluded.
            values = np.unique(read_image(path))
            raise DataError(
                f'{self.name} scene {scene!r}: {path} marks no pixel visible; expected 255 = '
                f'visible in both views; got values {values[:8].tolist()}'
            )
        return nonocc

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        folder = root / scene
        outside = Path(scene).is_absolute() or '..' in Path(scene).parts
        if outside or not folder.is_dir() or self._lacks(folder):
            raise self.missing(root, scene, split)
        left = self._one(folder, scene, 'left image', self._image_names('left'))
        right = self._one(folder, scene, 'right image', self._image_names('right'))
        gt = self._one(folder, scene, 'disparity', self.disparity_names)
        mask = folder / 'nonocc.png'
        calib = folder / 'calib.txt'
        return _sample(
            {
                'left': left,
                'right': right,
                'disparity': gt,
                'nonocc': mask if mask.is_file() else None,
            },
            dataset=self.name,
            scene=scene,
            left=read_image(left),
            right=read_image(right),
            disparity=self._disparity(gt),
            nonocc=self._mask(mask, scene) if mask.is_file() else None,
            calib=read_middlebury_calibration(calib) if calib.is_file() else None,
        )


class Motorcycle(StereoDataset):
    """The Middlebury 2014 Motorcycle pair at quarter size shipped with scikit-image
    (``skimage.data.stereo_motorcycle()``); no root needed, one scene ``motorcycle``."""

    name = 'motorcycle'
    layout = 'no files: skimage.data.stereo_motorcycle() (scikit-image)'
    needs_root = False
    # From the scikit-image docstring, for the downsampled pair; baseline 193.001 mm.
    calib = Calibration(
        fx=994.978, fy=994.978, cx=311.193, cy=254.877, baseline=0.193001, doffs=31.086
    )

    def list_scenes(self, root: Path, split: str | None) -> list[str]:
        return ['motorcycle']

    def load_scene(self, root: Path, scene: str, split: str | None) -> StereoSample:
        if scene != 'motorcycle':
            raise DataError(f'motorcycle has one scene, "motorcycle"; got {scene!r}')
        try:
            from skimage import data
        except ImportError as exc:
            raise DataError(
                'the motorcycle pair needs scikit-image; expected `import skimage` to work'
            ) from exc
        left, right, disparity = data.stereo_motorcycle()
        return StereoSample(
            dataset=self.name,
            scene=scene,
            left=np.ascontiguousarray(left, dtype=np.uint8),
            right=np.ascontiguousarray(right, dtype=np.uint8),
            disparity=_clean_disparity(disparity),
            calib=self.calib,
        )


#: name → data set loader.
DATASETS: Registry[StereoDataset] = Registry('data set')
for _dataset in (
    Kitti2012(),
    Kitti2015(),
    Middlebury2014(),
    Middlebury2001(),
    Middlebury2003(),
    Middlebury2005(),
    Middlebury2006(),
    Eth3d(),
    FlyingThings3D(),
    SceneFlowExtra(),
    TartanAir(),
    Motorcycle(),
    StereoFolder(),
):
    DATASETS.add(_dataset.name, _dataset)
del _dataset

#: Data sets to train on (the paper trains on KITTI 2012).
TRAIN_DATASETS: tuple[str, ...] = (
    'kitti2012',
    'flyingthings3d',
    'sceneflow_extra',
    'tartanair',
    'eth3d',
    'middlebury2001',
    'middlebury2005',
    'middlebury2006',
)
#: Data sets to develop and report on; never train on them.
DEVELOP_DATASETS: tuple[str, ...] = ('kitti2015', 'middlebury2003', 'middlebury2014')


def _resolve(name: str, root: PathLike | None) -> tuple[StereoDataset, Path]:
    dataset = DATASETS.get(name)
    if root is None:
        if dataset.needs_root:
            raise ConfigError(
                f'{name} needs a root folder ({dataset.layout}); got root=None'
            )
        return dataset, Path('.')
    path = Path(root).expanduser()
    if dataset.needs_root and not path.is_dir():
        raise DataError(f'{name} root {path} is not a folder; expected {dataset.layout}')
    # A folder that holds several data sets under their registered names works as root too.
    if (path / name).is_dir():
        path = path / name
    return dataset, path


def list_scenes(name: str, root: PathLike | None, split: str | None = None) -> list[str]:
    """Scene ids of a data set, sorted.

    Args:
        name: Registered data set name (see :data:`DATASETS`).
        root: Folder of the data set (e.g. the one holding ``training/`` for KITTI), or a
            folder holding it under its registered name (``<root>/kitti2015/training/…``);
            None only for ``motorcycle`` (which ignores it).
        split: Data-set specific split (``trainingQ``/``trainingH``/``trainingF`` for
            ``middlebury2014``, ``TRAIN``/``TEST`` for ``flyingthings3d``, ...); None = default.

    Raises:
        ConfigError: Unknown name or split, or a missing root.
        DataError: The root holds no pair in the expected layout.
    """
    dataset, path = _resolve(name, root)
    resolved = dataset.resolve_split(split)
    scenes = dataset.list_scenes(path, resolved)
    if not scenes:
        raise dataset.no_pairs(path, resolved)
    return scenes


def skipped_scenes(
    name: str, root: PathLike | None, split: str | None = None
) -> list[tuple[str, str]]:
    """``(scene, 'no <file> …')`` of each scene that :func:`list_scenes` leaves out because a
    file is missing (a KITTI ground truth without its right image, a Middlebury folder without
    im1.png, a stereo_folder scene without a right image), sorted; empty if none. Folders
    that are no scene to score in the layout (KITTI ``testing/``, the ``_11`` frames) are not
    listed.

    Raises:
        ConfigError: Unknown name or split, or a missing root.
    """
    dataset, path = _resolve(name, root)
    return dataset.skipped(path, dataset.resolve_split(split))


def skipped_notice(name: str, root: PathLike | None, split: str | None = None) -> str:
    """One line naming the scenes :func:`skipped_scenes` finds, for a command to print where
    it lists scenes (a partial download is then no silently smaller evaluation); '' if none."""
    skipped = skipped_scenes(name, root, split)
    if not skipped:
        return ''
    return f'{name}: {len(skipped)} scene(s) left out, a file missing: {_describe(skipped, 5)}'


def load_scene(
    name: str, root: PathLike | None, scene: str, split: str | None = None
) -> StereoSample:
    """Load one scene of a data set.

    Args:
        name: Registered data set name.
        root: As for :func:`list_scenes`.
        scene: Scene id as returned by :func:`list_scenes`.
        split: As for :func:`list_scenes`.

    Returns:
        The :class:`StereoSample` at the data set's native resolution.

    Raises:
        ConfigError: Unknown name or split, or a missing root.
        DataError: Missing or unreadable files.
    """
    dataset, path = _resolve(name, root)
    return dataset.load_scene(path, scene, dataset.resolve_split(split))


def load_dataset(
    name: str,
    root: PathLike | None,
    split: str | None = None,
    max_scenes: int | None = None,
) -> Iterator[StereoSample]:
    """Iterate over the scenes of a data set, loading one pair at a time.

    The scene list is read (and its errors raised) by this call; each pair is loaded only when
    the iterator reaches it, in :func:`list_scenes` order.

    Args:
        name: Registered data set name.
        root: As for :func:`list_scenes`.
        split: As for :func:`list_scenes`.
        max_scenes: Stop after this many scenes (None = all).

    Raises:
        ConfigError: Unknown name or split, missing root, ``max_scenes`` not an integer ≥ 0.
        DataError: No pairs, or (while iterating) unreadable files.
    """
    if max_scenes is not None and (
        isinstance(max_scenes, bool) or not isinstance(max_scenes, Integral) or max_scenes < 0
    ):
        # 2.5 failed in the slice with a TypeError, True read as 1.
        raise ConfigError(f'max_scenes must be an integer ≥ 0 or None; got {max_scenes!r}')
    scenes = list_scenes(name, root, split)
    if max_scenes is not None:
        scenes = scenes[:max_scenes]
    return (load_scene(name, root, scene, split) for scene in scenes)
