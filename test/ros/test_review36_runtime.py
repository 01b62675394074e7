"""Review 36 of the node as it runs on a robot: parameters changed at run time, the managed node
driven by a lifecycle manager, days of frames (regression tests of the faults found)."""

from __future__ import annotations

import time

from node_test_utils import (
    SMALL_MLM,
    Spinner,
    StereoClient,
    feed_frame,
    first_stamp,
    held_pipeline,
    localhost_context,
    set_parameters_by_service,
    spare_domain_id,
    textured_pair,
    wait_until,
)
import pytest
from rclpy.lifecycle import TransitionCallbackReturn
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode, ManagedConfidenceNode

pytestmark = pytest.mark.timeout(120)


def test_two_bad_start_up_values_of_the_managed_node_can_be_fixed_one_at_a_time() -> None:
    # Start-up values are checked at configure; each `param set` was checked with all the other
    # values, so with two faults each fix was refused for the other's fault and the node could
    # only be restarted ("set other parameters and configure again" notwithstanding).
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(
            context=context,
            parameter_overrides=[
                *SMALL_MLM,
                Parameter('subpixel', value='cubic'),
                Parameter('depth_encoding', value='16UC2'),
                Parameter('roi_top', value=0.6),
            ],
        )
        client = StereoClient(context)
        spinner = Spinner(context, node, client.node)
        try:
            assert node.trigger_configure() == TransitionCallbackReturn.FAILURE
            # A change that is itself at fault is still refused, with its own reason.
            (refused,) = set_parameters_by_service(client.node, subpixel='bicubic')
            assert not refused.successful
            assert "got 'bicubic'" in refused.reason
            assert node.get_parameter('subpixel').value == 'cubic'
            # So is one in conflict with a value kept (roi_top 0.6).
            (conflict,) = set_parameters_by_service(client.node, roi_bottom=0.5)
            assert not conflict.successful
            assert 'roi_top must be smaller than roi_bottom' in conflict.reason
            (one,) = set_parameters_by_service(client.node, subpixel='parabola')
            assert one.successful, one.reason
            (other,) = set_parameters_by_service(client.node, depth_encoding='16UC1')
            assert other.successful, other.reason
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert node.pipeline_config.subpixel == 'parabola'
            assert node.node_config.depth_encoding == '16UC1'
        finally:
            spinner.stop()
            client.node.destroy_node()
            node.destroy_node()


def test_a_frame_left_unpublished_by_a_deactivate_counts_as_dropped() -> None:
    # The frame in progress at a deactivate finished unpublished and counted nowhere: frames
    # received ran ahead of processed + dropped + throttled + invalid + failed for good.
    with localhost_context(spare_domain_id()) as context:
        node = ManagedConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
        try:
            assert node.trigger_configure() == TransitionCallbackReturn.SUCCESS
            assert node.trigger_activate() == TransitionCallbackReturn.SUCCESS
            started, release = held_pipeline(node)
            left, right = textured_pair()
            stamp = first_stamp()
            feed_frame(node, left, right, stamp)
            assert started.wait(20.0)
            feed_frame(node, left, right, stamp + 10**8)  # waits in the mailbox
            assert node.trigger_deactivate() == TransitionCallbackReturn.SUCCESS
            release.set()
            counted = ('frames_processed', 'frames_dropped', 'frames_throttled',
                       'frames_invalid', 'frames_failed')
            assert wait_until(
                lambda: sum(node.stats()[key] for key in counted) == 2, 10.0
            ), node.stats()
            stats = node.stats()
            assert stats['frames_received'] == 2
            assert stats['frames_dropped'] == 2
            assert stats['frames_processed'] == 0
        finally:
            node.destroy_node()


def test_a_stage_switched_off_at_run_time_leaves_no_mean_time_in_diagnostics() -> None:
    # speckle_size 0 and subpixel none at run time: /diagnostics kept mean_speckle_ms and
    # mean_subpixel_ms at their last values for as long as the node ran.
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, parameter_overrides=list(SMALL_MLM))
        try:
            left, right = textured_pair()
            stamp = first_stamp()
            feed_frame(node, left, right, stamp)
            assert wait_until(lambda: node.stats()['frames_processed'] == 1, 30.0)
            keys = {kv.key for kv in node.diagnostics().values}
            assert {'mean_speckle_ms', 'mean_subpixel_ms'} <= keys
            results = node.set_parameters([
                Parameter('speckle_size', value=0), Parameter('subpixel', value='none'),
            ])
            assert all(result.successful for result in results)
            time.sleep(0.05)
            feed_frame(node, left, right, stamp + 10**9)
            assert wait_until(lambda: node.stats()['frames_processed'] == 2, 30.0)
            values = {kv.key: kv.value for kv in node.diagnostics().values}
            stale = {'mean_speckle_ms', 'mean_subpixel_ms', 'last_speckle_ms',
                     'last_subpixel_ms'} & set(values)
            assert not stale, values
            assert 'mean_frame_ms' in values
        finally:
            node.destroy_node()
