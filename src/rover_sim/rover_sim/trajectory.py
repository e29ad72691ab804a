"""Following a trajectory_msgs/JointTrajectory: piecewise-linear position targets in time."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np


class TrajectoryError(ValueError):
    """A trajectory that cannot be followed (unknown joint, NaN, times not increasing)."""


class JointTrajectoryFollower:
    """Holds the active trajectory of a joint group and gives position/velocity targets at time t.

    A new trajectory replaces the old one from its start time on (ROS trajectory semantics);
    before its first point the joints move linearly from where they were.
    """

    def __init__(self, joint_names: Sequence[str], initial: np.ndarray) -> None:
        self.joint_names = tuple(joint_names)
        self._hold = np.array(initial, dtype=float)
        self._times: np.ndarray | None = None
        self._points: np.ndarray | None = None
        self._index: np.ndarray | None = None

    def set(self, names: Sequence[str], times_s: Sequence[float],
            positions: Sequence[Sequence[float]], start_s: float, current: np.ndarray) -> None:
        """Install a trajectory: names a subset of the group; times relative to start_s."""
        if len(names) == 0 or len(set(names)) != len(names):
            raise TrajectoryError('joint names empty or repeated')
        unknown = [n for n in names if n not in self.joint_names]
        if unknown:
            raise TrajectoryError(f'unknown joints {unknown}')
        pts = np.asarray(positions, dtype=float)
        t = np.asarray(times_s, dtype=float)
        if pts.ndim != 2 or pts.shape != (len(t), len(names)) or len(t) == 0:
            raise TrajectoryError(f'expected {len(names)} positions per point')
        if not (np.all(np.isfinite(pts)) and np.all(np.isfinite(t))):
            raise TrajectoryError('NaN or Inf in trajectory')
        if np.any(np.diff(t) <= 0) or t[0] < 0:
            raise TrajectoryError('time_from_start must be >= 0 and strictly increasing')
        idx = np.array([self.joint_names.index(n) for n in names])
        self._hold = np.array(current, dtype=float)
        self._index = idx
        self._times = np.concatenate([[start_s], start_s + t]) if t[0] > 0 else start_s + t
        start = self._hold[idx][None, :]
        self._points = np.vstack([start, pts]) if t[0] > 0 else pts

    def target(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities) for every joint of the group at time now_s."""
        pos = self._hold.copy()
        vel = np.zeros_like(pos)
        if self._times is None:
            return pos, vel
        t, pts = self._times, self._points
        if now_s <= t[0]:
            return pos, vel
        if now_s >= t[-1]:
            pos[self._index] = pts[-1]
            return pos, vel
        k = int(np.searchsorted(t, now_s, side='right')) - 1
        a = (now_s - t[k]) / (t[k + 1] - t[k])
        pos[self._index] = pts[k] + a * (pts[k + 1] - pts[k])
        vel[self._index] = (pts[k + 1] - pts[k]) / (t[k + 1] - t[k])
        return pos, vel
