"""The slave's insertion loop (slave.py) on rover_sim's world core, no DDS: fixes are the true
marker positions in a fixed camera's frame plus stereo-like noise at 4 Hz; the arm, base, F/T and
odometry are the simulator's. Checks the loop's phases end to end and the bad-input rules."""
import math

import numpy as np
import pytest

from coop_insertion.errors import InsertionError
from coop_insertion.slave import Phase, SlaveController
from coop_insertion.task import TaskModel

rover_sim = pytest.importorskip('rover_sim.world')
from coop_insertion.force_trials import run_trial  # noqa: E402
from rover_sim.worldgen import INCH  # noqa: E402


def _run(slot_in: float, seed: int, **kw):
    trial, st, phases, ctl = run_trial(slot_in, seed, **kw)
    return st, trial.seated, trial.max_penetration_mm * 1e-3, phases, ctl


def test_an_easy_insertion_seats_the_card_through_every_phase():
    """The slave's default verdict (SeatVerdict.FLOOR_FORCE) on the simulator's world core."""
    st, seated, pen, phases, ctl = _run(5.0, 1)
    assert st.done and st.success, st.reason
    assert seated and not st.awaiting_fix
    assert pen <= 5e-4
    assert phases == [Phase.READY, Phase.VISUAL_SERVO, Phase.FORCE_INSERT, Phase.DONE]
    assert 0.0 < ctl.peak_force_n <= 25.0
    assert ctl.relocations == 0     # the first fix within the servo's reach


def test_without_vision_the_slave_stops_short_and_never_descends():
    st, seated, pen, phases, _ctl = _run(5.0, 2, vision=False, sim_s=20.0)
    assert not st.done and not st.descending and not seated
    assert st.awaiting_fix          # the approach done: what tells the master to re-place
    assert Phase.FORCE_INSERT not in phases
    assert pen == 0.0


def test_a_failure_in_contact_backs_off_and_leaves_no_force_on_the_card():
    """A timeout (the master silent, the caller's limit) half a second into contact: the
    card's target rises and the truth's contact force on the card is gone 2 s later."""
    trial, st, phases, ctl = run_trial(5.0, 1, fail_in_contact_s=0.5,
                                       slave_options={'seat_verdict': 'both_corners'})
    assert Phase.FORCE_INSERT in phases and st.done and not st.success
    assert 'backed off 20 mm' in st.reason
    assert ctl.hold_joints is not None
    assert trial.end_contact_n < 0.5, trial.end_contact_n
    # a failure before the card comes down leaves the arm where it is
    ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1])
    ctl.add_state(0.0, [0.0, 0.6, -1.0, 0.4], [0.0] * 3, [0.0] * 6)
    ctl.step(0.0)
    ctl.fail('canceled')
    assert ctl.hold_joints is None and ctl.step(0.01).arm_joints is None


def test_bad_inputs_are_refused():
    with pytest.raises(InsertionError):
        SlaveController(TaskModel(), [0.0, math.nan, 0.1])
    ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1])
    with pytest.raises(InsertionError, match='before the first state'):
        ctl.step(0.0)
    with pytest.raises(InsertionError):
        ctl.add_state(0.0, [0.0] * 3, [0.0] * 3, [0.0] * 6)


def test_seated_is_both_corners_on_the_floor_by_the_wrench():
    from coop_insertion.contact import ContactState, SeatCheck
    from coop_insertion.slave import card_seated
    geo = {'slot_depth_m': 0.030, 'card_width_m': 4.25 * INCH, 'seat_force_n': 4.0}
    seated, corner = ContactState.SEATED, ContactState.CORNER_ON_BOTTOM
    ok = SeatCheck((2.5, 2.5), 0.0, 'corner_and_side:-1', 15.0, True)
    geo_ok = {**geo, 'seat': ok}
    assert card_seated(seated, 0.0298, 0.0, floor_force_n=5.0, **geo_ok)
    # the estimate may be a degree off: the wrench decides, the estimate only within 4 mm
    assert card_seated(seated, 0.0295, math.radians(1.0), floor_force_n=5.0, **geo_ok)
    assert not card_seated(seated, 0.0240, 0.0, floor_force_n=5.0, **geo_ok)
    # pressed too lightly for one corner's moment to show: not yet
    assert not card_seated(seated, 0.0298, 0.0, floor_force_n=2.0, **geo_ok)
    # on one corner, however flat and deep the estimate says it is (through the graph: a card
    # 0.3 deg from flat by the estimate, tilted past its tolerance by the truth)
    for state in (corner, ContactState.TWO_POINT, ContactState.FREE, ContactState.CORNER_ON_WALL,
                  ContactState.CORNER_AND_SIDE):
        assert not card_seated(state, 0.0300, math.radians(0.3), floor_force_n=8.0, **geo_ok)
    # SEATED by the fit and 3.4 N on the floor, but the seat check failed or was not made (the
    # graph's false seat: one corner down, the other held up by a jaw): not seated
    failed = SeatCheck((2.3, 1.1), 0.0, 'corner_and_side:-1', 0.0, False)
    for seat in (failed, None):
        assert not card_seated(seated, 0.0299, math.radians(0.1), floor_force_n=4.2,
                               **{**geo, 'seat': seat})
    # the corner-loads verdict reads the corners' loads alone: both >= 1 N passes without the
    # rival margin, a corner carrying 0.1 N (a card landing on one corner) does not
    from coop_insertion.slave import SeatVerdict
    loads = {**geo, 'verdict': SeatVerdict.CORNER_LOADS}
    assert card_seated(seated, 0.0299, 0.0, floor_force_n=4.2, seat=failed, **loads)
    one = SeatCheck((2.5, 0.1), 0.0, 'corner_and_side:-1', 0.0, False)
    for seat in (one, None):
        assert not card_seated(seated, 0.0299, 0.0, floor_force_n=4.2, seat=seat, **loads)
    # the floor's push alone passes the one-corner landing: the default's known flaw
    assert card_seated(seated, 0.0299, 0.0, floor_force_n=4.2, seat=one,
                       **{**geo, 'verdict': SeatVerdict.FLOOR_FORCE})


def test_a_card_on_one_corner_held_up_by_a_jaw_is_not_called_seated():
    """The false seat through the graph as the slave's verdict sees it: a 4.5 in slot 30 mm
    deep, the left corner on the floor, the right one 3 mm up the right wall held there by the
    wall's friction (mu 0.4, the simulator's default), the estimate 29.9 mm deep and 0.1 deg
    from flat. The floor's sum is over the seat force; the verdict is not seated."""
    from coop_insertion.contact import CardPose, ContactIdentifier, SlotGeometry
    from coop_insertion.slave import card_seated
    geo = SlotGeometry(slot_width_m=4.5 * INCH, slot_depth_m=0.030)
    half, wc, mu = geo.slot_width_m / 2, geo.card_width_m, 0.4
    c_l, c_r = np.array([half - wc, -0.030]), np.array([half, -0.027])
    f_l, f_w = 2.4, 2.5
    fx = min(mu * f_l, f_w) - f_w
    fy = f_l + mu * f_w
    w = np.array([fx, fy, c_l[0] * f_l - c_l[1] * min(mu * f_l, f_w) +
                  c_r[0] * mu * f_w - c_r[1] * -f_w])
    est = CardPose(0.0015, -0.0299, math.radians(0.1))
    ident = ContactIdentifier(geo).identify(w, est)
    assert ident.floor_force_n >= 3.0
    assert not card_seated(ident.state, -est.y, est.theta, floor_force_n=ident.floor_force_n,
                           seat_force_n=3.0, slot_depth_m=0.030, card_width_m=wc,
                           seat=ident.seat)


def test_the_floor_felt_sets_the_depth_of_the_cards_lowest_corner():
    from coop_insertion.contact import CardPose, Contact, ContactState, Identification
    from coop_insertion.slave import floor_correction
    geo = {'slot_depth_m': 0.030, 'card_width_m': 4.25 * INCH, 'min_force_n': 1.5}

    def ident(kind: str, force: float, state=ContactState.CORNER_ON_BOTTOM) -> Identification:
        c = Contact(np.array([-0.05, -0.03]), np.array([0.0, 1.0]), force, 0.0, -1, kind)
        return Identification(state, -1, (c,), 0.0, 0.0)

    # the estimate put the edge's centre 32.7 mm down at 1.4 deg: its lowest corner 34.0 mm,
    # through the floor; felt on the bottom, the lowest corner is at 30 mm, the other 27.4 mm
    tilt = math.radians(1.4)
    pose = CardPose(0.0, -0.0327, tilt)
    dy = floor_correction(ident('corner_on_bottom', 6.0), pose, **geo)
    lowest = pose.y + dy - geo['card_width_m'] / 2 * math.sin(tilt)
    assert dy > 0 and lowest == pytest.approx(-0.030)
    # seated flat 1 mm short of the floor by the estimate: moved down 1 mm
    assert floor_correction(ident('seated', 4.0, ContactState.SEATED), CardPose(0.0, -0.029, 0.0),
                            **geo) == pytest.approx(-0.001)
    # no correction: a light touch, a contact that is not the floor, a floor 2 cm off the
    # estimate (that is a jaw's mouth, whatever the identification says)
    assert floor_correction(ident('corner_on_bottom', 1.0), pose, **geo) == 0.0
    assert floor_correction(ident('corner_on_wall', 9.0), pose, **geo) == 0.0
    assert floor_correction(ident('corner_on_bottom', 9.0), CardPose(0.0, -0.010, 0.0),
                            **geo) == 0.0


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


def test_the_first_step_after_a_vision_hold_moves_the_arm_one_period_not_the_whole_hold():
    """A hold (vision older than the servo's timeout) must not leave the next step to integrate
    the arm's velocity over the whole hold: that is a jump of the card, not a command."""
    from types import SimpleNamespace

    from coop_insertion.servo import ServoCommand
    ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1], max_relocations=0)
    q = [0.0, 0.6, -1.0, 0.4]
    arm_v = np.array([0.01, 0.0, 0.0])          # 10 mm/s forward, the card's own direction
    held = {'now': False}

    def command(_t):
        return ServoCommand(0.0, 0.0, arm_v if not held['now'] else np.zeros(3), np.zeros(3),
                            np.full(3, 0.05), np.zeros(3), held['now'],
                            'vision too old' if held['now'] else '', 0.1)
    ctl.servo = SimpleNamespace(goal=object(), command=command, newest_fix_stamp=0.0,
                                add_odometry=lambda *_: None)
    ctl.phase = Phase.VISUAL_SERVO
    t = 0.0
    moves = []
    for k in range(400):                         # 0.5 s moving, 1 s held, 0.5 s moving
        t = 0.005 * k
        held['now'] = 0.5 <= t < 1.5
        ctl.add_state(t, q, [0.0] * 3, [0.0] * 6)
        before = ctl._target.position.copy() if ctl._target is not None else None
        ctl.step(t)
        if before is not None:
            moves.append(float(np.linalg.norm(ctl._target.position - before)))
    # every step moves the card at most one 5 ms period at 10 mm/s (0.05 mm)
    assert max(moves) <= 0.01 * 0.005 + 1e-9, max(moves)


def test_a_fix_far_to_the_side_relocates_the_base_once():
    """A fix whose goal lies 0.25 m to the card's left (the two rovers' odometry frames
    disagree, as after a long mission): a skid-steer base cannot move the card sideways, so
    the slave does not servo; the arm goes back to its carry pose and the base turns to face
    the pose that puts the card at the goal (relocating, not awaiting a fix), once."""
    from coop_insertion.servo import VisionFix
    ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1], ready_s=0.1)
    q = [0.0, 0.6, -1.0, 0.4]
    for k in range(40):                          # READY, then VISUAL_SERVO with no fix
        ctl.add_state(0.005 * k, q, [0.0] * 3, [0.0] * 6)
        ctl.step(0.005 * k)
    assert ctl.phase is Phase.VISUAL_SERVO and ctl.relocations == 0
    t = 0.2
    ctl.add_state(t, q, [0.0] * 3, [0.0] * 6)
    ctl.servo.add_vision(VisionFix(t, np.array([0.02, 0.25, 0.0]), np.zeros(3),
                                   np.eye(6) * 1e-6))
    cmd = ctl.step(t)
    assert ctl.relocations == 1
    assert cmd.status.relocating and not cmd.status.awaiting_fix
    assert cmd.base_linear_x == 0.0 and cmd.base_angular_z > 0.0   # turning left, on the spot
    np.testing.assert_allclose(ctl._target.position, ctl.carry)
    for k in range(1, 20):                       # still on its way: no second relocation
        ctl.add_state(t + 0.005 * k, q, [0.0] * 3, [0.0] * 6)
        assert ctl.step(t + 0.005 * k).status.relocating
    assert ctl.relocations == 1
    # within reach: 3 cm aside is the servo's
    near = SlaveController(TaskModel(), [0.01, 0.3, 0.1], ready_s=0.1)
    for k in range(40):
        near.add_state(0.005 * k, q, [0.0] * 3, [0.0] * 6)
        near.step(0.005 * k)
    near.add_state(t, q, [0.0] * 3, [0.0] * 6)
    near.servo.add_vision(VisionFix(t, np.array([0.02, 0.03, 0.0]), np.zeros(3),
                                    np.eye(6) * 1e-6))
    assert not near.step(t).status.relocating and near.relocations == 0


def test_a_card_come_in_at_an_angle_is_turned_by_the_base_and_seats():
    """The slave's map 9 cm aside: its approach steers the base that way and the card arrives
    0.18 rad about the vertical from the goal, which the 4-DOF arm cannot turn; without a
    relocation the servo holds there aligned but turned, never descending (seed 2 of the
    20-seed mission). The base turns it (once) and the card seats."""
    trial, st, _phases, ctl = run_trial(5.0, 1, map_error_m=(0.0, 0.09), sim_s=60.0)
    assert ctl.relocations == 1
    assert st.done and st.success, st.reason
    assert trial.seated and trial.max_penetration_mm <= 0.5


@pytest.mark.known_issue
def test_an_easy_insertion_seats_the_card_by_both_corners():
    """Open: the truth seats the card, but the both-corners seat check (each corner loaded, a
    margin over every one-corner rival) does not pass within 45 sim s: the press churns
    between seated, corner-on-bottom and two-point readings, the corners' loads swing from one
    to the other, and the card ends against a jaw, where a card held up by that jaw fits the
    wrench as well. The verdict does not lie (not seated is said, seated is true: a miss)."""
    st, seated, pen, _phases, _ctl = _run(5.0, 1, slave_options={'seat_verdict': 'both_corners'})
    assert st.done and st.success, st.reason
    assert seated and pen <= 5e-4


def test_one_jolting_reading_counts_for_its_share_of_the_force_period():
    """Each arm command starts with a jolt of the links that the F/T sensor reads for a
    reading or two: through the graph one such reading (3.8 N, the card touching nothing
    8 mm above the floor) was identified as both corners on the floor and ended the goal
    "seated". The contact is identified on the mean of the force period's readings: one jolt
    among quiet readings weighs as that jolt spread over the period."""
    site = np.eye(4)
    site[:3, 3] = (0.9, 0.0, 0.4)
    q = [0.0, 0.6, -1.0, 0.4]
    jolt = np.array([0.4, -3.0, 3.8, 0.05, -0.1, 0.0])

    def identified(readings) -> np.ndarray:
        ctl = SlaveController(TaskModel(), [0.01, 0.3, 0.1])
        ctl.phase, ctl._tare, ctl._last_force_step = Phase.FORCE_INSERT, np.zeros(6), -1.0
        ctl._site_in_odom = lambda: site          # the site the fixes put there
        seen = []
        identify = ctl.identifier.identify
        ctl.identifier.identify = lambda w, pose: seen.append(np.array(w)) or identify(w, pose)
        for k, w in enumerate(readings):
            ctl.add_state(0.005 * k, q, [0.0] * 3, w)
        ctl.step(0.005 * (len(readings) - 1))
        return seen[0]

    n = round(0.05 / 0.005)                     # the force period's readings
    one = identified([np.zeros(6)] * (n - 1) + [jolt])
    np.testing.assert_allclose(one, identified([jolt / n] * n), atol=1e-9)
    # its push a tenth of what the jolt read in every reading would be
    full = identified([jolt] * n)
    assert np.linalg.norm(full[:2]) > 3.0
    np.testing.assert_allclose(one[:2], full[:2] / n, atol=1e-9)
