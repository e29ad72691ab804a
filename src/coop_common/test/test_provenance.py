import subprocess

from coop_common.provenance import source_revision


def _git(cwd, *args):
    subprocess.run(['git', *args], cwd=cwd, check=True, capture_output=True,
                   env={'GIT_AUTHOR_NAME': 't', 'GIT_AUTHOR_EMAIL': 't@t',
                        'GIT_COMMITTER_NAME': 't', 'GIT_COMMITTER_EMAIL': 't@t',
                        'PATH': '/usr/bin:/bin'})


def test_revision_of_a_checkout_and_its_dirty_state(tmp_path):
    _git(tmp_path, 'init', '-q')
    (tmp_path / 'a.txt').write_text('1')
    _git(tmp_path, 'add', 'a.txt')
    _git(tmp_path, 'commit', '-q', '-m', 'one')
    head = subprocess.run(['git', 'rev-parse', 'HEAD'], cwd=tmp_path, check=True,
                          capture_output=True, text=True).stdout.strip()
    assert source_revision(tmp_path / 'a.txt') == head
    (tmp_path / 'b.txt').write_text('untracked files do not count')
    assert source_revision(tmp_path) == head
    (tmp_path / 'a.txt').write_text('2')
    assert source_revision(tmp_path) == f'{head}-dirty'


def test_no_checkout_gives_none(tmp_path):
    assert source_revision(tmp_path) is None
