"""Review 30 of calibration.py and plots.py: colour scales of constant, inverted and zero maps,
NaN thresholds and masks, integer and complex inputs, PNG paths that cannot be written, ROC
curves that are no curves, and reliability tables whose means lie outside their bins."""

from __future__ import annotations

import json
from pathlib import Path

from matplotlib import colormaps
from matplotlib.image import imread
import numpy as np
import pytest

from cva_confidence_ros.calibration import ReliabilityTable, reliability
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.plots import (
    CORRECT_RGB,
    WRONG_RGB,
    confidence_overlay,
    correctness_classes,
    optimal_roc_curve,
    save_confidence_map,
    save_correctness_overlay,
    save_disparity_map,
    save_reliability_diagram,
    save_roc_curves,
)


def _rgb(path: Path) -> np.ndarray:
    return np.round(imread(path)[..., :3] * 255.0).astype(np.int64)


def test_a_constant_map_still_saturates_its_infinities(tmp_path: Path) -> None:
    # Before: the zero span drew every pixel mid-grey, +inf and -inf included.
    confidence = np.array([[2.0, 2.0, np.inf, -np.inf]])
    rgb = _rgb(save_confidence_map(confidence, tmp_path / 'c.png'))
    assert rgb[0, 0].tolist() == [128, 128, 128]
    assert rgb[0, 2].tolist() == [255, 255, 255]
    assert rgb[0, 3].tolist() == [0, 0, 0]


def test_finite_extremes_do_not_overflow_the_span(tmp_path: Path) -> None:
    # Before: vmax − vmin overflowed to inf, the largest value came out NaN and was drawn black.
    big = np.finfo(np.float64).max
    rgb = _rgb(save_confidence_map(np.array([[-big, 0.0, big]]), tmp_path / 'c.png'))
    assert rgb[0, 0].tolist() == [0, 0, 0]
    assert abs(int(rgb[0, 1, 0]) - 128) <= 1
    assert rgb[0, 2].tolist() == [255, 255, 255]


def test_vmin_above_vmax_inverts_the_scale(tmp_path: Path) -> None:
    # "vmin: value drawn black, vmax: value drawn white"; before: all mid-grey.
    rgb = _rgb(save_confidence_map(np.array([[0.0, 1.0]]), tmp_path / 'c.png', 1.0, 0.0))
    assert rgb[0, 0].tolist() == [255, 255, 255]
    assert rgb[0, 1].tolist() == [0, 0, 0]


@pytest.mark.parametrize(('vmin', 'vmax'), [(np.nan, 1.0), (0.0, np.nan), (0.0, np.inf)])
def test_a_bound_that_is_no_finite_number_is_refused(tmp_path: Path, vmin, vmax) -> None:
    # Before: NaN made the whole map mid-grey without a word.
    with pytest.raises(InputError, match=r'vm(in|ax) must be a finite number'):
        save_confidence_map(np.array([[0.0, 1.0]]), tmp_path / 'c.png', vmin, vmax)


def test_a_disparity_map_of_zeros_is_drawn_dark(tmp_path: Path) -> None:
    # Before: the range [0, 0] drew zero disparity in the colormap's middle (a mid-range d).
    darkest = (np.array(colormaps['magma'](0.0)[:3]) * 255.0 + 0.5).astype(np.int64)
    rgb = _rgb(save_disparity_map(np.zeros((1, 2), np.float32), tmp_path / 'd.png'))
    assert rgb[0, 0].tolist() == darkest.tolist()
    assert rgb[0, 1].tolist() == darkest.tolist()


@pytest.mark.parametrize('max_disparity', [0, -5.0, np.nan, np.inf])
def test_a_max_disparity_that_is_no_positive_number_is_refused(tmp_path, max_disparity) -> None:
    with pytest.raises(InputError, match='max_disparity must be a finite number > 0'):
        save_disparity_map(np.array([[0.0, 5.0]]), tmp_path / 'd.png', max_disparity)


def test_complex_maps_and_images_are_refused(tmp_path: Path) -> None:
    # Before: the imaginary part was dropped with only a ComplexWarning.
    with pytest.raises(InputError, match='confidence must be real numbers or bool; got dtype '
                                         'complex128'):
        save_confidence_map(np.array([[1 + 1j, 0j]]), tmp_path / 'c.png')
    with pytest.raises(InputError, match='image must be real numbers; got dtype <U'):
        save_correctness_overlay(np.zeros((1, 2)), np.zeros((1, 2), bool), tmp_path / 'o.png',
                                 image=np.array([['a', 'b']]))


@pytest.mark.parametrize('tau', [float('nan'), '0.5', None])
def test_a_tau_that_is_no_number_is_refused(tmp_path: Path, tau) -> None:
    # Before: NaN compared False both ways and painted every pixel red.
    confidence = np.array([[0.9, 0.1]])
    error = np.array([[False, True]])
    with pytest.raises(InputError, match='tau must be a real number'):
        save_correctness_overlay(confidence, error, tmp_path / 'o.png', tau=tau)
    rgb = _rgb(save_correctness_overlay(confidence, error, tmp_path / 'o.png', tau=0.5))
    assert rgb[0].tolist() == [list(CORRECT_RGB), list(CORRECT_RGB)]


def test_nan_in_a_float_mask_is_refused(tmp_path: Path) -> None:
    # Before: NaN cast to True and the pixel was drawn as evaluated.
    confidence = np.array([[0.9, 0.9]])
    error = np.array([[True, True]])
    with pytest.raises(InputError, match='mask must be a bool array; got NaN'):
        save_correctness_overlay(confidence, error, tmp_path / 'o.png',
                                 mask=np.array([[np.nan, 1.0]]))
    rgb = _rgb(save_correctness_overlay(confidence, error, tmp_path / 'o.png',
                                        mask=np.array([[0.0, 1.0]])))
    assert rgb[0].tolist() == [[0, 0, 0], list(WRONG_RGB)]


def test_correctness_classes_refuses_nan_errors() -> None:
    # Before: NaN cast to True counted as a wrong disparity.
    with pytest.raises(InputError, match='error must be a bool array.*1 NaN'):
        correctness_classes(np.array([0.2, 0.9]), np.array([np.nan, 0.0]))
    assert correctness_classes(np.array([0.2, 0.9]), np.array([1.0, 0.0])).tolist() == [
        True, True]


def test_confidence_overlay_refuses_an_integer_confidence() -> None:
    # Before: a 0–255 map was clipped to [0, 1], so 128 showed as fully confident green.
    image = np.full((1, 3), 100, np.uint8)
    kept = np.ones((1, 3), bool)
    with pytest.raises(InputError, match='confidence must be a float array.*uint8'):
        confidence_overlay(image, np.array([[0, 128, 255]], np.uint8), kept)
    half = confidence_overlay(image, np.array([[0, 128 / 255, 1]], np.float16), kept)
    assert half[0, 1, 0] > 40 and half[0, 1, 1] > 40  # yellow-ish, not green


def _write_any(kind: str, path: Path) -> Path:
    if kind == 'map':
        return save_confidence_map(np.zeros((2, 2)), path)
    if kind == 'roc':
        return save_roc_curves({'a': (np.array([0.5, 1.0]), np.array([0.0, 0.1]))}, path)
    table = reliability(np.array([0.2, 0.9]), np.array([False, True]))
    return save_reliability_diagram({'x': table}, path)


@pytest.mark.parametrize('kind', ['map', 'roc', 'reliability'])
def test_png_writers_name_a_path_they_cannot_write(tmp_path: Path, kind: str) -> None:
    # Before: FileExistsError "File exists: '.../file'" (naming the file in the way, not the
    # PNG) or "Not a directory: '.../file/deeper'". Still OSErrors: callers handle those.
    (tmp_path / 'file').write_text('')
    for target in (tmp_path / 'file' / 'x.png', tmp_path / 'file' / 'deeper' / 'x.png'):
        with pytest.raises(NotADirectoryError, match=r'cannot write PNG .*x\.png: .*file is a '
                                                     'file, not a folder'):
            _write_any(kind, target)
    with pytest.raises(IsADirectoryError, match='cannot write PNG .*: it is a folder'):
        _write_any(kind, tmp_path)
    written = _write_any(kind, tmp_path / 'new' / 'deeper' / 'x.png')
    assert written.is_file() and written.read_bytes()[:4] == b'\x89PNG'


def test_optimal_roc_curve_refuses_what_is_no_number() -> None:
    # Before: TypeError from a comparison or from numpy's linspace.
    with pytest.raises(InputError, match='samples must be an integer ≥ 2; got 2.5'):
        optimal_roc_curve(0.1, 2.5)
    with pytest.raises(InputError, match=r"error_rate must be in \[0, 1\]; got '0.1'"):
        optimal_roc_curve('0.1')
    assert optimal_roc_curve(np.float32(0.5), 4)[0].tolist() == [0.25, 0.5, 0.75, 1.0]


@pytest.mark.parametrize(
    ('density', 'rate', 'message'),
    [
        ([0.5, np.nan], [0.1, 0.2], '1 NaN density'),
        ([0.5, 1.0], [0.1, np.nan], '1 NaN error rate'),
        ([0.5, 1.5], [0.1, 0.2], r'density in \[0.5, 1.5\]'),
        ([0.5, 1.0], [-0.1, 0.2], r'error rate in \[-0.1, 0.2\]'),
        ([1.0, 0.5], [0.1, 0.2], 'density 1 before 0.5'),
    ],
)
def test_roc_curves_that_are_no_curves_are_refused(tmp_path, density, rate, message) -> None:
    # Before: matplotlib drew a gap, a zigzag or a point off the axes without a word.
    with pytest.raises(InputError, match=rf"curve 'a' .*{message}"):
        save_roc_curves({'a': (np.array(density), np.array(rate))}, tmp_path / 'r.png')


def test_from_dict_refuses_a_mean_outside_its_bin() -> None:
    table = reliability(np.array([0.15, 0.95, 0.9]), np.array([False, True, True]), bins=2)
    data = json.loads(json.dumps(table.as_dict()))
    assert ReliabilityTable.from_dict(data).ece == pytest.approx(table.ece)
    data['bins']['mean_confidence'] = [0.9, 0.925]  # bin 0 is [0, 0.5)
    with pytest.raises(InputError, match=r'mean_confidence\[0\] must lie in its bin \[0, 0.5\]; '
                                         'got 0.9'):
        ReliabilityTable.from_dict(data)
