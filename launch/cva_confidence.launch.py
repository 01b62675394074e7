"""Launch the cva_confidence node with the shipped parameter file.

Usage (full ROS 2 install)::

    ros2 launch cva_confidence_ros cva_confidence.launch.py \
        stereo_namespace:=/stereo params_file:=/path/to/params.yaml \
        matcher:=census_sgm max_disparity:=128

The node subscribes to ``<stereo_namespace>/{left,right}/{image_rect,camera_info}`` and
publishes ``disparity``, ``disparity_filtered``, ``confidence``, ``points2``, ``depth``,
``confidence_overlay``, ``scan`` and ``camera_info`` in the same namespace, like
``stereo_image_proc``. Launch arguments left empty keep the file's value (e.g.
``max_rate_hz:=2.0`` caps the CPU the node takes, ``speckle_size:=0`` turns the speckle filter
off, ``scan_frame_id:=camera_link`` names the frame of ``scan``).

``cloud_filter_threshold:=0.8`` also starts the ``cloud_filter`` node in that namespace: the
confidence node then publishes every point with its confidence (``points_confidence: true``) and
the filter republishes those with confidence >= 0.8 on ``points2_filtered``.

``rviz:=true`` also starts ``rviz2`` in that namespace with the shipped layout
(``config/cva_confidence.rviz``: the kept points, the scan coloured by confidence, the overlay
and the confidence map); ``rviz_fixed_frame:=base_link`` views it in the robot's frame (TF
needed), the default is the left camera's optical frame of the bag tools.

``lifecycle:=true`` starts the managed node (``lifecycle_node``) instead, as a
``launch_ros`` ``LifecycleNode`` for a lifecycle manager to configure and activate;
``autostart:=true`` with it makes the node configure and activate itself.
"""

# The repository's own launch/ folder makes ruff take the `launch` package for first-party.
# ruff: noqa: I001

from __future__ import annotations

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node

PACKAGE = 'cva_confidence_ros'

# Launch arguments that override one parameter of the file, with the parameter's type.
OVERRIDES: dict[str, type] = {
    'matcher': str,
    'max_disparity': int,
    'confidence_method': str,
    'model_path': str,
    'device': str,
    'confidence_threshold': float,
    'downsample': int,
    'speckle_size': int,
    'max_rate_hz': float,
    'scan_frame_id': str,
    'roi_top': float,
    'roi_bottom': float,
    'mask_path': str,
}


def _node(context: LaunchContext) -> list[Node | LifecycleNode]:
    overrides = {}
    for name, kind in OVERRIDES.items():
        value = LaunchConfiguration(name).perform(context)
        if value:
            overrides[name] = kind(value)
    use_sim_time = LaunchConfiguration('use_sim_time').perform(context).lower() == 'true'
    lifecycle = LaunchConfiguration('lifecycle').perform(context).lower() == 'true'
    node_class, executable = Node, 'node'
    if lifecycle:
        node_class, executable = LifecycleNode, 'lifecycle_node'
        overrides['autostart'] = (
            LaunchConfiguration('autostart').perform(context).lower() == 'true'
        )
    namespace = LaunchConfiguration('stereo_namespace')
    cloud_threshold = LaunchConfiguration('cloud_filter_threshold').perform(context)
    nodes = []
    if cloud_threshold:
        overrides['points_confidence'] = True
        nodes.append(
            Node(
                package=PACKAGE,
                executable='cloud_filter',
                name='cva_cloud_filter',
                namespace=namespace,
                output='screen',
                emulate_tty=True,
                parameters=[{'threshold': float(cloud_threshold), 'use_sim_time': use_sim_time}],
            )
        )
    if LaunchConfiguration('rviz').perform(context).lower() == 'true':
        layout = os.path.join(
            get_package_share_directory(PACKAGE), 'config', 'cva_confidence.rviz'
        )
        frame = LaunchConfiguration('rviz_fixed_frame').perform(context)
        nodes.append(
            Node(
                package='rviz2',
                executable='rviz2',
                name='cva_rviz',
                namespace=namespace,
                arguments=['-d', layout, *(['-f', frame] if frame else [])],
                parameters=[{'use_sim_time': use_sim_time}],
            )
        )
    return [
        node_class(
            package=PACKAGE,
            executable=executable,
            name='cva_confidence',
            namespace=namespace,
            output='screen',
            emulate_tty=True,
            parameters=[
                LaunchConfiguration('params_file'),
                {'use_sim_time': use_sim_time},
                overrides,
            ],
        ),
        *nodes,
    ]


def generate_launch_description() -> LaunchDescription:
    """Declare the launch arguments and the node."""
    default_params = os.path.join(
        get_package_share_directory(PACKAGE), 'config', 'cva_confidence.yaml'
    )
    arguments = [
        DeclareLaunchArgument(
            'stereo_namespace', default_value='', description='Namespace of the stereo topics.'
        ),
        DeclareLaunchArgument(
            'params_file', default_value=default_params, description='Node parameter file.'
        ),
        DeclareLaunchArgument(
            'use_sim_time', default_value='false', description='Use the /clock topic.'
        ),
        DeclareLaunchArgument(
            'lifecycle',
            default_value='false',
            description='Start the managed (lifecycle) node instead of the plain one.',
        ),
        DeclareLaunchArgument(
            'autostart',
            default_value='false',
            description='With lifecycle:=true: configure and activate at once.',
        ),
        DeclareLaunchArgument(
            'cloud_filter_threshold',
            default_value='',
            description='Also start cloud_filter at this threshold (points_confidence on); '
            'empty = no filter.',
        ),
        DeclareLaunchArgument(
            'rviz',
            default_value='false',
            description='Also start rviz2 with the shipped layout (config/cva_confidence.rviz).',
        ),
        DeclareLaunchArgument(
            'rviz_fixed_frame',
            default_value='',
            description="rviz2's fixed frame (e.g. base_link, with TF); empty keeps the "
            "layout's left_camera_optical_frame.",
        ),
    ]
    arguments += [
        DeclareLaunchArgument(
            name, default_value='', description=f'Override {name}; empty keeps it.'
        )
        for name in OVERRIDES
    ]
    return LaunchDescription([*arguments, OpaqueFunction(function=_node)])
