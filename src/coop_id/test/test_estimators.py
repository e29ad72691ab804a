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
    a, x, y, scale = _problem()
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
