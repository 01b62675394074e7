"""The Fast DDS profile for image-sized messages (no rclpy import: the benchmarks and the bag
tools set it in a child's environment before any participant exists).

``config/fastdds_large_messages.xml`` is the same profile as a file for users (a test keeps
the two equal); :func:`write_profile` writes this copy where a run needs one.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ['FASTDDS_LARGE_MESSAGES_XML', 'PROFILE_VARIABLES', 'profile_environment',
           'write_profile']

#: The environment variables Fast DDS reads its XML profile file from: Fast DDS 2.x (ROS 2
#: Jazzy) reads the first, Fast DDS 3 the second.
PROFILE_VARIABLES = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')

#: Fast DDS profile for image-sized messages on one host: a 16 MB shared-memory segment per
#: participant instead of the stock 512 kB. With the stock segment, the four ~1 MB messages of
#: one 640×480 frame do not all fit; the ones that miss are repaired only at the writer's next
#: heartbeat (every 3 s) with reliable QoS, and lost with best effort.
FASTDDS_LARGE_MESSAGES_XML = """\
<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>shm_large_messages</transport_id>
      <type>SHM</type>
      <segment_size>16777216</segment_size>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>udp</transport_id>
      <type>UDPv4</type>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="cva_large_messages" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>shm_large_messages</transport_id>
        <transport_id>udp</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
    </rtps>
  </participant>
</profiles>
"""


def write_profile(folder: str | Path) -> Path:
    """Write :data:`FASTDDS_LARGE_MESSAGES_XML` as ``fastdds_large_messages.xml`` into
    ``folder``; returns the file."""
    path = Path(folder) / 'fastdds_large_messages.xml'
    path.write_text(FASTDDS_LARGE_MESSAGES_XML, encoding='utf-8')
    return path


def profile_environment(path: str | Path) -> dict[str, str]:
    """The environment variables that make a process's participants use the profile file."""
    return {name: str(path) for name in PROFILE_VARIABLES}
