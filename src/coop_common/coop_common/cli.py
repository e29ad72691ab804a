"""argparse types for the experiment executables: a bad argument is a usage error with the
reason (exit 2 before any work), not a traceback deep in a run or a silent run on NaN."""
from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from enum import Enum
from pathlib import Path


def enum_choices(kind: type[Enum]) -> list[str]:
    """The values of an Enum of string modes as argparse `choices`: an unknown value is a
    usage error naming them as they are typed (given the members themselves, argparse names
    their reprs, `<Strategy.CONSTANT: 'constant'>`). The option's value stays a string; the
    core it goes to takes it as the member."""
    return [m.value for m in kind]


def number(kind: type = float, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, hi_open: bool = False) -> Callable[[str], float | int]:
    """A finite `kind` (int or float) within [lo, hi] ((lo, ... / ..., hi) when open)."""
    def parse(text: str) -> float | int:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f'{text!r} is not {kind.__name__}') from None
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f'{text!r} is not finite')
        if lo is not None and (v <= lo if lo_open else v < lo):
            raise argparse.ArgumentTypeError(f'{v} must be {">" if lo_open else ">="} {lo}')
        if hi is not None and (v >= hi if hi_open else v > hi):
            raise argparse.ArgumentTypeError(f'{v} must be {"<" if hi_open else "<="} {hi}')
        return v
    parse.__name__ = kind.__name__      # argparse names the type in "invalid ... value"
    return parse


def output_path(text: str) -> Path:
    """A file to write at the end of a run: refused at once when it cannot be created (a
    directory there, or a file where a parent directory has to be), not after the run."""
    p = Path(text)
    if p.is_dir():
        raise argparse.ArgumentTypeError(f'{text} is a directory')
    for parent in p.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise argparse.ArgumentTypeError(f'{parent} is not a directory')
            break
    return p


def output_dir(text: str) -> Path:
    """A directory to write into (made when missing): refused at once when a file is there
    or on its way."""
    p = Path(text)
    for q in (p, *p.absolute().parents):
        if q.exists():
            if not q.is_dir():
                raise argparse.ArgumentTypeError(f'{q} is not a directory')
            break
    return p


#: the figure formats the experiments write (matplotlib's Agg: the format from the suffix)
FIGURE_SUFFIXES = ('.png', '.pdf', '.svg')


def figure_path(text: str) -> Path:
    """`output_path` of a figure whose suffix names a format it can be written in."""
    p = output_path(text)
    if p.suffix.lower() not in FIGURE_SUFFIXES:
        raise argparse.ArgumentTypeError(f'{text}: a figure file ends in one of '
                                         f'{", ".join(FIGURE_SUFFIXES)}')
    return p
