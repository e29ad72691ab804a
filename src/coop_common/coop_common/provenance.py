"""Where a result came from: the source revision a long run's records carry, so that a run
resumed over several checkouts says which attempts ran on which code."""
from __future__ import annotations

import subprocess
from pathlib import Path


def source_revision(path: str | Path | None = None) -> str | None:
    """The git commit of the checkout holding `path` (default: this module's), with '-dirty'
    appended when tracked files differ from it; None outside a git checkout or without git.
    An installed (not symlinked) package has no checkout and gives None."""
    where = Path(path if path is not None else __file__).resolve()
    cwd = where if where.is_dir() else where.parent
    try:
        head = subprocess.run(['git', 'rev-parse', 'HEAD'], cwd=cwd, check=True,
                              capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(['git', 'status', '--porcelain', '--untracked-files=no'],
                               cwd=cwd, check=True, capture_output=True, text=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return f'{head}-dirty' if dirty else head
