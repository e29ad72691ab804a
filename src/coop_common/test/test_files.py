import json

import pytest

from coop_common.files import save_figure, write_json, write_text_atomic


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


def test_save_figure_writes_atomically_and_closes(tmp_path):
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots()
    ax.plot([0, 1], [0, 1])
    path = save_figure(fig, tmp_path / 'sub' / 'f.png', dpi=50)
    assert path.read_bytes()[:8] == b'\x89PNG\r\n\x1a\n'
    assert not plt.fignum_exists(fig.number)
    assert [p.name for p in path.parent.iterdir()] == ['f.png']     # no temporary left


def test_written_files_get_plain_open_permissions(tmp_path):
    """Not mkstemp's 0600: a new file gets 0666 less the umask, a replaced one keeps its mode."""
    import os

    from coop_common.files import _UMASK, write_text_atomic
    p = write_text_atomic(tmp_path / 'a.txt', 'x')
    assert p.stat().st_mode & 0o777 == 0o666 & ~_UMASK
    os.chmod(p, 0o640)
    write_text_atomic(p, 'y')
    assert p.stat().st_mode & 0o777 == 0o640 and p.read_text() == 'y'
    assert sorted(x.name for x in tmp_path.iterdir()) == ['a.txt']     # no temporary left
