"""``cva_*`` options that change nothing for the configured method (a hand-crafted measure,
a cascade fraction without a cascade) are named in the node's log: they were accepted without a
word, and a user tuning them saw no change."""

from __future__ import annotations

from node_test_utils import SMALL_MLM, LogRecorder, localhost_context, spare_domain_id
import pytest
from rclpy.parameter import Parameter

from cva_confidence_ros.node import ConfidenceNode
from cva_confidence_ros.pipeline import PipelineConfig

pytestmark = pytest.mark.timeout(120)


def test_unused_options_of_a_config() -> None:
    assert PipelineConfig().unused_options() == []
    assert PipelineConfig(cva_cascade='pkrn', cva_cascade_fraction=0.1).unused_options() == []
    assert PipelineConfig(cva_cascade_fraction=0.1).unused_options() == [
        'cva_cascade_fraction 0.1']
    config = PipelineConfig(confidence_method='pkrn', cva_stride=4, cva_backend='onnxruntime')
    assert config.unused_options() == ['cva_stride 4', "cva_backend 'onnxruntime'"]


def test_the_node_names_options_without_effect_and_says_nothing_otherwise() -> None:
    with localhost_context(spare_domain_id()) as context:
        node = ConfidenceNode(
            context=context,
            parameter_overrides=[*SMALL_MLM, Parameter('cva_stride', value=4)],
        )
        recorder = LogRecorder()
        node.get_logger = lambda: recorder  # type: ignore[method-assign]
        try:
            node._warn_if_slow(node._pipeline)
            assert ('warning', 'cva_stride 4: no effect on confidence_method mlm (they apply '
                    'to cva_net, cva_net_lite, cva_net_fast)') in recorder.lines
            # Set back: nothing to say (the warning comes with every rebuild of the pipeline).
            assert node.set_parameters([Parameter('cva_stride', value=1)])[0].successful
            recorder.lines.clear()
            node._warn_if_slow(node._pipeline)
            assert not [line for _, line in recorder.lines if 'no effect' in line]
        finally:
            node.destroy_node()
