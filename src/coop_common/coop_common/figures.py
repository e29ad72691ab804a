"""Figures a test measures, kept for a results page.

Some results are what a test measures as it checks them: the decoder's counts over 10^5
damaged frames, the rates through the hardware bridge, an identification through the emulator.
A test records them (`FigureLog.add`) and prints them through the same formatter a results
page names; `python -m pytest ... --figures-json PATH` (the root conftest's option) writes
every record of the run to PATH, and `tools/results_pages.py` makes the page's block from it.
So a page quotes no test output by hand.

The file: `{"source": <git revision>, "records": {KEY: [record, ...]}}`, one record per run
of the test that adds KEY (`--count 3` gives three).
"""
from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from coop_common.errors import CoopCommonError
from coop_common.files import write_json
from coop_common.provenance import source_revision

_SCALARS = (str, int, float, bool, type(None))


def _plain(value: Any, where: str) -> Any:
    """`value` as JSON types (numpy scalars and arrays included), or CoopCommonError."""
    if isinstance(value, _SCALARS):
        return value
    if isinstance(value, Mapping):
        return {str(k): _plain(v, f'{where}.{k}') for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v, f'{where}[{i}]') for i, v in enumerate(value)]
    tolist = getattr(value, 'tolist', None)          # numpy arrays and scalars
    if callable(tolist):
        return _plain(tolist(), where)
    raise CoopCommonError(f'{where}: {type(value).__name__} is not a JSON value')


class FigureLog:
    """The records of one test session, by key, in the order the tests added them."""

    def __init__(self) -> None:
        self.records: dict[str, list[dict[str, Any]]] = {}

    def add(self, key: str, record: Mapping[str, Any]) -> dict[str, Any]:
        """Keep `record` (JSON values, numpy ones converted) under `key`; returns it as kept."""
        if not key:
            raise CoopCommonError('a record needs a key')
        kept = _plain(dict(record), key)
        self.records.setdefault(key, []).append(kept)
        return kept

    def write(self, path: str | Path) -> Path:
        """Write every record, with the source revision, atomically to `path`."""
        return write_json(path, {'source': source_revision(), 'records': self.records})


def records(data: Mapping[str, Any], key: str) -> list[dict[str, Any]]:
    """The records under `key` of a figures file's parsed JSON, or CoopCommonError naming what the
    file holds (a page that names a key no test of the run added)."""
    got = data.get('records', {})
    if key not in got:
        raise CoopCommonError(f'no {key!r} records in the figures file (it holds {sorted(got)})')
    return list(got[key])
