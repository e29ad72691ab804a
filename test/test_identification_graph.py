"""One identification end to end over DDS (issue #3): the installed `rover_sim sim` and
`coop_id identifier` nodes, an `identify` goal (strategy information, 20 sim-s, 10 % sensor
noise) from this process, the result compared with the simulator's latched truth. The same path
as `coop_id table_2_1 --sim --lockstep` (coop_id.sim_mode): the simulator in lockstep with the
identifier and this client, as fast as they answer. At 10 s the
error through the graph scattered from 2.4 to 21.2 % over eleven runs (one CI failure at 21.2 %);
at 20 s from 2.1 to 3.7 % over four (docs/results/identification.md)."""
from __future__ import annotations

import os

import numpy as np
import pytest

from coop_common.dynparams import PARAM_NAMES
from rover_hw.figures import sim_line

pytestmark = pytest.mark.graph

DURATION_S = 20.0
RATE_HZ = 200.0


def test_information_identification_through_rover_sim_is_within_20_percent(tmp_path, figures):
    from coop_id.sim_mode import run_sim_identification
    r = run_sim_identification(duration_s=DURATION_S, strategy='information', noise=0.1,
                               domain_id=int(os.environ['ROS_DOMAIN_ID']), log_dir=tmp_path,
                               lockstep=True)
    est, std, truth = r['estimate'], r['std'], r['truth']
    table = '\n'.join(f'{p:8s} {truth[i]:9.4g} {est[i]:10.4g} +- {std[i]:.2g}'
                      for i, p in enumerate(PARAM_NAMES))
    kept = figures.add('ident_sim', {k: r[k] for k in ('message', 'samples',
                                                       'mean_abs_rel_error')})
    print(f'{sim_line(kept)}\n{table}')
    assert r['success'], r['message']
    # the node loses no sensor sample on the way (in lockstep every one is handed over)
    assert r['samples'] == DURATION_S * RATE_HZ + 1, r['samples']
    assert np.all(np.isfinite(est)) and np.all(np.isfinite(std))
    # Table 2-1's figure: mean abs. relative error over the 20 non-zero parameters (the
    # inertias alone scatter by +-30-50 % at 10 % noise in 10 s, unbiased since the rover_sim
    # fixes; the noise-free check of the inertias is src/coop_id/test/test_sim_residual.py)
    assert r['mean_abs_rel_error'] <= 0.20, table
