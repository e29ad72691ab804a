"""Batch pseudo-inverse and the recursive Kalman filter (filterpy)."""
import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from coop_id.estimators import (
    EstimationError,
    RankDeficientError,
    RecursiveEstimator,
    batch_estimate,
)


def _problem(seed=0, m=600, n=5, noise=0.01):
    rng = np.random.default_rng(seed)
    scale = np.array([1.0, 0.01, 100.0, 3000.0, 0.3])[:n]
    a = rng.normal(size=(m, n)) / scale
    x = rng.uniform(0.5, 1.5, size=n) * scale
    y = a @ x + noise * rng.normal(size=m)
    return a, x, y, scale


def test_batch_recovers_exactly_without_noise():
    a, x, y, scale = _problem(noise=0.0)
    res = batch_estimate(a, y, scale=scale)
    np.testing.assert_allclose(res.x, x, rtol=1e-9)
    assert res.rank == 5


def test_rank_deficient_window_flagged_not_solved():
    a, _x, y, scale = _problem()
    a[:, 2] = 0.0
    with pytest.raises(RankDeficientError) as info:
        batch_estimate(a, y, scale=scale)
    null = info.value.null_space[:, 0]
    assert abs(null[2]) / np.linalg.norm(null) > 0.999 and info.value.rank == 4


def test_kalman_matches_batch_and_keeps_covariance_symmetric():
    a, x, y, scale = _problem(noise=0.05)
    kf = RecursiveEstimator(x0=np.zeros(5), std0=1e4 * scale, scale=scale, n_rows=3)
    for i in range(0, 600, 3):
        kf.update(a[i:i + 3], y[i:i + 3], np.full(3, 0.05 ** 2))
        assert kf.kf.x.shape == (5, 1)        # the filterpy pitfall is guarded
    res = batch_estimate(a, y, scale=scale)
    np.testing.assert_allclose(kf.x, res.x, rtol=1e-4)
    assert np.allclose(kf.cov, kf.cov.T)
    assert np.all(np.linalg.eigvalsh(kf.cov_scaled) > 0)
    # 95 % interval of the KF covers the truth for most parameters at this noise level
    std = np.sqrt(np.diag(kf.cov))
    assert np.mean(np.abs(kf.x - x) < 1.96 * std) >= 0.6


def test_filterpy_pitfall_is_real():
    # documents why RecursiveEstimator always passes a column vector
    kf = KalmanFilter(dim_x=3, dim_z=2)
    kf.x = np.zeros((3, 1))
    kf.update(np.array([1.0, 2.0]), H=np.eye(2, 3), R=np.eye(2))
    assert kf.x.shape != (3, 1)


def test_bad_rows_rejected():
    kf = RecursiveEstimator(x0=np.zeros(2), std0=np.ones(2), scale=np.ones(2), n_rows=1)
    with pytest.raises(EstimationError):
        kf.update(np.array([[np.nan, 1.0]]), np.array([1.0]), np.array([1.0]))
    with pytest.raises(EstimationError):
        kf.update(np.ones((1, 2)), np.array([1.0]), np.array([0.0]))
    assert kf.updates == 0


def test_drift_lets_the_filter_follow_a_step():
    rng = np.random.default_rng(3)
    kf = RecursiveEstimator(x0=np.zeros(1), std0=np.ones(1), scale=np.ones(1), n_rows=1,
                            drift_per_s=0.05)
    for k in range(400):
        truth = 1.0 if k < 200 else 1.2
        h = rng.normal(size=(1, 1))
        kf.predict(0.01)
        kf.update(h, h[:, 0] * truth + 0.01 * rng.normal(size=1), np.array([1e-4]))
    assert abs(kf.x[0] - 1.2) < 0.02


def test_batched_update_equals_sequential_filterpy_updates():
    """One compressed update of a window's rows = the 18-row filterpy updates one after the
    other (the identifier's window: 20 instants x 18 rows, R per row, ill-scaled columns)."""
    rng = np.random.default_rng(7)
    n, per, k = 22, 18, 20
    scale = np.exp(rng.uniform(np.log(0.01), np.log(3000.0), size=n))
    x_true = rng.uniform(0.2, 1.0, size=n) * scale
    a = rng.normal(size=(k * per, n)) / scale * np.exp(rng.uniform(-3, 3, size=n))
    r = np.tile(np.exp(rng.uniform(-4, 1, size=6)), k * per // 6)
    y = a @ x_true + np.sqrt(r) * rng.normal(size=k * per)
    kw = dict(x0=0.5 * scale, std0=scale / np.sqrt(12.0), scale=scale, n_rows=per)
    seq, bat = RecursiveEstimator(**kw), RecursiveEstimator(**kw)
    # a filterpy filter driven by hand, row blocks in sequence (the reference)
    ref = KalmanFilter(dim_x=n, dim_z=per)
    ref.x, ref.P = (0.5 * np.ones(n)).reshape(n, 1), np.eye(n) / 12.0
    for _ in range(2):                       # two windows: the second starts from a posterior
        for i in range(0, k * per, per):
            seq.update(a[i:i + per], y[i:i + per], r[i:i + per])
            ref.update(y[i:i + per].reshape(-1, 1), R=np.diag(r[i:i + per]),
                       H=a[i:i + per] * scale)
        x_before, p_before = bat.kf.x[:, 0].copy(), bat.kf.P.copy()
        innov, s_diag = bat.update_batch(a, y, r)
        h = a * scale
        np.testing.assert_allclose(innov, y - h @ x_before, rtol=1e-12)
        np.testing.assert_allclose(s_diag, np.diag(h @ p_before @ h.T) + r, rtol=1e-10)
        np.testing.assert_allclose(bat.kf.x[:, 0], ref.x[:, 0], rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(bat.x, seq.x, rtol=1e-7, atol=1e-10 * scale.max())
        np.testing.assert_allclose(bat.cov_scaled, ref.P, rtol=1e-6, atol=1e-14)
        np.testing.assert_allclose(bat.cov_scaled, seq.cov_scaled, rtol=1e-6, atol=1e-14)
    assert np.allclose(bat.cov_scaled, bat.cov_scaled.T, rtol=0, atol=0)
    assert bat.updates == 2 and seq.updates == 2 * k


def test_batched_update_with_fewer_rows_than_states():
    """k < n rows (a short call): the QR keeps k compressed rows, still exact."""
    rng = np.random.default_rng(8)
    n = 5
    scale = np.ones(n)
    a, y, r = rng.normal(size=(3, n)), rng.normal(size=3), np.array([0.1, 0.2, 0.3])
    seq = RecursiveEstimator(x0=np.zeros(n), std0=np.ones(n), scale=scale, n_rows=3)
    bat = RecursiveEstimator(x0=np.zeros(n), std0=np.ones(n), scale=scale, n_rows=3)
    seq.update(a, y, r)
    bat.update_batch(a, y, r)
    np.testing.assert_allclose(bat.x, seq.x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(bat.cov, seq.cov, rtol=1e-10, atol=1e-12)
    with pytest.raises(EstimationError):
        bat.update_batch(a, y, np.array([0.1, 0.0, 0.3]))


def test_per_state_drift_and_explicit_process_noise():
    kf = RecursiveEstimator(x0=np.zeros(3), std0=np.ones(3), scale=np.ones(3), n_rows=1,
                            drift_per_s=np.array([0.1, 0.0, 0.2]))
    np.testing.assert_allclose(np.diag(kf.process_noise(4.0)), [0.04, 0.0, 0.16])
    kf.predict(4.0)
    np.testing.assert_allclose(np.diag(kf.cov), [1.04, 1.0, 1.16])
    q = np.zeros((3, 3))
    q[0, 0] = q[2, 2] = q[0, 2] = q[2, 0] = 0.5            # one direction only
    kf.predict(1.0, q)
    np.testing.assert_allclose(kf.cov[[0, 2], [0, 2]], [1.54, 1.66])
    assert kf.cov[0, 2] == 0.5 and kf.cov[1, 1] == 1.0
    for bad in (np.eye(2), -np.eye(3), np.triu(np.ones((3, 3)))):
        with pytest.raises(EstimationError):
            kf.predict(1.0, bad)
    with pytest.raises(EstimationError):
        RecursiveEstimator(x0=np.zeros(3), std0=np.ones(3), scale=np.ones(3), n_rows=1,
                           drift_per_s=np.array([0.1, -0.1, 0.0]))
