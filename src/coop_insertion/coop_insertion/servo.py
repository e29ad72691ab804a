"""The slave's servo-rate core (Sujan 2002, §5.1, §5.3): close the vision error when vision
arrives at a few Hz and the servo loop runs at ~100 Hz ("commanded motions must account for
this for effective visual servo control").

Each vision fix is the required motion of the card (Eq. 5-4 in the slave's base frame R_S, see
frames.required_motion) at the image's time stamp, with its covariance. The core turns it into a
goal pose of the card in the odometry frame, using the slave's own odometry (base pose in odom)
and arm kinematics (card pose in the base) at that stamp, looked up in a short history, so a fix
that arrives late is still applied where the slave was when the image was taken. Between fixes
the error is predicted from the current odometry and kinematics against that goal. Successive
fixes are fused by a Kalman update of the goal whose process noise is the odometry drift over
the distance (and heading change) the base travelled since the previous fix.

Commands are a card velocity proportional to the predicted error, split between the skid-steer
base (forward speed and yaw rate, only to keep the goal within the arm's reach around
arm_home_m) and the arm (the rest, with the base's effect on the card fed forward), each
bounded. It holds (zero command) when vision is older than vision_timeout_s (markers lost) or
has never arrived, and never drives the card forward into contact blind: along the approach
axis it never commands the card closer than n_sigma goal sigmas to the contact plane (the goal
is a pre-insertion pose standoff_m in front of it); the force-feedback phase (contact.py) does
the rest.

No rclpy here.
"""
from __future__ import annotations

from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation

from .errors import InsertionError

__all__ = ['ServoCommand', 'VisionFix', 'VisualServo']


def _finite(name: str, v: ArrayLike, shape: tuple[int, ...]) -> np.ndarray:
    a = np.asarray(v, float)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise InsertionError(f'{name} must be a finite array of shape {shape}, got {a.shape}')
    return a


def _pose(name: str, t: ArrayLike) -> np.ndarray:
    a = _finite(name, t, (4, 4))
    r = a[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise InsertionError(f'{name}: rotation block is not a proper rotation')
    return a


def _log(r: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(r).as_rotvec()


def _exp(v: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(v).as_matrix()


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v * (limit / n) if n > limit else v


@dataclass(frozen=True)
class VisionFix:
    """One vision measurement: the card's required motion in the slave's base frame at `stamp`
    (s): translation (m) and rotation vector (rad, about the card frame's origin), their 6x6
    covariance (translation first), and optionally the approach axis (unit, base frame at
    stamp: the direction the card will move into the slot)."""

    stamp: float
    translation: np.ndarray
    rotvec: np.ndarray
    covariance: np.ndarray
    approach_axis: np.ndarray | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.stamp):
            raise InsertionError('vision stamp must be finite')
        object.__setattr__(self, 'translation', _finite('translation', self.translation, (3,)))
        object.__setattr__(self, 'rotvec', _finite('rotvec', self.rotvec, (3,)))
        c = _finite('covariance', self.covariance, (6, 6))
        if not np.allclose(c, c.T, atol=1e-15) or np.min(np.linalg.eigvalsh(c)) <= 0:
            raise InsertionError('covariance must be symmetric positive definite')
        object.__setattr__(self, 'covariance', c)
        if self.approach_axis is not None:
            a = _finite('approach_axis', self.approach_axis, (3,))
            if np.linalg.norm(a) < 1e-9:
                raise InsertionError('approach_axis must be non-zero')
            object.__setattr__(self, 'approach_axis', a / np.linalg.norm(a))


@dataclass(frozen=True)
class ServoCommand:
    """Base (forward m/s, yaw rad/s) and arm (card linear m/s and angular rad/s, base frame)
    velocity commands; the predicted error (base frame) they act on; held with the reason when
    the command is zero on purpose; the age of the newest vision fix (inf if none)."""

    base_linear_x: float
    base_angular_z: float
    arm_linear: np.ndarray
    arm_angular: np.ndarray
    error_translation: np.ndarray
    error_rotvec: np.ndarray
    held: bool
    reason: str
    vision_age_s: float

    @property
    def displacement_error_m(self) -> float:
        return float(np.linalg.norm(self.error_translation))

    @property
    def angle_error_rad(self) -> float:
        return float(np.linalg.norm(self.error_rotvec))


class VisualServo:
    """Vision-rate fixes in, servo-rate bounded base/arm velocities out (see the module notes).

    Options (keyword-only): gain_translation, gain_rotation (1/s, card error to card velocity);
    base_gain (1/s) and base_yaw_gain (1/s) with base_deadband_m (how far the goal may sit from
    arm_home_m, the card position in the base frame the arm works best at, before the base
    moves; the same dead band, sideways, before it turns); max_base_speed_m_s (app. D: 0.25),
    max_base_yaw_rate_rad_s, max_arm_speed_m_s, max_arm_rate_rad_s; vision_timeout_s (hold
    beyond it); history_s (odometry kept for late fixes); odom_drift_fraction (1-sigma
    translation drift per metre travelled) and odom_yaw_drift_fraction (per radian turned),
    goal_walk_m and goal_walk_rad (random walk per square-root second of the goal in odom, so
    the fused goal keeps following vision); standoff_m (the goal's distance in front of the
    contact plane along the approach axis) and n_sigma (the margin kept to that plane)."""

    def __init__(self, *, gain_translation: float = 1.0, gain_rotation: float = 1.0,
                 base_gain: float = 0.5, base_yaw_gain: float = 0.5,
                 base_deadband_m: float = 0.05, arm_home_m: Sequence[float] = (0.35, 0.0, 0.25),
                 max_base_speed_m_s: float = 0.25, max_base_yaw_rate_rad_s: float = 0.5,
                 max_arm_speed_m_s: float = 0.05, max_arm_rate_rad_s: float = 0.3,
                 vision_timeout_s: float = 1.0, history_s: float = 3.0,
                 odom_drift_fraction: float = 0.02, odom_yaw_drift_fraction: float = 0.02,
                 goal_walk_m: float = 0.001, goal_walk_rad: float = 0.005,
                 standoff_m: float = 0.02, n_sigma: float = 3.0) -> None:
        def pos(name: str, v: float, zero_ok: bool = False) -> float:
            x = float(v)
            if not np.isfinite(x) or x < 0 or (x == 0 and not zero_ok):
                raise InsertionError(f'{name} must be finite and {">=" if zero_ok else ">"} 0, '
                                     f'got {v}')
            return x

        self.gain_translation = pos('gain_translation', gain_translation)
        self.gain_rotation = pos('gain_rotation', gain_rotation)
        self.base_gain = pos('base_gain', base_gain, True)
        self.base_yaw_gain = pos('base_yaw_gain', base_yaw_gain, True)
        self.base_deadband_m = pos('base_deadband_m', base_deadband_m, True)
        self.arm_home_m = _finite('arm_home_m', arm_home_m, (3,))
        self.max_base_speed = pos('max_base_speed_m_s', max_base_speed_m_s)
        self.max_base_yaw_rate = pos('max_base_yaw_rate_rad_s', max_base_yaw_rate_rad_s)
        self.max_arm_speed = pos('max_arm_speed_m_s', max_arm_speed_m_s)
        self.max_arm_rate = pos('max_arm_rate_rad_s', max_arm_rate_rad_s)
        self.vision_timeout_s = pos('vision_timeout_s', vision_timeout_s)
        self.history_s = pos('history_s', history_s)
        self.odom_drift = pos('odom_drift_fraction', odom_drift_fraction, True)
        self.odom_yaw_drift = pos('odom_yaw_drift_fraction', odom_yaw_drift_fraction, True)
        self.goal_walk_m = pos('goal_walk_m', goal_walk_m, True)
        self.goal_walk_rad = pos('goal_walk_rad', goal_walk_rad, True)
        self.standoff_m = pos('standoff_m', standoff_m, True)
        self.n_sigma = pos('n_sigma', n_sigma, True)
        self.reset()

    def reset(self) -> None:
        """Forget the goal and the odometry history (a new insertion)."""
        self._hist: deque[tuple[float, np.ndarray, np.ndarray]] = deque()
        self._goal_p: np.ndarray | None = None
        self._goal_r: np.ndarray | None = None
        self._cov = np.zeros((6, 6))
        self._axis: np.ndarray | None = None
        self._last_stamp = -np.inf
        self._last_base: np.ndarray | None = None

    # -- inputs -------------------------------------------------------------------------------
    def add_odometry(self, t: float, t_odom_base: ArrayLike, t_base_card: ArrayLike) -> None:
        """The base's pose in odom (wheel odometry) and the card's in the base (arm encoders and
        kinematics) at time t (s, non-decreasing)."""
        if not np.isfinite(t):
            raise InsertionError('odometry time must be finite')
        ob, bc = _pose('t_odom_base', t_odom_base), _pose('t_base_card', t_base_card)
        if self._hist and t < self._hist[-1][0]:
            raise InsertionError(f'odometry time went back: {t} < {self._hist[-1][0]}')
        self._hist.append((float(t), ob, bc))
        while len(self._hist) > 2 and self._hist[1][0] < t - self.history_s:
            self._hist.popleft()

    def _at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        if not self._hist:
            raise InsertionError('no odometry yet')
        if t < self._hist[0][0] - 1e-9:
            raise InsertionError(f'vision stamp {t} is older than the odometry history '
                                 f'(from {self._hist[0][0]})')
        if t >= self._hist[-1][0]:
            return self._hist[-1][1], self._hist[-1][2]
        times = [h[0] for h in self._hist]
        k = int(np.searchsorted(times, t, side='right'))
        t0, a0, b0 = self._hist[k - 1]
        t1, a1, b1 = self._hist[k]
        s = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
        return self._interp(a0, a1, s), self._interp(b0, b1, s)

    @staticmethod
    def _interp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
        out = np.eye(4)
        out[:3, 3] = (1 - s) * a[:3, 3] + s * b[:3, 3]
        out[:3, :3] = _exp(s * _log(b[:3, :3] @ a[:3, :3].T)) @ a[:3, :3]
        return out

    def add_vision(self, fix: VisionFix) -> None:
        """Fuse one fix (any delay, as long as its stamp is within the odometry history)."""
        if not isinstance(fix, VisionFix):
            raise InsertionError('add_vision needs a VisionFix')
        ob, bc = self._at(fix.stamp)
        r_ob = ob[:3, :3]
        p_goal = r_ob @ (bc[:3, 3] + fix.translation) + ob[:3, 3]
        r_goal = r_ob @ _exp(fix.rotvec) @ bc[:3, :3]
        rot6 = np.zeros((6, 6))
        rot6[:3, :3] = rot6[3:, 3:] = r_ob
        c = rot6 @ fix.covariance @ rot6.T
        if self._goal_p is None:
            self._goal_p, self._goal_r, self._cov = p_goal, r_goal, c
        else:
            q = self._drift(self._last_base, ob, p_goal, self._last_stamp, fix.stamp)
            p = self._cov + q
            assert self._goal_r is not None          # set with _goal_p
            nu = np.concatenate([p_goal - self._goal_p, _log(r_goal @ self._goal_r.T)])
            k = p @ np.linalg.inv(p + c)
            d = k @ nu
            self._goal_p = self._goal_p + d[:3]
            self._goal_r = _exp(d[3:]) @ self._goal_r
            self._cov = (np.eye(6) - k) @ p
            self._cov = 0.5 * (self._cov + self._cov.T)
        if fix.approach_axis is not None:
            self._axis = r_ob @ fix.approach_axis
        if fix.stamp >= self._last_stamp:
            self._last_stamp = fix.stamp
            self._last_base = ob

    def _drift(self, before: np.ndarray | None, after: np.ndarray, p_goal: np.ndarray,
               before_t: float, after_t: float) -> np.ndarray:
        """Odometry drift between two base poses (and times), as goal process noise (odom
        frame): per metre travelled, per radian turned (times the lever to the goal), and a
        random walk per second for what the odometry does not see (slip while turning on the
        spot, arm calibration)."""
        q = np.zeros((6, 6))
        if before is None:
            return q
        dist = float(np.linalg.norm(after[:3, 3] - before[:3, 3]))
        turn = float(np.linalg.norm(_log(after[:3, :3] @ before[:3, :3].T)))
        lever = float(np.linalg.norm(p_goal - after[:3, 3]))
        st = np.hypot(self.odom_drift * dist, self.odom_yaw_drift * turn * lever)
        sr = self.odom_yaw_drift * turn
        dt = max(0.0, float(after_t - before_t))
        q[:3, :3] = (st ** 2 + self.goal_walk_m ** 2 * dt) * np.eye(3)
        q[3:, 3:] = (sr ** 2 + self.goal_walk_rad ** 2 * dt) * np.eye(3)
        return q

    # -- output -------------------------------------------------------------------------------
    def _hold(self, reason: str, age: float, e_p: np.ndarray | None = None,
              e_r: np.ndarray | None = None) -> ServoCommand:
        z = np.zeros(3)
        return ServoCommand(0.0, 0.0, z.copy(), z.copy(), z if e_p is None else e_p,
                            z if e_r is None else e_r, True, reason, age)

    @property
    def goal(self) -> np.ndarray | None:
        """4x4 pose of the fused goal (the card frame where the fixes want it) in odom, None
        before the first fix."""
        if self._goal_p is None:
            return None
        out = np.eye(4)
        out[:3, :3], out[:3, 3] = self._goal_r, self._goal_p
        return out

    @property
    def newest_fix_stamp(self) -> float:
        """Stamp of the newest fix (-inf before the first)."""
        return self._last_stamp

    @property
    def goal_covariance(self) -> np.ndarray:
        """6x6 covariance of the fused goal (odom frame, translation then rotation)."""
        return self._cov.copy()

    def command(self, t: float) -> ServoCommand:
        """The command for servo time t, from the newest odometry and the fused goal."""
        if not np.isfinite(t):
            raise InsertionError('time must be finite')
        if not self._hist:
            return self._hold('no odometry', np.inf)
        if self._goal_p is None:
            return self._hold('no vision yet', np.inf)
        age = float(t - self._last_stamp)
        _, ob, bc = self._hist[-1]
        r_ob = ob[:3, :3]
        card_p = r_ob @ bc[:3, 3] + ob[:3, 3]
        card_r = r_ob @ bc[:3, :3]
        e_p_odom = self._goal_p - card_p
        e_r_odom = _log(self._goal_r @ card_r.T)
        e_p, e_r = r_ob.T @ e_p_odom, r_ob.T @ e_r_odom
        if age > self.vision_timeout_s:
            return self._hold(f'vision lost: newest fix {age:.2f} s old', age, e_p, e_r)
        reason = 'servo'
        if self._axis is not None:
            a = self._axis
            # drift since the newest fix widens the goal's uncertainty before it is applied
            cov = self._cov + self._drift(self._last_base, ob, self._goal_p, self._last_stamp,
                                          self._hist[-1][0])
            sigma = float(np.sqrt(a @ cov[:3, :3] @ a))
            along = float(e_p_odom @ a)
            room = along + self.standoff_m - self.n_sigma * sigma
            if along > room:
                e_p_odom = e_p_odom + (max(room, min(along, 0.0)) - along) * a
                e_p = r_ob.T @ e_p_odom
                reason = f'approach limited: goal sigma {sigma * 1e3:.1f} mm along the axis'
        v = self.gain_translation * e_p
        w = self.gain_rotation * e_r
        # base: keep the goal within the arm's reach around arm_home_m
        goal_b = bc[:3, 3] + e_p
        dx = goal_b[0] - self.arm_home_m[0]
        dx = np.sign(dx) * max(0.0, abs(dx) - self.base_deadband_m)
        vb = float(np.clip(self.base_gain * dx, -self.max_base_speed, self.max_base_speed))
        lat = goal_b[1] - self.arm_home_m[1]
        lat = np.sign(lat) * max(0.0, abs(lat) - self.base_deadband_m)
        bearing = float(np.arctan2(lat, max(goal_b[0], 1e-3)))
        wb = float(np.clip(self.base_yaw_gain * bearing, -self.max_base_yaw_rate,
                           self.max_base_yaw_rate))
        # arm: the rest, with the base's own effect on the card fed forward
        base_effect = np.array([vb, 0.0, 0.0]) + np.cross([0.0, 0.0, wb], bc[:3, 3])
        arm_v = _clip_norm(v - base_effect, self.max_arm_speed)
        arm_w = _clip_norm(w - np.array([0.0, 0.0, wb]), self.max_arm_rate)
        return ServoCommand(vb, wb, arm_v, arm_w, e_p, e_r, False, reason, age)
