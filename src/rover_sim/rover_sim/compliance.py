"""The base compliance of thesis ch. 2.2 / Eq. B-3: a 6-DOF linear spring-damper at the base c.g.

Pure numpy: deflections are taken in the chassis-anchor frame (frame II of Fig. 2-2), the wrench is
returned in the world frame, ready for the physics engine.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

GRAVITY = np.array([0.0, 0.0, -9.81])


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion (x, y, z, w) (scalar math: called at 200 Hz)."""
    x, y, z, w = (float(v) for v in q)
    n = 1.0 / math.sqrt(x * x + y * y + z * z + w * w)
    x, y, z, w = x * n, y * n, z * n, w * n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (x, y, z, w) of a rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=float)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [(m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s, 0.25 * s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s, (m[2, 1] - m[1, 2]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s, (m[0, 2] - m[2, 0]) / s]
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s, (m[1, 0] - m[0, 1]) / s]
    qv = np.array(q)
    return qv / np.linalg.norm(qv)


def rotation_vector(r: np.ndarray) -> np.ndarray:
    """Axis-angle vector (log map) of a rotation matrix; exact, also for small angles."""
    cos = np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)
    angle = np.arccos(cos)
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-7:
        return 0.5 * w
    return angle / (2.0 * np.sin(angle)) * w


def rpy_to_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """R = Rz(yaw) Ry(pitch) Rx(roll) (REP 103 fixed-axis roll, pitch, yaw)."""
    cr, sr, cp, sp, cy, sy = (np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch),
                              np.cos(yaw), np.sin(yaw))
    return np.array([
        [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
        [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
        [-sp, cp * sr, cp * cr],
    ])


def matrix_to_rpy(r: np.ndarray) -> np.ndarray:
    """(roll, pitch, yaw) with R = Rz(yaw) Ry(pitch) Rx(roll)."""
    pitch = -math.asin(min(1.0, max(-1.0, float(r[2, 0]))))
    roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
    yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
    return np.array([roll, pitch, yaw])


@dataclass(frozen=True)
class Deflection:
    """Base motion relative to its chassis anchor, in the anchor frame (thesis d r_1, d theta)."""

    dr: np.ndarray       # translation of the c.g. (m)
    dtheta: np.ndarray   # rotation vector (rad)
    dv: np.ndarray       # translational velocity (m/s)
    domega: np.ndarray   # angular velocity (rad/s)


def deflection(p_cg: np.ndarray, r_base: np.ndarray, v_cg: np.ndarray, w_base: np.ndarray,
               p_anchor: np.ndarray, r_anchor: np.ndarray, v_anchor: np.ndarray,
               w_anchor: np.ndarray) -> Deflection:
    """Deflection of the base (c.g. position, orientation, world velocities) from its anchor."""
    rt = r_anchor.T
    return Deflection(
        dr=rt @ (p_cg - p_anchor),
        dtheta=rotation_vector(rt @ r_base),
        dv=rt @ (v_cg - v_anchor),
        domega=rt @ (w_base - w_anchor),
    )


def compliance_wrench(d: Deflection, stiffness: np.ndarray, damping: np.ndarray,
                      preload: np.ndarray, r_anchor: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. B-3: (force, torque) on the base at its c.g., world frame.

    stiffness, damping: (k_x, k_y, k_z, k_roll, k_pitch, k_yaw) about the anchor axes;
    preload: the anchor-frame wrench (6,) that holds the rover at its nominal pose under gravity.
    """
    k = np.asarray(stiffness, dtype=float)
    b = np.asarray(damping, dtype=float)
    f = -k[:3] * d.dr - b[:3] * d.dv + preload[:3]
    t = -k[3:] * d.dtheta - b[3:] * d.domega + preload[3:]
    return r_anchor @ f, r_anchor @ t


def static_preload(masses: np.ndarray, com_positions: np.ndarray, p_cg: np.ndarray,
                   r_anchor: np.ndarray) -> np.ndarray:
    """Anchor-frame wrench at the base c.g. that balances gravity on all bodies of the rover.

    masses (n,), com_positions (n, 3) world; the suspension then rests at zero deflection, and the
    identification works on deviations from that equilibrium as in Eq. 2-1's d(.) terms.
    """
    m = np.asarray(masses, dtype=float)
    c = np.asarray(com_positions, dtype=float)
    weight = m[:, None] * GRAVITY[None, :]
    force = -weight.sum(axis=0)
    torque = -np.cross(c - p_cg, weight).sum(axis=0)
    return np.concatenate([r_anchor.T @ force, r_anchor.T @ torque])


def cross3(a: Sequence[float] | np.ndarray, b: Sequence[float] | np.ndarray) -> np.ndarray:
    """a x b of two 3-vectors in scalar math (np.cross costs ~50 us on 3-vectors)."""
    ax, ay, az = (float(v) for v in a)
    bx, by, bz = (float(v) for v in b)
    return np.array([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx])


def _qmul(a: tuple[float, float, float, float], b: tuple[float, float, float, float]
          ) -> tuple[float, float, float, float]:
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return (aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz)


def relative_rotation_vector(qa: tuple[float, float, float, float],
                             qb: tuple[float, float, float, float]) -> np.ndarray:
    """Rotation vector (log map) of R_a^T R_b for unit quaternions (x, y, z, w): the rotation
    from pose a to pose b in a's axes. Scalar math (the gyro model, every control step)."""
    x, y, z, w = _qmul((-qa[0], -qa[1], -qa[2], qa[3]), (qb[0], qb[1], qb[2], qb[3]))
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    n = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 if n < 1e-12 else 2.0 * math.atan2(n, w) / n
    return np.array([scale * x, scale * y, scale * z])


def quat_rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]
                ) -> tuple[float, float, float]:
    """v rotated by unit quaternion q (x, y, z, w); scalar math for per-sub-step use."""
    return _rotate(q, v)


def quat_rotate_inverse(q: tuple[float, float, float, float], v: tuple[float, float, float]
                        ) -> tuple[float, float, float]:
    """v rotated by the inverse of unit quaternion q (x, y, z, w)."""
    x, y, z, w = q
    return _rotate((-x, -y, -z, w), v)


def _rotate(q: tuple[float, float, float, float], v: tuple[float, float, float]
            ) -> tuple[float, float, float]:
    """v rotated by unit quaternion q (x, y, z, w)."""
    x, y, z, w = q
    tx, ty, tz = 2 * (y * v[2] - z * v[1]), 2 * (z * v[0] - x * v[2]), 2 * (x * v[1] - y * v[0])
    return (v[0] + w * tx + y * tz - z * ty, v[1] + w * ty + z * tx - x * tz,
            v[2] + w * tz + x * ty - y * tx)


class FastCompliance:
    """Eq. B-3 for one rover in scalar Python, for the physics sub-step loop (numpy's per-call
    overhead on 3-vectors dominates there). Same result as `deflection` + `compliance_wrench`
    for an anchor that only yaws (flat ground); checked against them in the tests.

    midpoint_damper: evaluate the translational damper at the sub-step's start instant. The
    engine integrates semi-implicitly (v += h a(x_n, v_n); x += h v): the velocity it reports is
    the one of the interval before, half a sub-step older than the position, so -B v_n lags
    the -B v(t_n) of Eq. B-3 by h/2 and acts, at the identification's frequencies (w h << 1),
    as an extra mass -B h/2 on each axis (b_z h / 2 = 2.5 % of the mass at 10 sub-steps of
    Table 2-1). With it the velocity is extrapolated half a sub-step from the last two calls
    (Adams-Bashforth, error O(h^2); stable while b h / m < 1, here ~0.05). The rotational
    damper lags the same way; there b h / I reaches 1 and the extrapolation would be unstable,
    so its h/2 lag is compensated implicitly in the base link's inertia instead
    (rover_model.base_link_inertial, damper_lag_s)."""

    def __init__(self, stiffness: np.ndarray, damping: np.ndarray, preload: np.ndarray,
                 inertial_quat: np.ndarray, com_offset: np.ndarray | None = None, *,
                 midpoint_damper: bool = False) -> None:
        c = (0.0, 0.0, 0.0) if com_offset is None else com_offset
        self.com_offset = (float(c[0]), float(c[1]), float(c[2]))
        self.k = tuple(float(v) for v in stiffness)
        self.b = tuple(float(v) for v in damping)
        self.pre = tuple(float(v) for v in preload)
        x, y, z, w = (float(v) for v in inertial_quat)
        self.q_in_inv = (-x, -y, -z, w)
        self.midpoint_damper = midpoint_damper
        self._dv_prev: tuple[float, float, float] | None = None

    def reset(self) -> None:
        """Forget the velocity history (after the base is placed by hand)."""
        self._dv_prev = None

    def state(self, com: Sequence[float], quat: Sequence[float], com_vel: Sequence[float],
              ang: Sequence[float], anchor_pos: Sequence[float], anchor_yaw: float,
              anchor_vel: Sequence[float], anchor_w: float
              ) -> tuple[tuple, tuple, tuple, tuple, tuple, tuple]:
        """(sprung c.g. position (world), c.o.m. minus c.g. (world), dr, dtheta, dv, domega
        (anchor axes)) from PyBullet's base link c.o.m. position, principal-axes orientation,
        velocity and angular velocity: the deflection of Eq. B-3 and its rates."""
        q_link = _qmul((quat[0], quat[1], quat[2], quat[3]), self.q_in_inv)
        ox, oy, oz = _rotate(q_link, self.com_offset)
        pos = (com[0] - ox, com[1] - oy, com[2] - oz)
        vel = (com_vel[0] - (ang[1] * oz - ang[2] * oy),
               com_vel[1] - (ang[2] * ox - ang[0] * oz),
               com_vel[2] - (ang[0] * oy - ang[1] * ox))
        c, s = math.cos(anchor_yaw), math.sin(anchor_yaw)
        # world -> anchor: rotate by -yaw about z
        dx, dy, dz = pos[0] - anchor_pos[0], pos[1] - anchor_pos[1], pos[2] - anchor_pos[2]
        dr = (c * dx + s * dy, -s * dx + c * dy, dz)
        vx, vy, vz = vel[0] - anchor_vel[0], vel[1] - anchor_vel[1], vel[2] - anchor_vel[2]
        dv = (c * vx + s * vy, -s * vx + c * vy, vz)
        wx, wy, wz = ang[0], ang[1], ang[2] - anchor_w
        dw = (c * wx + s * wy, -s * wx + c * wy, wz)
        h = 0.5 * anchor_yaw
        q_rel = _qmul((0.0, 0.0, -math.sin(h), math.cos(h)), q_link)
        qx, qy, qz, qw = q_rel
        if qw < 0.0:
            qx, qy, qz, qw = -qx, -qy, -qz, -qw
        n = math.sqrt(qx * qx + qy * qy + qz * qz)
        scale = 2.0 if n < 1e-9 else 2.0 * math.atan2(n, qw) / n
        dth = (scale * qx, scale * qy, scale * qz)
        return pos, (ox, oy, oz), dr, dth, dv, dw

    def wrench(self, com: Sequence[float], quat: Sequence[float], com_vel: Sequence[float],
               ang: Sequence[float], anchor_pos: Sequence[float], anchor_yaw: float,
               anchor_vel: Sequence[float], anchor_w: float
               ) -> tuple[list[float], list[float], list[float]]:
        """(force, torque, point) in the world frame: the compliance wrench acts at the sprung
        body's c.g. (the base link origin); com, com_vel, quat are PyBullet's base link c.o.m.
        position, velocity and principal-axes orientation."""
        pos, _, dr, dth, dv, dw = self.state(com, quat, com_vel, ang, anchor_pos, anchor_yaw,
                                             anchor_vel, anchor_w)
        c, s = math.cos(anchor_yaw), math.sin(anchor_yaw)
        k, b, pre = self.k, self.b, self.pre
        if self.midpoint_damper:
            prev = self._dv_prev if self._dv_prev is not None else dv
            self._dv_prev = dv
            dv = tuple(1.5 * dv[i] - 0.5 * prev[i] for i in range(3))
        f = [-k[i] * dr[i] - b[i] * dv[i] + pre[i] for i in range(3)]
        t = [-k[i + 3] * dth[i] - b[i + 3] * dw[i] + pre[i + 3] for i in range(3)]
        # anchor -> world
        return ([c * f[0] - s * f[1], s * f[0] + c * f[1], f[2]],
                [c * t[0] - s * t[1], s * t[0] + c * t[1], t[2]], list(pos))
