"""The rovers' own bodies out of their clouds: a self and teammate filter (no rclpy).

A rover's stereo sees its own arm and its teammates. Fused as they are, a teammate becomes an
obstacle where it stood, and stays one until some later ray happens to cross the spot: the view
planner then plans around ghosts. Like robot_body_filter or the self filter of MoveIt, the mapper
drops the points that fall inside a body volume around every rover's known pose before fusing
them. The volume is a vertical cylinder about the rover's camera (the only pose every rover
publishes in the map frame): `radius_m` horizontally, from the ground up to `above_camera_m`
over the camera; the default 0.6 m covers rover_sim's 0.5 m x 0.36 m base, its wheels and the
mast, seen from the camera 0.16 m off the base centre. A teammate's pose counts when it was
taken at most `pose_tolerance_s` before the cloud (the latest such; a pose from after the cloud
is not used, so the live mapper and an off-line replay decide alike).
"""
from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass

import numpy as np

__all__ = ['BodyFilter', 'pose_at']


@dataclass(frozen=True)
class BodyFilter:
    """The volume about each rover's camera whose points are dropped from the map (the rovers'
    own bodies)."""

    radius_m: float = 0.6           # horizontal radius about each rover's camera; 0: no filter
    above_camera_m: float = 0.3     # the volume's top over the camera
    pose_tolerance_s: float = 2.0   # how old a teammate's pose may be, before the cloud

    def __post_init__(self) -> None:
        for name in ('radius_m', 'above_camera_m', 'pose_tolerance_s'):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f'{name} must be finite and >= 0, got {v}')

    @property
    def enabled(self) -> bool:
        return self.radius_m > 0

    def mask(self, points: np.ndarray, cameras: Iterable[np.ndarray]) -> np.ndarray:
        """(N,) bool: the points inside the body volume of any rover whose camera position
        (x, y, z in the cloud's frame, z up) is in `cameras`."""
        pts = np.asarray(points, dtype=float).reshape(-1, 3)
        inside = np.zeros(len(pts), bool)
        if not self.enabled:
            return inside
        r2 = self.radius_m ** 2
        for camera in cameras:
            c = np.asarray(camera, dtype=float).reshape(3)
            inside |= (((pts[:, 0] - c[0]) ** 2 + (pts[:, 1] - c[1]) ** 2 < r2)
                       & (pts[:, 2] < c[2] + self.above_camera_m))
        return inside

    def drop(self, points: np.ndarray, covariances: np.ndarray | None,
             cameras: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray | None, int]:
        """(points, covariances, number dropped) with the points inside a body volume (`mask`)
        removed; covariances (N, 6) or None follow the points."""
        inside = self.mask(points, cameras)
        if not inside.any():
            return points, covariances, 0
        keep = ~inside
        return (points[keep], None if covariances is None else covariances[keep],
                int(inside.sum()))

    def cameras_at(self, stamp_ns: int, own: np.ndarray,
                   others: Iterable[Mapping[int, np.ndarray]]) -> list[np.ndarray]:
        """The camera positions whose bodies are filtered out of a cloud taken at `stamp_ns`
        from `own`: `own` and, of every teammate's poses (stamp ns -> position), the one
        `pose_at` picks, where there is one."""
        tol = round(self.pose_tolerance_s * 1e9)
        out = [np.asarray(own, float)]
        for poses in others:
            p = pose_at(poses, stamp_ns, tol)
            if p is not None:
                out.append(p)
        return out


def pose_at(poses: Mapping[int, np.ndarray], stamp_ns: int, tolerance_ns: int
            ) -> np.ndarray | None:
    """Of `poses` (stamp ns -> position), the latest taken at or before `stamp_ns` and at most
    `tolerance_ns` before it; None if there is none."""
    best = None
    for s in poses:
        if stamp_ns - tolerance_ns <= s <= stamp_ns and (best is None or s > best):
            best = s
    return None if best is None else np.asarray(poses[best], float)
