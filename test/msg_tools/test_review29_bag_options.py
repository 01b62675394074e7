"""Review 29: cva-bag-replay refuses a sync tolerance exact sync would ignore, and its
approximate sync takes the node's tolerance unless told otherwise."""

from __future__ import annotations

import pytest

from cva_confidence_ros.errors import ConfigError
from cva_confidence_ros.ros.params import NodeConfig
from msg_tools.bag_replay import SYNC_TOLERANCE_S, build_parser, options_from_args


def _options(*extra: str):
    args = ['in', '--out', 'out', '--report', 'report', *extra]
    return options_from_args(build_parser().parse_args(args))


def test_a_tolerance_without_approximate_sync_is_refused() -> None:
    # Exact sync pairs equal stamps only: the tolerance was ignored without a word.
    with pytest.raises(ConfigError, match='--sync-tolerance needs --approximate-sync'):
        _options('--sync-tolerance', '0.005')


def test_approximate_sync_takes_the_nodes_tolerance_by_default() -> None:
    # It was 0 s: --approximate-sync alone paired equal stamps only, unlike the node.
    assert SYNC_TOLERANCE_S == NodeConfig().approximate_sync_tolerance_seconds
    assert _options('--approximate-sync').sync_tolerance_s == SYNC_TOLERANCE_S
    assert _options('--approximate-sync', '--sync-tolerance', '0').sync_tolerance_s == 0.0
    assert _options().sync_tolerance_s == 0.0 and not _options().approximate_sync
