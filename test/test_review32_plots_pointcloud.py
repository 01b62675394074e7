"""Review 32 of plots.py and pointcloud.py: colour scales with one bound given, PNGs that are
RGB and written whole or not at all, ROC error rates that are no numbers, and projection
matrices in the wrong grid."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
import re
import signal

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import InputError
from cva_confidence_ros.plots import (
    CORRECT_RGB,
    WRONG_RGB,
    save_confidence_map,
    save_correctness_overlay,
    save_disparity_map,
    save_roc_curves,
)
from cva_confidence_ros.pointcloud import StereoGeometry

resource = pytest.importorskip('resource')


def _rgb(path: Path) -> np.ndarray:
    bgr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert bgr is not None and bgr.ndim == 3
    return bgr[..., 2::-1].astype(np.int64) if bgr.shape[2] == 3 else bgr


def test_one_bound_given_never_inverts_the_scale(tmp_path: Path) -> None:
    cases: list[tuple[list[float], tuple[float | None, float | None], list[int]]] = [
        # (values, (vmin, vmax), drawn). Wholly below a given vmin: black. Before: the
        # default vmax (0.3) lay below vmin, the scale was inverted and all drawn white (255).
        ([0.1, 0.2, 0.3], (0.5, None), [0, 0, 0]),
        # Wholly above a given vmax: white. Before: black (0).
        ([0.7, 0.8, 0.9], (None, 0.5), [255, 255, 255]),
        # Only infinities with vmin = 5: +inf white, -inf black. Before: the other way round.
        ([np.inf, -np.inf], (5.0, None), [255, 0]),
        # The bound given still counts when the data reach beyond it on the other side.
        ([0.0, 0.5, 1.0], (0.5, None), [0, 0, 255]),
    ]
    for values, bounds, expected in cases:
        rgb = _rgb(save_confidence_map(np.array([values]), tmp_path / 'c.png', *bounds))
        assert rgb[0, :, 0].tolist() == expected, (values, bounds)


def test_maps_are_rgb_pngs_with_green_as_green(tmp_path: Path) -> None:
    # Before: matplotlib's imsave wrote RGBA (4 channels) where the docstrings promise RGB.
    overlay = save_correctness_overlay(
        np.array([[0.9, 0.1]]), np.array([[False, False]]), tmp_path / 'o.png'
    )
    assert overlay.read_bytes()[25] == 2  # IHDR colour type 2: RGB, no alpha
    rgb = _rgb(overlay)
    assert rgb.shape == (1, 2, 3)
    assert rgb[0, 0].tolist() == list(CORRECT_RGB) and rgb[0, 1].tolist() == list(WRONG_RGB)
    tiny = _rgb(save_disparity_map(np.array([[3.0]]), tmp_path / 'd.png'))
    assert tiny.shape == (1, 1, 3)


@contextmanager
def _small_file_limit() -> Iterator[None]:
    """Files of this process may not grow beyond 4 KiB (a full disk, in effect)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    handler = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # EFBIG instead of a kill
    resource.setrlimit(resource.RLIMIT_FSIZE, (4096, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, handler)


def test_a_write_that_fails_half_way_leaves_the_old_png_whole(tmp_path: Path) -> None:
    # Before: a 4096-byte truncated PNG replaced the good one of ~270 KB (PIL removes only a
    # file it created itself).
    noise = np.random.default_rng(0).random((300, 300))
    path = save_confidence_map(noise, tmp_path / 'c.png')
    good = path.read_bytes()
    assert len(good) > 4096
    with _small_file_limit(), pytest.raises(OSError):
        save_confidence_map(noise[::-1], path)
    assert path.read_bytes() == good
    assert sorted(p.name for p in tmp_path.iterdir()) == ['c.png']  # no partial file left
    save_confidence_map(noise[::-1], path)  # the next write goes through
    assert path.read_bytes() != good and _rgb(path).shape == (300, 300, 3)


@pytest.mark.parametrize('error_rate', ['0.3', True, 'x'])
def test_roc_error_rate_that_is_no_number_is_refused(tmp_path: Path, error_rate: object) -> None:
    # Before: float(error_rate) let '0.3' and True (drawn as ε = 1) through, and 'x' raised a
    # bare ValueError that named no argument.
    with pytest.raises(InputError, match='error_rate must be in'):
        save_roc_curves({}, tmp_path / 'roc.png', error_rate=error_rate)  # type: ignore[arg-type]
    assert not (tmp_path / 'roc.png').exists()


P_LEFT = np.array([[500.0, 0.0, 320.0, 0.0], [0.0, 500.0, 240.0, 0.0], [0.0, 0.0, 1.0, 0.0]])
P_RIGHT = P_LEFT + np.array([[0.0, 0.0, 0.0, -60.0], [0.0] * 4, [0.0] * 4])


def test_a_projection_matrix_in_another_grid_is_named() -> None:
    # Before: a transposed P (4×3) was read row-major and refused as "focal lengths must be
    # > 0; got fx=500.0, fy=0.0"; a 2×6 one was taken as it came.
    for left, right in ((P_LEFT.T, P_RIGHT.T), (P_LEFT.reshape(2, 6), P_RIGHT.reshape(2, 6)),
                        (P_LEFT[None], P_RIGHT[None])):
        named = re.escape(str(left.shape))
        with pytest.raises(InputError, match=rf'P_left must be a 3×4 .*got shape {named}$'):
            StereoGeometry.from_projections(left, right)
    # A grid of 3×4 or the 12 values in a row are read as before.
    for shape in ((3, 4), (12,), (1, 12), (12, 1)):
        geometry = StereoGeometry.from_projections(P_LEFT.reshape(shape), P_RIGHT.reshape(shape))
        assert (geometry.fx, geometry.cx, geometry.cy, geometry.baseline) == (500, 320, 240, 0.12)


def test_the_baseline_is_the_difference_of_the_two_cameras_tx() -> None:
    # A rectified frame whose origin is not the left camera (P_left[0, 3] = −5): the baseline
    # is (Tx_left − Tx_right) / fx = 0.10 m; −Tx_right / fx alone read 0.15 m (depth 50 % far).
    p_left = [100.0, 0.0, 50.0, -5.0, 0.0, 100.0, 40.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    p_right = [100.0, 0.0, 50.0, -15.0, 0.0, 100.0, 40.0, 0.0, 0.0, 0.0, 1.0, 0.0]
    geometry = StereoGeometry.from_projections(p_left, p_right)
    assert geometry.baseline == pytest.approx(0.10)
    p_left[3] = 0.0  # the usual layout: the left camera at the origin
    assert StereoGeometry.from_projections(p_left, p_right).baseline == pytest.approx(0.15)
