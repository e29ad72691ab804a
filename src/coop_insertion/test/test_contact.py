"""Contact states (app. A.4, Fig. A-6) on hand-built wrenches, and the least-resistance step."""
from __future__ import annotations

import numpy as np
import pytest

from coop_insertion.contact import (
    INCH,
    CardPose,
    ContactIdentifier,
    ContactState,
    LeastResistance,
    SlotGeometry,
    planar_step_in_frame,
    planar_wrench,
    task_wrench,
)
from coop_insertion.errors import InsertionError
from coop_insertion.frames import homogeneous, rot_x, rot_z

GEOM = SlotGeometry(slot_width_m=4.375 * INCH, slot_depth_m=0.05)
W, WC, D = GEOM.slot_width_m, GEOM.card_width_m, GEOM.slot_depth_m


def wrench(*contacts) -> np.ndarray:
    """(point, normal, normal force, friction force along z x normal) -> (F_x, F_y, M_z)."""
    total = np.zeros(3)
    for pt, normal, fn, ft in contacts:
        n = np.asarray(normal, float) / np.linalg.norm(normal)
        f = fn * n + ft * np.array([-n[1], n[0]])
        total += [f[0], f[1], pt[0] * f[1] - pt[1] * f[0]]
    return total


def case_free():
    return CardPose(0.001, 0.01, 0.0), np.array([0.3, -0.4, 0.01]), (ContactState.FREE, 0)


def case_corner_on_mouth():
    # card 10 mm to the right, flat on the right jaw's mouth face; vision's estimate 1 mm off
    true = CardPose(0.010, 0.0, 0.0)
    corner = true.corner(1, WC)
    w = wrench((corner, (0, 1), 10.0, 0.8))
    return CardPose(0.009, 0.0, 0.0), w, (ContactState.CORNER_ON_MOUTH, 1)


def case_edge_on_face():
    # tilted clockwise, right end entering the gap, leading face resting on the left jaw's edge
    th = -0.1
    e = np.array([-W / 2, 0.0])
    v = np.array([np.cos(th), np.sin(th)])
    u = np.array([-np.sin(th), np.cos(th)])
    p = e + 0.04 * v
    pose = CardPose(p[0], p[1], th)
    assert pose.corner(1, WC)[0] < W / 2 and pose.corner(-1, WC)[1] > 0
    return pose, wrench((e, u, 8.0, -1.0)), (ContactState.EDGE_ON_FACE, -1)


def case_edge_on_side():
    # partly in, tilted clockwise, the right jaw's edge on the card's right side face
    th = -0.05
    u = np.array([-np.sin(th), np.cos(th)])
    v = np.array([np.cos(th), np.sin(th)])
    e = np.array([W / 2, 0.0])
    c_r = e - 0.02 * u
    p = c_r - WC / 2 * v
    pose = CardPose(p[0], p[1], th)
    assert pose.corner(-1, WC)[0] > -W / 2
    return pose, wrench((e, -v, 6.0, 1.0)), (ContactState.EDGE_ON_SIDE, 1)


def case_corner_on_wall():
    # inside, slight counter-clockwise tilt, left corner on the left wall, sliding down
    th = 0.01
    v = np.array([np.cos(th), np.sin(th)])
    c_l = np.array([-W / 2, -0.03])
    p = c_l + WC / 2 * v
    pose = CardPose(p[0], p[1], th)
    return pose, wrench((c_l, (1, 0), 10.0, 2.0)), (ContactState.CORNER_ON_WALL, -1)


def case_corner_on_bottom():
    th = 0.05
    v = np.array([np.cos(th), np.sin(th)])
    c_l = np.array([-0.05, -D])
    p = c_l + WC / 2 * v
    pose = CardPose(p[0], p[1], th)
    return pose, wrench((c_l, (0, 1), 10.0, 0.5)), (ContactState.CORNER_ON_BOTTOM, -1)


def case_seated():
    pose = CardPose(0.001, -D, 0.0)
    c_l, c_r = pose.corner(-1, WC), pose.corner(1, WC)
    return pose, wrench((c_l, (0, 1), 5.5, 0.0), (c_r, (0, 1), 4.5, 0.0)), \
        (ContactState.SEATED, 0)


def wedge_pose(th: float) -> CardPose:
    """Clockwise tilt th < 0: left corner on the left wall, right side face on the right edge."""
    y_l = (W - WC * np.cos(th)) / np.tan(th) - WC * np.sin(th)
    v = np.array([np.cos(th), np.sin(th)])
    p = np.array([-W / 2, y_l]) + WC / 2 * v
    return CardPose(p[0], p[1], th)


def case_two_point():
    th = -0.1
    pose = wedge_pose(th)
    c_l = pose.corner(-1, WC)
    assert -D < c_l[1] < 0 and np.isclose(c_l[0], -W / 2)
    v = pose.v
    e_r = np.array([W / 2, 0.0])
    w = wrench((c_l, (1, 0), 12.0, 2.0), (e_r, -v, 12.0, 1.0))
    return pose, w, (ContactState.TWO_POINT, -1)


def test_a_wedge_fit_takes_the_least_squeeze_that_explains_the_wrench():
    """Two opposed contacts can squeeze the card with any force and leave the wrench as it is:
    the fit must not make a small reading into large contact forces, nor the planner a large
    retreat from them. The case is a force-feedback step of a 4.5 in trial (card 29.7 mm in,
    0.76 N and a 0.19 N m couple), which the bare NNLS fitted with 54 N a contact and answered
    with a 23 mm retreat."""
    geo = SlotGeometry(slot_width_m=4.5 * INCH, slot_depth_m=0.030)
    pose = CardPose(-0.00208, -0.02965, -6.8e-5)
    w = np.array([0.04, 0.76, -0.19])
    ident = ContactIdentifier(geo, friction=0.3).identify(w, pose)
    assert ident.state is ContactState.TWO_POINT
    assert max(c.normal_force_n for c in ident.contacts) < 5.0, ident.contacts
    # friction unknown in 0.2-0.6 (the cones at 0.6): the couple is friction's more, still small
    ident = ContactIdentifier(geo).identify(w, pose)
    assert ident.state is ContactState.TWO_POINT
    assert max(c.normal_force_n for c in ident.contacts) < 10.0, ident.contacts
    planner = LeastResistance(geo)
    step = planner.step(ident, w, pose)
    assert not step.retreat
    assert np.hypot(step.dx, step.dy) <= planner.max_step_m * (1 + 1e-9)


def test_a_retreat_goes_out_of_the_slot_and_is_bounded():
    """Both contacts of a wedge over the force limit: their constraints conflict, and the
    projection's answer for a 4.5 in trial's step was 122 mm and 44 deg into the slot (the fit
    at mu 0.3 puts 127 N on each contact: a couple with little force that only a squeeze
    explains)."""
    geo = SlotGeometry(slot_width_m=4.5 * INCH, slot_depth_m=0.030)
    pose = CardPose(0.00268, -0.02621, 0.0811)
    w = np.array([0.72, -1.86, 0.3])
    ident = ContactIdentifier(geo, friction=0.3).identify(w, pose)
    assert min(c.normal_force_n for c in ident.contacts) > 25.0
    planner = LeastResistance(geo)
    step = planner.step(ident, w, pose)
    assert step.dx * pose.u[0] + step.dy * pose.u[1] >= 0.0          # out, not in
    assert np.hypot(step.dx, step.dy) <= planner.max_step_m * (1 + 1e-9)
    assert abs(step.dtheta) <= planner.max_rotation_rad * (1 + 1e-9)


CASES = [case_free, case_corner_on_mouth, case_edge_on_face, case_edge_on_side,
         case_corner_on_wall, case_corner_on_bottom, case_seated, case_two_point]


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.__name__[5:])
def test_each_state_on_a_hand_built_wrench(case):
    pose, w, (state, side) = case()
    ident = ContactIdentifier(GEOM).identify(w, pose)
    assert ident.state is state, (ident.state, sorted(ident.scores.items(), key=lambda x: x[1]))
    assert ident.side == side
    # the fitted contacts reproduce the wrench (FREE: the wrench is all residual, in the noise)
    assert ident.wrench_chi2 < (9.0 if state is ContactState.FREE else 1e-6)


@pytest.mark.parametrize('case', CASES, ids=lambda c: c.__name__[5:])
def test_each_state_under_sensor_noise(case):
    """The same wrenches (normal forces 6-12 N) with the identifier's own 1-sigma noise (seeded):
    at most 3 of 50 misidentified (a single contact's chi^2 with 3 dof beyond the 9 a second
    contact costs is a few per cent)."""
    pose, w, (state, side) = case()
    ident = ContactIdentifier(GEOM)
    rng = np.random.default_rng(11)
    wrong = 0
    for _ in range(50):
        noisy = w + rng.normal(size=3) * [ident.force_noise_n, ident.force_noise_n,
                                          ident.moment_noise_nm]
        got = ident.identify(noisy, pose)
        wrong += (got.state is not state) or (got.side != side)
    assert wrong <= 3, wrong


def test_contact_point_located_from_the_moment():
    # corner on the mouth: the contact x comes from M = x F_y (the pose estimate is 1 mm off)
    pose, w, _ = case_corner_on_mouth()
    ident = ContactIdentifier(GEOM).identify(w, pose)
    c = ident.contacts[0]
    assert np.isclose(c.point[0], CardPose(0.010, 0.0, 0.0).corner(1, WC)[0], atol=1e-4)
    assert np.isclose(c.normal_force_n, 10.0, atol=1e-6)
    assert np.isclose(c.friction_force_n, 0.8, atol=1e-3)     # (the fit's ridge: < 1e-3 N)


def test_contact_location_error_grows_with_sensor_noise():
    """Fig. A-7: the located contact point's error grows with the F/T noise."""
    pose, w, _ = case_corner_on_mouth()
    truth = CardPose(0.010, 0.0, 0.0).corner(1, WC)[0]
    rng = np.random.default_rng(12)
    errors = []
    for sigma_m in (0.002, 0.02, 0.05):
        ident = ContactIdentifier(GEOM, moment_noise_nm=max(sigma_m, 0.02))
        e = []
        for _ in range(100):
            noisy = w + np.array([rng.normal(0, 0.1), rng.normal(0, 0.1),
                                  rng.normal(0, sigma_m)])
            got = ident.identify(noisy, pose)
            e.append(abs(got.contacts[0].point[0] - truth) if got.contacts else np.inf)
        errors.append(float(np.median(e)))
    assert errors[0] < errors[1] < errors[2], errors
    assert errors[0] < 0.0005


def test_friction_outside_the_cone_is_not_a_single_contact():
    # a mostly tangential force on the mouth (beyond mu = 0.3) cannot be a corner on the face
    pose = CardPose(0.009, 0.0, 0.0)
    corner = CardPose(0.010, 0.0, 0.0).corner(1, WC)
    w = wrench((corner, (0, 1), 8.0, 6.0))
    ident = ContactIdentifier(GEOM, friction=0.3).identify(w, pose)
    assert ident.state is not ContactState.CORNER_ON_MOUTH
    ident = ContactIdentifier(GEOM, friction=0.8).identify(w, pose)
    assert ident.state is ContactState.CORNER_ON_MOUTH


# --- least resistance ---------------------------------------------------------------------

def plan(case, **kw):
    pose, w, _ = case()
    ident = ContactIdentifier(GEOM).identify(w, pose)
    return pose, w, ident, LeastResistance(GEOM, **kw).step(ident, w, pose)


def test_free_advances_and_aligns():
    _pose, _, _, s = plan(case_free)
    assert s.dy < 0 and s.dx < 0 and not s.done and not s.retreat


def test_corner_on_mouth_slides_towards_the_slot():
    _pose, w, ident, s = plan(case_corner_on_mouth)
    assert s.dx < 0 and s.dy >= 0
    # bounded by max_step_m and by the travel an unforeseen contact allows under the limit
    budget = (25.0 - np.hypot(w[0], w[1])) / 2e4
    assert np.isclose(np.hypot(s.dx, s.dy), min(0.002, budget))
    # with looser bounds it puts the corner just inside the edge
    _pose, _, ident, s = plan(case_corner_on_mouth, max_step_m=0.02, stiffness_n_per_m=500.0)
    corner_after = ident.contacts[0].point[0] + s.dx
    lr = LeastResistance(GEOM)
    assert np.isclose(corner_after, W / 2 - lr.entry_margin_m)


def test_edge_on_face_shifts_clear_and_aligns():
    pose, _, _, s = plan(case_edge_on_face, max_step_m=0.05, max_rotation_rad=0.2,
                         stiffness_n_per_m=100.0)
    assert s.dx > 0 and s.dtheta > 0
    # enough to take the left corner past the left jaw's edge
    assert pose.corner(-1, WC)[0] + s.dx > -W / 2


def test_edge_on_side_slides_in_and_aligns():
    _pose, _, _, s = plan(case_edge_on_side)
    assert s.dtheta > 0                      # tilt -0.05 rad reduced
    assert s.dy < 0 and s.dx < 0             # in, and away from the right edge


def test_corner_on_wall_slides_along_the_wall():
    pose, _, ident, s = plan(case_corner_on_wall)
    assert s.dy < 0 and s.dx >= 0 and s.dtheta < 0
    c = ident.contacts[0]
    # no penetration of the wall at the contact point
    rel = c.point - pose.p
    vx = s.dx - s.dtheta * rel[1]
    assert vx >= -1e-12


def test_two_point_backs_off_and_rotates_out():
    _pose, _, _, s = plan(case_two_point)
    assert s.dy > 0 and s.dtheta > 0
    assert s.predicted_force_n <= 25.0 + 1e-9


def test_corner_on_bottom_pivots_flat():
    pose, _, ident, s = plan(case_corner_on_bottom)
    assert s.dtheta < 0
    # the corner on the bottom stays put (pivot) to first order
    c = ident.contacts[0].point
    rel = c - pose.p
    v = np.array([s.dx - s.dtheta * rel[1], s.dy + s.dtheta * rel[0]])
    assert np.linalg.norm(v) < 1e-9


def test_seated_is_done():
    _, _, _, s = plan(case_seated)
    assert s.done and s.dx == s.dy == s.dtheta == 0.0


def test_force_limit_is_never_exceeded():
    """Random states and force levels: the step never predicts a force above the limit; a force
    above it gives a retreat that brings it back to the limit."""
    rng = np.random.default_rng(13)
    ident = ContactIdentifier(GEOM)
    checked = 0
    for case in CASES[1:]:
        pose, w0, _ = case()
        for _ in range(25):
            scale = rng.uniform(0.2, 4.0)
            w = w0 * scale
            lr = LeastResistance(GEOM, force_limit_n=rng.uniform(10, 30),
                                 stiffness_n_per_m=rng.uniform(5e3, 5e4),
                                 insert_step_m=rng.uniform(1e-4, 2e-3))
            got = ident.identify(w, pose)
            s = lr.step(got, w, pose)
            assert s.predicted_force_n <= lr.force_limit_n + 1e-6, (case.__name__, s)
            forces = [c.normal_force_n for c in got.contacts] + [np.hypot(*w[:2])]
            if max(forces) > lr.force_limit_n:
                assert s.retreat
            checked += 1
    assert checked == 7 * 25


def test_above_the_limit_the_step_retreats_from_the_wall():
    pose, w, _ = case_corner_on_wall()
    w = w * 6.0                                    # 30 N on the wall
    ident = ContactIdentifier(GEOM).identify(w, pose)
    lr = LeastResistance(GEOM, force_limit_n=25.0, stiffness_n_per_m=2e4)
    s = lr.step(ident, w, pose)
    assert s.retreat and s.dx > 0
    rel = ident.contacts[0].point - pose.p
    away = s.dx - s.dtheta * rel[1]
    f_wall = ident.contacts[0].normal_force_n
    assert f_wall > 25.0
    assert away >= (f_wall - 25.0) / 2e4 - 1e-9
    assert s.predicted_force_n <= 25.0 + 1e-6


def test_task_wrench_transform_and_sum():
    # sensor rotated 90 deg about z, 0.1 m along x of the task frame; reading (base on arm)
    t = homogeneous(rot_z(np.pi / 2), [0.1, 0.0, 0.0])
    reading = np.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.2])
    tare = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.1])
    w = task_wrench(reading, t, tare=tare)
    # force (0, 1, 0) in the task frame, negated; moment 0.1 + 0.1 x 1 about z, negated
    assert np.allclose(w, [0, -1, 0, 0, 0, -0.2])
    assert np.allclose(task_wrench(reading, t, tare=tare, reaction=False), -w)
    assert np.allclose(planar_wrench([w, w]), [0, -2, -0.4])
    with pytest.raises(InsertionError):
        planar_wrench(np.zeros((2, 5)))
    with pytest.raises(InsertionError):
        task_wrench([np.nan] * 6, t)


def test_planar_step_in_a_tilted_frame():
    s = LeastResistance(GEOM).step(ContactIdentifier(GEOM).identify(np.zeros(3),
                                                                   CardPose(0, 0.01, 0)),
                                   np.zeros(3), CardPose(0, 0.01, 0))
    dp, rv = planar_step_in_frame(s, CardPose(0, 0.01, 0), homogeneous(rot_x(np.pi / 2),
                                                                        [1, 2, 3]))
    assert np.allclose(dp, [s.dx, 0, s.dy]) and np.allclose(rv, [0, -s.dtheta, 0])


def test_bad_options_and_inputs_raise():
    with pytest.raises(InsertionError):
        SlotGeometry(slot_width_m=4.0 * INCH)
    with pytest.raises(InsertionError):
        ContactIdentifier(GEOM, force_noise_n=0.0)
    with pytest.raises(InsertionError):
        LeastResistance(GEOM, force_limit_n=-1)
    with pytest.raises(InsertionError):
        LeastResistance(GEOM, contact_force_n=30.0)
    with pytest.raises(InsertionError):
        ContactIdentifier(GEOM).identify([1.0, np.nan, 0.0], CardPose(0, 0, 0))
    with pytest.raises(InsertionError):
        CardPose(0.0, np.inf, 0.0)


# --- closed loop against a planar penalty-contact card ---------------------------------------

def penalty_wrench(geom: SlotGeometry, pose: CardPose, k: float) -> tuple[np.ndarray, float]:
    """The site's wrench on a kinematically moved card: a corner inside a jaw or below the
    bottom, or a jaw edge inside the card, pushed out the shortest way with k * depth."""
    half, d, w, h = geom.slot_width_m / 2, geom.slot_depth_m, geom.card_width_m, \
        geom.card_height_m
    total, peak = np.zeros(3), 0.0
    for s in (-1, 1):
        c = pose.corner(s, w)
        f = None
        if abs(c[0]) > half and c[1] < 0:
            f = (k * -c[1] * np.array([0.0, 1.0]) if -c[1] < abs(c[0]) - half else
                 k * (abs(c[0]) - half) * np.array([-np.sign(c[0]), 0.0]))
        elif c[1] < -d:
            f = k * (-d - c[1]) * np.array([0.0, 1.0])
        if f is not None:
            total += [f[0], f[1], c[0] * f[1] - c[1] * f[0]]
            peak = max(peak, float(np.hypot(*f)))
        e = np.array([s * half, 0.0])
        xi, eta = (e - pose.p) @ pose.v, (e - pose.p) @ pose.u
        if abs(xi) < w / 2 and 0 < eta < h:
            f = (k * eta * pose.u if eta < w / 2 - abs(xi) else
                 -k * (w / 2 - abs(xi)) * np.sign(xi) * pose.v)
            total += [f[0], f[1], e[0] * f[1] - e[1] * f[0]]
            peak = max(peak, float(np.hypot(*f)))
    return total, peak


def insert(geom: SlotGeometry, start, bias, *, k: float = 2e4, steps: int = 400):
    rng = np.random.default_rng(21)
    # (the seat probe moves by the stiffness of this world's contacts)
    ident = ContactIdentifier(geom)
    lr = LeastResistance(geom, stiffness_n_per_m=k, probe_stiffness_n_per_m=k)
    x, y, th = start
    peak = 0.0
    for _ in range(steps):
        w, f = penalty_wrench(geom, CardPose(x, y, th), k)
        peak = max(peak, f)
        w = w + rng.normal(size=3) * [0.3, 0.3, 0.01]
        est = CardPose(x + bias[0], y + bias[1], th + bias[2])
        s = lr.step(ident.identify(w, est), w, est)
        if s.done:
            return True, peak, (x, y, th)
        x, y, th = x + s.dx, y + s.dy, th + s.dtheta
    return False, peak, (x, y, th)


@pytest.mark.parametrize('width_in', [5.0, 4.5, 4.375])
@pytest.mark.parametrize('start', [(0.008, 0.004, 0.03), (-0.004, 0.002, -0.02)])
def test_closed_loop_seats_with_a_good_pose_estimate(width_in, start):
    """Pose estimate 1 mm off (within every Table 5-1 clearance): seated, force under 25 N."""
    geom = SlotGeometry(slot_width_m=width_in * INCH, slot_depth_m=0.03)
    ok, peak, end = insert(geom, start, (0.001, 0.0, 0.0))
    assert ok and peak <= 25.0, (ok, peak, end)
    assert end[1] < -0.029 and abs(end[2]) < 0.02


@pytest.mark.known_issue
@pytest.mark.parametrize('bias', [(-0.006, 0.0, 0.0), (0.0, 0.0, -0.04)])
def test_closed_loop_seats_with_a_pose_estimate_off_by_more_than_the_clearance(bias):
    """Open: the step aligns to the pose estimate, which the contacts contradict; the identified
    contact locations and normals should correct it (lateral offset, tilt). Today: limit cycles,
    a corner held on the bottom, and penalty forces far above 25 N in the 4.5 in slot."""
    geom = SlotGeometry(slot_width_m=4.5 * INCH, slot_depth_m=0.03)
    ok, peak, end = insert(geom, (0.0, 0.004, 0.0), bias)
    assert ok and peak <= 25.0, (ok, peak, end)


# --- friction not known, and a seated verdict that does not lie ------------------------------

GEOM_45 = SlotGeometry(slot_width_m=4.5 * INCH, slot_depth_m=0.030)
#: the estimate of the card through the graph that was called seated: flat and deep
EST_FLAT = CardPose(0.0015, -0.0299, np.radians(0.1))


def held_up_by_a_jaw(mu: float, f_floor: float, f_wall: float, h: float) -> np.ndarray:
    """The left corner on the floor of a 4.5 in slot, 30 mm deep; the right corner against the
    right jaw's wall h above the floor, sliding down it at mu (the wall's friction holds it up)
    and the floor's friction at the left corner pushing back against the wall as far as mu
    lets it."""
    half = GEOM_45.slot_width_m / 2
    c_l = np.array([half - WC, -0.030])
    c_r = np.array([half, -0.030 + h])
    # friction along z x n: the floor's t = (-1, 0), the right wall's t = (0, -1)
    return wrench((c_l, (0, 1), f_floor, -min(mu * f_floor, f_wall)),
                  (c_r, (-1, 0), f_wall, -mu * f_wall))


@pytest.mark.parametrize('mu, f_floor, f_wall', [(0.6, 2.0, 2.0), (0.4, 2.4, 2.5),
                                                 (0.6, 4.0, 4.0)])
def test_a_card_on_one_corner_held_up_by_a_jaw_is_not_seated(mu, f_floor, f_wall):
    """The false seat: the wrench's floor sum is 3.2 N or more and the estimate flat and deep,
    but the right corner is 3 mm up the wall (tilted 1.6 deg: not seated by the truth). The fit
    may call it SEATED; the seat check must not pass it."""
    w = held_up_by_a_jaw(mu, f_floor, f_wall, 0.003)
    assert w[1] >= 3.2
    ident = ContactIdentifier(GEOM_45)
    got = ident.identify(w, EST_FLAT)
    assert got.state in (ContactState.SEATED, ContactState.CORNER_AND_SIDE), got.state
    if got.state is ContactState.SEATED:
        assert got.floor_force_n >= 3.0 and got.seat is not None and not got.seat.passed
    check = ident.seat_check(w, EST_FLAT)
    assert not check.passed and check.margin < ident.seat_margin
    # so the planner does not call it done: it probes
    step = LeastResistance(GEOM_45).step(got, w, EST_FLAT)
    assert not step.done


def test_a_seated_card_passes_the_seat_check_under_noise():
    """Both corners on the floor at 3 N each (the probe presses to 6 N and evens the corners),
    a little lateral friction, the estimate 1 mm off: passed noiseless, and in 19 of 20 seeded
    draws of a third of the identifier's noise (a force period's mean of ten readings). Split
    6:2 it is not passed: a jaw's friction at mu 0.6 could carry the lighter corner's share."""
    ident = ContactIdentifier(GEOM_45)
    est = CardPose(0.001, -0.0299, 0.0)
    truth = CardPose(0.0, -0.030, 0.0)
    w = wrench((truth.corner(-1, WC), (0, 1), 3.0, 0.05),
               (truth.corner(1, WC), (0, 1), 3.0, 0.05))
    got = ident.identify(w, est)
    assert got.state is ContactState.SEATED and got.seat.passed, got.seat
    assert min(got.seat.corner_forces_n) > 2.5
    lopsided = wrench((truth.corner(-1, WC), (0, 1), 6.0, 0.05),
                      (truth.corner(1, WC), (0, 1), 2.0, 0.05))
    assert not ident.seat_check(lopsided, est).passed
    assert LeastResistance(GEOM_45).step(got, w, est).done
    rng = np.random.default_rng(31)
    sigma = np.array([ident.force_noise_n, ident.force_noise_n, ident.moment_noise_nm]) / 3
    passed = sum(ident.seat_check(w + rng.normal(size=3) * sigma, est).passed
                 for _ in range(20))
    assert passed >= 19, passed


def test_the_probe_turns_the_lighter_corner_down_and_presses():
    """SEATED by the fit, the check failed: the step is no 'done' but a probe: the card turns
    about its heavier corner (left) so the lighter (right) comes down, and presses towards
    twice seat_force_n."""
    w = held_up_by_a_jaw(0.4, 2.4, 2.5, 0.003)
    got = ContactIdentifier(GEOM_45).identify(w, EST_FLAT)
    assert got.state is ContactState.SEATED and not got.seat.passed
    assert got.seat.lighter_side == 1
    step = LeastResistance(GEOM_45).step(got, w, EST_FLAT)
    assert not step.done and 'probe' in step.reason
    assert step.dtheta < 0          # clockwise: the right corner down
    assert step.dy < 0              # 3.4 N is under 2 x 3 N: press


@pytest.mark.parametrize('mu', [0.2, 0.6])
def test_friction_0_2_and_0_6_are_identified_without_being_told(mu):
    """A corner sliding down a wall and a corner sliding on a mouth face, at the simulator's mu
    the identifier is not told: the default (mu somewhere in 0.2-0.6) names both, and the fit's
    friction is within the cone; fitted at a fixed 0.3, the 0.6 slide is not a single contact."""
    th = 0.01
    v = np.array([np.cos(th), np.sin(th)])
    c_l = np.array([-W / 2, -0.03])
    wall_pose = CardPose(*(c_l + WC / 2 * v), th)
    wall = wrench((c_l, (1, 0), 10.0, mu * 10.0))
    true = CardPose(0.010, 0.0, 0.0)
    mouth = wrench((true.corner(1, WC), (0, 1), 10.0, -mu * 10.0))
    cases = [(wall_pose, wall, ContactState.CORNER_ON_WALL, -1),
             (CardPose(0.009, 0.0, 0.0), mouth, ContactState.CORNER_ON_MOUTH, 1)]
    for pose, w, state, side in cases:
        got = ContactIdentifier(GEOM).identify(w, pose)
        assert (got.state, got.side) == (state, side), (mu, got.state, got.side)
        assert mu - 0.01 <= got.friction_needed <= 0.6 + 1e-9, got.friction_needed
        told_03 = ContactIdentifier(GEOM, friction=0.3).identify(w, pose)
        if mu > 0.3:
            assert told_03.state is not state
