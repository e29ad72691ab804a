"""Atomic file writes: a reader never sees a half-written file, and a crash keeps the old one."""
from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any

# the process's umask, read once at import (os.umask can only be read by setting it, which
# would race with other threads creating files later)
_UMASK = os.umask(0o022)
os.umask(_UMASK)


def write_atomic(path: str | os.PathLike[str], mode: str, write: Callable[[IO], object]
                 ) -> Path:
    """Call `write` on a temporary file in `path`'s directory, fsync, then os.replace. The file
    gets the permissions a plain open() would give it (an existing file's, else 0666 less the
    umask), not mkstemp's 0600."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        perms = path.stat().st_mode & 0o7777
    except FileNotFoundError:
        perms = 0o666 & ~_UMASK
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        os.fchmod(fd, perms)
        with os.fdopen(fd, mode, encoding=None if 'b' in mode else 'utf-8') as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Write `text` to `path` through a temporary file in the same directory + os.replace."""
    return write_atomic(path, 'w', lambda f: f.write(text))


def save_figure(fig: Any, path: str | Path, *, dpi: int = 100) -> Path:
    """Lay out a matplotlib figure, write it atomically (format from the suffix) and close it."""
    import matplotlib.pyplot as plt  # noqa: PLC0415 - only the plotting paths need it
    path = Path(path)
    fig.tight_layout()
    try:
        return write_atomic(path, 'wb', lambda f: fig.savefig(
            f, dpi=dpi, format=path.suffix.lstrip('.') or 'png'))
    finally:
        plt.close(fig)


def write_json(path: str | Path, obj: Any, *, indent: int = 2) -> Path:
    """Write `obj` as JSON to `path` atomically (benchmark and experiment results)."""
    return write_text_atomic(path, json.dumps(obj, indent=indent) + '\n')
