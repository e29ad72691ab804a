"""Excitation: Eq. 2-21, limits, prediction and the LM optimiser (Eq. 2-16 .. 2-20)."""
import numpy as np
import pytest

from coop_common.dynparams import load_truth
from coop_id.excitation import (
    CostContext,
    ExcitationBounds,
    ExcitationError,
    WindowPredictor,
    constant_excitation,
    optimise,
    residuals,
)
from coop_id.model import ArmModel, load_prior_ranges


def test_constant_is_eq_2_21():
    e = constant_excitation()
    f, fd, fdd = e(1.0)
    assert f == pytest.approx(np.pi / 4 + 2 * np.pi / 9 * np.sin(np.pi / 2))
    assert fd == pytest.approx(2 * np.pi / 9 * np.pi / 2 * np.cos(np.pi / 2), abs=1e-12)


def test_feasible_respects_joint_limits():
    b = ExcitationBounds()
    for d in ([5.0, 30.0, 1.0], [1.2, 10.0, -1.0], [0.01, 0.1, 3.0]):
        a, w, a0 = b.feasible(np.array(d))
        lim = b.limits
        assert abs(a0) + a <= lim.position_rad + 1e-12
        assert a * w <= lim.speed_rad_s + 1e-12 and a * w * w <= lim.accel_rad_s2 + 1e-9
        assert b.frequency[0] <= w <= b.frequency[1]


def _ctx():
    rng = load_prior_ranges()
    scale = rng[:, 1] - rng[:, 0]
    x = rng.mean(axis=1)
    return CostContext(x=x, info_scaled=np.eye(22) * 12.0, scale=scale, ranges=rng,
                       row_var=np.full(6, 1e-2))


def test_predictor_rows_scale_with_excitation():
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(20) * 0.02)
    x = load_truth().to_vector()
    small = pred.rows(x, np.array([0.05, 5.0, 0.0]))
    big = pred.rows(x, np.array([0.5, 5.0, 0.0]))
    assert small.shape == (60, 6, 22)
    assert np.linalg.norm(big) > 5 * np.linalg.norm(small)


@pytest.mark.parametrize('strategy', ['information', 'condition', 'd_optimal', 'a_optimal'])
def test_optimiser_never_worsens_the_cost(strategy):
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(20) * 0.02)
    ctx = _ctx()
    start = constant_excitation()
    r0 = residuals(strategy, start.d, pred, ctx)
    exc, v = optimise(strategy, start, pred, ctx, iterations=2)
    assert v <= 0.5 * float(r0 @ r0) + 1e-12
    b = ExcitationBounds()
    np.testing.assert_allclose(b.feasible(exc.d), exc.d)


def test_unknown_strategy_rejected():
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(4) * 0.02)
    with pytest.raises(ExcitationError):
        residuals('random', np.array([0.3, 2.0, 0.0]), pred, _ctx())
