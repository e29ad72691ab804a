"""Model core against analytic cases: noise-free data recovers the truth exactly."""
import numpy as np
import pytest

from coop_common.dynparams import PARAM_NAMES, load_truth
from coop_id.estimators import batch_estimate
from coop_id.model import (
    GRAVITY,
    IDX,
    FilterBank,
    ModelError,
    assemble_rows,
    filtered_rows,
    load_prior_ranges,
    raw_channels,
)
from coop_id.modelsim import ThesisRover, stack_frames


def _two_tone(t):
    # starts at rest (x = x' = 0), as the identifier assumes
    w1, w2 = 6.0, 19.0
    x = 0.01 * (1 - np.cos(w1 * t)) + 0.004 * (1 - np.cos(w2 * t))
    xd = 0.01 * w1 * np.sin(w1 * t) + 0.004 * w2 * np.sin(w2 * t)
    xdd = 0.01 * w1 ** 2 * np.cos(w1 * t) + 0.004 * w2 ** 2 * np.cos(w2 * t)
    rest = t < 0     # one sample at rest before the motion primes the filters
    return tuple(np.where(rest, 0.0, v) for v in (x, xd, xdd))


def test_single_axis_spring_mass_recovered_through_filter_bank():
    # m x'' + b x' + k x = -F_x: one translational axis, analytic motion from rest
    m, b, k = 2.5, 40.0, 900.0
    t = np.arange(-1, 1200) * 0.005
    x, xd, xdd = _two_tone(t)
    n = t.size
    spec = np.zeros((n, 3))
    spec[:, 0] = xdd
    spec[:, 2] = GRAVITY
    force = np.zeros((n, 3))
    force[:, 0] = -(m * xdd + b * xd + k * x)
    ch = raw_channels(specific_force=spec, gyro=np.zeros((n, 3)), incl_roll_pitch=np.zeros((n, 2)),
                      force=force, torque=np.zeros((n, 3)))
    a, y = filtered_rows(FilterBank(), ch)
    cols = [IDX['mass'], IDX['b_x'], IDX['k_x']]
    sol, *_ = np.linalg.lstsq(a[400:, 0, cols], y[400:, 0], rcond=None)
    np.testing.assert_allclose(sol, [m, b, k], rtol=1e-2)


def test_filter_bank_integrates_consistently():
    t = np.arange(-1, 1600) * 0.005
    x, _xd, xdd = _two_tone(t)
    bank = FilterBank()
    pos_from_acc = bank.apply('a', -2, xdd[:, None])
    pos = bank.apply('p', 0, x[:, None])
    # trapezoidal integration of a sampled analytic signal: agreement to O((w dt)^2) once the
    # start-up transient (acceleration step at t = 0, seen as a ramp by the sampler) has decayed
    late = t > 3.0
    assert np.max(np.abs(pos_from_acc - pos)[late]) < 1e-2 * np.max(np.abs(pos[late]))


def test_noise_free_thesis_scenario_recovers_all_22_exactly():
    truth = load_truth()
    xt = truth.to_vector()
    rover = ThesisRover(truth)
    frames = [rover.rest_frame()]
    for kk in range(1200):
        tt = (kk + 1) * 0.005
        w = 3.0 if tt < 3 else 14.0
        a = 0.3
        frames.append(rover.step((0.5 + a * np.sin(w * tt), a * w * np.cos(w * tt),
                                  -a * w * w * np.sin(w * tt))))
    d = stack_frames(frames)
    bank = FilterBank()
    rows, rhs = [], []
    for mo in range(3):
        ch = raw_channels(specific_force=d['specific_force'][:, mo], gyro=d['gyro'][:, mo],
                          incl_roll_pitch=d['incl'][:, mo], force=d['force'][:, mo],
                          torque=d['torque'][:, mo])
        a_, y_ = filtered_rows(bank, ch, tag=str(mo))
        rows.append(a_[200:].reshape(-1, 22))
        rhs.append(y_[200:].ravel())
    rng = load_prior_ranges()
    res = batch_estimate(np.vstack(rows), np.concatenate(rhs), scale=rng[:, 1] - rng[:, 0])
    nz = xt != 0
    rel = np.abs(res.x - xt)[nz] / np.abs(xt[nz])
    # exact up to the model's neglected second-order terms (theta x a, arm-base coupling)
    assert rel.max() < 5e-3, dict(zip(np.array(PARAM_NAMES)[nz], rel, strict=False))
    assert np.all(np.abs(res.x[~nz]) < 1e-3)


def test_rows_have_the_thesis_structure():
    n = 1
    rnd = np.random.default_rng(0)
    kw = {k: rnd.normal(size=(n, 3)) for k in ('acc', 'vel', 'pos', 'th', 'th_d', 'th_dd',
                                                'force', 'tilt_x_force', 'torque')}
    a, y = assemble_rows(gyro_reg=np.zeros((n, 18)), **kw)
    assert a.shape == (1, 6, 22) and y.shape == (1, 6)
    # translational rows see only mass, b_r, k_r; rotational rows never see them
    trans = [IDX[p] for p in ('mass', 'b_x', 'b_y', 'b_z', 'k_x', 'k_y', 'k_z')]
    assert np.all(a[0, 3:, trans] == 0)
    assert np.count_nonzero(a[0, :3]) == 9
    a2, _ = assemble_rows(gyro_reg=np.zeros((n, 18)), accelerometer=False, **kw)
    assert np.all(a2[0, :3] == 0)


def test_bad_shapes_rejected():
    with pytest.raises(ModelError):
        raw_channels(specific_force=np.zeros((3, 3)), gyro=np.zeros((3, 3)),
                     incl_roll_pitch=np.zeros((3, 3)), force=np.zeros((3, 3)),
                     torque=np.zeros((3, 3)))
    with pytest.raises(ModelError):
        FilterBank(highpass_rad_s=50.0, lowpass_rad_s=10.0)


def test_noise_gram_matches_monte_carlo():
    from coop_id.model import noise_gram
    bank = FilterBank()
    g = noise_gram(bank)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(20000, 1))
    outs = np.stack([FilterBank().apply('n', p, x)[2000:, 0] for p in (-2, -1, 0, 1)])
    emp = outs @ outs.T / outs.shape[1]
    np.testing.assert_allclose(np.diag(emp), np.diag(g), rtol=0.15)
    assert np.all(np.linalg.eigvalsh(g) > -1e-12)


def test_regressor_noise_structure():
    from coop_id.model import SensorNoise, noise_gram, regressor_noise
    g = noise_gram(FilterBank())
    sn = SensorNoise(np.full(3, 0.01), np.full(3, 0.001), np.full(2, 1e-4), np.full(3, 0.1))
    cov, cxy = regressor_noise(sn, g)
    assert cov.shape == (6, 22, 22) and cxy.shape == (6, 22)
    for r in range(6):
        assert np.allclose(cov[r], cov[r].T) and np.all(np.linalg.eigvalsh(cov[r]) > -1e-15)
    assert cov[0, IDX['mass'], IDX['mass']] > 0 and cov[3, IDX['mass'], IDX['mass']] == 0
    cov2, _ = regressor_noise(sn, g, accelerometer=False)
    assert np.all(cov2[:3] == 0)


def test_tilt_tracker_integrates_the_gyro_and_ignores_a_coarse_inclinometer():
    from coop_id.model import TiltTracker
    dt = 0.005
    t = np.arange(2000) * dt
    roll = 4e-4 * np.sin(6.0 * t) + 2e-4 * (1 - np.cos(1.0 * t))
    pitch = -3e-4 * np.sin(15.0 * t)
    gyro = np.column_stack([np.gradient(roll, dt), np.gradient(pitch, dt), np.zeros_like(t)])
    step = 6.8e-4                                  # 10 bits over +-20 deg
    incl = np.round(np.column_stack([roll, pitch]) / step) * step
    tr = TiltTracker(rate_hz=1 / dt)
    est = np.vstack([tr.update(gyro[i:i + 100], incl[i:i + 100]) for i in range(0, t.size, 100)])
    err = est - np.column_stack([roll, pitch])
    assert np.abs(err).max() < 0.25 * step          # the quantised reading alone: 0.5 step
    assert np.sqrt((err ** 2).mean()) < 0.1 * step
