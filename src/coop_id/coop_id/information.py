"""Observability metrics of §2.4 (no rclpy): the classical rank test (Eq. 2-5) and the
per-parameter mutual information of an n-bit 'sensor' (Eq. 2-6 .. 2-12)."""
from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from .errors import CoopIdError


class InformationError(CoopIdError):
    """Bad arguments to an information metric."""


def observability_matrix(phi: np.ndarray, h: np.ndarray, steps: int | None = None) -> np.ndarray:
    """Xi^T of Eq. 2-5: rows H, H Phi, ..., H Phi^(steps-1) (steps defaults to n)."""
    phi = np.asarray(phi, dtype=float)
    h = np.atleast_2d(np.asarray(h, dtype=float))
    n = phi.shape[0]
    if phi.shape != (n, n) or h.shape[1] != n:
        raise InformationError(f'Phi must be (n, n) and H (m, n); got {phi.shape}, {h.shape}')
    steps = n if steps is None else steps
    blocks, cur = [], h
    for _ in range(steps):
        blocks.append(cur)
        cur = cur @ phi
    return np.vstack(blocks)


def rank_test(xi: np.ndarray, *, rtol: float = 1e-9, scale: np.ndarray | None = None
              ) -> tuple[int, bool, np.ndarray]:
    """Eq. 2-5: rank of the stacked measurement matrix, whether it is full (observable) and the
    unobservable directions (columns; in the unscaled parameter space)."""
    xi = np.asarray(xi, dtype=float)
    if xi.ndim != 2:
        raise InformationError('need a 2-D matrix')
    n = xi.shape[1]
    sc = np.ones(n) if scale is None else np.asarray(scale, dtype=float)
    _, s, vt = np.linalg.svd(xi * sc, full_matrices=True)
    rank = int(np.sum(s > rtol * s[0])) if s.size and s[0] > 0 else 0
    null = (vt[rank:] * sc).T
    return rank, rank == n, null


def mutual_information_bits(mean: np.ndarray, std: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                            *, bits: int = 10) -> np.ndarray:
    """In(x, y) = H(x) - H(x|y) per parameter (Eq. 2-8, 2-12), in bits (any array shape).

    H(x) = n bits: a uniform prior over 2^n bins of [lo, hi] (Eq. 2-12a with p_i = 1/2^n).
    H(x|y) = -sum q_i log2 q_i with q_i the Gaussian posterior N(mean, std) (Eq. 2-11) mass in
    bin i, normalised over [lo, hi] (Eq. 2-12b). n bits when std -> 0; ~0 when the posterior is
    as wide as the range.

    Evaluated without summing 2^n bins: where the normalised posterior is smooth on the scale of
    a bin (its length scale, std, or std / (distance outside the range in std) when the mean
    lies outside, is >= 2 bins), the bin sum is, to O(bin^4), the entropy of the truncated
    normal on [lo, hi] minus log2(bin) plus bin^2 J / 24 nats, J its Fisher information (the
    midpoint-rule boundary terms cancel; lo and hi are bin edges, so no bin straddles the
    truncation). Otherwise the bins are summed exactly, only the ~100 at most that hold all but
    1e-18 of the mass. Agrees with the sum over all 2^n bins to < 3e-4 bits (test_information).
    """
    mean, std, lo, hi = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (mean, std, lo, hi))
    if not (mean.shape == std.shape == lo.shape == hi.shape):
        raise InformationError('mean, std, lo, hi must have the same shape')
    if not (1 <= bits <= 16):
        raise InformationError('bits must be in 1..16')
    if np.any(std < 0) or np.any(hi <= lo) or not np.all(np.isfinite(mean)):
        raise InformationError('need std >= 0, hi > lo, finite mean')
    shape = mean.shape
    mean, std, lo, hi = (v.ravel() for v in (mean, std, lo, hi))
    nb = 2 ** bits
    width = hi - lo
    bin_w = width / nb
    out = np.full(mean.shape, float(bits))
    known = std <= width * 1e-9                    # a point mass: n bits
    unknown = ~np.isfinite(std)
    out[unknown] = 0.0
    calc = np.flatnonzero(~(known | unknown))
    if calc.size == 0:
        return out.reshape(shape)
    m, sd, a_, w_, bw = mean[calc], std[calc], lo[calc], width[calc], bin_w[calc]
    alpha, beta = (a_ - m) / sd, (a_ + w_ - m) / sd
    outside = np.maximum(np.maximum(alpha, -beta), 0.0)        # mean outside, in std
    # Z = Phi(beta) - Phi(alpha), on the side of the mean where it does not cancel
    upper = alpha > 0
    z = np.where(upper, ndtr(-alpha) - ndtr(-beta), ndtr(beta) - ndtr(alpha))
    smooth = (sd >= _SMOOTH_BINS * bw * np.maximum(outside, 1.0)) & (z > 1e-300)
    res = np.full(calc.size, float(bits))
    if np.any(smooth):
        al, be, zs = alpha[smooth], beta[smooth], z[smooth]
        with np.errstate(under='ignore'):
            tail = (_phi_x(al) - _phi_x(be)) / zs
        h_nats = np.log(np.sqrt(2 * np.pi * np.e) * sd[smooth] * zs) + 0.5 * tail
        # + bin^2 / 24 x Fisher information of the truncated normal (the discretisation term)
        h_nats += (bw[smooth] / sd[smooth]) ** 2 * (1.0 + tail) / 24.0
        res[smooth] = bits - (h_nats / np.log(2.0) - np.log2(bw[smooth]))
    exact = np.flatnonzero(~smooth)
    if exact.size:
        me, se, le, we = m[exact], sd[exact], a_[exact], w_[exact]
        # the bins holding all but 1e-18 of the mass normalised over [lo, hi]: from the edge
        # nearest the mean (or mean - 9 std) to where the density is 1e-18 of its peak there
        t_hi = np.sqrt(np.maximum(alpha[exact], 0.0) ** 2 + 83.0)
        t_lo = -np.sqrt(np.maximum(-beta[exact], 0.0) ** 2 + 83.0)
        first = np.clip(np.floor((me + t_lo * se - le) / we * nb), 0, nb)
        last = np.clip(np.ceil((me + t_hi * se - le) / we * nb), 0, nb)
        span = int(np.max(last - first)) + 1
        idx = np.minimum(first[:, None] + np.arange(span + 1)[None, :], last[:, None])
        t = (le[:, None] + we[:, None] * idx / nb - me[:, None]) / se[:, None]
        # every edge above the mean: 1 - Phi(t) differences (Phi(t) ~ 1 would cancel)
        flip = t[:, :1] > 0
        q = np.diff(np.where(flip, -ndtr(-t), ndtr(t)), axis=1)
        total = q.sum(axis=1, keepdims=True)
        # posterior entirely outside the range: certain it is at an edge (n bits)
        ok = total[:, 0] > 1e-300
        q = np.where(ok[:, None], q / np.where(ok[:, None], total, 1.0), 0.0)
        with np.errstate(divide='ignore', invalid='ignore'):
            plogp = np.where(q > 0, q * np.log2(np.where(q > 0, q, 1.0)), 0.0)
        res[exact] = np.where(ok, bits + plogp.sum(axis=1), float(bits))
    out[calc] = res
    return np.clip(out, 0.0, bits).reshape(shape)


#: Closed form where the posterior's length scale is >= this many bins (error < 3e-4 bits).
_SMOOTH_BINS = 2.0


def _phi_x(v: np.ndarray) -> np.ndarray:
    """v phi(v) (0 at +-inf)."""
    v = np.where(np.isfinite(v), v, 0.0)
    return v * np.exp(-0.5 * v * v) / np.sqrt(2 * np.pi)
