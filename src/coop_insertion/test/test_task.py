"""The task model, marker labelling and the card's required motion (task.py), and the drive to a
camera pose (drive.py), on hand-built frames."""
import math

import numpy as np
import pytest

from coop_common.rover_geometry import card_in_base
from coop_insertion.drive import FollowPath, GoToPose, wrap
from coop_insertion.errors import InsertionError
from coop_insertion.frames import homogeneous, invert, rot_z
from coop_insertion.locate import SiteEstimate, search_points
from coop_insertion.task import (
    SlotPair,
    TaskModel,
    card_required_motion,
    find_slot,
    label_markers,
    site_from_slot,
    slot_from_site,
)
from coop_insertion.triangulate import StereoMarker

MODEL = TaskModel()
R2 = np.array([0.01, 0.3, 0.1])
Q = np.array([0.05, 0.6, -1.1, 0.5])


def _camera():
    """A camera 0.6 m in front of the site (+y), looking back at it, pitched down 30 deg:
    pose of the optical frame (z forward, x right, y down) in the site frame."""
    pitch = math.radians(30)
    fwd = np.array([0.0, -math.cos(pitch), -math.sin(pitch)])
    right = np.array([-1.0, 0.0, 0.0])
    down = np.cross(fwd, right)
    return homogeneous(np.column_stack([right, down, fwd]), [0.0, 0.6, 0.35])


def _observe(cam, site_card, *, rng=None, sigma=0.0):
    """The four markers in the camera frame for the card frame at `site_card` (site frame),
    as StereoMarkers with plausible image radii (f = 850 px)."""
    pts = [site_card[:3, :3] @ p + site_card[:3, 3] for p in MODEL.card_markers] + \
        list(MODEL.slot_markers)
    radii = [MODEL.card_marker_radius_m] * 2 + [MODEL.slot_marker_radius_m] * 2
    ms, rs = [], []
    for k, (p, r) in enumerate(zip(pts, radii, strict=False)):
        pc = invert(cam)[:3, :3] @ p + invert(cam)[:3, 3]
        if rng is not None:
            pc = pc + rng.normal(0.0, sigma, 3)
        ms.append(StereoMarker(k, k, pc, np.eye(3) * max(sigma, 1e-4) ** 2, (0, 0), (0, 0)))
        rs.append(850.0 * r / pc[2])
    order = [2, 0, 3, 1]                      # detection order is arbitrary
    up = invert(cam)[:3, :3] @ np.array([0.0, 0.0, 1.0])
    return [ms[i] for i in order], [rs[i] for i in order], up


def test_a_remembered_slot_labels_the_card_when_a_slot_marker_is_hidden():
    """The card in front of the mouth hides a slot marker: with the slot pair seen before
    (the card out of view, find_slot), the card's pair is labelled against it; a slot marker
    still in view is never taken for a card marker."""
    cam = _camera()
    ms, rs, up = _observe(cam, MODEL.card_goal(0.05))
    full = label_markers(ms, rs, 850.0, up, MODEL)
    slot_ix = [k for k, m in enumerate(ms) if m.left >= 2]     # detection order 2, 0, 3, 1
    card_ix = [k for k in range(4) if k not in slot_ix]
    memory = find_slot([ms[k] for k in slot_ix], [rs[k] for k in slot_ix], 850.0, up, MODEL)
    assert memory is not None
    np.testing.assert_allclose(memory.points, full.points[2:], atol=1e-12)
    assert find_slot([ms[k] for k in card_ix], [rs[k] for k in card_ix], 850.0, up,
                     MODEL) is None                               # the card's pair is no slot
    seen = card_ix + slot_ix[:1]                                   # one slot marker hidden
    with pytest.raises(InsertionError, match='no slot pair'):
        label_markers([ms[k] for k in seen], [rs[k] for k in seen], 850.0, up, MODEL)
    lab = label_markers([ms[k] for k in seen], [rs[k] for k in seen], 850.0, up, MODEL,
                        slot_memory=memory)
    assert lab.slot_remembered and not full.slot_remembered
    np.testing.assert_allclose(lab.points, full.points, atol=1e-12)
    # the visible slot marker and a stray marker at the card's spacing from it: the gate keeps
    # the slot marker out of the card's candidates, so no false card pair
    stray_pos = ms[slot_ix[0]].position + [2 * MODEL.card_marker_x_m, 0.0, 0.0]
    stray = StereoMarker(8, 8, stray_pos, np.eye(3) * 1e-8, (0, 0), (0, 0))
    with pytest.raises(InsertionError):
        label_markers([ms[slot_ix[0]], stray], [rs[slot_ix[0]], rs[card_ix[0]]], 850.0, up,
                      MODEL, slot_memory=memory)


def test_labels_follow_size_and_the_site_x_whatever_the_detection_order():
    cam = _camera()
    card = MODEL.card_goal(0.05)
    ms, rs, up = _observe(cam, card)
    lab = label_markers(ms, rs, 850.0, up, MODEL)
    site = [invert(cam)[:3, :3] @ p + invert(cam)[:3, 3] for p in MODEL.slot_markers]
    np.testing.assert_allclose(lab.points[2:], site, atol=1e-12)
    assert lab.points[0] @ np.cross(up, [0, 0, 1]) < lab.points[1] @ np.cross(up, [0, 0, 1])
    with pytest.raises(InsertionError, match='no card pair'):
        label_markers(ms[:1] + ms[2:], rs[:1] + rs[2:], 850.0, up, MODEL)
    with pytest.raises(InsertionError, match='no slot pair'):
        far = TaskModel(slot_width_m=0.2)
        label_markers(ms, rs, 850.0, up, far)
    # a slot marker imaged larger than it is (blur): still labelled by the spacings
    big = [r * (1.5 if abs(r - max(rs)) > 1e-9 and r < max(rs) else 1.0) for r in rs]
    lab2 = label_markers(ms, big, 850.0, up, MODEL)
    np.testing.assert_allclose(lab2.points, lab.points)
    # a fiducial-sized marker among them is ignored
    fid = StereoMarker(9, 9, ms[0].position + [0.3, 0.0, 0.0], np.eye(3) * 1e-8, (0, 0), (0, 0))
    lab3 = label_markers(ms + [fid], rs + [850.0 * 0.02 / fid.position[2]], 850.0, up, MODEL)
    np.testing.assert_allclose(lab3.points, lab.points)


@pytest.mark.parametrize('slot_in', [5.0, 4.5, 4.375])
def test_required_motion_is_zero_at_the_goal_and_the_offset_elsewhere(slot_in):
    model = TaskModel(slot_width_m=slot_in * 0.0254)
    cam = _camera()
    t_base_card = card_in_base(Q, R2)
    # the slave's base somewhere, turned: the site in the base frame follows from the card
    for offset, turn in (((0.0, 0.0, 0.0), 0.0), ((0.012, -0.004, 0.02), 0.03)):
        card_site = model.card_goal(model.standoff_m)
        card_site = homogeneous(rot_z(turn), offset) @ card_site
        ms, rs, up = _observe(cam, card_site)
        lab = label_markers(ms, rs, 850.0, up, model)
        m = card_required_motion(lab, t_base_card, model, above_m=model.standoff_m)
        # the base frame's view of the site: card_in_base = base_site @ card_site
        base_site = t_base_card @ invert(card_site)
        goal_base = base_site @ model.card_goal(model.standoff_m) @ model.card_marker_frame
        now = t_base_card @ model.card_marker_frame
        np.testing.assert_allclose(m.translation_s, goal_base[:3, 3] - now[:3, 3], atol=1e-9)
        assert m.angle_error_rad == pytest.approx(abs(turn), abs=1e-9)


def test_required_motion_carries_the_stereo_covariance():
    cam = _camera()
    rng = np.random.default_rng(3)
    card = MODEL.card_goal(MODEL.standoff_m)
    shifts = []
    for _ in range(120):
        ms, rs, up = _observe(cam, card, rng=rng, sigma=5e-4)
        lab = label_markers(ms, rs, 850.0, up, MODEL)
        m = card_required_motion(lab, card_in_base(Q, R2), MODEL, above_m=MODEL.standoff_m)
        shifts.append(m.translation_s)
    spread = np.std(np.array(shifts), axis=0)
    predicted = np.sqrt(np.diag(m.covariance_s)[:3])
    np.testing.assert_allclose(spread, predicted, rtol=0.35)


def test_go_to_pose_turns_drives_and_turns_on_a_unicycle():
    x, y, yaw = 0.0, 0.0, 0.0
    drive = GoToPose((1.0, -0.5), math.pi / 2)
    dt = 0.02
    for _ in range(3000):
        c = drive.command(x, y, yaw)
        if c.arrived:
            break
        yaw = wrap(yaw + c.angular_z * dt)
        x += c.linear_x * math.cos(yaw) * dt
        y += c.linear_x * math.sin(yaw) * dt
    assert c.arrived
    assert math.hypot(x - 1.0, y + 0.5) <= 0.02
    assert abs(wrap(yaw - math.pi / 2)) <= 0.02
    with pytest.raises(InsertionError):
        GoToPose((math.nan, 0.0), 0.0)


def test_follow_path_passes_every_waypoint_and_ends_at_the_heading():
    x, y, yaw = 0.0, 0.0, math.pi          # facing away from the path
    wps = [(1.0, 0.0), (1.0, 1.0), (0.0, 1.5)]
    drive = FollowPath(wps, -math.pi / 2)
    dt, closest = 0.02, [math.inf] * 3
    for _ in range(20000):
        c = drive.command(x, y, yaw)
        if c.arrived:
            break
        assert abs(c.linear_x) <= 0.2 + 1e-9
        yaw = wrap(yaw + c.angular_z * dt)
        x += c.linear_x * math.cos(yaw) * dt
        y += c.linear_x * math.sin(yaw) * dt
        closest = [min(d, math.hypot(x - wx, y - wy))
                   for d, (wx, wy) in zip(closest, wps, strict=False)]
    assert c.arrived
    assert closest[0] <= 0.25 and closest[1] <= 0.25        # passed within pass_m
    assert math.hypot(x, y - 1.5) <= 0.08                   # the last within tolerance
    assert abs(wrap(yaw + math.pi / 2)) <= 0.05
    for bad in ([], [(math.inf, 0.0)]):
        with pytest.raises(InsertionError):
            FollowPath(bad)
    with pytest.raises(InsertionError):
        FollowPath([(0.0, 0.0)], math.nan)


def test_the_site_from_the_slot_pair_is_the_site_frame_in_the_camera():
    """The slot pair alone, seen by a camera standing anywhere round the site's face, gives
    the site frame in the camera frame: site_from_slot(pair) = inverse(camera in site)."""
    for yaw in (-0.6, 0.0, 0.5):
        cam = homogeneous(rot_z(yaw), np.zeros(3)) @ _camera()
        ms, rs, up = _observe(cam, MODEL.card_goal(0.05))
        slot = [k for k, m in enumerate(ms) if m.left >= 2]
        pair = find_slot([ms[k] for k in slot], [rs[k] for k in slot], 850.0, up, MODEL)
        np.testing.assert_allclose(site_from_slot(pair, up, MODEL), invert(cam), atol=1e-9)
    with pytest.raises(InsertionError, match='side by side'):
        site_from_slot(SlotPair(np.array([[0, 0, 1.0], [0, -0.1, 1.0]]), np.zeros((2, 3, 3))),
                       [0, -1.0, 0], MODEL)


def test_the_slot_pair_a_located_site_predicts_is_the_one_the_camera_sees():
    """slot_from_site is site_from_slot's inverse: the pair it predicts from the site's pose
    in the camera is the pair seen (same order), and gives that pose back."""
    for yaw in (-0.6, 0.0, 0.5):
        cam = homogeneous(rot_z(yaw), np.zeros(3)) @ _camera()
        ms, rs, up = _observe(cam, MODEL.card_goal(0.05))
        slot = [k for k, m in enumerate(ms) if m.left >= 2]
        seen = find_slot([ms[k] for k in slot], [rs[k] for k in slot], 850.0, up, MODEL)
        pred = slot_from_site(invert(cam), MODEL, sigma_m=0.01)
        np.testing.assert_allclose(pred.points, seen.points, atol=1e-9)
        np.testing.assert_allclose(pred.covariances, [np.eye(3) * 1e-4] * 2)
        np.testing.assert_allclose(site_from_slot(pred, up, MODEL), invert(cam), atol=1e-9)
    for bad in ({'site_in_camera': np.full((4, 4), np.nan), 'sigma_m': 0.01},
                {'site_in_camera': np.eye(4), 'sigma_m': 0.0}):
        with pytest.raises(InsertionError):
            slot_from_site(bad['site_in_camera'], MODEL, sigma_m=bad['sigma_m'])


def test_the_search_covers_the_region_from_its_centre_out():
    pts = search_points([3.0, 0.0, 0.4], [0.0, 2.0, 0.5], half_width_m=0.3, spacing_m=0.3)
    assert pts.shape == (9, 3)
    np.testing.assert_allclose(pts[0], [3.0, 0.0, 0.4])
    np.testing.assert_allclose(pts[1], [3.0, 0.3, 0.4])          # the camera's side first
    d = np.hypot(*(pts[:, :2] - [3.0, 0.0]).T)
    assert np.all(np.diff(d) >= -1e-12)
    np.testing.assert_allclose(sorted(set(np.round(pts[:, 0], 9))), [2.7, 3.0, 3.3])
    np.testing.assert_allclose(pts[:, 2], 0.4)
    # a spacing that does not divide the region: its edges still covered, no gap wider
    pts = search_points([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], half_width_m=0.3, spacing_m=0.25)
    xs = np.array(sorted(set(np.round(pts[:, 0], 9))))
    assert xs[0] == -0.3 and xs[-1] == 0.3 and np.max(np.diff(xs)) <= 0.25
    assert len(search_points([0, 0, 0], [1, 0, 0], half_width_m=0.0, spacing_m=0.3)) == 1
    with pytest.raises(InsertionError, match='vertical'):
        search_points([0, 0, 0], [0, 0, 1.0], half_width_m=0.3, spacing_m=0.3)


def test_the_site_estimate_averages_positions_and_headings_across_the_wrap():
    est = SiteEstimate()
    with pytest.raises(InsertionError):
        _ = est.position
    for h, dx in ((math.pi - 0.01, 0.002), (-math.pi + 0.03, -0.002)):
        est.add(homogeneous(rot_z(h), [1.0 + dx, 2.0, 0.4]))
    assert len(est) == 2
    np.testing.assert_allclose(est.position, [1.0, 2.0, 0.4])
    assert abs(wrap(est.heading - (math.pi + 0.01))) < 1e-9
    np.testing.assert_allclose(est.normal, [-math.sin(est.heading), math.cos(est.heading), 0])
    assert est.spread_m == pytest.approx(0.002)
    est.clear()
    assert len(est) == 0
