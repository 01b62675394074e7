"""Review 27: camera infos that are not a rectified pair or whose binning and region of
interest the images do not follow are refused by the node's decoder, the bag tools' geometry
and the replay; NodeConfig's switches take booleans only."""

from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace

from node_test_utils import image_msg, info_msgs
import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.ros.convert import (
    camera_info_to_geometry,
    image_camera_info,
    stereo_pair_from_messages,
)
from cva_confidence_ros.ros.params import NodeConfig, build_configs
from msg_tools.convert import camera_geometry, camera_info_msgs

IMAGE = np.zeros((64, 96), np.uint8)


def _pair() -> tuple:
    return image_msg(IMAGE, 0), image_msg(IMAGE, 0)


@pytest.mark.parametrize(
    ('index', 'value', 'match'),
    [
        (6, 10.0, r'must share cy .*P_left\[1, 2\] = 32 and P_right\[1, 2\] = 10$'),
        (5, 120.0, r'must share fy .*P_left\[1, 1\] = 100 and P_right\[1, 1\] = 120$'),
    ],
)
def test_rows_that_do_not_correspond_are_refused(index: int, value: float, match: str) -> None:
    left_info, right_info = info_msgs(0)
    right_info.p[index] = value
    with pytest.raises(InputError, match=match):
        stereo_pair_from_messages(*_pair(), left_info, right_info)
    with pytest.raises(InputError, match=match):
        camera_geometry(left_info, right_info)


def test_float_noise_in_fy_and_cy_is_accepted() -> None:
    left_info, right_info = info_msgs(0)
    right_info.p[5] += 1e-4 * right_info.p[5]
    right_info.p[6] += 0.05
    geometry = stereo_pair_from_messages(*_pair(), left_info, right_info)[2]
    assert (geometry.fy, geometry.cy) == (100.0, 32.0)  # the left camera's
    assert camera_geometry(left_info, right_info)[0] == geometry


@pytest.mark.parametrize(
    'change',
    [{'binning_x': 2}, {'binning_y': 4}, {'x_offset': 8, 'y_offset': 4, 'width': 48, 'height': 32},
     {'x_offset': 8}],
)
def test_images_of_the_calibration_size_take_p_as_it_is(change: dict[str, int]) -> None:
    # P is for the full resolution (REP 104) and the images have it: binning or an ROI (the
    # valid rectified area, as some drivers fill it) does not move the geometry, in the node
    # and in the bag tools once they know the image size.
    plain = stereo_pair_from_messages(*_pair(), *info_msgs(0))[2]
    for side in ('left', 'right'):
        infos = info_msgs(0)
        info = infos[0] if side == 'left' else infos[1]
        for name, value in change.items():
            setattr(info if name.startswith('binning') else info.roi, name, value)
        assert stereo_pair_from_messages(*_pair(), *infos)[2] == plain
        # Published as it is read (review 31): the same K and P, no binning or ROI left.
        published = image_camera_info(info, 96, 64)
        assert list(published.p) == list(info.p) and list(published.k) == list(info.k)
        assert (published.binning_x, published.binning_y) == (0, 0)
        assert (published.roi.x_offset, published.roi.y_offset, published.roi.width,
                published.roi.height) == (0, 0, 0, 0)
        assert camera_geometry(*infos, image_size=(96, 64)) == (plain, 96, 64)


@pytest.mark.parametrize(
    ('change', 'described'),
    [
        ({'binning_x': 2}, r'got 96×128 \(binning 2×0 and region of interest 0×0 at \(0, 0\) of '
                          r'its 192×128\)'),
        ({'x_offset': 8, 'y_offset': 4, 'width': 48, 'height': 32},
         r'got 48×32 \(binning 0×0 and region of interest 48×32 at \(8, 4\) of its 192×128\)'),
    ],
)
def test_binning_or_roi_that_the_images_do_not_follow_is_refused(
    change: dict[str, int], described: str
) -> None:
    # 96×64 images, infos of a 192×128 calibration whose binning or ROI give another size.
    for side in ('left', 'right'):
        infos = info_msgs(0, height=128, width=192)
        for info in infos:
            info.binning_x = info.binning_y = 2
        info = infos[0] if side == 'left' else infos[1]
        info.binning_x = info.binning_y = 0
        for name, value in change.items():
            setattr(info if name.startswith('binning') else info.roi, name, value)
        with pytest.raises(InputError, match=rf'^{side} camera info must be for 96×64 images; '
                                             rf'{described}$'):
            stereo_pair_from_messages(*_pair(), *infos)
        with pytest.raises(InputError, match='must be for 96×64 images'):
            image_camera_info(info, 96, 64)


@pytest.mark.parametrize('binning', [0, 1])
def test_binning_0_or_1_and_an_empty_or_full_roi_mean_none(binning: int) -> None:
    plain = stereo_pair_from_messages(*_pair(), *info_msgs(0))[2]
    infos = info_msgs(0)
    for info in infos:
        info.binning_x = info.binning_y = binning
    infos[1].roi.width, infos[1].roi.height, infos[1].roi.do_rectify = 96, 64, True
    assert stereo_pair_from_messages(*_pair(), *infos)[2] == plain
    assert image_camera_info(infos[0], 96, 64) is infos[0]
    assert camera_geometry(*infos) == (plain, 96, 64)


def test_roi_outside_the_calibration_is_refused() -> None:
    infos = info_msgs(0, height=128, width=192)
    infos[0].roi.x_offset, infos[0].roi.width, infos[0].roi.height = 150, 96, 64
    with pytest.raises(InputError, match=r'^left camera info: roi 96×64 at \(150, 0\) must lie '
                                         r'within its calibration size 192×128'):
        camera_info_to_geometry(*infos, 96, 64)
    with pytest.raises(InputError, match=r'^left camera info: roi 96×64 at \(150, 0\)'):
        camera_geometry(*infos)


def test_bag_geometry_folds_binning_and_roi_as_the_node_does() -> None:
    # camera_geometry read the calibration size and P as they were: a binned bag's expected
    # outputs (cva-replay --live) had the full size and twice the focal length.
    infos = info_msgs(0, height=128, width=192, fx=200.0)
    for info in infos:
        info.binning_x = info.binning_y = 2
    node = camera_info_to_geometry(*infos, 96, 64)
    assert camera_geometry(*infos) == (node, 96, 64)
    assert (node.fx, node.cx, node.cy) == (100.0, 48.0, 32.0)
    infos = info_msgs(0, height=128, width=192, fx=200.0)
    for info in infos:
        info.roi.x_offset, info.roi.y_offset, info.roi.width, info.roi.height = 50, 20, 96, 64
    node = camera_info_to_geometry(*infos, 96, 64)
    assert camera_geometry(*infos) == (node, 96, 64)
    assert (node.cx, node.cy) == (46.0, 44.0)
    # Infos written by the bag tools themselves (binning 0, all-zero roi) read back as written.
    geometry = camera_geometry(*infos)[0]
    assert camera_geometry(*camera_info_msgs(geometry, 96, 64, 0, ('l', 'r')))[0] == geometry


def test_replay_skips_a_frame_of_unequal_cy() -> None:
    from msg_tools.replay import _process_pair, stereo_inputs

    left_info, right_info = info_msgs(0)
    right_info.p[6] = 10.0
    items = {'left': image_msg(IMAGE, 0), 'right': image_msg(IMAGE, 0),
             'left_info': left_info, 'right_info': right_info}
    with pytest.raises(InputError, match='must share cy'):
        stereo_inputs(items)

    skipped: list[tuple[str, Exception]] = []
    session = SimpleNamespace(
        options=None, skip=lambda what, err, stamp=None: skipped.append((what, err)),
        frame_epoch=lambda stamp: 0,
    )
    matched = SimpleNamespace(stamp_ns=5, items={key: (msg, 5) for key, msg in items.items()})
    _process_pair(session, None, matched, frame=3)  # type: ignore[arg-type]
    assert [what for what, _ in skipped] == ['frame 3 (stamp 5 ns)']
    assert 'must share cy' in str(skipped[0][1])


BOOLS = [f.name for f in fields(NodeConfig) if isinstance(f.default, bool)]


def test_every_switch_is_checked() -> None:
    assert {'approximate_sync', 'publish_points', 'points_organized', 'points_confidence',
            'publish_depth', 'publish_scan'} == set(BOOLS)


@pytest.mark.parametrize('name', BOOLS)
@pytest.mark.parametrize('value', ['false', 1, 0, None])
def test_node_config_switches_take_booleans_only(name: str, value: object) -> None:
    with pytest.raises(ConfigError, match=rf'^{name} must be True or False; got {value!r}$'):
        NodeConfig(**{name: value})
    assert getattr(NodeConfig(**{name: True}), name) is True


def test_build_configs_refuses_a_string_approximate_sync() -> None:
    from rclpy.parameter import Parameter

    from cva_confidence_ros.ros.params import PARAMETERS

    values = {spec.name: spec.default for spec in PARAMETERS}
    with pytest.raises(ConfigError, match="^approximate_sync must be True or False; got 'yes'$"):
        build_configs(values, [Parameter('approximate_sync', Parameter.Type.STRING, 'yes')])
