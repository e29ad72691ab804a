"""Unit tests of the simulator's pure parts: compliance (Eq. B-3), sensor models, trajectories,
world generator, configuration."""
import math

import numpy as np
import pytest

from rover_sim.compliance import (
    Deflection,
    FastCompliance,
    compliance_wrench,
    deflection,
    matrix_to_quat,
    matrix_to_rpy,
    quat_to_matrix,
    rotation_vector,
    rpy_to_matrix,
    static_preload,
)
from rover_sim.config import ConfigError, SimConfig, config_from_mapping, load_config
from rover_sim.sensors import DEG, InclinometerModel, WhiteNoise, specific_force, wheel_speeds
from rover_sim.trajectory import JointTrajectoryFollower, TrajectoryError
from rover_sim.worldgen import generate_world, occlusion_fraction

K = np.array([1000.0, 1000.0, 500.0, 2500.0, 2000.0, 3000.0])
B = np.array([100.0, 100.0, 300.0, 300.0, 200.0, 400.0])


def test_compliance_wrench_hand_case():
    # 1 mm along x, 0.01 rad about y, 0.1 m/s along z, nothing else; anchor at identity
    d = Deflection(np.array([1e-3, 0, 0]), np.array([0, 0.01, 0]), np.array([0, 0, 0.1]),
                   np.zeros(3))
    f, t = compliance_wrench(d, K, B, np.zeros(6), np.eye(3))
    np.testing.assert_allclose(f, [-1.0, 0.0, -30.0])
    np.testing.assert_allclose(t, [0.0, -20.0, 0.0])


def test_compliance_wrench_rotates_with_the_anchor():
    d = Deflection(np.array([1e-3, 0, 0]), np.zeros(3), np.zeros(3), np.zeros(3))
    ra = rpy_to_matrix(0, 0, math.pi / 2)
    f, _ = compliance_wrench(d, K, B, np.zeros(6), ra)
    np.testing.assert_allclose(f, [0.0, -1.0, 0.0], atol=1e-12)


def test_fast_compliance_matches_reference():
    rng = np.random.default_rng(3)
    q_in = matrix_to_quat(rpy_to_matrix(-0.27, 0.0, 0.0))
    pre = rng.normal(size=6)
    fast = FastCompliance(K, B, pre, q_in)
    for _ in range(20):
        yaw = rng.uniform(-3, 3)
        r_link = rpy_to_matrix(*rng.normal(scale=0.02, size=2), yaw + rng.normal(scale=0.02))
        p = rng.normal(size=3)
        pa = p + rng.normal(scale=0.01, size=3)
        v, w = rng.normal(size=3), rng.normal(size=3)
        va, wa = np.array([0.1 * math.cos(yaw), 0.1 * math.sin(yaw), 0.0]), 0.3
        ra = rpy_to_matrix(0, 0, yaw)
        d = deflection(p, r_link, v, w, pa, ra, va, np.array([0, 0, wa]))
        f_ref, t_ref = compliance_wrench(d, K, B, pre, ra)
        quat_reported = matrix_to_quat(r_link @ quat_to_matrix(q_in))
        f, t, at = fast.wrench(p, quat_reported, v, w, pa, yaw, va, wa)
        np.testing.assert_allclose(at, p)
        np.testing.assert_allclose(f, f_ref, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(t, t_ref, rtol=1e-6, atol=1e-8)


def test_static_preload_balances_gravity():
    masses = np.array([3.0, 1.0])
    coms = np.array([[0.0, 0.0, 0.3], [0.2, 0.3, 0.4]])
    pre = static_preload(masses, coms, coms[0], np.eye(3))
    np.testing.assert_allclose(pre[:3], [0, 0, 4 * 9.81])
    # torque = -(r x m g) of the arm about the c.g.: r = (0.2, 0.3, 0.1), m g = (0, 0, -9.81)
    np.testing.assert_allclose(pre[3:], -np.cross([0.2, 0.3, 0.1], [0, 0, -9.81]))


def test_rotation_helpers_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(20):
        rpy = rng.uniform([-1, -1.2, -3], [1, 1.2, 3])
        r = rpy_to_matrix(*rpy)
        np.testing.assert_allclose(matrix_to_rpy(r), rpy, atol=1e-12)
        np.testing.assert_allclose(quat_to_matrix(matrix_to_quat(r)), r, atol=1e-12)
    np.testing.assert_allclose(rotation_vector(rpy_to_matrix(0.0, 0.3, 0.0)), [0, 0.3, 0],
                               atol=1e-12)


def test_inclinometer_quantises_calibrates_and_saturates():
    model = InclinometerModel(noise=WhiteNoise(0.0, 1.0))
    rng = np.random.default_rng(0)
    lsb = 40.0 / 1024 * DEG
    angles, volts, sat = model.read(5 * DEG, -3 * DEG, rng)
    assert not sat
    np.testing.assert_allclose(angles, [5 * DEG, -3 * DEG], atol=lsb / 2 + 1e-12)
    # Eq. D-1 inverse: V = V0 + S * angle_deg (Table D-1, robot 1)
    np.testing.assert_allclose(volts, [2.406 + 0.033631 * 5, 2.381 - 0.034733 * 3],
                               atol=0.034733 * 40 / 1024)
    angles, _, sat = model.read(30 * DEG, 0.0, rng)
    assert sat and angles[0] == pytest.approx(20 * DEG)
    assert model.variance() == pytest.approx(lsb ** 2 / 12)


def test_white_noise_bounded_by_fraction_of_max_sensed():
    n = WhiteNoise(0.1, 2.0)
    x = n.sample(np.random.default_rng(1), 20000)
    assert np.abs(x).max() <= 0.2 and np.abs(x).max() > 0.19
    assert x.var() == pytest.approx(n.variance, rel=0.05)
    with pytest.raises(ValueError):
        WhiteNoise(1.5, 1.0)


def test_wheel_speeds_and_specific_force():
    np.testing.assert_allclose(wheel_speeds(0.3, 0.0, track_m=0.3, radius_m=0.06), [5, 5, 5, 5])
    left, right = wheel_speeds(0.0, 1.0, track_m=0.3, radius_m=0.06)[:2]
    assert left == pytest.approx(-2.5) and right == pytest.approx(2.5)
    np.testing.assert_allclose(specific_force(np.zeros(3), np.eye(3)), [0, 0, 9.81])
    tilted = rpy_to_matrix(0.0, 0.1, 0.0)
    assert specific_force(np.zeros(3), tilted)[0] == pytest.approx(-9.81 * math.sin(0.1))


def test_trajectory_installed_now_is_read_at_once():
    """Re-planned from where the reference is (its value and speed now), the path goes on
    unchanged, also at the instant of the re-plan itself: the controller reads its first
    reference there, and a hold (speed 0) would kick the joint at every re-plan (a device
    re-planning at each set-point, 200 times a second)."""
    f = JointTrajectoryFollower(('a',), np.zeros(1))
    f.set(['a'], [0.1, 0.2], [[0.1], [0.2]], start_s=0.0, current=np.zeros(1),
          velocities=[[1.0], [1.0]], current_velocity=np.ones(1))
    q, qd = f.target(0.05)
    np.testing.assert_allclose((q[0], qd[0]), (0.05, 1.0))
    f.set(['a'], [0.05, 0.15], [[0.1], [0.2]], start_s=0.05, current=q, velocities=[[1.0], [1.0]],
          current_velocity=qd)
    np.testing.assert_allclose([v[0] for v in f.target(0.05)], (0.05, 1.0))
    lin = JointTrajectoryFollower(('a',), np.zeros(1))
    lin.set(['a'], [0.0, 0.1], [[0.0], [0.2]], start_s=1.0, current=np.zeros(1))
    np.testing.assert_allclose([v[0] for v in lin.target(1.0)], (0.0, 2.0))


def test_trajectory_follower_interpolates_and_holds():
    f = JointTrajectoryFollower(('a', 'b'), np.array([0.0, 1.0]))
    f.set(['b'], [1.0, 2.0], [[2.0], [4.0]], start_s=10.0, current=np.array([0.0, 1.0]))
    pos, vel = f.target(10.5)
    np.testing.assert_allclose(pos, [0.0, 1.5])
    np.testing.assert_allclose(vel, [0.0, 1.0])
    np.testing.assert_allclose(f.target(11.5)[0], [0.0, 3.0])
    np.testing.assert_allclose(f.target(99.0)[0], [0.0, 4.0])
    with pytest.raises(TrajectoryError):
        f.set(['c'], [1.0], [[0.0]], 0.0, np.zeros(2))
    with pytest.raises(TrajectoryError):
        f.set(['a'], [1.0, 0.5], [[0.0], [1.0]], 0.0, np.zeros(2))
    with pytest.raises(TrajectoryError):
        f.set(['a'], [1.0], [[float('nan')]], 0.0, np.zeros(2))


def test_trajectory_follower_cubic_with_velocities():
    """Points with velocities: a cubic through every point with its velocity (speed continuous
    at the points, unlike the linear segments whose slope steps there)."""
    f = JointTrajectoryFollower(('a', 'b'), np.zeros(2))
    w = 30.0
    ts = np.arange(0.0, 0.2, 0.01)
    f.set(['a'], ts, np.sin(w * ts)[:, None], start_s=1.0, current=np.zeros(2),
          velocities=(w * np.cos(w * ts))[:, None])
    for t in ts[1:-1]:
        pos, vel = f.target(1.0 + t)
        assert pos[0] == pytest.approx(math.sin(w * t), abs=1e-12)
        assert vel[0] == pytest.approx(w * math.cos(w * t), abs=1e-9)
        before, after = f.target(1.0 + t - 1e-9)[1][0], f.target(1.0 + t + 1e-9)[1][0]
        assert after == pytest.approx(before, abs=1e-5)
    # between the points: the cubic follows the sine far closer than the chords
    mid = ts[:-1] + 0.005
    cubic = np.array([f.target(1.0 + t)[0][0] for t in mid])
    assert np.abs(cubic - np.sin(w * mid)).max() < 2e-4
    linear = JointTrajectoryFollower(('a', 'b'), np.zeros(2))
    linear.set(['a'], ts, np.sin(w * ts)[:, None], start_s=1.0, current=np.zeros(2))
    chords = np.array([linear.target(1.0 + t)[0][0] for t in mid])
    assert np.abs(chords - np.sin(w * mid)).max() > 10 * np.abs(cubic - np.sin(w * mid)).max()
    with pytest.raises(TrajectoryError):
        f.set(['a'], [0.0, 0.1], [[0.0], [1.0]], 0.0, np.zeros(2), velocities=[[0.0]])
    with pytest.raises(TrajectoryError):
        f.set(['a'], [0.0], [[0.0]], 0.0, np.zeros(2), velocities=[[float('inf')]])


def test_cubic_to_a_later_first_point_starts_from_the_old_target_speed():
    f = JointTrajectoryFollower(('a',), np.zeros(1))
    f.set(['a'], [0.1], [[0.2]], start_s=0.0, current=np.zeros(1), velocities=[[1.0]],
          current_velocity=np.array([2.0]))
    assert f.target(1e-9)[1][0] == pytest.approx(2.0, abs=1e-6)
    assert f.target(0.1 - 1e-9)[1][0] == pytest.approx(1.0, abs=1e-6)


def test_fast_compliance_midpoint_damper_reads_the_velocity_half_a_substep_on():
    """The engine's velocity is half a sub-step older than its position: with midpoint_damper
    the translational damper extrapolates it (1.5 v_n - 0.5 v_n-1); the rest is unchanged."""
    q_in = np.array([0.0, 0.0, 0.0, 1.0])
    fast = FastCompliance(K, B, np.zeros(6), q_in, midpoint_damper=True)
    p, pa = np.array([0.0, 0.0, 0.3]), np.array([0.0, 0.0, 0.3])
    v1, v2 = np.array([0.1, -0.2, 0.3]), np.array([0.2, 0.1, -0.1])
    w = np.array([0.5, 0.0, -0.5])
    f1, _t1, _ = fast.wrench(p, q_in, v1, w, pa, 0.0, np.zeros(3), 0.0)
    np.testing.assert_allclose(f1, -B[:3] * v1)            # no history yet: as measured
    f2, t2, _ = fast.wrench(p, q_in, v2, w, pa, 0.0, np.zeros(3), 0.0)
    np.testing.assert_allclose(f2, -B[:3] * (1.5 * v2 - 0.5 * v1))
    np.testing.assert_allclose(t2, -B[3:] * w)              # rotation: see base_link_inertial
    fast.reset()
    np.testing.assert_allclose(fast.wrench(p, q_in, v2, w, pa, 0.0, np.zeros(3), 0.0)[0],
                               -B[:3] * v2)


def test_base_link_carries_the_rotational_damper_lag():
    from coop_common.dynparams import load_truth
    from rover_sim.rover_model import base_link_inertial
    truth = load_truth()
    m0, c0, i0 = base_link_inertial(truth)
    m1, c1, i1 = base_link_inertial(truth, damper_lag_s=2.5e-4)
    assert m1 == m0
    np.testing.assert_allclose(c1, c0)
    np.testing.assert_allclose(i1 - i0, 2.5e-4 * np.diag(truth.damping[3:]), atol=1e-15)
    with pytest.raises(ValueError, match='damper_lag_s'):
        base_link_inertial(truth, damper_lag_s=-1.0)


def test_world_generator_density_determinism_and_clearance():
    a = generate_world(seed=4, occlusion_density=0.2, keep_clear=((-2.0, 0.0, 1.0),))
    b = generate_world(seed=4, occlusion_density=0.2, keep_clear=((-2.0, 0.0, 1.0),))
    c = generate_world(seed=5, occlusion_density=0.2, keep_clear=((-2.0, 0.0, 1.0),))
    assert a == b and a != c
    assert 0.2 <= occlusion_fraction(a) < 0.2 + 0.7 / 100
    obs = a.obstacles
    for i, o in enumerate(obs):
        assert math.hypot(o.position[0] + 2.0, o.position[1]) > 1.0 + o.radius
        for p in obs[i + 1:]:
            assert (math.hypot(o.position[0] - p.position[0], o.position[1] - p.position[1])
                    > o.radius + p.radius)
    assert generate_world(seed=1, occlusion_density=0.0).obstacles == ()
    with pytest.raises(ValueError):
        generate_world(seed=1, occlusion_density=0.9)
    site = a.site
    assert abs(site.markers[0][1] - site.markers[1][1]) == pytest.approx(0.124)


def test_config_errors_name_the_field(tmp_path):
    with pytest.raises(ConfigError, match='stereo_rate_hz'):
        config_from_mapping({'stereo_rate_hz': 100.0})
    with pytest.raises(ConfigError, match='bogus'):
        config_from_mapping({'bogus': 1})
    with pytest.raises(ConfigError, match=r'noise\.fraction'):
        config_from_mapping({'noise': {'fraction': 'high'}})
    with pytest.raises(ConfigError, match='rovers'):
        config_from_mapping({'rovers': 2.5})
    with pytest.raises(ConfigError, match='supersample'):
        config_from_mapping({'supersample': 2})       # no sample on the pixel centre
    for bad in (3.0, True):
        with pytest.raises(ConfigError, match='supersample'):
            SimConfig(supersample=bad)
    with pytest.raises(ConfigError, match='supersample'):
        SimConfig(image_width=1920, image_height=1440, supersample=3)   # 24.9 M px an image
    SimConfig(image_width=640, image_height=480, supersample=7)          # 15.1 M px: allowed
    bad = tmp_path / 'bad.yaml'
    bad.write_text('rovers: [1, 2\n')
    with pytest.raises(ConfigError, match='not valid YAML'):
        load_config(bad)
    good = tmp_path / 'good.yaml'
    good.write_text('occlusion_density: 0.2\nnoise:\n  fraction: 0.05\n')
    cfg = load_config(good)
    assert cfg.occlusion_density == 0.2 and cfg.noise.fraction == 0.05
    assert cfg.rovers == SimConfig().rovers


def test_substeps_respect_the_stability_minimum():
    from coop_common.dynparams import load_truth
    from rover_sim.world import substeps_for
    t = load_truth()
    n = substeps_for([t], 0.005)
    assert n == 10                               # b / I = 2000 1/s on every rotational axis
    stiff = SimConfig(physics_substeps=25)
    assert stiff.physics_substeps == 25
    with pytest.raises(ConfigError, match='physics_substeps'):
        SimConfig(physics_substeps=-1)


def test_odometry_drifts_as_a_random_walk_in_the_wheels_travel():
    from rover_sim.config import NoiseConfig
    from rover_sim.sensors import odometry_step
    drift, dt, n = NoiseConfig().odom_drift, 0.005, 4000
    rng = np.random.default_rng(0)
    xy, yaw = np.zeros((n, 2)), np.zeros(n)
    errors = {}
    for k in range(1, 1001):              # 5 s at 0.2 m/s: a metre, 4000 rovers at once
        xy, yaw = odometry_step(xy, yaw, 0.2, 0.0, dt, drift=drift, track_m=0.4,
                                noise=rng.standard_normal((n, 3)))
        if k in (250, 1000):
            errors[k] = (xy[:, 0] - 0.2 * k * dt, yaw)
    # heading drift sqrt(d / 1 m) rad, along-track drift sqrt(d x 1 m): 2 cm after a metre,
    # half that after a quarter (not a quarter: a random walk, not a scale error)
    along, head = errors[1000]
    assert np.std(head) == pytest.approx(drift, rel=0.05)
    assert np.std(along) == pytest.approx(drift, rel=0.05)
    assert np.std(errors[250][0]) == pytest.approx(drift / 2, rel=0.05)
    assert abs(np.mean(along)) < 3 * drift / np.sqrt(n)
    # turning on the spot drifts by the wheels' travel too; standing still does not drift
    _xy2, yaw2 = odometry_step(np.zeros(2), 0.0, 0.0, 1.0, dt, drift=drift, track_m=0.4,
                              noise=np.ones(3))
    assert yaw2 == pytest.approx(dt + drift * np.sqrt(0.2 * dt))
    assert np.allclose(odometry_step(np.zeros(2), 0.3, 0.0, 0.0, dt, drift=drift, track_m=0.4,
                                     noise=np.ones(3))[0], 0.0)


def test_truth_topics_are_named_in_one_place():
    from rover_sim.config import is_truth_topic, truth_topic
    assert truth_topic('rover2', 'contact') == 'sim/rover2/contact'
    assert all(is_truth_topic(t) for t in ('/sim/rover2/card_pose', 'sim/world',
                                           '/team_a/sim/rover1/base_pose'))
    assert not any(is_truth_topic(t) for t in ('/sim/lockstep/tick', '/rover1/odom',
                                               '/sim/reset', '/rover1/sim/stereo'))
    with pytest.raises(ConfigError):
        truth_topic('rover1', 'odom')
