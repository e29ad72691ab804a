"""The thesis scenario at reduced size: the information strategy beats the constant one."""
import numpy as np
import pytest

from coop_common.dynparams import PARAM_NAMES, load_truth
from coop_id.experiment import mass_step_tracking, reference_noise_scales, run_identification
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
    """Issue #3 item 5: after the estimate has converged (8 s) the rover picks up a rock of
    +20 % of its mass. With the mass drifting (random walk 1 % of its range per sqrt(s)) every
    published mass from 2 s after the step on is within 5 % of the new mass, in every seed, and
    nothing else wanders (mean error of all parameters <= 10 % there). Without drift the mass
    stays 7-19 % low; with every parameter walking (the code before) it ran away."""
    truth, scales = scenario
    runs = mass_step_tracking(truth, seeds=[0, 1, 2, 3, 4], scales=scales,
                              config_factory=lambda: IdentifierConfig(drift_per_s=0.01))
    for r in runs:
        mass_err, mean_err = r.worst_after(2.0)
        assert mass_err <= 0.05, (r.seed, mass_err)
        assert mean_err <= 0.10, (r.seed, mean_err)


def test_drift_config_validated():
    for bad in (dict(drift_per_s=-0.1), dict(drift_per_s=float('nan')),
                dict(drift_parameters=('mass', 'rock')), dict(drift_horizon_s=0.4)):
        with pytest.raises(IdentifierError):
            Identifier(IdentifierConfig(**bad))


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


def test_a_duration_without_a_window_is_refused(scenario):
    truth, scales = scenario
    with pytest.raises(ValueError, match='holds no 0.4 s identification window'):
        run_identification(truth, strategy='information', seed=0, duration_s=0.1, noise=0.1,
                           scales=scales)


@pytest.mark.parametrize('args, reason', [
    (['--drift-parameters', 'mass,weight'], "unknown ['weight']"),
    (['--step', '20', '--duration', '14'], 'must come before the end'),
    (['--fraction', '-1'], '--fraction: -1.0 must be > -1.0'),
    (['--strategy', 'magic'], "invalid choice: 'magic'"),
    (['--duration', 'nan'], "'nan' is not finite"),
])
def test_mass_step_cli_refuses_before_any_run(capsys, args, reason):
    from coop_common.testing import usage_error
    from coop_id.experiment import main
    assert reason in usage_error(main, args, capsys)
