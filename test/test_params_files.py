"""Every parameter file in the repository is keyed so that it still applies under a namespace
(`/**/node:` or `/**:`): a file keyed `node:` is silently ignored by a namespaced node."""
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
FILES = sorted(p for p in ROOT.glob('src/*/**/*.yaml')
               if 'ros__parameters' in p.read_text(encoding='utf-8'))


def test_there_are_parameter_files():
    assert FILES


@pytest.mark.parametrize('path', FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_keyed_for_any_namespace(path):
    data = yaml.safe_load(path.read_text(encoding='utf-8'))
    for key, body in data.items():
        assert key == '/**' or key.startswith('/**/'), f'{path}: {key!r} is not /**/<node>'
        assert 'ros__parameters' in body, f'{path}: {key!r} has no ros__parameters'
