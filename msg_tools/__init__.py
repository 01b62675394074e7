"""rosbag2 tools of cva_confidence_ros: data sets → bags, and bag replay evaluation.

Everything here reads and writes rosbag2 files (MCAP or sqlite3) through ``rosbags``, without a
ROS installation; only the ``live`` replay mode talks DDS through rclpy.

Modules:
    bagio: opening input bags and writing output bags, with :class:`BagError` for every fault.
    convert: ``rosbags`` message types (ROS 2 Jazzy typestore) ⇄ numpy arrays.
    scoring: per-frame confidence metrics and the JSON / CSV / Markdown / PNG report.
    replay: the offline replay engine, :mod:`live`: the live one (over DDS, against the node).
    bag_from_dataset, bag_replay: the two command-line tools.
"""

from __future__ import annotations

__all__: list[str] = []
