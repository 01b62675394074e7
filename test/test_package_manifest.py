"""package.xml and setup.py declare every package that the installed code imports.

A colcon workspace installs what ``package.xml`` names (rosdep), a plain ``pip install`` what
``install_requires`` names; an import that neither declares works here only because ``make
setup`` installed it anyway. The imports are read from the sources (every ``import`` statement,
also those inside functions), so a new third-party import fails here until it is declared, or
until this table says why it needs no declaration.
"""

from __future__ import annotations

import ast
from pathlib import Path
import sys
import xml.etree.ElementTree as ET

ROOT = Path(__file__).resolve().parents[1]
SOURCES = [ROOT / 'cva_confidence_ros', ROOT / 'msg_tools', ROOT / 'launch']
OWN = {'cva_confidence_ros', 'msg_tools'}

# top-level module → (rosdep key in package.xml or None, pip name in install_requires or None)
DECLARATIONS: dict[str, tuple[str | None, str | None]] = {
    # ROS packages: rosdep keys; on pip they are the ros-jazzy-* wheels, left to ROS / the Makefile
    'rclpy': ('rclpy', None),
    'rcl_interfaces': ('rcl_interfaces', None),
    'sensor_msgs': ('sensor_msgs', None),
    'stereo_msgs': ('stereo_msgs', None),
    'std_msgs': ('std_msgs', None),
    'diagnostic_msgs': ('diagnostic_msgs', None),
    'lifecycle_msgs': ('lifecycle_msgs', None),
    'builtin_interfaces': ('builtin_interfaces', None),
    'ament_index_python': ('ament_index_python', None),
    'launch': ('launch', None),
    'launch_ros': ('launch_ros', None),
    # Python packages
    'numpy': ('python3-numpy', 'numpy'),
    'cv2': ('python3-opencv', 'opencv-python-headless'),
    'skimage': ('python3-skimage', 'scikit-image'),
    'torch': ('python3-torch', 'torch'),
    'numba': ('python3-numba', 'numba'),
    'matplotlib': ('python3-matplotlib', 'matplotlib'),
    'tqdm': ('python3-tqdm', 'tqdm'),
    'rosbags': ('python3-rosbags-pip', 'rosbags'),
    'yaml': ('python3-yaml', 'pyyaml'),  # cva-param (rclpy needs it too)
    # pip only (no rosdep key): package.xml says so in a comment, the README says `pip install`
    'mc_cnn': (None, 'mccnn'),
    # imported only where present: rosbags' own sqlite3 driver (its dependency), and the build
    'apsw': (None, None),
    # optional, cva-export's check: setup.py's extras_require['export'], the Makefile installs it
    'onnxruntime': (None, None),
    'onnx': (None, None),  # the exporter's writer (torch.onnx needs it), the same extra
    # optional, the image readers' header check (scikit-image and matplotlib depend on Pillow;
    # without it OpenCV reads as before)
    'PIL': (None, None),
    'setuptools': (None, 'setuptools'),
}


def _imported_modules() -> dict[str, set[str]]:
    """Top-level module → source files that import it (third-party only)."""
    found: dict[str, set[str]] = {}
    stdlib = set(sys.stdlib_module_names)
    for source in SOURCES:
        for path in sorted(source.rglob('*.py')):
            tree = ast.parse(path.read_text(), filename=str(path))
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                else:
                    continue
                for name in names:
                    top = name.split('.')[0]
                    if top in stdlib or top in OWN or top == '__future__':
                        continue
                    found.setdefault(top, set()).add(str(path.relative_to(ROOT)))
    return found


def _package_xml_keys() -> set[str]:
    root = ET.parse(ROOT / 'package.xml').getroot()
    tags = ('depend', 'exec_depend', 'build_export_depend')
    return {element.text.strip() for tag in tags for element in root.iter(tag) if element.text}


def _install_requires() -> set[str]:
    tree = ast.parse((ROOT / 'setup.py').read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'install_requires':
            value = ast.literal_eval(node.value)
            return {requirement.split('=')[0].split('<')[0].split('>')[0] for requirement in value}
    raise AssertionError('setup.py has no install_requires')


def test_every_third_party_import_is_in_the_table() -> None:
    unknown = {
        module: sorted(files)
        for module, files in _imported_modules().items()
        if module not in DECLARATIONS
    }
    assert not unknown, f'imports with no declaration decided: {unknown}'


def test_package_xml_declares_every_import() -> None:
    keys = _package_xml_keys()
    missing = {
        module: DECLARATIONS[module][0]
        for module in _imported_modules()
        if module in DECLARATIONS and DECLARATIONS[module][0] is not None
        and DECLARATIONS[module][0] not in keys
    }
    assert not missing, f'package.xml lacks exec_depend for: {missing}'


def test_install_requires_declares_every_python_import() -> None:
    requires = _install_requires()
    missing = {
        module: DECLARATIONS[module][1]
        for module in _imported_modules()
        if module in DECLARATIONS and DECLARATIONS[module][1] is not None
        and DECLARATIONS[module][1] not in requires
    }
    assert not missing, f'setup.py install_requires lacks: {missing}'


def test_package_xml_declares_nothing_unused() -> None:
    imported_keys = {DECLARATIONS[module][0] for module in _imported_modules()
                     if module in DECLARATIONS}
    unused = _package_xml_keys() - imported_keys
    assert not unused, f'package.xml exec_depends on packages nothing imports: {sorted(unused)}'


def test_the_pip_only_dependency_is_explained_in_package_xml() -> None:
    text = (ROOT / 'package.xml').read_text()
    assert 'pip install mccnn' in text
