"""coop_common.figures: what a test records is what its results page is made from."""
from __future__ import annotations

import json

import numpy as np
import pytest

from coop_common.errors import CoopCommonError
from coop_common.figures import FigureLog, records


def test_records_keep_their_order_and_become_json_values(tmp_path):
    log = FigureLog()
    kept = log.add('rate', {'hz': np.float64(200.0), 'sigma': np.array([0.1, 0.2]),
                            'pair': (1, 2), 'nested': {'n': np.int64(3)}})
    log.add('rate', {'hz': 199.5})
    assert kept == {'hz': 200.0, 'sigma': [0.1, 0.2], 'pair': [1, 2], 'nested': {'n': 3}}
    assert type(kept['nested']['n']) is int
    data = json.loads(log.write(tmp_path / 'sub' / 'f.json').read_text())
    assert [r['hz'] for r in records(data, 'rate')] == [200.0, 199.5]
    assert 'source' in data


def test_a_value_json_cannot_hold_is_refused_with_where_it_is():
    with pytest.raises(CoopCommonError, match=r'rate\.when: object'):
        FigureLog().add('rate', {'when': object()})
    with pytest.raises(CoopCommonError, match='key'):
        FigureLog().add('', {})


def test_a_page_asking_for_records_the_run_did_not_make_is_told_what_it_holds():
    with pytest.raises(CoopCommonError, match=r"no 'fuzz' records .* \['rate'\]"):
        records({'records': {'rate': []}}, 'fuzz')
