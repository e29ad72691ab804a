"""Two rovers carrying one part into a truss stage (app. A.4, Fig. A-8): decentralised master /
slave hybrid position-force control with surrogate sensing. No rclpy.

Both rovers hold one rigid segment (mass m) at a grasp point each, on the line along the
segment. Neither sees the other's force sensor: each reads its own arm-base F/T and estimates
the partner's force from the part's model (surrogate sensing),

    f_own + f_partner + f_contact = m (a - g)                      (the part's Newton equation)
    f_partner_est = m (a_ref - g) - f_own - f_contact_est,

with a_ref the part's planned acceleration, which the master sends with its reference.

- The **master** runs position control of the part: it plans the grasp line's path (lift to an
  approach height above where it believes the stage is, descend, search, seat), sends that
  reference, and follows it with its own arm. Its model of the slave is that the slave carries
  its share, 1/2 m (a_ref - g), so any force of its own beyond its share is the stage's:
  f_contact_est = 1/2 m (a_ref - g) - f_own. Contact on a wall's top (the part misaligned
  by more than the clearance) gives the side from the contact moment about the grasp line
  (r_x = -M_y / f_z), and the channel's centre is searched by bisection; contact at the floor
  with the load on both lower corners is seated (Fig. A-5's states).
- The **slave** runs hybrid control: position along the master's reference in pitch, force
  along x, y and z: an admittance moves its grasp point off the reference until its own force
  on the part is its share. Its estimate of the internal force (the part of the two forces that
  cancels) is 1/2 (f_partner_est - f_own) = 1/2 m (a_ref - g) - f_own in free space, which the
  admittance drives to zero. A master that falls silent makes it hold where it is and ramp its
  force target to the part's static share: it never follows an extrapolated plan.

Frames: the team's common frame (x forward, z up, the grasp line along y), as both rovers
share their heading and odometry. Forces are on the part, N.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from coop_common.rover_geometry import (
    ARM_MASS,
    BASE_HEIGHT_M,
    arm_gravity_moment,
    card_fk,
    card_ik,
    card_in_base,
    joint2_in_base,
)

from .errors import InsertionError
from .feedforward import ArmModel

G = 9.81
UP = np.array([0.0, 0.0, 1.0])


class SegmentPhase(Enum):
    """The master's phases of the segment insertion."""

    HOLD = 'hold'               # holding the part where it was grasped, awaiting a task
    LIFT = 'lift'               # to the approach height above the believed stage
    DESCEND = 'descend'         # down at the insertion speed until contact or the floor
    BACK_OFF = 'back_off'       # up and over after a contact on a wall's top
    SEAT = 'seat'               # at the floor: press and judge
    DONE = 'done'
    FAILED = 'failed'


@dataclass(frozen=True)
class PartModel:
    """The part as both rovers know it: mass, cross-section (x width, z height)."""

    mass_kg: float = 0.5
    width_m: float = 0.04
    height_m: float = 0.04

    def __post_init__(self) -> None:
        for name in ('mass_kg', 'width_m', 'height_m'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise InsertionError(f'part {name}: must be a positive number, got {v!r}')

    def share(self, accel: np.ndarray) -> np.ndarray:
        """Each of two equal grasps' share of the force the part needs: 1/2 m (a - g)."""
        return 0.5 * self.mass_kg * (np.asarray(accel, float) + G * UP)


@dataclass(frozen=True)
class PartReference:
    """The master's reference for the grasp line: its point on the master's grasp (common
    frame), velocity and acceleration, the part's pitch (rad about the grasp line), and the
    stamp it was made at."""

    stamp_s: float
    position: np.ndarray
    velocity: np.ndarray
    accel: np.ndarray
    pitch: float = 0.0


def force_on_part(force: np.ndarray, torque: np.ndarray, q: np.ndarray,
                  cg_to_arm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What a rover's gripper exerts on the part (force, and couple about the grasp point, base
    axes) from its arm-base F/T reading (F_12, N_12 of Eq. B-1, sensor = base axes) and its
    arm's joints, quasi-statically: the sensor carries the arm's weight and what the part
    pulls, F_12 = M_arm g_up + f, N_12 = N_arm(q) + r x f + m, with r the grasp point from the
    sensor. Slow arm motions (the insertion's) make the arm's inertial terms small."""
    f_12, n_12 = np.asarray(force, float), np.asarray(torque, float)
    if f_12.shape != (3,) or n_12.shape != (3,) or not (np.all(np.isfinite(f_12))
                                                          and np.all(np.isfinite(n_12))):
        raise InsertionError('force_on_part: need finite 3-vectors of force and torque')
    f = f_12 - ARM_MASS * G * UP
    r = card_in_base(q, cg_to_arm)[:3, 3] - np.asarray(cg_to_arm, float)
    m = n_12 - arm_gravity_moment(q) - np.cross(r, f)
    return f, m


def partner_force(model: PartModel, accel: np.ndarray, own: np.ndarray,
                  contact: np.ndarray | None = None) -> np.ndarray:
    """Surrogate sensing: the partner's force on the part from one's own and the part's
    Newton equation, f_p = m (a - g) - f_own - f_contact (contact: its estimate, or none)."""
    f = 2.0 * model.share(accel) - np.asarray(own, float)
    return f if contact is None else f - np.asarray(contact, float)


def internal_force(f_1: np.ndarray, f_2: np.ndarray) -> np.ndarray:
    """The part of two grasp forces that cancels out, 1/2 (f_1 - f_2)."""
    return 0.5 * (np.asarray(f_1, float) - np.asarray(f_2, float))


def _rz(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class RoverArm:
    """One rover's own view of its grasp, in the team's common frame: where its grasp point is
    and what it exerts on the part, from its encoders, odometry and arm-base F/T; the joints that
    put the grasp at a target; the joint torques that hold the arm and its share of the part
    (Eq. A-4's G: the arm's PD is tuned to the arm alone, and the wrist's would let the part sag
    0.15 rad). The base stands level at BASE_HEIGHT_M over the odometry frame's origin plane.
    q0: the arm's joints at the grasp (the part's pitch is counted from theirs)."""

    def __init__(self, cg_to_arm: np.ndarray, q0: np.ndarray, *, share_kg: float) -> None:
        self.r2 = np.asarray(cg_to_arm, float)
        q0 = np.asarray(q0, float)
        if self.r2.shape != (3,) or q0.shape != (4,) or not (
                np.all(np.isfinite(self.r2)) and np.all(np.isfinite(q0))):
            raise InsertionError('RoverArm: cg_to_arm (3) and q0 (4) must be finite')
        self.pitch0 = card_fk(*q0[1:4])[2]
        self.model = ArmModel.rover(self.r2, load_kg=share_kg)

    @staticmethod
    def _base(xy: np.ndarray) -> np.ndarray:
        return np.array([xy[0], xy[1], BASE_HEIGHT_M])

    def grasp(self, q: np.ndarray, xy: np.ndarray, yaw: float) -> np.ndarray:
        """The grasp point, common frame."""
        return _rz(yaw) @ card_in_base(q, self.r2)[:3, 3] + self._base(xy)

    def pitch(self, q: np.ndarray) -> float:
        """The gripper's pitch from the grasp's (rad)."""
        return card_fk(*np.asarray(q, float)[1:4])[2] - self.pitch0

    def force(self, force: np.ndarray, torque: np.ndarray, q: np.ndarray, yaw: float
              ) -> tuple[np.ndarray, np.ndarray]:
        """force_on_part in the common frame."""
        f, m = force_on_part(force, torque, q, self.r2)
        return _rz(yaw) @ f, _rz(yaw) @ m

    def joints(self, target: np.ndarray, pitch: float, xy: np.ndarray, yaw: float
               ) -> tuple[float, float, float, float]:
        """Arm joints that put the grasp at `target` (common frame) with the part at `pitch`
        from the grasp's (ReachError out of reach)."""
        p = _rz(yaw).T @ (np.asarray(target, float) - self._base(xy))
        local = p - joint2_in_base(self.r2)
        heading = math.atan2(local[1], local[0])
        return (heading, *card_ik(math.hypot(local[0], local[1]), float(local[2]),
                                  self.pitch0 + pitch))

    def gravity(self, q: np.ndarray) -> np.ndarray:
        """The joint torques that hold the arm and its share of the part at q (N m)."""
        return self.model.gravity(q)


class _Lowpass:
    """First-order low-pass of a vector (time constant tau, s) at irregular stamps."""

    def __init__(self, tau_s: float) -> None:
        self.tau = tau_s
        self.value: np.ndarray | None = None
        self.t = -math.inf

    def update(self, t: float, x: np.ndarray) -> np.ndarray:
        if self.value is None or t <= self.t:
            self.value = np.array(x, float)
        else:
            a = 1.0 - math.exp(-(t - self.t) / self.tau)
            self.value = self.value + a * (np.asarray(x, float) - self.value)
        self.t = t
        return self.value


@dataclass(frozen=True)
class MasterSettings:
    """The master's plan and thresholds (SI units)."""

    approach_above_m: float = 0.03     # the part's bottom above the believed mouth to start
    lift_speed_m_s: float = 0.04
    insert_speed_m_s: float = 0.01
    touch_n: float = 2.0               # the contact estimate's z that stops a descent
    touch_pitch_rad: float = 0.008     # or the part's pitch off level
    seat_n: float = 3.0                # the press at the floor that ends the insertion
    search_halfwidth_m: float = 0.03   # the channel's centre within the prior +- this
    clearance_m: float = 0.004         # the channel's width less the part's, as designed
    back_off_m: float = 0.004          # up after a wall-top contact before moving over
    search_step_fraction: float = 0.5  # the search's step, of the clearance (< 1: no gaps)
    timeout_s: float = 150.0
    filter_tau_s: float = 0.05
    seat_timeout_s: float = 4.0        # at the floor and not seated for this long: failed
    level_rad: float = 0.02            # the part's pitch a seated part is within
    floor_tolerance_m: float = 0.01    # its bottom within this of the believed floor
    tracking_gain_1_s: float = 3.0     # the integral that takes out the arm's sag
    max_tracking_m: float = 0.03


@dataclass
class MasterStatus:
    """The master's phase, its tries at the channel, why it ended, its contact estimate."""

    phase: SegmentPhase
    tries: int
    reason: str = ''
    contact_estimate: np.ndarray = field(default_factory=lambda: np.zeros(3))


class SegmentMaster:
    """The master: position control of the part (module docstring). `step` takes the own
    grasp point (common frame, from the arm's encoders), the own force and couple on the part
    (force_on_part, rotated to the common frame) and returns the reference to follow and send.
    stage_x, stage_top_z: where it believes the channel's centre and mouth are (common frame),
    e.g. from its map; the truth may differ by the search half-width. hold: start in HOLD,
    holding the part level where it is (its integrals running) until `begin`; else the task
    begins at t0."""

    def __init__(self, model: PartModel, *, grasp: np.ndarray, stage_x: float,
                 stage_top_z: float, stage_depth_m: float, t0: float,
                 settings: MasterSettings | None = None, hold: bool = False) -> None:
        self.model = model
        self.s = settings or MasterSettings()
        self.depth = float(stage_depth_m)
        self.top = float(stage_top_z)
        self.prior_x = float(stage_x)
        self.target_x = float(stage_x)
        self.pos = np.asarray(grasp, float).copy()
        self.vel = np.zeros(3)
        self.phase = SegmentPhase.LIFT
        self.t0 = self.t = t0
        self.tries = 0
        self.reason = ''
        self._force = _Lowpass(self.s.filter_tau_s)
        self._couple = _Lowpass(self.s.filter_tau_s)
        self._bias: tuple[np.ndarray, np.ndarray] | None = None
        self._wait_until = -math.inf
        self._back_off_z = self.approach_z
        #: the grasp line's height at the first wall contact: later tries come down fast to
        #: just above it
        self._wall_z: float | None = None
        self.contact = np.zeros(3)
        #: what the master adds to its reference for its own arm: the integral of the
        #: reference less its grasp as its encoders see it (the arm sags under the part)
        self.tracking = np.zeros(3)
        self.pitch_tracking = 0.0
        self._own_pitch = 0.0
        self.last_touch: tuple[float, float, float] | None = None
        if hold:
            self.phase = SegmentPhase.HOLD

    def begin(self, t: float, *, stage_x: float | None = None,
              stage_top_z: float | None = None, timeout_s: float | None = None) -> None:
        """Start the task from where the part is held (a new belief of the stage, if given)."""
        if stage_x is not None:
            self.prior_x = self.target_x = float(stage_x)
        if stage_top_z is not None:
            self.top = float(stage_top_z)
        if timeout_s is not None:
            self.s = dataclasses.replace(self.s, timeout_s=float(timeout_s))
        self.phase, self.t0, self.tries, self.reason = SegmentPhase.LIFT, t, 0, ''
        self._bias, self._wait_until, self._wall_z = None, -math.inf, None
        self.contact, self.last_touch = np.zeros(3), None

    def hold(self) -> None:
        """Back to HOLD where the part is (after a task ended, or to stop one)."""
        self.phase = SegmentPhase.HOLD
        self.vel = np.zeros(3)

    @property
    def command(self) -> np.ndarray:
        """Where the master's own arm is sent: the reference plus the tracking integral."""
        return self.pos + self.tracking

    @property
    def command_pitch(self) -> float:
        """The pitch the master's own arm is sent to (the reference's is 0: level)."""
        return self.pitch_tracking

    @property
    def approach_z(self) -> float:
        """The grasp line's height with the part's bottom approach_above_m over the mouth."""
        return self.top + self.s.approach_above_m + self.model.height_m / 2

    def _move_towards(self, goal: np.ndarray, speed: float, dt: float) -> bool:
        d = goal - self.pos
        n = float(np.linalg.norm(d))
        step = speed * dt
        if n <= step:
            self.vel = d / dt if dt > 0 else np.zeros(3)
            self.pos = goal.copy()
            return True
        self.vel = d / n * speed
        self.pos = self.pos + self.vel * dt
        return False

    def step(self, t: float, own_grasp: np.ndarray, own_force: np.ndarray,
             own_couple: np.ndarray, own_pitch: float = 0.0) -> PartReference:
        """One control step: the reference for the grasp line. own_pitch: the gripper's pitch
        from its encoders, from where it was at the grasp (rad)."""
        dt = max(0.0, t - self.t)
        self.t = t
        f = self._force.update(t, own_force)
        m = self._couple.update(t, own_couple)
        s = self.s
        self._own_pitch = float(own_pitch)
        # the tracking integral: along x and y always, along z only in free motion (a
        # contact stops the part, and the integral would press through it)
        err = self.pos - np.asarray(own_grasp, float)
        if self.phase not in (SegmentPhase.HOLD, SegmentPhase.LIFT, SegmentPhase.BACK_OFF):
            err[2] = 0.0
        if self.phase not in (SegmentPhase.DONE, SegmentPhase.FAILED, SegmentPhase.SEAT):
            self.tracking = np.clip(self.tracking + s.tracking_gain_1_s * err * dt,
                                    -s.max_tracking_m, s.max_tracking_m)
        # and the part kept level in free motion: the wrist's PD is tuned to the arm alone (in
        # contact the integral would wind up against what holds the part)
        free = self.phase in (SegmentPhase.HOLD, SegmentPhase.LIFT) or (
            self.phase is SegmentPhase.DESCEND and self.contact[2] < 0.5 * s.touch_n
            and abs(self._own_pitch) < 0.5 * s.touch_pitch_rad)
        if free:
            self.pitch_tracking = float(np.clip(
                self.pitch_tracking - s.tracking_gain_1_s * float(own_pitch) * dt, -0.3, 0.3))
        share = self.model.share(np.zeros(3))
        if self.phase in (SegmentPhase.HOLD, SegmentPhase.DONE, SegmentPhase.FAILED):
            self.vel = np.zeros(3)
            return self._ref(t)
        if t - self.t0 > s.timeout_s:
            return self._fail(t, f'not seated after {s.timeout_s:.0f} s ({self.phase.value})')
        if self.phase is SegmentPhase.LIFT:
            goal = np.array([self.target_x, self.pos[1], self.approach_z])
            if self._move_towards(goal, s.lift_speed_m_s, dt) and t >= self._wait_until:
                if self._wait_until == -math.inf:
                    self._wait_until = t + 0.5       # settle, then the free-space bias
                else:
                    self._bias = (f.copy(), m.copy())
                    self._wait_until = -math.inf
                    self.phase = SegmentPhase.DESCEND
            return self._ref(t)
        bias_f, bias_m = self._bias if self._bias is not None else (share, np.zeros(3))
        # what the stage pushes on the part, as the master sees it: its own force beyond the
        # free-space share it carried at the approach (the slave carries the rest)
        self.contact = -(f - bias_f)
        couple = -(m - bias_m)
        bottom = float(own_grasp[2]) - self.model.height_m / 2
        if self.phase is SegmentPhase.DESCEND:
            floor = self.top - self.depth
            # a contact stops the part or turns it about the corner that meets something (the
            # wrist gives first: its turn shows before the force has built up)
            if self.contact[2] > s.touch_n or abs(self._own_pitch) > s.touch_pitch_rad:
                self.vel = np.zeros(3)
                #: what stopped the last descent: the contact's push (N) and the pitch (rad)
                self.last_touch = (float(self.contact[2]), self._own_pitch, bottom)
                if bottom < floor + 0.5 * self.depth:
                    self.phase = SegmentPhase.SEAT
                    self._wait_until = t + 0.3
                    return self._ref(t)
                return self._wall_contact(t, float(own_grasp[0]), couple)
            goal = np.array([self.pos[0], self.pos[1], floor - 0.02 + self.model.height_m / 2])
            fast = self._wall_z is not None and self.pos[2] > self._wall_z + 0.002
            if self._move_towards(goal, s.insert_speed_m_s * (3.0 if fast else 1.0), dt):
                return self._fail(t, 'reached 2 cm below the believed floor without contact')
            return self._ref(t)
        if self.phase is SegmentPhase.BACK_OFF:
            goal = np.array([self.pos[0], self.pos[1], self._back_off_z])
            if self._move_towards(goal, s.insert_speed_m_s * 2, dt):
                over = np.array([self.target_x, self.pos[1], self._back_off_z])
                if self._move_towards(over, s.insert_speed_m_s, dt):
                    self.phase = SegmentPhase.DESCEND
            return self._ref(t)
        if self.phase is SegmentPhase.SEAT:
            floor = self.top - self.depth
            self.vel = np.zeros(3)
            # press down a little more each step until the seat force is reached
            if self.contact[2] < s.seat_n:
                self.pos = self.pos - UP * s.insert_speed_m_s * 0.5 * dt
            # seated: pressed at the floor's depth with the part level. Its level is held by the
            # wrist's integral against the encoders, so a part on one corner (against a wall,
            # or on the mouth's edge) shows as a pitch the integral cannot take out
            level = abs(self._own_pitch) <= s.level_rad
            at_floor = abs(bottom - floor) <= s.floor_tolerance_m
            if t >= self._wait_until and self.contact[2] >= s.seat_n and level and at_floor:
                self.phase = SegmentPhase.DONE
                self.reason = 'seated'
            elif t >= self._wait_until + s.seat_timeout_s:
                return self._fail(t, f'pressed {self.contact[2]:.1f} N at '
                                     f'{(bottom - floor) * 1e3:+.1f} mm from the floor, pitch '
                                     f'{self._own_pitch:+.3f} rad: not seated')
            return self._ref(t)
        raise InsertionError(f'unknown phase {self.phase}')

    def _wall_contact(self, t: float, x_now: float, couple: np.ndarray) -> PartReference:
        """A contact above the floor: the part is on a wall's top or against the mouth's edge,
        off the channel by more than half the clearance. Which side is not observable from
        the master's own sensors here: the wrist's turn under the vertical reaction dwarfs
        the corner's moment (0.22 against 0.04 N m at 2 N), and the contact moment about the
        grasp line is shared with the slave's wrist. So the search steps out from the belief
        by the clearance each way in turn (0, +c, -c, +2c, ...), which covers every place
        the channel can be to within it, up to the search half-width."""
        del x_now, couple
        self.tries += 1
        k = (self.tries + 1) // 2
        offset = k * self.s.search_step_fraction * self.s.clearance_m * (
            1 if self.tries % 2 else -1)
        if self._wall_z is None:
            self._wall_z = float(self.pos[2])
        if abs(offset) > self.s.search_halfwidth_m:
            return self._fail(t, f'no way in after {self.tries - 1} tries (searched '
                                 f'+-{self.s.search_halfwidth_m * 1e3:.0f} mm)')
        self.target_x = self.prior_x + offset
        self._back_off_z = self.pos[2] + self.s.back_off_m
        self.phase = SegmentPhase.BACK_OFF
        return self._ref(t)

    def _fail(self, t: float, reason: str) -> PartReference:
        self.phase = SegmentPhase.FAILED
        self.reason = reason
        self.vel = np.zeros(3)
        return self._ref(t)

    def _ref(self, t: float) -> PartReference:
        return PartReference(t, self.pos.copy(), self.vel.copy(), np.zeros(3), 0.0)

    @property
    def status(self) -> MasterStatus:
        return MasterStatus(self.phase, self.tries, self.reason, self.contact.copy())


@dataclass(frozen=True)
class SlaveSettings:
    """The slave's admittance and silence handling (SI units)."""

    admittance_m_s_per_n: float = 0.004    # grasp-point speed per N of force error
    max_speed_m_s: float = 0.05
    max_offset_m: float = 0.05             # how far off the reference the admittance may go
    silence_s: float = 0.3                 # no reference for this long: the master is silent
    filter_tau_s: float = 0.03
    pitch_gain_1_s: float = 3.0            # the integral that holds the pitch reference


class SegmentSlave:
    """The slave: hybrid position-force control of its grasp (module docstring). `step` takes
    the latest reference received (or None), its own force on the part (common frame), and
    returns its grasp point's target (common frame) and pitch."""

    def __init__(self, model: PartModel, *, grasp: np.ndarray,
                 master_grasp: np.ndarray | None = None, t0: float,
                 settings: SlaveSettings | None = None) -> None:
        """grasp, master_grasp: the two grasp points when the part was taken (common frame):
        the slave's grasp rides the reference at that offset. Without master_grasp, the first
        reference's position is taken as it (the master sends its grasp first)."""
        self.model = model
        self.s = settings or SlaveSettings()
        self.offset: np.ndarray | None = (
            None if master_grasp is None
            else np.asarray(grasp, float) - np.asarray(master_grasp, float))
        self.hold = np.asarray(grasp, float).copy()
        self.delta = np.zeros(3)
        self.t = t0
        self.last_ref: PartReference | None = None
        self.silent_since: float | None = None
        self._force = _Lowpass(self.s.filter_tau_s)
        self.partner_estimate = model.share(np.zeros(3))
        self.internal_estimate = np.zeros(3)
        self.target = self.hold.copy()
        self.pitch = 0.0
        self.pitch_tracking = 0.0

    @property
    def silent(self) -> bool:
        return self.silent_since is not None

    def step(self, t: float, reference: PartReference | None, own_force: np.ndarray,
             own_pitch: float = 0.0) -> tuple[np.ndarray, float]:
        """own_pitch: the gripper's pitch from its encoders, from the grasp's (rad). Returns
        the grasp point's target and the pitch to command (the reference's, with the
        integral that holds it against the wrist's sag)."""
        dt = max(0.0, t - self.t)
        self.t = t
        f = self._force.update(t, own_force)
        if reference is not None:
            self.last_ref = reference
        ref = self.last_ref
        fresh = ref is not None and t - ref.stamp_s <= self.s.silence_s
        if fresh:
            assert ref is not None
            if self.offset is None:
                self.offset = self.hold - ref.position
            self.silent_since = None
            accel = ref.accel
            base = ref.position + self.offset
            self.pitch = ref.pitch
            target_f = self.model.share(accel)
        else:
            # silent (or not started): hold where the grasp is, the force target the part's
            # static share: the speed-limited admittance releases what the last plan put in
            if self.silent_since is None:
                self.silent_since = t
                self.hold = self.target.copy()
                self.delta = np.zeros(3)
            accel = np.zeros(3)
            base = self.hold
            target_f = self.model.share(accel)
        self.partner_estimate = partner_force(self.model, accel, f)
        self.internal_estimate = internal_force(self.partner_estimate, f)
        err = f - target_f
        speed = np.clip(-self.s.admittance_m_s_per_n * err, -self.s.max_speed_m_s,
                        self.s.max_speed_m_s)
        self.delta = np.clip(self.delta + speed * dt, -self.s.max_offset_m, self.s.max_offset_m)
        self.target = base + self.delta
        self.pitch_tracking = float(np.clip(
            self.pitch_tracking + self.s.pitch_gain_1_s * (self.pitch - own_pitch) * dt,
            -0.3, 0.3))
        return self.target.copy(), self.pitch + self.pitch_tracking
