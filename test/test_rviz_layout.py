"""``config/cva_confidence.rviz``: the RViz2 layout shows the node's outputs by their names.

rviz2 is not on the package index, so the layout is checked against the node's own topic
table rather than opened.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from cva_confidence_ros.node import _TOPICS
from cva_confidence_ros.plots import CORRECT_RGB, WRONG_RGB
from msg_tools.bag_from_dataset import BagSpec

yaml = pytest.importorskip('yaml')

ROOT = Path(__file__).resolve().parents[1]
LAYOUT = ROOT / 'config' / 'cva_confidence.rviz'

#: rviz display class → the message type it shows.
SHOWS = {
    'rviz_default_plugins/PointCloud2': 'sensor_msgs/PointCloud2',
    'rviz_default_plugins/LaserScan': 'sensor_msgs/LaserScan',
    'rviz_default_plugins/Image': 'sensor_msgs/Image',
}


def _displays() -> list[dict]:
    return yaml.safe_load(LAYOUT.read_text())['Visualization Manager']['Displays']


def test_every_display_shows_a_node_output_of_its_type() -> None:
    outputs = {name: kind for direction, name, kind, _ in _TOPICS if direction == 'out'}
    shown = {}
    for display in _displays():
        if 'Topic' not in display:
            continue
        topic = display['Topic']
        name = topic['Value']
        # Relative: rviz2 started in the stereo namespace finds <namespace>/<name>.
        assert not name.startswith('/'), name
        assert outputs[name] == SHOWS[display['Class']], name
        # Best effort matches the node's output_qos either way (reliable or sensor_data).
        assert topic['Reliability Policy'] == 'Best Effort', name
        shown[name] = display
    assert set(shown) == {'points2', 'scan', 'confidence_overlay', 'confidence'}
    assert shown['points2']['Color Transformer'] == 'RGB8'  # the x y z rgb cloud
    # The scan's intensity is the confidence: coloured over [0, 1], red to green as the overlay.
    scan = shown['scan']
    assert scan['Color Transformer'] == 'Intensity'
    assert scan['Autocompute Intensity Bounds'] is False
    assert (scan['Min Intensity'], scan['Max Intensity']) == (0, 1)
    assert (scan['Min Color'], scan['Max Color']) == tuple(
        '; '.join(map(str, rgb)) for rgb in (WRONG_RGB, CORRECT_RGB))
    confidence = shown['confidence']
    assert (confidence['Normalize Range'], confidence['Min Value'], confidence['Max Value']) \
        == (False, 0, 1)


def test_the_fixed_frame_is_the_bag_tools_left_camera() -> None:
    options = yaml.safe_load(LAYOUT.read_text())['Visualization Manager']['Global Options']
    assert options['Fixed Frame'] == BagSpec.__dataclass_fields__['left_frame'].default
