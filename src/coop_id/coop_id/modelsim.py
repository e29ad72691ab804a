"""Fast model-level simulation of the thesis scenario (§2.6.1), no rclpy.

A rigid base (truth from a YAML via coop_common.dynparams.load_truth) on the 6-DOF linear
compliance of Eq. B-3 at its c.g., carrying the known rigid arm of §2.6.1 on an F/T sensor at r_2.
The arm base joint follows f(t) = a0 + a sin(w t) (Eq. B-1 / 2-21) through a stiff PD (as the
simulator's joint controller), one copy per rotation mode (about x, y, z, §2.2) so every sample
gives the 18 equations of the thesis. Small base motions, linearised about the initial rest pose;
the coupled base + arm equations are integrated with Newmark (average acceleration, i.e. the
trapezoidal rule, unconditionally stable: the rotational suspension has poles near -1000 1/s) at
the 5 ms sampling time.
Sensors: accelerometer (specific force at the c.g.), gyro, 2-axis inclinometer, arm-base F/T,
each corrupted by white noise uniform in +-noise x (maximum sensed deviation of that channel).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from coop_common.dynparams import BaseParameters

from .model import GRAVITY, ArmModel, cross, skew

Z_HAT = np.array([0.0, 0.0, 1.0])
MODE_AXES = np.eye(3)  # rotation about x, y, z (§2.2)


def rotation(axis: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Rodrigues: (..., 3, 3) rotations about unit `axis` by `angle` (...)."""
    angle = np.asarray(angle, dtype=float)
    k = skew(axis)
    s, c = np.sin(angle)[..., None, None], np.cos(angle)[..., None, None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def mode_geometry(arm: ArmModel) -> tuple[np.ndarray, np.ndarray]:
    """Per mode the arm c.m. offset at zero joint angle and the arm frame at zero angle.

    Mode z (joint 1) and y (joint 2) start with the arm along base x; mode x is joint 2 with
    joint 1 = pi/2, i.e. the arm along base y rotating about base x.
    """
    L = arm.com_distance_m
    rho0 = np.array([[0.0, L, 0.0], [L, 0.0, 0.0], [L, 0.0, 0.0]])
    r0 = np.stack([rotation(Z_HAT, np.pi / 2), np.eye(3), np.eye(3)])
    return rho0, r0


_GEOM: dict[float, tuple[np.ndarray, np.ndarray]] = {}


@dataclass
class ArmKinematics:
    """Arm kinematics relative to the base, per mode (leading axis 3)."""

    rho: np.ndarray      # (3, 3) arm c.m. from the arm base
    rho_dd: np.ndarray   # (3, 3) its acceleration relative to the base
    omega: np.ndarray    # (3, 3) arm angular velocity relative to the base
    alpha: np.ndarray    # (3, 3)
    inertia: np.ndarray  # (3, 3, 3) arm inertia about its c.m. in base axes


def arm_kinematics(arm: ArmModel, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray
                   ) -> ArmKinematics:
    """Rigid arm rotating about each mode axis by joint angle q (..., 3) (one per mode)."""
    rho0, r0 = _GEOM.get(arm.com_distance_m) or _GEOM.setdefault(arm.com_distance_m,
                                                                  mode_geometry(arm))
    rot = rotation(MODE_AXES, q)
    rho = np.einsum('...mab,mb->...ma', rot, rho0)
    omega = MODE_AXES * np.asarray(qd)[..., None]
    alpha = MODE_AXES * np.asarray(qdd)[..., None]
    rho_dd = cross(alpha, rho) + cross(omega, cross(omega, rho))
    rarm = rot @ r0
    inertia = rarm @ arm.inertia @ np.swapaxes(rarm, -1, -2)
    return ArmKinematics(rho, rho_dd, omega, alpha, inertia)


def arm_wrench(arm: ArmModel, kin: ArmKinematics, r2: np.ndarray, acc: np.ndarray,
               th_dd: np.ndarray, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. B-1: wrench the base exerts on the arm at the arm base, base axes, per mode."""
    c = r2 + kin.rho
    tilt = cross(theta, Z_HAT)
    force = arm.mass * (acc + cross(th_dd, c) + kin.rho_dd + GRAVITY * (Z_HAT - tilt))
    iw = np.einsum('...ab,...b->...a', kin.inertia, kin.omega)
    torque = (cross(kin.rho, force)
              + np.einsum('...ab,...b->...a', kin.inertia, kin.alpha + th_dd)
              + cross(kin.omega, iw))
    return force, torque


@dataclass(frozen=True)
class JointLimits:
    """Arm base joint limits used by the excitation optimiser and the PD (§2.5 constraints)."""

    position_rad: float = 1.6
    speed_rad_s: float = 3.0
    accel_rad_s2: float = 60.0


@dataclass
class SensorFrame:
    """One 5 ms sample of every sensor, per mode (leading axis 3)."""

    t: float
    specific_force: np.ndarray  # (3, 3)
    gyro: np.ndarray            # (3, 3)
    incl: np.ndarray            # (3, 2)
    force: np.ndarray           # (3, 3)
    torque: np.ndarray          # (3, 3)
    joint: np.ndarray           # (3,) arm joint angle per mode


class ThesisRover:
    """Three copies (arm modes x, y, z) of the rover of Fig. 2-2, integrated together."""

    def __init__(self, truth: BaseParameters, *, arm: ArmModel | None = None,
                 r_sample_s: float = 0.005, substeps: int = 1, q0: float = np.pi / 4,
                 limits: JointLimits | None = None) -> None:
        self.p = truth
        self.arm = arm or ArmModel()
        self.dt = r_sample_s / substeps
        self.substeps = substeps
        self.limits = limits or JointLimits()
        self.t = 0.0
        self.q = np.zeros((3, 6))
        self.qd = np.zeros((3, 6))
        self.qdd = np.zeros((3, 6))
        self.joint = np.full(3, float(q0))
        self.joint_d = np.zeros(3)
        self.joint_dd = np.zeros(3)
        self._kp, self._kd = 30.0 ** 2, 2 * 30.0
        self.mass_offset = 0.0  # a rock picked up: added to the base mass at run time
        kin = arm_kinematics(self.arm, self.joint, self.joint_d, self.joint_dd)
        c0 = truth.cg_to_arm + kin.rho
        self._tau0 = self.arm.mass * GRAVITY * cross(c0, Z_HAT)
        self._force = np.tile(self.arm.mass * GRAVITY * Z_HAT, (3, 1))
        self._b = np.diag(np.concatenate([truth.damping[:3], truth.damping[3:]]))
        self._k = np.diag(np.concatenate([truth.stiffness[:3], truth.stiffness[3:]]))

    def _matrices(self, kin: ArmKinematics) -> tuple[np.ndarray, np.ndarray]:
        m2 = self.arm.mass
        c = self.p.cg_to_arm + kin.rho
        sc = skew(c)
        mm = np.zeros((3, 6, 6))
        mm[:, :3, :3] = (self.p.mass + self.mass_offset + m2) * np.eye(3)
        mm[:, :3, 3:] = -m2 * sc
        mm[:, 3:, :3] = m2 * sc
        mm[:, 3:, 3:] = self.p.inertia + kin.inertia - m2 * sc @ sc
        kk = np.repeat(self._k[None], 3, 0)
        kk[:, 3:, 3:] += m2 * GRAVITY * sc @ skew(Z_HAT)
        return mm, kk

    def _drive(self, kin: ArmKinematics) -> np.ndarray:
        m2 = self.arm.mass
        c = self.p.cg_to_arm + kin.rho
        theta, w = self.q[:, 3:], self.qd[:, 3:]
        u = np.zeros((3, 6))
        tilt = cross(theta, Z_HAT)
        u[:, :3] = -m2 * kin.rho_dd + m2 * GRAVITY * tilt - cross(theta, self._force)
        iw = np.einsum('mab,mb->ma', kin.inertia, kin.omega)
        u[:, 3:] = (-m2 * cross(c, kin.rho_dd + GRAVITY * Z_HAT)
                    - np.einsum('mab,mb->ma', kin.inertia, kin.alpha)
                    - cross(kin.omega, iw) + self._tau0
                    - cross(w, w @ self.p.inertia.T))
        return u

    def rest_frame(self) -> SensorFrame:
        """The sensors at rest before the excitation starts (primes the estimator's filters)."""
        kin = arm_kinematics(self.arm, self.joint, self.joint_d, self.joint_dd)
        z3 = np.zeros((3, 3))
        force, torque = arm_wrench(self.arm, kin, self.p.cg_to_arm, z3, z3, z3)
        spec = np.tile(GRAVITY * Z_HAT, (3, 1))
        return SensorFrame(self.t, spec, z3.copy(), np.zeros((3, 2)), force, torque,
                           self.joint.copy())

    def step(self, ref: tuple[float, float, float]) -> SensorFrame:
        """Advance one sample (5 ms) with the arm tracking f = ref (position, speed, accel)."""
        f, fd, fdd = ref
        lim = self.limits
        gamma, beta = 0.5, 0.25
        dt = self.dt
        for _ in range(self.substeps):
            self.t += dt
            jdd = fdd + self._kp * (f - self.joint) + self._kd * (fd - self.joint_d)
            self.joint_dd = np.clip(jdd, -lim.accel_rad_s2, lim.accel_rad_s2)
            self.joint_d = self.joint_d + dt * self.joint_dd
            self.joint = self.joint + dt * self.joint_d
            kin = arm_kinematics(self.arm, self.joint, self.joint_d, self.joint_dd)
            mm, kk = self._matrices(kin)
            u = self._drive(kin)
            pred_d = self.qd + (1 - gamma) * dt * self.qdd
            pred = self.q + dt * self.qd + (0.5 - beta) * dt * dt * self.qdd
            lhs = mm + gamma * dt * self._b + beta * dt * dt * kk
            rhs = u - pred_d @ self._b.T - np.einsum('mab,mb->ma', kk, pred)
            self.qdd = np.linalg.solve(lhs, rhs[..., None])[..., 0]
            self.qd = pred_d + gamma * dt * self.qdd
            self.q = pred + beta * dt * dt * self.qdd
            acc, th_dd, theta = self.qdd[:, :3], self.qdd[:, 3:], self.q[:, 3:]
            self._force, torque = arm_wrench(self.arm, kin, self.p.cg_to_arm, acc, th_dd, theta)
        theta = self.q[:, 3:]
        spec = self.qdd[:, :3] + GRAVITY * (Z_HAT - cross(theta, Z_HAT))
        return SensorFrame(self.t, spec, self.qd[:, 3:].copy(), theta[:, :2].copy(),
                           self._force.copy(), torque, self.joint.copy())


CHANNELS = ('specific_force', 'gyro', 'incl', 'force', 'torque')


def stack_frames(frames: list[SensorFrame]) -> dict[str, np.ndarray]:
    """List of frames to arrays (n, 3 modes, c) per channel, plus t (n,) and joint (n, 3)."""
    out = {c: np.stack([getattr(fr, c) for fr in frames]) for c in CHANNELS}
    out['t'] = np.array([fr.t for fr in frames])
    out['joint'] = np.stack([fr.joint for fr in frames])
    return out


def noise_scales(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Maximum sensed deviation from the initial rest reading, per channel and mode."""
    return {c: np.max(np.abs(data[c] - data[c][0:1]), axis=0) for c in CHANNELS}


def add_noise(data: dict[str, np.ndarray], scales: dict[str, np.ndarray], frac: float,
              rng: np.random.Generator) -> dict[str, np.ndarray]:
    """White noise uniform in +-frac x scale (§2.6.1: 'up to 10% of the maximum sensed value')."""
    out = dict(data)
    for c in CHANNELS:
        out[c] = data[c] + frac * scales[c] * rng.uniform(-1.0, 1.0, size=data[c].shape)
    return out
