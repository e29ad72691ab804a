"""The BRAID camera mast (issue #37, deliverable 5): the optical frame's forward kinematics on
the pan link and the view table the planner takes its reachable views from."""
import math

import numpy as np
import pytest

from coop_braid.errors import BraidError
from coop_braid.ik import Weights
from coop_braid.mast import (
    OPTICAL_IN_BODY,
    BraidMast,
    MastKind,
    Tolerance,
    heading_pitch,
    roll_of,
    view_rotation,
    view_table,
)


def test_straight_mast_holds_a_level_camera_above_the_pan_joint():
    m = BraidMast.uniform(4, base_above_pan_m=-0.1, camera_above_end_m=0.03)
    for state, leg in ((0, 0.045), (7, 0.060)):
        t = m.optical_in_pan([state] * 4)
        np.testing.assert_allclose(t[:3, 3], [0.0, 0.0, -0.1 + 4 * leg + 0.03], atol=1e-12)
        np.testing.assert_allclose(t[:3, :3], OPTICAL_IN_BODY, atol=1e-12)
        assert heading_pitch(t) == pytest.approx((0.0, 0.0), abs=1e-12)


def test_optical_pose_is_base_chain_camera_product():
    m = BraidMast.uniform(3, base_above_pan_m=0.05, camera_above_end_m=0.02)
    s = [1, 6, 3]
    want = np.eye(4)
    want[2, 3] = 0.05
    cam = np.eye(4)
    cam[:3, :3], cam[2, 3] = OPTICAL_IN_BODY, 0.02
    np.testing.assert_allclose(m.optical_in_pan(s), want @ m.chain.pose(s) @ cam, atol=1e-15)
    # end_target inverts it: the chain end that puts the camera there
    np.testing.assert_allclose(m.end_target(m.optical_in_pan(s)), m.chain.pose(s), atol=1e-12)


def test_one_leg_extended_pitches_the_camera_up_by_the_stage_tilt():
    # leg 1 (on +x, the camera's side) long: the platform's x axis, the optical axis, tilts up
    m = BraidMast.uniform(1)
    _, pitch = heading_pitch(m.optical_in_pan([1]))
    assert math.degrees(pitch) == pytest.approx(-14.45, abs=0.05)


def test_view_rotation_heading_pitch_roll_round_trip():
    r = np.eye(4)
    r[:3, :3] = view_rotation(math.radians(12.0), math.radians(-30.0), math.radians(7.0))
    h, p = heading_pitch(r)
    assert (math.degrees(h), math.degrees(p)) == pytest.approx((-30.0, 12.0), abs=1e-9)
    assert math.degrees(roll_of(r)) == pytest.approx(7.0 * math.cos(math.radians(12.0)),
                                                     abs=0.1)


def test_view_table_keeps_views_within_tolerance_at_their_reached_pose():
    m = BraidMast.rover(5)
    # the straight chain's own views are reached exactly; one 0.4 m above the straight,
    # extended mast is not, and is reported with its residual
    top = -0.33 + 5 * 0.060 + 0.03
    vt = view_table(m, heights_m=[top - 0.03, top + 0.4], pitches_rad=[0.0],
                    weights=Weights(orientation=0.3))
    assert [t.reached for t in vt.tried] == [True, False]
    assert vt.tried[1].pos_err_m > 0.3
    (v,) = vt.views
    np.testing.assert_allclose(v.pose, m.optical_in_pan(v.states), atol=1e-15)
    assert v.pos_err_m <= Tolerance().position_m
    assert abs(v.pitch - 0.0) <= Tolerance().pitch_rad
    assert abs(v.roll_rad) <= Tolerance().roll_rad


def test_a_tight_pitch_tolerance_rejects_what_a_loose_one_keeps():
    m = BraidMast.rover(5)
    kw = {'heights_m': [-0.05], 'pitches_rad': [math.radians(5.0)],
          'headings_rad': [0.0, math.radians(8.0)], 'rolls_rad': [0.0, math.radians(12.0)],
          'weights': Weights(orientation=0.3)}
    loose = view_table(m, tolerance=Tolerance(position_m=0.05, pitch_rad=math.radians(10),
                                              roll_rad=math.radians(30)), **kw)
    tight = view_table(m, tolerance=Tolerance(position_m=0.05, pitch_rad=math.radians(0.01),
                                              roll_rad=math.radians(30)), **kw)
    assert len(loose.views) == 1
    assert not tight.views and not tight.tried[0].reached
    assert tight.tried[0].pitch_err_rad == pytest.approx(loose.views[0].pitch_err_rad)


def test_bad_input_is_refused_with_the_reason():
    with pytest.raises(BraidError, match='position_m'):
        Tolerance(position_m=0.0)
    with pytest.raises(BraidError, match='base_above_pan_m'):
        BraidMast.uniform(2, base_above_pan_m=math.nan)
    with pytest.raises(BraidError, match='at least one'):
        view_table(BraidMast.uniform(2), heights_m=[], pitches_rad=[0.0])
    with pytest.raises(BraidError, match='not finite'):
        view_table(BraidMast.uniform(2), heights_m=[0.1], pitches_rad=[math.inf])
    assert MastKind('braid') is MastKind.BRAID
    with pytest.raises(ValueError):
        MastKind('telescope')
