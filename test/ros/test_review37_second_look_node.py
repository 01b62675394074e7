"""Second look at review 37's node changes (regression tests of the faults found in them)."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
from node_test_utils import SMALL_MLM, localhost_context, spare_domain_id
import numpy as np
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode

pytestmark = pytest.mark.timeout(120)


def test_a_file_parameter_set_again_rebuilds_the_pipeline_only_for_a_changed_file(
    tmp_path: Path,
) -> None:
    # Setting mask_path (or model_path) again to its path rebuilt the pipeline every time,
    # the file changed or not: a parameter file loaded again (every parameter set, the
    # paths among them) swapped in a cold pipeline, warmed up before the next frame.
    mask = np.full((48, 64), 255, np.uint8)
    mask[40:] = 0
    path = tmp_path / 'bumper.png'
    assert cv2.imwrite(str(path), mask)
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(context=context, parameter_overrides=[
            *SMALL_MLM, Parameter('mask_path', value=str(path)),
            Parameter('diagnostics_period_seconds', value=600.0),
        ])
        try:
            before = node._pipeline
            (result,) = node.set_parameters([Parameter('mask_path', value=str(path))])
            assert result.successful, result.reason
            assert node._pipeline is before
            # Edited under its name (a mast added): read anew.
            mask[:, 20:30] = 0
            assert cv2.imwrite(str(path), mask)
            stat = path.stat()  # a later modification time, as a second's wait would give
            os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
            (result,) = node.set_parameters([Parameter('mask_path', value=str(path))])
            assert result.successful, result.reason
            assert node._pipeline is not before
            assert not node._pipeline._mask[:, 20:30].any()
        finally:
            node.destroy_node()
