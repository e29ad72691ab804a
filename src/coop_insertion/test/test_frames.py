"""Eq. 5-1..5-4 on hand-built frames (Sujan 2002, §5.1)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_insertion.errors import InsertionError
from coop_insertion.frames import (
    a_ts,
    a_vt,
    euler_eq_5_1,
    euler_from_rotation,
    frame_from_points,
    homogeneous,
    invert,
    required_motion,
    required_motion_from_points,
    rot_x,
    rot_y,
    rot_z,
    rotation_from_euler,
    third_point,
)


def points_of(t: np.ndarray, length: float = 0.05) -> np.ndarray:
    """P1 (origin), P2 (on x), P3 (on z) of the frame t, in t's parent frame."""
    return np.array([t[:3, 3], t[:3, 3] + length * t[:3, 0], t[:3, 3] + length * t[:3, 2]])


def test_elementary_rotations_are_right_handed():
    assert np.allclose(rot_z(np.pi / 2) @ [1, 0, 0], [0, 1, 0])
    assert np.allclose(rot_x(np.pi / 2) @ [0, 1, 0], [0, 0, 1])
    assert np.allclose(rot_y(np.pi / 2) @ [0, 0, 1], [1, 0, 0])


def test_euler_round_trip_in_eq_5_2_order():
    rng = np.random.default_rng(1)
    for _ in range(200):
        ang = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi])
        r = rotation_from_euler(ang)
        assert np.allclose(r, rot_x(ang[0]) @ rot_y(ang[1]) @ rot_z(ang[2]))
        assert np.allclose(euler_from_rotation(r), ang, atol=1e-9)
    # gimbal lock: R_y = pi/2, only R_x + R_z is defined; the rotation still round-trips
    r = rotation_from_euler([0.3, np.pi / 2, 0.2])
    assert np.allclose(rotation_from_euler(euler_from_rotation(r)), r, atol=1e-9)


def test_frame_from_points_recovers_hand_built_frames():
    rng = np.random.default_rng(2)
    for _ in range(100):
        r = Rotation.random(random_state=rng).as_matrix()
        t = homogeneous(r, rng.uniform(-2, 2, 3))
        p = points_of(t, length=rng.uniform(0.01, 0.5))
        assert np.allclose(frame_from_points(*p), t, atol=1e-9)
        assert np.allclose(a_vt(*p), t, atol=1e-9)
    # P3 off the z axis in the x-z plane still gives the same frame (z is orthogonalised)
    t = homogeneous(rotation_from_euler([0.2, -0.1, 0.4]), [0.3, -0.2, 1.5])
    p = points_of(t)
    p[2] += 0.02 * t[:3, 0]
    assert np.allclose(frame_from_points(*p), t, atol=1e-9)


def test_eq_5_1_literal_matches_single_axis_rotations():
    # R_z alone and R_x alone: exact anywhere
    for a in (-1.2, -0.3, 0.0, 0.4, 1.3):
        for origin in ([0.0, 0.0, 0.0], [1.5, -0.4, 0.2]):
            for ang in ([0.0, 0.0, a], [a, 0.0, 0.0]):
                t = homogeneous(rotation_from_euler(ang), origin)
                assert np.allclose(euler_eq_5_1(*points_of(t)), ang, atol=1e-9)
    # R_y alone: exact when P2 lies radially towards the camera's vertical (z) axis from P1,
    # i.e. the frame's x axis points back at the camera horizontally (frame on the -x side)
    for a in (-0.8, 0.25, 0.9):
        t = homogeneous(rot_y(a), [-2.0, 0.0, 0.3])
        assert np.allclose(euler_eq_5_1(*points_of(t)), [0.0, a, 0.0], atol=1e-9)


def test_eq_5_1_literal_is_a_small_angle_reading():
    # small combined rotations: the printed formula agrees to second order with the exact frame
    ang = np.array([0.02, -0.015, 0.03])
    t = homogeneous(rotation_from_euler(ang), [-1.5, 0.0, 0.2])
    lit = euler_eq_5_1(*points_of(t))
    exact = euler_from_rotation(frame_from_points(*points_of(t))[:3, :3])
    assert np.allclose(exact, ang, atol=1e-12)
    assert np.max(np.abs(lit - ang)) < 2e-3
    # large combined rotations: it does not (the reason the transforms use the exact frame)
    ang = np.array([0.5, 0.4, 0.6])
    t = homogeneous(rotation_from_euler(ang), [-1.5, 0.0, 0.2])
    assert np.max(np.abs(euler_eq_5_1(*points_of(t)) - ang)) > 0.05


@pytest.mark.parametrize('bad', [
    [[0, 0, 1], [0.1, 0, 1], [0.2, 0, 1]],          # collinear
    [[0, 0, 1], [0, 0, 1], [0, 0.1, 1]],            # P2 = P1
    [[0, 0, 1], [0.1, 0, 1], [0, 0, 1]],            # P3 = P1
    [[0, 0, 1], [0.1, 0, 1], [0.1 - 1e-6, 1e-6, 1]],  # almost collinear (reversed)
    [[0, 0, np.nan], [0.1, 0, 1], [0, 0.1, 1]],     # non-finite
    [[0, 0, 1], [0.1, 0, np.inf], [0, 0.1, 1]],
])
def test_degenerate_points_raise(bad):
    with pytest.raises(InsertionError):
        frame_from_points(*bad)
    with pytest.raises(InsertionError):
        euler_eq_5_1(*bad)


def test_bad_shapes_and_transforms_raise():
    with pytest.raises(InsertionError):
        frame_from_points([0, 0], [1, 0, 0], [0, 0, 1])
    with pytest.raises(InsertionError):
        invert(np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(InsertionError):
        invert(bad)
    with pytest.raises(InsertionError):
        required_motion(np.eye(4), np.eye(4), np.full((4, 4), np.nan))
    with pytest.raises(InsertionError):
        third_point([0, 0, 0], [1, 0, 0], [2, 0, 0])
    with pytest.raises(InsertionError):
        required_motion_from_points(np.eye(3), np.eye(3), np.eye(4),
                                    covariances=np.zeros((5, 3, 3)))


def test_third_point_for_two_marker_targets():
    p1, p2 = np.array([0.4, 0.1, 1.0]), np.array([0.5, 0.12, 1.0])
    up = np.array([0.0, -1.0, 0.05])
    p3 = third_point(p1, p2, up)
    assert np.isclose(np.linalg.norm(p3 - p1), np.linalg.norm(p2 - p1))
    assert abs(np.dot(p3 - p1, p2 - p1)) < 1e-12
    f = frame_from_points(p1, p2, p3)
    assert np.dot(f[:3, 2], up) > 0          # z points along the given direction


def test_inverse_and_round_trip():
    rng = np.random.default_rng(3)
    for _ in range(20):
        t = homogeneous(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        assert np.allclose(invert(t) @ t, np.eye(4), atol=1e-12)
        assert np.allclose(invert(invert(t)), t, atol=1e-12)


def test_required_motion_eq_5_4_pure_translation():
    # object and goal frames parallel: Eq. 5-4 is P_O1 - P_R1 and no rotation, in R_V; in R_S
    # the same vector rotated by R_SV
    r_v = rotation_from_euler([0.1, -0.2, 0.7])
    vt = homogeneous(r_v, [0.2, 0.1, 1.4])
    vo = homogeneous(r_v, [0.25, 0.05, 1.5])
    ts = a_ts(rot_z(0.3), [0.5, 0.0, 0.3])
    m = required_motion(vt, vo, ts)
    assert np.allclose(m.translation_v, [0.05, -0.05, 0.1])
    assert np.allclose(m.euler_difference_v, 0.0) and np.allclose(m.rotation_v, np.eye(3))
    r_sv = ts[:3, :3] @ vt[:3, :3].T
    assert np.allclose(m.translation_s, r_sv @ [0.05, -0.05, 0.1])
    assert np.isclose(m.displacement_error_m, np.linalg.norm([0.05, -0.05, 0.1]))
    assert m.angle_error_rad < 1e-12


def test_required_motion_moves_object_onto_goal_in_slave_frame():
    """Hand-built world: camera, slave base, object and site frames known in a world frame; the
    required motion computed from camera-frame measurements and the arm's A_TS, applied to the
    object in R_S, puts it on the goal (about the object's origin)."""
    rng = np.random.default_rng(4)
    for _ in range(50):
        w_cam = homogeneous(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        w_base = homogeneous(rot_z(rng.uniform(-3, 3)), np.r_[rng.normal(size=2), 0.0])
        w_obj = homogeneous(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        w_site = homogeneous(Rotation.random(random_state=rng).as_matrix(), rng.normal(size=3))
        offset = homogeneous(rotation_from_euler(rng.uniform(-0.3, 0.3, 3)),
                             rng.uniform(-0.05, 0.05, 3))
        vt = invert(w_cam) @ w_obj
        vo = invert(w_cam) @ w_site
        ts = invert(w_base) @ w_obj
        m = required_motion(vt, vo, ts, goal_offset=offset)
        goal_s = invert(w_base) @ w_site @ offset
        assert np.allclose(m.goal_s, goal_s, atol=1e-9)
        moved = homogeneous(m.rotation_s @ ts[:3, :3], ts[:3, 3] + m.translation_s)
        assert np.allclose(moved, goal_s, atol=1e-9)
        assert np.allclose(Rotation.from_rotvec(m.rotvec_s).as_matrix(), m.rotation_s)
        assert np.allclose(rotation_from_euler(m.euler_s), m.rotation_s, atol=1e-9)
        # Eq. 5-4 in R_V: the translation is the goal origin minus the object origin
        assert np.allclose(m.translation_v, (vo @ offset)[:3, 3] - vt[:3, 3])
        # and the same vector in R_S, rotated by R_SV = R_TS R_VT^T
        assert np.allclose(m.translation_s, ts[:3, :3] @ vt[:3, :3].T @ m.translation_v)


def test_eq_5_4_euler_difference_small_rotations():
    # Eq. 5-4's R_O - R_RT equals the exact rotation's angles to first order
    vt = homogeneous(rotation_from_euler([0.01, 0.02, -0.01]), [0, 0, 1])
    vo = homogeneous(rotation_from_euler([0.02, 0.0, 0.015]), [0.01, 0, 1])
    m = required_motion(vt, vo, np.eye(4))
    assert np.allclose(m.euler_difference_v, [0.01, -0.02, 0.025])
    exact = euler_from_rotation(m.rotation_v)
    assert np.allclose(exact, m.euler_difference_v, atol=1e-3)
    assert not np.allclose(exact, m.euler_difference_v, atol=1e-6)


def test_required_motion_from_points_and_covariance_propagation():
    rng = np.random.default_rng(5)
    w_cam = homogeneous(rotation_from_euler([-1.6, 0.0, -1.5]), [0.0, 0.0, 0.8])
    w_base = homogeneous(rot_z(0.2), [0.5, 0.3, 0.0])
    w_obj = homogeneous(rotation_from_euler([0.05, 0.02, 0.1]), [2.0, 0.1, 0.3])
    w_site = homogeneous(rotation_from_euler([0.0, 0.0, 0.0]), [2.1, 0.0, 0.3])
    obj = points_of(invert(w_cam) @ w_obj, 0.06)
    site = points_of(invert(w_cam) @ w_site, 0.06)
    ts = invert(w_base) @ w_obj
    sigma = 0.001
    cov = np.broadcast_to(sigma ** 2 * np.eye(3), (6, 3, 3))
    m = required_motion_from_points(obj, site, ts, covariances=cov)
    assert np.allclose(m.goal_s, invert(w_base) @ w_site, atol=1e-9)
    c = m.covariance_s
    assert c.shape == (6, 6) and np.allclose(c, c.T)
    assert np.all(np.linalg.eigvalsh(c) > -1e-18)
    # Monte Carlo check of the first-order covariance (seeded)
    samples = []
    for _ in range(800):
        o = obj + rng.normal(scale=sigma, size=(3, 3))
        s = site + rng.normal(scale=sigma, size=(3, 3))
        samples.append(required_motion_from_points(o, s, ts).twist_s)
    mc = np.cov(np.array(samples).T)
    sd_lin, sd_mc = np.sqrt(np.diag(c)), np.sqrt(np.diag(mc))
    assert np.allclose(sd_lin, sd_mc, rtol=0.12), (sd_lin, sd_mc)
    # translation of the object origin: both origins carry sigma, so >= sqrt(2) sigma each axis
    assert np.all(sd_lin[:3] > 1.3 * sigma)
