"""Observability metrics: Eq. 2-5 rank test and the Eq. 2-12 mutual information."""
import numpy as np
import pytest

from coop_id.information import (
    InformationError,
    mutual_information_bits,
    observability_matrix,
    rank_test,
)


def test_information_limits_for_a_10_bit_sensor():
    lo, hi = np.zeros(3), np.ones(3)
    zero = mutual_information_bits(np.full(3, 0.4), np.zeros(3), lo, hi, bits=10)
    np.testing.assert_allclose(zero, 10.0)
    wide = mutual_information_bits(np.full(3, 0.5), np.full(3, 50.0), lo, hi, bits=10)
    assert np.all(wide < 0.01)
    # a Gaussian 1 bin wide carries about n - log2(sqrt(2 pi e) sigma / bin) bits
    sig = 8.0 / 1024
    mid = mutual_information_bits(np.array([0.5]), np.array([sig]), lo[:1], hi[:1], bits=10)
    expect = 10 - np.log2(np.sqrt(2 * np.pi * np.e) * sig * 1024)
    assert abs(mid[0] - expect) < 0.05


def test_information_decreases_with_noise_and_bits_scale():
    stds = np.array([1e-4, 1e-3, 1e-2, 1e-1])
    info = mutual_information_bits(np.full(4, 0.5), stds, np.zeros(4), np.ones(4), bits=10)
    assert np.all(np.diff(info) < 0)
    b8 = mutual_information_bits(np.array([0.5]), np.array([0.0]), np.zeros(1), np.ones(1),
                                 bits=8)
    assert b8[0] == pytest.approx(8.0)


def test_rank_test_finds_the_unobservable_direction():
    # x_k+1 = x_k (constant parameters), H sees x0 + x1 and x2 only: x0 - x1 is unobservable
    phi = np.eye(3)
    h = np.array([[1.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    rank, full, null = rank_test(observability_matrix(phi, h))
    assert rank == 2 and not full
    v = null[:, 0] / np.linalg.norm(null[:, 0])
    assert abs(abs(v @ np.array([1, -1, 0]) / np.sqrt(2)) - 1) < 1e-9
    # a rotating state model makes it observable (Eq. 2-5 with Phi != I)
    phi2 = np.array([[1, 0.1, 0], [0, 1, 0], [0, 0, 1.0]])
    assert rank_test(observability_matrix(phi2, h[:1]), rtol=1e-12)[0] == 2


def test_bad_arguments():
    with pytest.raises(InformationError):
        mutual_information_bits(np.zeros(2), np.ones(2), np.ones(2), np.zeros(2))
    with pytest.raises(InformationError):
        mutual_information_bits(np.zeros(1), -np.ones(1), np.zeros(1), np.ones(1))


def _information_all_bins(mean, std, lo, hi, bits):
    """Eq. 2-12 literally: every one of the 2^n bins summed (each bin's mass computed on the
    side of the mean where the normal CDF does not cancel)."""
    from scipy.special import ndtr
    out = np.zeros(mean.size)
    for i in range(mean.size):
        t = (lo[i] + (hi[i] - lo[i]) * np.linspace(0.0, 1.0, 2 ** bits + 1) - mean[i]) / std[i]
        q = np.where(t[:-1] >= 0, ndtr(-t[:-1]) - ndtr(-t[1:]), ndtr(t[1:]) - ndtr(t[:-1]))
        if q.sum() <= 1e-300:
            out[i] = bits
            continue
        q = q[q > 0] / q.sum()
        out[i] = bits + np.sum(q * np.log2(q))
    return np.clip(out, 0, bits)


@pytest.mark.parametrize('bits', [10, 4])
def test_information_matches_the_sum_over_every_bin(bits):
    """Closed form + windowed sums = the literal 2^n-bin sum, posteriors from far narrower than
    a bin to far wider than the range, mean inside, at and far outside the range."""
    rng = np.random.default_rng(1)
    n = 3000
    lo = rng.uniform(-1, 1, n)
    w = 10 ** rng.uniform(-2, 3, n)
    mean = lo + w * rng.uniform(-0.5, 1.5, n)
    std = w * 10 ** rng.uniform(-5, 1.5, n)
    fast = mutual_information_bits(mean.reshape(60, 50), std.reshape(60, 50),
                                   lo.reshape(60, 50), (lo + w).reshape(60, 50), bits=bits)
    assert fast.shape == (60, 50)
    ref = _information_all_bins(mean, std, lo, lo + w, bits)
    np.testing.assert_allclose(fast.ravel(), ref, atol=3e-4, rtol=0)
    # a posterior 10 std beyond the upper or lower edge is still resolved near that edge
    edge = mutual_information_bits(np.array([-0.3, 1.3]), np.array([0.03, 0.03]), np.zeros(2),
                                   np.ones(2), bits=bits)
    np.testing.assert_allclose(edge, _information_all_bins(np.array([-0.3, 1.3]),
                                                           np.array([0.03, 0.03]), np.zeros(2),
                                                           np.ones(2), bits), atol=3e-4)
