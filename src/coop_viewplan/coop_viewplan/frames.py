"""Camera frames (REP 103/105): the planner's yaw/pitch (x forward, pitch positive nose down)
and the optical frame (z forward, x right, y down) that ViewRating.pose carries."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from .raycast import rotations

#: Columns: the optical frame's x, y, z axes expressed in the body (x forward) frame.
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def optical_quaternion(yaw: float, pitch: float) -> np.ndarray:
    """Quaternion (x, y, z, w) of the optical frame in the map for a camera at yaw/pitch."""
    r = rotations(np.array([yaw]), np.array([pitch]))[0] @ BODY_FROM_OPTICAL
    return Rotation.from_matrix(r).as_quat()


def yaw_pitch_from_optical(quat_xyzw: ArrayLike) -> tuple[float, float]:
    """Inverse of optical_quaternion: heading of the optical axis (z)."""
    q = np.asarray(quat_xyzw, float)
    if not np.all(np.isfinite(q)) or np.linalg.norm(q) < 1e-9:
        raise ValueError('orientation quaternion must be finite and non-zero')
    fwd = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()[:, 2]
    return float(np.arctan2(fwd[1], fwd[0])), float(-np.arcsin(np.clip(fwd[2], -1, 1)))


def camera_pose(position: ArrayLike, quat_xyzw: ArrayLike) -> tuple[np.ndarray, float, float]:
    """A camera's pose from a pose message's position (x, y, z) and optical-frame orientation:
    (position (3,), yaw, pitch). The guard the `view_planner` node applies to a request and
    `coop_viewplan.offline` to a bag's poses: ValueError unless the position is finite and the
    quaternion finite and non-zero."""
    pos = np.asarray(position, dtype=float).reshape(3)
    if not np.all(np.isfinite(pos)):
        raise ValueError('current pose position must be finite')
    yaw, pitch = yaw_pitch_from_optical(quat_xyzw)
    return pos, yaw, pitch


def look_at_quaternion(camera: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Optical frame orientation pointing the camera axis at the target (Eq. 4-1 assumes it)."""
    d = np.asarray(target, float) - np.asarray(camera, float)
    if d.shape[0] == 2:
        d = np.r_[d, 0.0]
    yaw = float(np.arctan2(d[1], d[0]))
    pitch = float(-np.arctan2(d[2], np.hypot(d[0], d[1])))
    return optical_quaternion(yaw, pitch)
