"""Every command a README shows names something that exists: `ros2 run PKG EXE` an installed
executable where ros2 run looks (and, with the real ros2cli, one that `ros2 pkg executables`
lists), `ros2 launch PKG FILE` an installed launch file, `python -m MOD` a module, and
`bench/`, `tools/` (.py, .sh, .yaml, .txt) and `install/...` paths files. The READMEs are read
at test time."""
from __future__ import annotations

import importlib.util
import re
import subprocess
from functools import cache
from pathlib import Path

import pytest
from ament_index_python.packages import get_package_share_directory

from coop_common.testing import executable_path, ros2_tools

ROOT = Path(__file__).resolve().parents[1]
READMES = sorted({ROOT / 'README.md', ROOT / 'bags' / 'README.md',
                  *ROOT.glob('src/*/README.md'), *ROOT.glob('docs/**/*.md')})

RUN = re.compile(r'ros2 run ([a-z_]+) ([\w.-]+)')
LAUNCH = re.compile(r'ros2 launch ([a-z_]+) ([\w.-]+\.launch\.py)')
MODULE = re.compile(r'python3? -m ([a-z_][\w.]*)')
PATHS = re.compile(r'(?<![\w/.-])((?:bench|tools)/[\w-]+\.(?:py|sh|yaml|txt)'
                   r'|install/[\w/-]+(?:\.(?:py|yaml|json|txt))?)')


def _commands(kind: re.Pattern) -> list[tuple[str, tuple[str, ...]]]:
    out = []
    for readme in READMES:
        for m in kind.finditer(readme.read_text(encoding='utf-8')):
            out.append((str(readme.relative_to(ROOT)), m.groups()))
    return sorted(set(out))


def _ids(cases):
    return [f'{where}: {" ".join(args)}' for where, args in cases]


RUNS = _commands(RUN)
LAUNCHES = _commands(LAUNCH)
MODULES = [c for c in _commands(MODULE) if c[1][0] not in ('pytest', 'pip', 'venv')]
FILES = _commands(PATHS)


def test_the_readmes_show_commands():
    assert len(RUNS) >= 8 and LAUNCHES and MODULES and FILES


@pytest.mark.parametrize('where,args', RUNS, ids=_ids(RUNS))
def test_ros2_run_executable_is_installed(where, args):
    executable_path(*args)


@cache
def _ros2_executables(ros2: str, pkg: str) -> str:
    return subprocess.run([ros2, 'pkg', 'executables', pkg], check=False, capture_output=True,
                          text=True, timeout=60).stdout


@pytest.mark.parametrize('where,args', RUNS, ids=_ids(RUNS))
def test_ros2_run_resolves_with_the_real_ros2cli(where, args):
    pkg, exe = args
    assert f'{pkg} {exe}' in _ros2_executables(ros2_tools(), pkg).splitlines()


@pytest.mark.parametrize('where,args', LAUNCHES, ids=_ids(LAUNCHES))
def test_ros2_launch_file_is_installed(where, args):
    pkg, name = args
    assert (Path(get_package_share_directory(pkg)) / 'launch' / name).is_file()


@pytest.mark.parametrize('where,args', MODULES, ids=_ids(MODULES))
def test_python_module_exists(where, args):
    assert importlib.util.find_spec(args[0]) is not None, f'{where}: no module {args[0]}'


@pytest.mark.parametrize('where,args', FILES, ids=_ids(FILES))
def test_path_exists(where, args):
    path = ROOT / args[0]
    assert path.exists(), f'{where}: {args[0]} does not exist (after make build)'


def test_the_root_readme_stays_short():
    """The root README is the front page: under 8,000 characters (the rest is in the package
    READMEs and docs/)."""
    n = len((ROOT / 'README.md').read_text(encoding='utf-8'))
    assert n < 8000, f'README.md has {n} characters'
