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
- condition: log10 condition number of the scaled accumulated information matrix (A^T A).
- d_optimal: det(J)^(-1/(2n)) (maximises log det of the information matrix J).
- a_optimal: sqrt(trace(J^-1)).
- constant: Eq. 2-21, never changed.
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .information import mutual_information_bits
from .model import GRAVITY, ArmModel, assemble_rows, cross, skew
from .modelsim import Z_HAT, JointLimits, arm_kinematics

STRATEGIES = ('constant', 'information', 'condition', 'd_optimal', 'a_optimal')


class ExcitationError(ValueError):
    """Bad excitation arguments."""


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


@dataclass(frozen=True)
class ExcitationBounds:
    """Box on d plus the arm joint position / speed / acceleration (torque) limits."""

    amplitude: tuple[float, float] = (0.05, 1.2)
    frequency: tuple[float, float] = (0.5, 30.0)
    offset: tuple[float, float] = (-1.0, 1.0)
    limits: JointLimits = JointLimits()

    def feasible(self, d: np.ndarray) -> np.ndarray:
        """Clip d into the box, then shrink the amplitude to the joint limits."""
        a, w, a0 = (float(np.clip(v, *b)) for v, b in
                    zip(d, (self.amplitude, self.frequency, self.offset)))
        lim = self.limits
        a = min(a, lim.position_rad - abs(a0), lim.speed_rad_s / w, lim.accel_rad_s2 / w ** 2)
        return np.array([max(a, 1e-3), w, a0])

    def to_unit(self, d: np.ndarray) -> np.ndarray:
        lo, hi = self._box()
        return (np.asarray(d) - lo) / (hi - lo)

    def from_unit(self, u: np.ndarray) -> np.ndarray:
        lo, hi = self._box()
        return lo + np.clip(u, 0.0, 1.0) * (hi - lo)

    def _box(self) -> tuple[np.ndarray, np.ndarray]:
        b = np.array([self.amplitude, self.frequency, self.offset])
        return b[:, 0], b[:, 1]


class WindowPredictor:
    """Predicted rows of A x = F for the next window under excitation d (harmonic steady state
    of the base model linearised at the mean arm pose, with the current estimate)."""

    def __init__(self, *, arm: ArmModel, times: np.ndarray, harmonics: int = 4,
                 points: int = 32, accelerometer: bool = True, weight: float = 1.0) -> None:
        """times: prediction instants in the window; weight: filter updates per instant."""
        self.arm, self.times = arm, np.asarray(times, dtype=float)
        self.weight = float(weight)
        self.harmonics, self.points, self.accel = harmonics, points, accelerometer

    def rows(self, x: np.ndarray, d: np.ndarray) -> np.ndarray:
        """(len(times) * 3 modes, 6, 22) predicted rows for consistent estimate x."""
        a, w, a0 = d
        arm, m2 = self.arm, self.arm.mass
        tau = np.arange(self.points) * (2 * np.pi / w) / self.points
        q, qd, qdd = (np.repeat(v[:, None], 3, 1) for v in _sine(a, w, a0, tau))
        kin = arm_kinematics(arm, q, qd, qdd)
        r2 = x[7:10]
        c = r2 + kin.rho
        iw = np.einsum('...ab,...b->...a', kin.inertia, kin.omega)
        u = np.concatenate([-m2 * kin.rho_dd,
                            -m2 * cross(c, kin.rho_dd + GRAVITY * Z_HAT)
                            - np.einsum('...ab,...b->...a', kin.inertia, kin.alpha)
                            - cross(kin.omega, iw)], axis=-1)      # (P, 3, 6)
        uk = np.fft.rfft(u, axis=0)[1:self.harmonics + 1]               # (H, 3, 6)
        kin0 = arm_kinematics(arm, np.full(3, a0), np.zeros(3), np.zeros(3))
        mm, kk, bb = _matrices(x, arm, kin0)
        kw = w * np.arange(1, uk.shape[0] + 1)
        z = (-(kw ** 2)[:, None, None, None] * mm + 1j * kw[:, None, None, None] * bb + kk)
        qk = np.linalg.solve(z, uk[..., None])[..., 0] * (2.0 / self.points)  # (H, 3, 6)
        ph = np.exp(1j * np.outer(self.times, kw))                      # (T, H)
        pos = np.real(np.einsum('th,hmc->tmc', ph, qk))
        vel = np.real(np.einsum('th,hmc->tmc', ph * 1j * kw, qk))
        acc = np.real(np.einsum('th,hmc->tmc', ph * -(kw ** 2), qk))
        qt, qdt, qddt = (np.repeat(v[:, None], 3, 1) for v in _sine(a, w, a0, self.times))
        kt = arm_kinematics(arm, qt, qdt, qddt)
        ct = r2 + kt.rho
        force = m2 * (acc[..., :3] + cross(acc[..., 3:], ct) + kt.rho_dd
                      - GRAVITY * cross(pos[..., 3:], Z_HAT))
        torque = (cross(kt.rho, force + m2 * GRAVITY * Z_HAT)
                  + np.einsum('...ab,...b->...a', kt.inertia, kt.alpha + acc[..., 3:]))
        torque = torque - torque.mean(axis=0)
        n = force.shape[0] * 3
        z3 = np.zeros((n, 3))
        rows, _ = assemble_rows(
            acc=acc[..., :3].reshape(n, 3), vel=vel[..., :3].reshape(n, 3),
            pos=pos[..., :3].reshape(n, 3), th=pos[..., 3:].reshape(n, 3),
            th_d=vel[..., 3:].reshape(n, 3), th_dd=acc[..., 3:].reshape(n, 3),
            gyro_reg=np.zeros((n, 18)), force=force.reshape(n, 3), tilt_x_force=z3,
            torque=torque.reshape(n, 3), accelerometer=self.accel)
        return rows


def _sine(a: float, w: float, a0: float, t: np.ndarray) -> tuple:
    return a0 + a * np.sin(w * t), a * w * np.cos(w * t), -a * w * w * np.sin(w * t)


def _matrices(x: np.ndarray, arm: ArmModel, kin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mass, stiffness (with the arm's gravity term) and damping of the coupled base, per mode."""
    m2 = arm.mass
    mass = x[0]
    inertia = np.array([[x[1], x[6], x[4]], [x[6], x[2], x[5]], [x[4], x[5], x[3]]])
    c = x[7:10] + kin.rho
    sc = skew(c)
    mm = np.zeros((3, 6, 6))
    mm[:, :3, :3] = (mass + m2) * np.eye(3)
    mm[:, :3, 3:] = -m2 * sc
    mm[:, 3:, :3] = m2 * sc
    mm[:, 3:, 3:] = inertia + kin.inertia - m2 * sc @ sc
    kk = np.zeros((3, 6, 6))
    kk[:] = np.diag(np.concatenate([x[16:19], [x[20], x[19], x[21]]]))
    kk[:, 3:, 3:] += m2 * GRAVITY * sc @ skew(Z_HAT)
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


def residuals(strategy: str, d: np.ndarray, predictor: WindowPredictor,
              ctx: CostContext) -> np.ndarray:
    """R(d) of Eq. 2-14 for a strategy (V = 1/2 R^T R, Eq. 2-15)."""
    rows = predictor.rows(ctx.x, d)                          # (n, 6, 22)
    h = (rows * ctx.scale / np.sqrt(ctx.row_var)[None, :, None]).reshape(-1, rows.shape[-1])
    j_new = ctx.info_scaled + predictor.weight * (h.T @ h)
    act = np.arange(len(ctx.scale)) if ctx.active is None else np.flatnonzero(ctx.active)
    j_act = j_new[np.ix_(act, act)]
    if strategy == 'information':
        cov = np.linalg.inv(j_new)
        std = np.sqrt(np.clip(np.diag(cov), 0, None)) * ctx.scale
        info = mutual_information_bits(ctx.x, std, ctx.ranges[:, 0], ctx.ranges[:, 1],
                                       bits=ctx.bits)[act]
        u = info / ctx.bits
        if ctx.literal_eq_2_13:
            return np.sqrt(1.0 - u + u * u)
        return 1.0 - u
    if strategy == 'condition':
        ev = np.linalg.eigvalsh(j_act)
        return np.array([0.5 * np.log10(max(ev[-1], 1e-300) / max(ev[0], 1e-300))])
    if strategy == 'd_optimal':
        sign, logdet = np.linalg.slogdet(j_act)
        return np.array([np.exp(-logdet / (2 * len(act)))]) if sign > 0 else np.array([1e6])
    if strategy == 'a_optimal':
        return np.array([np.sqrt(np.trace(np.linalg.inv(j_act)))])
    raise ExcitationError(f'unknown strategy {strategy!r} (one of {STRATEGIES})')


def optimise(strategy: str, current: Excitation, predictor: WindowPredictor, ctx: CostContext,
             *, bounds: ExcitationBounds | None = None, iterations: int = 3,
             starts: tuple[np.ndarray, ...] = (), fd_step: float = 0.02
             ) -> tuple[Excitation, float]:
    """Levenberg-Marquardt (Eq. 2-16 .. 2-20) over d in unit box coordinates, from the best of
    the current d and optional extra starts; returns the feasible excitation and its V(d)."""
    if strategy == 'constant':
        return current, float('nan')
    bounds = bounds or ExcitationBounds()

    def cost_of(u: np.ndarray) -> tuple[float, np.ndarray]:
        r = residuals(strategy, bounds.feasible(bounds.from_unit(u)), predictor, ctx)
        return 0.5 * float(r @ r), r

    # pick the best start by its cost, then refine it (LM from every start costs 2x more)
    best_u, best_v, best_r = None, np.inf, None
    for d0 in (current.d, *starts):
        u0 = bounds.to_unit(bounds.feasible(np.asarray(d0, dtype=float)))
        v0, r0 = cost_of(u0)
        if v0 < best_v:
            best_u, best_v, best_r = u0, v0, r0
    u, v, r = best_u, best_v, best_r
    mu = 1e-3
    for _ in range(iterations):
        jac = np.empty((r.size, 3))
        for k in range(3):  # forward differences: J of Eq. 2-16
            du = np.zeros(3)
            du[k] = fd_step if u[k] + fd_step <= 1 else -fd_step
            jac[:, k] = (cost_of(u + du)[1] - r) / du[k]
        g = jac.T @ r                                         # Eq. 2-16
        jtj = jac.T @ jac                                     # Eq. 2-17 without S(d)
        step = -np.linalg.solve(jtj + mu * (np.diag(np.diag(jtj)) + 1e-9 * np.eye(3)), g)
        moved = False
        for alpha in (1.0, 0.5, 0.25):                         # Eq. 2-19 line search
            u_new = np.clip(u + alpha * step, 0.0, 1.0)
            v_new, r_new = cost_of(u_new)
            if v_new < v:
                u, v, r, moved = u_new, v_new, r_new, True
                break
        mu = mu * 0.3 if moved else mu * 10.0
    best_u, best_v = u, v
    d = bounds.feasible(bounds.from_unit(best_u))
    if np.allclose(d, current.d, rtol=1e-6, atol=1e-9):
        return current, best_v
    return replace(current, amplitude_rad=float(d[0]), frequency_rad_s=float(d[1]),
                   offset_rad=float(d[2])), best_v


class ArmReference:
    """The arm base joints' reference (arm_joint_1, arm_joint_2) over time for the rotation modes
    of §2.2, without steps.

    modes: per mode (joint driven, joint-1 hold angle, unused), the driven joint following the
    excitation f(t - t0). A new mode or excitation never steps the command: the reference blends
    from the trajectory it follows into the new one with a quintic smoothstep (position, speed
    and acceleration continuous) no faster than `speed_rad_s`. A step makes an effort-limited
    joint controller whip the arm at tens of rad/s: base loads of ~100 N for a few ms, far
    outside the small-motion model of Eq. 2-1 (and outside what a simulated or real F/T sensor
    resolves)."""

    def __init__(self, modes, *, speed_rad_s: float = 1.5, min_blend_s: float = 0.2) -> None:
        self.modes = modes
        self.speed, self.min_blend = speed_rad_s, min_blend_s
        self._key = None
        self._old = None
        self._new = None
        self._t0 = 0.0
        self._dur = 1.0

    def _target(self, mode: int, exc: Excitation, t0: float):
        joint, hold1, _ = self.modes[mode]

        def ref(t: float) -> tuple[np.ndarray, np.ndarray]:
            f, fd, _ = exc(t - t0)
            if joint == 'arm_joint_1':
                return np.array([float(f), 0.0]), np.array([float(fd), 0.0])
            return np.array([hold1, float(f)]), np.array([0.0, float(fd)])
        return ref

    def update(self, now: float, mode: int, exc: Excitation, exc_t0: float,
               here: np.ndarray, horizon_s: float, lead_s: float = 0.0) -> None:
        """Follow mode / excitation, blending in from `now + lead_s` on (until then the old
        reference holds: a command that reaches the arm up to lead_s late finds it on the same
        path); `here`: joint positions for the first call."""
        key = (mode, exc, exc_t0)
        if key == self._key:
            if self._old is not None and now >= self._t0 + self._dur:
                self._old = None            # blend over: forget the old trajectory
            return
        new = self._target(mode, exc, exc_t0)
        if self._new is None:
            here = np.asarray(here, dtype=float)
            zero = np.zeros(2)

            def live(_t: float) -> tuple[np.ndarray, np.ndarray]:
                return here, zero
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
        pos, vel = (np.array(v) for v in zip(*(live(t) for t in grid)))

        def old(t: float) -> tuple[np.ndarray, np.ndarray]:
            return (np.array([np.interp(t, grid, pos[:, j]) for j in range(2)]),
                    np.array([np.interp(t, grid, vel[:, j]) for j in range(2)]))
        self._old, self._new = old, new
        self._t0, self._dur = start, dur
        self._key = key

    def __call__(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(position, speed) of (arm_joint_1, arm_joint_2) at t."""
        return _blend(self._old, self._new, self._t0, self._dur, t)


def _blend(old, new, t0: float, dur: float, t: float) -> tuple[np.ndarray, np.ndarray]:
    qn, vn = new(t)
    u = (t - t0) / dur
    if old is None or u >= 1.0:
        return qn, vn
    qo, vo = old(t)
    u = max(u, 0.0)
    s = u * u * u * (10.0 - 15.0 * u + 6.0 * u * u)
    ds = 30.0 * u * u * (1.0 - u) ** 2 / dur
    return qo + s * (qn - qo), vo + s * (vn - vo) + ds * (qn - qo)
