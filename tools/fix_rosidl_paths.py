#!/usr/bin/env python3
"""Point the ROS wheels' exported CMake targets at this venv's real include directories.

The PyPI builds of the message packages export INTERFACE_INCLUDE_DIRECTORIES naming the build
machine's Python (``/opt/python/cp311-cp311/...``); CMake refuses targets whose include
directories do not exist, so ``rosidl_generate_interfaces`` of our own ``coop_msgs`` fails until
they are rewritten (see shared/docs/platform.md). Idempotent: a second run changes nothing.
"""
from __future__ import annotations

import os
import sys
import sysconfig
from pathlib import Path

BUILD_PREFIX = '/opt/python/cp311-cp311'


def main() -> int:
    """Rewrite the build machine's paths in the venv's exported CMake files; 1 if an
    include directory is missing."""
    import numpy  # noqa: PLC0415 - the venv's numpy, imported only here

    prefix = Path(sys.prefix)
    py_include = sysconfig.get_paths()['include']
    np_include = numpy.get_include()
    site = Path(numpy.__file__).resolve().parent.parent
    replacements = [
        (f'{BUILD_PREFIX}/lib/python3.11/site-packages/numpy/_core/include', np_include),
        (f'{BUILD_PREFIX}/lib/python3.11/site-packages', str(site)),
        (f'{BUILD_PREFIX}/include/python3.11', py_include),
    ]
    changed = 0
    for path in (prefix / 'share').glob('*/cmake/*.cmake'):
        text = path.read_text()
        if BUILD_PREFIX not in text:
            continue
        for old, new in replacements:
            text = text.replace(old, new)
        tmp = path.with_suffix('.cmake.tmp')
        tmp.write_text(text)
        os.replace(tmp, path)
        changed += 1
    missing = [p for _, p in replacements if not Path(p).is_dir()]
    if missing:
        print(f'fix_rosidl_paths: include directories missing: {missing}', file=sys.stderr)
        return 1
    print(f'fix_rosidl_paths: rewrote {changed} CMake export files under {prefix / "share"}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
