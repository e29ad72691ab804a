"""Observability metrics of §2.4 (no rclpy): the classical rank test (Eq. 2-5) and the
per-parameter mutual information of an n-bit 'sensor' (Eq. 2-6 .. 2-12)."""
from __future__ import annotations

import numpy as np
from scipy.special import ndtr


class InformationError(ValueError):
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
    """In(x, y) = H(x) - H(x|y) per parameter (Eq. 2-8, 2-12), in bits.

    H(x) = n bits: a uniform prior over 2^n bins of [lo, hi] (Eq. 2-12a with p_i = 1/2^n).
    H(x|y) = -sum q_i log2 q_i with q_i the Gaussian posterior N(mean, std) (Eq. 2-11) mass in
    bin i, normalised over [lo, hi] (Eq. 2-12b). n bits when std -> 0; ~0 when the posterior is
    as wide as the range.
    """
    mean, std, lo, hi = (np.atleast_1d(np.asarray(v, dtype=float)) for v in (mean, std, lo, hi))
    if not (mean.shape == std.shape == lo.shape == hi.shape):
        raise InformationError('mean, std, lo, hi must have the same shape')
    if not (1 <= bits <= 16):
        raise InformationError('bits must be in 1..16')
    if np.any(std < 0) or np.any(hi <= lo) or not np.all(np.isfinite(mean)):
        raise InformationError('need std >= 0, hi > lo, finite mean')
    nb = 2 ** bits
    frac = np.linspace(0.0, 1.0, nb + 1)
    width = hi - lo
    out = np.full(mean.shape, float(bits))
    known = std <= width * 1e-9                    # a point mass: n bits
    unknown = ~np.isfinite(std)
    calc = ~(known | unknown)
    out[unknown] = 0.0
    # well inside the range and many bins wide: the discretised Gaussian entropy is
    # log2(sqrt(2 pi e) sigma / bin) to < 1e-3 bits, no need to sum 2^n bins
    bin_w = width / nb
    smooth = calc & (std >= 4 * bin_w) & (mean - 8 * std >= lo) & (mean + 8 * std <= hi)
    out[smooth] = bits - np.log2(np.sqrt(2 * np.pi * np.e) * std[smooth] / bin_w[smooth])
    calc &= ~smooth
    if np.any(calc):
        edges = lo[calc, None] + width[calc, None] * frac[None, :]
        cdf = ndtr((edges - mean[calc, None]) / std[calc, None])
        q = np.diff(cdf, axis=1)
        total = q.sum(axis=1, keepdims=True)
        # posterior entirely outside the range: certain it is at an edge (n bits)
        ok = total[:, 0] > 1e-300
        q = np.where(ok[:, None], q / np.where(ok[:, None], total, 1.0), 0.0)
        with np.errstate(divide='ignore', invalid='ignore'):
            plogp = np.where(q > 0, q * np.log2(np.where(q > 0, q, 1.0)), 0.0)
        out[calc] = np.where(ok, bits + plogp.sum(axis=1), float(bits))
    return np.clip(out, 0.0, bits)
