#!/usr/bin/env python3
"""Regenerate the printed tables in docs/results/*.md (and the parameter tables in the package
READMEs) from the JSON the commands wrote and the code's own tables.

A results page is prose around generated blocks. A block names the function that prints the
table (the same function the command calls to print it) and the JSON file the command wrote:

    <!-- generated: text coop_id.table_2_1:format_json data/table_2_1.json -->
    ...replaced on every run...
    <!-- end generated -->

`text` puts the function's output in a fenced block, as the command printed it; `md` inserts it
as it is (the function returns Markdown). The JSON path is relative to the page's directory.
The function takes the parsed JSON and returns a string. In place of a JSON path a block may
name a Python object, `MODULE:NAME` (e.g. a node's parameter table), passed as it is. So a page
cannot drift from the code: `--check` (run by the tests) fails when a page is not what the code
makes of its JSON.

Usage: python tools/results_pages.py [--check] [PAGE.md ...]   (default: every docs/results page)
"""
from __future__ import annotations

import argparse
import difflib
import importlib
import json
import re
import sys
from collections.abc import Callable
from pathlib import Path

from coop_common.files import write_text_atomic

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / 'docs' / 'results'
sys.path.insert(0, str(ROOT))     # bench/*.py format their tables too: `bench.sim_rate:...`

BLOCK = re.compile(
    r'(?P<open><!-- generated: (?P<kind>text|md) (?P<func>[\w.]+:\w+) (?P<json>[\w./:-]+) -->\n)'
    r'(?P<body>.*?)'
    r'(?P<close><!-- end generated -->)',
    re.DOTALL)


class PageError(Exception):
    """A generated block that cannot be made: a missing JSON file, module or function."""


def _function(spec: str, *, want_callable: bool = True) -> Callable[[object], str]:
    module, _, name = spec.partition(':')
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError, ValueError) as exc:
        raise PageError(f'{spec}: {exc}') from None
    if want_callable and not callable(fn):
        raise PageError(f'{spec} is not callable')
    return fn


def render(page: Path) -> str:
    """The page with every generated block made anew from its JSON."""
    text = page.read_text(encoding='utf-8')

    def block(m: re.Match[str]) -> str:
        if not m['json'].endswith('.json'):
            data = _function(m['json'], want_callable=False)
        else:
            try:
                data = json.loads((page.parent / m['json']).read_text(encoding='utf-8'))
            except (OSError, ValueError) as exc:
                raise PageError(f'{page.name}: {m["json"]}: {exc}') from None
        out = _function(m['func'])(data).rstrip('\n')
        body = f'```text\n{out}\n```\n' if m['kind'] == 'text' else f'{out}\n'
        return m['open'] + body + m['close']

    return BLOCK.sub(block, text)


def main(argv: list[str] | None = None) -> int:
    """Regenerate the result pages, or with `--check` report the stale ones."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--check', action='store_true',
                    help='change nothing; exit 1 and show a diff when a page is stale')
    ap.add_argument('pages', nargs='*', type=Path,
                    help='pages (default: docs/results/*.md and src/*/README.md)')
    args = ap.parse_args(argv)
    pages = args.pages or [*sorted(RESULTS.glob('*.md')),
                           *sorted(ROOT.glob('src/*/README.md'))]
    stale = 0
    for page in pages:
        try:
            new = render(page)
        except PageError as exc:
            print(f'results_pages: {exc}', file=sys.stderr)
            return 2
        old = page.read_text(encoding='utf-8')
        if new == old:
            continue
        stale += 1
        if args.check:
            sys.stdout.writelines(difflib.unified_diff(
                old.splitlines(True), new.splitlines(True), str(page), f'{page} (generated)'))
        else:
            write_text_atomic(page, new)
            print(f'results_pages: wrote {page}')
    if args.check and stale:
        print(f'results_pages: {stale} page(s) differ from their JSON; run '
              f'python tools/results_pages.py', file=sys.stderr)
        return 1
    return 0


if __name__ == '__main__':
    sys.exit(main())
