"""Review 32 of ``cva-bag-from-dataset`` and ``cva-mask``: stamps as the start time was
written, unknown ground truth as NaN, frame ids tf2 takes, draw_mask's polygons checked, and
mask files the node can read whoever runs it."""

from __future__ import annotations

from collections.abc import Iterator
import os
from pathlib import Path
import re
import stat

from msg_test_utils import read_bag, synthetic_samples
import numpy as np
import pytest

from cva_confidence_ros.datasets import StereoSample
from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.mask import load_mask
from msg_tools.bag_from_dataset import BagSpec, main, write_dataset_bag
from msg_tools.mask_tool import draw_mask
from msg_tools.mask_tool import main as mask_main


def test_the_start_time_is_stamped_as_written() -> None:
    # 1700000000.999 s was stamped 1700000000999000064 ns: float arithmetic, 64 ns off; three
    # in four start times with milliseconds came out off so.
    assert BagSpec(start_time_s=1700000000.999).stamp_ns(0) == 1700000000_999000000
    for ms in range(0, 1000, 7):
        spec = BagSpec(start_time_s=1700000000 + ms / 1000, rate_hz=4.0)
        assert spec.stamp_ns(0) == 1700000000_000000000 + ms * 1_000_000
        assert spec.stamp_ns(3) == 1700000000_750000000 + ms * 1_000_000
    assert BagSpec(start_time_s=12.345678912, rate_hz=3.0).stamp_ns(1) == 12_679012245


def test_the_start_time_reaches_the_bag_as_written(tmp_path: Path) -> None:
    out = tmp_path / 'bag'
    write_dataset_bag(synthetic_samples(1), out, BagSpec(start_time_s=1700000000.999),
                      log=lambda _: None)
    for topic, rows in read_bag(out).items():
        [(logged, message)] = rows
        assert logged == 1700000000_999000000, topic
        assert (message.header.stamp.sec, message.header.stamp.nanosec) == (
            1700000000, 999000000
        ), topic


def test_unknown_ground_truth_is_nan_in_the_bag(tmp_path: Path) -> None:
    # +inf is how Middlebury's PFMs (and read_pfm) mark unknown; it went into the bag as +inf,
    # a valid disparity (depth 0 m) to any reader but this package's.
    sample = synthetic_samples(1)[0]
    gt = sample.disparity.copy()
    gt[0, :5] = np.inf
    with_inf = StereoSample(sample.dataset, sample.scene, sample.left, sample.right, gt,
                            calib=sample.calib)
    out = tmp_path / 'bag'
    write_dataset_bag([with_inf], out, log=lambda _: None)
    [(_, message)] = read_bag(out)['/ground_truth/disparity']
    image = message.image
    values = np.frombuffer(bytes(image.data), '<f4').reshape(image.height, image.width)
    assert image.encoding == '32FC1'
    assert np.isnan(values[0, :5]).all()
    np.testing.assert_array_equal(np.isfinite(values), np.isfinite(gt))
    assert np.isfinite(message.max_disparity)


@pytest.mark.parametrize('option', ['--left-frame', '--right-frame'])
def test_a_frame_id_tf2_refuses_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str
) -> None:
    # tf2: 'frame_ids cannot start with a /'; no cloud of the node could be placed.
    with pytest.raises(ConfigError, match="must not start with '/'"):
        BagSpec(left_frame='/left_camera')
    out = tmp_path / 'bag'
    assert main(['--dataset', 'motorcycle', '--out', str(out), option, '/camera']) == 2
    err = capsys.readouterr().err
    assert "frame id must not start with '/'" in err and "'/camera'" in err
    assert len(err.strip().splitlines()) == 1
    assert not out.exists()


@pytest.fixture
def umask_022() -> Iterator[None]:
    old = os.umask(0o022)
    yield
    os.umask(old)


@pytest.mark.usefixtures('umask_022')
def test_the_mask_and_preview_are_readable_by_the_node(tmp_path: Path) -> None:
    # They were written through mkstemp, 0600: a node running as another user (a service, a
    # container) could not open mask_path.
    import cv2

    frame = tmp_path / 'frame.png'
    cv2.imwrite(str(frame), np.full((20, 24, 3), 90, np.uint8))
    out = tmp_path / 'mask.png'
    assert mask_main([str(out), '--image', str(frame), '--below', '15']) == 0
    for path in (out, tmp_path / 'mask_preview.png'):
        assert stat.S_IMODE(path.stat().st_mode) == 0o644, path
    # A replaced mask keeps the permissions given to it.
    out.chmod(0o640)
    assert mask_main([str(out), '--start', str(out), '--rect', '0', '0', '4', '4',
                      '--overwrite']) == 0
    assert stat.S_IMODE(out.stat().st_mode) == 0o640
    keep = load_mask(out)
    assert keep.shape == (20, 24) and not keep[15:].any() and not keep[:4, :4].any()


def test_draw_mask_takes_corners_as_lists_and_checks_them() -> None:
    triangle = draw_mask(10, 10, polygons=[np.array([(0, 0), (5, 0), (0, 5)], np.int32)])
    # A list of (x, y) and int64 corners draw the same (a list failed inside OpenCV).
    for corners in ([(0, 0), (5, 0), (0, 5)], np.array([(0, 0), (5, 0), (0, 5)])):
        np.testing.assert_array_equal(draw_mask(10, 10, polygons=[corners]), triangle)
    bad = {
        # a line and a point were drawn as such (the docstring asks for N >= 3)
        'needs 3 corners or more; got 2': np.array([(0, 0), (5, 5)], np.int32),
        'needs 3 corners or more; got 1': np.array([(1, 1)], np.int32),
        # 2**32 + 5 wrapped around to x = 5: the same triangle, silently
        'within ±2147483647 px': np.array([(0, 0), (2**32 + 5, 0), (0, 5)]),
        # OpenCV's assertion on CV_32S before
        'whole pixels': np.array([(0, 0), (5.5, 0), (0, 5)]),
        '(N, 2)': np.array([0, 0, 5, 0, 0, 5], np.int32),
    }
    for message, corners in bad.items():
        with pytest.raises(ConfigError, match=re.escape(message)):
            draw_mask(10, 10, polygons=[corners])
    with pytest.raises(ConfigError, match=re.escape('(N, 2) corners (x, y); got shape (3,)')):
        draw_mask(10, 10, polygons=[[(0, 0), (5,), (0, 5)]])  # numpy's ValueError before
