"""Nodes `segment_master` and `segment_slave`: two rovers carry one segment into a truss stage
(thesis app. A.4, Fig. A-8), each on its own sensors, talking only through the master's
reference (coop_insertion.segment holds the control; these nodes convert and wire).

Both run in the team's namespace for the rover named by `rover` (they may run on different
computers: all they share is `<master>/segment/reference` over DDS). Each reads its own
`<rover>/joint_states`, `<rover>/odom` and `<rover>/arm/wrench`, and commands
`<rover>/arm/joint_command` and `<rover>/arm/feedforward` (the gravity of its arm and its share
of the part, Eq. A-4's G) at `command_rate_hz`, from its first joint state on: it holds the
part from the start.

- `segment_master`: action `<rover>/insert_segment` (coop_msgs/action/InsertSegment): position
  control of the part (segment.SegmentMaster); its reference on `<rover>/segment/reference`
  (coop_msgs/PartReference) at the command rate, also while idle (its grasp, held).
- `segment_slave`: hybrid position-force control on `<partner>/segment/reference`
  (segment.SegmentSlave): rides it, yields to its force to carry its share, holds where it is
  when the reference stops for `silence_s`; its surrogate estimate of the partner's force on
  `<rover>/segment/estimate` (coop_msgs/PartEstimate).

The team's common frame is each rover's odometry frame (rover_sim starts odometry at the true
pose on the map; two rovers on hardware share it by the team's localisation).
"""
from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import Vector3, WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.lockstep_node import Lockstep
from coop_common.node_util import (
    BadInputCounter,
    declare_parameters,
    finite_wrench,
    planar_pose,
    run_node,
    stamp,
)
from coop_common.params import ParamSpec
from coop_common.qos import COMMAND_QOS, SENSOR_QOS, with_depth
from coop_common.rover_geometry import ARM_JOINTS, NOMINAL_CG_TO_ARM, ReachError
from coop_msgs.action import InsertSegment
from coop_msgs.msg import PartEstimate, PartReference

from .errors import InsertionError
from .segment import (
    MasterSettings,
    PartModel,
    RoverArm,
    SegmentMaster,
    SegmentPhase,
    SegmentSlave,
    SlaveSettings,
)
from .segment import PartReference as Reference

COMMON = {
    'lockstep': ParamSpec(False, "Answer rover_sim's lockstep rounds (a participant in its "
                          'lockstep_participants), so the outcome does not depend on load',
                          read_only=True),
    'cg_to_arm': ParamSpec(list(NOMINAL_CG_TO_ARM), "r_2, the arm mount from the base c.g. (m) "
                           "(the default: the design's nominal mount)", read_only=True),
    'part_mass_kg': ParamSpec(0.5, "The part's mass as this rover knows it (kg)", lo=0.01,
                              hi=3.0, read_only=True),
    'command_rate_hz': ParamSpec(100.0, 'Arm command rate (Hz)', lo=10.0, hi=200.0,
                                 read_only=True),
}
MASTER_PARAMS = {
    'rover': ParamSpec('rover1', 'The master rover (its topics are <rover>/...)',
                       read_only=True),
    **COMMON,
    'stage_x': ParamSpec(-1.56, "The stage channel's centre along x in the common frame (m), "
                         "when the goal gives none: where the rover thinks it is (the default: "
                         "rover_sim's segment scenario's stage, from the rovers' start)",
                         lo=-100.0, hi=100.0),
    'stage_top_z': ParamSpec(0.28, "The stage's mouth height (m), when the goal gives none",
                             lo=0.05, hi=1.0),
    'stage_depth_m': ParamSpec(0.05, "The channel's depth (m)", lo=0.005, hi=0.2),
    'clearance_m': ParamSpec(0.004, "The channel's width less the part's, as designed (m)",
                             lo=0.0005, hi=0.05),
    'search_halfwidth_m': ParamSpec(0.03, "How far from its belief the master looks for the "
                                    "channel's centre (m)", lo=0.0, hi=0.2),
    'timeout_s': ParamSpec(90.0, 'Task timeout when the goal gives none (sim s)', lo=1.0,
                           hi=3600.0),
}
SLAVE_PARAMS = {
    'rover': ParamSpec('rover2', 'The slave rover (its topics are <rover>/...)',
                       read_only=True),
    'partner': ParamSpec('rover1', 'The master rover whose <partner>/segment/reference this one '
                         'follows', read_only=True),
    **COMMON,
    'silence_s': ParamSpec(0.3, 'No reference for this long (sim s): the master is silent, and '
                           'the slave holds and lets the part settle on its share', lo=0.02,
                           hi=10.0, read_only=True),
    'admittance_m_s_per_n': ParamSpec(0.004, "The grasp's speed per N of force off its share "
                                      '(m/s/N)', lo=1e-5, hi=0.05, read_only=True),
}


def _stamp_s(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


def _vec(v) -> Vector3:
    return Vector3(x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _check_r2(p: dict) -> str | None:
    v = p['cg_to_arm']
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        return 'cg_to_arm must be three finite numbers'
    return None


class _CarryingRover(Node):
    """What both rovers do: read their own sensors, hold the part (gravity compensation from
    the first joint state), command their arm. `_control(t, q)` is each one's law."""

    def __init__(self, name: str, params: dict, **kwargs) -> None:
        super().__init__(name, **kwargs)
        self.p = declare_parameters(self, params, check_all=_check_r2)
        self.bad = BadInputCounter(self)
        self.r = self.p['rover']
        self.model = PartModel(mass_kg=self.p['part_mass_kg'])
        self.odom: tuple[np.ndarray, float] | None = None
        self.wrench: np.ndarray | None = None
        self.arm: RoverArm | None = None
        self._last_cmd = -math.inf
        self.ls = Lockstep(self, self.p['lockstep'])

    def _sensors(self) -> None:
        """The own sensors; in lockstep a round's odometry and wrench come before its joint
        state, which steps the law (the order of these subscriptions)."""
        r = self.r
        self.ls.subscription(Odometry, f'{r}/odom', self._on_odom, SENSOR_QOS)
        self.ls.subscription(WrenchStamped, f'{r}/arm/wrench', self._on_wrench,
                             with_depth(SENSOR_QOS, 50))
        self.ls.subscription(JointState, f'{r}/joint_states', self._on_joints,
                             with_depth(SENSOR_QOS, 50))
        self.pub_arm = self.ls.publisher(JointTrajectory, f'{r}/arm/joint_command', COMMAND_QOS)
        self.pub_ff = self.ls.publisher(JointState, f'{r}/arm/feedforward', COMMAND_QOS)

    def _on_odom(self, msg: Odometry) -> None:
        x, y, yaw = planar_pose(msg.pose.pose)
        self.odom = (np.array([x, y]), yaw)

    def _on_wrench(self, msg: WrenchStamped) -> None:
        if (w := finite_wrench(msg, self.bad)) is not None:
            self.wrench = w

    def _on_joints(self, msg: JointState) -> None:
        if self.odom is None or self.wrench is None:
            return
        idx = {n: i for i, n in enumerate(msg.name)}
        if not all(n in idx for n in ARM_JOINTS) or len(msg.position) != len(msg.name):
            self.bad.reject('joint_states', 'arm joints missing')
            return
        q = np.array([msg.position[idx[n]] for n in ARM_JOINTS])
        if not np.all(np.isfinite(q)):
            self.bad.reject('joint_states', 'non-finite arm joints')
            return
        t = _stamp_s(msg)
        if self.arm is None:
            self.arm = RoverArm(np.asarray(self.p['cg_to_arm'], float), q,
                                share_kg=0.5 * self.model.mass_kg)
            self.get_logger().info(f'{self.r} holds the part: r_2 '
                                   f'{np.round(self.arm.r2, 4).tolist()}, share '
                                   f'{0.5 * self.model.mass_kg:.3f} kg')
        if t < self._last_cmd or t - self._last_cmd >= 1.0 / self.p['command_rate_hz'] - 1e-6:
            self._last_cmd = t
            try:
                self._control(t, q)
            except (InsertionError, ReachError) as exc:
                self.bad.reject('control', str(exc))

    def _command(self, t: float, q: np.ndarray, target: np.ndarray, pitch: float) -> None:
        assert self.arm is not None and self.odom is not None
        joints = self.arm.joints(target, pitch, *self.odom)
        tr = JointTrajectory(joint_names=list(ARM_JOINTS))
        pt = JointTrajectoryPoint(positions=[float(v) for v in joints])
        pt.time_from_start.nanosec = int(2e9 / self.p['command_rate_hz'])
        tr.points = [pt]
        self.pub_arm.publish(tr)
        ff = JointState(name=list(ARM_JOINTS),
                        effort=[float(v) for v in self.arm.gravity(q)])
        ff.header.stamp = stamp(t)
        self.pub_ff.publish(ff)

    def _own(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Own grasp point, force and couple on the part (common frame)."""
        assert self.arm is not None and self.odom is not None and self.wrench is not None
        f, m = self.arm.force(self.wrench[:3], self.wrench[3:], q, self.odom[1])
        return self.arm.grasp(q, *self.odom), f, m

    def _control(self, t: float, q: np.ndarray) -> None:
        raise NotImplementedError


class SegmentMasterNode(_CarryingRover):
    """The master: position control of the part, an action (module docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('segment_master', MASTER_PARAMS, **kwargs)
        r = self.r
        self._sensors()
        self.pub_ref = self.ls.publisher(PartReference, f'{r}/segment/reference', COMMAND_QOS)
        self.ctl: SegmentMaster | None = None
        self._goal: InsertSegment.Goal | None = None
        self._t_goal: float | None = None
        self._timeout = 0.0
        self._wake: Future | None = None
        self._busy = False
        self._done_t = 0.0
        self.create_timer(0.2, self._wakeup, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._server = ActionServer(self, InsertSegment, f'{r}/insert_segment',
                                    execute_callback=self._execute, goal_callback=self._on_goal,
                                    cancel_callback=lambda _g: CancelResponse.ACCEPT)
        self.get_logger().info(f'segment master ready: {r}, action {r}/insert_segment')

    def _control(self, t: float, q: np.ndarray) -> None:
        grasp, f, m = self._own(q)
        assert self.arm is not None
        p = self.p
        if self.ctl is None:
            # from the first state on: the part held level where it was grasped
            self.ctl = SegmentMaster(
                self.model, grasp=grasp, stage_x=p['stage_x'], stage_top_z=p['stage_top_z'],
                stage_depth_m=p['stage_depth_m'], t0=t, hold=True,
                settings=MasterSettings(clearance_m=p['clearance_m'],
                                        search_halfwidth_m=p['search_halfwidth_m'],
                                        timeout_s=p['timeout_s']))
        ctl = self.ctl
        if self._goal is not None and self._t_goal is None:
            g = self._goal
            stage_x = g.stage_x if math.isfinite(g.stage_x) else p['stage_x']
            top = g.stage_top_z if math.isfinite(g.stage_top_z) else p['stage_top_z']
            ctl.begin(t, stage_x=stage_x, stage_top_z=top, timeout_s=g.timeout_s or p['timeout_s'])
            self._t_goal = t
            self.get_logger().info(f'inserting the segment: stage believed at x {stage_x:.4f}, '
                                   f'mouth {top:.4f} m')
        tries = ctl.tries
        ref = ctl.step(t, grasp, f, m, self.arm.pitch(q))
        if ctl.tries != tries and ctl.last_touch is not None:
            push, pitch_at, bottom = ctl.last_touch
            self.get_logger().info(
                f'touch {ctl.tries} at x {grasp[0]:.4f}: push {push:.2f} N, pitch '
                f'{pitch_at:+.4f} rad, bottom {bottom:.4f} m; next x {ctl.target_x:.4f}')
        if self._t_goal is not None and ctl.phase in (SegmentPhase.DONE, SegmentPhase.FAILED):
            self._done_t = t
            self._wakeup()
        self._command(t, q, ctl.command, ctl.command_pitch)
        msg = PartReference(phase=ctl.phase.value, pitch=float(ref.pitch))
        msg.header.stamp, msg.header.frame_id = stamp(t), 'map'
        msg.position.x, msg.position.y, msg.position.z = (float(v) for v in ref.position)
        msg.velocity, msg.acceleration = _vec(ref.velocity), _vec(ref.accel)
        self.pub_ref.publish(msg)

    # -- the action ---------------------------------------------------------------------------
    def _wakeup(self) -> None:
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)

    def _on_goal(self, goal: InsertSegment.Goal) -> GoalResponse:
        if self._busy:
            self.get_logger().warn('insert_segment: a goal is running; rejected')
            return GoalResponse.REJECT
        if not (math.isfinite(goal.timeout_s) and goal.timeout_s >= 0):
            return GoalResponse.REJECT
        if math.isinf(goal.stage_x) or math.isinf(goal.stage_top_z):
            return GoalResponse.REJECT
        self._busy = True
        return GoalResponse.ACCEPT

    async def _execute(self, handle) -> InsertSegment.Result:
        self._goal, self._t_goal = handle.request, None
        last_fb = -math.inf
        try:
            while True:
                self._wake = Future()
                await self._wake
                ctl = self.ctl
                if ctl is None or self._t_goal is None:
                    continue
                if handle.is_cancel_requested:
                    ctl.hold()
                    handle.canceled()
                    return self._result(False, 'canceled', ctl)
                if time.monotonic() - last_fb > 0.2:
                    last_fb = time.monotonic()
                    handle.publish_feedback(InsertSegment.Feedback(
                        phase=ctl.phase.value, tries=ctl.tries,
                        contact_force=_vec(ctl.contact)))
                if ctl.phase in (SegmentPhase.DONE, SegmentPhase.FAILED):
                    ok = ctl.phase is SegmentPhase.DONE
                    (handle.succeed if ok else handle.abort)()
                    self.get_logger().info(f'segment insertion {"done" if ok else "failed"}: '
                                           f'{ctl.reason}')
                    result = self._result(ok, ctl.reason, ctl)
                    ctl.hold()
                    return result
        finally:
            self._goal, self._t_goal, self._busy = None, None, False

    def _result(self, ok: bool, reason: str, ctl: SegmentMaster | None
                ) -> InsertSegment.Result:
        dur = (self._done_t - self._t_goal) if self._t_goal is not None else 0.0
        return InsertSegment.Result(success=bool(ok), reason=reason,
                                    tries=int(ctl.tries) if ctl is not None else 0,
                                    duration_s=float(dur))


class SegmentSlaveNode(_CarryingRover):
    """The slave: hybrid position-force control on the master's reference (module
    docstring)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('segment_slave', SLAVE_PARAMS, **kwargs)
        r = self.r
        # the partner's reference first: in lockstep a round's reference is handed out before
        # the joint state that steps the law
        self.ls.subscription(PartReference, f'{self.p["partner"]}/segment/reference',
                             self._on_reference, with_depth(SENSOR_QOS, 20))
        self._sensors()
        # (what it reports closes no loop on the simulator: not a lockstep publisher, which
        # would wait for a reader)
        self.pub_est = self.create_publisher(PartEstimate, f'{r}/segment/estimate', SENSOR_QOS)
        self.ctl: SegmentSlave | None = None
        self._ref: Reference | None = None
        self._was_silent = True
        self.get_logger().info(f'segment slave ready: {r} follows '
                               f'{self.p["partner"]}/segment/reference')

    def _on_reference(self, msg: PartReference) -> None:
        v = [msg.position.x, msg.position.y, msg.position.z, msg.velocity.x, msg.velocity.y,
             msg.velocity.z, msg.acceleration.x, msg.acceleration.y, msg.acceleration.z,
             msg.pitch]
        if not all(math.isfinite(x) for x in v):
            self.bad.reject('reference', 'non-finite')
            return
        self._ref = Reference(_stamp_s(msg), np.array(v[0:3]), np.array(v[3:6]),
                              np.array(v[6:9]), float(v[9]))

    def _control(self, t: float, q: np.ndarray) -> None:
        grasp, f, _ = self._own(q)
        assert self.arm is not None
        if self.ctl is None:
            self.ctl = SegmentSlave(self.model, grasp=grasp, t0=t, settings=SlaveSettings(
                silence_s=self.p['silence_s'],
                admittance_m_s_per_n=self.p['admittance_m_s_per_n']))
        ref, self._ref = self._ref, None
        target, pitch = self.ctl.step(t, ref, f, self.arm.pitch(q))
        if self.ctl.silent != self._was_silent:
            self._was_silent = self.ctl.silent
            # (rclpy wants one severity per call site)
            if self.ctl.silent:
                self.get_logger().warn(f'{self.p["partner"]} is silent: holding')
            else:
                self.get_logger().info(f'{self.p["partner"]} is heard')
        self._command(t, q, target, pitch)
        est = PartEstimate(own_force=_vec(f), partner_force=_vec(self.ctl.partner_estimate),
                           internal_force=_vec(self.ctl.internal_estimate),
                           partner_silent=bool(self.ctl.silent))
        est.header.stamp, est.header.frame_id = stamp(t), 'map'
        self.pub_est.publish(est)


def main_master(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion segment_master`."""
    return run_node(SegmentMasterNode, args)


def main_slave(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion segment_slave`."""
    return run_node(SegmentSlaveNode, args)
