"""Batched 3x3 symmetric Gaussian algebra on the 6 unique terms (xx, xy, xz, yy, yz, zz).

Closed forms instead of np.linalg on (N, 3, 3) stacks: the map merges hundreds of thousands of
point Gaussians per frame and the generic batched LAPACK calls are several times slower.
No rclpy here.
"""
from __future__ import annotations

import numpy as np

from .errors import MappingError

#: Index of the 6 unique terms in a row-major 3x3 matrix.
SYM6 = np.array([0, 1, 2, 4, 5, 8])


class NotPositiveDefinite(MappingError, ValueError):
    """A covariance that should be positive definite is not."""


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrices [v]x of (..., 3) vectors, [a]x b = a x b."""
    v = np.asarray(v, float)
    z = np.zeros(v.shape[:-1])
    return np.stack([np.stack([z, -v[..., 2], v[..., 1]], -1),
                     np.stack([v[..., 2], z, -v[..., 0]], -1),
                     np.stack([-v[..., 1], v[..., 0], z], -1)], -2)


def sym6_from_mat(c: np.ndarray) -> np.ndarray:
    """(N, 3, 3) -> (N, 6) xx, xy, xz, yy, yz, zz."""
    c = np.asarray(c, dtype=np.float64)
    if c.shape[-2:] != (3, 3):
        raise ValueError(f'expected (..., 3, 3), got {c.shape}')
    return c.reshape(*c.shape[:-2], 9)[..., SYM6]


def mat_from_sym6(s: np.ndarray) -> np.ndarray:
    """(N, 6) -> (N, 3, 3)."""
    s = np.asarray(s, dtype=np.float64)
    xx, xy, xz, yy, yz, zz = np.moveaxis(s, -1, 0)
    return np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1),
                     np.stack([xz, yz, zz], -1)], -2)


def sym6_inv(s: np.ndarray, *, require_pd: bool = False) -> np.ndarray:
    """Inverse of symmetric 3x3 matrices given as (N, 6), by the adjugate.

    Computed on contiguous (6, N) rows with preallocated temporaries (the strided columns of
    an (N, 6) array cost more than the copy); same operations, so the same bits as the
    column-wise form. Raises NotPositiveDefinite when a determinant is not > 0, or with
    require_pd when a matrix is not positive definite (Sylvester: a, a d - b^2 and the
    determinant all > 0; a matrix with two negative eigenvalues has det > 0)."""
    s = np.asarray(s, dtype=np.float64)
    shape = s.shape
    r = np.ascontiguousarray(np.moveaxis(s, -1, 0).reshape(6, -1))
    a, b, c, d, e, f = r
    o = np.empty_like(r)
    t = np.empty(r.shape[1])
    # cofactors of [[a b c] [b d e] [c e f]]
    for out, (p, q), (u, w) in ((o[0], (d, f), (e, e)), (o[1], (c, e), (b, f)),
                                (o[2], (b, e), (c, d)), (o[3], (a, f), (c, c)),
                                (o[4], (b, c), (a, e)), (o[5], (a, d), (b, b))):
        np.multiply(p, q, out=out)
        np.multiply(u, w, out=t)
        np.subtract(out, t, out=out)
    det = a * o[0]
    np.multiply(b, o[1], out=t)
    det += t
    np.multiply(c, o[2], out=t)
    det += t
    if require_pd:
        bad = ~((a > 0) & (o[5] > 0) & (det > 0))
        if bad.any():
            raise NotPositiveDefinite(f'{int(bad.sum())} matrices not positive definite '
                                      f'(first: {int(np.argmax(bad))})')
    elif np.any(~(det > 0)):
        raise NotPositiveDefinite('covariance/information matrix with det <= 0 or NaN')
    o /= det
    return np.moveaxis(o.reshape(6, *shape[:-1]), 0, -1).copy()


def sym6_matvec(s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 6) times (N, 3)."""
    a, b, c, d, e, f = (s[..., i] for i in range(6))
    x, y, z = (v[..., i] for i in range(3))
    out = np.empty(v.shape, np.float64)
    out[..., 0] = a * x + b * y + c * z
    out[..., 1] = b * x + d * y + e * z
    out[..., 2] = c * x + e * y + f * z
    return out


def sym6_cholesky(s: np.ndarray) -> np.ndarray:
    """Lower Cholesky factor L (C = L L^T) as (N, 6): l11, l21, l31, l22, l32, l33."""
    a, b, c, d, e, f = np.moveaxis(np.asarray(s, dtype=np.float64), -1, 0)
    with np.errstate(invalid='ignore', divide='ignore'):
        l11 = np.sqrt(a)
        l21 = b / l11
        l31 = c / l11
        l22 = np.sqrt(d - l21 * l21)
        l32 = (e - l31 * l21) / l22
        l33 = np.sqrt(f - l31 * l31 - l32 * l32)
    out = np.stack([l11, l21, l31, l22, l32, l33], -1)
    if not np.all(np.isfinite(out)):
        raise NotPositiveDefinite('covariance not positive definite (Cholesky failed)')
    return out


def sym6_from_cholesky(L: np.ndarray) -> np.ndarray:
    """(N, 6) Cholesky factor -> (N, 6) covariance L L^T."""
    l11, l21, l31, l22, l32, l33 = np.moveaxis(np.asarray(L, dtype=np.float64), -1, 0)
    return np.stack([l11 * l11, l11 * l21, l11 * l31, l21 * l21 + l22 * l22,
                     l21 * l31 + l22 * l32, l31 * l31 + l32 * l32 + l33 * l33], -1)


def rotate_sym6(s: np.ndarray, R: np.ndarray) -> np.ndarray:
    """Eq. 3-9: express covariances given in a sensor frame in the common frame, R C R^T.

    `R` (3, 3) rotates sensor-frame vectors into the common frame (the thesis writes the same
    operation as R(-theta)^T C R(-theta))."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise ValueError(f'R must be (3, 3), got {R.shape}')
    C = mat_from_sym6(s)
    return sym6_from_mat(R @ C @ R.T)


def merge_two(mean1: np.ndarray, cov1: np.ndarray, mean2: np.ndarray, cov2: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3-10 (Stroupe/Smith form) product of two Gaussians, full 3x3 matrices.

    C = C1 - C1 (C1 + C2)^-1 C1, x = x1 + C1 (C1 + C2)^-1 (x2 - x1). The thesis prints
    C1 (I - C1 (C1 + C2)^-1), which is not symmetric in general; the form here is the one of
    the cited references and equals (C1^-1 + C2^-1)^-1. Reference implementation used by the
    tests to check the map's batched information-form merge."""
    mean1, mean2 = np.asarray(mean1, float), np.asarray(mean2, float)
    cov1, cov2 = np.asarray(cov1, float), np.asarray(cov2, float)
    K = cov1 @ np.linalg.inv(cov1 + cov2)
    return mean1 + K @ (mean2 - mean1), cov1 - K @ cov1
