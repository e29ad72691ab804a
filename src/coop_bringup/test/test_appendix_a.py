"""appendix_a on short runs: the feed-forward on the identified model takes most of the
first drive step's jolt off the card, and the tip-over limiter keeps the true zero-moment
point inside the footprint on swings that leave it when run as planned."""
from __future__ import annotations

from pathlib import Path

import pytest
from coop_bringup.appendix_a import (
    SETTLE,
    format_json,
    identified_parameters,
    nominal_parameters,
    run,
    run_tipover,
    score,
)

REPO = Path(__file__).resolve().parents[3]
IDENTIFIED = REPO / 'docs' / 'results' / 'data' / 'table_2_1_sim.json'


def test_the_identified_feedforward_takes_the_drive_steps_jolt_off_the_card():
    ident, unobserved = identified_parameters(IDENTIFIED)
    assert set(unobserved) <= {'Izz'}
    length = SETTLE[1] + 1.0                              # the settle, then the first step
    errs = {v: score('driving', **{k: r[k] for k in ('t', 'error')})
            for v, r in (('none', run('none', 'driving', nominal_parameters(), seed=1,
                                      duration_s=length)),
                         ('identified', run('identified', 'driving', ident, seed=1,
                                            duration_s=length)))}
    assert errs['identified']['rms'] < 0.6 * errs['none']['rms']


def test_the_limiter_keeps_the_true_zmp_inside_where_the_plan_leaves():
    res = run_tipover(seed=1, identified=IDENTIFIED, motions=2)
    assert res['left_without'] >= 1
    assert res['left_with'] == 0 and res['min_margin_with'] > 0.0
    assert 'tip-over' in format_json({'tipover': res})


def test_a_missing_identification_is_a_clear_error(tmp_path):
    with pytest.raises(ValueError, match="no 'information' estimates"):
        identified_parameters(tmp_path / 'none.json')
