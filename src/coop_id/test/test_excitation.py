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
    f, fd, _fdd = e(1.0)
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
    r0 = residuals(start.d, pred, ctx, strategy=strategy)
    exc, v = optimise(start, pred, ctx, strategy=strategy, iterations=2)
    assert v <= 0.5 * float(r0 @ r0) + 1e-12
    b = ExcitationBounds()
    np.testing.assert_allclose(b.feasible(exc.d), exc.d)


def test_unknown_strategy_rejected():
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(4) * 0.02)
    with pytest.raises(ExcitationError):
        residuals(np.array([0.3, 2.0, 0.0]), pred, _ctx(), strategy='random')


def test_unknown_modes_are_refused_naming_the_allowed_values():
    from coop_id.excitation import ArmReference, residuals_batch
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(4) * 0.02)
    d = np.array([[0.3, 2.0, 0.0]])
    allowed = r"\['information', 'condition', 'd_optimal', 'a_optimal'\]"
    for bad in ('random', 'constant'):      # constant has no cost: refused, not A-optimal
        with pytest.raises(ExcitationError, match=f'strategy must be one of {allowed}'):
            residuals_batch(d, pred, _ctx(), strategy=bad)
    with pytest.raises(ExcitationError, match=r"strategy must be one of \['constant', "
                       r"'information', 'condition', 'd_optimal', 'a_optimal'\], got 'shake'"):
        optimise(constant_excitation(), pred, _ctx(), strategy='shake')
    ctx = _ctx()
    ctx.condition_matrix = 'eigen'
    with pytest.raises(ExcitationError, match=r"condition_matrix must be one of "
                       r"\['accumulated', 'window', 'unscaled'\], got 'eigen'"):
        residuals_batch(d, pred, ctx, strategy='condition')
    with pytest.raises(ExcitationError, match=r"\['arm_joint_1', 'arm_joint_2'\]"):
        ArmReference((('arm_joint_3', 0.0, None),))
    # 'constant' is a strategy of the optimiser: it keeps the excitation
    same, v = optimise(constant_excitation(), pred, _ctx(), strategy='constant')
    assert same == constant_excitation() and np.isnan(v)


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


def test_arm_reference_rest_blends_into_standing_still_at_home():
    from coop_id.excitation import ArmReference, Excitation
    from coop_id.identifier_node import MODES
    ref = ArmReference(MODES, speed_rad_s=1.5)
    home = np.array([0.1, -0.6])
    exc = Excitation(0.8, 6.0, 0.3)
    ref.update(0.0, 2, exc, 0.0, home, 1.2)
    t_rest = ref.rest(3.0, np.array([9.0, 9.0]), lead_s=0.1)    # `here` unused once started
    assert 3.1 + 0.2 <= t_rest < 3.1 + 1.875 * (0.8 + 0.3 + 1.0 + 0.7) / 1.5
    ts = np.arange(2.95, t_rest + 1.0, 0.001)   # (it holds from 50 ms before `now` on)
    q, qd = map(np.array, zip(*(ref(t) for t in ts), strict=False))
    assert np.abs(np.diff(q, axis=0)).max() < 0.01 and np.abs(np.diff(qd, axis=0)).max() < 0.1
    before = ts < 3.1           # the lead: the excitation goes on (tabulated at 1 ms)
    np.testing.assert_allclose(q[before][:, 1], [exc(t)[0] for t in ts[before]], atol=1e-6)
    after = ts >= t_rest
    np.testing.assert_allclose(q[after], np.broadcast_to(home, q[after].shape), atol=1e-12)
    np.testing.assert_allclose(qd[after], 0.0, atol=1e-12)
    # a reference never started rests where the arm is
    idle = ArmReference(MODES)
    idle.rest(0.0, home)
    np.testing.assert_allclose(idle(5.0)[0], home)


def test_closed_form_arm_kinematics_is_modelsim_s():
    from coop_id.excitation import _ModeKinematics
    from coop_id.modelsim import arm_kinematics
    arm = ArmModel()
    q, qd, qdd = np.random.default_rng(0).normal(size=(3, 5, 7, 3))
    ref, fast = arm_kinematics(arm, q, qd, qdd), _ModeKinematics(arm)(q, qd, qdd)
    for f in ('rho', 'rho_dd', 'omega', 'alpha', 'inertia'):
        np.testing.assert_allclose(getattr(fast, f), getattr(ref, f), atol=1e-14)


def test_batched_prediction_equals_one_candidate_at_a_time():
    from coop_id.excitation import residuals_batch
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(10) * 0.04, weight=2.0)
    x = load_truth().to_vector()
    d = np.array([[0.1, 30.0, 0.3], [0.5, 2.0, -0.5], [0.066, 30.0, 1.0]])
    batch = pred.rows_batch(x, d)
    ctx = _ctx()
    for k in range(3):
        np.testing.assert_array_equal(batch[k], pred.rows(x, d[k]))
        for s in ('information', 'condition', 'd_optimal', 'a_optimal'):
            np.testing.assert_allclose(residuals_batch(d, pred, ctx, strategy=s)[k],
                                       residuals(d[k], pred, ctx, strategy=s), rtol=1e-12)


def _lm_one_at_a_time(strategy, current, pred, ctx, iterations, starts, fd_step=0.02):
    """Eq. 2-16 .. 2-20 as written: one cost evaluation after the other (the reference)."""
    b = ExcitationBounds()

    def cost(u):
        r = residuals(b.feasible(b.from_unit(u)), pred, ctx, strategy=strategy)
        return 0.5 * float(r @ r), r
    best = None
    for d0 in (current.d, *starts):
        u0 = b.to_unit(b.feasible(np.asarray(d0, dtype=float)))
        v0, r0 = cost(u0)
        if best is None or v0 < best[1]:
            best = (u0, v0, r0)
    u, v, r = best
    mu = 1e-3
    for _ in range(iterations):
        jac = np.empty((r.size, 3))
        for k in range(3):
            du = np.zeros(3)
            du[k] = fd_step if u[k] + fd_step <= 1 else -fd_step
            jac[:, k] = (cost(u + du)[1] - r) / du[k]
        g, jtj = jac.T @ r, jac.T @ jac
        step = -np.linalg.solve(jtj + mu * (np.diag(np.diag(jtj)) + 1e-9 * np.eye(3)), g)
        moved = False
        for alpha in (1.0, 0.5, 0.25):
            u_new = np.clip(u + alpha * step, 0.0, 1.0)
            v_new, r_new = cost(u_new)
            if v_new < v:
                u, v, r, moved = u_new, v_new, r_new, True
                break
        mu = mu * 0.3 if moved else mu * 10.0
    return b.feasible(b.from_unit(u)), v


@pytest.mark.parametrize('strategy', ['information', 'condition', 'd_optimal', 'a_optimal'])
def test_grouped_lm_takes_the_one_at_a_time_iterates(strategy):
    from coop_id.excitation import Excitation
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(10) * 0.04, weight=2.0)
    rng = np.random.default_rng(3)
    for trial in range(3):
        ctx = _ctx()
        a = rng.normal(size=(200, 22))
        ctx.info_scaled = a.T @ a * 10 ** rng.uniform(0, 3) + 12.0 * np.eye(22)
        ctx.row_var = np.array([1, 1, 1, 0.1, 0.1, 0.1]) * 10.0 ** (trial - 1)
        cur = (constant_excitation(), Excitation(0.3, 5.0, 0.2), Excitation(0.1, 25.0, 0.5))[trial]
        starts = (np.array([0.6, 16.0, 0.5]),)
        exc, v = optimise(cur, pred, ctx, strategy=strategy, iterations=3, starts=starts)
        d_ref, v_ref = _lm_one_at_a_time(strategy, cur, pred, ctx, 3, starts)
        np.testing.assert_allclose(exc.d, d_ref, rtol=1e-9)
        assert v == pytest.approx(v_ref, rel=1e-9)


def test_condition_matrix_readings():
    from coop_id.excitation import residuals_batch
    pred = WindowPredictor(arm=ArmModel(), times=np.arange(10) * 0.04, weight=2.0)
    d = np.array([[0.1, 30.0, 0.3], [0.5, 2.0, -0.5]])
    out = {}
    for m in ('accumulated', 'window', 'unscaled'):
        ctx = _ctx()
        ctx.condition_matrix = m
        out[m] = residuals_batch(d, pred, ctx, strategy='condition')[:, 0]
    # SI columns span 0.01 .. 3000: the unscaled matrix is orders of magnitude worse
    assert np.all(out['unscaled'] > out['accumulated'] + 2)
    assert np.all(np.isfinite(out['window']))
    ctx = _ctx()
    ctx.condition_matrix = 'eigen'
    with pytest.raises(ExcitationError):
        residuals_batch(d, pred, ctx, strategy='condition')
