"""docs/results pages are what the code makes of the committed JSON (tools/results_pages.py)."""
from __future__ import annotations

import importlib.util
import json
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
