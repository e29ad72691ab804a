"""Eq. 2-1 / B-4 against the PyBullet rover (rover_sim.world, no DDS): the identifier's own rows
A x = F with the TRUE parameter vector must balance on the simulator's data.

The arm is driven as the identifier node drives it (coop_id.excitation.ArmReference: rotation
modes z, y, x, blended without steps). Two sources of the base states:

- the simulator's truth (deflections dr, dtheta in the anchor frame, rates by differences),
  which checks the model and the F/T sensor;
- the sensors as the identifier uses them (accelerometer, gyro, TiltTracker), which checks the
  state reconstruction.
"""
import numpy as np
import pytest

from coop_common.dynparams import load_truth
from coop_id.excitation import ArmReference, Excitation
from coop_id.identifier_node import MODES
from coop_id.model import (
    FilterBank,
    TiltTracker,
    assemble_rows,
    cross,
    filtered_rows,
    inertia_basis,
    raw_channels,
)

world_mod = pytest.importorskip('rover_sim.world')
config_mod = pytest.importorskip('rover_sim.config')
compliance = pytest.importorskip('rover_sim.compliance')

SETTLE_S = 0.5
MODE_S = 1.0
SKIP = 140          # samples after the start: the band-pass filters' start-up


@pytest.fixture(scope='module')
def run():
    """3 s of the arm exciting the base, noise off: sensor readings and truth per 5 ms step."""
    truth = load_truth()
    cfg = config_mod.SimConfig(rovers=1, noise=config_mod.NoiseConfig(fraction=0.0),
                               stereo_rate_hz=0.0)
    exc = Excitation(0.5, 8.0, 0.5)
    ref = ArmReference(MODES)
    rec = {k: [] for k in ('f', 'n', 'sf', 'gyro', 'incl', 'dr', 'rot')}
    with world_mod.World(cfg, [truth]) as w:
        n_settle = int(round(SETTLE_S / w.dt))
        t0 = None
        for k in range(n_settle + int(round(3 * MODE_S / w.dt))):
            if k >= n_settle and (k - n_settle) % 80 == 0:      # a 0.4 s window
                now = w.time_s
                t0 = now if t0 is None else t0
                mode = int((now - t0) // MODE_S) % 3
                ref.update(now, mode, exc, t0,
                           w.joint_positions(0, ['arm_joint_1', 'arm_joint_2']), 1.2)
                # as the node: points on a 10 ms grid half a sample off the control instants
                g0 = np.floor((now - 0.5 * w.dt) / 0.01) * 0.01 + 0.5 * w.dt
                ts = np.arange(122) * 0.01
                w.command_arm(0, ['arm_joint_1', 'arm_joint_2'], ts,
                              [ref(g0 + tk)[0] for tk in ts], start_s=g0)
            w.step()
            if k < n_settle - 1:
                continue
            s, tr = w.sense(0), w.truth(0)
            for key, v in (('f', s.force), ('n', s.torque), ('sf', s.specific_force),
                           ('gyro', s.angular_velocity), ('incl', s.incl_angles),
                           ('dr', tr.dr), ('rot', tr.base_rotation)):
                rec[key].append(np.array(v, dtype=float))
        dt = w.dt
    out = {k: np.array(v) for k, v in rec.items()}
    out['dt'] = dt
    out['x'] = truth.to_vector()
    return out


def _mid(a):
    """Trapezoid mean over each sampling period of point samples (the F/T and the
    accelerometer report period means)."""
    out = a.copy()
    out[1:] = 0.5 * (a[1:] + a[:-1])
    return out


def _truth_rows(d):
    """Rows from the true deflections: position and rotation (small angles about the rest pose;
    the anchor does not move) through W s^p, rates by differences."""
    f = FilterBank().apply
    rot = d['rot']
    # rotation vector of each pose w.r.t. the rest pose: the compliance's dtheta
    th = np.array([compliance.rotation_vector(rot[0].T @ r) for r in rot])
    # period-mean body rate from consecutive poses (the gyroscopic products only)
    w = np.zeros_like(th)
    w[1:] = [compliance.rotation_vector(a.T @ b) / d['dt'] for a, b in zip(rot[:-1], rot[1:])]
    pos, ang = _mid(d['dr']), _mid(th)
    n = th.shape[0]
    reg = cross(w[:, None, :], np.einsum('jab,nb->nja', inertia_basis(), w)).reshape(n, 18)
    force, torque = d['f'], d['n']
    return assemble_rows(
        acc=f('r', 2, pos), vel=f('r', 1, pos), pos=f('r', 0, pos),
        th=f('t', 0, ang), th_d=f('t', 1, ang), th_dd=f('t', 2, ang),
        gyro_reg=f('g', 0, reg), force=f('F', 0, force),
        tilt_x_force=f('tF', 0, cross(ang, force)), torque=f('N', 0, torque))


def _sensor_rows(d):
    """Rows exactly as coop_id.identifier_core builds them (incl_weight 0: tilt from the gyro)."""
    tilt = TiltTracker(rate_hz=1.0 / d['dt']).update(d['gyro'], d['incl'])
    ch = raw_channels(specific_force=d['sf'], gyro=d['gyro'], incl_roll_pitch=d['incl'],
                      force=d['f'], torque=d['n'], tilt=tilt)
    return filtered_rows(FilterBank(rate_hz=1.0 / d['dt']), ch, incl_weight=0.0)


def _relative_residual(a, y, x):
    res = (y - a @ x)[SKIP:]
    return np.sqrt((res ** 2).mean(axis=0)) / np.sqrt((y[SKIP:] ** 2).mean(axis=0))


def test_excitation_moves_the_base_in_every_row(run):
    a, y = _truth_rows(run)
    rms = np.sqrt((y[SKIP:] ** 2).mean(axis=0))
    assert np.all(rms[:3] > 0.5) and np.all(rms[3:] > 0.2), rms     # N, N m


def test_true_states_balance_eq_2_1_with_the_true_parameters(run):
    """Model + F/T + truth agree: every row balances to a few % of its right-hand side."""
    a, y = _truth_rows(run)
    rel = _relative_residual(a, y, run['x'])
    assert np.all(rel[:3] < 0.05), rel
    assert np.all(rel[3:] < 0.10), rel


def test_accelerometer_states_balance_the_translational_rows(run):
    a, y = _sensor_rows(run)
    rel = _relative_residual(a, y, run['x'])
    assert np.all(rel[:3] < 0.08), rel


def test_gyro_states_balance_the_rotational_rows(run):
    """The gyro reports the period-mean body rate, like the F/T and the accelerometer report
    period means (a point sample aliased the sub-period torque ripple: 124% residual)."""
    a, y = _sensor_rows(run)
    rel = _relative_residual(a, y, run['x'])
    assert np.all(rel[3:] < 0.10), rel

