"""Review 29 leftovers: one REP 104 reading of camera infos for the node and the bag tools, and
the node's hand-over that keeps both sets of a short jump back."""

from __future__ import annotations

from node_test_utils import info_msgs
import pytest

from cva_confidence_ros import camera_info
from cva_confidence_ros.errors import InputError
from cva_confidence_ros.ros.confidence_node import _Mailbox
from cva_confidence_ros.ros.convert import camera_info_to_geometry
from cva_confidence_ros.sync import MatchedSet
from msg_tools.convert import camera_geometry


def test_the_bag_tools_check_a_known_image_size_as_the_node_does() -> None:
    # Live replay passes the images' size: an info for other images was read as if it were
    # theirs (the node refuses that frame, so its outputs were expected at the wrong size).
    infos = info_msgs(0)  # 96×64
    with pytest.raises(InputError, match=r'^left camera info must be for 80×64 images; got 96×64'):
        camera_geometry(*infos, image_size=(80, 64))
    with pytest.raises(InputError, match=r'^left camera info must be for 80×64 images; got 96×64'):
        camera_info_to_geometry(*infos, 80, 64)
    assert camera_geometry(*infos, image_size=(96, 64))[0] == camera_info_to_geometry(
        *infos, 96, 64
    )


def test_one_reading_of_binning_and_roi_serves_both() -> None:
    left, right = info_msgs(0)
    for info in (left, right):
        info.binning_x = info.binning_y = 2
        info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 8, 4, 80, 56
    size, projection = camera_info.image_projection(left, 'left camera info')
    assert size == (40, 28)
    assert projection[0, 2] == pytest.approx((left.p[2] - 8) / 2)
    assert projection[1, 2] == pytest.approx((left.p[6] - 4) / 2)
    node = camera_info_to_geometry(left, right, 40, 28)
    assert camera_geometry(left, right) == (node, 40, 28)


def _set(stamp: int) -> MatchedSet:
    return MatchedSet(stamp_ns=stamp, items={}, stamps_ns={})


def test_the_mailbox_keeps_both_sets_a_short_jump_back_emits() -> None:
    # The synchroniser emits the first frame of a loop and the second at once; a one-slot
    # mailbox dropped the first (counted as dropped: each pass of a looped bag lost a frame).
    mailbox = _Mailbox()
    assert mailbox.put([_set(1), _set(2)]) == 0
    assert mailbox.take().stamp_ns == 1
    assert mailbox.take().stamp_ns == 2
    # A newer call's sets still replace those never taken (the newest wins under load).
    mailbox.put([_set(3), _set(4)])
    assert mailbox.put([_set(5)]) == 2
    assert mailbox.take().stamp_ns == 5
    mailbox.put([_set(6), _set(7)])
    assert mailbox.clear() == 2
    mailbox.close()
    assert mailbox.take() is None
