"""Every dependency key of every package.xml is one that a ROS 2 Jazzy install resolves: a package
of this workspace, a ROS 2 Jazzy package (JAZZY_PACKAGES), a key of ros/rosdistro's rosdep
database (pinned in tools/rosdistro-keys.yaml) or of the repository's own (tools/rosdep.yaml),
and each of the last two resolves on Ubuntu 24.04. No ROS graph."""
from __future__ import annotations

import xml.etree.ElementTree as ET
from functools import cache
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_XMLS = sorted([ROOT / 'msg' / 'package.xml', *ROOT.glob('src/*/package.xml')])
DEPEND_TAGS = ('depend', 'build_depend', 'buildtool_depend', 'build_export_depend',
               'exec_depend', 'test_depend')
PROJECT_KEYS = ROOT / 'tools' / 'rosdep.yaml'
ROSDISTRO_KEYS = ROOT / 'tools' / 'rosdistro-keys.yaml'

#: The ROS 2 Jazzy packages (Debian packages ros-jazzy-*) that the package.xml files name: each
#: a package of ros/rosdistro's jazzy/distribution.yaml at commit 8468e88ccd52.
JAZZY_PACKAGES = frozenset({
    'action_msgs', 'ament_cmake', 'ament_index_python', 'builtin_interfaces', 'geometry_msgs',
    'launch', 'launch_ros', 'lifecycle_msgs', 'nav_msgs', 'rcl_interfaces', 'rclpy',
    'ros2launch', 'rosgraph_msgs', 'rosidl_default_generators', 'rosidl_default_runtime',
    'sensor_msgs', 'std_msgs', 'std_srvs', 'tf2_msgs', 'trajectory_msgs', 'visualization_msgs',
})
#: the platform the Jazzy install is for: Ubuntu 24.04
OS_NAME, OS_VERSION = 'ubuntu', 'noble'


def _package(path: Path) -> tuple[str, list[tuple[str, str]]]:
    root = ET.parse(path).getroot()
    deps = [(tag, e.text.strip()) for tag in DEPEND_TAGS for e in root.iter(tag)]
    return root.findtext('name').strip(), deps


@cache
def _workspace() -> dict[str, list[tuple[str, str]]]:
    return dict(_package(p) for p in PACKAGE_XMLS)


def _keys_used() -> set[str]:
    return {key for deps in _workspace().values() for _, key in deps} - set(_workspace())


@cache
def _rosdep_data(path: Path) -> dict:
    data = yaml.safe_load(path.read_text(encoding='utf-8'))
    assert isinstance(data, dict) and data, f'{path.name}: not a rosdep YAML'
    return data


def _resolve(key: str) -> tuple[str, list[str]]:
    """(installer, packages) of a key of the two rosdep YAMLs on Ubuntu 24.04, by rosdep's rules:
    the OS entry (or the '*' one), then the version entry (or '*'), then a list of Debian packages
    or an installer's entry."""
    data = {**_rosdep_data(ROSDISTRO_KEYS), **_rosdep_data(PROJECT_KEYS)}[key]
    entry = data.get(OS_NAME, data.get('*'))
    assert entry is not None, f'{key}: nothing for {OS_NAME}'
    if isinstance(entry, dict) and not {'pip', 'apt'} & entry.keys():
        entry = entry.get(OS_VERSION, entry.get('*'))
        assert entry is not None, f'{key}: nothing for {OS_NAME} {OS_VERSION}'
    if isinstance(entry, list):
        return 'apt', entry
    (installer, spec), = entry.items()
    return installer, list(spec['packages'] if isinstance(spec, dict) else spec)


def test_every_dependency_key_is_known():
    known = (set(_workspace()) | JAZZY_PACKAGES | set(_rosdep_data(ROSDISTRO_KEYS))
             | set(_rosdep_data(PROJECT_KEYS)))
    unknown = [f'{name}: <{tag}>{key}' for name, deps in _workspace().items()
               for tag, key in deps if key not in known]
    assert not unknown, ('keys that are no workspace package, JAZZY_PACKAGES entry, '
                         'tools/rosdistro-keys.yaml or tools/rosdep.yaml key:\n'
                         + '\n'.join(unknown))


def test_the_key_files_hold_only_used_keys_each_once():
    project, rosdistro = set(_rosdep_data(PROJECT_KEYS)), set(_rosdep_data(ROSDISTRO_KEYS))
    assert not project & rosdistro, 'tools/rosdep.yaml redefines rosdistro keys'
    assert not (project | rosdistro) & JAZZY_PACKAGES
    assert not (project | rosdistro) - _keys_used(), 'keys no package.xml uses'
    assert _keys_used() - set(_workspace()) - JAZZY_PACKAGES <= project | rosdistro


def test_every_key_resolves_on_ubuntu_noble():
    for key in sorted(_keys_used() - JAZZY_PACKAGES):
        installer, packages = _resolve(key)
        assert installer in ('apt', 'pip') and packages, (key, installer, packages)
        assert key.endswith('-pip') == (installer == 'pip'), key
