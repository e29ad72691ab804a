"""Linearly implicit integration of the stiff forces the world adds to PyBullet's step: the base
compliance of Eq. B-3 and the arm joints' PD. No rclpy, no pybullet: numpy in and out.

Why: the thesis's rotational damping is heavy (b / I = 2000 1/s on every axis), so the
spring-damper applied as an explicit force needs >= 10 engine steps per 5 ms control step to be
stable (`world.substeps_for`). Here it is solved once per engine step of any length h, together
with the engine's own integration (Featherstone, semi-implicit Euler: u+ = u + h M^-1 Q, then
the positions move with u+; the force is a kick at the step's starting instant):

    F = F0 - E (Y du),      du = du_free + h A Y^T F,

F the stacked compliance wrench (anchor axes: force at the sprung c.g., torque) and arm joint
torques, Y the map from the generalised velocities u (base angular and linear velocity in the
base's principal axes, arm joint rates) to the spring-dampers' rates (deflection rate, joint
rates), A the inverse of the engine's mass matrix (mast locked: its motors hold it), and

    F0 = -k x - b x_dot + preload,   E = theta b   (arm: kp e + kd e_dot, E = theta kd).

With theta = 1/2 each damper acts on the mean of the rates before and after the kick, the rate
at the kick's instant (the trapezoid: A-stable, second order, no lag); springs act on the
instant's position (leapfrog, stable while sqrt(k / I) h < 2). du_free, the velocity change of
everything else (gravity, Coriolis, the mast motors) over the
step, is the step taken first without them in a probe world of the rovers alone (the engine's
step is linear in the applied forces: A Y^T F is exact to rounding); contacts, which only the
world has, act after, in the engine's own constraint solve.

What it costs: at one step per 5 ms the rate signals (F/T, accelerometer, gyro) are 5-9 % off
the 200-sub-step explicit reference (explicit 10 sub-steps: about 1 %), from the trapezoid's
own discretisation of the 15 Hz arm servo and the stiff damper; the identifier's moment rows
balance on them (coop_id test_sim_residual.py). The world's F/T sensor reads the arm's momentum
at the last kick's positions (World._probe_kick_state) for the same reason. Numbers:
docs/results/simulator.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: weight of the kick's after-rate in each damper (0.5: the trapezoid, centred on the instant the
#: engine applies the force at; 1: backward Euler, half a step ahead of it)
DAMPER_THETA = 0.5

def skew(v: np.ndarray) -> np.ndarray:
    """[v]x, the matrix with [v]x w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@dataclass(frozen=True)
class BaseKinematics:
    """What the solve needs of one rover's sprung base at the start of an engine step."""

    rot: np.ndarray          # base principal-axes frame in the world (PyBullet's base frame)
    rot_anchor: np.ndarray   # anchor (chassis) frame in the world
    offset: np.ndarray       # sprung c.g. (link origin) minus the base c.o.m., world frame
    deflection: np.ndarray   # (dr, dtheta), anchor axes
    rate: np.ndarray         # (dv, domega), anchor axes


def rate_jacobian(k: BaseKinematics) -> np.ndarray:
    """6x6 T with (dv, domega) = T (omega_b, v_b) + anchor terms: the deflection rates of the
    sprung c.g. from the base's generalised velocity (principal axes, angular first as in
    PyBullet's mass matrix). Its transpose maps an anchor-axes wrench at the c.g. to the
    generalised force."""
    ra_t = k.rot_anchor.T
    t = np.zeros((6, 6))
    ra_t_rot = ra_t @ k.rot
    # v_origin = v_com + w x offset = v_com - [offset]x w, offset = origin - com
    t[0:3, 0:3] = -ra_t @ skew(k.offset) @ k.rot
    t[0:3, 3:6] = ra_t_rot
    t[3:6, 0:3] = ra_t_rot
    return t


class ImplicitSolver:
    """The linearly implicit step of one rover's spring-dampers (see the module doc)."""

    def __init__(self, stiffness: np.ndarray, damping: np.ndarray, preload: np.ndarray,
                 n_arm: int) -> None:
        self.k = np.asarray(stiffness, dtype=float)
        self.b = np.asarray(damping, dtype=float)
        self.preload = np.asarray(preload, dtype=float)
        self.n_arm = int(n_arm)

    def solve(self, h: float, mass_matrix: np.ndarray, base: BaseKinematics,
              du_free: np.ndarray, arm_position_error: np.ndarray,
              arm_rate_error: np.ndarray, kp: np.ndarray, kd: np.ndarray, effort: np.ndarray,
              arm_feedforward: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(wrench (force, torque) in anchor axes at the sprung c.g., arm joint torques) for the
        engine step of length h; du_free: the step's change of the generalised velocity (6
        base + n_arm) without them.

        arm_position_error: q_ref - q; arm_rate_error: qd_ref - qd at the step's instant;
        torques beyond `effort` are clipped (the joint's actuator limit); `arm_feedforward`
        (n_arm, N m) is added to the PD's torques, held over the step."""
        n = 6 + self.n_arm
        a = np.linalg.inv(mass_matrix)
        y = np.zeros((n, n))
        y[:6, :6] = rate_jacobian(base)
        y[6:, 6:] = np.eye(self.n_arm)
        x, xd = base.deflection, base.rate
        f0 = np.empty(n)
        e = np.empty(n)
        f0[:6] = -self.k * x - self.b * xd + self.preload
        e[:6] = DAMPER_THETA * self.b
        f0[6:] = kp * arm_position_error + kd * arm_rate_error
        if arm_feedforward is not None:
            f0[6:] += arm_feedforward
        e[6:] = DAMPER_THETA * kd
        s = h * (y @ a @ y.T)
        lhs = np.eye(n) + e[:, None] * s
        rhs = f0 - e * (y @ du_free)
        f = np.linalg.solve(lhs, rhs)
        # a joint at its actuator's limit holds that torque whatever the step's rates: its row
        # becomes the limit and the rest are solved again, so the base's wrench is the one
        # for the torques the arm really gets (a joint may leave the limit as others join it)
        for _ in range(self.n_arm):
            over = np.abs(f[6:]) > effort * (1.0 + 1e-9)
            if not over.any():
                break
            rows = 6 + np.flatnonzero(over)
            lhs[rows, :] = 0.0
            lhs[rows, rows] = 1.0
            rhs[rows] = np.clip(f[rows], -effort[rows - 6], effort[rows - 6])
            f = np.linalg.solve(lhs, rhs)
        tau = np.clip(f[6:], -effort, effort)
        f[6:] = tau
        return f[:6], tau
