"""Ignore masks (``cva_confidence_ros.mask``) and the pipeline's ``mask_path``: real files,
the real matcher and network."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.mask import check_mask_size, load_mask, mask_rows, reduce_mask
from cva_confidence_ros.pipeline import PipelineConfig, StereoPipeline, output_region

#: A stereo pair (left, right) of uint8 images: the ``slanted_pair`` fixture (conftest).
Pair = tuple[np.ndarray, np.ndarray]

def _write(path: Path, image: np.ndarray) -> Path:
    assert cv2.imwrite(str(path), image)
    return path


def _bumper_mask(height: int = 96, width: int = 120) -> np.ndarray:
    """A hood over the last 16 rows and a bumper corner at the lower left (uint8, 0 = ignore)."""
    mask = np.full((height, width), 255, np.uint8)
    mask[80:] = 0
    mask[60:, :20] = 0
    return mask


def test_black_is_ignored_in_grey_colour_and_16_bit_files(tmp_path: Path) -> None:
    grey = _bumper_mask()
    np.testing.assert_array_equal(load_mask(_write(tmp_path / 'grey.png', grey)), grey > 0)
    # Colour: ignored only where every channel is 0 (a dark red pixel is judged).
    colour = np.repeat(grey[..., None], 3, axis=2)
    colour[0, 0] = (0, 0, 40)
    keep = load_mask(_write(tmp_path / 'colour.png', colour))
    assert keep.shape == (96, 120) and keep[0, 0] and not keep[90, 50]
    deep = grey.astype(np.uint16) * 257
    np.testing.assert_array_equal(load_mask(_write(tmp_path / 'deep.png', deep)), grey > 0)


@pytest.mark.parametrize(
    ('content', 'message'),
    [
        (None, 'is not a file'),
        (b'', 'is an empty file'),
        (b'\x89PNG\r\n\x1a\n broken', 'cannot be read as an image'),
        ('black', 'ignores every pixel'),
    ],
)
def test_bad_mask_files_are_named(tmp_path: Path, content: object, message: str) -> None:
    path = tmp_path / 'mask.png'
    if content == 'black':
        _write(path, np.zeros((8, 8), np.uint8))
    elif isinstance(content, bytes):
        path.write_bytes(content)
    with pytest.raises(ConfigError, match=f"mask_path '.*mask.png' {message}"):
        load_mask(path)
    # The pipeline refuses it when it is built (the node: at start or on the parameter change).
    with pytest.raises(ConfigError, match=message):
        StereoPipeline(PipelineConfig(confidence_method='pkrn', mask_path=str(path)))


def test_reduced_masks_ignore_every_block_with_an_ignored_pixel() -> None:
    keep = np.ones((9, 10), dtype=bool)
    keep[0, 0] = keep[5, 7] = False
    small = reduce_mask(keep, 2)
    assert small.shape == (4, 5)  # the odd last row is cropped, as resize_image crops
    assert np.flatnonzero(~small.ravel()).tolist() == [0, 2 * 5 + 3]
    assert reduce_mask(keep, 1) is not None and reduce_mask(keep, 1).shape == (9, 10)
    for factor in (0, -2, 1.5, True):  # was a ZeroDivisionError / a reshape error
        with pytest.raises(ConfigError, match=f'factor must be an integer ≥ 1; got {factor!r}'):
            reduce_mask(keep, factor)  # type: ignore[arg-type]
    assert mask_rows(keep) == (0, 9)
    keep[:3] = False
    keep[7:] = False
    assert mask_rows(keep) == (3, 7) and mask_rows(np.zeros((4, 4), bool)) == (0, 0)
    with pytest.raises(InputError, match='the mask .* is 10×9 px but the images are 12×9 px'):
        check_mask_size(keep, 12, 9)


@pytest.mark.parametrize('method', ['pkrn', 'cva_net_fast'])
def test_masked_pixels_publish_nothing_and_the_rest_is_the_whole_image_result(
    tmp_path: Path, method: str, slanted_pair: Pair
) -> None:
    left, right = slanted_pair
    mask = _bumper_mask()
    path = _write(tmp_path / 'mask.png', mask)
    base = {'confidence_method': method, 'speckle_size': 0, 'device': 'cpu', 'max_disparity': 64,
            'matcher': 'census_bm'}
    whole = StereoPipeline(PipelineConfig(**base)).process(left, right)
    part = StereoPipeline(PipelineConfig(**base, mask_path=str(path))).process(left, right)
    keep = mask > 0
    # The hood's rows are not processed at all: the rows stop at the last judged row (79).
    assert part.rows == (0, 80)
    for name in ('disparity', 'confidence', 'raw_confidence', 'valid'):
        np.testing.assert_array_equal(getattr(part, name)[keep], getattr(whole, name)[keep],
                                      err_msg=name)
    assert np.isnan(part.disparity[~keep]).all() and np.isnan(part.raw_confidence[~keep]).all()
    assert (part.confidence[~keep] == 0).all() and not part.valid[~keep].any()
    np.testing.assert_array_equal(part.region, keep)
    np.testing.assert_array_equal(part.mask, keep)
    assert part.kept_fraction == pytest.approx(whole.valid[keep].mean())
    # From the outside (live replay): the same region from the config and the mask file.
    np.testing.assert_array_equal(
        output_region(PipelineConfig(**base, mask_path=str(path)), (96, 120), load_mask(path)),
        keep,
    )


def test_mask_with_a_region_of_interest_downsampling_and_the_speckle_filter(
    tmp_path: Path, slanted_pair: Pair
) -> None:
    left, right = slanted_pair
    path = _write(tmp_path / 'mask.png', _bumper_mask())
    config = PipelineConfig(confidence_method='pkrn', max_disparity=32, mask_path=str(path),
                            roi_top=0.25, downsample=2)
    result = StereoPipeline(config).process(left, right)
    # At half size: the mask's judged rows are 0-39, the region's 12-47: rows 12-39.
    assert result.rows == (12, 40) and result.mask.shape == (48, 60)
    region = result.region
    assert region is not None and not region[:12].any() and not region[40:].any()
    assert not region[30:, :10].any() and region[12:30].all()
    assert not result.valid[~region].any() and result.valid[region].any()
    assert result.kept_fraction == pytest.approx(result.valid[region].mean())
    # The speckle filter's share is of the judged pixels too.
    filtered = StereoPipeline(config.replace(speckle_size=100)).process(left, right)
    assert 0 <= filtered.speckle_fraction <= 1
    assert filtered.valid.sum() <= result.valid.sum()
    assert np.count_nonzero(filtered.valid & ~region) == 0


def test_a_mask_of_another_size_or_apart_from_the_region_is_a_clear_error(
    tmp_path: Path, slanted_pair: Pair
) -> None:
    left, right = slanted_pair
    path = _write(tmp_path / 'mask.png', _bumper_mask(48, 60))
    pipeline = StereoPipeline(
        PipelineConfig(confidence_method='pkrn', max_disparity=32, mask_path=str(path))
    )
    with pytest.raises(InputError, match='mask .* is 60×48 px but the images are 120×96 px'):
        pipeline.process(left, right)
    with pytest.raises(InputError, match='60×48 px but the images are 120×96'):
        pipeline.check_input_size(120, 96)
    pipeline.check_input_size(60, 48)
    hood = _write(tmp_path / 'hood.png', _bumper_mask())
    apart = PipelineConfig(confidence_method='pkrn', mask_path=str(hood), roi_top=0.9)
    with pytest.raises(InputError, match='region of interest .* mask .* no pixel in common'):
        StereoPipeline(apart).process(left, right)
    with pytest.raises(ConfigError, match='mask_path must be a string'):
        PipelineConfig(mask_path=3)  # type: ignore[arg-type]
