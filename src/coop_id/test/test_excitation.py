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


def test_arm_reference_never_steps_and_respects_the_blend_speed():
    from coop_id.excitation import ArmReference, Excitation
    from coop_id.identifier_node import MODES
    ref = ArmReference(MODES, speed_rad_s=1.5)
    here = np.array([0.0, -0.6])                        # the arm's home pose
    a = Excitation(0.5, 8.0, 0.4)
    b = Excitation(1.0, 2.0, -0.5)
    events = [(0.0, 0, a, 0.0), (0.4, 0, a, 0.0), (0.8, 0, b, 0.8), (1.2, 1, b, 0.8),
              (1.6, 2, b, 0.8), (2.0, 2, a, 2.0)]
    ts = np.arange(0.0, 5.0, 0.001)
    q, qd = [], []
    k = 0
    for t in ts:
        while k < len(events) and events[k][0] <= t + 1e-12:
            t_ev, mode, exc, t0 = events[k]
            ref.update(t_ev, mode, exc, t0, here, 1.2)
            k += 1
        p, v = ref(t)
        q.append(p)
        qd.append(v)
    q, qd = np.array(q), np.array(qd)
    np.testing.assert_allclose(q[0], here, atol=1e-12)            # starts where the arm is
    dq = np.abs(np.diff(q, axis=0)).max()
    assert dq < 0.01, dq                                          # no position step (1 ms)
    assert np.abs(np.diff(qd, axis=0)).max() < 0.1                # nor a speed step
    # the speeds it reports are the derivative of the positions
    np.testing.assert_allclose(qd[1:-1], (q[2:] - q[:-2]) / 0.002, atol=2e-3)
    # once a blend is over, the driven joint follows f(t) exactly (mode 2: joint 2, j1 = pi/2)
    t = 4.95
    np.testing.assert_allclose(ref(t)[0], [np.pi / 2, a(t - 2.0)[0]], atol=1e-12)
