"""docs/results pages are what the code makes of the committed JSON (tools/results_pages.py):
every generated block matches its JSON, every JSON a page names is committed in
docs/results/data/, and no output block is quoted by hand but the listed ones still to be made."""
from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location(
    'results_pages', ROOT / 'tools' / 'results_pages.py')
results_pages = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(results_pages)


def test_every_results_page_is_generated_from_its_json(capsys):
    assert results_pages.main(['--check']) == 0, capsys.readouterr().out


def test_a_block_is_remade_and_a_stale_one_is_found(tmp_path, capsys):
    (tmp_path / 'r.json').write_text(json.dumps({'a': [1, 2]}))
    page = tmp_path / 'p.md'
    page.write_text('# p\n<!-- generated: text json:dumps r.json -->\nold\n'
                    '<!-- end generated -->\ntail\n')
    assert results_pages.main(['--check', str(page)]) == 1
    assert '+{"a": [1, 2]}' in capsys.readouterr().out
    assert results_pages.main([str(page)]) == 0
    assert page.read_text() == ('# p\n<!-- generated: text json:dumps r.json -->\n```text\n'
                                '{"a": [1, 2]}\n```\n<!-- end generated -->\ntail\n')
    assert results_pages.main(['--check', str(page)]) == 0


def test_a_missing_json_is_an_error_not_a_silent_page(tmp_path, capsys):
    page = tmp_path / 'p.md'
    page.write_text('<!-- generated: md json:dumps nothing.json -->\n<!-- end generated -->\n')
    assert results_pages.main(['--check', str(page)]) == 2
    assert 'nothing.json' in capsys.readouterr().err


@pytest.mark.parametrize('spec', ['json:no_such_function', 'no_such_module_xyz:f'])
def test_an_unknown_function_is_an_error(tmp_path, spec):
    (tmp_path / 'r.json').write_text('{}')
    page = tmp_path / 'p.md'
    page.write_text(f'<!-- generated: md {spec} r.json -->\n<!-- end generated -->\n')
    assert results_pages.main(['--check', str(page)]) == 2


def test_a_block_may_name_an_object_such_as_a_parameter_table(tmp_path):
    page = tmp_path / 'p.md'
    page.write_text('<!-- generated: md coop_common.params:markdown_table '
                    'rover_sim.sim_node:PARAMS -->\n<!-- end generated -->\n')
    assert results_pages.main([str(page)]) == 0
    text = page.read_text()
    assert '| `seed` | int | `1` | 0 .. 2147483647 | no |' in text
    assert '| `real_time_factor` | float | `1.0` | 0.0 .. 100.0 | yes |' in text


# --- Every output on a results page is made from a committed JSON file -----------------------

#: A fenced block is a command block when every non-blank line is a command (or a comment) and
#: an output block otherwise: the command words a line may start with.
COMMAND_WORDS = ('python', 'python3', 'make', 'ros2', 'colcon', 'source', '.', 'cd', 'export',
                 'git', 'pip', 'bash', 'bench/', 'tools/', '#', '$')
#: `--json PATH` (or pytest's `--figures-json PATH`, coop_common.figures) where PATH is a JSON
#: file; the bare word `--json` in prose names no file.
JSON_OPTION = re.compile(r'--(?:figures-)?json\s+`?([\w./-]+\.json)')
#: a generated marker, written as one or quoted in the prose, and the JSON it names
MARKER_JSON = re.compile(r'<!-- generated: (?:\w+ )?\S+ ([\w./-]+\.json) -->')
#: a placeholder file name (NAME.json, OUT.json) marks a command as an example, not a run
PLACEHOLDER = re.compile(r'(?:^|/)[A-Z][A-Z0-9_]*\.json$')

#: The output blocks still quoted by hand, one entry per block: (page, how the block's first line
#: starts, why). The text before each says which command makes its JSON and the generated marker
#: that replaces it. Emptied as they are made; an entry that matches no block fails the test, so
#: the list cannot rot.
QUOTED: list[tuple[str, str, str]] = []
#: The JSON files the pages name (in `--json PATH` or a marker) that have not been made yet:
#: the commands the QUOTED blocks are waiting for. Same rule: a file made must leave the list.
AWAITED: set[str] = set()


def _pages() -> list[Path]:
    return sorted(results_pages.RESULTS.glob('*.md'))


def _without_generated_bodies(text: str) -> str:
    """The page with each generated block's body (program output, not the page's own words)
    left out; the marker lines stay."""
    return results_pages.BLOCK.sub(lambda m: m['open'] + m['close'], text)


def _is_command(line: str) -> bool:
    return not line.strip() or line.lstrip().startswith(COMMAND_WORDS)


def _quoted_output_blocks(text: str) -> list[str]:
    """The first line of every fenced output block outside the generated markers."""
    out, block = [], None
    for line in _without_generated_bodies(text).splitlines():
        if line.lstrip().startswith('```'):
            if block is None:
                block = []
                continue
            if not all(_is_command(b) for b in block):
                out.append(next(b for b in block if b.strip()).strip())
            block = None
        elif block is not None:
            block.append(line)
    return out


def _named_json(page: Path) -> set[str]:
    """The JSON files a page names, as paths from the repository root: `--json PATH` (a command
    runs from the root) and each generated marker's file (relative to the page)."""
    text = _without_generated_bodies(page.read_text(encoding='utf-8'))
    names = set(JSON_OPTION.findall(text))
    rel = page.parent.relative_to(ROOT)
    names |= {str(rel / p) for p in MARKER_JSON.findall(text)}
    return {n for n in names if not PLACEHOLDER.search(n)}


def test_no_output_is_quoted_by_hand_but_the_listed_blocks():
    """No fenced output block stands outside a `<!-- generated: ... -->` marker unless QUOTED
    lists it. A fenced block is output unless each of its non-blank lines starts with one of
    COMMAND_WORDS (`python ...`, `make ...`, `ros2 ...`, a `#` comment), which makes it a
    block of commands; indented blocks are commands by the pages' convention and not read."""
    unlisted, unused = [], list(QUOTED)
    for page in _pages():
        for first in _quoted_output_blocks(page.read_text(encoding='utf-8')):
            entry = next((q for q in unused if q[0] == page.name and first.startswith(q[1])), None)
            if entry is None:
                unlisted.append(f'{page.name}: {first[:80]}')
            else:
                unused.remove(entry)
    assert unlisted == [], 'output quoted by hand; make it a generated block'
    assert unused == [], 'QUOTED lists a block the pages no longer quote; remove it'


def test_every_json_a_page_names_exists():
    """Every `--json PATH` on a results page and every JSON a generated marker names is a file
    in the repository, unless it is a placeholder (a file name in capitals: `NAME.json`) or
    AWAITED. A `--json` path outside docs/results/data/ (e.g. out/) is not committed, so it
    must be a placeholder."""
    missing, outside = set(), set()
    for page in _pages():
        for name in _named_json(page):
            if not (ROOT / name).is_file() and name not in AWAITED:
                missing.add(f'{page.name}: {name}')
            if not name.startswith('docs/results/data/'):
                outside.add(f'{page.name}: {name}')
    assert missing == set()
    assert outside == set()
    named = set().union(*(_named_json(page) for page in _pages()))
    assert {a for a in AWAITED if (ROOT / a).is_file() or a not in named} == set(), \
        'AWAITED lists a file that exists or that no page names; remove it'


def test_the_rules_read_a_page_as_meant():
    page = ('x\n```text\nout 1\n```\n```\npython -m a --json docs/results/data/a.json\n'
            '# c\n\nmake test\n```\n<!-- generated: text m:f data/b.json -->\n```text\n'
            'gen --json nowhere.json\n```\n<!-- end generated -->\nsee `--json` and '
            '`--json docs/results/data/NAME.json`\n')
    assert _quoted_output_blocks(page) == ['out 1']
    text = _without_generated_bodies(page)
    assert 'nowhere' not in text
    assert set(JSON_OPTION.findall(text)) == {'docs/results/data/a.json',
                                              'docs/results/data/NAME.json'}
    assert MARKER_JSON.findall(text) == ['data/b.json']
    assert PLACEHOLDER.search('docs/results/data/NAME.json')
    assert not PLACEHOLDER.search('docs/results/data/table_4_1.json')
