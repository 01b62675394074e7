"""Build script of the cva_confidence_ros ament_python package.

Two installs are supported from this one file:

* ``colcon build`` in a ROS 2 workspace, which runs ``setup.py develop`` or ``setup.py install``
  directly. The scripts then land in ``lib/cva_confidence_ros`` (see ``setup.cfg``), where
  ``ros2 run cva_confidence_ros <name>`` looks for them, under the ROS-style names.
* ``pip install`` into a virtual environment (PEP 517 build). The scripts land on ``PATH`` under
  ``cva-*`` names only: a plain ``node`` executable there would shadow Node.js. ``make setup``
  installs the dependencies first (torch pinned to the CPU build, rclpy and the message packages
  as the ``ros-jazzy-*`` wheels, which ``install_requires`` leaves to ROS or to the Makefile) and
  then this package with ``--no-deps``.
"""

from glob import glob
import sys

from setuptools import find_packages, setup

PACKAGE = 'cva_confidence_ros'

# (ros2 run name, pip console-script name, module:function)
ENTRY_POINTS = [
    ('node', 'cva-node', 'cva_confidence_ros.node:main'),
    ('lifecycle_node', 'cva-lifecycle-node', 'cva_confidence_ros.node:lifecycle_main'),
    ('lifecycle', 'cva-lifecycle', 'cva_confidence_ros.ros.lifecycle_cli:main'),
    ('param', 'cva-param', 'cva_confidence_ros.ros.param_cli:main'),
    ('cloud_filter', 'cva-cloud-filter', 'cva_confidence_ros.cloud_filter:main'),
    ('train', 'cva-train', 'cva_confidence_ros.training.cli:main'),
    ('evaluate', 'cva-evaluate', 'cva_confidence_ros.evaluation.cli:main'),
    ('table1', 'cva-table1', 'cva_confidence_ros.evaluation.table1:main'),
    ('benchmark', 'cva-benchmark', 'cva_confidence_ros.benchmark:main'),
    ('demo', 'cva-demo', 'cva_confidence_ros.demo:main'),
    ('export', 'cva-export', 'cva_confidence_ros.model.export:main'),
    ('bag_from_dataset', 'cva-bag-from-dataset', 'msg_tools.bag_from_dataset:main'),
    ('bag_replay', 'cva-bag-replay', 'msg_tools.bag_replay:main'),
    ('mask', 'cva-mask', 'msg_tools.mask_tool:main'),
]


def _built_by_colcon() -> bool:
    """Tell a direct ``setup.py install/develop`` run (colcon's ament_python build) from pip."""
    return any(arg in ('install', 'develop') for arg in sys.argv[1:])


def _console_scripts() -> list[str]:
    if _built_by_colcon():
        return [f'{ros_name} = {target}' for ros_name, _, target in ENTRY_POINTS]
    return [f'{pip_name} = {target}' for _, pip_name, target in ENTRY_POINTS]


setup(
    name=PACKAGE,
    version='0.1.0',
    packages=find_packages(exclude=['test', 'test.*']),
    package_data={PACKAGE: ['py.typed']},
    data_files=[
        ('share/ament_index/resource_index/packages', [f'resource/{PACKAGE}']),
        (f'share/{PACKAGE}', ['package.xml']),
        (f'share/{PACKAGE}/launch', glob('launch/*.launch.py')),
        (f'share/{PACKAGE}/config', glob('config/*.yaml') + glob('config/*.xml')
                                             + glob('config/*.rviz')),
        (f'share/{PACKAGE}/models', sorted(glob('models/*.pt') + glob('models/*.md')
                                             + glob('models/*.json') + glob('models/*.yaml'))),
    ],
    install_requires=['setuptools', 'numpy', 'opencv-python-headless', 'scikit-image', 'numba',
                      'torch', 'matplotlib', 'tqdm', 'rosbags', 'mccnn', 'pyyaml'],
    zip_safe=True,
    maintainer='cva_confidence_ros maintainers',
    maintainer_email='maintainers@cva-confidence-ros.dev',
    description='Online per-pixel stereo confidence with CVA-Net for ROS 2.',
    license='Apache-2.0',
    python_requires='>=3.10',
    extras_require={'export': ['onnx', 'onnxruntime']},  # cva-export and its check
    tests_require=['pytest', 'scipy'],
    entry_points={'console_scripts': _console_scripts()},
)
