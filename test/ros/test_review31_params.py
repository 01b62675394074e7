"""Review 31 of the node parameters: a read-only double given as a whole number at start-up
is a double, as the settable ones are."""

from __future__ import annotations

import os

from node_test_utils import SMALL_MLM, localhost_context, spare_domain_id
import pytest
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.ros.cloud_filter_node import CloudFilterNode

pytestmark = pytest.mark.timeout(120)

NAMESPACE = f'review31_{os.getpid()}'


@pytest.mark.parametrize('kind', ['confidence', 'cloud_filter'])
def test_a_read_only_double_given_as_a_whole_number_is_a_double(kind: str) -> None:
    # -p diagnostics_period_seconds:=2 is an integer to rcl; read-only, nothing could retype
    # it after the declaration: ros2 param describe/get said "Integer" for good.
    name = 'diagnostics_period_seconds'
    overrides = [Parameter(name, value=2)]
    with localhost_context(spare_domain_id()) as context:
        if kind == 'confidence':
            overrides += SMALL_MLM
            node = ConfidenceNode(context=context, namespace=NAMESPACE,
                                  parameter_overrides=overrides)
        else:
            node = CloudFilterNode(context=context, namespace=NAMESPACE,
                                   parameter_overrides=overrides)
        try:
            value = node.get_parameter(name)
            descriptor = node.describe_parameter(name)
            assert descriptor.read_only
            assert descriptor.type == ParameterType.PARAMETER_DOUBLE
            assert value.type_ == Parameter.Type.DOUBLE
            assert value.value == 2.0 and isinstance(value.value, float)
        finally:
            node.destroy_node()
