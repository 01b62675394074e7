"""Review 31: the pipeline's region-of-interest rows under float rounding, a mask that judges
nothing inside the region, numpy integer options, the threshold's type and the name of the
mask option in the messages."""

from __future__ import annotations

from pathlib import Path
import re

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline, output_region


def _pair(height: int, width: int, shift: int = 3) -> tuple[np.ndarray, np.ndarray]:
    texture = np.random.default_rng(31).integers(0, 256, (height, width + shift), np.uint8)
    return (np.ascontiguousarray(texture[:, shift:]),
            np.ascontiguousarray(texture[:, :width]))


def _config(**changes: object) -> PipelineConfig:
    return PipelineConfig(confidence_method='pkrn', max_disparity=8, device='cpu').replace(
        **changes
    )


def _write(path: Path, mask: np.ndarray) -> str:
    assert cv2.imwrite(str(path), mask)
    return str(path)


def test_roi_rows_are_not_moved_by_float_rounding() -> None:
    # 0.28 × 25 = 7.000000000000001 in floats: ceil made it 8 rows, not 7; 0.58 × 50 =
    # 28.999999999999996: floor began the region at row 28, not 29.
    assert _config(roi_bottom=0.28).roi_rows(25) == (0, 7)
    assert _config(roi_top=0.58).roi_rows(50) == (29, 50)
    assert _config(roi_top=0.7).roi_rows(90) == (63, 90)
    # Exact products are as before.
    assert _config(roi_top=0.25, roi_bottom=0.75).roi_rows(64) == (16, 48)
    assert _config(roi_top=0.3, roi_bottom=0.31).roi_rows(10) == (3, 4)
    left, right = _pair(50, 40)
    result = StereoPipeline(_config(roi_top=0.58, speckle_size=0)).process(left, right)
    assert result.rows == (29, 50)
    assert np.isnan(result.disparity[:29]).all() and np.isfinite(result.disparity[29]).any()


def test_a_region_in_a_black_band_of_the_mask_is_refused(tmp_path: Path) -> None:
    # The mask judges rows 0-9 and 30-39, the region of interest is rows 12-28: nothing to
    # judge, yet every frame was processed (kept share 0, nothing published) without a word.
    mask = np.full((40, 48), 255, np.uint8)
    mask[10:30] = 0
    config = _config(roi_top=0.3, roi_bottom=0.7, mask_path=_write(tmp_path / 'm.png', mask))
    pipeline = StereoPipeline(config)
    left, right = _pair(40, 48)
    message = (r'the region of interest \(rows 12 to 28\) and the mask \(judged pixels in rows '
               r'0 to 40 at the processed resolution\) have no pixel in common')
    with pytest.raises(InputError, match=message):
        pipeline.process(left, right)
    with pytest.raises(InputError, match=message):
        pipeline.check_input_size(48, 40)
    with pytest.raises(InputError, match=message):
        output_region(config, (40, 48), mask > 0)


def test_rows_black_at_the_edge_of_the_region_are_not_processed(tmp_path: Path) -> None:
    # Region rows 12-39, mask black in rows 10-29: rows 12-29 were processed and judged as
    # nothing; now the region starts at the mask's first judged row inside it.
    mask = np.full((40, 48), 255, np.uint8)
    mask[10:30] = 0
    config = _config(roi_top=0.3, mask_path=_write(tmp_path / 'm.png', mask), speckle_size=0)
    left, right = _pair(40, 48)
    result = StereoPipeline(config).process(left, right)
    assert result.rows == (30, 40)
    region = output_region(config, result.disparity.shape, mask > 0)
    assert region is not None and result.region is not None
    np.testing.assert_array_equal(region, result.region)
    assert region[30:].all() and not region[:30].any()
    whole = StereoPipeline(_config(speckle_size=0)).process(left, right)
    np.testing.assert_array_equal(result.disparity[30:], whole.disparity[30:])


def test_a_mask_that_judges_nothing_at_the_processed_size_says_so(tmp_path: Path) -> None:
    # A checkerboard has no whole 2×2 block judged: the message spoke of "judged pixels in
    # rows 0 to 0".
    mask = np.where((np.indices((40, 48)).sum(axis=0) % 2) == 0, 255, 0).astype(np.uint8)
    pipeline = StereoPipeline(_config(downsample=2,
                                      mask_path=_write(tmp_path / 'm.png', mask)))
    with pytest.raises(InputError, match=r'the mask \(no judged pixel at the processed '
                                         r'resolution, where a pixel is judged only when its '
                                         r'whole downsample block is\) have no pixel in common'):
        pipeline.check_input_size(48, 40)


def test_numpy_integer_options_are_kept_as_python_ints() -> None:
    # np.uint8(250) + 16 wrapped to 10: the warm-up failed with "max_disparity must be
    # smaller than the image width 10; got 250".
    config = _config(max_disparity=np.uint8(250), downsample=np.int64(2),
                     speckle_size=np.uint16(20), lr_check=np.bool_(False))
    assert [type(getattr(config, name)) for name in
            ('max_disparity', 'downsample', 'speckle_size', 'cva_stride', 'lr_check')] == \
        [int, int, int, int, bool]
    assert config.max_disparity == 250
    StereoPipeline(config).warm_up()
    left, right = _pair(24, 40)
    result = StereoPipeline(_config(max_disparity=np.int8(8), downsample=np.int64(2))).process(
        left, right
    )
    assert type(result.scale) is float and result.scale == 0.5


class _Constant:
    """A confidence method that says 0.7 (stored as float32) everywhere."""

    def __call__(self, inputs: object) -> np.ndarray:
        return np.full(inputs.shape, 0.7, dtype=np.float32)  # type: ignore[attr-defined]

    def to_unit_interval(self, values: np.ndarray) -> np.ndarray:
        return values


def test_the_threshold_compares_in_the_confidences_float32() -> None:
    # A numpy float64 threshold 0.7 compared in float64 and dropped every pixel whose stored
    # confidence is float32(0.7); a Python float 0.7 kept them.
    left, right = _pair(24, 40)
    for threshold in (0.7, np.float64(0.7), np.float32(0.7)):
        pipeline = StereoPipeline(_config(confidence_threshold=threshold, speckle_size=0))
        pipeline._method = _Constant()  # type: ignore[assignment]
        result = pipeline.process(left, right)
        np.testing.assert_array_equal(result.valid, np.isfinite(result.disparity))
        assert result.valid.any(), threshold


def test_mask_messages_name_the_callers_option_and_the_file(tmp_path: Path) -> None:
    mask = np.full((32, 48), 255, np.uint8)
    path = _write(tmp_path / 'half.png', mask)
    quoted = re.escape(repr(path))
    left, right = _pair(64, 96)
    # The bag tools call it --mask; the messages said mask_path.
    pipeline = StereoPipeline(_config(mask_path=path), mask_option='--mask')
    with pytest.raises(InputError, match=rf'the mask \(--mask {quoted}\) is 48×32 px but the '
                                         r'images are 96×64 px'):
        pipeline.process(left, right)
    with pytest.raises(ConfigError, match=r"--mask '.*nowhere.png' is not a file"):
        StereoPipeline(_config(mask_path=str(tmp_path / 'nowhere.png')), mask_option='--mask')
    # The node's parameter by default, with the file.
    with pytest.raises(InputError, match=rf'the mask \(mask_path {quoted}\) is 48×32 px'):
        StereoPipeline(_config(mask_path=path)).check_input_size(96, 64)
    with pytest.raises(InputError, match=rf'the mask \(--mask {quoted}\) is 48×32 px but the '
                                         r'outputs are 96×64 px'):
        output_region(_config(mask_path=path), (64, 96), mask > 0, option='--mask')
