"""Every executable is where `ros2 run <pkg> <exe>` looks: the package is in the ament index on
AMENT_PREFIX_PATH, and <prefix>/lib/<pkg>/<exe> is an executable file."""
import ast
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_prefix, get_package_share_directory

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent for p in (ROOT / 'src').glob('*/package.xml'))


def console_scripts(setup_py: Path) -> list[str]:
    """Executable names from setup(entry_points={'console_scripts': [...]}) (static parse)."""
    tree = ast.parse(setup_py.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.keyword) and node.arg == 'entry_points':
            entry = ast.literal_eval(node.value)
            return [s.split('=')[0].strip() for s in entry.get('console_scripts', [])]
    return []


def test_every_package_is_found():
    assert len(PACKAGES) >= 2
    names = {ET.parse(p / 'package.xml').getroot().findtext('name') for p in PACKAGES}
    assert names == {p.name for p in PACKAGES}, 'package.xml names must match their directories'
    for name in names | {'coop_msgs'}:
        prefix = Path(get_package_prefix(name))
        marker = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / name
        assert marker.is_file(), marker
        assert (Path(get_package_share_directory(name)) / 'package.xml').is_file()


@pytest.mark.parametrize('pkg', PACKAGES, ids=lambda p: p.name)
def test_executables_are_where_ros2_run_looks(pkg):
    for exe in console_scripts(pkg / 'setup.py'):
        path = Path(get_package_prefix(pkg.name)) / 'lib' / pkg.name / exe
        assert path.is_file() and os.access(path, os.X_OK), f'ros2 run {pkg.name} {exe}: {path}'


@pytest.mark.parametrize('pkg', PACKAGES, ids=lambda p: p.name)
def test_setup_cfg_installs_scripts_for_ros2_run(pkg):
    text = (pkg / 'setup.cfg').read_text()
    assert f'script_dir=$base/lib/{pkg.name}' in text
    assert f'install_scripts=$base/lib/{pkg.name}' in text
    assert (pkg / 'resource' / pkg.name).is_file()
