"""The slave's insertion loop (slave.py) on rover_sim's world core, no DDS: fixes are the true
marker positions in a fixed camera's frame plus stereo-like noise at 4 Hz; the arm, base, F/T and
odometry are the simulator's. Checks the loop's phases end to end and the bad-input rules."""
import math

import numpy as np
import pytest

from coop_common.dynparams import load_truth
from coop_common.rover_geometry import ARM_JOINTS, joint2_in_base
from coop_insertion.errors import InsertionError
from coop_insertion.slave import Phase, SlaveController
from coop_insertion.task import LabelledMarkers, TaskModel

rover_sim = pytest.importorskip('rover_sim.world')
from rover_sim.config import NoiseConfig, SimConfig  # noqa: E402
from rover_sim.world import World  # noqa: E402
from rover_sim.worldgen import INCH  # noqa: E402

SIGMA_DEPTH_M = 5e-4      # a 0.1 px disparity at 0.6 m with f = 850 px, b = 38 mm


def _run(slot_in: float, seed: int, *, vision: bool = True, sim_s: float = 45.0):
    gap = slot_in * INCH
    cfg = SimConfig(rovers=2, occlusion_density=0.0, stereo_rate_hz=0.0, slot_gap_m=gap,
                    seed=seed, noise=NoiseConfig(encoder_rad=0.0077))
    rng = np.random.default_rng(seed)
    with World(cfg, [load_truth()] * 2) as w:
        model = TaskModel(slot_width_m=gap)
        r2 = w.rovers[1].params.cg_to_arm
        sx, sy, top = w.layout.site.slot_centre
        j2 = joint2_in_base(r2)
        w.place_rover(1, sx - 0.30 - j2[0] - 0.55 + rng.uniform(-0.03, 0.03),
                      sy - j2[1] + rng.uniform(-0.02, 0.02), rng.uniform(-0.05, 0.05))
        site = np.eye(4)
        site[:3, 3] = (sx, sy, top)
        ctl = SlaveController(model, r2, site_in_odom=site)
        cam_p = np.array([sx, sy + 0.6, top + 0.35])
        look = np.array([sx, sy, top]) - cam_p
        look /= np.linalg.norm(look)
        xc = np.cross(look, [0.0, 0.0, 1.0])
        xc /= np.linalg.norm(xc)
        r_wc = np.column_stack([xc, np.cross(look, xc), look])
        var = np.array([SIGMA_DEPTH_M ** 2 / 9, SIGMA_DEPTH_M ** 2 / 9, SIGMA_DEPTH_M ** 2])
        k, pen, phases = 0, 0.0, []
        while w.time_s < sim_s:
            w.step()
            k += 1
            rd = w.sense(1)
            xy, yaw, _, _ = w.odometry(1)
            ctl.add_state(w.time_s, rd.joint_positions[:4], [xy[0], xy[1], yaw],
                          np.concatenate([rd.force, rd.torque]))
            c, r = w.card_pose(1)
            seen = abs(c[0] - sx) < 0.15      # the camera's field at the site
            if vision and seen and k % 50 == 0:
                pts = [c + r @ m for m in model.card_markers] + \
                    [np.array(m) for m in w.layout.site.slot_markers]
                pc = np.array([r_wc.T @ (p - cam_p) for p in pts])
                pc += rng.normal(size=(4, 3)) * np.sqrt(var)
                ctl.add_observation(w.time_s, LabelledMarkers(
                    pc, np.array([np.diag(var)] * 4), r_wc.T @ np.array([0.0, 0.0, 1.0])))
            cmd = ctl.step(w.time_s)
            if cmd.arm_joints is not None and k % 2 == 0:
                w.command_arm(1, ARM_JOINTS, [0.02], [list(cmd.arm_joints)])
            w.command_velocity(1, cmd.base_linear_x, cmd.base_angular_z)
            cs = w.contact(1)
            pen = max(pen, cs.max_penetration_m if cs else 0.0)
            if not phases or phases[-1] != cmd.status.phase:
                phases.append(cmd.status.phase)
            if cmd.status.done:
                break
        return cmd.status, w.seated(1), pen, phases, ctl


def test_an_easy_insertion_seats_the_card_through_every_phase():
    st, seated, pen, phases, ctl = _run(5.0, 1)
    assert st.done and st.success, st.reason
    assert seated
    assert pen <= 5e-4
    assert phases == [Phase.READY, Phase.VISUAL_SERVO, Phase.FORCE_INSERT, Phase.DONE]
    assert 0.0 < ctl.peak_force_n <= 25.0


def test_without_vision_the_slave_stops_short_and_never_descends():
    st, seated, pen, phases, ctl = _run(5.0, 2, vision=False, sim_s=20.0)
    assert not st.done and not st.descending and not seated
    assert Phase.FORCE_INSERT not in phases
    assert pen == 0.0


def test_bad_inputs_are_refused():
    with pytest.raises(InsertionError):
        SlaveController(TaskModel(), [0.0, math.nan, 0.1])
    ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1])
    with pytest.raises(InsertionError, match='before the first state'):
        ctl.step(0.0)
    with pytest.raises(InsertionError):
        ctl.add_state(0.0, [0.0] * 3, [0.0] * 3, [0.0] * 6)


def test_a_card_tilted_on_one_corner_is_not_seated():
    from coop_insertion.contact import ContactState
    from coop_insertion.slave import card_seated
    geo = {'slot_depth_m': 0.030, 'card_width_m': 4.25 * INCH, 'seat_angle_rad': 0.02}
    corner = ContactState.CORNER_ON_BOTTOM
    # 29.2 mm at the lower edge's centre, tilted 2 deg: the higher corner is 27.3 mm down
    assert not card_seated(corner, 0.0292, math.radians(2.0), stalled=True, **geo)
    assert not card_seated(corner, 0.0295, -0.03, stalled=False, **geo)
    # flat: at the floor within 1 mm, or stalled within 4 mm against the bottom
    assert card_seated(corner, 0.0296, math.radians(0.5), stalled=False, **geo)
    assert card_seated(corner, 0.0265, 0.0, stalled=True, **geo)
    assert not card_seated(corner, 0.0265, 0.0, stalled=False, **geo)
    assert not card_seated(ContactState.FREE, 0.0265, 0.0, stalled=True, **geo)
    assert card_seated(ContactState.SEATED, 0.020, 0.0, stalled=False, **geo)


def test_the_abort_needs_a_force_sustained_over_three_readings():
    from coop_insertion.slave import ABORT_SAMPLES

    def force_phase():
        ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1], max_force_n=20.0)
        ctl.phase, ctl._tare, ctl._last_force_step = Phase.FORCE_INSERT, np.zeros(6), 1e9
        return ctl

    q = [0.0, 0.6, -1.0, 0.4]
    ctl = force_phase()       # one 73 N reading among small ones: an impact's ring, go on
    for k, f in enumerate([1.0, 73.0, 1.0, 1.0]):
        ctl.add_state(0.005 * k, q, [0.0] * 3, [0.0, 0.0, f, 0.0, 0.0, 0.0])
        assert not ctl.step(0.005 * k).status.done
    assert ctl.peak_force_n == 73.0
    ctl = force_phase()       # three in a row above 1.5 x 20 N: abort
    for k in range(ABORT_SAMPLES):
        ctl.add_state(0.005 * k, q, [0.0] * 3, [0.0, 0.0, 40.0, 0.0, 0.0, 0.0])
        st = ctl.step(0.005 * k).status
    assert st.done and not st.success and 'abort limit 30.0 N' in st.reason
