"""Fiducial-based camera motion correction as a running estimator (Sujan 2002, §3.2.5).

Each new stereo frame: fiducials tracked from the previous left image (Lucas-Kanade), ranged
from the disparity, g01 solved (Eq. 3-18 'linear' / 'linear_so3', a covariance-weighted 'rigid'
fit, or 'pnp' = reprojection of the mapped fiducials), averaged over the frames of a step
(Eq. 3-19), fiducial positions refined by the EKF (Eq. 3-20), fiducials lost by the tracker or
rejected by the fit replaced by the best-scoring candidates of the fiducial evaluation function
(Eq. 3-21/3-22). The prediction is the previous estimate
composed with the commanded / dead-reckoned motion.

The camera pose carries a 6x6 covariance ("the camera pose uncertainty must be accounted for",
§3.2.5): the g01 measurement's covariance is propagated from the fiducials' map covariances and
the measurement noise through the solver, the pose uncertainty enters the covariance of every
fiducial placed with it and the measurement noise of the Eq. 3-20 update, and when the
per-step error of the commanded motion is known (OdometryConfig.sigma_t_m / sigma_rot_rad) the
prediction and the measurement are fused by their covariances (Kalman update of the pose)
instead of the measurement replacing the prediction. No rclpy here.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from functools import partial

import cv2
import numpy as np

from coop_common.params import choice

from .errors import OptionError
from .gauss import skew
from .motion import (
    FiducialWeights,
    MotionError,
    RecursivePoseStats,
    camera_pose_covariance,
    certainty_term,
    ekf_point_update,
    fiducial_scores,
    fit_g01,
    robust_g01,
    select_fiducials,
    track,
)
from .stereo import ErrorModel, StereoCamera, disparity_to_points
from .voxelmap import VoxelMap


class PoseMethod(StrEnum):
    """g01 from the tracked fiducials: Eq. 3-18 ('linear', its SO(3) projection 'linear_so3'),
    a covariance-weighted 'rigid' fit, or 'pnp' (reprojection, no range in the fit)."""

    LINEAR = 'linear'
    LINEAR_SO3 = 'linear_so3'
    RIGID = 'rigid'
    PNP = 'pnp'


METHODS = tuple(PoseMethod)


@dataclass(frozen=True)
class OdometryConfig:
    """Fiducial-odometry trial settings: the fiducials, the pose method and the motion errors."""

    n_fiducials: int = 40
    method: PoseMethod = PoseMethod.PNP
    scene_distance: float = 1.1     # m, sets the resolution of the first scan's map
    spacing_px: float = 20.0
    #: per-step error of the commanded motion (per axis, 1 sigma, in the camera frame). Both
    #: set: prediction and fiducial measurement are fused by their covariances; both None: the
    #: measurement replaces the prediction (and the prediction is used only when it fails).
    sigma_t_m: float | None = None
    sigma_rot_rad: float | None = None
    #: image-position noise (px) of a tracked fiducial and of a stereo point's left-image
    #: position: the matching accuracy the stereo error model assumes for the disparity
    #: (ErrorModel.from_stereo sigma_d_px)
    sigma_px: float = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, 'method', choice(PoseMethod, self.method, 'method',
                                                  error=OptionError))
        if self.n_fiducials < 4:
            raise OptionError('n_fiducials must be >= 4')
        if (self.sigma_t_m is None) != (self.sigma_rot_rad is None):
            raise OptionError('give both sigma_t_m and sigma_rot_rad, or neither')
        if self.sigma_t_m is not None and self.sigma_rot_rad is not None and \
                not (self.sigma_t_m > 0 and self.sigma_rot_rad > 0):
            raise OptionError('sigma_t_m and sigma_rot_rad must be > 0')
        if not self.sigma_px > 0:
            raise OptionError('sigma_px must be > 0')


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
    # accept a sample only where the disparity is consistent over its 5x5 neighbourhood. The
    # disparity of a plane is linear in (u, v) in a rectified pair, so "consistent" is measured
    # after removing the window's least-squares plane: a raw max - min gate also rejects slanted
    # planes, and their disparity slope grows as 1 / distance (at 350 mm half of the ground
    # and box faces failed it on the true disparity).
    uc = np.clip(np.round(u).astype(int), 2, disp.shape[1] - 3)
    vc = np.clip(np.round(v).astype(int), 2, disp.shape[0] - 3)
    offs = [(dv, du) for dv in range(-2, 3) for du in range(-2, 3)]
    win = np.stack([disp[vc + dv, uc + du] for dv, du in offs], 1)
    ou = np.array([du for _, du in offs], float)
    ov = np.array([dv for dv, _ in offs], float)
    with np.errstate(invalid='ignore'):
        # symmetric offsets: the plane fit decouples into mean and two slopes
        res = win - (win.mean(1)[:, None] + (win @ ou / (ou @ ou))[:, None] * ou
                     + (win @ ov / (ov @ ov))[:, None] * ov)
        spread = np.max(res, 1) - np.min(res, 1)
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


def pose_jacobian_cam(x: np.ndarray, R: np.ndarray, c: np.ndarray) -> np.ndarray:
    """d/d(theta, c) of the camera-frame points R^T (x - c) of common-frame points x, for the
    camera pose (R, c) perturbed as (Exp(theta) R, c + dc): (N, 3, 6)."""
    v = x - c
    n = len(x)
    return np.concatenate([R.T[None] @ skew(v), -np.broadcast_to(R.T, (n, 3, 3))], 2)


def pose_jacobian_placed(x: np.ndarray, c: np.ndarray) -> np.ndarray:
    """d/d(theta, c) of common-frame points x = c + R p placed from a camera pose (R, c) with
    fixed camera-frame p, the pose perturbed as (Exp(theta) R, c + dc): dx = dc - [x - c]x
    dtheta; (N, 3, 6)."""
    v = x - c
    return np.concatenate([-skew(v), np.broadcast_to(np.eye(3), (len(x), 3, 3))], 2)


def pnp_covariance(x: np.ndarray, P: np.ndarray, g: np.ndarray, cam: StereoCamera,
                   sigma_px: float) -> np.ndarray:
    """First-order covariance of the camera pose (theta, c) from the unweighted reprojection
    fit (pnp_g01) at g: sandwich H^-1 (sum J^T S J) H^-1 with S_i = sigma_px^2 I + the fiducial's
    map covariance P_i projected into the image."""
    T = np.linalg.inv(g)
    R, c = T[:3, :3], T[:3, 3]
    pc = (x - c) @ R
    z = pc[:, 2]
    Jp = np.zeros((len(x), 2, 3))
    Jp[:, 0, 0] = cam.fx / z
    Jp[:, 0, 2] = -cam.fx * pc[:, 0] / z ** 2
    Jp[:, 1, 1] = cam.fy / z
    Jp[:, 1, 2] = -cam.fy * pc[:, 1] / z ** 2
    J = Jp @ pose_jacobian_cam(x, R, c)
    S = sigma_px ** 2 * np.eye(2)[None] + Jp @ (R.T[None] @ P @ R[None]) @ np.swapaxes(Jp, 1, 2)
    Hinv = np.linalg.inv(np.einsum('nji,njl->il', J, J))
    C = Hinv @ np.einsum('nji,njk,nkl->il', J, S, J) @ Hinv
    return 0.5 * (C + C.T)


def stereo_point_cov(pc: np.ndarray, cam: StereoCamera, sigma_px: float, sigma_d_px: float
                     ) -> np.ndarray:
    """First-order covariance of stereo points pc (N, 3) (left optical frame) from independent
    noise on the left image position (sigma_px) and on the disparity (sigma_d_px): J diag J^T
    with x = (u - cx) z / f, y = (v - cy) z / f, z = f b / d (Eq. 3-4..3-6 for all three
    coordinates). The range error lies along the line of sight through the left camera."""
    pc = np.asarray(pc, float)
    z = pc[:, 2]
    n = len(pc)
    J = np.zeros((n, 3, 3))                  # d(x, y, z) / d(u, v, d)
    J[:, 0, 0] = z / cam.fx
    J[:, 1, 1] = z / cam.fy
    dz = -z * z / (cam.fx * cam.baseline)    # dz/dd
    J[:, 2, 2] = dz
    J[:, 0, 2] = pc[:, 0] / z * dz
    J[:, 1, 2] = pc[:, 1] / z * dz
    D = np.diag([sigma_px ** 2, sigma_px ** 2, sigma_d_px ** 2])
    return J @ D[None] @ np.swapaxes(J, 1, 2)


def _rot_vec(R: np.ndarray) -> np.ndarray:
    return cv2.Rodrigues(np.ascontiguousarray(R))[0].ravel()


def fuse_pose(T_pred: np.ndarray, S_pred: np.ndarray, T_meas: np.ndarray, S_meas: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Kalman update of a camera pose (camera -> common) by a measurement of it, both with 6x6
    covariances in (theta, c): rotation perturbed as Exp(theta) R in the common frame, position
    c. Returns (T, S)."""
    innov = np.concatenate([_rot_vec(T_meas[:3, :3] @ T_pred[:3, :3].T),
                            T_meas[:3, 3] - T_pred[:3, 3]])
    K = S_pred @ np.linalg.inv(S_pred + S_meas)
    d = K @ innov
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(d[:3].reshape(3, 1))[0] @ T_pred[:3, :3]
    T[:3, 3] = T_pred[:3, 3] + d[3:]
    S = (np.eye(6) - K) @ S_pred
    return T, 0.5 * (S + S.T)


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
        #: fiducials carried over (tracked, not rejected) at each step, before new ones are added
        self.kept: list[int] = []
        #: Eq. 3-19 covariance of the translation over the frames of the last step (m^2)
        self.C_X = np.zeros((3, 3))
        #: covariance of the pose estimate, 6x6 in (theta, c) (see fuse_pose); the initial pose
        #: is taken as known (§3.2.5: "the original configuration is known very precisely")
        self.S = np.zeros((6, 6))
        self.Q = np.zeros((6, 6))              # per-step error of the commanded motion
        if cfg.sigma_t_m is not None and cfg.sigma_rot_rad is not None:     # both or neither
            self.Q = np.diag([cfg.sigma_rot_rad ** 2] * 3 + [cfg.sigma_t_m ** 2] * 3)

    def _cam_cov(self, pc: np.ndarray) -> np.ndarray:
        """Covariance of stereo points in the camera frame: first-order propagation of the
        pixel and disparity noise (stereo_point_cov), the disparity sigma the one of the Eq. 3-7
        model (S = sigma_d / (f b)). Eq. 3-7's diagonal sigma = S T L^2 (T = 0.1, 0.1, 1) is
        kept for the map; for fiducials it misplaces the error: its lateral part grows as L^2
        (3-6x the pixel-noise value at 1.1-1.9 m here) and it has no x-z / y-z correlation,
        while a disparity error moves the point along its line of sight (up to 20 deg off the
        optical axis in this field of view), which the covariance-weighted fits rely on."""
        sigma_d = self.em.S * self.cam.fx * self.cam.baseline
        return stereo_point_cov(pc, self.cam, self.cfg.sigma_px, sigma_d)

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
        C = R[None] @ self._cam_cov(pc[idx]) @ R.T[None]
        # the point is placed with the current pose: its uncertainty is part of the point's
        Jx = pose_jacobian_placed(pw[idx], t)
        C = C + Jx @ self.S[None] @ np.swapaxes(Jx, 1, 2)
        self.x = np.vstack([self.x, pw[idx]])
        self.P = np.concatenate([self.P, C])
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
        # covariance of the prediction: the step s = R t_delta turns with the rotation error
        # (dc' = dc - [s]x dtheta), and the step's own error is added in the new camera frame
        F = np.eye(6)
        F[3:, :3] = -skew(self.T[:3, :3] @ delta_cam[:3, 3])
        G = np.kron(np.eye(2), predicted[:3, :3])
        S_pred = F @ self.S @ F.T + G @ self.Q @ G.T
        left0 = frames[0][0]
        assert self.prev_left is not None, 'start() takes the first frames'
        uv, ok = track(self.prev_left, left0, self.uv)
        stats = RecursivePoseStats()
        fitted = np.zeros(len(uv), bool)          # in at least one frame's g01 fit
        inl = np.zeros(len(uv), bool)             # kept by at least one frame's fit
        S_meas = None
        pcs = []
        K = np.array([[self.cam.fx, 0, self.cam.cx], [0, self.cam.fy, self.cam.cy], [0, 0, 1]])
        g_pred = np.linalg.inv(predicted)
        for left, disp in frames:
            if left is left0:
                uvf, okf = uv, ok
            else:                                 # a fiducial lost in this frame is not used
                uvf, okt = track(left0, left, uv)
                okf = ok & okt
            pc, okd = sample_points(disp, uvf, self.cam)
            use = okf & okd
            pcs.append((pc, use))
            try:
                if self.cfg.method is PoseMethod.PNP:
                    use = okf.copy()
                    if use.sum() < 8:
                        continue
                    g, keep = pnp_g01(self.x[use], uvf[use], K, g_pred)
                else:
                    if use.sum() < 8:
                        continue
                    # residual covariance: the stereo point's (_cam_cov) and the fiducial's map
                    # covariance seen from the predicted pose. The rigid fit weights by it (and
                    # gates on the Mahalanobis residual); Eq. 3-18 is unweighted and keeps the
                    # gate on the plain residual, the cost it minimises
                    Rp = g_pred[:3, :3]
                    Sr = self._cam_cov(pc[use]) + Rp[None] @ self.P[use] @ Rp.T[None]
                    g, keep = robust_g01(
                        self.x[use], pc[use], method=self.cfg.method,
                        covariances=Sr if self.cfg.method is PoseMethod.RIGID else None)
                idx = np.flatnonzero(use)[keep]
                if S_meas is None:
                    # frames of a step share the map and the tracks: the first frame's
                    # covariance is kept for the Eq. 3-19 mean (only image noise averages out)
                    if self.cfg.method is PoseMethod.PNP:
                        S_meas = pnp_covariance(self.x[idx], self.P[idx], g, self.cam,
                                                self.cfg.sigma_px)
                    else:
                        Ci = self._cam_cov(pc[idx])
                        Si = Sr[keep]
                        S_meas = camera_pose_covariance(
                            partial(fit_g01, method=self.cfg.method, covariances=Si),
                            self.x[idx], pc[idx], self.P[idx], Ci)
            except (MotionError, np.linalg.LinAlgError):
                continue
            stats.update(g)
            fitted[use] = True
            inl[idx] = True
        if stats.i == 0:
            self.T, self.S = predicted, S_pred
            self.fallbacks += 1
        else:
            T_meas = np.linalg.inv(stats.g01())
            assert S_meas is not None       # set by the first frame the statistics took
            self.C_X = stats.C_X.copy()
            if self.cfg.sigma_t_m is None:
                self.T, self.S = T_meas, S_meas
            else:
                self.T, self.S = fuse_pose(predicted, S_pred, T_meas, S_meas)
            # Eq. 3-20: refine the fiducials seen at this step with the new measurement, its
            # noise the stereo error (_cam_cov) plus the pose uncertainty it is mapped with
            g = np.linalg.inv(self.T)
            Rcw, tcw = g[:3, :3], g[:3, 3]
            pc, use = pcs[0]
            sel = use & inl
            if sel.any():
                n = int(sel.sum())
                Jz = pose_jacobian_cam(self.x[sel], self.T[:3, :3], self.T[:3, 3])
                Rz = self._cam_cov(pc[sel]) + Jz @ self.S[None] @ np.swapaxes(Jz, 1, 2)
                self.x[sel], self.P[sel] = ekf_point_update(
                    self.x[sel], self.P[sel], pc[sel], Rz,
                    lambda x: x @ Rcw.T + tcw, lambda x: np.broadcast_to(Rcw, (n, 3, 3)))
        # a fiducial is dropped when it is lost by the tracker (left the view, failed the
        # forward-backward check) or rejected as an outlier by the g01 fit it took part in; one
        # that is tracked but had no valid range at this step stays (it is ranged again later)
        ok = ok & ~(fitted & ~inl)
        self.kept.append(int(ok.sum()))
        self.x, self.P, self.uv = self.x[ok], self.P[ok], uv[ok]
        self._add_fiducials(left0, frames[0][1])
        self.prev_left = left0
        return self.T
