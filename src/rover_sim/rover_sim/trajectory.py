"""Following a trajectory_msgs/JointTrajectory: position/velocity targets in time.

Interpolation as ros2_control's joint_trajectory_controller: linear between points that carry
positions only, cubic (Hermite: position and velocity continuous) when every point also carries
velocities. The difference matters to the base identification: the slope of a linear segment
steps at every point, the joint PD answers each step with a torque kick (~10 N m at 30 rad/s on
a 10 ms grid), and the base vibrates at the points' rate, a multiple of the sensors' 200 Hz that
the period-mean sensors fold back into the excitation band.
"""
from __future__ import annotations

import bisect
from collections.abc import Sequence

import numpy as np

from .errors import SimError


class TrajectoryError(SimError):
    """A trajectory that cannot be followed (unknown joint, NaN, times not increasing)."""


class JointTrajectoryFollower:
    """Holds the active trajectory of a joint group and gives position/velocity targets at time t.

    A new trajectory replaces the old one from its start time on (ROS trajectory semantics);
    before its first point the joints move from where they were (linearly, or along a cubic
    from the old target's position and velocity when the new points carry velocities).
    """

    def __init__(self, joint_names: Sequence[str], initial: np.ndarray) -> None:
        self.joint_names = tuple(joint_names)
        self._hold = np.array(initial, dtype=float)
        self._times: np.ndarray | None = None
        self._points: np.ndarray | None = None
        self._vels: np.ndarray | None = None
        self._index: np.ndarray | None = None

    def set(self, names: Sequence[str], times_s: Sequence[float],
            positions: Sequence[Sequence[float]], start_s: float, current: np.ndarray,
            velocities: Sequence[Sequence[float]] | None = None,
            current_velocity: np.ndarray | None = None) -> None:
        """Install a trajectory: names a subset of the group; times relative to start_s.
        velocities (optional, one per position): cubic interpolation; current_velocity: the
        group's target velocity now (start of the cubic to a first point after start_s)."""
        if len(names) == 0 or len(set(names)) != len(names):
            raise TrajectoryError('joint names empty or repeated')
        unknown = [n for n in names if n not in self.joint_names]
        if unknown:
            raise TrajectoryError(f'unknown joints {unknown}')
        pts = np.asarray(positions, dtype=float)
        t = np.asarray(times_s, dtype=float)
        if pts.ndim != 2 or pts.shape != (len(t), len(names)) or len(t) == 0:
            raise TrajectoryError(f'expected {len(names)} positions per point')
        vel = None
        if velocities is not None:
            vel = np.asarray(velocities, dtype=float)
            if vel.shape != pts.shape:
                raise TrajectoryError(f'expected {len(names)} velocities per point')
            if not np.all(np.isfinite(vel)):
                raise TrajectoryError('NaN or Inf in trajectory')
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
        self._vels = None
        if vel is not None:
            v0 = (np.zeros(len(idx)) if current_velocity is None
                  else np.asarray(current_velocity, dtype=float)[idx])
            self._vels = np.vstack([v0[None, :], vel]) if t[0] > 0 else vel
        self._tl, self._pl, self._il = (self._times.tolist(), self._points.tolist(),
                                        idx.tolist())
        self._vl = None if self._vels is None else self._vels.tolist()

    def target(self, now_s: float) -> tuple[np.ndarray, np.ndarray]:
        """(positions, velocities) for every joint of the group at time now_s."""
        pos, vel = self.targets([now_s])
        return np.array(pos[0]), np.array(vel[0])

    def targets(self, times_s: Sequence[float]) -> tuple[list[list[float]], list[list[float]]]:
        """(positions, velocities) for every joint at several instants (the joint controller's
        instants within a control step), as lists: scalar math, numpy's per-call overhead
        dominates on a handful of joints (called at the physics rate)."""
        hold = self._hold.tolist()
        if self._times is None:
            return [hold[:] for _ in times_s], [[0.0] * len(hold) for _ in times_s]
        t, pts, idx = self._tl, self._pl, self._il
        vels = self._vl
        out_p, out_v = [], []
        for now in times_s:
            pos, vel = hold[:], [0.0] * len(hold)
            if now >= t[-1]:
                for j, i in enumerate(idx):
                    pos[i] = pts[-1][j]
            elif now >= t[0]:
                # at t[0] itself too: the first segment's start (a trajectory installed now is
                # read at once; the hold there would drop the speed reference to zero)
                k = bisect.bisect_right(t, now) - 1
                span = t[k + 1] - t[k]
                a = (now - t[k]) / span
                p0, p1 = pts[k], pts[k + 1]
                if vels is None:
                    for j, i in enumerate(idx):
                        pos[i] = p0[j] + a * (p1[j] - p0[j])
                        vel[i] = (p1[j] - p0[j]) / span
                else:
                    v0, v1 = vels[k], vels[k + 1]
                    a2 = a * a
                    a3 = a2 * a
                    h00, h10, h01, h11 = (2 * a3 - 3 * a2 + 1, a3 - 2 * a2 + a, 3 * a2 - 2 * a3,
                                          a3 - a2)
                    d00, d10, d01, d11 = (6 * a2 - 6 * a, 3 * a2 - 4 * a + 1, 6 * a - 6 * a2,
                                          3 * a2 - 2 * a)
                    for j, i in enumerate(idx):
                        m0, m1 = span * v0[j], span * v1[j]
                        pos[i] = h00 * p0[j] + h10 * m0 + h01 * p1[j] + h11 * m1
                        vel[i] = (d00 * p0[j] + d10 * m0 + d01 * p1[j] + d11 * m1) / span
            out_p.append(pos)
            out_v.append(vel)
        return out_p, out_v
