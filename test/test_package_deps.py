"""Every dependency key of every package.xml is one that a ROS 2 Jazzy install resolves: a package
of this workspace, a ROS 2 Jazzy package (JAZZY_PACKAGES), a key of ros/rosdistro's rosdep
database (pinned in tools/rosdistro-keys.yaml) or of the repository's own (tools/rosdep.yaml).
The Jazzy install of docs/install.md agrees with them: its `rosdep install` skips exactly the keys
that resolve to pip on Ubuntu 24.04, and tools/requirements-jazzy.txt installs their packages.
Where a `rosdep` command is at hand (the pinned venv has one), rosdep itself runs the documented
`rosdep install` as a dry run for Ubuntu 24.04, offline, from those files. No ROS graph."""
from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from functools import cache
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
PACKAGE_XMLS = sorted([ROOT / 'msg' / 'package.xml', *ROOT.glob('src/*/package.xml')])
DEPEND_TAGS = ('depend', 'build_depend', 'buildtool_depend', 'build_export_depend',
               'exec_depend', 'test_depend')
PROJECT_KEYS = ROOT / 'tools' / 'rosdep.yaml'
ROSDISTRO_KEYS = ROOT / 'tools' / 'rosdistro-keys.yaml'
VENV_REQUIREMENTS = ROOT / 'tools' / 'requirements-jazzy.txt'
INSTALL_DOCS = (ROOT / 'docs' / 'install.md', ROOT / 'README.md')

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


def _pip_keys() -> set[str]:
    return {k for k in _keys_used() - JAZZY_PACKAGES if _resolve(k)[0] == 'pip'}


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


def _requirements(path: Path) -> dict[str, tuple[str, str]]:
    """Name -> (version, the comment after it) of a `name==version  # comment` file."""
    out = {}
    for line in path.read_text(encoding='utf-8').splitlines():
        pin, _, comment = line.partition('#')
        if pin.strip():
            name, _, version = pin.strip().partition('==')
            out[name.lower()] = (version, comment.strip())
    return out


def test_the_venv_requirements_are_the_pip_keys_at_the_locked_versions():
    wanted = {p.lower(): key for key in _pip_keys() for p in _resolve(key)[1]}
    have = _requirements(VENV_REQUIREMENTS)
    assert set(have) == set(wanted), 'tools/requirements-jazzy.txt vs the pip keys'
    lock = _requirements(ROOT / 'requirements.lock')
    for name, (version, comment) in have.items():
        assert comment == wanted[name], f'{name}: the comment names its key {wanted[name]}'
        assert version == lock[name][0], f'{name}=={version}, requirements.lock {lock[name][0]}'


def _documented(command: str) -> list[tuple[str, list[str]]]:
    """Each `command ...` a doc shows in a code block (continuation lines joined, up to `&&`,
    `;`, `|` or a comment): (doc, argv)."""
    out = []
    for doc in INSTALL_DOCS:
        text = doc.read_text(encoding='utf-8').replace('\\\n', ' ')
        for block in re.findall(r'```bash\n(.*?)```', text, flags=re.S):
            for line in block.splitlines():
                if command in line:
                    rest = line[line.index(command):]
                    argv = shlex.split(re.split(r'&&|;|\||#', rest)[0])
                    out.append((doc.name, argv))
    return out


def _option(argv: list[str], name: str) -> str | None:
    return argv[argv.index(name) + 1] if name in argv else None


def test_the_documented_rosdep_install_skips_exactly_the_pip_keys():
    commands = _documented('rosdep install')
    assert {doc for doc, _ in commands} == {d.name for d in INSTALL_DOCS}
    for doc, argv in commands:
        assert argv[2:6] == ['--from-paths', 'msg', 'src', '--ignore-src'], (doc, argv)
        skipped = set((_option(argv, '--skip-keys') or '').split())
        assert skipped == _pip_keys(), f'{doc}: --skip-keys {sorted(skipped)}'


def test_the_docs_register_the_repository_keys():
    for doc in INSTALL_DOCS:
        text = doc.read_text(encoding='utf-8')
        assert 'yaml file://$PWD/tools/rosdep.yaml' in text, doc.name
        assert 'pip install -r tools/requirements-jazzy.txt' in text, doc.name


def _rosdep() -> str:
    path = os.pathsep.join([str(Path(sys.executable).parent), os.environ.get('PATH', '')])
    exe = shutil.which('rosdep', path=path)
    if exe is None:
        pytest.skip('no rosdep command here (the pinned venv has one; on Ubuntu: '
                    'apt install python3-rosdep)')
    return exe


def _offline_rosdep(tmp: Path) -> dict[str, str]:
    """An environment in which rosdep reads only the two key files and a rosdistro index of
    JAZZY_PACKAGES, all local: the rosdep database of a Jazzy install, without the network."""
    sources = tmp / 'sources.list.d'
    sources.mkdir()
    (sources / '20-default.list').write_text(f'yaml {ROSDISTRO_KEYS.as_uri()}\n')
    (sources / '50-coop.list').write_text(f'yaml {PROJECT_KEYS.as_uri()}\n')
    (tmp / 'jazzy').mkdir()
    repos = {p: {'release': {'version': '0.0.0-1', 'url': f'https://example.invalid/{p}.git',
                             'tags': {'release': 'release/jazzy/{package}/{version}'}}}
             for p in sorted(JAZZY_PACKAGES)}
    (tmp / 'jazzy' / 'distribution.yaml').write_text(yaml.safe_dump(
        {'type': 'distribution', 'version': 2, 'release_platforms': {OS_NAME: [OS_VERSION]},
         'repositories': repos}))
    (tmp / 'index.yaml').write_text(yaml.safe_dump(
        {'type': 'index', 'version': 4, 'distributions': {'jazzy': {
            'distribution': ['jazzy/distribution.yaml'], 'distribution_status': 'active',
            'distribution_type': 'ros2', 'python_version': 3}}}))
    # no AMENT_PREFIX_PATH / ROS_PACKAGE_PATH: --ignore-src skips every ROS package they hold
    # (the pinned venv's, a sourced /opt/ros/jazzy's), and here every key is to be resolved;
    # PIP_BREAK_SYSTEM_PACKAGES: a rosdep outside a venv refuses to print pip commands without it
    env = {k: v for k, v in os.environ.items()
           if k not in ('AMENT_PREFIX_PATH', 'ROS_PACKAGE_PATH')}
    return {**env, 'ROSDEP_SOURCE_PATH': str(sources), 'ROS_HOME': str(tmp / 'home'),
            'ROSDISTRO_INDEX_URL': (tmp / 'index.yaml').as_uri(), 'ROS_DISTRO': 'jazzy',
            'ROS_PYTHON_VERSION': '3', 'PIP_BREAK_SYSTEM_PACKAGES': '1'}


def _simulate(rosdep: str, argv: list[str], env: dict[str, str]) -> dict[str, set[str]]:
    """Run `rosdep install ...` as a dry run for Ubuntu 24.04 (every key, installed or not):
    installer -> the packages it would install."""
    cmd = [rosdep, *argv[1:], '--simulate', '--reinstall', '--os', f'{OS_NAME}:{OS_VERSION}',
           '--rosdistro', 'jazzy']
    out = subprocess.run(cmd, cwd=ROOT, env=env, check=False, capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, f'{shlex.join(cmd)}:\n{out.stdout}{out.stderr}'
    found: dict[str, set[str]] = {}
    installer = None
    for line in out.stdout.splitlines():
        if m := re.match(r'#\[(\w+)\] Installation commands:', line):
            installer = m.group(1)
        elif line.startswith('  ') and installer:
            found.setdefault(installer, set()).add(line.split()[-1])
    return found


def test_rosdep_dry_run_of_the_documented_install(tmp_path):
    rosdep = _rosdep()
    env = _offline_rosdep(tmp_path)
    update = subprocess.run([rosdep, 'update', '--rosdistro', 'jazzy'], env=env,
                            check=False, capture_output=True, text=True, timeout=300)
    assert update.returncode == 0, update.stdout + update.stderr
    (doc, argv), *_ = _documented('rosdep install')
    debs = {p for k in _keys_used() - JAZZY_PACKAGES - _pip_keys() for p in _resolve(k)[1]}
    debs |= {'ros-jazzy-' + p.replace('_', '-') for p in _keys_used() & JAZZY_PACKAGES}
    # as documented: the Debian packages, nothing by pip
    assert _simulate(rosdep, argv, env) == {'apt': debs}, doc
    # without --skip-keys: the pip keys are what tools/requirements-jazzy.txt installs
    i = argv.index('--skip-keys')
    every = _simulate(rosdep, argv[:i] + argv[i + 2:], env)
    assert every == {'apt': debs, 'pip': set(_requirements(VENV_REQUIREMENTS))}
