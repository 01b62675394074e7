"""rosbag2 tools of cva_confidence_ros: data sets → bags, and bag replay evaluation.

Bags are read and written (MCAP or sqlite3) through ``rosbags``, without the rosbag2 C++ stack.
The node's output messages are built with the ROS message packages and serialised with
``rclpy.serialization``, so rclpy and the message packages are needed (the ``ros-jazzy-*``
wheels of ``make setup`` will do); only the ``live`` replay mode talks DDS.

Modules:
    bagio: opening input bags and writing output bags, with ``BagError`` for every fault.
    convert: ``rosbags`` message types (ROS 2 Jazzy typestore) ⇄ numpy arrays.
    scoring: per-frame confidence metrics and the JSON / CSV / Markdown / PNG report.
    replay: options, topic names, the node's outputs, the shared session, the offline mode.
    live: the live mode (the bag played over DDS to a real ``cva-node``).
    progress: progress lines on stderr and Ctrl-C that never cuts a bag write in half.
    bag_from_dataset, bag_replay: the two command-line tools.

The replay decodes inputs and builds outputs with the node's own code
(``cva_confidence_ros.ros.convert``, the pipeline's [0, 1] confidence), so its output bag
holds what the node publishes.
"""

from __future__ import annotations

__all__: list[str] = []
