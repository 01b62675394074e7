"""Review 31: ``cva-demo``, the laser scan and the stamp synchroniser (each a regression test
of a fault found there): keys that cannot be dict keys, and what ``score_scan`` is handed that
is not a scan, a geometry or a config."""

from __future__ import annotations

import numpy as np
import pytest

from cva_confidence_ros.errors import ConfigError, InputError
from cva_confidence_ros.pointcloud import StereoGeometry
from cva_confidence_ros.scan import ScanConfig, disparity_to_scan, score_scan
from cva_confidence_ros.sync import StampSynchronizer

GEOMETRY = StereoGeometry(fx=100.0, fy=100.0, cx=47.5, cy=3.5, cx_right=47.5, baseline=0.1)


@pytest.mark.parametrize('keys', [None, 5, [['left'], 'right']])
def test_keys_that_are_no_sequence_of_names_are_a_config_error(keys: object) -> None:
    # Were a bare TypeError ("'NoneType' object is not iterable", "unhashable type: 'list'").
    with pytest.raises(ConfigError, match='keys must be a sequence of hashable stream names'):
        StampSynchronizer(keys)  # type: ignore[arg-type]


@pytest.mark.parametrize('key', [['left'], {'left': 1}])
def test_an_unhashable_key_offered_is_an_unknown_key(key: object) -> None:
    # Was a bare TypeError ("unhashable type: 'list'") out of add().
    sync = StampSynchronizer(('left', 'right'))
    with pytest.raises(ConfigError, match=r"^unknown key .*; expected one of \('left', 'right'\)"):
        sync.add(key, 1, 'msg')  # type: ignore[arg-type]
    assert sync.dropped == 0 and sync.pending() == {'left': 0, 'right': 0}


def _scan():
    config = ScanConfig(min_height=-1.0, max_height=1.0)
    return disparity_to_scan(np.full((8, 96), 5.0, np.float32), GEOMETRY, config=config)


def test_score_scan_names_what_is_not_a_scan_a_geometry_or_a_config() -> None:
    # Were AttributeErrors ("'dict' object has no attribute 'min_height'", "'NoneType' object
    # has no attribute 'fx'"); disparity_to_scan already named a config that is no ScanConfig.
    scan = _scan()
    with pytest.raises(ConfigError, match='^config must be a ScanConfig; got dict$'):
        score_scan(scan, scan, GEOMETRY, {'pitch': 0.1})  # type: ignore[arg-type]
    with pytest.raises(InputError, match='^geometry must be a StereoGeometry; got NoneType$'):
        score_scan(scan, scan, None)  # type: ignore[arg-type]
    with pytest.raises(InputError, match='^truth must be a Scan; got ndarray$'):
        score_scan(scan, np.zeros(3), GEOMETRY)  # type: ignore[arg-type]
    with pytest.raises(InputError, match='^estimate must be a Scan; got list$'):
        score_scan([], scan, GEOMETRY)  # type: ignore[arg-type]
    assert score_scan(scan, scan, GEOMETRY).phantom == 0
