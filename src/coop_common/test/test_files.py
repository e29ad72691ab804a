import json

import pytest

from coop_common.files import write_json, write_text_atomic


def test_write_json_creates_parents_and_replaces(tmp_path):
    path = tmp_path / 'a' / 'b' / 'r.json'
    write_json(path, {'x': 1})
    write_json(path, {'x': 2})
    assert json.loads(path.read_text()) == {'x': 2}
    assert [p.name for p in path.parent.iterdir()] == ['r.json']     # no temporary left


def test_a_failed_write_keeps_the_old_file(tmp_path):
    path = tmp_path / 'r.json'
    write_text_atomic(path, 'old')
    with pytest.raises(TypeError):
        write_json(path, {'x': object()})
    assert path.read_text() == 'old'
    assert [p.name for p in tmp_path.iterdir()] == ['r.json']
