"""Contact in the world core: the Table 5-1 site, the card entering the slot or landing on a
jaw, penetration, and the contact force at the F/T sensor (ch. 5, app. A.4)."""
import math

import numpy as np
import pytest

from coop_common.dynparams import load_truth
from rover_sim.config import ConfigError, NoiseConfig, SimConfig
from rover_sim.rover_model import ReachError, card_fk, card_ik
from rover_sim.scenarios import card_over_slot, lower_card
from rover_sim.world import World
from rover_sim.worldgen import CARD_WIDTH_M, INCH, TABLE_5_1_GAPS_M, generate_world

QUIET = NoiseConfig(fraction=0.0)


def test_site_geometry_is_table_5_1s():
    assert [round(g / INCH, 3) for g in TABLE_5_1_GAPS_M] == [5.0, 4.5, 4.375]
    for gap in TABLE_5_1_GAPS_M:
        site = generate_world(seed=1, occlusion_density=0.0, slot_gap_m=gap).site
        near, far, floor = site.jaws
        inner_near = near.centre[0] + near.half_extents[0]
        inner_far = far.centre[0] - far.half_extents[0]
        assert inner_far - inner_near == pytest.approx(gap)
        assert site.slot_centre[0] == pytest.approx((inner_near + inner_far) / 2)
        assert floor.centre[2] + floor.half_extents[2] == pytest.approx(
            site.slot_centre[2] - site.seat_depth_m)
        # the fiducials of the target-frame initialisation stay where coop_mapping knows them
        assert site.markers == ((2.9, -0.062, 0.25), (2.9, 0.062, 0.25))
        # slot markers on the jaws' +y faces, either side of the mouth
        (xa, ya, za), (xb, yb, zb) = site.slot_markers
        assert ya == yb == pytest.approx(near.centre[1] + near.half_extents[1])
        assert xa < inner_near and xb > inner_far and za == zb < site.slot_centre[2]
    with pytest.raises(ValueError, match='slot_gap_m'):
        generate_world(seed=1, occlusion_density=0.0, slot_gap_m=CARD_WIDTH_M)
    with pytest.raises(ConfigError, match='slot_gap_m'):
        SimConfig(slot_gap_m=0.1)


def test_card_ik_is_the_inverse_of_fk_and_refuses_what_is_out_of_reach():
    for x, z, pitch in ((0.30, -0.02, 0.0), (0.35, 0.05, 0.1), (0.25, -0.10, -0.2)):
        q = card_ik(x, z, pitch)
        np.testing.assert_allclose(card_fk(*q), (x, z, pitch), atol=1e-12)
    with pytest.raises(ReachError):
        card_ik(0.8, 0.0)


def _world(gap: float) -> World:
    return World(SimConfig(rovers=2, occlusion_density=0.0, stereo_rate_hz=0.0, slot_gap_m=gap,
                           noise=QUIET), [load_truth()] * 2)


def test_an_aligned_card_is_seated_without_penetration():
    with _world(TABLE_5_1_GAPS_M[2]) as w:
        start = card_over_slot(w, 1)
        assert w.insertion_depth(1) < 0 and not w.seated(1)
        assert w.contact(1).points == 0
        worst = max(c.max_penetration_m for c in lower_card(
            w, start, depth_m=0.02 + w.layout.site.seat_depth_m + 0.005, hold_s=1.5))
        assert w.seated(1), w.insertion_depth(1)
        assert 'floor' in w.contact(1).bodies
        assert worst < 0.5e-3


def test_a_misaligned_card_lands_on_the_far_jaw_and_is_not_seated():
    with _world(TABLE_5_1_GAPS_M[2]) as w:
        start = card_over_slot(w, 1, offset_m=0.004)
        worst = max(c.max_penetration_m for c in lower_card(w, start, depth_m=0.04, hold_s=1.0))
        cs = w.contact(1)
        assert cs.bodies == ('jaw_far',) and cs.force[2] > 0.5
        assert w.insertion_depth(1) == -math.inf and not w.seated(1)
        assert worst < 0.5e-3


def test_the_contact_force_reaches_the_ft_sensor():
    """Pressing on a jaw, the F/T sensor reads what statics says the base holds: the arm's
    weight and the contact wrench, the force in the sensor's axes, the moment about its origin
    (weight moments from the links' own masses and c.o.m.s, not from the sensor model)."""
    with _world(TABLE_5_1_GAPS_M[2]) as w:
        start = card_over_slot(w, 1, offset_m=0.004)
        *_, cs = lower_card(w, start, depth_m=0.04, hold_s=1.0)
        s, rot, p = w.sense(1), w.truth(1).base_rotation, w._sensor_origin(w.rovers[1])
        centre = w.card_pose(1)[0]
        assert np.linalg.norm(cs.force) > 1.0
        m, c = w.link_masses_and_coms(1, w.rovers[1].arm_links)
        g = np.array([0.0, 0.0, -9.81])
        force = -(m.sum() * g) - cs.force
        moment = (-np.cross(c - p, m[:, None] * g).sum(axis=0)
                  - (cs.torque + np.cross(centre - p, cs.force)))
        np.testing.assert_allclose(s.force, rot.T @ force, atol=0.03)
        np.testing.assert_allclose(s.torque, rot.T @ moment, atol=0.01)


def test_camera_mount_puts_the_camera_where_asked():
    from rover_sim.rover_model import MAST_JOINTS, camera_mount

    with _world(TABLE_5_1_GAPS_M[1]) as w:
        for xy, yaw, pitch in (((1.0, -0.5), 0.7, 0.3), ((2.0, 1.0), -2.5, -0.1)):
            m = camera_mount(xy, yaw, pitch)
            w.place_rover(0, *m.base_xy, m.base_yaw)
            w.command_mast(0, MAST_JOINTS, [0.1], [[m.pan, m.tilt]])
            for _ in range(200):
                w.step()
            pos, rot = w.camera_pose(0)
            axis = rot[:, 2]
            np.testing.assert_allclose(pos, [*xy, m.camera_z], atol=0.01)
            assert math.atan2(axis[1], axis[0]) == pytest.approx(yaw, abs=0.01)
            assert -math.asin(axis[2]) == pytest.approx(pitch, abs=0.01)
    with pytest.raises(ReachError):
        camera_mount((0.0, 0.0), 0.0, 1.5)


def test_shared_geometry_puts_card_and_camera_where_the_sim_has_them():
    """coop_common.rover_geometry (what the insertion nodes reason with) against the world:
    the card from the arm's encoders and the left camera from the mast's, in the base frame."""
    from coop_common.rover_geometry import (
        ARM_JOINTS,
        MAST_JOINTS,
        camera_in_base,
        card_in_base,
        card_joints,
    )

    with _world(TABLE_5_1_GAPS_M[1]) as w:
        r2 = w.rovers[1].params.cg_to_arm
        for heading, given, pitch, mast in ((0.0, None, 0.0, (0.0, 0.3)),
                                            (0.3, None, 0.1, (0.4, -0.2))):
            target = given
            if target is None:     # in the plane joint 1 turns the arm into
                target = np.array([r2[0] + 0.45 * math.cos(heading),
                                   r2[1] + 0.45 * math.sin(heading), 0.2])
            q = card_joints(target, heading, pitch, r2)
            w.command_arm(1, ARM_JOINTS, [0.3], [list(q)])
            w.command_mast(1, MAST_JOINTS, [0.1], [list(mast)])
            for _ in range(300):
                w.step()
            t = w.truth(1)
            qm = w.joint_positions(1, ARM_JOINTS)
            pan, tilt = w.joint_positions(1, MAST_JOINTS)
            pos, rot = w.card_pose(1)
            tc = card_in_base(qm, r2)
            np.testing.assert_allclose(t.base_rotation @ tc[:3, 3] + t.base_position, pos,
                                       atol=2e-4)
            np.testing.assert_allclose(t.base_rotation @ tc[:3, :3], rot, atol=2e-4)
            cam = camera_in_base(pan, tilt)
            cp, cr = w.camera_pose(1)
            np.testing.assert_allclose(t.base_rotation @ cam[:3, 3] + t.base_position, cp,
                                       atol=2e-4)
            np.testing.assert_allclose(t.base_rotation @ cam[:3, :3], cr, atol=2e-4)
    with pytest.raises(ReachError, match='off the arm plane'):
        card_joints((0.5, 0.5, 0.3), 0.0, 0.0, r2)
