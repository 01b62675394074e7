"""Review 33: the metric meaning of what the data sets become (calibration, depth)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.datasets import load_scene
from msg_tools.bag_from_dataset import BagSpec, sample_geometry

H, W = 6, 12
FX, CX, CY = 100.0, 5.0, 3.0


def _projection(tx: float) -> str:
    return f'{FX} 0 {CX} {tx} 0 {FX} {CY} 0 0 0 1 0'


def _kitti2012_scene(root: Path) -> None:
    """One colour KITTI 2012 pair whose calib has gray cameras 0.5 m apart (P0/P1) and colour
    cameras 0.48 m apart (P2/P3, offset from cam 0 as in the real files)."""
    base = root / 'training'
    rng = np.random.default_rng(0)
    for folder in ('colored_0', 'colored_1'):
        (base / folder).mkdir(parents=True)
        image = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        assert cv2.imwrite(str(base / folder / '000070_10.png'), image)
    (base / 'disp_occ').mkdir()
    assert cv2.imwrite(
        str(base / 'disp_occ' / '000070_10.png'), np.full((H, W), 4 * 256, np.uint16)
    )
    (base / 'calib').mkdir()
    (base / 'calib' / '000070.txt').write_text(
        f'P0: {_projection(0.0)}\nP1: {_projection(-FX * 0.5)}\n'
        f'P2: {_projection(FX * 0.06)}\nP3: {_projection(-FX * 0.42)}\n'
    )


def test_kitti2012_colour_pair_takes_the_gray_cameras_calibration(tmp_path: Path) -> None:
    # colored_0/1 of the stereo benchmark are pixel-aligned with image_0/1 (on 000070 the
    # best shift between them is 0 px where a 6 cm offset would give 4-9 px) and share
    # their ground truth: the baseline is P0/P1's (0.537 m there), not P2/P3's (0.532 m),
    # which gave every depth 0.9 % short (41.83 m instead of 42.21 m at one pixel).
    _kitti2012_scene(tmp_path)
    sample = load_scene('kitti2012', tmp_path, '000070')
    assert sample.calib is not None
    assert sample.calib.baseline == pytest.approx(0.5)
    assert float(sample.calib.depth(np.float32(4.0))) == pytest.approx(FX * 0.5 / 4.0)
    geometry, assumed = sample_geometry(sample, BagSpec())
    assert not assumed and geometry.baseline == pytest.approx(0.5)
