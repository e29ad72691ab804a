"""The slave's side of the cooperative insertion (Sujan 2002, §5.1, §5.3, app. A.4), no rclpy.

`SlaveController` runs at the slave's servo rate (its joint-state rate) and turns what the slave
knows into arm-joint and base-velocity commands through three phases:

1. READY: the arm brings the card to its carry pose (level, `carry_reach_m` ahead of arm joint 2,
   `carry_height_m` above it) and the F/T reading settles.
2. VISUAL_SERVO: each master fix (the four labelled markers, task.label_markers) becomes the
   card's required motion in the base frame (Eq. 5-1..5-4, task.card_required_motion) to the
   pre-insertion pose, the card's lower edge `standoff_m` above the mouth; servo.VisualServo
   fuses the fixes with odometry and arm kinematics, and splits the motion between the base
   (to keep the goal within the arm's reach) and the arm. The arm's card target integrates the
   servo's card velocity (an integral loop on the encoders' card pose: the arm's sag under load
   is taken out). Once the error is below the goal's tolerances for `settle_s`, the card
   descends at `descent_speed_m_s` along the site's vertical while vision keeps correcting
   across the slot; it holds whenever vision is older than the servo's timeout (never into
   contact blind). The F/T is tared when the descent starts.
3. FORCE_INSERT: when the tared force exceeds `contact_threshold_n`, every `force_period_s` the
   card's pose in the site frame (from the fused vision goal, odometry and encoders) and the
   tared F/T wrench in the task frame go to contact.ContactIdentifier, and
   contact.LeastResistance's bounded step moves the card's target (the base stands still). The
   tare is taken when the descent starts; what the arm's own weight changes at the sensor as
   its links move after that (rover_geometry.arm_gravity_moment) is taken out too. When the
   floor pushes back, the card's depth is the floor's (floor_correction): the estimate's
   lowest corner is put on it. On one corner, the card turns about it towards the other
   (by the contact's side when the estimate disagrees); both corners on the floor by the
   wrench (SEATED), pressed to `seat_force_n`, each corner carrying load and every one-corner
   rival (a corner on the floor, the card held up by a jaw) a margin worse on the mean wrench
   of the last force period (ContactIdentifier.seat_check) in SEAT_CONFIRMATIONS periods
   in a row, end it with success
   (card_seated); SEATED by the fit but not by that check, the planner probes (turns the
   lighter corner down, presses harder) until it is; a force above
   `abort_force_factor` x `max_force_n` in ABORT_SAMPLES consecutive readings ends it with
   failure, as does the caller's timeout.

A failure (a timeout, a cancel, an error) once the card is descending or in contact backs off:
the card's target rises `backoff_m` along the vertical and stays there, so that no force is
left on the card and nothing pushes on (the master silent mid-insertion: vision holds the
descent, the timeout ends it, the card lifts).

Frames: base = `<slave>/base_link` (c.g., x forward, z up); odom = `<slave>/odom` (wheel
odometry, planar); the F/T sensor frame is the base frame's axes at r_2 (rover_sim's
`<slave>/ft_sensor_link`). The site frame is task.py's; contact.py's planar frame is its
(x, z) plane: planar y = site z, planar z = -site y.
"""
from __future__ import annotations

import dataclasses
import enum
import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from coop_common.params import choice
from coop_common.rover_geometry import (
    BASE_HEIGHT_M,
    ReachError,
    arm_gravity_moment,
    card_in_base,
    card_joints,
    joint2_in_base,
)

from .contact import (
    CardPose,
    ContactIdentifier,
    ContactState,
    Identification,
    LeastResistance,
    SeatCheck,
    planar_step_in_frame,
    planar_wrench,
    task_wrench,
)
from .drive import GoToPose
from .errors import InsertionError
from .frames import homogeneous, invert
from .servo import VisionFix, VisualServo
from .task import LabelledMarkers, TaskModel, card_required_motion

__all__ = ['Phase', 'SlaveCommand', 'SlaveController', 'SlaveStatus', 'pose_2d']

#: the site frame's axes as contact.py's planar frame sees them (columns: planar x, y, z in site)
SITE_FROM_PLANAR = homogeneous(np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]),
                               np.zeros(3))


class Phase(enum.IntEnum):
    """The phases, numbered as coop_msgs/action/Insert's feedback (READY is before them)."""

    PLACE_CAMERA = 0
    VISUAL_SERVO = 1
    FORCE_INSERT = 2
    DONE = 3
    READY = 10


def pose_2d(x: float, y: float, yaw: float, z: float = BASE_HEIGHT_M) -> np.ndarray:
    """4x4 of the base's pose from planar odometry: the c.g. at height z over the ground
    (the odometry frame's origin is on the ground)."""
    c, s = math.cos(yaw), math.sin(yaw)
    return homogeneous(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), [x, y, z])


@dataclass(frozen=True)
class SlaveStatus:
    """The slave controller's state after a step (the insert action's feedback)."""

    phase: Phase
    displacement_error_m: float        # card to its current goal (vision), nan before a fix
    angle_error_rad: float
    wrench: np.ndarray                 # tared F/T reading (sensor frame, 6)
    contact_state: str                 # contact.ContactState value in FORCE_INSERT, else ''
    done: bool
    success: bool
    reason: str
    descending: bool = False
    card_in_site: tuple[float, float, float] | None = None   # planar (x, y, theta) estimate
    awaiting_fix: bool = False         # VISUAL_SERVO, no fix yet, the coarse approach done
    #                                    (or no fix since a relocation ended)
    relocating: bool = False           # VISUAL_SERVO: the base drives the card to a goal aside


@dataclass(frozen=True)
class SlaveCommand:
    """What the slave controller commands for one step: arm joints, base twist, and its status."""

    arm_joints: tuple[float, float, float, float] | None     # None: leave the arm as it is
    base_linear_x: float
    base_angular_z: float
    status: SlaveStatus


@dataclass
class _State:
    t: float
    q: np.ndarray
    odom: np.ndarray
    wrench: np.ndarray


@dataclass
class _Target:
    position: np.ndarray         # card centre, base frame
    pitch: float


#: the contact force must exceed the abort limit in this many consecutive F/T readings
ABORT_SAMPLES = 3
#: the seat check must pass in this many consecutive force periods (each period's wrench has
#: its own noise: a check a card on one corner passes by chance once in a few hundred periods
#: would, over a long press, pass it once)
SEAT_CONFIRMATIONS = 3
#: the floor felt corrects the site frame's depth only when the pose estimate puts the card's
#: lowest corner within this of the floor (never a jaw's mouth, a slot depth away)
FLOOR_GATE_M = 0.008


def floor_correction(ident: Identification, pose: CardPose, *, slot_depth_m: float,
                     card_width_m: float, min_force_n: float, gate_m: float = FLOOR_GATE_M
                     ) -> float:
    """How far to move the card pose's depth estimate (planar y, m) so that its lowest corner
    lies on the slot's floor, when the floor pushes back by more than min_force_n
    (Identification.floor_force_n); 0 otherwise. The floor is where the card stands: its depth
    is then measured by touch, not by the millimetre-off pose that vision, odometry and
    encoders make."""
    if ident.floor_force_n <= min_force_n:
        return 0.0
    lowest = pose.y - card_width_m / 2 * abs(math.sin(pose.theta))
    dy = -slot_depth_m - lowest
    return dy if abs(dy) <= gate_m else 0.0


class SeatVerdict(enum.StrEnum):
    """What ends the force-feedback insertion with "seated" (card_seated)."""

    #: the fit's SEATED, the floor's summed push at seat_force_n, the estimate deep enough:
    #: it inserts, and it is fooled by a card landing on one corner (the other unloaded) and by
    #: one whose other corner a jaw holds up (docs/results/insertion.md)
    FLOOR_FORCE = 'floor_force'
    #: that and the seat check (each corner loaded, every one-corner rival a margin worse) in
    #: SEAT_CONFIRMATIONS force periods in a row, the planner probing until it passes: no false
    #: seat measured, and most cards the truth has seated never pass it in time
    BOTH_CORNERS = 'both_corners'
    #: the floor's push with each corner carrying the identifier's seat_corner_force_n in the
    #: seated fit, in SEAT_CONFIRMATIONS force periods in a row (no rival margin): a card
    #: landing on one corner is not passed on its first period's sum, the planner probing (the
    #: lighter corner turned down) until both carry; a jaw's friction holding the other corner
    #: up still reads as its load; through the graph the fit's state churns period by period
    #: and two of four attempts timed out with the truth seated (docs/results/insertion.md)
    CORNER_LOADS = 'corner_loads'


def card_seated(state: ContactState, depth_m: float, tilt_rad: float, *, floor_force_n: float,
                seat_force_n: float, slot_depth_m: float, card_width_m: float,
                seat: SeatCheck | None,
                verdict: SeatVerdict = SeatVerdict.BOTH_CORNERS,
                corner_force_n: float = 1.0) -> bool:
    """Whether the force-feedback insertion is done: the wrench says both of the card's corners
    are on the floor (SEATED), the floor pushes back by at least seat_force_n, and, by the
    BOTH_CORNERS verdict, the seat check passed (ContactIdentifier.seat_check: each corner
    carries load, every one-corner rival fits the wrench a margin worse; None, not checked, is
    not seated), by CORNER_LOADS each corner carrying `corner_force_n` in the seated fit. The
    floor's sum alone passed a card on one corner whose other corner a jaw's friction held up:
    through the graph 3.4 N, 29.9 mm deep and 0.1 deg from flat by the estimate, and not seated
    by the truth. The pose estimate only has to agree that the higher corner is within 4 mm of
    the floor (half the card's width x sin(tilt) above the edge's centre); alone it decides
    nothing: it put a free card 30.3 mm in, a wedged one 30.8 mm, and through the graph a card
    on one corner, 0.3 deg from flat, where the truth had it tilted by more than the 1.06 deg
    its 2 mm allow."""
    depth_high = depth_m - card_width_m / 2 * math.sin(abs(tilt_rad))
    checked = (verdict is SeatVerdict.FLOOR_FORCE or
               (verdict is SeatVerdict.CORNER_LOADS and seat is not None and
                min(seat.corner_forces_n) >= corner_force_n) or
               (verdict is SeatVerdict.BOTH_CORNERS and seat is not None and seat.passed))
    return (state is ContactState.SEATED and floor_force_n >= seat_force_n and checked and
            depth_high >= slot_depth_m - 0.004)


class SlaveController:
    """The slave's insertion loop (see the module notes). Options (keyword-only):
    tolerance_m, angle_tolerance_rad (the vision phase's goal before descent: displacement and
    the card's tilt in the insertion plane), yaw_tolerance_rad (the whole rotation), settle_s,
    standoff_m override (else the model's), descent_speed_m_s, contact_threshold_n, max_force_n
    (the least-resistance force limit), abort_force_factor, force_period_s, carry_reach_m,
    carry_height_m, ready_s, servo (a VisualServo; default one with arm_home at the carry
    pose), identifier / planner options through `contact_options` / `step_options`,
    approach_speed_m_s, seat_force_n (the floor's push on both corners that ends it),
    seat_verdict (SeatVerdict: what that push must show besides)."""

    def __init__(self, model: TaskModel, cg_to_arm: ArrayLike, *, tolerance_m: float = 0.003,
                 angle_tolerance_rad: float = 0.03, yaw_tolerance_rad: float = 0.15,
                 settle_s: float = 1.0,
                 descent_speed_m_s: float = 0.005, contact_threshold_n: float = 1.5,
                 max_force_n: float = 25.0, abort_force_factor: float = 1.5,
                 force_period_s: float = 0.05, carry_reach_m: float = 0.30,
                 carry_height_m: float = 0.0, ready_s: float = 2.0,
                 servo: VisualServo | None = None, contact_options: dict | None = None,
                 step_options: dict | None = None, site_in_odom: ArrayLike | None = None,
                 approach_speed_m_s: float = 0.1, seat_force_n: float = 3.0,
                 seat_verdict: SeatVerdict | str = SeatVerdict.FLOOR_FORCE,
                 backoff_m: float = 0.02, relocate_beyond_m: float = 0.10,
                 max_relocations: int = 2) -> None:
        if not isinstance(model, TaskModel):
            raise InsertionError('model must be a TaskModel')
        self.model = model
        self.r2 = np.asarray(cg_to_arm, float)
        if self.r2.shape != (3,) or not np.all(np.isfinite(self.r2)):
            raise InsertionError('cg_to_arm must be a finite 3-vector')
        for name, v in (('tolerance_m', tolerance_m), ('angle_tolerance_rad',
                        angle_tolerance_rad), ('descent_speed_m_s', descent_speed_m_s),
                        ('contact_threshold_n', contact_threshold_n),
                        ('max_force_n', max_force_n), ('force_period_s', force_period_s),
                        ('carry_reach_m', carry_reach_m), ('ready_s', ready_s),
                        ('backoff_m', backoff_m), ('relocate_beyond_m', relocate_beyond_m)):
            if not (math.isfinite(v) and v > 0):
                raise InsertionError(f'{name} must be finite and > 0, got {v}')
        if not abort_force_factor >= 1:
            raise InsertionError('abort_force_factor must be >= 1')
        self.tolerance_m = float(tolerance_m)
        self.angle_tolerance_rad = float(angle_tolerance_rad)
        self.yaw_tolerance_rad = float(yaw_tolerance_rad)
        self.settle_s = float(settle_s)
        self.descent_speed = float(descent_speed_m_s)
        self.contact_threshold_n = float(contact_threshold_n)
        self.max_force_n = float(max_force_n)
        self.abort_force_n = float(abort_force_factor * max_force_n)
        self.force_period_s = float(force_period_s)
        self.carry = joint2_in_base(self.r2) + np.array([carry_reach_m, 0.0, carry_height_m])
        self.ready_s = float(ready_s)
        self.backoff_m = float(backoff_m)
        self.relocate_beyond_m = float(relocate_beyond_m)
        if not (isinstance(max_relocations, int) and max_relocations >= 0):
            raise InsertionError('max_relocations must be an integer >= 0')
        self.max_relocations = max_relocations
        self.site_in_odom = None if site_in_odom is None else np.asarray(site_in_odom, float)
        if self.site_in_odom is not None and (self.site_in_odom.shape != (4, 4) or not
                                              np.all(np.isfinite(self.site_in_odom))):
            raise InsertionError('site_in_odom must be a finite 4x4 pose')
        self.approach_speed = float(approach_speed_m_s)
        if not 0 < seat_force_n < max_force_n:
            raise InsertionError('seat_force_n must be in (0, max_force_n)')
        self.seat_force_n = float(seat_force_n)
        self.seat_verdict = choice(SeatVerdict, seat_verdict, 'seat_verdict',
                                   error=InsertionError)
        self.servo = servo if servo is not None else VisualServo(
            arm_home_m=tuple(self.carry), max_arm_speed_m_s=0.04, base_deadband_m=0.04)
        geo = model.geometry
        self.identifier = ContactIdentifier(geo, **(contact_options or {}))
        self.planner = LeastResistance(geo, force_limit_n=max_force_n,
                                       seat_force_n=seat_force_n, **(step_options or {}))
        self.reset()

    # -- lifecycle ----------------------------------------------------------------------------
    def reset(self) -> None:
        self.servo.reset()
        self.phase = Phase.READY
        self._state: _State | None = None
        self._start_t: float | None = None
        self._target: _Target | None = None
        self._last_t: float | None = None     # the last visual-servo step's time
        self._settled_since: float | None = None
        self._descending = False
        self._descent_start: float | None = None
        self._tare: np.ndarray | None = None
        self._tare_moment = np.zeros(3)     # the arm's weight's moment at the tare
        self._recent: deque[tuple[float, np.ndarray]] = deque()
        self._last_force_step = -math.inf
        self._done = False
        self._success = False
        self._reason = ''
        self._contact_state = ''
        self._errors = (math.nan, math.nan)
        self._awaiting_fix = False
        self._card_in_site: tuple[float, float, float] | None = None
        self._floor_offset_m = 0.0      # the site's depth as the floor was felt (planar y)
        self.peak_force_n = 0.0
        self.last_seat: SeatCheck | None = None   # the last force step's seat check (SEATED)
        self._seat_passes = 0                     # consecutive force periods it passed
        self._hold_joints: tuple | None = None    # after a failure in contact: backed off
        self._relocation: GoToPose | None = None  # the base on its way to a far fix's goal
        self._relocated_t = -math.inf             # when the last relocation ended
        self.relocations = 0

    # -- inputs -------------------------------------------------------------------------------
    def add_state(self, t: float, q: ArrayLike, odom_xy_yaw: Sequence[float], wrench: ArrayLike
                  ) -> None:
        """Servo-rate sensing: arm joints (4, rad), odometry (x, y, yaw) and the F/T reading
        (force, torque in the sensor frame)."""
        qa = np.asarray(q, float)
        w = np.asarray(wrench, float)
        o = np.asarray(odom_xy_yaw, float)
        if qa.shape != (4,) or w.shape != (6,) or o.shape != (3,) or not (
                np.all(np.isfinite(qa)) and np.all(np.isfinite(w)) and np.all(np.isfinite(o))
                and math.isfinite(t)):
            raise InsertionError('state: finite q (4), odometry (3) and wrench (6) needed')
        odom = pose_2d(*o)
        self._state = _State(float(t), qa, odom, w)
        self.servo.add_odometry(t, odom, self._card_marker_in_base(qa))
        self._recent.append((float(t), w))
        while self._recent and self._recent[0][0] < t - 0.25:
            self._recent.popleft()
        if self._start_t is None:
            self._start_t = float(t)

    def add_observation(self, stamp: float, obs: LabelledMarkers) -> None:
        """A master fix: the four labelled markers at the image's stamp."""
        if self._state is None or self.phase is Phase.READY or self._done:
            return
        q_at = self._state.q      # the arm moves slowly: kinematics now, odometry at the stamp
        m = card_required_motion(obs, self._card_marker_in_base(q_at), self.model,
                                 above_m=self.model.standoff_m)
        cov = m.covariance_s + np.diag([1e-8] * 3 + [1e-6] * 3)
        self.servo.add_vision(VisionFix(stamp, m.translation_s, m.rotvec_s, cov))

    def _card_marker_in_base(self, q: np.ndarray) -> np.ndarray:
        return card_in_base(q, self.r2) @ self.model.card_marker_frame

    # -- output -------------------------------------------------------------------------------
    def step(self, t: float) -> SlaveCommand:
        """The command for servo time t (after add_state)."""
        s = self._state
        if s is None:
            raise InsertionError('step before the first state')
        if self._done:
            return self._command(self._hold_joints, 0.0, 0.0)
        if self._target is None:
            self._target = _Target(self.carry.copy(), 0.0)
        if self.phase is Phase.READY:
            assert self._start_t is not None         # the first state set it
            if t - self._start_t >= self.ready_s:
                self.phase = Phase.VISUAL_SERVO
            return self._command(self._joints(), 0.0, 0.0)
        if self.phase is Phase.VISUAL_SERVO:
            return self._visual(t, s)
        return self._force(t, s)

    def fail(self, reason: str) -> None:
        """End the insertion as a failure (a timeout, a cancel): hold, or once the card
        descends or touches, back off (the card's target backoff_m higher: the joints in
        `hold_joints`)."""
        if self._done:
            return
        if (self._descending or self.phase is Phase.FORCE_INSERT) and \
                self._target is not None:
            before = self._target.position.copy()
            try:
                self._hold_joints = self._move_target(
                    np.array([0.0, 0.0, self.backoff_m]), 0.0)
            except ReachError:
                self._hold_joints = None
            rose = float(self._target.position[2] - before[2])
            reason += (f' (backed off {1e3 * rose:.0f} mm)' if rose > 0 else
                       ' (could not back off: the raised card is out of reach)')
        self._done, self._success, self._reason = True, False, reason
        self.phase = Phase.DONE

    @property
    def hold_joints(self) -> tuple | None:
        """The arm's joints once ended: backed off after a failure in contact, else None
        (the arm stays where it is)."""
        return self._hold_joints

    def _finish(self, success: bool, reason: str) -> None:
        self._done, self._success, self._reason = True, success, reason
        self.phase = Phase.DONE

    def _joints(self) -> tuple[float, float, float, float]:
        tg = self._target
        assert tg is not None                       # the first step sets it
        j2 = joint2_in_base(self.r2)
        heading = math.atan2(tg.position[1] - j2[1], tg.position[0] - j2[0])
        return card_joints(tg.position, heading, tg.pitch, self.r2)

    def _plane_normal(self) -> np.ndarray:
        """The arm plane's normal (base frame): the axis the card's pitch turns about."""
        tg = self._target
        assert tg is not None
        j2 = joint2_in_base(self.r2)
        heading = math.atan2(tg.position[1] - j2[1], tg.position[0] - j2[0])
        return np.array([-math.sin(heading), math.cos(heading), 0.0])

    def _tared(self, w: np.ndarray) -> np.ndarray:
        """The F/T reading less the tare and less what the arm's own weight has changed in it
        since the tare (its links moved: 0.1-0.2 N m at the sensor after a 30 mm descent, which
        the contact identification read as a couple, a wedge)."""
        if self._tare is None:
            return np.zeros(6)
        assert self._state is not None              # a tare is taken from a state
        moved = arm_gravity_moment(self._state.q) - self._tare_moment
        return w - self._tare - np.concatenate([np.zeros(3), moved])

    def _status(self) -> SlaveStatus:
        w = self._tared(self._state.wrench) if self._state is not None else np.zeros(6)
        return SlaveStatus(self.phase, self._errors[0], self._errors[1], w,
                           self._contact_state, self._done, self._success, self._reason,
                           self._descending, self._card_in_site, self._awaiting_fix,
                           self._relocation is not None)

    def _command(self, joints: tuple[float, float, float, float] | None, v: float, w: float
                 ) -> SlaveCommand:
        return SlaveCommand(joints, float(v), float(w), self._status())

    def _move_target(self, dp: np.ndarray, dpitch: float) -> tuple | None:
        """Move the arm's card target, undoing the move when the arm cannot reach it."""
        tg = self._target
        assert tg is not None
        old = (tg.position.copy(), tg.pitch)
        tg.position = tg.position + dp
        tg.pitch += dpitch
        try:
            return self._joints()
        except ReachError:
            tg.position, tg.pitch = old
            return self._joints()

    def _approach(self, s: _State) -> SlaveCommand:
        """Before the first fix: the base brings the card towards the pre-insertion pose the
        map puts it at (site_in_odom, odometry), so that it enters the master's view; it
        stops within approach_tolerance of it and waits for vision."""
        m = self.model
        goal = self.site_in_odom @ m.card_goal(m.standoff_m)
        card = s.odom @ card_in_base(s.q, self.r2)
        e = s.odom[:3, :3].T @ (goal[:3, 3] - card[:3, 3])     # base frame
        self._errors = (float(np.linalg.norm(e)), math.nan)
        # the arm takes the card to the pre-insertion height on the way (20 mm/s)
        dz = float(np.clip(e[2], -0.02 / 200.0, 0.02 / 200.0))
        joints = self._move_target(np.array([0.0, 0.0, dz]), 0.0)
        self._awaiting_fix = bool(abs(e[0]) < 0.02 and abs(e[1]) < 0.05)
        if self._awaiting_fix:
            return self._command(joints, 0.0, 0.0)
        v = float(np.clip(1.0 * e[0], -self.approach_speed, self.approach_speed))
        w = float(np.clip(0.8 * math.atan2(e[1], max(abs(e[0]), 0.3)), -0.3, 0.3))
        return self._command(joints, v, w)

    def _relocate(self, t: float, s: _State) -> SlaveCommand | None:
        """A fix whose goal lies more than relocate_beyond_m to the side of the card (the two
        rovers' odometry frames disagree: the card stood where the slave's map put the site,
        out of the master's view, until the master panned to it), or turned about the
        vertical by more than yaw_tolerance_rad (the base came in at an angle): the servo
        closes distance ahead with the base and the rest with the arm, but a skid-steer base
        cannot move sideways and the 4-DOF arm cannot turn the card about the vertical. The
        arm back at its carry pose, the base drives (turn, drive, turn) to the pose that puts
        the card at the goal, on odometry, at most max_relocations times; the servo is for
        what is left. The command while the base is on its way, else None."""
        goal = self.servo.goal
        if self._relocation is None:
            if goal is None or self._descending or self.relocations >= self.max_relocations:
                return None
            card = s.odom @ self._card_marker_in_base(s.q)
            e = s.odom[:3, :3].T @ (goal[:3, 3] - card[:3, 3])      # base frame
            r = goal[:3, :3] @ card[:3, :3].T
            yaw = math.atan2(r[1, 0], r[0, 0])          # the card's turn about the vertical
            if abs(float(e[1])) <= self.relocate_beyond_m and \
                    abs(yaw) <= self.yaw_tolerance_rad:
                return None
            self._errors = (float(np.linalg.norm(e)), abs(yaw))
            self._target = _Target(self.carry.copy(), 0.0)
            base = goal @ invert(self._card_marker_in_base(np.asarray(self._joints())))
            self._relocation = GoToPose(base[:2, 3], math.atan2(base[1, 0], base[0, 0]),
                                        max_speed_m_s=self.approach_speed)
            self.relocations += 1
        c = self._relocation.command(s.odom[0, 3], s.odom[1, 3],
                                     math.atan2(s.odom[1, 0], s.odom[0, 0]))
        self._last_t = t            # the servo's next step integrates from here, not before
        self._awaiting_fix = False
        if c.arrived:
            self._relocation = None
            self._relocated_t = t
            return None
        return self._command(self._joints(), c.linear_x, c.angular_z)

    def _visual(self, t: float, s: _State) -> SlaveCommand:
        if self.servo.goal is None and self.site_in_odom is not None:
            return self._approach(s)
        relocating = self._relocate(t, s)
        if relocating is not None:
            return relocating
        # guided by the fixes; before the first with no map to approach by, it holds there,
        # as it does after a relocation until a fix from where the card now is
        self._awaiting_fix = self.servo.goal is None or \
            self.servo.newest_fix_stamp < self._relocated_t
        cmd = self.servo.command(t)
        self._errors = (cmd.displacement_error_m, cmd.angle_error_rad) \
            if math.isfinite(cmd.vision_age_s) else (math.nan, math.nan)
        # the period since the last step, held or not: a hold's steps count (integrating the
        # arm's velocity over a whole hold at the first step after it would jump the card)
        dt = 1.0 / 200.0 if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        if cmd.held:
            return self._command(self._joints(), 0.0, 0.0)
        arm_v = cmd.arm_linear.copy()
        if not self._descending:
            # the arm turns the card about its plane's normal only (4 DOF): the rest of the
            # rotation (yaw from the base's heading) is tolerated up to yaw_tolerance_rad
            tilt = abs(float(cmd.error_rotvec @ self._plane_normal()))
            ok = (cmd.displacement_error_m <= self.tolerance_m and
                  tilt <= self.angle_tolerance_rad and
                  float(np.linalg.norm(cmd.error_rotvec)) <= self.yaw_tolerance_rad)
            if not ok:
                self._settled_since = None
            elif self._settled_since is None:
                self._settled_since = t
            elif t - self._settled_since >= self.settle_s:
                self._descending = True
                self._descent_start = t
                self._tare = np.mean([w for _, w in self._recent], axis=0)
                self._tare_moment = arm_gravity_moment(s.q)
        if self._descending:
            arm_v[2] = -self.descent_speed
            tared = self._tared(s.wrench)
            force = float(np.linalg.norm(tared[:3]))
            recent = self._tared(np.mean([w for _, w in list(self._recent)[-4:]], axis=0))
            if float(np.linalg.norm(recent[:3])) > self.contact_threshold_n:
                self.phase = Phase.FORCE_INSERT
                self._contact_since = t
                return self._command(self._joints(), 0.0, 0.0)
            self.peak_force_n = max(self.peak_force_n, force)
        # only the card's pitch (about the arm plane's normal) is the arm's to turn
        joints = self._move_target(arm_v * dt, float(cmd.arm_angular @ self._plane_normal()) * dt)
        base_v = 0.0 if self._descending else cmd.base_linear_x
        base_w = 0.0 if self._descending else cmd.base_angular_z
        return self._command(joints, base_v, base_w)

    # -- force feedback -----------------------------------------------------------------------
    def _site_in_odom(self) -> np.ndarray:
        goal = self.servo.goal          # the card-marker frame's pre-insertion goal, odom
        m = self.model
        return goal @ invert(m.card_goal(m.standoff_m) @ m.card_marker_frame)

    def _seat_ok(self, seat: SeatCheck) -> bool:
        """One force period's seat check as the verdict reads it."""
        if self.seat_verdict is SeatVerdict.CORNER_LOADS:
            return min(seat.corner_forces_n) >= self.identifier.seat_corner_force_n
        return seat.passed

    def _force(self, t: float, s: _State) -> SlaveCommand:
        tared = self._tared(s.wrench)
        force = float(np.linalg.norm(tared[:3]))
        self.peak_force_n = max(self.peak_force_n, force)
        # abort on a force sustained over the last ABORT_SAMPLES readings, not on one reading:
        # a stiff contact's impact rings for a single physics step
        last = [float(np.linalg.norm(self._tared(w)[:3]))
                for _, w in list(self._recent)[-ABORT_SAMPLES:]]
        if len(last) == ABORT_SAMPLES and min(last) > self.abort_force_n:
            self.fail(f'contact force {min(last):.1f} N above the abort limit '
                      f'{self.abort_force_n:.1f} N for {ABORT_SAMPLES} readings')
            return self._command(self._hold_joints, 0.0, 0.0)
        if t - self._last_force_step < self.force_period_s - 1e-9:
            return self._command(self._joints(), 0.0, 0.0)
        self._last_force_step = t
        site_odom = self._site_in_odom()
        base_in_planar = invert(SITE_FROM_PLANAR) @ invert(site_odom) @ s.odom
        card = base_in_planar @ card_in_base(s.q, self.r2)
        m = self.model
        lead = card[:3, 3] - card[:3, 2] * (m.card_height_m / 2)
        theta = math.atan2(card[1, 0], card[0, 0])
        pose = CardPose(float(lead[0]), float(lead[1]) + self._floor_offset_m, theta)
        sensor = base_in_planar.copy()
        sensor[:3, 3] = base_in_planar[:3, :3] @ self.r2 + base_in_planar[:3, 3]
        w = planar_wrench([task_wrench(self._tared(s.wrench), sensor)])
        # the contact is identified (and the seat checked) on the mean of the last force
        # period's readings: one reading holds the jolt of the arm's links as each new arm
        # command starts (a straight move done in 20 ms: the joints are up to speed within a
        # physics step), which the sensor reads as a push; through the graph one such reading
        # (3.8 N, the card touching nothing 8 mm above the floor) was taken for a seated
        # card, floor_correction having moved the depth estimate onto the floor on the one
        # before. Over a period a completed move's momentum change averages out, and the
        # torque's noise too (a few times the identifier's moment noise over one reading)
        period = [r for tr, r in self._recent if tr > t - self.force_period_s] or [s.wrench]
        w_mean = planar_wrench([task_wrench(self._tared(np.mean(period, axis=0)), sensor)])
        ident = self.identifier.identify(w_mean, pose)
        dy = floor_correction(ident, pose, slot_depth_m=m.slot_depth_m,
                              card_width_m=m.card_width_m, min_force_n=self.contact_threshold_n)
        if dy:
            self._floor_offset_m += dy
            pose = CardPose(pose.x, pose.y + dy, pose.theta)
            ident = self.identifier.identify(w_mean, pose)
        if ident.state is ContactState.SEATED:
            ident = dataclasses.replace(ident, seat=self.identifier.seat_check(w_mean, pose))
        self.last_seat = ident.seat
        self._seat_passes = self._seat_passes + 1 if ident.seat and self._seat_ok(ident.seat) \
            else 0
        self._card_in_site = (pose.x, pose.y, pose.theta)
        self._contact_state = ident.state.value
        # seated: both corners on the floor by the wrench, pressed to seat_force_n
        depth = -pose.y
        both = self.seat_verdict is SeatVerdict.BOTH_CORNERS
        confirmed = self.seat_verdict is SeatVerdict.FLOOR_FORCE or \
            self._seat_passes >= SEAT_CONFIRMATIONS
        if card_seated(ident.state, depth, pose.theta, floor_force_n=ident.floor_force_n,
                       seat_force_n=self.seat_force_n, slot_depth_m=m.slot_depth_m,
                       card_width_m=m.card_width_m, seat=ident.seat,
                       verdict=self.seat_verdict,
                       corner_force_n=self.identifier.seat_corner_force_n) and confirmed:
            c = ident.seat
            check = (f'{c.corner_forces_n[0]:.1f} + {c.corner_forces_n[1]:.1f} N, '
                     f'{c.margin:.0f} chi^2 over {c.rival}' if c is not None else '')
            loads = check if both else (f'{ident.floor_force_n:.1f} N' + (
                f' (seat check {"passed" if c.passed else "failed"}: {check})' if c else ''))
            self._finish(True, f'seated ({self.seat_verdict.value}): both corners on the '
                               f'floor at {loads}, '
                               f'card edge {depth * 1e3:.1f} mm '
                               f'into the slot by the estimate, '
                               f'tilt {math.degrees(abs(pose.theta)):.1f} deg, peak force '
                               f'{self.peak_force_n:.1f} N')
            return self._command(self._joints(), 0.0, 0.0)
        step = self.planner.step(ident, w, pose)
        planar_in_base = invert(base_in_planar)
        d_lead, rotvec = planar_step_in_frame(step, pose, planar_in_base)
        centre = card_in_base(s.q, self.r2)[:3, 3]
        lead_b = planar_in_base[:3, :3] @ lead + planar_in_base[:3, 3]
        dp = d_lead + np.cross(rotvec, centre - lead_b)
        joints = self._move_target(dp, float(rotvec @ self._plane_normal()))
        return self._command(joints, 0.0, 0.0)

