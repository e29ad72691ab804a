"""Exciting trajectories of §2.5 (no rclpy).

f(t) = a0 + a sin(w t) on the arm base joint (Eq. B-1); d = (a, w, a0) is re-optimised every
window (0.4 s) by Levenberg-Marquardt / Gauss-Newton (Eq. 2-16 .. 2-20) with a line search
(Eq. 2-19) on a predicted cost. The prediction: the arm motion for d drives the base model with
the CURRENT (consistent) estimate (never the truth), solved in harmonic steady state; the
predicted rows of A x = F for the next window give the predicted information matrix, hence the
posterior covariance, hence each strategy's cost:

- information: V(d) = 1/2 sum_i r_i^2, r_i = 1 - In_i / In_max (Eq. 2-13 .. 2-15 with
  In_max = n bits). NOTE: Eq. 2-13 as printed, r_i^2 = 1 - u + u^2 with u = In_i / In_max, is
  smallest at u = 1/2, i.e. it would penalise a fully known parameter as much as an unknown one;
  we use the information deficit r_i = 1 - u (monotone; parameters with less information weigh
  more through the square), see README. `literal_eq_2_13=True` gives the printed form.
- condition: log10 condition number of A, the stacked rows (sqrt of that of A^T A): all rows so
  far and the predicted window, columns scaled by the prior ranges (CostContext.condition_matrix
  for the window-only and SI-unit readings).
- d_optimal: det(J)^(-1/(2n)) (maximises log det of the information matrix J).
- a_optimal: sqrt(trace(J^-1)).
- constant: Eq. 2-21, never changed.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Literal, assert_never, get_args

import numpy as np

from coop_common.params import choice

from .errors import CoopIdError
from .information import mutual_information_bits
from .model import GRAVITY, ArmModel, assemble_rows, cross, skew
from .modelsim import MODE_AXES, Z_HAT, ArmKinematics, JointLimits, mode_geometry


class Strategy(StrEnum):
    """How the arm excites the base (§2.6): the thesis's constant Eq. 2-21 motion, or one
    re-optimised every window by information (Eq. 2-12), condition number, D- or A-optimality."""

    CONSTANT = 'constant'
    INFORMATION = 'information'
    CONDITION = 'condition'
    D_OPTIMAL = 'd_optimal'
    A_OPTIMAL = 'a_optimal'


class ConditionMatrix(StrEnum):
    """The matrix whose condition number the 'condition' strategy lowers (CostContext)."""

    ACCUMULATED = 'accumulated'
    WINDOW = 'window'
    UNSCALED = 'unscaled'


STRATEGIES = tuple(Strategy)
#: the strategies with a cost to lower (`residuals`): every one but 'constant'
COSTED_STRATEGIES = tuple(s for s in Strategy if s is not Strategy.CONSTANT)

#: the arm joints a rotation mode of §2.2 may drive (ArmReference)
ArmJoint = Literal['arm_joint_1', 'arm_joint_2']
ARM_JOINTS: tuple[str, ...] = get_args(ArmJoint)


class ExcitationError(CoopIdError):
    """Bad excitation arguments."""


def costed_strategy(strategy: Strategy | str) -> Strategy:
    """`strategy` as a member of COSTED_STRATEGIES; ExcitationError naming them otherwise
    (an unknown name, or 'constant', which has no cost to lower)."""
    if strategy in COSTED_STRATEGIES:
        return Strategy(strategy)
    why = " ('constant' never changes: nothing to cost)" if strategy == Strategy.CONSTANT else ''
    raise ExcitationError(f'strategy must be one of {[m.value for m in COSTED_STRATEGIES]}, '
                          f'got {strategy!r}{why}')


@dataclass(frozen=True)
class Excitation:
    """f(t) = offset + amplitude sin(frequency (t - t_ref)) (Eq. B-1)."""

    amplitude_rad: float
    frequency_rad_s: float
    offset_rad: float
    t_ref: float = 0.0

    def __call__(self, t: float | np.ndarray) -> tuple:
        """(position, speed, acceleration) at t."""
        ph = self.frequency_rad_s * (np.asarray(t) - self.t_ref)
        a, w = self.amplitude_rad, self.frequency_rad_s
        return (self.offset_rad + a * np.sin(ph), a * w * np.cos(ph), -a * w * w * np.sin(ph))

    @property
    def d(self) -> np.ndarray:
        return np.array([self.amplitude_rad, self.frequency_rad_s, self.offset_rad])


def constant_excitation() -> Excitation:
    """Eq. 2-21: pi/4 + 2 pi/9 sin(pi/2 t)."""
    return Excitation(2 * np.pi / 9, np.pi / 2, np.pi / 4)


#: the arm's joint limits ExcitationBounds holds unless told otherwise
DEFAULT_LIMITS = JointLimits()


@dataclass(frozen=True)
class ExcitationBounds:
    """Box on d plus the arm joint position / speed / acceleration (torque) limits."""

    amplitude: tuple[float, float] = (0.05, 1.2)
    frequency: tuple[float, float] = (0.5, 30.0)
    offset: tuple[float, float] = (-1.0, 1.0)
    limits: JointLimits = DEFAULT_LIMITS

    def feasible(self, d: np.ndarray) -> np.ndarray:
        """Clip d into the box, then shrink the amplitude to the joint limits."""
        a, w, a0 = (float(np.clip(v, *b)) for v, b in
                    zip(d, (self.amplitude, self.frequency, self.offset), strict=False))
        lim = self.limits
        a = min(a, lim.position_rad - abs(a0), lim.speed_rad_s / w, lim.accel_rad_s2 / w ** 2)
        return np.array([max(a, 1e-3), w, a0])

    def feasible_batch(self, d: np.ndarray) -> np.ndarray:
        """feasible() for K candidates (K, 3)."""
        lo, hi = self._box()
        a, w, a0 = np.clip(np.asarray(d, dtype=float), lo, hi).T
        lim = self.limits
        a = np.minimum.reduce([a, lim.position_rad - np.abs(a0), lim.speed_rad_s / w,
                               lim.accel_rad_s2 / w ** 2])
        return np.stack([np.maximum(a, 1e-3), w, a0], axis=1)

    def to_unit(self, d: np.ndarray) -> np.ndarray:
        lo, hi = self._box()
        return (np.asarray(d) - lo) / (hi - lo)

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        lo, hi = self._box()
        return lo + np.clip(u, 0.0, 1.0) * (hi - lo)

    def _box(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.array([self.amplitude, self.frequency, self.offset])
        return b[:, 0], b[:, 1]


class _ModeKinematics:
    """modelsim.arm_kinematics in closed form for the predictor (numpy-call overhead, not
    arithmetic, is its cost): the arm turns about the fixed axis e of each mode, so with
    rot(q) = e e^T + cos q (1 - e e^T) + sin q [e]x every quantity is a fixed combination of
    (1, cos q, sin q) or, for the inertia, of their pairwise products."""

    def __init__(self, arm: ArmModel) -> None:
        rho0, r0 = mode_geometry(arm)
        e = MODE_AXES
        pe = np.einsum('ma,mb->mab', e, e)
        qe = np.eye(3) - pe
        k = skew(e)
        along = np.einsum('mab,mb->ma', pe, rho0)
        self.rho_c = rho0 - along                       # rho = along + cos C + sin S
        self.rho_s = np.einsum('mab,mb->ma', k, rho0)
        self.rho_1 = along
        i0 = r0 @ arm.inertia @ np.swapaxes(r0, -1, -2)
        kt = np.swapaxes(k, -1, -2)
        # inertia = sum_j coef_j(q) T_j, coef = (1, c, s, c^2, s^2, c s)
        self.t_inertia = np.stack([
            pe @ i0 @ pe, pe @ i0 @ qe + qe @ i0 @ pe, pe @ i0 @ kt + k @ i0 @ pe,
            qe @ i0 @ qe, k @ i0 @ kt, qe @ i0 @ kt + k @ i0 @ qe],
            axis=1).reshape(3, 6, 9)                                    # (3 modes, 6, 3 x 3)

    def __call__(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray) -> ArmKinematics:
        """(..., 3 modes) joint angle, speed, acceleration -> ArmKinematics (..., 3, .)."""
        c, s = np.cos(q)[..., None], np.sin(q)[..., None]
        qd_, qdd_ = np.asarray(qd)[..., None], np.asarray(qdd)[..., None]
        rho = self.rho_1 + c * self.rho_c + s * self.rho_s
        rho_dd = (qdd_ * (c * self.rho_s - s * self.rho_c)
                  - qd_ * qd_ * (c * self.rho_c + s * self.rho_s))
        c, s = c[..., 0], s[..., 0]
        coef = np.stack([np.ones_like(c), c, s, c * c, s * s, c * s], axis=-1)[..., None, :]
        inertia = (coef @ self.t_inertia).reshape(c.shape + (3, 3))
        return ArmKinematics(rho, rho_dd, MODE_AXES * qd_, MODE_AXES * qdd_, inertia)


class WindowPredictor:
    """Predicted rows of A x = F for the next window under excitation d (harmonic steady state
    of the base model linearised at the mean arm pose, with the current estimate)."""

    def __init__(self, *, arm: ArmModel, times: np.ndarray, harmonics: int = 4,
                 points: int = 32, accelerometer: bool = True, weight: float = 1.0) -> None:
        """times: prediction instants in the window; weight: filter updates per instant."""
        self.arm, self.times = arm, np.asarray(times, dtype=float)
        self.weight = float(weight)
        self.harmonics, self.points, self.accel = harmonics, points, accelerometer
        self._kin = _ModeKinematics(arm)

    def rows(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(len(times) * 3 modes, 6, 22) predicted rows for consistent estimate x."""
        return self.rows_batch(x, np.asarray(d, dtype=float)[None])[0]

    def rows_batch(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(K, len(times) * 3 modes, 6, 22) predicted rows for K candidates d (K, 3) at once
        (one set of numpy calls for every candidate of an LM step: the cost of a call is
        mostly numpy's per-call overhead, not arithmetic)."""
        d = np.atleast_2d(np.asarray(d, dtype=float))
        a, w, a0 = d[:, 0, None], d[:, 1, None], d[:, 2, None]               # (K, 1)
        arm, m2 = self.arm, self.arm.mass
        ncand = d.shape[0]
        # one period of the arm motion, P points: its wrench on the base, the harmonics of it
        tau = np.arange(self.points) * (2 * np.pi / self.points) / w          # (K, P)
        kin = self._kin(*(np.repeat(v[..., None], 3, -1)
                          for v in _sine(a, w, a0, tau)))                     # (K, P, 3, .)
        r2 = x[7:10]
        c = r2 + kin.rho
        iw = _mv(kin.inertia, kin.omega)
        u = np.concatenate([-m2 * kin.rho_dd,
                            -m2 * cross(c, kin.rho_dd + GRAVITY * Z_HAT)
                            - _mv(kin.inertia, kin.alpha) - cross(kin.omega, iw)],
                           axis=-1)                                    # (K, P, 3, 6)
        uk = np.fft.rfft(u, axis=1)[:, 1:self.harmonics + 1]            # (K, H, 3, 6)
        kin0 = self._kin(np.repeat(a0, 3, -1), np.zeros((ncand, 3)), np.zeros((ncand, 3)))
        mm, kk, bb = _matrices(x, arm, kin0)                            # (K, 3, 6, 6)
        kw = w * np.arange(1, uk.shape[1] + 1)                          # (K, H)
        kw5 = kw[:, :, None, None, None]
        z = -(kw5 ** 2) * mm[:, None] + 1j * kw5 * bb + kk[:, None]     # (K, H, 3, 6, 6)
        qk = np.linalg.solve(z, uk[..., None])[..., 0] * (2.0 / self.points)  # (K, H, 3, 6)
        ph = np.exp(1j * self.times[None, :, None] * kw[:, None, :])    # (K, T, H)
        kw_ = kw[:, None, None, :]
        ph3 = ph[:, None] * np.concatenate([np.ones_like(kw_), 1j * kw_, -kw_ * kw_], axis=1)
        motion = np.real(ph3 @ qk.reshape(ncand, 1, qk.shape[1], 18))   # (K, 3, T, 18)
        pos, vel, acc = (motion[:, i].reshape(ncand, -1, 3, 6) for i in range(3))
        kt = self._kin(*(np.repeat(v[..., None], 3, -1)
                         for v in _sine(a, w, a0, self.times[None, :])))
        ct = r2 + kt.rho
        force = m2 * (acc[..., :3] + cross(acc[..., 3:], ct) + kt.rho_dd
                      - GRAVITY * cross(pos[..., 3:], Z_HAT))
        torque = (cross(kt.rho, force + m2 * GRAVITY * Z_HAT)
                  + _mv(kt.inertia, kt.alpha + acc[..., 3:]))
        torque = torque - torque.mean(axis=1, keepdims=True)
        n = force.shape[0] * force.shape[1] * 3
        z3 = np.zeros((n, 3))
        rows, _ = assemble_rows(
            acc=acc[..., :3].reshape(n, 3), vel=vel[..., :3].reshape(n, 3),
            pos=pos[..., :3].reshape(n, 3), th=pos[..., 3:].reshape(n, 3),
            th_d=vel[..., 3:].reshape(n, 3), th_dd=acc[..., 3:].reshape(n, 3),
            gyro_reg=np.zeros((n, 18)), force=force.reshape(n, 3), tilt_x_force=z3,
            torque=torque.reshape(n, 3), accelerometer=self.accel)
        return rows.reshape(ncand, -1, 6, rows.shape[-1])


def _mv(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Matrix (..., 3, 3) times vector (..., 3)."""
    return (m @ v[..., None])[..., 0]


def _sine(a: np.ndarray | float, w: np.ndarray | float, a0: np.ndarray | float,
          t: np.ndarray | float) -> tuple:
    return a0 + a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t)


def _matrices(x: np.ndarray, arm: ArmModel, kin: ArmKinematics
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass, stiffness (with the arm's gravity term) and damping of the coupled base, per mode
    (kin with leading axes (..., 3 modes)): (..., 3, 6, 6) each, damping (6, 6)."""
    m2 = arm.mass
    mass = x[0]
    inertia = np.array([[x[1], x[6], x[4]], [x[6], x[2], x[5]], [x[4], x[5], x[3]]])
    c = x[7:10] + kin.rho
    sc = skew(c)
    lead = c.shape[:-1]
    mm = np.zeros(lead + (6, 6))
    mm[..., :3, :3] = (mass + m2) * np.eye(3)
    mm[..., :3, 3:] = -m2 * sc
    mm[..., 3:, :3] = m2 * sc
    mm[..., 3:, 3:] = inertia + kin.inertia - m2 * sc @ sc
    kk = np.zeros(lead + (6, 6))
    kk[:] = np.diag(np.concatenate([x[16:19], [x[20], x[19], x[21]]]))
    kk[..., 3:, 3:] += m2 * GRAVITY * sc @ skew(Z_HAT)
    bb = np.diag(np.concatenate([x[10:13], [x[14], x[13], x[15]]]))
    return mm, kk, bb


@dataclass
class CostContext:
    """What a strategy's cost needs besides d."""

    x: np.ndarray              # current consistent estimate (SI)
    info_scaled: np.ndarray    # current information matrix P^-1 in scaled coordinates
    scale: np.ndarray
    ranges: np.ndarray         # (22, 2) Eq. 2-12b ranges
    row_var: np.ndarray        # (6,) R per row type
    bits: int = 10
    active: np.ndarray | None = None   # parameters that count (observable subset)
    literal_eq_2_13: bool = False
    #: the matrix whose condition number the 'condition' strategy lowers (§2.6.1: "matrix A"):
    #: 'accumulated' = all rows so far + the predicted window, columns scaled by the prior
    #: ranges (default); 'window' = the predicted window's rows alone; 'unscaled' = accumulated
    #: in SI units (columns 0.01 .. 3000 apart)
    condition_matrix: ConditionMatrix = ConditionMatrix.ACCUMULATED

    def __post_init__(self) -> None:
        self.condition_matrix = choice(ConditionMatrix, self.condition_matrix,
                                       'condition_matrix', error=ExcitationError)


def residuals(d: np.ndarray, predictor: WindowPredictor, ctx: CostContext, *,
              strategy: Strategy | str) -> np.ndarray:
    """R(d) of Eq. 2-14 for a strategy (V = 1/2 R^T R, Eq. 2-15)."""
    return residuals_batch(np.asarray(d, dtype=float)[None], predictor, ctx,
                           strategy=strategy)[0]


def residuals_batch(d: np.ndarray, predictor: WindowPredictor, ctx: CostContext, *,
                    strategy: Strategy | str) -> np.ndarray:
    """R(d) of Eq. 2-14 for K candidates d (K, 3) at once: (K, len(R)). `strategy`: one of
    COSTED_STRATEGIES (ExcitationError otherwise, as for an unknown ctx.condition_matrix)."""
    strategy = costed_strategy(strategy)
    condition_matrix = choice(ConditionMatrix, ctx.condition_matrix, 'condition_matrix',
                              error=ExcitationError)
    rows = predictor.rows_batch(ctx.x, d)                    # (K, n, 6, 22)
    ncand, npar = rows.shape[0], rows.shape[-1]
    h = (rows * (ctx.scale / np.sqrt(ctx.row_var)[:, None])).reshape(ncand, -1, npar)
    j_new = ctx.info_scaled + predictor.weight * np.matmul(h.transpose(0, 2, 1), h)
    act = np.arange(npar) if ctx.active is None else np.flatnonzero(ctx.active)
    if strategy is Strategy.INFORMATION:
        var = np.diagonal(np.linalg.inv(j_new), axis1=1, axis2=2)
        std = np.sqrt(np.clip(var, 0, None)) * ctx.scale
        shape = std.shape
        info = mutual_information_bits(np.broadcast_to(ctx.x, shape), std,
                                       np.broadcast_to(ctx.ranges[:, 0], shape),
                                       np.broadcast_to(ctx.ranges[:, 1], shape),
                                       bits=ctx.bits)[:, act]
        u = info / ctx.bits
        if ctx.literal_eq_2_13:
            return np.sqrt(1.0 - u + u * u)
        return 1.0 - u
    j_act = j_new[:, act[:, None], act[None, :]]
    match strategy:
        case Strategy.CONDITION:
            match condition_matrix:
                case ConditionMatrix.WINDOW:
                    j_act = np.matmul(h.transpose(0, 2, 1), h)[:, act[:, None], act[None, :]]
                case ConditionMatrix.UNSCALED:
                    j_act = j_act / np.outer(ctx.scale[act], ctx.scale[act])
                case ConditionMatrix.ACCUMULATED:
                    pass
                case _:
                    assert_never(condition_matrix)
            ev = np.maximum(np.linalg.eigvalsh(j_act), 1e-300)
            return 0.5 * np.log10(ev[:, -1:] / ev[:, :1])
        case Strategy.D_OPTIMAL:
            sign, logdet = np.linalg.slogdet(j_act)
            return np.where(sign > 0, np.exp(-logdet / (2 * len(act))), 1e6)[:, None]
        case Strategy.A_OPTIMAL:
            return np.sqrt(np.trace(np.linalg.inv(j_act), axis1=1, axis2=2))[:, None]
    # costed_strategy let nothing else through (information returned above)
    raise AssertionError(f'strategy {strategy!r} has no cost')


def optimise(current: Excitation, predictor: WindowPredictor, ctx: CostContext, *,
             strategy: Strategy | str, bounds: ExcitationBounds | None = None,
             iterations: int = 3, starts: tuple[np.ndarray, ...] = (), fd_step: float = 0.02
             ) -> tuple[Excitation, float]:
    """Levenberg-Marquardt (Eq. 2-16 .. 2-20) over d in unit box coordinates, from the best of
    the current d (warm start: last window's optimum) and optional extra starts; returns the
    feasible excitation and its V(d).

    The candidates of a step are costed together (residuals_batch): the starts with the
    forward-difference neighbours of the current d (J of Eq. 2-16), then per iteration the
    line-search points alpha = 1, 1/2, 1/4 (Eq. 2-19) with the neighbours of the full step
    (the next iteration's Jacobian when the full step is taken, as it mostly is). The iterates
    are exactly those of the one-at-a-time algorithm; only the evaluations are grouped (3 numpy
    passes instead of ~14 for 2 iterations). 'constant' returns `current` and NaN; a name
    that is not a Strategy is refused (ExcitationError naming them)."""
    strategy = choice(Strategy, strategy, 'strategy', error=ExcitationError)
    if strategy is Strategy.CONSTANT:
        return current, float('nan')
    bounds = bounds or ExcitationBounds()

    def costs(us: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        r = residuals_batch(bounds.feasible_batch(bounds.from_unit(np.stack(us))), predictor,
                            ctx, strategy=strategy)
        return 0.5 * np.einsum('kr,kr->k', r, r), r

    def neighbours(u: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
        du = np.where(u + fd_step <= 1, fd_step, -fd_step)
        return [u + du[k] * np.eye(3)[k] for k in range(3)], du

    u_starts = [bounds.to_unit(bounds.feasible(np.asarray(d0, dtype=float)))
                for d0 in (current.d, *starts)]
    ns = len(u_starts)
    nb, du = neighbours(u_starts[0])
    v_all, r_all = costs(u_starts + nb)
    best = int(np.argmin(v_all[:ns]))       # first of equal costs, as a sequential scan
    u, v, r = u_starts[best], float(v_all[best]), r_all[best]
    fd = (r_all[ns:], du) if best == 0 else None
    mu = 1e-3
    alphas = (1.0, 0.5, 0.25)
    for it in range(iterations):
        if fd is None:
            nb, du = neighbours(u)
            fd = (costs(nb)[1], du)
        jac = ((fd[0] - r) / fd[1][:, None]).T                 # (len(R), 3): J of Eq. 2-16
        g = jac.T @ r                                         # Eq. 2-16
        jtj = jac.T @ jac                                     # Eq. 2-17 without S(d)
        step = -np.linalg.solve(jtj + mu * (np.diag(np.diag(jtj)) + 1e-9 * np.eye(3)), g)
        trial = [np.clip(u + a * step, 0.0, 1.0) for a in alphas]
        last = it == iterations - 1
        if last:
            nb = []                     # no finite differences after the last step
        else:
            nb, du = neighbours(trial[0])
        v_all, r_all = costs(trial + nb)
        fd = None
        moved = False
        for i in range(len(alphas)):                           # Eq. 2-19 line search
            if v_all[i] < v:
                u, v, r, moved = trial[i], float(v_all[i]), r_all[i], True
                if i == 0 and not last:
                    fd = (r_all[len(alphas):], du)
                break
        mu = mu * 0.3 if moved else mu * 10.0
    d = bounds.feasible(bounds.from_unit(u))
    if np.allclose(d, current.d, rtol=1e-6, atol=1e-9):
        return current, v
    return replace(current, amplitude_rad=float(d[0]), frequency_rad_s=float(d[1]),
                   offset_rad=float(d[2])), v


class ArmReference:
    """The arm base joints' reference (arm_joint_1, arm_joint_2) over time for the rotation modes
    of §2.2, without steps.

    modes: per mode (joint driven, joint-1 hold angle, unused), the driven joint following the
    excitation f(t - t0). A new mode or excitation never steps the command: the reference blends
    from the trajectory it follows into the new one with a quintic smoothstep (position, speed
    and acceleration continuous) no faster than `speed_rad_s`. A step makes an effort-limited
    joint controller whip the arm at tens of rad/s: base loads of ~100 N for a few ms, far
    outside the small-motion model of Eq. 2-1 (and outside what a simulated or real F/T sensor
    resolves). A mode driving a joint that is not one of ARM_JOINTS is refused
    (ExcitationError)."""

    def __init__(self, modes: Sequence[tuple[str, float, float]], *, speed_rad_s: float = 1.5,
                 min_blend_s: float = 0.2) -> None:
        bad = [m[0] for m in modes if m[0] not in ARM_JOINTS]
        if bad:
            raise ExcitationError(f'a mode drives one of {list(ARM_JOINTS)}, got {bad}')
        self.modes = modes
        self.speed, self.min_blend = speed_rad_s, min_blend_s
        self._key: tuple | None = None
        self._old: Callable[[float], tuple[np.ndarray, np.ndarray]] | None = None
        self._new: Callable[[float], tuple[np.ndarray, np.ndarray]] | None = None
        self._t0 = 0.0
        self._dur = 1.0
        self._home: np.ndarray | None = None

    def _target(self, mode: int, exc: Excitation, t0: float
                ) -> Callable[[float], tuple[np.ndarray, np.ndarray]]:
        joint, hold1, _ = self.modes[mode]

        def ref(t: float) -> tuple[np.ndarray, np.ndarray]:
            f, fd, _ = exc(t - t0)
            match joint:
                case 'arm_joint_1':
                    return np.array([float(f), 0.0]), np.array([float(fd), 0.0])
                case 'arm_joint_2':
                    return np.array([hold1, float(f)]), np.array([0.0, float(fd)])
            raise AssertionError(f'joint {joint!r} passed the constructor')
        return ref

    def update(self, now: float, mode: int, exc: Excitation, exc_t0: float,
               here: np.ndarray, horizon_s: float, lead_s: float = 0.0) -> None:
        """Follow mode / excitation, blending in from `now + lead_s` on (until then the old
        reference holds: a command that reaches the arm up to lead_s late finds it on the same
        path); `here`: joint positions for the first call (the pose `rest` returns to)."""
        self._switch((mode, exc, exc_t0), self._target(mode, exc, exc_t0), now, here,
                     horizon_s, lead_s)

    def rest(self, now: float, here: np.ndarray, lead_s: float = 0.0) -> float:
        """Blend from the reference into standing still at the pose of the first `update`
        (`here` if there was none) from `now + lead_s` on, as smoothly as any other switch; the
        time at which the arm is at rest. A trajectory that ends while the arm still swings
        leaves the joint controller holding the last point: a speed step, the whip `update`'s
        blends avoid."""
        home = np.array(self._home if self._home is not None else here, dtype=float)
        zero = np.zeros(2)

        def still(_t: float) -> tuple[np.ndarray, np.ndarray]:
            return home, zero
        self._switch(('rest',), still, now, here, 1.0, lead_s)   # 1 s: the swing's reach
        return self._t0 + self._dur

    def _switch(self, key: tuple, new: Callable[[float], tuple[np.ndarray, np.ndarray]],
                now: float, here: np.ndarray, horizon_s: float, lead_s: float) -> None:
        if key == self._key:
            if self._old is not None and now >= self._t0 + self._dur:
                self._old = None            # blend over: forget the old trajectory
            return
        live: Callable[[float], tuple[np.ndarray, np.ndarray]]
        if self._new is None:
            here = np.asarray(here, dtype=float)
            self._home = here.copy()
            zero = np.zeros(2)

            def hold(_t: float) -> tuple[np.ndarray, np.ndarray]:
                return here, zero
            live = hold
        else:
            live = self.__call__
        start = now + lead_s
        span = np.linspace(start, start + horizon_s, 25)
        gap = max(float(np.max(np.abs(live(t)[0] - new(t)[0]))) for t in span)
        dur = max(self.min_blend, 1.875 * gap / self.speed)
        # the old side, tabulated from a little before `now` (a command may restate the last
        # moments before it) to the blend's end (1 ms, linear interpolation): blends that
        # overlap never nest
        t_a = now - 0.05
        grid = np.linspace(t_a, start + dur, int(np.ceil((start + dur - t_a) / 1e-3)) + 1)
        pos, vel = (np.array(v) for v in zip(*(live(t) for t in grid), strict=False))

        def old(t: float) -> tuple[np.ndarray, np.ndarray]:
            return (np.array([np.interp(t, grid, pos[:, j]) for j in range(2)]),
                    np.array([np.interp(t, grid, vel[:, j]) for j in range(2)]))
        self._old, self._new = old, new
        self._t0, self._dur = start, dur
        self._key = key

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, speed) of (arm_joint_1, arm_joint_2) at t."""
        assert self._new is not None, 'no reference yet (start or rest first)'
        return _blend(self._old, self._new, self._t0, self._dur, t)


def _blend(old: Callable[[float], tuple[np.ndarray, np.ndarray]] | None,
           new: Callable[[float], tuple[np.ndarray, np.ndarray]], t0: float, dur: float, t: float
           ) -> tuple[np.ndarray, np.ndarray]:
    qn, vn = new(t)
    u = (t - t0) / dur
    if old is None or u >= 1.0:
        return qn, vn
    qo, vo = old(t)
    u = max(u, 0.0)
    s = u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
    ds = 30.0 * u * u * (1.0 - u) ** 2 / dur
    return qo + s * (qn - qo), vo + s * (vn - vo) + ds * (qn - qo)
