"""The thesis scenario at reduced size: the information strategy beats the constant one."""
import numpy as np
import pytest

from coop_common.dynparams import PARAM_NAMES, load_truth
from coop_id.experiment import reference_noise_scales, run_identification
from coop_id.identifier_core import Identifier, IdentifierConfig, IdentifierError
from coop_id.model import IDX, TRANSLATIONAL
from coop_id.table_2_1 import rel_errors


@pytest.fixture(scope='module')
def scenario():
    truth = load_truth()
    return truth, reference_noise_scales(truth, 4.0)


def test_information_beats_constant_and_stays_consistent(scenario):
    truth, scales = scenario
    x = truth.to_vector()
    errs = {}
    for s in ('constant', 'information'):
        r = run_identification(truth, strategy=s, seed=11, duration_s=4.0, noise=0.1,
                               scales=scales)
        errs[s] = rel_errors(r.estimates[-1], x).mean()
        assert all(r.consistent)
    assert errs['information'] < 0.3
    assert errs['information'] < 0.5 * errs['constant']


def test_without_accelerometer_reports_translational_unobservable(scenario):
    truth, scales = scenario
    x = truth.to_vector()
    r = run_identification(truth, strategy='information', seed=2, duration_s=3.2, noise=0.1,
                           scales=scales, config=IdentifierConfig(accelerometer=False))
    for n in TRANSLATIONAL:
        assert not r.observable[IDX[n]], n
    for n in ('k_pitch', 'k_roll', 'b_pitch', 'cg_y', 'cg_z'):
        i = PARAM_NAMES.index(n)
        assert r.observable[i] and abs(r.estimates[-1][i] - x[i]) < 0.1 * abs(x[i]), n


def test_mass_step_is_followed(scenario):
    truth, scales = scenario
    cfg = IdentifierConfig(drift_per_s=0.02)
    r = run_identification(truth, strategy='information', seed=4, duration_s=10.0, noise=0.1,
                           scales=scales, config=cfg, mass_step=(4.0, 0.6))
    m = np.stack(r.estimates)[:, IDX['mass']]
    t = r.times
    before = m[(t > 2.0) & (t <= 4.0)].mean()
    after = m[t > 8.0].mean()
    # the estimate moves towards the new mass (3.6 kg); how far it gets in 6 s is reported
    # honestly in the README (mass is the weakest-observed parameter at 10 % noise)
    assert after - before > 0.15


def test_bad_config_rejected():
    with pytest.raises(IdentifierError):
        Identifier(IdentifierConfig(strategy='magic'))


def test_bias_compensation_removes_errors_in_variables_bias(scenario):
    truth, scales = scenario
    x = truth.to_vector()
    err = {}
    for bc in (False, True):
        r = run_identification(truth, strategy='information', seed=5, duration_s=4.0,
                               noise=0.1, scales=scales, bias_compensation=bc)
        err[bc] = rel_errors(r.estimates[-1], x)
        assert all(r.consistent)
    # stiffness x/y/z are attenuated by the integrated accelerometer noise without it
    k = [list(np.flatnonzero(x != 0)).index(IDX[n]) for n in ('k_x', 'k_y', 'k_z')]
    assert err[True][k].mean() < err[False][k].mean()
    assert err[True].mean() < err[False].mean()
