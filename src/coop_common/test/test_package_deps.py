"""Every package's package.xml declares what its modules import or run, so a rosdep install (or
a reader) gets the full list: the imports of each `src/<pkg>/<pkg>/` module (ast, function-local
ones included) and the installed executables it starts (`NodeProcess('pkg', ...)`), mapped to
rosdep keys by the explicit table below. An import the table does not know fails the test until
it is added there, so the declarations cannot drift from the code."""
from __future__ import annotations

import ast
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[2]
PACKAGES = sorted(p.parent for p in SRC.glob('*/package.xml'))

#: import name -> rosdep key (ros/rosdistro's, or tools/rosdep.yaml's where it has none:
#: test/test_package_deps.py checks each key resolves)
ROSDEP = {
    'numpy': 'python3-numpy',
    'scipy': 'python3-scipy',
    'cv2': 'python3-opencv',
    'yaml': 'python3-yaml',
    'matplotlib': 'python3-matplotlib',
    'pybullet': 'python3-pybullet-pip',
    'ruamel': 'python3-ruamel.yaml',
    'rosbags': 'python3-rosbags-pip',
    'mcap': 'python3-mcap-pip',
    'filterpy': 'python3-filterpy-pip',
    'pytest': 'python3-pytest',
    'tqdm': 'python3-tqdm',
    'foxglove': 'python3-foxglove-sdk-pip',
    'websockets': 'python3-websockets',
    'serial': 'python3-serial',
    'cobs': 'python-cobs-pip',
    'zstandard': 'python3-zstandard',
    'lz4': 'python3-lz4',
}
#: ROS packages imported under their own name (client library, message and project packages)
ROS_PACKAGES = {
    'rclpy', 'rcl_interfaces', 'ament_index_python', 'builtin_interfaces', 'std_msgs',
    'std_srvs', 'geometry_msgs', 'sensor_msgs', 'nav_msgs', 'trajectory_msgs',
    'visualization_msgs', 'rosgraph_msgs', 'coop_msgs', 'action_msgs', 'lifecycle_msgs',
    'tf2_msgs', 'launch', 'launch_ros',
} | {p.name for p in PACKAGES}


def _imports(pkg: Path) -> dict[str, set[str]]:
    """Top-level names imported by the package's modules -> the files that import them."""
    out: dict[str, set[str]] = {}
    for f in sorted((pkg / pkg.name).rglob('*.py')):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for n in names:
                top = n.split('.')[0]
                if top not in sys.stdlib_module_names and top not in ('__future__', pkg.name):
                    out.setdefault(top, set()).add(f.name)
    return out


def _runs(pkg: Path) -> dict[str, set[str]]:
    """Packages whose installed executables the modules start: NodeProcess('pkg', 'exe', ...)
    and executable_path('pkg', 'exe') with a literal package name."""
    out: dict[str, set[str]] = {}
    for f in sorted((pkg / pkg.name).rglob('*.py')):
        for node in ast.walk(ast.parse(f.read_text(), str(f))):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                    and node.func.id in ('NodeProcess', 'executable_path') and node.args
                    and isinstance(node.args[0], ast.Constant)
                    and node.args[0].value != pkg.name):
                out.setdefault(node.args[0].value, set()).add(f.name)
    return out


def _declared(pkg: Path, *tags: str) -> set[str]:
    root = ET.parse(pkg / 'package.xml').getroot()
    return {e.text.strip() for t in tags for e in root.iter(t) if e.text}


def test_the_scan_sees_function_local_and_aliased_imports(tmp_path):
    pkg = tmp_path / 'demo_pkg'
    (pkg / 'demo_pkg').mkdir(parents=True)
    (pkg / 'demo_pkg' / 'm.py').write_text(
        'import os\nimport numpy as np\nfrom . import x\nfrom demo_pkg import y\n'
        'def f():\n    import cv2.aruco\n    from rover_bag.bagio import read_messages\n'
        "    NodeProcess('rover_sim', 'sim', [])\n")
    assert set(_imports(pkg)) == {'numpy', 'cv2', 'rover_bag'}
    assert set(_runs(pkg)) == {'rover_sim'}


@pytest.mark.parametrize('pkg', PACKAGES, ids=lambda p: p.name)
def test_package_xml_declares_every_import_and_executable(pkg):
    declared = _declared(pkg, 'exec_depend', 'depend')
    unknown, missing = [], []
    for name, files in sorted(_imports(pkg).items()):
        key = name if name in ROS_PACKAGES else ROSDEP.get(name)
        if key is None:
            unknown.append(f'{name} ({", ".join(sorted(files))})')
        elif key not in declared:
            missing.append(f'{key} (import {name} in {", ".join(sorted(files))})')
    for name, files in sorted(_runs(pkg).items()):
        if name not in declared:
            missing.append(f'{name} (runs its executables in {", ".join(sorted(files))})')
    assert not unknown, f'{pkg.name}: imports with no rosdep key in ROSDEP: {unknown}'
    assert not missing, f'{pkg.name}/package.xml lacks <exec_depend> for: {missing}'
