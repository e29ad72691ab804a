"""Fiducial-based camera motion correction as a running estimator (Sujan 2002, §3.2.5).

Each new stereo frame: fiducials tracked from the previous left image (Lucas-Kanade), ranged
from the disparity, g01 solved (Eq. 3-18 'linear', a weighted 'rigid' fit, or 'pnp' =
reprojection of the mapped fiducials), averaged over the frames of a step (Eq. 3-19), fiducial
positions refined by the EKF (Eq. 3-20), lost fiducials replaced by the best-scoring candidates
of the fiducial evaluation function (Eq. 3-21/3-22). The prediction is the previous estimate
composed with the commanded / dead-reckoned motion. No rclpy here.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .motion import (
    FiducialWeights,
    MotionError,
    RecursivePoseStats,
    certainty_term,
    ekf_point_update,
    fiducial_scores,
    robust_g01,
    select_fiducials,
    track,
)
from .stereo import ErrorModel, StereoCamera, disparity_to_points
from .voxelmap import VoxelMap

METHODS = ('linear', 'linear_so3', 'rigid', 'pnp')


@dataclass(frozen=True)
class OdometryConfig:
    n_fiducials: int = 40
    method: str = 'pnp'
    scene_distance: float = 1.1     # m, sets the resolution of the first scan's map
    spacing_px: float = 20.0

    def __post_init__(self) -> None:
        if self.method not in METHODS:
            raise ValueError(f'method must be one of {METHODS}, got {self.method!r}')
        if self.n_fiducials < 4:
            raise ValueError('n_fiducials must be >= 4')


def sample_points(disp: np.ndarray, uv: np.ndarray, cam: StereoCamera
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points at sub-pixel uv from a disparity image (bilinear over valid)."""
    u, v = uv[:, 0], uv[:, 1]
    u0 = np.clip(np.floor(u).astype(int), 0, disp.shape[1] - 2)
    v0 = np.clip(np.floor(v).astype(int), 0, disp.shape[0] - 2)
    fu, fv = u - u0, v - v0
    d = (disp[v0, u0] * (1 - fu) * (1 - fv) + disp[v0, u0 + 1] * fu * (1 - fv)
         + disp[v0 + 1, u0] * (1 - fu) * fv + disp[v0 + 1, u0 + 1] * fu * fv)
    # stereo is wrong on occlusion edges (foreground and background mix in the SGBM window):
    # accept a sample only where the disparity is consistent over its 5x5 neighbourhood
    uc = np.clip(np.round(u).astype(int), 2, disp.shape[1] - 3)
    vc = np.clip(np.round(v).astype(int), 2, disp.shape[0] - 3)
    win = np.stack([disp[vc + dv, uc + du] for dv in range(-2, 3) for du in range(-2, 3)], 1)
    with np.errstate(invalid='ignore'):
        spread = np.max(win, 1) - np.min(win, 1)
    ok = np.isfinite(d) & (d > 0.5) & np.isfinite(spread) & (spread <= 1.0)
    z = np.where(ok, cam.fx * cam.baseline / np.where(ok, d, 1.0), np.nan)
    p = np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], -1)
    return p, ok


def pnp_g01(x: np.ndarray, uv: np.ndarray, K: np.ndarray, g_pred: np.ndarray
         ) -> tuple[np.ndarray, np.ndarray]:
    """g01 from the image positions of mapped fiducials (Levenberg-Marquardt reprojection fit
    started at the predicted pose, then one pass of 3-sigma-of-median outlier rejection)."""
    rv, _ = cv2.Rodrigues(g_pred[:3, :3])
    tv = g_pred[:3, 3].reshape(3, 1).copy()
    keep = np.ones(len(x), bool)
    for _ in range(2):
        ok, rv, tv = cv2.solvePnP(x[keep], uv[keep], K, None, rv.copy(), tv.copy(),
                                  useExtrinsicGuess=True, flags=cv2.SOLVEPNP_ITERATIVE)
        if not ok:
            raise MotionError('solvePnP failed')
        proj, _ = cv2.projectPoints(x, rv, tv, K, None)
        res = np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1)
        new = res <= 3.0 * max(np.median(res[keep]), 0.1)
        if new.sum() < 6 or np.array_equal(new, keep):
            break
        keep = new
    g = np.eye(4)
    g[:3, :3] = cv2.Rodrigues(rv)[0]
    g[:3, 3] = tv.ravel()
    return g, keep


class FiducialOdometry:
    """The corrected pose chain: fiducials selected, tracked, used for g01, refined by EKF."""

    def __init__(self, cam: StereoCamera, cfg: OdometryConfig, T0: np.ndarray) -> None:
        self.cam = cam
        self.cfg = cfg
        self.em = ErrorModel.from_stereo(cam)
        self.T = T0.copy()                       # current estimate, camera -> common
        self.x = np.empty((0, 3))                # fiducials in the common frame
        self.P = np.empty((0, 3, 3))
        self.uv = np.empty((0, 2))
        self.prev_left: np.ndarray | None = None
        self.map: VoxelMap | None = None
        self.weights = FiducialWeights(spacing_px=cfg.spacing_px)
        self.fallbacks = 0
        #: Eq. 3-19 covariance of the translation over the frames of the last step (m^2)
        self.C_X = np.zeros((3, 3))

    def _cam_cov(self, pc: np.ndarray) -> np.ndarray:
        s = self.em.sigmas(pc)
        C = np.zeros((len(pc), 3, 3))
        C[:, [0, 1, 2], [0, 1, 2]] = s * s
        return C

    def _add_fiducials(self, left: np.ndarray, disp: np.ndarray) -> None:
        need = self.cfg.n_fiducials - len(self.x)
        if need <= 0:
            return
        corners = cv2.goodFeaturesToTrack(left, maxCorners=400, qualityLevel=0.01,
                                          minDistance=4, blockSize=5)
        if corners is None:
            return
        uv = corners.reshape(-1, 2).astype(float)
        pc, ok = sample_points(disp, uv, self.cam)
        uv, pc = uv[ok], pc[ok]
        if len(uv) == 0:
            return
        depth = self.cam.fx * self.cam.baseline / disp
        R, t = self.T[:3, :3], self.T[:3, 3]
        pw = pc @ R.T + t
        cert = None
        if self.map is not None:
            cert = certainty_term(pw, self.map.probability_at, self.map.resolution)
        score = fiducial_scores(left, depth, uv, certainty=cert, weights=self.weights)
        idx = select_fiducials(uv, score, need, existing=self.uv, weights=self.weights)
        C = self._cam_cov(pc[idx])
        self.x = np.vstack([self.x, pw[idx]])
        self.P = np.concatenate([self.P, R[None] @ C @ R.T[None]])
        self.uv = np.vstack([self.uv, uv[idx]])

    def first(self, left: np.ndarray, disp: np.ndarray) -> None:
        """Initial pose known (§3.2.2): build the map of the first scan, pick fiducials."""
        res = self.cfg.scene_distance / 40
        self.map = VoxelMap(res)
        pc, _ = disparity_to_points(disp, self.cam, stride=2)
        R, t = self.T[:3, :3], self.T[:3, 3]
        self.map.insert_scan(pc @ R.T + t, t, covariances=self.em.covariances(pc, R))
        self._add_fiducials(left, disp)
        self.prev_left = left

    def step(self, frames: list[tuple[np.ndarray, np.ndarray]], delta_cam: np.ndarray
             ) -> np.ndarray:
        """frames: [(left, disparity)] taken at this step; delta_cam: commanded motion."""
        predicted = self.T @ delta_cam
        left0 = frames[0][0]
        uv, ok = track(self.prev_left, left0, self.uv)
        stats = RecursivePoseStats()
        inl = np.zeros(len(uv), bool)
        pcs = []
        K = np.array([[self.cam.fx, 0, self.cam.cx], [0, self.cam.fy, self.cam.cy], [0, 0, 1]])
        g_pred = np.linalg.inv(predicted)
        for left, disp in frames:
            uvf = uv if left is left0 else track(left0, left, uv)[0]
            pc, okd = sample_points(disp, uvf, self.cam)
            use = ok & okd
            pcs.append((pc, use))
            try:
                if self.cfg.method == 'pnp':
                    use = ok.copy()
                    if use.sum() < 8:
                        continue
                    g, keep = pnp_g01(self.x[use], uvf[use], K, g_pred)
                else:
                    if use.sum() < 8:
                        continue
                    wz = 1.0 / self.em.sigmas(pc[use])[:, 2] ** 2
                    g, keep = robust_g01(self.x[use], pc[use], method=self.cfg.method,
                                         weights=wz)
            except MotionError:
                continue
            stats.update(g)
            inl[np.flatnonzero(use)[keep]] = True
        inl &= pcs[0][1]
        if stats.i == 0:
            self.T = predicted
            self.fallbacks += 1
        else:
            self.T = np.linalg.inv(stats.g01())
            self.C_X = stats.C_X.copy()
            # Eq. 3-20: refine the fiducials seen at this step with the new measurement
            g = stats.g01()
            Rcw, tcw = g[:3, :3], g[:3, 3]
            pc, use = pcs[0]
            sel = use & inl
            if sel.any():
                Rz = self._cam_cov(pc[sel])
                n = int(sel.sum())
                self.x[sel], self.P[sel] = ekf_point_update(
                    self.x[sel], self.P[sel], pc[sel], Rz,
                    lambda x: x @ Rcw.T + tcw, lambda x: np.broadcast_to(Rcw, (n, 3, 3)))
            ok = ok & inl
        # fiducials that left the view or failed are dropped; new ones selected
        self.x, self.P, self.uv = self.x[ok], self.P[ok], uv[ok]
        self._add_fiducials(left0, frames[0][1])
        self.prev_left = left0
        return self.T
