"""The base model of Eq. 2-1 / B-1..B-4 recast as A x = F for the 22 unknowns (no rclpy).

Conventions (REP 103, base frame at the base c.g.): theta = (roll, pitch, yaw) small rotations of
the base, r the small c.g. translation, F/N the wrench the base exerts ON the arm at the arm base
(the F/T sensor, Eq. B-1), in base axes. Per sample and per arm rotation mode there are six rows:

  translation (Eq. B-4, 1st):  m a + B_r r_dot + K_r r             = -(F + theta x F)
  rotation    (Eq. B-4, 2nd):  I th_dd + th_d x (I th_d) + r_2 x F
                                + B_th th_d + K_th th              = -N

where `a` is the kinematic c.g. acceleration from the accelerometer's specific force
(a = f_meas - g z + g theta x z, the d(R_0^-1 g) term of Eq. 2-1) and theta x F rotates the
measured base-frame force into the suspension's axes. Constant (static) parts of both sides are
removed by filtering every column and the right-hand side with the same band-pass W(s) (a linear
filter preserves A x = F because x is constant); r and r_dot come from the accelerometer through
W/s^2 and W/s, theta_dd from the gyro through W s, so no signal is ever differentiated or
integrated open loop. The three arm modes (rotation about x, y, z) stack to 18 rows (§2.2).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml
from scipy import signal

from coop_common.dynparams import PARAM_NAMES

from .errors import CoopIdError

GRAVITY = 9.81
N_PARAMS = len(PARAM_NAMES)
IDX = {n: i for i, n in enumerate(PARAM_NAMES)}
#: Inertia entries in parameter order and their (row, col) in the 3x3 tensor.
_INERTIA = {'Ixx': ((0, 0),), 'Iyy': ((1, 1),), 'Izz': ((2, 2),), 'Ixz': ((0, 2), (2, 0)),
            'Iyz': ((1, 2), (2, 1)), 'Ixy': ((0, 1), (1, 0))}
#: Damping / stiffness parameter of each axis (x, y, z) for translation and rotation.
B_R = ('b_x', 'b_y', 'b_z')
K_R = ('k_x', 'k_y', 'k_z')
B_TH = ('b_roll', 'b_pitch', 'b_yaw')
K_TH = ('k_roll', 'k_pitch', 'k_yaw')
#: Columns that need the accelerometer (the translational subset). Without an accelerometer
#: (the thesis's experimental rover, §2.6.2) these are unobservable and reported so.
TRANSLATIONAL = ('mass', *B_R, *K_R)
DEFAULT_PRIOR_PATH = Path(__file__).resolve().parent / 'data' / 'prior_ranges.yaml'


class ModelError(CoopIdError):
    """Bad shapes or values handed to the model."""


@dataclass(frozen=True)
class ArmModel:
    """Known arm of §2.6.1: mass 1 kg, inertia about its c.m. (arm frame), c.m. distance."""

    mass: float = 1.0
    inertia: np.ndarray = field(default_factory=lambda: np.diag([0.02, 0.001, 0.02]))
    com_distance_m: float = 0.25


def load_prior_ranges(path: str | Path | None = None) -> np.ndarray:
    """(22, 2) a-priori [min, max] per parameter (Eq. 2-12b range; never the truth)."""
    path = Path(path) if path is not None else DEFAULT_PRIOR_PATH
    data = yaml.safe_load(Path(path).read_text())
    try:
        rng = np.array([[float(data[n][0]), float(data[n][1])] for n in PARAM_NAMES])
    except (KeyError, TypeError, IndexError, ValueError) as exc:
        raise ModelError(f'{path}: bad prior range file: {exc}') from exc
    if not np.all(rng[:, 1] > rng[:, 0]):
        raise ModelError(f'{path}: every range needs max > min')
    return rng


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b over the last axis (broadcasting); np.cross is ~10x slower on small arrays."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def skew(v: np.ndarray) -> np.ndarray:
    """[v]x for (..., 3) vectors: (..., 3, 3)."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1], out[..., 0, 2] = -v[..., 2], v[..., 1]
    out[..., 1, 0], out[..., 1, 2] = v[..., 2], -v[..., 0]
    out[..., 2, 0], out[..., 2, 1] = -v[..., 1], v[..., 0]
    return out


def inertia_basis() -> np.ndarray:
    """(6, 3, 3) unit tensors E_j with I = sum_j x_j E_j over Ixx, Iyy, Izz, Ixz, Iyz, Ixy."""
    basis = np.zeros((6, 3, 3))
    for j, name in enumerate(('Ixx', 'Iyy', 'Izz', 'Ixz', 'Iyz', 'Ixy')):
        for r, c in _INERTIA[name]:
            basis[j, r, c] = 1.0
    return basis


_EI = inertia_basis()


def raw_channels(*, specific_force: np.ndarray, gyro: np.ndarray, incl_roll_pitch: np.ndarray,
                 force: np.ndarray, torque: np.ndarray,
                 tilt: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Per-sample products of Eq. 2-1 formed before filtering ((n, 3) inputs, one arm mode).

    Returns the channels the filter bank consumes: kinematic acceleration a (Eq. 2-1
    d(R_0^-1 g) term), gyro, inclinometer roll/pitch, gyroscopic regressor
    th_d x (E_j th_d), force F, theta x F and torque N. `tilt` (n, 2): the base roll/pitch to
    use in the two products (default: the inclinometer), e.g. from TiltTracker when the
    inclinometer's resolution is coarser than the tilt the excitation produces.
    """
    arrays = [np.asarray(a, dtype=float) for a in
              (specific_force, gyro, incl_roll_pitch, force, torque)]
    n = arrays[0].shape[0]
    shapes = [(n, 3), (n, 3), (n, 2), (n, 3), (n, 3)]
    for a, shp, name in zip(arrays, shapes, ('specific_force', 'gyro', 'incl', 'force',
                                              'torque'), strict=False):
        if a.shape != shp:
            raise ModelError(f'{name}: expected shape {shp}, got {a.shape}')
    f_sp, w, incl, force, torque = arrays
    tl = incl if tilt is None else np.asarray(tilt, dtype=float)
    if tl.shape != (n, 2):
        raise ModelError(f'tilt: expected shape {(n, 2)}, got {tl.shape}')
    theta_tilt = np.column_stack([tl, np.zeros(n)])
    tilt_x_z = np.column_stack([tl[:, 1], -tl[:, 0], np.zeros(n)])  # theta x z_hat
    acc = f_sp + GRAVITY * tilt_x_z
    acc[:, 2] -= GRAVITY
    gyro_reg = cross(w[:, None, :], np.einsum('jab,nb->nja', _EI, w))  # (n, 6, 3)
    return {
        'acc': acc, 'gyro': w, 'incl': incl,
        'gyro_reg': gyro_reg.reshape(n, 18),
        'force': force, 'tilt_x_force': cross(theta_tilt, force), 'torque': torque,
    }


def assemble_rows(*, acc: np.ndarray, vel: np.ndarray, pos: np.ndarray, th: np.ndarray,
                  th_d: np.ndarray, th_dd: np.ndarray, gyro_reg: np.ndarray,
                  force: np.ndarray, tilt_x_force: np.ndarray, torque: np.ndarray,
                  accelerometer: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 2-1 / B-4 as A x = F: (n, 6, 22) rows and (n, 6) right-hand sides for one arm mode.

    Inputs are (already filtered) signals; with accelerometer=False the three translational rows
    are returned as zeros (no information), as on the thesis's experimental rover.
    """
    n = acc.shape[0]
    a = np.zeros((n, 6, N_PARAMS))
    y = np.zeros((n, 6))
    if accelerometer:
        a[:, 0:3, IDX['mass']] = acc
        for i in range(3):
            a[:, i, IDX[B_R[i]]] = vel[:, i]
            a[:, i, IDX[K_R[i]]] = pos[:, i]
        y[:, 0:3] = -(force + tilt_x_force)
    # I th_dd + th_d x (I th_d): column j is E_j th_dd + th_d x (E_j th_d)
    inert = np.einsum('jab,nb->naj', _EI, th_dd) + gyro_reg.reshape(n, 6, 3).transpose(0, 2, 1)
    for j, name in enumerate(('Ixx', 'Iyy', 'Izz', 'Ixz', 'Iyz', 'Ixy')):
        a[:, 3:6, IDX[name]] = inert[:, :, j]
    # r_2 x F: column k is e_k x F
    fx, fy, fz = force[:, 0], force[:, 1], force[:, 2]
    a[:, 4, IDX['cg_x']], a[:, 5, IDX['cg_x']] = -fz, fy      # e_x x F = (0, -Fz, Fy)
    a[:, 3, IDX['cg_y']], a[:, 5, IDX['cg_y']] = fz, -fx      # e_y x F = (Fz, 0, -Fx)
    a[:, 3, IDX['cg_z']], a[:, 4, IDX['cg_z']] = -fy, fx      # e_z x F = (-Fy, Fx, 0)
    for i in range(3):
        a[:, 3 + i, IDX[B_TH[i]]] = th_d[:, i]
        a[:, 3 + i, IDX[K_TH[i]]] = th[:, i]
    y[:, 3:6] = -torque
    return a, y


class FilterBank:
    """Streaming band-pass W(s) = s^3 l2^2 / ((s + l1)^3 (s + l2)^2) and its s^-2 .. s^2 siblings.

    The same W is applied to every column and the right-hand side so the filtered equation is
    exact (x constant). Three zeros at s = 0 so even W/s^2 (position from acceleration) blocks
    static offsets and sensor bias; the low-pass stage removes the noise above the excitation
    band. Each channel starts in the steady state of its first sample (at rest before).
    """

    def __init__(self, *, rate_hz: float = 200.0, highpass_rad_s: float = 3.0,
                 lowpass_rad_s: float = 40.0) -> None:
        if not (rate_hz > 0 and 0 < highpass_rad_s < lowpass_rad_s < np.pi * rate_hz):
            raise ModelError('need 0 < highpass < lowpass < Nyquist')
        l1, l2 = highpass_rad_s, lowpass_rad_s
        poles = [-l1] * 3 + [-l2] * 2
        # second-order sections: the transfer-function form of 5 clustered poles near z = 1 is
        # numerically useless
        self._sos = {p: signal.zpk2sos(*signal.bilinear_zpk([0.0] * (3 + p), poles, l2 ** 2,
                                                             fs=rate_hz))
                     for p in (-2, -1, 0, 1, 2)}
        self._state: dict[tuple[str, int], np.ndarray] = {}

    def apply(self, name: str, power: int, x: np.ndarray) -> np.ndarray:
        """Filter (n, c) samples of channel `name` through W s^power, keeping the state."""
        sos = self._sos[power]
        key = (name, power)
        zi = self._state.get(key)
        if zi is None:  # at rest before the first sample: steady state for its value
            zi = signal.sosfilt_zi(sos)[:, :, None] * x[0][None, None, :]
        out, zf = signal.sosfilt(sos, x, axis=0, zi=zi)
        self._state[key] = zf
        return out

    def reset(self) -> None:
        self._state.clear()


def filtered_rows(bank: FilterBank, ch: dict[str, np.ndarray], *, accelerometer: bool = True,
                  tag: str = '', incl_weight: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Filter the raw channels of one arm mode and assemble Eq. 2-1 rows (see module doc).

    incl_weight: share of the inclinometer in the roll/pitch angle columns (the rest: the
    integrated gyro). 0 when the inclinometer cannot resolve the dynamic tilt."""
    f = bank.apply
    gyro_int = f(tag + 'gyro', -1, ch['gyro'])
    th = gyro_int.copy()
    if incl_weight > 0:
        # roll/pitch seen twice (inclinometer and integrated gyro): weigh the two
        th[:, 0:2] = ((1.0 - incl_weight) * gyro_int[:, 0:2]
                      + incl_weight * f(tag + 'incl', 0, ch['incl']))
    return assemble_rows(
        acc=f(tag + 'acc', 0, ch['acc']), vel=f(tag + 'acc', -1, ch['acc']),
        pos=f(tag + 'acc', -2, ch['acc']), th=th, th_d=f(tag + 'gyro', 0, ch['gyro']),
        th_dd=f(tag + 'gyro', 1, ch['gyro']), gyro_reg=f(tag + 'gyro_reg', 0, ch['gyro_reg']),
        force=f(tag + 'force', 0, ch['force']),
        tilt_x_force=f(tag + 'tilt_x_force', 0, ch['tilt_x_force']),
        torque=f(tag + 'torque', 0, ch['torque']), accelerometer=accelerometer)


def noise_gram(bank: FilterBank, *, seconds: float = 20.0, rate_hz: float = 200.0
               ) -> np.ndarray:
    """(4, 4) Gram <h_p, h_q> of the impulse responses of W s^p, p = -2..1: the covariance of
    unit white sample noise after the filters (index p + 2)."""
    n = int(seconds * rate_hz)
    imp = np.zeros((n, 1))
    imp[0, 0] = 1.0
    fresh = FilterBank.__new__(FilterBank)
    fresh._sos, fresh._state = bank._sos, {}
    h = np.stack([fresh.apply('imp', p, np.vstack([np.zeros((1, 1)), imp]))[1:, 0]
                  for p in (-2, -1, 0, 1)])
    return h @ h.T


@dataclass(frozen=True)
class SensorNoise:
    """1-sigma white noise of each sensor channel (one arm mode): datasheet / message
    covariances, never the parameter truth."""

    specific_force: np.ndarray   # (3,) m/s^2
    gyro: np.ndarray             # (3,) rad/s
    incl: np.ndarray             # (2,) rad
    force: np.ndarray            # (3,) N


def regressor_noise(noise: SensorNoise, gram: np.ndarray, *, accelerometer: bool = True,
                    incl_weight: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Errors-in-variables statistics of the filtered rows (see filtered_rows):
    (6, 22, 22) covariance of the noise in each row's regressors and (6, 22) covariance between
    that noise and the row's right-hand-side noise. Used to remove the attenuation bias of
    least squares with noisy regressors (bias-compensated LS)."""
    g = gram
    cov = np.zeros((6, N_PARAMS, N_PARAMS))
    cxy = np.zeros((6, N_PARAMS))
    s_f, s_w, s_i, s_fo = (np.asarray(v, dtype=float) for v in
                           (noise.specific_force, noise.gyro, noise.incl, noise.force))
    if incl_weight == 0:
        s_i = np.zeros(2)        # tilt from the integrated gyro (TiltTracker): no incl noise
    if accelerometer:
        # acc_kin = f + g theta x z: x row sees pitch, y row sees roll
        tilt = (s_i[1], s_i[0], 0.0)
        for i in range(3):
            var = s_f[i] ** 2 + (GRAVITY * tilt[i]) ** 2
            cols = [IDX['mass'], IDX[B_R[i]], IDX[K_R[i]]]
            pw = [2, 1, 0]                       # W, W/s, W/s^2 -> gram index p + 2
            for a_, pa in zip(cols, pw, strict=False):
                for b_, pb in zip(cols, pw, strict=False):
                    cov[i, a_, b_] = var * g[pa, pb]
            # rhs -(F + theta x F): (theta x F)_x = pitch F_z, _y = -roll F_z with F_z ~ m2 g;
            # the mass column carries +g pitch (x) and -g roll (y): correlated with the rhs
            if i < 2:
                cxy[i, IDX['mass']] = -GRAVITY * tilt[i] ** 2 * GRAVITY * g[2, 2]
    inert = {0: ('Ixx', 'Ixy', 'Ixz'), 1: ('Ixy', 'Iyy', 'Iyz'), 2: ('Ixz', 'Iyz', 'Izz')}
    cg_cols = {0: (('cg_y', 2), ('cg_z', 1)), 1: (('cg_x', 2), ('cg_z', 0)),
               2: (('cg_x', 1), ('cg_y', 0))}
    for i in range(3):
        r = 3 + i
        # theta_dd_j (gyro_j through W s) in the inertia column coupling row i with axis j
        for j in range(3):
            cov[r, IDX[inert[i][j]], IDX[inert[i][j]]] += s_w[j] ** 2 * g[3, 3]
        # gyro_i also drives b_th (W) and, its share, k_th (W/s); inclinometer the rest
        c_dd, c_b, c_k = IDX[inert[i][i]], IDX[B_TH[i]], IDX[K_TH[i]]
        wk = 1.0 - incl_weight if i < 2 else 1.0
        for a_, pa, ca in ((c_dd, 3, 1.0), (c_b, 2, 1.0), (c_k, 1, wk)):
            for b_, pb, cb in ((c_dd, 3, 1.0), (c_b, 2, 1.0), (c_k, 1, wk)):
                if a_ == c_dd and b_ == c_dd:
                    continue
                cov[r, a_, b_] += ca * cb * s_w[i] ** 2 * g[pa, pb]
        if i < 2:
            cov[r, c_k, c_k] += incl_weight ** 2 * s_i[i] ** 2 * g[2, 2]
        for name, comp in cg_cols[i]:
            cov[r, IDX[name], IDX[name]] += s_fo[comp] ** 2 * g[2, 2]
    return cov, cxy


class TiltTracker:
    """Base roll/pitch at the sample rate from the gyro, integrated from rest (trapezoid), held
    to the inclinometer only at very low frequency (complementary filter, crossover
    `crossover_rad_s`). For the products theta x F and g theta x z, which need the angle before
    filtering, when the inclinometer's step is coarser than the dynamic tilt."""

    def __init__(self, *, rate_hz: float = 200.0, crossover_rad_s: float = 0.2) -> None:
        self.dt, self.c = 1.0 / rate_hz, crossover_rad_s
        self._theta: np.ndarray | None = None
        self._w_prev = np.zeros(2)

    def update(self, gyro: np.ndarray, incl: np.ndarray) -> np.ndarray:
        """(n, 2) roll/pitch for (n, 3) gyro and (n, 2) inclinometer samples."""
        gyro, incl = np.asarray(gyro, dtype=float), np.asarray(incl, dtype=float)
        out = np.empty((gyro.shape[0], 2))
        th = self._theta
        for k in range(gyro.shape[0]):
            w = gyro[k, :2]
            if th is None:       # at rest: start from the inclinometer
                th, self._w_prev = incl[k].copy(), w
            else:
                th = th + 0.5 * self.dt * (w + self._w_prev) + self.c * self.dt * (incl[k] - th)
                self._w_prev = w
            out[k] = th
        self._theta = th
        return out
