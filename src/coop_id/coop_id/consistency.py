"""Physically consistent, honest estimates (beyond the thesis; no rclpy).

Projection to m > 0, inertia positive definite with the triangle inequality, k, b >= 0;
per-parameter standard deviation and 95 % interval; parameters the data cannot see are flagged
unobservable (their value stays the prior and is never reported as identified).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from coop_common.dynparams import PARAM_NAMES, BaseParameters, check_physical

from .errors import CoopIdError
from .model import B_R, B_TH, IDX, K_R, K_TH

_NONNEG = [IDX[n] for n in (*B_R, *B_TH, *K_R, *K_TH)]
Z95 = 1.959963984540054


class ConsistencyError(CoopIdError):
    """Bad arguments."""


def project_physical(x: np.ndarray, *, min_mass: float = 1e-3,
                     min_moment: float = 1e-5) -> np.ndarray:
    """Nearest (Euclidean per block) physically consistent parameter vector.

    Mass clipped to >= min_mass; the inertia's principal moments clipped to >= min_moment, then
    moved onto the triangle inequality plane l1 + l2 = l3 if they violate it; damping and
    stiffness clipped to >= 0; c.g. untouched.
    """
    x = np.array(x, dtype=float)
    if x.shape != (len(PARAM_NAMES),) or not np.all(np.isfinite(x)):
        raise ConsistencyError('need 22 finite parameters')
    p = BaseParameters.from_vector(x)
    lam, vec = np.linalg.eigh(p.inertia)
    lam = np.maximum(lam, min_moment)
    excess = lam[2] - lam[0] - lam[1]
    if excess > 0:  # orthogonal projection onto l1 + l2 - l3 = 0
        lam = lam + excess / 3.0 * np.array([1.0, 1.0, -1.0])
        lam = np.maximum(lam, min_moment)
    inertia = (vec * lam) @ vec.T
    out = BaseParameters(max(p.mass, min_mass), inertia, p.cg_to_arm, p.damping,
                         p.stiffness).to_vector()
    out[_NONNEG] = np.maximum(out[_NONNEG], 0.0)
    return out


@dataclass(frozen=True)
class Report:
    """What gets published: consistent values, std, 95 % interval, information, observability."""

    values: np.ndarray
    std: np.ndarray
    ci_low: np.ndarray
    ci_high: np.ndarray
    information_bits: np.ndarray
    observable: np.ndarray
    consistent: bool


def make_report(x: np.ndarray, cov: np.ndarray, info_bits: np.ndarray, *,
                prior_std: np.ndarray, min_bits: float = 1.0,
                max_std_ratio: float = 0.5) -> Report:
    """Consistent values + honest uncertainty.

    A parameter is observable when it carries >= min_bits of information and its posterior std
    has shrunk below max_std_ratio x its prior std; otherwise it is flagged (never filled in).
    The 95 % interval is mean +- 1.96 std of the consistent estimate, cut to the physical domain.
    """
    cov = np.asarray(cov, dtype=float)
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    values = project_physical(x)
    lo, hi = values - Z95 * std, values + Z95 * std
    lo[_NONNEG] = np.maximum(lo[_NONNEG], 0.0)
    lo[IDX['mass']] = max(lo[IDX['mass']], 0.0)
    observable = (np.asarray(info_bits) >= min_bits) & (std <= max_std_ratio * prior_std)
    return Report(values, std, lo, hi, np.asarray(info_bits, dtype=float), observable,
                  not check_physical(values))


class ChangeDetector:
    """Forgetting on evidence (drift tracking): when the normalised innovation squared of a
    window exceeds `threshold` times its expectation, the filter covariance is inflated so a
    changed parameter (a +20 % mass step) is re-learnt instead of averaged away."""

    def __init__(self, *, threshold: float = 4.0, inflation: float = 100.0,
                 warmup_windows: int = 5) -> None:
        if threshold <= 1 or inflation < 1:
            raise ConsistencyError('threshold > 1 and inflation >= 1 required')
        self.threshold, self.inflation, self.warmup = threshold, inflation, warmup_windows
        self.windows = 0
        self.detections = 0

    def check(self, nis_mean: float) -> bool:
        """nis_mean: mean over the window of innovation^2 / predicted innovation variance."""
        self.windows += 1
        if self.windows <= self.warmup or not np.isfinite(nis_mean):
            return False
        if nis_mean > self.threshold:
            self.detections += 1
            return True
        return False
