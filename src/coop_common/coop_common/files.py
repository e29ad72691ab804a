"""Atomic file writes: a reader never sees a half-written file, and a crash keeps the old one."""
from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def _write_atomic(path: str | Path, mode: str, write: Callable[[IO], None]) -> Path:
    """Call `write` on a temporary file in `path`'s directory, fsync, then os.replace."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(fd, mode, **({} if 'b' in mode else {'encoding': 'utf-8'})) as f:
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
    return _write_atomic(path, 'w', lambda f: f.write(text))


def save_figure(fig: Any, path: str | Path, *, dpi: int = 100) -> Path:
    """Lay out a matplotlib figure, write it atomically (format from the suffix) and close it."""
    import matplotlib.pyplot as plt  # noqa: PLC0415 - only the plotting paths need it
    path = Path(path)
    fig.tight_layout()
    try:
        return _write_atomic(path, 'wb', lambda f: fig.savefig(
            f, dpi=dpi, format=path.suffix.lstrip('.') or 'png'))
    finally:
        plt.close(fig)


def write_json(path: str | Path, obj: Any, *, indent: int = 2) -> Path:
    """Write `obj` as JSON to `path` atomically (benchmark and experiment results)."""
    return write_text_atomic(path, json.dumps(obj, indent=indent) + '\n')
