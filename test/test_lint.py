"""Lint gate, as ament_flake8 does in a ROS package's tests: ruff with ament's settings
(line length 99, single quotes, pyflakes, pycodestyle, import order) and the rules ruff.toml
adds (bugbear, pyupgrade, simplify, ruff, pylint, naming, pydocstyle). `make lint` runs it and
mypy."""
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_ruff_clean():
    ruff = shutil.which('ruff') or str(Path(sys.executable).parent / 'ruff')
    out = subprocess.run([ruff, 'check', '--output-format', 'concise', str(ROOT)],
                         check=False, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
