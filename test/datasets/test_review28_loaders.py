"""Review of the data set loaders and resizing: regressions on tiny files in ``tmp_path``."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
import re

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import (
    StereoSample,
    fit_disparity_range,
    load_scene,
    write_pfm,
)
from cva_confidence_ros.errors import ConfigError, DataError

H, W = 6, 12


def write_image(path: Path, image: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), image)


def write_gt_pfm(path: Path, shape: tuple[int, int]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_pfm(path, np.full(shape, 2.5, np.float32))


def pair(folder: Path, left: str, right: str) -> None:
    image = np.random.default_rng(0).integers(0, 256, (H, W, 3), np.uint8)
    write_image(folder / left, image)
    write_image(folder / right, image)


def kitti2015_gt(root: Path) -> tuple[str, Path]:
    base = root / 'training'
    pair(base, 'image_2/000000_10.png', 'image_3/000000_10.png')
    gt = base / 'disp_occ_0' / '000000_10.png'
    write_image(gt, np.full((H, W - 2), 640, np.uint16))
    return '000000', gt


def kitti2012_noc(root: Path) -> tuple[str, Path]:
    base = root / 'training'
    pair(base, 'colored_0/000001_10.png', 'colored_1/000001_10.png')
    write_image(base / 'disp_occ' / '000001_10.png', np.full((H, W), 640, np.uint16))
    noc = base / 'disp_noc' / '000001_10.png'
    write_image(noc, np.full((H - 1, W), 640, np.uint16))
    return '000001', noc


def middlebury2014_mask(root: Path) -> tuple[str, Path]:
    folder = root / 'trainingQ' / 'Piano'
    pair(folder, 'im0.png', 'im1.png')
    write_gt_pfm(folder / 'disp0GT.pfm', (H, W))
    mask = folder / 'mask0nocc.png'
    write_image(mask, np.full((H + 1, W), 255, np.uint8))
    return 'Piano', mask


def middlebury2003_gt(root: Path) -> tuple[str, Path]:
    folder = root / 'teddy'
    pair(folder, 'teddy_image_02.png', 'teddy_image_06.png')
    gt = folder / 'teddy_disp_02.png'
    write_image(gt, np.full((H, W + 3), 10, np.uint8))
    return 'teddy', gt


def flyingthings3d_gt(root: Path) -> tuple[str, Path]:
    pair(root / 'frames_cleanpass' / 'TRAIN' / 'A' / '0000', 'left/0006.png', 'right/0006.png')
    gt = root / 'disparity' / 'TRAIN' / 'A' / '0000' / 'left' / '0006.pfm'
    write_gt_pfm(gt, (H // 2, W // 2))
    return 'TRAIN/A/0000/0006', gt


def sceneflow_extra_occlusion(root: Path) -> tuple[str, Path]:
    folder = root / 'sttr_A-0001-0002'
    pair(folder / 'RGB_cleanpass', 'left/x.png', 'right/x.png')
    write_gt_pfm(folder / 'disparity' / 'left' / 'x.pfm', (H, W))
    occlusion = folder / 'occlusion' / 'left' / 'x.png'
    write_image(occlusion, np.zeros((H, W - 1), np.uint8))
    return 'sttr_A-0001-0002/x', occlusion


def tartanair_gt(root: Path) -> tuple[str, Path]:
    folder = root / 'OldTown' / 'EasyP000'
    pair(folder, '000001_left.png', '000001_right.png')
    gt = folder / '000001_left_disp.npy'
    np.save(gt, np.full((H, W + 1), 2.5, np.float32))
    return 'OldTown/EasyP000/000001', gt


@pytest.mark.parametrize(
    ('name', 'build'),
    [
        ('kitti2015', kitti2015_gt),
        ('kitti2012', kitti2012_noc),
        ('middlebury2014', middlebury2014_mask),
        ('middlebury2003', middlebury2003_gt),
        ('flyingthings3d', flyingthings3d_gt),
        ('sceneflow_extra', sceneflow_extra_occlusion),
        ('tartanair', tartanair_gt),
    ],
)
def test_ground_truth_or_mask_of_another_size_names_its_file(
    tmp_path: Path, name: str, build: Callable[[Path], tuple[str, Path]]
) -> None:
    # The shape error used to name only '<data set>/<scene>', not the file of the wrong size.
    scene, wrong = build(tmp_path)
    with pytest.raises(DataError, match='must be') as raised:
        load_scene(name, tmp_path, scene)
    assert re.search(re.escape(str(wrong)), str(raised.value)), str(raised.value)


@pytest.mark.parametrize('max_disparity', [float('nan'), float('inf'), None, '64'])
def test_fit_disparity_range_refuses_a_depth_that_is_no_number(max_disparity: object) -> None:
    # NaN, inf and None used to escape as ValueError, OverflowError and TypeError.
    image = np.zeros((4, 8), np.uint8)
    sample = StereoSample('t', 's', image, image, np.full((4, 8), 3.0, np.float32))
    with pytest.raises(ConfigError, match='max_disparity must be an integer'):
        fit_disparity_range(sample, max_disparity)  # type: ignore[arg-type]


def test_fit_disparity_range_still_takes_a_whole_float() -> None:
    image = np.zeros((4, 8), np.uint8)
    disparity = np.full((4, 8), 3.0, np.float32)
    sample = StereoSample('t', 's', image, image, disparity)
    assert fit_disparity_range(sample, 3.0)[1] == 2  # type: ignore[arg-type]
    assert fit_disparity_range(sample, np.int64(4))[1] == 1  # type: ignore[arg-type]
