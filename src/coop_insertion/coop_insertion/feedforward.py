"""Model-based feed-forward of a compliant base's motion into the arm's joint control (Sujan
2002, app. A.1-A.2, Eq. A-3/A-4), no rclpy.

The arm rides on a base that sways on its suspension. Written for the arm alone, the base's
motion d (its c.g.'s small translation r and rotation theta, base axes, REP 103 order x, y, z,
roll, pitch, yaw) is a disturbance on every joint (Eq. A-4):

    tau = H(q) q'' + h(q, q') q' + F(q) d'' + f(q, q') d' + G(q)

and the joint command of A.2 step 3 is PD + gravity compensation + that disturbance fed forward:

    tau_cmd = K_p (q_r - q) + K_D (q_r' - q') + F d'' + f d' + G.

`ArmModel` is the arm of coop_common.rover_geometry (four links on the F/T sensor at r_2 from the
base c.g., a load in the gripper) with a recursive Newton-Euler pass on a moving base: F is
d tau / d d'' (the coupling inertia), f d' the torques the base's turn rate drives at the
current joint rates (`coupling` gives f as the thesis's matrix, the linear part; the torque
uses the whole term, whose centrifugal rest a steady turn makes the larger), G the weight's
torques in a tilted base. r_2 is one of the identified parameters, so the same arm on nominal
or identified parameters has different F and f.

The base's motion d'', d' comes from `BaseObserver`: the base of Eq. B-4, linear about rest,

    M d'' + B d' + K d = w,    w = -(F_s, N_s + r_2 x F_s) (deviations from rest)

built from the 22 parameters of ch. 2 (mass, inertia, r_2, damping, stiffness), driven by the
F/T sensor's wrench (F_s, N_s: the base's push on the arm, so the arm's on the base is its
negative) and corrected by the gyro and accelerometer in a Kalman filter; d'' is the mean the
model predicts over the coming period from the filtered state with the measured wrench held
(the torque is held over that period, and a drive step settles the base's turn within a
millisecond, far inside it). This is A.1's model predictive feed-forward: the
sensed disturbance passed through the base's dynamic model; a model with the wrong mass,
stiffness or r_2 predicts the wrong d''. The anchor (where the wheels hold the suspension) is
the rover's commanded motion: a step of its velocity is a step of the relative rate d'.

`FeedForward` joins them and changes parameter sets without a jump: the torque blends from the
old model's to the new one's over `blend_s`. `accept_estimate` says whether an identified set
may be used at all (physically consistent, observed enough, recent), and why not.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike
from scipy.linalg import expm

from coop_common.dynparams import BaseParameters, check_physical
from coop_common.rover_geometry import ARM_JOINT1_ABOVE_SENSOR_M, ARM_LINKS, CARD_OFFSET_M

from .errors import InsertionError

__all__ = ['Acceptance', 'ArmModel', 'BaseObserver', 'FeedForward', 'FeedForwardError',
           'ParameterSource',
           'accept_estimate']

GRAVITY = 9.81


class FeedForwardError(InsertionError):
    """Bad input to the feed-forward core: wrong shapes, non-finite values, a parameter set
    that is not a physical body."""


class ParameterSource(Enum):
    """Which base parameters the feed-forward's model uses (NONE: no base feed-forward, the
    PD and gravity compensation alone)."""

    NONE = 'none'
    NOMINAL = 'nominal'
    IDENTIFIED = 'identified'


def _vec(name: str, v: ArrayLike, n: int) -> np.ndarray:
    a = np.asarray(v, dtype=float).reshape(-1)
    if a.shape != (n,):
        raise FeedForwardError(f'{name}: {a.size} values, expected {n}')
    if not np.all(np.isfinite(a)):
        raise FeedForwardError(f'{name}: not finite')
    return a


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation by `angle` about the unit `axis` (Rodrigues; built directly about y and z,
    the rover arm's axes)."""
    c, s = math.cos(angle), math.sin(angle)
    if axis[0] == 0.0 and axis[2] == 0.0 and axis[1] == 1.0:
        return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    if axis[0] == 0.0 and axis[1] == 0.0 and axis[2] == 1.0:
        return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    x, y, z = axis
    c, s = np.cos(angle), np.sin(angle)
    k = np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


@dataclass(frozen=True)
class ArmModel:
    """A serial arm of revolute joints on the base: joint i sits at `origins[i]` in link i-1's
    frame (link 0 = the base c.g. frame) and turns about `axes[i]`; link i has `masses[i]` at
    `coms[i]` with `inertias[i]` (3x3, about the c.o.m., link axes)."""

    origins: np.ndarray          # (n, 3)
    axes: np.ndarray             # (n, 3) unit
    masses: np.ndarray           # (n,)
    coms: np.ndarray             # (n, 3)
    inertias: np.ndarray         # (n, 3, 3)

    @property
    def n(self) -> int:
        return len(self.masses)

    @classmethod
    def rover(cls, cg_to_arm: ArrayLike, *, load_kg: float = 0.0,
              load_offset_m: float = CARD_OFFSET_M) -> ArmModel:
        """The thesis rover's arm (coop_common.rover_geometry) mounted at r_2 = `cg_to_arm`
        from the base c.g., with a point load in the gripper (`load_kg` at `load_offset_m`
        along the last link: the card, 0.01 kg, or a part)."""
        r2 = _vec('cg_to_arm', cg_to_arm, 3)
        if not (np.isfinite(load_kg) and load_kg >= 0.0):
            raise FeedForwardError(f'load_kg {load_kg}: must be >= 0')
        n = len(ARM_LINKS)
        origins = np.zeros((n, 3))
        origins[0] = r2 + (0.0, 0.0, ARM_JOINT1_ABOVE_SENSOR_M)
        origins[1] = (0.0, 0.0, ARM_LINKS[0].length)
        for k in (2, 3):
            origins[k] = (ARM_LINKS[k - 1].length, 0.0, 0.0)
        axes = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
        masses = np.array([link.mass for link in ARM_LINKS])
        coms = np.array([link.com for link in ARM_LINKS], dtype=float)
        inertias = np.array([np.diag(link.inertia) for link in ARM_LINKS])
        if load_kg > 0.0:
            # the load joins the last link: combined mass, c.o.m. and inertia (parallel axes)
            m4, c4 = masses[-1], coms[-1].copy()
            cl = np.array([load_offset_m, 0.0, 0.0])
            m = m4 + load_kg
            c = (m4 * c4 + load_kg * cl) / m
            inertias[-1] = (inertias[-1] + _shift(m4, c4 - c) + _shift(load_kg, cl - c))
            masses[-1], coms[-1] = m, c
        return cls(origins, axes, masses, coms, inertias)

    def com_positions(self, q: ArrayLike) -> np.ndarray:
        """Each link's centre of mass in the base frame at q (n, 3): the arm as particles
        (Eq. A-5's tip-over sums)."""
        q = _vec('q', q, self.n)
        rot, origin = np.eye(3), np.zeros(3)
        out = np.empty((self.n, 3))
        for i in range(self.n):
            origin = origin + rot @ self.origins[i]
            rot = rot @ _axis_rotation(self.axes[i], q[i])
            out[i] = origin + rot @ self.coms[i]
        return out

    def joint_torques(self, q: ArrayLike, qd: ArrayLike, qdd: ArrayLike, *,
                      base_acceleration: ArrayLike = (0.0, 0.0, 0.0),
                      base_angular_velocity: ArrayLike = (0.0, 0.0, 0.0),
                      base_angular_acceleration: ArrayLike = (0.0, 0.0, 0.0)) -> np.ndarray:
        """Inverse dynamics (recursive Newton-Euler): the joint torques that move the arm at
        q, q', q'' on a base whose c.g. frame accelerates by `base_acceleration` (m/s^2, base
        axes; add -g in base axes for the weight) and turns at `base_angular_velocity` with
        `base_angular_acceleration` (rad/s, rad/s^2)."""
        q, qd, qdd = (_vec(nm, v, self.n) for nm, v in (('q', q), ('qd', qd), ('qdd', qdd)))
        base = [_vec(nm, v, 3)[None] for nm, v in (
            ('base_acceleration', base_acceleration),
            ('base_angular_velocity', base_angular_velocity),
            ('base_angular_acceleration', base_angular_acceleration))]
        return self._rnea(q, qd[None], qdd[None], *base)[0]

    def _rnea(self, q: np.ndarray, qd: np.ndarray, qdd: np.ndarray, a: np.ndarray,
              w: np.ndarray, dw: np.ndarray) -> np.ndarray:
        """Newton-Euler for k cases at once on one configuration q (n,): joint rates and
        accelerations (k, n), base acceleration, turn rate and its rate (k, 3); (k, n).
        Row vectors throughout: v @ rot is rot^T v, v @ [c]x is v x c; a turn rate's
        cross products go through its skew matrices, one build per link."""
        rots, forces, moments = [], [], []
        sw = _skew_rows(w)                                    # the base's
        for i in range(self.n):
            rot = _axis_rotation(self.axes[i], q[i])          # link i in link i-1
            sp, z, sz = self._skew_origins[i], self.axes[i], self._skew_axes[i]
            # the joint's origin moves with the link before it, then into link i's axes
            a = (a + dw @ sp + _apply(sw, w @ sp)) @ rot
            w_in = w @ rot
            w = w_in + qd[:, i, None] * z
            # w_in x (qd z) = qd (w_in x z)
            dw = dw @ rot + qdd[:, i, None] * z + qd[:, i, None] * (w_in @ sz)
            sw = _skew_rows(w)
            sc, inertia = self._skew_coms[i], self.inertias[i]
            spin = _apply(sw, np.stack([w @ sc, w @ inertia.T], axis=-1))
            forces.append(self.masses[i] * (a + dw @ sc + spin[..., 0]))
            moments.append(dw @ inertia.T + spin[..., 1])
            rots.append(rot)
        tau = np.empty(qd.shape)
        f_next = n_next = np.zeros((0, 3))
        for i in reversed(range(self.n)):
            # c x f = -(f x c)
            f, n = forces[i], moments[i] - forces[i] @ self._skew_coms[i]
            if i + 1 < self.n:
                # the next link's wrench in this link's axes: rot v is v rot^T for rows
                r_next = rots[i + 1]
                f_out, n_out = f_next @ r_next.T, n_next @ r_next.T
                f = f + f_out
                n = n + n_out - f_out @ self._skew_origins[i + 1]
            tau[:, i] = n @ self.axes[i]
            f_next, n_next = f, n
        return tau

    @cached_property
    def _skew_axes(self) -> np.ndarray:
        return _skews(self.axes)

    @cached_property
    def _skew_origins(self) -> np.ndarray:
        return _skews(self.origins)

    @cached_property
    def _skew_coms(self) -> np.ndarray:
        return _skews(self.coms)

    def coupling(self, q: ArrayLike, qd: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        """(F, f), each (n, 6): the joint torques per unit base acceleration d'' and per unit
        base rate d' (columns x, y, z, roll, pitch, yaw; base axes) at q with joint rates qd.
        F is exact (the torques are linear in d''); f is the derivative at d' = 0 of the
        torques that are quadratic in the base's turn rate (a translation's rate drives no
        torque), taken by a central difference, exact for a quadratic."""
        q, qd = _vec('q', q, self.n), _vec('qd', qd, self.n)
        eye, zero3 = np.eye(3), np.zeros((3, 3))
        rates = np.zeros((12, self.n))
        rates[6:] = qd
        tau = self._rnea(q, rates, np.zeros((12, self.n)), np.vstack([eye, zero3, zero3, zero3]),
                         np.vstack([zero3, zero3, eye, -eye]),
                         np.vstack([zero3, eye, zero3, zero3]))
        small_f = np.zeros((self.n, 6))
        small_f[:, 3:] = (tau[6:9] - tau[9:12]).T / 2.0
        return tau[:6].T, small_f

    def gravity(self, q: ArrayLike, *, roll: float = 0.0, pitch: float = 0.0) -> np.ndarray:
        """G: the torques that hold the arm's weight at q on a base tilted by roll and pitch
        (rad)."""
        q = _vec('q', q, self.n)
        zero = np.zeros((1, self.n))
        return self._rnea(q, zero, zero, GRAVITY * _up(roll, pitch)[None], np.zeros((1, 3)),
                          np.zeros((1, 3)))[0]

    def terms(self, q: ArrayLike, qd: ArrayLike, *, base_rate: ArrayLike = (0.0, 0.0, 0.0),
              roll: float = 0.0, pitch: float = 0.0, qd_ref: ArrayLike | None = None,
              qdd_ref: ArrayLike | None = None
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """What Eq. A-4 needs at one instant, in one Newton-Euler pass of 10 cases: F (as
        `coupling`); the torques the base's turn rate `base_rate` drives at the joint rates qd
        (f(q, q', d') d' in full: its linear part, `coupling`'s f d', and the centrifugal
        rest, which a steady turn makes the larger); G (as `gravity`); and the arm's own
        H q_r'' + h q_r' for a reference's rates at q (zero without one)."""
        q, qd = _vec('q', q, self.n), _vec('qd', qd, self.n)
        omega = _vec('base_rate', base_rate, 3)
        eye, zero3, none = np.eye(3), np.zeros((3, 3)), np.zeros((4, 3))
        # cases: 3 base accelerations, 3 turn accelerations, the weight, the reference on a
        # base at rest, the joint rates with and without the base's turn
        rates = np.zeros((10, self.n))
        accels = np.zeros((10, self.n))
        if qd_ref is not None:
            rates[7] = _vec('qd_ref', qd_ref, self.n)
        if qdd_ref is not None:
            accels[7] = _vec('qdd_ref', qdd_ref, self.n)
        rates[8:] = qd
        lin = np.zeros((10, 3))
        lin[:3], lin[6] = eye, GRAVITY * _up(roll, pitch)
        turn = np.zeros((10, 3))
        turn[8] = omega
        tau = self._rnea(q, rates, accels, lin, turn, np.vstack([zero3, eye, none]))
        return tau[:6].T, tau[8] - tau[9], tau[6], tau[7]


def _up(roll: float, pitch: float) -> np.ndarray:
    """The world's up in the axes of a base tilted by roll and pitch: R^T z for
    R = R_y(pitch) R_x(roll)."""
    cr, sr, cp, sp = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch)
    return np.array([-sp, sr * cp, cr * cp])


def _skews(v: np.ndarray) -> np.ndarray:
    """[v]x for each row of v (n, 3): (n, 3, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2], out[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    out[:, 1, 0], out[:, 2, 0], out[:, 2, 1] = v[:, 2], -v[:, 1], v[:, 0]
    return out


#: skew(w) = (w @ _LEVI).reshape(3, 3) for a row w: [w]x[i, j] = -eps_ijl w_l
_LEVI = np.zeros((3, 9))
for _i, _j, _l, _sign in ((0, 1, 2, -1.0), (0, 2, 1, 1.0), (1, 0, 2, 1.0), (1, 2, 0, -1.0),
                          (2, 0, 1, -1.0), (2, 1, 0, 1.0)):
    _LEVI[_l, 3 * _i + _j] = _sign


def _skew_rows(w: np.ndarray) -> np.ndarray:
    """[w]x for each row of w (k, 3): (k, 3, 3), in one product."""
    return (w @ _LEVI).reshape(-1, 3, 3)


def _apply(sw: np.ndarray, v: np.ndarray) -> np.ndarray:
    """w x v per row, from w's skew matrices (k, 3, 3), for v (k, 3) or several (k, 3, m)."""
    if v.ndim == 2:
        return np.matmul(sw, v[:, :, None])[:, :, 0]
    return np.matmul(sw, v)


def _shift(mass: float, c: np.ndarray) -> np.ndarray:
    """Parallel-axis term m (|c|^2 E - c c^T)."""
    return mass * (float(c @ c) * np.eye(3) - np.outer(c, c))


def _parameters(params: BaseParameters) -> BaseParameters:
    reasons = check_physical(params.to_vector())
    if reasons:
        raise FeedForwardError('base parameters are not a physical body: ' + '; '.join(reasons))
    return params


@dataclass
class BaseObserver:
    """The base's deflection d, d' (12 states, base axes, deviations from the rest it was
    started at) in a Kalman filter on Eq. B-4's linear model (module docstring). Each `update`
    takes one sensor sample: the F/T wrench (F_s, N_s about the sensor), the gyro and the
    accelerometer's specific force, and the anchor's commanded velocity (forward speed and
    yaw rate); the first sample is the rest."""

    params: BaseParameters
    dt: float
    gyro_std: float = 2e-3            # rad/s, the gyro and the model error it absorbs
    accel_std: float = 2e-2           # m/s^2
    model_accel_std: float = 0.05     # m/s^2 (rad/s^2) of unmodelled base acceleration
    x: np.ndarray = field(default_factory=lambda: np.zeros(12))
    p: np.ndarray = field(default_factory=lambda: np.eye(12) * 1e-6)
    _rest: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    _anchor: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not (np.isfinite(self.dt) and self.dt > 0.0):
            raise FeedForwardError(f'dt {self.dt}: must be > 0')
        self.set_parameters(self.params)

    def set_parameters(self, params: BaseParameters) -> None:
        """Use another parameter set from now on (the state carries over)."""
        p = _parameters(params)
        mass = np.zeros((6, 6))
        mass[:3, :3] = p.mass * np.eye(3)
        mass[3:, 3:] = p.inertia
        self._m_inv = np.linalg.inv(mass)
        self._k, self._b = np.diag(p.stiffness), np.diag(p.damping)
        self._r2 = np.asarray(p.cg_to_arm, float)
        # x' = A x + Bu w: continuous, then exact zero-order-hold discretisation
        a = np.zeros((12, 12))
        a[:6, 6:] = np.eye(6)
        a[6:, :6] = -self._m_inv @ self._k
        a[6:, 6:] = -self._m_inv @ self._b
        bu = np.zeros((12, 6))
        bu[6:] = self._m_inv
        block = np.zeros((18, 18))
        block[:12, :12], block[:12, 12:] = a * self.dt, bu * self.dt
        e = expm(block)
        self._ad, self._bd = e[:12, :12], e[:12, 12:]
        self._a_acc, self._b_acc = a[6:], bu[6:]         # d'' = A_acc x + B_acc w
        self.params = p
        q = np.zeros((12, 12))
        q[6:, 6:] = np.eye(6) * (self.model_accel_std * self.dt) ** 2
        self._q = q

    def base_wrench(self, force: np.ndarray, torque: np.ndarray) -> np.ndarray:
        """w of Eq. B-4 (about the c.g.) from a sensor wrench's deviation from rest."""
        r, f = self._r2, force
        moment = (r[1] * f[2] - r[2] * f[1], r[2] * f[0] - r[0] * f[2], r[0] * f[1] - r[1] * f[0])
        return -np.concatenate([force, torque + moment])

    def update(self, *, force: ArrayLike, torque: ArrayLike, gyro: ArrayLike,
               specific_force: ArrayLike, anchor_speed: float = 0.0,
               anchor_yaw_rate: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """One sample in; the base's d'' over the next period of dt (the mean the model
        predicts for it) and d' now (each 6: x, y, z, roll, pitch, yaw), d' with the anchor's
        own yaw rate added (the arm feels the whole turn rate)."""
        f, n = _vec('force', force, 3), _vec('torque', torque, 3)
        g, sf = _vec('gyro', gyro, 3), _vec('specific_force', specific_force, 3)
        if not (np.isfinite(anchor_speed) and np.isfinite(anchor_yaw_rate)):
            raise FeedForwardError('anchor velocity not finite')
        if self._rest is None:
            self._rest = (f, n, sf)
            self._anchor = (float(anchor_speed), float(anchor_yaw_rate))
        f0, n0, sf0 = self._rest
        w = self.base_wrench(f - f0, n - n0)
        # the sample ends the period just gone (its wrench that period's): predict across it
        # from the last estimate, then correct
        self.x = self._ad @ self.x + self._bd @ w
        self.p = self._ad @ self.p @ self._ad.T + self._q
        # measurements: the turn rate relative to the anchor (as it was commanded over that
        # period), and the c.g.'s acceleration (deviation of the specific force; the tilt's
        # share of gravity is slow and small)
        h = np.zeros((6, 12))
        h[:3, 9:] = np.eye(3)
        h[3:] = self._a_acc[:3]
        z = np.concatenate([g - (0.0, 0.0, self._anchor[1]), sf - sf0])
        z_hat = h @ self.x + np.concatenate([np.zeros(3), self._b_acc[:3] @ w])
        r = np.diag([self.gyro_std ** 2] * 3 + [self.accel_std ** 2] * 3)
        s = h @ self.p @ h.T + r
        k = np.linalg.solve(s, h @ self.p).T
        self.x = self.x + k @ (z - z_hat)
        self.p = (np.eye(12) - k @ h) @ self.p
        # the command for the coming period: a step of the anchor's velocity is the opposite
        # step of the base's rate relative to it
        dv, dw = anchor_speed - self._anchor[0], anchor_yaw_rate - self._anchor[1]
        if dv or dw:
            self.x[6] -= dv
            self.x[11] -= dw
            self._anchor = (float(anchor_speed), float(anchor_yaw_rate))
        # d'' over the coming period, the torque's zero-order hold: the change of rate the
        # model predicts across it (a drive step settles the base's turn rate within a
        # millisecond, far inside one period: its instantaneous d'' would overshoot 10-fold)
        dd = ((self._ad @ self.x + self._bd @ w)[6:] - self.x[6:]) / self.dt
        d = self.x[6:].copy()
        d[5] += anchor_yaw_rate
        return dd, d


@dataclass(frozen=True)
class Acceptance:
    """Whether an identified parameter set may drive the feed-forward, and why not."""

    ok: bool
    reason: str


def accept_estimate(values: ArrayLike, *, observable: Sequence[bool],
                    physically_consistent: bool, age_s: float, max_age_s: float,
                    min_observable: int = 20) -> Acceptance:
    """An identified set is used only when it is a physical body (checked here too, not only
    trusted from the flag), at most `max_age_s` old, and at least `min_observable` of its 22
    parameters are observed. An unobserved parameter's value is the identifier's best guess
    so far (its estimate with the prior range's weight), which is kept: replacing it by a
    nominal value can make the set unphysical (a nominal I_z beside estimated I_x, I_y breaks
    the triangle inequality). Otherwise the caller keeps its last good set (or the nominal)."""
    x = np.asarray(values, dtype=float)
    if x.shape != (22,) or not np.all(np.isfinite(x)):
        return Acceptance(False, f'{x.size} values or not finite (need 22)')
    seen = sum(bool(o) for o in observable)
    if len(observable) != 22 or seen < min_observable:
        return Acceptance(False, f'{seen} of 22 parameters observable yet (need '
                                 f'{min_observable})')
    reasons = check_physical(x)
    if not physically_consistent or reasons:
        return Acceptance(False, 'not physically consistent'
                          + (': ' + '; '.join(reasons) if reasons else ''))
    if not age_s <= max_age_s:
        return Acceptance(False, f'stale: {age_s:.1f} s old (max {max_age_s:.1f} s)')
    return Acceptance(True, '')


class FeedForward:
    """Eq. A-4's feed-forward torque for one arm: F d'' + f d' + G (f d' in full, centrifugal
    part too) from the base observer's
    d'', d' and the arm's model, with parameter changes blended over `blend_s`.

    `source` NONE gives G alone (the baseline: PD and gravity compensation); otherwise
    `params` is the base model in use (nominal or identified)."""

    def __init__(self, params: BaseParameters, *, dt: float, source: ParameterSource,
                 load_kg: float = 0.0, blend_s: float = 0.5) -> None:
        if not blend_s >= 0.0:
            raise FeedForwardError(f'blend_s {blend_s}: must be >= 0')
        self.source, self.dt, self.blend_s, self.load_kg = source, dt, blend_s, load_kg
        self._observer = BaseObserver(params, dt)
        self._arm = ArmModel.rover(params.cg_to_arm, load_kg=load_kg)
        self._old: tuple[BaseObserver, ArmModel] | None = None
        self._blend = 1.0

    @property
    def params(self) -> BaseParameters:
        return self._observer.params

    def set_parameters(self, params: BaseParameters) -> None:
        """Switch to another set: the new model starts from the current state and its torque
        takes over from the old one's linearly over blend_s (no jump)."""
        _parameters(params)
        old = (self._observer, self._arm)
        new = BaseObserver(params, self.dt)
        new.x, new.p = old[0].x.copy(), old[0].p.copy()
        new._rest, new._anchor = old[0]._rest, old[0]._anchor
        self._old = old if self.blend_s > 0.0 else None
        self._blend = 0.0 if self.blend_s > 0.0 else 1.0
        self._observer, self._arm = new, ArmModel.rover(params.cg_to_arm, load_kg=self.load_kg)

    def torque(self, *, q: ArrayLike, qd: ArrayLike, force: ArrayLike, torque: ArrayLike,
               gyro: ArrayLike, specific_force: ArrayLike, roll: float = 0.0,
               pitch: float = 0.0, anchor_speed: float = 0.0, anchor_yaw_rate: float = 0.0,
               qd_ref: ArrayLike | None = None, qdd_ref: ArrayLike | None = None
               ) -> np.ndarray:
        """The joint torques to add to the PD for one sensor sample (n,): the arm's own
        H q_r'' + h q_r' when given a reference's rates, G, and (unless NONE) F d'' + f d'.
        roll and pitch are the base's tilt at rest (the inclinometer's, which reads the
        specific force's direction and so not the sway); the observer adds the sway."""
        sample = dict(force=force, torque=torque, gyro=gyro, specific_force=specific_force,
                      anchor_speed=anchor_speed, anchor_yaw_rate=anchor_yaw_rate)
        ref = dict(qd_ref=qd_ref, qdd_ref=qdd_ref)
        tau = self._one(self._observer, self._arm, q, qd, roll, pitch, sample, ref)
        if self._old is not None:
            self._blend = min(1.0, self._blend + self.dt / self.blend_s)
            old = self._one(*self._old, q, qd, roll, pitch, sample, ref)
            tau = self._blend * tau + (1.0 - self._blend) * old
            if self._blend >= 1.0:
                self._old = None
        return tau

    def _one(self, observer: BaseObserver, arm: ArmModel, q: ArrayLike, qd: ArrayLike,
             roll: float, pitch: float, sample: dict, ref: dict) -> np.ndarray:
        dd, d = observer.update(**sample)
        if self.source is ParameterSource.NONE:
            _, _, g, own = arm.terms(q, qd, roll=roll, pitch=pitch, **ref)
            return own + g
        # the weight in the base as it sways: the rest tilt plus the observed deflection
        big_f, turning, g, own = arm.terms(q, qd, base_rate=d[3:], roll=roll + observer.x[3],
                                           pitch=pitch + observer.x[4], **ref)
        return own + big_f @ dd + turning + g
