"""Camera motion correction by scene fiducials (Sujan 2002, §3.2.5, Eq. 3-16..3-22).

* fiducial evaluation function (Eq. 3-21, 3-22): certainty f(P), visual contrast g(C), depth
  contrast h(H), and a spacing penalty, over candidate pixels of a rectified left image;
* tracking between frames (pyramidal Lucas-Kanade with a forward-backward check);
* the least-squares transform g01 (Eq. 3-16..3-18) between fiducials' positions in the common
  frame and in the camera frame, rigid alternatives (scalar- and covariance-weighted), and the
  first-order covariance of the camera pose any of these solvers returns;
* the recursive mean / covariance of the translation and of every rotation entry (Eq. 3-19);
* the EKF update of a fiducial's position from a new camera-frame measurement (Eq. 3-20).
No rclpy here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import assert_never

import cv2
import numpy as np

from coop_common.params import choice

from .errors import MappingError, OptionError
from .gauss import skew

__all__ = [
    'G01_METHODS',
    'FiducialWeights',
    'G01Method',
    'MotionError',
    'RecursivePoseStats',
    'camera_pose_covariance',
    'certainty_term',
    'depth_contrast',
    'ekf_point_update',
    'fiducial_scores',
    'fit_g01',
    'project_to_so3',
    'robust_g01',
    'select_fiducials',
    'solve_g01',
    'solve_g01_so3',
    'solve_rigid',
    'solve_rigid_cov',
    'track',
    'visual_contrast',
]


class MotionError(MappingError, ValueError):
    """Too few or degenerate correspondences, bad shapes."""


# ---------------------------------------------------------------- fiducial evaluation (3-21)
def visual_contrast(image: np.ndarray, uv: np.ndarray, *, windows: tuple[int, ...] = (3, 5, 9,
                                                                                     15, 21)
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3-22 C(u, v) = (I(x) - mean_w) / mean_w, grown over window sizes w while |C| grows;
    returns (|C| at the chosen w, w). g(C) = |C| * w."""
    img = image.astype(np.float64)
    u = np.clip(np.round(uv[:, 0]).astype(int), 0, img.shape[1] - 1)
    v = np.clip(np.round(uv[:, 1]).astype(int), 0, img.shape[0] - 1)
    centre = img[v, u]
    best_c = np.zeros(len(uv))
    best_w = np.full(len(uv), float(windows[0]))
    growing = np.ones(len(uv), bool)
    for w in windows:
        mean_w = cv2.blur(img, (w, w), borderType=cv2.BORDER_REFLECT)[v, u]
        c = np.abs(centre - mean_w) / np.maximum(mean_w, 1.0)
        upd = growing & (c >= best_c)
        best_c[upd] = c[upd]
        best_w[upd] = w
        growing &= upd  # stop at the first window after which the contrast decreases
    return best_c, best_w


def depth_contrast(depth: np.ndarray, uv: np.ndarray, *, windows: tuple[int, ...] = (3, 5, 9,
                                                                                    15, 21)
                   ) -> tuple[np.ndarray, np.ndarray]:
    """h(H(x)) heuristic the thesis allows for the 3-D spectral measure: the relative depth
    spread (std / mean of valid depths) in a window, grown while it grows; returns (H, w)."""
    z = np.where(np.isfinite(depth), depth, 0.0).astype(np.float64)
    valid = np.isfinite(depth).astype(np.float64)
    u = np.clip(np.round(uv[:, 0]).astype(int), 0, z.shape[1] - 1)
    v = np.clip(np.round(uv[:, 1]).astype(int), 0, z.shape[0] - 1)
    best_h = np.zeros(len(uv))
    best_w = np.full(len(uv), float(windows[0]))
    growing = np.ones(len(uv), bool)
    for w in windows:
        n = cv2.blur(valid, (w, w))[v, u]
        s1 = cv2.blur(z, (w, w))[v, u]
        s2 = cv2.blur(z * z, (w, w))[v, u]
        with np.errstate(invalid='ignore', divide='ignore'):
            mean = s1 / n
            std = np.sqrt(np.maximum(s2 / n - mean * mean, 0.0))
            h = np.where(n > 0.5, std / mean, 0.0)
        upd = growing & (h >= best_h)
        best_h[upd] = h[upd]
        best_w[upd] = w
        growing &= upd
    return best_h, best_w


def certainty_term(points: np.ndarray, probability: Callable[[np.ndarray], np.ndarray],
                   resolution: float, *, max_radius: int = 4) -> np.ndarray:
    """f(P(x)) ~ P(x) / r: certainty |2P - 1| of the fiducial's voxel over the radius r (in
    voxels) of the sphere inside which the neighbours' certainty descends (the first shell whose
    mean certainty rises again ends it)."""
    pts = np.asarray(points, float)
    cert0 = np.abs(2 * probability(pts) - 1)
    offs = np.stack(np.meshgrid(*[np.arange(-max_radius, max_radius + 1)] * 3, indexing='ij'),
                    -1).reshape(-1, 3)
    dist = np.linalg.norm(offs, axis=1)
    r = np.full(len(pts), float(max_radius))
    prev = cert0.copy()
    done = np.zeros(len(pts), bool)
    for rad in range(1, max_radius + 1):
        shell = offs[(dist > rad - 1) & (dist <= rad)] * resolution
        c = np.abs(2 * probability((pts[:, None, :] + shell[None]).reshape(-1, 3)) - 1)
        c = c.reshape(len(pts), len(shell)).mean(1)
        rising = ~done & (c > prev)
        r[rising] = rad
        done |= rising
        prev = c
    return cert0 / r


@dataclass(frozen=True)
class FiducialWeights:
    """Weights of the three Eq. 3-21 terms and of the spacing penalty."""

    certainty: float = 1.0
    visual: float = 1.0
    depth: float = 1.0
    spacing_px: float = 20.0
    spacing_penalty: float = 10.0


def fiducial_scores(image: np.ndarray, depth: np.ndarray, uv: np.ndarray, *,
                    certainty: np.ndarray | None = None,
                    weights: FiducialWeights = FiducialWeights()) -> np.ndarray:
    """Eq. 3-21 F.E.F. = f(P) + g(C) + h(H) for candidate pixels uv (N, 2), before the spacing
    penalty. Terms are normalised by their median over the candidates so the weights are
    comparable. `certainty` is f(P) (see certainty_term), or None when no map is there yet."""
    c, wc = visual_contrast(image, uv)
    h, wh = depth_contrast(depth, uv)
    g = c * wc
    hh = h * wh

    def norm(x: np.ndarray) -> np.ndarray:
        m = np.median(x[x > 0]) if np.any(x > 0) else 1.0
        return x / m

    score = weights.visual * norm(g) + weights.depth * norm(hh)
    if certainty is not None:
        score = score + weights.certainty * norm(np.asarray(certainty, float))
    return score


def select_fiducials(uv: np.ndarray, score: np.ndarray, n: int, *,
                     existing: np.ndarray | None = None,
                     weights: FiducialWeights = FiducialWeights()) -> np.ndarray:
    """Greedy choice of n candidates by score minus a Gaussian penalty for closeness to the
    fiducials already chosen (and to `existing` ones). Returns indices into uv."""
    s = np.asarray(score, float).copy()
    uv = np.asarray(uv, float)
    sig2 = 2 * weights.spacing_px ** 2

    def penalise(p: np.ndarray) -> None:
        s[:] -= weights.spacing_penalty * np.exp(-np.sum((uv - p) ** 2, 1) / sig2)

    if existing is not None:
        for p in np.asarray(existing, float).reshape(-1, 2):
            penalise(p)
    chosen = []
    for _ in range(min(n, len(uv))):
        i = int(np.argmax(s))
        if not np.isfinite(s[i]):
            break
        chosen.append(i)
        penalise(uv[i])
        s[i] = -np.inf
    return np.array(chosen, dtype=int)


# ---------------------------------------------------------------- tracking
def track(prev: np.ndarray, curr: np.ndarray, uv: np.ndarray, *, window: int = 21,
          levels: int = 3, fb_max_px: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Pyramidal Lucas-Kanade from prev to curr with a forward-backward check.
    Returns (new uv (N, 2), ok mask)."""
    if len(uv) == 0:
        return np.empty((0, 2)), np.zeros(0, bool)
    p0 = np.asarray(uv, np.float32).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    # (OpenCV's stubs want an array for nextPts; None has it computed)
    p1, st1, _ = cv2.calcOpticalFlowPyrLK(  # type: ignore[call-overload]
        prev, curr, p0, None, winSize=(window, window), maxLevel=levels, criteria=crit)
    pb, st2, _ = cv2.calcOpticalFlowPyrLK(  # type: ignore[call-overload]
        curr, prev, p1, None, winSize=(window, window), maxLevel=levels, criteria=crit)
    fb = np.linalg.norm((pb - p0).reshape(-1, 2), axis=1)
    p1 = p1.reshape(-1, 2).astype(np.float64)
    h, w = curr.shape
    ok = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < fb_max_px) & \
        (p1[:, 0] >= 0) & (p1[:, 0] <= w - 1) & (p1[:, 1] >= 0) & (p1[:, 1] <= h - 1)
    return p1, ok


# ---------------------------------------------------------------- g01 (3-16..3-18)
def solve_g01(r_common: np.ndarray, p_camera: np.ndarray) -> np.ndarray:
    """Eq. 3-17/3-18: the 4x4 g01 with u = g01 r in the least-squares sense, the 9 rotation
    entries treated as independent. r_common: (N, 3) fiducials in the common (base) frame;
    p_camera: (N, 3) the same points in the camera frame, i.e. (k u, k v, k f) of Eq. 3-16 with
    k from the stereo disparity. With r, u as 4 x N matrices the normal-equation solution is
    g01 = u r^T (r r^T)^-1 (the thesis prints (r^T r)^-1, the transposed form)."""
    r = np.asarray(r_common, float)
    p = np.asarray(p_camera, float)
    if r.shape != p.shape or r.ndim != 2 or r.shape[1] != 3:
        raise MotionError('need matching (N, 3) point sets')
    if len(r) < 4:
        raise MotionError(f'g01 needs >= 4 points, got {len(r)}')
    R4 = np.vstack([r.T, np.ones(len(r))])
    U4 = np.vstack([p.T, np.ones(len(p))])
    M = R4 @ R4.T
    if np.linalg.cond(M) > 1e12:
        raise MotionError('degenerate fiducial geometry (coplanar or collinear points)')
    g = np.linalg.solve(M, (U4 @ R4.T).T).T
    g[3] = [0.0, 0.0, 0.0, 1.0]
    return g


def solve_g01_so3(r_common: np.ndarray, p_camera: np.ndarray) -> np.ndarray:
    """Eq. 3-18 (solve_g01), its R projected onto SO(3), and X re-solved for that R at the
    centroids, X = mean(p) - R mean(r). Taking X from the 12-entry solution as it stands gives
    the camera position -R^T X = mean(r) - R^T mean(p) + (R^T A - I) mean(r), A the affine
    3x3 the noise made non-rigid: an error proportional to the fiducials' distance from the
    common frame's origin, which is arbitrary (the first camera pose in fig_3_24)."""
    g = solve_g01(r_common, p_camera)
    R = project_to_so3(g[:3, :3])
    g[:3, :3] = R
    g[:3, 3] = np.mean(p_camera, 0) - R @ np.mean(r_common, 0)
    return g


def project_to_so3(R: np.ndarray) -> np.ndarray:
    """Nearest rotation (SVD) to a 3x3 matrix with independently estimated entries."""
    U, _, Vt = np.linalg.svd(R)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    return U @ D @ Vt


def solve_rigid(r_common: np.ndarray, p_camera: np.ndarray,
                weights: np.ndarray | None = None) -> np.ndarray:
    """Weighted rigid alternative to Eq. 3-18 (Kabsch/Horn): the same g01 = [R X; 0 1] with R
    constrained to SO(3), i.e. 6 unknowns instead of 12, so stereo range noise is not absorbed
    into a non-rigid R. weights: per point, e.g. 1 / sigma_range^2 from Eq. 3-6."""
    r = np.asarray(r_common, float)
    p = np.asarray(p_camera, float)
    if r.shape != p.shape or r.ndim != 2 or r.shape[1] != 3:
        raise MotionError('need matching (N, 3) point sets')
    if len(r) < 3:
        raise MotionError(f'rigid fit needs >= 3 points, got {len(r)}')
    w = np.ones(len(r)) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    rc, pc = w @ r, w @ p
    H = ((r - rc) * w[:, None]).T @ (p - pc)
    U, sv, Vt = np.linalg.svd(H)
    if sv[1] < 1e-12 * max(sv[0], 1e-300):
        raise MotionError('degenerate fiducial geometry (collinear points)')
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    g = np.eye(4)
    g[:3, :3] = R
    g[:3, 3] = pc - R @ rc
    return g


def solve_rigid_cov(r_common: np.ndarray, p_camera: np.ndarray, cov: np.ndarray, *,
                    iterations: int = 10) -> np.ndarray:
    """Rigid g01 minimising the Mahalanobis residuals sum_i e_i^T S_i^-1 e_i, e_i = R r_i + X -
    p_i, with S_i (N, 3, 3) the covariance of e_i (the camera-frame measurement's, Eq. 3-7, plus
    the fiducial's map covariance rotated into the camera frame). Stereo points are ~10x better
    across the line of sight than along it (Eq. 3-7, T = (0.1, 0.1, 1)); a scalar weight per
    point (solve_rigid) cannot use that. Gauss-Newton from the scalar-weighted Kabsch solution
    (weights 1 / trace S_i)."""
    r = np.asarray(r_common, float)
    p = np.asarray(p_camera, float)
    S = np.asarray(cov, float)
    W = np.linalg.inv(S)
    g = solve_rigid(r, p, 1.0 / np.trace(S, axis1=1, axis2=2))
    R, X = g[:3, :3], g[:3, 3]
    for _ in range(iterations):
        q = r @ R.T
        e = q + X - p
        # e(dw, dX) = Exp(dw) R r + X + dX - p: de/dw = -[R r]x, de/dX = I
        J = np.concatenate([-skew(q), np.broadcast_to(np.eye(3), (len(r), 3, 3))], 2)
        H = np.einsum('nji,njk,nkl->il', J, W, J)
        b = np.einsum('nji,njk,nk->i', J, W, e)
        try:
            d = -np.linalg.solve(H, b)
        except np.linalg.LinAlgError as exc:
            raise MotionError('degenerate fiducial geometry') from exc
        R = cv2.Rodrigues(d[:3].reshape(3, 1))[0] @ R
        X = X + d[3:]
        if np.linalg.norm(d) < 1e-12:
            break
    g = np.eye(4)
    g[:3, :3] = project_to_so3(R)
    g[:3, 3] = X
    return g


class G01Method(StrEnum):
    """The solvers of g01 from 3-D correspondences: Eq. 3-18 as printed ('linear'), the same
    with R projected onto SO(3) and X re-solved ('linear_so3'), the rigid fit ('rigid')."""

    LINEAR = 'linear'
    LINEAR_SO3 = 'linear_so3'
    RIGID = 'rigid'


G01_METHODS = tuple(G01Method)


def fit_g01(r_common: np.ndarray, p_camera: np.ndarray, *, method: G01Method | str,
            weights: np.ndarray | None = None, covariances: np.ndarray | None = None
            ) -> np.ndarray:
    """g01 by `method`: 'linear' Eq. 3-18 as printed (solve_g01), 'linear_so3'
    (solve_g01_so3), 'rigid' (solve_rigid_cov with `covariances` (N, 3, 3), else solve_rigid
    with scalar `weights`); another method is refused (OptionError naming them)."""
    method = choice(G01Method, method, 'method', error=OptionError)
    match method:
        case G01Method.LINEAR:
            return solve_g01(r_common, p_camera)
        case G01Method.LINEAR_SO3:
            return solve_g01_so3(r_common, p_camera)
        case G01Method.RIGID:
            if covariances is not None:
                return solve_rigid_cov(r_common, p_camera, covariances)
            w = np.ones(len(r_common)) if weights is None else weights
            return solve_rigid(r_common, p_camera, w)
        case _:
            assert_never(method)


def robust_g01(r_common: np.ndarray, p_camera: np.ndarray, *, iterations: int = 3,
               gate: float = 3.0, min_points: int = 6,
               method: G01Method | str = G01Method.LINEAR,
               weights: np.ndarray | None = None, covariances: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """g01 (method 'linear': Eq. 3-18 as printed; 'linear_so3': solve_g01_so3; 'rigid':
    solve_rigid, or solve_rigid_cov when `covariances` are given) with iterative rejection of
    tracking outliers (residual > gate x median). With `covariances` (N, 3, 3) of the residuals
    the gate is on the Mahalanobis length of each residual: range noise grows as L^2 (Eq. 3-7),
    so a gate on the raw length rejects the far fiducials for being far. Returns (g01, inlier
    mask); another method is refused (OptionError naming them)."""
    r = np.asarray(r_common, float)
    p = np.asarray(p_camera, float)
    method = choice(G01Method, method, 'method', error=OptionError)
    w = np.ones(len(r)) if weights is None else np.asarray(weights, float)
    C = None if covariances is None else np.asarray(covariances, float)
    Winv = None if C is None else np.linalg.inv(C)

    def fit(m: np.ndarray) -> np.ndarray:
        return fit_g01(r[m], p[m], method=method, weights=w[m],
                       covariances=None if C is None else C[m])

    def residual(g: np.ndarray) -> np.ndarray:
        e = r @ g[:3, :3].T + g[:3, 3] - p
        if Winv is None:
            return np.linalg.norm(e, axis=1)
        return np.sqrt(np.einsum('ni,nij,nj->n', e, Winv, e))

    keep = np.ones(len(r), bool)
    g = fit(keep)
    for _ in range(iterations):
        res = residual(g)
        new = res <= gate * max(np.median(res[keep]), 1e-9)
        if new.sum() < min_points or np.array_equal(new, keep):
            break
        keep = new
        g = fit(keep)
    return g, keep


def camera_pose_covariance(fit: Callable[[np.ndarray, np.ndarray], np.ndarray],
                           r_common: np.ndarray, p_meas: np.ndarray, cov_r: np.ndarray,
                           cov_p: np.ndarray, *, eps: float = 1e-6) -> np.ndarray:
    """First-order covariance of the camera pose T = g01^-1 that `fit(r, p) -> g01` returns,
    from independent input covariances: cov_r (N, 3, 3) of the fiducials' common-frame positions
    and cov_p (N, k, k) of their measurements (camera-frame points, k = 3, or pixels, k = 2).
    Numerical Jacobian of the solver itself (forward differences of size eps), so it holds for
    the 12-entry Eq. 3-18 solution (its rotation projected onto SO(3), X as solved, as
    RecursivePoseStats.g01 uses it) as well as for the rigid fits. Returned in the parameters
    (theta, c): T's rotation perturbed as Exp(theta) R in the common frame, its position c
    shifted by c; 6x6, theta first."""
    r = np.asarray(r_common, float)
    p = np.asarray(p_meas, float)

    # as RecursivePoseStats.g01: R projected onto SO(3)
    def params(g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        R = project_to_so3(g[:3, :3])
        return R.T, -R.T @ g[:3, 3]

    R0, c0 = params(fit(r, p))
    cov = np.zeros((6, 6))
    for arr, C in ((r, np.asarray(cov_r, float)), (p, np.asarray(cov_p, float))):
        k = arr.shape[1]
        J = np.zeros((len(arr), 6, k))
        for i in range(len(arr)):
            for j in range(k):
                a = arr.copy()
                a[i, j] += eps
                R, c = params(fit(a, p) if arr is r else fit(r, a))
                dR = R @ R0.T                    # Exp(theta) to first order: I + [theta]x
                J[i, :3, j] = 0.5 * np.array([dR[2, 1] - dR[1, 2], dR[0, 2] - dR[2, 0],
                                              dR[1, 0] - dR[0, 1]]) / eps
                J[i, 3:, j] = (c - c0) / eps
        cov += np.einsum('nik,nkl,njl->ij', J, C, J)
    return 0.5 * (cov + cov.T)


# ---------------------------------------------------------------- Eq. 3-19
class RecursivePoseStats:
    """Eq. 3-19: recursive mean and covariance of the translation X and of every entry of R."""

    def __init__(self) -> None:
        self.i = 0
        self.X = np.zeros(3)
        self.C_X = np.zeros((3, 3))
        self.R = np.zeros((3, 3))
        self.C_R = np.zeros((3, 3))   # variance of entry (l, m)

    def update(self, g01: np.ndarray) -> None:
        g = np.asarray(g01, float)
        X, R = g[:3, 3], g[:3, :3]
        i = self.i
        self.X = (i * self.X + X) / (i + 1)
        dX = X - self.X
        self.C_X = (i * self.C_X + np.outer(dX, dX)) / (i + 1)
        self.R = (i * self.R + R) / (i + 1)
        dR = R - self.R
        self.C_R = (i * self.C_R + dR * dR) / (i + 1)
        self.i = i + 1

    def g01(self) -> np.ndarray:
        """Mean transform, its rotation projected onto SO(3)."""
        g = np.eye(4)
        g[:3, :3] = project_to_so3(self.R)
        g[:3, 3] = self.X
        return g


# ---------------------------------------------------------------- Eq. 3-20
def ekf_point_update(x: np.ndarray, P: np.ndarray, z: np.ndarray, Rz: np.ndarray,
                     h: Callable[[np.ndarray], np.ndarray],
                     H: Callable[[np.ndarray], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 3-20c for a batch of points: x (N, 3) with covariance P (N, 3, 3), measurement z
    (N, m) = h(x) + v with v ~ N(0, Rz (N, m, m)), Jacobian H(x) (N, m, 3) at the current
    estimate (Eq. 3-20b). Returns the updated (x, P)."""
    x = np.asarray(x, float)
    P = np.asarray(P, float)
    Hk = H(x)
    S = Hk @ P @ np.swapaxes(Hk, 1, 2) + Rz
    K = P @ np.swapaxes(Hk, 1, 2) @ np.linalg.inv(S)
    innov = np.asarray(z, float) - h(x)
    x_new = x + np.einsum('nij,nj->ni', K, innov)
    P_new = (np.eye(3)[None] - K @ Hk) @ P
    return x_new, 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
