"""Review 37: ignore masks as a robot integrator makes them (``cva-mask``, an image editor's
export) and gives them to the node (each test a regression test of a fault found then)."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.mask import load_mask
from msg_tools.mask_tool import main as mask_main


def _bumper_and_mast() -> np.ndarray:
    """A 0/255 mask: a bumper corner and a mast ignored."""
    mask = np.full((48, 64), 255, np.uint8)
    mask[30:, :20] = 0
    mask[:, 50:] = 0
    return mask


@pytest.mark.parametrize(
    ('name', 'params'),
    [
        ('mask.jpg', [cv2.IMWRITE_JPEG_QUALITY, 95]),
        ('mask.jpg', [cv2.IMWRITE_JPEG_QUALITY, 20]),
        ('mask.png', [cv2.IMWRITE_JPEG_QUALITY, 75]),  # a JPEG named .png: by its content
        ('mask.webp', [cv2.IMWRITE_WEBP_QUALITY, 75]),
    ],
)
def test_a_lossy_mask_keeps_the_black_next_to_its_edges_ignored(
    tmp_path: Path, name: str, params: list[int]
) -> None:
    # JPEG brings black back as 1, 2, … next to the edges; read as "not 0 = judge", 50 of the
    # 1032 ignored pixels at quality 95 (116 at 75) were published: the robot's outline.
    mask = _bumper_and_mast()
    path = tmp_path / name
    ok, data = cv2.imencode('.webp' if name.endswith('.webp') else '.jpg', mask, params)
    assert ok
    path.write_bytes(data.tobytes())
    decoded = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert ((decoded != 0) & (mask == 0)).any()  # the lossy rim is there
    np.testing.assert_array_equal(load_mask(path), mask != 0)
    # A lossless mask of 0 and 1 (a bool array saved as it is) still judges its 1s.
    ones = tmp_path / 'ones.png'
    assert cv2.imwrite(str(ones), (mask != 0).astype(np.uint8))
    np.testing.assert_array_equal(load_mask(ones), mask != 0)


def test_a_jpeg_mask_of_zeros_and_ones_is_refused_with_its_threshold(tmp_path: Path) -> None:
    # In a JPEG, 1 is black: every pixel ignored is named, with the value that judges.
    path = tmp_path / 'mask.jpg'
    assert cv2.imwrite(str(path), (_bumper_and_mast() != 0).astype(np.uint8))
    with pytest.raises(ConfigError, match=r'ignores every pixel .*\(in a JPEG: 64 or more\)'):
        load_mask(path)


def test_cva_mask_refuses_a_mask_name_that_is_not_png(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # `cva-mask mask.jpg` wrote PNG bytes into mask.jpg and said "use it with mask_path:=…";
    # the node then refused it as "a truncated JPEG: no end-of-image marker".
    out = tmp_path / 'mask.jpg'
    assert mask_main([str(out), '--size', '64x48', '--rect', '0', '0', '10', '10']) == 2
    assert capsys.readouterr().err.strip() == (
        f'cva-mask: error: out {out} must be named .png: cva-mask writes a PNG mask'
    )
    assert not out.exists()
    upper = tmp_path / 'mask.PNG'
    assert mask_main([str(upper), '--size', '64x48', '--rect', '0', '0', '10', '10']) == 0
    assert int((~load_mask(upper)).sum()) == 100


def test_replay_scores_only_the_pixels_the_node_judges() -> None:
    # The ground-truth metrics took every pixel with ground truth, the masked ones too: as
    # errors of confidence 0 (the node keeps nothing there), so a mask made the matcher wrong.
    from msg_tools.scoring import score_frame

    rng = np.random.default_rng(0)
    gt = rng.uniform(5, 20, (12, 16)).astype(np.float32)
    disparity = gt + 0.5
    confidence = rng.random((12, 16)).astype(np.float32)
    region = np.ones((12, 16), bool)
    region[8:, :6] = False  # the bumper
    disparity[~region] = np.nan
    confidence[~region] = 0.0
    kept = np.isfinite(disparity)
    score = score_frame(0, 0, disparity, confidence, kept, gt, region=region)
    assert score.error_rate == 0.0 and score.n_pixels == int(region.sum())
    whole = score_frame(0, 0, disparity, confidence, kept, gt)
    assert whole.error_rate == pytest.approx((~region).mean())
    nothing = score_frame(0, 0, disparity, confidence, kept,
                          np.where(region, np.nan, gt).astype(np.float32), region=region)
    assert nothing.auc is None and 'among those judged' in nothing.note


def test_an_image_file_is_checked_as_a_jpeg_by_its_content_not_its_name(tmp_path: Path) -> None:
    # A PNG named .jpg was refused as "a truncated JPEG"; a truncated JPEG named .png passed.
    from cva_confidence_ros.datasets.io import read_image
    from cva_confidence_ros.errors import DataError

    image = np.random.default_rng(1).integers(0, 256, (24, 32), dtype=np.uint8)
    png = tmp_path / 'frame.jpg'
    png.write_bytes(cv2.imencode('.png', image)[1].tobytes())
    np.testing.assert_array_equal(read_image(png), image)
    jpeg = cv2.imencode('.jpg', image)[1].tobytes()
    cut = tmp_path / 'frame.png'
    cut.write_bytes(jpeg[: len(jpeg) * 2 // 3])
    with pytest.raises(DataError, match='truncated JPEG'):
        read_image(cut)
