"""The feed-forward core (app. A, Eq. A-4): the arm's inverse dynamics on a moving base against
a hand-derived one-link case and PyBullet's, the base observer against the model it assumes,
parameter switches without a jump, and which estimates may be used."""
from __future__ import annotations

import math

import numpy as np
import pybullet as pb
import pytest

from coop_common.dynparams import load_truth
from coop_insertion.feedforward import (
    ArmModel,
    BaseObserver,
    FeedForward,
    FeedForwardError,
    ParameterSource,
    accept_estimate,
)
from rover_sim.rover_model import rover_urdf

G = 9.81


def one_link(m: float, length: float, origin: tuple[float, float, float]) -> ArmModel:
    """A point mass m at `length` along the link's x, the joint at `origin` turning about y."""
    return ArmModel(origins=np.array([origin], float), axes=np.array([[0.0, 1.0, 0.0]]),
                    masses=np.array([m]), coms=np.array([[length, 0.0, 0.0]]),
                    inertias=np.zeros((1, 3, 3)))


@pytest.mark.parametrize('q', [0.0, 0.4, -1.1, 2.0])
def test_one_link_coupling_and_gravity_are_the_hand_derived_ones(q):
    """Point mass m at l on a joint about y at p from the c.g.: its centre c = l (cos q, 0,
    -sin q) from the joint. A base acceleration a needs tau = m (c_z a_x - c_x a_z); a pitch
    acceleration alpha accelerates the mass by alpha y x (p + c), which needs
    m (|c|^2 + c . p) per rad/s^2; roll and yaw push it along the joint's axis (no torque).
    The weight on a base pitched by th needs -m g l cos(q + th). One link has no base-rate
    term (f = 0)."""
    m, length, p = 0.7, 0.3, np.array([0.1, 0.0, 0.2])
    arm = one_link(m, length, tuple(p))
    cx, cz = length * math.cos(q), -length * math.sin(q)
    big_f, small_f = arm.coupling([q], [1.3])
    expect = [m * cz, 0.0, -m * cx, 0.0, m * (cx * cx + cz * cz + cx * p[0] + cz * p[2]), 0.0]
    np.testing.assert_allclose(big_f[0], expect, atol=1e-12)
    np.testing.assert_allclose(small_f, 0.0, atol=1e-12)
    for th in (0.0, 0.15, -0.3):
        np.testing.assert_allclose(arm.gravity([q], pitch=th),
                                   [-m * G * length * math.cos(q + th)], atol=1e-12)
    # and the whole Eq. A-4 for a joint acceleration: m l^2 q'' on top
    tau = arm.joint_torques([q], [0.0], [2.0], base_acceleration=[0.5, 0.0, -0.2],
                            base_angular_acceleration=[0.0, 0.8, 0.0])
    assert tau[0] == pytest.approx(m * length ** 2 * 2.0 + big_f[0] @ [0.5, 0, -0.2, 0, 0.8, 0])


def test_the_rover_arm_matches_pybullets_inverse_dynamics():
    """The four-link arm of rover_geometry on a fixed base against PyBullet's inverse dynamics of
    the simulator's own URDF, gravity tilted: gravity -g is the base accelerating by +g, so
    this checks F's translational columns, the joint-rate terms h q' and H q''; and the links'
    centres of mass against PyBullet's."""
    truth = load_truth()
    arm = ArmModel.rover(truth.cg_to_arm)
    client = pb.connect(pb.DIRECT)
    try:
        import tempfile
        with tempfile.NamedTemporaryFile('w', suffix='.urdf') as f:
            f.write(rover_urdf('r', truth))
            f.flush()
            body = pb.loadURDF(f.name, useFixedBase=True, flags=pb.URDF_USE_INERTIA_FROM_FILE,
                               physicsClientId=client)
        names = [pb.getJointInfo(body, j, physicsClientId=client)[1].decode()
                 for j in range(pb.getNumJoints(body, physicsClientId=client))]
        movable = [j for j in range(len(names))
                   if pb.getJointInfo(body, j, physicsClientId=client)[2] != pb.JOINT_FIXED]
        arm_cols = [movable.index(names.index(f'arm_joint_{k}')) for k in range(1, 5)]
        rng = np.random.default_rng(3)
        for _ in range(5):
            q, qd, qdd = rng.uniform(-1, 1, (3, 4))
            g = rng.normal(size=3)
            g *= G / np.linalg.norm(g)
            pb.setGravity(*g, physicsClientId=client)
            full = [np.zeros(len(movable)) for _ in range(3)]
            for v, a in zip(full, (q, qd, qdd), strict=True):
                v[arm_cols] = a
            ref = np.array(pb.calculateInverseDynamics(body, *(v.tolist() for v in full),
                                                       physicsClientId=client))[arm_cols]
            ours = arm.joint_torques(q, qd, qdd, base_acceleration=-g)
            np.testing.assert_allclose(ours, ref, atol=1e-6)
            # the links' centres (Eq. A-5's particles) where PyBullet puts them
            for k, v in enumerate(q):
                pb.resetJointState(body, names.index(f'arm_joint_{k + 1}'), float(v),
                                   physicsClientId=client)
            # (a joint's index is its child link's)
            coms = [pb.getLinkState(body, names.index(f'arm_joint_{k + 1}'),
                                    computeForwardKinematics=1, physicsClientId=client)[0]
                    for k in range(4)]
            np.testing.assert_allclose(arm.com_positions(q), coms, atol=1e-9)
    finally:
        pb.disconnect(client)


def test_f_is_the_linear_part_of_the_base_rate_terms():
    """f d' is what the torques gain from a small base turn rate d' at the current joint rates
    (the quadratic rest vanishes as d'^2)."""
    arm = ArmModel.rover([0.01, 0.3, 0.1])
    q, qd = np.array([0.3, -0.5, 1.0, 0.2]), np.array([0.8, -0.4, 0.6, 1.0])
    _, small_f = arm.coupling(q, qd)
    assert np.abs(small_f[:, 3:]).max() > 1e-3              # the arm does feel it
    np.testing.assert_allclose(small_f[:, :3], 0.0)         # a translation's rate does not
    for eps in (1e-2, 1e-3):
        w = eps * np.array([0.3, -0.6, 0.8])
        change = (arm.joint_torques(q, qd, np.zeros(4), base_angular_velocity=w)
                  - arm.joint_torques(q, qd, np.zeros(4)))
        assert np.abs(change - small_f[:, 3:] @ w).max() < 5 * eps ** 2


def simulate_base(params, dt: float, n: int, seed: int):
    """The linear base of Eq. B-4 driven by a random smooth sensor wrench, at rest first: the
    sensor samples it gives, and per sample the d'' the model predicts over the next period
    from the true state with that sample's wrench held (what a perfect observer gives)."""
    obs = BaseObserver(params, dt)             # only for its exact discretisation
    rng = np.random.default_rng(seed)
    wrench = np.zeros(6)
    x = np.zeros(12)
    f0, n0 = np.array([0.0, 0.0, -9.8]), np.array([2.9, 0.0, 0.0])
    samples, truth = [], []
    for k in range(n):
        if k > 5:
            wrench = 0.97 * wrench + rng.normal(0.0, [0.6, 0.6, 0.6, 0.15, 0.15, 0.15])
        force, torque = f0 + wrench[:3], n0 + wrench[3:]
        w = obs.base_wrench(wrench[:3], wrench[3:])
        x = obs._ad @ x + obs._bd @ w
        dd = obs._a_acc @ x + obs._b_acc @ w
        truth.append(((obs._ad @ x + obs._bd @ w)[6:] - x[6:]) / dt)
        samples.append(dict(force=force, torque=torque, gyro=x[9:] + rng.normal(0, 1e-4, 3),
                            specific_force=np.array([0, 0, G]) + dd[:3]
                            + rng.normal(0, 5e-3, 3)))
    return samples, np.array(truth)


def test_the_observer_follows_the_base_it_models_and_not_a_wrong_one():
    truth = load_truth()
    dt = 0.005
    samples, dd_true = simulate_base(truth, dt, 800, seed=1)

    def error(params) -> float:
        obs = BaseObserver(params, dt)
        est = np.array([obs.update(**s)[0] for s in samples])
        return float(np.sqrt(np.mean((est[200:] - dd_true[200:]) ** 2)))
    scale = float(np.sqrt(np.mean(dd_true[200:] ** 2)))
    right = error(truth)
    wrong = error(type(truth)(mass=2 * truth.mass, inertia=2 * truth.inertia,
                              cg_to_arm=np.zeros(3), damping=3 * truth.damping,
                              stiffness=2.5 * truth.stiffness))
    assert right < 0.1 * scale
    assert wrong > 3 * right


def test_a_new_parameter_set_takes_over_without_a_jump():
    truth = load_truth()
    dt = 0.005
    samples, _ = simulate_base(truth, dt, 400, seed=2)
    nominal = type(truth)(mass=5.0, inertia=0.5 * np.eye(3), cg_to_arm=np.zeros(3),
                          damping=np.full(6, 500.0), stiffness=np.full(6, 2500.0))
    q, qd = [0.0, -0.6, 1.2, 0.0], [0.0] * 4

    def run(blend_s: float | None) -> np.ndarray:
        ff = FeedForward(nominal, dt=dt, source=ParameterSource.NOMINAL, blend_s=blend_s or 0.0)
        out = []
        for k, s in enumerate(samples):
            if k == 200 and blend_s is not None:
                ff.set_parameters(truth)
            out.append(ff.torque(q=q, qd=qd, **s))
        return np.array(out)
    stay, sharp, smooth = run(None), run(0.0), run(0.5)
    jump = np.abs(sharp[200] - stay[200]).max()
    assert jump > 0.01                                    # the two models do disagree
    assert np.abs(smooth[200] - stay[200]).max() < 0.05 * jump
    np.testing.assert_allclose(smooth[-1], sharp[-1], atol=1e-9)        # both on the new set


def test_none_is_gravity_compensation_alone():
    truth = load_truth()
    samples, _ = simulate_base(truth, 0.005, 50, seed=3)
    ff = FeedForward(truth, dt=0.005, source=ParameterSource.NONE)
    arm = ArmModel.rover(truth.cg_to_arm)
    q = [0.2, -0.6, 1.2, 0.1]
    for s in samples:
        np.testing.assert_allclose(ff.torque(q=q, qd=[0.0] * 4, **s), arm.gravity(q))


def test_estimates_are_used_only_when_physical_observable_and_recent():
    x = load_truth().to_vector()
    ok = dict(observable=[True] * 22, physically_consistent=True, age_s=1.0, max_age_s=5.0)
    assert accept_estimate(x, **ok).ok
    assert accept_estimate(x, **{**ok, 'observable': [True] * 20 + [False] * 2}).ok
    assert '19 of 22' in accept_estimate(x, **{**ok, 'observable': [True] * 19 + [False] * 3}
                                         ).reason
    bad = x.copy()
    bad[0] = -1.0
    assert 'mass' in accept_estimate(bad, **ok).reason          # checked, not the flag trusted
    assert 'stale' in accept_estimate(x, **{**ok, 'age_s': 9.0}).reason
    assert not accept_estimate(x[:21], **ok).ok
    with pytest.raises(FeedForwardError, match='physical'):
        FeedForward(load_truth().from_vector(bad), dt=0.005, source=ParameterSource.IDENTIFIED)
    with pytest.raises(FeedForwardError, match='q'):
        ArmModel.rover([0, 0.3, 0.1]).coupling([0.0] * 3, [0.0] * 4)
