"""Algorithm initialisation (Sujan 2002, §3.2.2): each rover finds the known target and puts
itself, and through it its map data, into the target's (common) frame.

The known target geometry is its markers' centres in the target frame (the insertion site's two
white discs in rover_sim; any number of markers works). A rover's stereo pair gives each marker
as a 3-D point with the Eq. 3-7 covariance in its camera frame (`triangulate_markers`); the
camera's pose in the target frame is the maximum-likelihood rigid transform

    min over (R, t) of  sum_i s_i^T C_i^-1 s_i,   s_i = p_i - R^T (m_i - t)

(p_i observed in the camera frame with covariance C_i, m_i the marker in the target frame), plus,
when the rover knows which way is up in its camera frame (inclinometer + mast encoders), the
term |(I - g g^T)(g - R^T u)|^2 / sigma_g^2 with u the target's up. It starts from a weighted
Horn/Kabsch fit (scalar weights 1 / mean variance; the up vector enters as one more direction)
and is refined by Gauss-Newton; the 6x6 covariance of the result is the inverse normal matrix.
Two markers fix only five degrees of freedom (the rotation about the line through them is
free): with the up vector they fix all six. The marker-to-observation assignment is found by
trying every pairing whose pairwise distances match the target's (distances are the same in
every frame), keeping the camera on the side the marker face looks to; extra observations
(bright blobs that are not markers) are left out.

No rclpy here.
"""
from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from .errors import MappingError
from .gauss import mat_from_sym6, skew, sym6_from_mat
from .stereo import ErrorModel, StereoCamera

__all__ = [
    'InitialisationStep',
    'Initialiser',
    'PoseFix',
    'TargetFrameError',
    'TargetGeometry',
    'detect_markers',
    'frame_alignment',
    'locate_in_target',
    'solve_pose',
    'transform_to_target',
    'triangulate_markers',
]


class TargetFrameError(MappingError, ValueError):
    """Too few or degenerate marker observations, bad shapes, no consistent assignment."""


@dataclass(frozen=True)
class TargetGeometry:
    """The known target: marker centres (M, 3) in the target frame, their labels, the target's
    up direction and (optional) the outward normal of the face the markers are on."""

    markers: np.ndarray
    labels: tuple[str, ...] = ()
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    facing: np.ndarray | None = None

    def __post_init__(self) -> None:
        m = np.asarray(self.markers, float)
        if m.ndim != 2 or m.shape[1] != 3 or len(m) < 2 or not np.all(np.isfinite(m)):
            raise TargetFrameError('markers must be a finite (M >= 2, 3) array')
        object.__setattr__(self, 'markers', m)
        if self.labels and len(self.labels) != len(m):
            raise TargetFrameError('one label per marker')
        u = np.asarray(self.up, float)
        object.__setattr__(self, 'up', u / np.linalg.norm(u))
        if self.facing is not None:
            f = np.asarray(self.facing, float)
            object.__setattr__(self, 'facing', f / np.linalg.norm(f))


@dataclass(frozen=True)
class PoseFix:
    """The observer (camera) frame in the target frame: x_target = R x_camera + t.

    covariance: 6x6 of (theta, dt) with R_true = exp([theta]_x) R, t_true = t + dt (theta in
    the target frame). chi2 with dof degrees of freedom measures the fit (about dof when the
    observation covariances are right). assignment[i]: the marker observation i is of."""

    R: np.ndarray
    t: np.ndarray
    covariance: np.ndarray
    chi2: float
    dof: int
    assignment: tuple[int, ...]

    def inverse(self) -> tuple[np.ndarray, np.ndarray]:
        """(R, t) of the target frame in the observer frame."""
        return self.R.T, -self.R.T @ self.t


def _weighted_kabsch(m: np.ndarray, p: np.ndarray, w: np.ndarray,
                     up_pair: tuple[np.ndarray, np.ndarray, float] | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """R, t minimising sum w_i |R p_i + t - m_i|^2 (+ w_g |R g - u|^2)."""
    W = w / w.sum()
    mc, pc = W @ m, W @ p
    H = (w[:, None] * (p - pc)).T @ (m - mc)
    if up_pair is not None:
        g, u, wg = up_pair
        H = H + wg * np.outer(g, u)
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0])
    R = Vt.T @ D @ U.T
    return R, mc - R @ pc


def solve_pose(markers: np.ndarray, observed: np.ndarray, covariances: np.ndarray, *,
               up_observed: np.ndarray | None = None, up_sigma_rad: float | None = None,
               up_target: np.ndarray | None = None, iterations: int = 30) -> PoseFix:
    """Maximum-likelihood camera pose in the target frame from marker i observed at
    observed[i] (camera frame, covariance covariances[i] as (6,) sym6 or (3, 3)) of the known
    markers[i] (target frame); optional up direction in the camera frame with its angular sigma
    (`up_target`: the target frame's up, +z by default). See the module docstring."""
    if up_target is None:
        up_target = np.array([0.0, 0.0, 1.0])
    m = np.asarray(markers, float)
    p = np.asarray(observed, float)
    C = np.asarray(covariances, float)
    if C.ndim == 2 and C.shape[1] == 6:
        C = mat_from_sym6(C)
    n = len(m)
    if m.shape != (n, 3) or p.shape != (n, 3) or C.shape != (n, 3, 3):
        raise TargetFrameError('markers, observed (N, 3) and covariances (N, 6 | 3x3) differ')
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(C))):
        raise TargetFrameError('observations contain NaN or inf')
    try:
        Winv = np.linalg.inv(C)
    except np.linalg.LinAlgError as exc:
        raise TargetFrameError('singular observation covariance') from exc
    up_pair = None
    if up_observed is not None:
        if not (up_sigma_rad and up_sigma_rad > 0):
            raise TargetFrameError('up_observed needs up_sigma_rad > 0')
        g = np.asarray(up_observed, float)
        g = g / np.linalg.norm(g)
        u = np.asarray(up_target, float)
        u = u / np.linalg.norm(u)
        Wg = (np.eye(3) - np.outer(g, g)) / up_sigma_rad ** 2
        up_pair = (g, u, 1.0 / up_sigma_rad ** 2)
    n_obs = 3 * n + (2 if up_pair is not None else 0)
    if n_obs < 6:
        raise TargetFrameError(f'{n} markers{" and the up vector" if up_pair else ""} cannot '
                               'fix 6 degrees of freedom')
    w = 3.0 / np.trace(C, axis1=1, axis2=2)
    R, t = _weighted_kabsch(m, p, w, up_pair)

    def normal_eq(R: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        q = (m - t) @ R              # R^T (m_i - t), camera frame
        s = p - q
        J = np.concatenate([-skew(q), np.broadcast_to(R.T, (n, 3, 3))], axis=2)  # (n, 3, 6)
        JW = np.einsum('nki,nkl->nil', J, Winv)
        A = np.einsum('nil,nlj->ij', JW, J)
        b = np.einsum('nil,nl->i', JW, s)
        chi2 = float(np.einsum('ni,nij,nj->', s, Winv, s))
        if up_pair is not None:
            a = R.T @ u
            sg = g - a
            Jg = np.concatenate([-skew(a), np.zeros((3, 3))], axis=1)
            A = A + Jg.T @ Wg @ Jg
            b = b + Jg.T @ Wg @ sg
            chi2 += float(sg @ Wg @ sg)
        return A, b, chi2

    for _ in range(iterations):
        A, b, chi2 = normal_eq(R, t)
        ev = np.linalg.eigvalsh(A)
        if not ev[0] > 1e-12 * max(ev[-1], 1e-300):
            raise TargetFrameError('degenerate marker geometry (collinear markers need the up '
                                   'vector, and it must not lie along their line)')
        # s(delta) ~ s + J delta; minimise |s + J delta|_W: delta = -(J^T W J)^-1 J^T W s
        d = -np.linalg.solve(A, b)
        R = R @ cv2.Rodrigues(np.ascontiguousarray(d[:3], float).reshape(3, 1))[0]
        t = t + d[3:]
        if np.linalg.norm(d[:3]) < 1e-12 and np.linalg.norm(d[3:]) < 1e-12:
            break
    U, _, Vt = np.linalg.svd(R)
    R = U @ Vt
    A, _, chi2 = normal_eq(R, t)
    P = np.linalg.inv(A)               # of (delta right-perturbation in camera frame, dt)
    G = np.zeros((6, 6))
    G[:3, :3] = R                      # theta = R delta (left perturbation, target frame)
    G[3:, 3:] = np.eye(3)
    cov = G @ P @ G.T
    return PoseFix(R, t, 0.5 * (cov + cov.T), chi2, n_obs - 6, tuple(range(n)))


def _assignments(M: np.ndarray, p: np.ndarray, C: np.ndarray, gate: float
                 ) -> Iterator[tuple[tuple[int, ...], tuple[int, ...]]]:
    """Every injective pairing of k = min(#obs, #markers) observations with markers whose
    pairwise distances all agree with the markers' within `gate` sigma (the distance between
    two points is frame-free): yields (observation indices, marker indices)."""
    k = min(len(p), len(M))
    dM = np.linalg.norm(M[:, None] - M[None], axis=2)
    diff = p[:, None] - p[None]
    dP = np.linalg.norm(diff, axis=2)
    u = diff / np.maximum(dP, 1e-12)[..., None]
    var = np.einsum('ijk,ikl,ijl->ij', u, C, u) + np.einsum('ijk,jkl,ijl->ij', u, C, u)
    tol = gate * np.sqrt(var) + 1e-9

    def extend(mk: tuple[int, ...], obs: list[int]
               ) -> Iterator[tuple[tuple[int, ...], tuple[int, ...]]]:
        if len(obs) == k:
            yield tuple(obs), mk
            return
        a = mk[len(obs)]
        for o in range(len(p)):
            if o in obs:
                continue
            if all(abs(dP[o, obs[i]] - dM[a, mk[i]]) <= tol[o, obs[i]]
                   for i in range(len(obs))):
                yield from extend(mk, obs + [o])

    for mk in itertools.combinations(range(len(M)), k):
        yield from extend(mk, [])


def locate_in_target(geometry: TargetGeometry, observed: np.ndarray, covariances: np.ndarray,
                     *, labels: tuple[str, ...] | None = None,
                     up_observed: np.ndarray | None = None, up_sigma_rad: float | None = None,
                     gate: float = 4.0, max_candidates: int = 5000) -> PoseFix:
    """The camera's pose in the target frame from unlabelled (or labelled) marker observations.

    Unlabelled: every pairing of observations with markers whose pairwise distances agree with
    the target's (within `gate` sigma) is solved and the one with the least chi2 whose camera
    lies in front of the marker face (when geometry.facing is given) is kept. With more
    observations than markers the extra ones are left out (assignment -1): bright blobs that
    are not markers."""
    p = np.asarray(observed, float)
    C = np.asarray(covariances, float)
    if C.ndim == 2 and C.shape[1] == 6:
        C = mat_from_sym6(C)
    M = geometry.markers
    if p.ndim != 2 or p.shape[1] != 3 or C.shape != (len(p), 3, 3) or len(p) < 2:
        raise TargetFrameError('need (N >= 2, 3) observations with (N, 6 | 3x3) covariances')
    if labels is not None:
        if not geometry.labels:
            raise TargetFrameError('labelled observations need a labelled geometry')
        try:
            candidates: Iterable[tuple[tuple[int, ...], tuple[int, ...]]] = [
            (tuple(range(len(p))), tuple(geometry.labels.index(x)
                                                       for x in labels))]
        except ValueError as exc:
            raise TargetFrameError(f'unknown marker label ({exc})') from exc
    else:
        candidates = itertools.islice(_assignments(M, p, C, gate), max_candidates)
    best = None
    for o, mk in candidates:
        try:
            fix = solve_pose(M[list(mk)], p[list(o)], C[list(o)], up_observed=up_observed,
                             up_sigma_rad=up_sigma_rad, up_target=geometry.up)
        except TargetFrameError:
            continue
        if geometry.facing is not None and \
                float((fix.t - M[list(mk)].mean(0)) @ geometry.facing) <= 0:
            continue
        if best is None or fix.chi2 < best.chi2:
            a = [-1] * len(p)
            for i, j in zip(o, mk, strict=False):
                a[i] = j
            best = PoseFix(fix.R, fix.t, fix.covariance, fix.chi2, fix.dof, tuple(a))
    if best is None:
        raise TargetFrameError('no assignment of the observations to the target markers gives '
                               'a pose (too few, inconsistent, degenerate, or the camera '
                               'behind the face)')
    return best


def transform_to_target(points: np.ndarray, covariances: np.ndarray, fix: PoseFix, *,
                        with_pose_covariance: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points and (N, 6) covariances -> the target frame: x = R p + t, C' = R C R^T
    (Eq. 3-9), plus the pose's own uncertainty A P A^T with A = [-[R p]_x, I]."""
    p = np.asarray(points, float)
    y = p @ fix.R.T
    C = fix.R @ mat_from_sym6(covariances) @ fix.R.T
    if with_pose_covariance:
        A = np.concatenate([-skew(y), np.broadcast_to(np.eye(3), (len(y), 3, 3))], axis=2)
        C = C + A @ fix.covariance @ np.swapaxes(A, 1, 2)
    return y + fix.t, sym6_from_mat(C)


def frame_alignment(fix: PoseFix, R_oc: np.ndarray, t_oc: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The rotation and translation taking the rover's own frame (in which its camera was at
    R_oc, t_oc when it saw the target) into the target frame: x_target = R x_own + t."""
    R = fix.R @ np.asarray(R_oc, float).T
    return R, fix.t - R @ np.asarray(t_oc, float)


# ---------------------------------------------------------------- marker detection
def detect_markers(image: np.ndarray, *, min_radius_px: float = 1.5, max_radius_px: float = 30.0,
                   min_contrast: float = 40.0, min_fill: float = 0.6
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Bright circular markers on a darker background in a mono8 image: white top-hat (a disc
    twice max_radius_px), components above min_contrast grey levels, kept if their area is that
    of a disc of min..max radius and they fill at least min_fill of their bounding circle.
    Returns (K, 2) sub-pixel centres (u, v) weighted by the top-hat response, (K,) radii."""
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        raise TargetFrameError('image must be 2-D uint8 (mono8)')
    k = int(2 * np.ceil(2 * max_radius_px) + 1)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    top = cv2.morphologyEx(image, cv2.MORPH_TOPHAT, kernel).astype(np.float64)
    mask = (top >= min_contrast).astype(np.uint8)
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    centres, radii = [], []
    for i in range(1, n):
        area = stats[i, cv2.CC_STAT_AREA]
        r = np.sqrt(area / np.pi)
        if not (min_radius_px <= r <= max_radius_px):
            continue
        x0, y0, w, h = (stats[i, j] for j in (cv2.CC_STAT_LEFT, cv2.CC_STAT_TOP,
                                              cv2.CC_STAT_WIDTH, cv2.CC_STAT_HEIGHT))
        if area < min_fill * np.pi * (max(w, h) / 2.0) ** 2:
            continue
        sub = lab[y0:y0 + h, x0:x0 + w] == i
        wgt = top[y0:y0 + h, x0:x0 + w] * sub
        vv, uu = np.mgrid[y0:y0 + h, x0:x0 + w]
        s = wgt.sum()
        centres.append([(wgt * uu).sum() / s, (wgt * vv).sum() / s])
        radii.append(r)
    return np.array(centres).reshape(-1, 2), np.array(radii)


def triangulate_markers(left: np.ndarray, right: np.ndarray, camera: StereoCamera, *,
                        error_model: ErrorModel | None = None, max_row_diff_px: float = 1.5,
                        max_disparity_px: float = 256.0, **detect_kw: Any
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Markers seen in both images of a rectified pair -> (K, 2) left uv, (K, 3) points in the
    left optical frame (Eq. 3-1..3-3), (K, 6) covariances (Eq. 3-7, default error model of the
    camera). A left marker is paired with the right one on the same row (within
    max_row_diff_px) at the smallest positive disparity, similar size; unpaired ones dropped."""
    em = error_model or ErrorModel.from_stereo(camera)
    ul, rl = detect_markers(left, **detect_kw)
    ur, rr = detect_markers(right, **detect_kw)
    uv_rows: list[list[float]] = []
    pt_rows: list[list[float]] = []
    used = set()
    for (u, v), r in zip(ul, rl, strict=False):
        d = u - ur[:, 0] if len(ur) else np.empty(0)
        ok = (np.abs(ur[:, 1] - v) <= max_row_diff_px) & (d > 0) & (d <= max_disparity_px) & \
            (np.abs(rr - r) <= 0.5 * r + 1.0) if len(ur) else np.zeros(0, bool)
        cand = [j for j in np.flatnonzero(ok) if j not in used]
        if not cand:
            continue
        j = min(cand, key=lambda j: d[j])
        used.add(j)
        z = camera.fx * camera.baseline / d[j]
        uv_rows.append([u, v])
        pt_rows.append([(u - camera.cx) * z / camera.fx, (v - camera.cy) * z / camera.fy, z])
    uv = np.array(uv_rows).reshape(-1, 2)
    pts = np.array(pt_rows).reshape(-1, 3)
    return uv, pts, em.covariances(pts)


# ---------------------------------------------------------------- the initialisation loop
@dataclass(frozen=True)
class InitialisationStep:
    """One stereo pair's attempt: the camera pose in the common frame from the target (None if
    the target was not found), its 6x6 (theta, dt) covariance there, the largest predicted
    position sigma, how many markers were seen, and whether this attempt fixed the alignment."""

    R: np.ndarray | None
    t: np.ndarray | None
    covariance: np.ndarray | None
    position_sigma_m: float
    n_markers: int
    accepted: bool
    reason: str = ''


class Initialiser:
    """§3.2.2 for one rover: until initialised, each stereo pair is searched for the target's
    markers and the camera located in the target frame (`triangulate_markers`,
    `locate_in_target`; the up direction is taken from the dead-reckoned camera orientation,
    whose own frame has z up from the inclinometer, so only its yaw and position may be wrong);
    the first fix whose largest predicted position sigma is below `max_position_sigma_m` fixes
    the transform from the rover's own (dead-reckoned) frame to the common frame, in which the
    target frame sits at (R_ct, t_ct). `to_common` then maps own-frame camera poses there, with
    the alignment's uncertainty added. No rclpy here."""

    def __init__(self, geometry: TargetGeometry, *, R_ct: np.ndarray | None = None,
                 t_ct: np.ndarray | None = None, max_position_sigma_m: float = 0.1,
                 up_sigma_rad: float | None = 0.01, **detect_kw: Any) -> None:
        self.geometry = geometry
        self.R_ct = np.eye(3) if R_ct is None else np.asarray(R_ct, float)
        self.t_ct = np.zeros(3) if t_ct is None else np.asarray(t_ct, float)
        self.max_position_sigma_m = float(max_position_sigma_m)
        self.up_sigma_rad = up_sigma_rad if up_sigma_rad and up_sigma_rad > 0 else None
        self.detect_kw = detect_kw
        self.alignment: tuple[np.ndarray, np.ndarray] | None = None  # own -> common (R, t)
        self.alignment_covariance: np.ndarray | None = None   # (theta, dt) at the fix camera
        self.fix_origin: np.ndarray | None = None   # camera position (common) at the fix
        self.attempts = 0

    @property
    def initialised(self) -> bool:
        return self.alignment is not None

    def observe(self, left: np.ndarray, right: np.ndarray, camera: StereoCamera,
                R_oc: np.ndarray, t_oc: np.ndarray, *, error_model: ErrorModel | None = None
                ) -> InitialisationStep:
        """One rectified pair with the dead-reckoned camera pose (own frame) it was taken at."""
        self.attempts += 1
        R_oc = np.asarray(R_oc, float)
        _, pts, cov = triangulate_markers(left, right, camera, error_model=error_model,
                                          **self.detect_kw)
        up = R_oc.T @ np.array([0.0, 0.0, 1.0]) if self.up_sigma_rad else None
        try:
            fix = locate_in_target(self.geometry, pts, cov, up_observed=up,
                                   up_sigma_rad=self.up_sigma_rad)
        except TargetFrameError as exc:
            return InitialisationStep(None, None, None, float('inf'), len(pts), False, str(exc))
        B = np.zeros((6, 6))
        B[:3, :3] = B[3:, 3:] = self.R_ct
        c = B @ fix.covariance @ B.T
        c = 0.5 * (c + c.T)
        R = self.R_ct @ fix.R
        t = self.R_ct @ fix.t + self.t_ct
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(c[3:, 3:])[-1], 0.0)))
        accepted = not self.initialised and sigma <= self.max_position_sigma_m
        if accepted:
            R_a = R @ R_oc.T
            self.alignment = (R_a, t - R_a @ np.asarray(t_oc, float))
            self.alignment_covariance = c
            self.fix_origin = t
        return InitialisationStep(R, t, c, sigma, len(pts), accepted,
                                  '' if accepted else 'position sigma above the threshold')

    def to_common(self, R_oc: np.ndarray, t_oc: np.ndarray,
                  covariance_own: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """An own-frame camera pose -> (R, t, 6x6 covariance) in the common frame. Covariances
        in ROS order (x, y, z, rot x, rot y, rot z): the own one rotated into the common frame
        plus the alignment's, carried to this camera: a rotation error theta of the alignment
        moves a camera d = t - (camera position at the fix) away by -[d]_x theta."""
        if self.alignment is None or self.alignment_covariance is None:     # set together
            raise TargetFrameError('not initialised')
        R_a, t_a = self.alignment
        R = R_a @ np.asarray(R_oc, float)
        t = R_a @ np.asarray(t_oc, float) + t_a
        J = np.zeros((6, 6))          # (theta, dt) at the fix -> ROS (dp, dtheta) here
        J[:3, :3] = -skew(t - self.fix_origin)
        J[:3, 3:] = np.eye(3)
        J[3:, :3] = np.eye(3)
        cov = J @ self.alignment_covariance @ J.T
        if covariance_own is not None:
            B = np.zeros((6, 6))
            B[:3, :3] = B[3:, 3:] = R_a
            cov = cov + B @ np.asarray(covariance_own, float).reshape(6, 6) @ B.T
        return R, t, 0.5 * (cov + cov.T)
