"""Node `slave`: the rover that carries the card and inserts it (thesis ch. 5, app. A.4).

Runs in the team's namespace for the rover named by `rover`. Action `<rover>/insert_card`
(coop_msgs/action/Insert; the master's `insert` action sends it once the camera is placed):
the arm brings the card to its carry pose, then coop_insertion.slave.SlaveController closes the
vision error from the master's `<master>/markers` at the servo rate (`<rover>/joint_states`,
with `<rover>/odom` and `<rover>/arm/wrench`), descends, and on contact finishes by force
feedback; it commands `<rover>/arm/joint_command` and `<rover>/cmd_vel`. The arm's mount r_2
comes from the identifier's `<rover>/dynamic_parameters` when it has published, else from the
`cg_to_arm` parameter. The site the coarse approach heads for is the goal's `site` (the master
located it from the slot's markers), else the `site_position` and `site_yaw` parameters.
"""
from __future__ import annotations

import math
import time
from enum import StrEnum

import numpy as np
from geometry_msgs.msg import Twist, WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.frames import FRAME_PARAMS, check_prefix
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
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS, with_depth
from coop_common.rover_geometry import ARM_JOINTS, NOMINAL_CG_TO_ARM, ReachError, yaw_of
from coop_msgs.action import Insert
from coop_msgs.msg import DynamicParameters, MarkerObservation

from .errors import InsertionError
from .slave import Phase, SeatVerdict, SlaveController
from .task import LABELS, LabelledMarkers, TaskModel

PARAMS = {
    'rover': ParamSpec('rover2', 'The slave rover (its topics are <rover>/...)',
                       read_only=True),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'master': ParamSpec('rover1', 'The master rover whose <master>/markers guide the card '
                        '(a goal naming another is rejected)', read_only=True),
    'lockstep': ParamSpec(False, "Answer rover_sim's lockstep rounds (a participant in its "
                          'lockstep_participants): the sensors of each round, then the '
                          'commands, so the outcome does not depend on load', read_only=True),
    'slot_width_m': ParamSpec(0.1143, "The slot's width (the task's given; Table 5-1: 5.0, "
                              '4.5, 4.375 in)', lo=0.1080, hi=0.25),
    'site_position': ParamSpec([3.0572, 0.0, 0.4], "The slot mouth's centre in the map frame "
                               '(m), for the coarse approach; the map frame is taken as the '
                               'odometry frame (rover_sim starts odometry at the true pose)'),
    'site_yaw': ParamSpec(0.0, "The site frame's heading in the map (rad): its x across the "
                          'slot', lo=-math.pi, hi=math.pi),
    'cg_to_arm': ParamSpec(list(NOMINAL_CG_TO_ARM), 'r_2, the arm mount from the base c.g. (m), '
                           "until the identifier publishes it (the default: the design's "
                           'nominal mount; set it to a calibration of the rover at hand)'),
    'tolerance_m': ParamSpec(0.003, 'Vision error to reach before descending, when the goal '
                             'gives none (m)', lo=1e-4, hi=0.1),
    'angle_tolerance_rad': ParamSpec(0.03, 'Card tilt error before descending, when the goal '
                                     'gives none (rad)', lo=1e-4, hi=1.0),
    'max_force_n': ParamSpec(25.0, 'Contact force limit, when the goal gives none (N)',
                             lo=1.0, hi=200.0),
    'timeout_s': ParamSpec(120.0, 'Task timeout when the goal gives none (sim s)', lo=1.0,
                           hi=3600.0),
    'descent_speed_m_s': ParamSpec(0.005, 'Speed of the vision-guided descent (m/s)',
                                   lo=0.001, hi=0.1),
    'contact_threshold_n': ParamSpec(1.5, 'Tared force that means contact (N)', lo=0.1,
                                     hi=50.0),
    'seat_verdict': ParamSpec(SeatVerdict.FLOOR_FORCE.value, "What ends the press with "
                              "seated: 'floor_force' (the fit's SEATED and the floor's push), "
                              "'corner_loads' (and each corner loaded, three force periods in "
                              "a row), 'both_corners' (each corner loaded and every one-corner "
                              'rival a margin worse): slave.SeatVerdict',
                              choices=[v.value for v in SeatVerdict]),
    'command_rate_hz': ParamSpec(100.0, 'Arm and base command rate (Hz)', lo=1.0, hi=200.0),
}


def _site_pose(position, yaw: float) -> np.ndarray:
    t = np.eye(4)
    c, s = math.cos(yaw), math.sin(yaw)
    t[:3, :3] = [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]
    t[:3, 3] = position
    return t


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


class R2Source(StrEnum):
    """Where the slave's r2 (the arm's offset from the rover's CG) comes from: the
    `cg_to_arm` parameter, until the identifier has published an observable CG."""

    PARAMETER = 'parameter'
    IDENTIFIED = 'identified'


class SlaveNode(Node):
    """The slave: carries the card and runs the insertion loop (vision, then force), an action."""

    def __init__(self, **kwargs) -> None:
        super().__init__('slave', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params,
                                    check_all=self._check)
        self.bad = BadInputCounter(self)
        r = self.p['rover']
        self.r2 = np.asarray(self.p['cg_to_arm'], float)
        self.r2_source = R2Source.PARAMETER
        # the team's map frame (frame_prefix: team_a/map), of the site it takes
        self.map_frame = self.p['frame_prefix'] + 'map'
        self.odom: tuple[float, float, float] | None = None
        self.wrench: np.ndarray | None = None
        self.ctl: SlaveController | None = None
        self._goal_t0: float | None = None
        self._timeout = 0.0
        self._last_cmd = -math.inf
        self._wake: Future | None = None
        self._busy = False
        self._status_t = 0.0           # stamp of the joint state the last status is of
        self._descended_t: float | None = None      # ... the first in the descent, or contact
        # the goal's stamp: its task starts with the first joint state after it (in lockstep
        # the goal can arrive before or after the round it was sent in is handed out here;
        # states and fixes up to its stamp are left out either way)
        self._given_t = -math.inf
        self._started = False
        # in lockstep a round's odometry, wrench and markers come before its joint state,
        # which steps the controller (the order of these subscriptions)
        self.ls = Lockstep(self, self.p['lockstep'])
        self.ls.subscription(Odometry, f'{r}/odom', self._on_odom, SENSOR_QOS)
        self.ls.subscription(WrenchStamped, f'{r}/arm/wrench', self._on_wrench,
                             with_depth(SENSOR_QOS, 50))
        self.ls.subscription(MarkerObservation, f'{self.p["master"]}/markers', self._on_markers,
                             SENSOR_QOS)
        self.ls.subscription(JointState, f'{r}/joint_states', self._on_joints,
                             with_depth(SENSOR_QOS, 50))
        self.create_subscription(DynamicParameters, f'{r}/dynamic_parameters', self._on_params_id,
                                 LATCHED_QOS)
        self.pub_arm = self.ls.publisher(JointTrajectory, f'{r}/arm/joint_command', COMMAND_QOS)
        self.pub_cmd = self.ls.publisher(Twist, f'{r}/cmd_vel', COMMAND_QOS)
        self.create_timer(0.2, self._wakeup, clock=Clock(clock_type=ClockType.STEADY_TIME))
        ActionServer(self, Insert, f'{r}/insert_card', execute_callback=self._execute,
                     goal_callback=self._on_goal,
                     cancel_callback=lambda _g: CancelResponse.ACCEPT)
        self.get_logger().info(f'slave ready: {r} carries the card, action {r}/insert_card')

    @staticmethod
    def _check(p: dict) -> str | None:
        if (bad := check_prefix(p['frame_prefix'])) is not None:
            return bad
        for name in ('cg_to_arm', 'site_position'):
            v = p[name]
            if len(v) != 3 or not all(math.isfinite(x) for x in v):
                return f'{name} must be three finite numbers'
        return None

    def _on_params(self, changed: dict) -> None:
        self.p.update(changed)
        if 'cg_to_arm' in changed and self.r2_source is R2Source.PARAMETER:
            self.r2 = np.asarray(changed['cg_to_arm'], float)

    def _on_params_id(self, msg: DynamicParameters) -> None:
        v = dict(zip(msg.names, msg.values, strict=False))
        obs = dict(zip(msg.names, msg.observable, strict=False)) \
            if len(msg.observable) == len(msg.names) else {}
        if all(k in v and obs.get(k, True) and math.isfinite(v[k])
               for k in ('cg_x', 'cg_y', 'cg_z')):
            self.r2 = np.array([v['cg_x'], v['cg_y'], v['cg_z']])
            self.r2_source = R2Source.IDENTIFIED

    # -- sensing ------------------------------------------------------------------------------
    def _on_odom(self, msg: Odometry) -> None:
        self.odom = planar_pose(msg.pose.pose)

    def _on_wrench(self, msg: WrenchStamped) -> None:
        if (w := finite_wrench(msg, self.bad)) is not None:
            self.wrench = w

    def _on_markers(self, msg: MarkerObservation) -> None:
        if self.ctl is None or not self._started:
            return
        n = len(msg.positions)
        if list(msg.labels) != list(LABELS) or len(msg.covariances) != 9 * n:
            self.bad.reject('markers', f'labels {list(msg.labels)}, {n} positions')
            return
        pts = np.array([[p.x, p.y, p.z] for p in msg.positions])
        cov = np.asarray(msg.covariances, float).reshape(n, 3, 3)
        up = np.array([msg.up.x, msg.up.y, msg.up.z])
        try:
            self.ctl.add_observation(_stamp(msg), LabelledMarkers(pts, cov, up))
        except InsertionError as exc:
            self.bad.reject('markers', str(exc))

    def _publish_arm(self, joints) -> None:
        if joints is None:
            return
        tr = JointTrajectory(joint_names=list(ARM_JOINTS))
        pt = JointTrajectoryPoint(positions=[float(v) for v in joints])
        pt.time_from_start.nanosec = int(2e9 / self.p['command_rate_hz'])
        tr.points = [pt]
        self.pub_arm.publish(tr)

    def _on_joints(self, msg: JointState) -> None:
        if self.ctl is None or self.odom is None or self.wrench is None:
            return
        idx = {n: i for i, n in enumerate(msg.name)}
        if not all(n in idx for n in ARM_JOINTS) or len(msg.position) != len(msg.name):
            self.bad.reject('joint_states', 'arm joints missing')
            return
        q = np.array([msg.position[idx[n]] for n in ARM_JOINTS])
        t = _stamp(msg)
        if t <= self._given_t:
            return
        self._started = True
        if self._goal_t0 is None:
            self._goal_t0 = t
        try:
            self.ctl.add_state(t, q, self.odom, self.wrench)
            if t - self._goal_t0 > self._timeout:
                self.ctl.fail(f'timed out after {self._timeout:.0f} s in '
                              f'{self.ctl.phase.name}')
            cmd = self.ctl.step(t)
        except (InsertionError, ReachError) as exc:
            self.ctl.fail(f'slave error: {exc}')
            self._wakeup()
            return
        # (sim time starts again at 0 after a simulator reset: a stamp before the last
        # command's is a new clock, not a command to skip)
        if t < self._last_cmd or t - self._last_cmd >= 1.0 / self.p['command_rate_hz'] - 1e-6:
            self._last_cmd = t
            self._publish_arm(cmd.arm_joints)
            tw = Twist()
            tw.linear.x, tw.angular.z = cmd.base_linear_x, cmd.base_angular_z
            self.pub_cmd.publish(tw)
        st = cmd.status
        key = (st.phase, st.descending, st.contact_state if st.phase is Phase.FORCE_INSERT
               else '')
        if key != getattr(self, '_logged', None):
            self._logged = key
            self.get_logger().info(f'{st.phase.name}{" (descending)" if st.descending else ""}'
                                   f'{" " + st.contact_state if key[2] else ""} at '
                                   f'{t - self._goal_t0:.1f} s')
        self.get_logger().info(f'error {st.displacement_error_m * 1e3:.1f} mm, '
                               f'{st.angle_error_rad:.3f} rad, |F| '
                               f'{np.linalg.norm(st.wrench[:3]):.1f} N',
                               throttle_duration_sec=5.0)
        self._status, self._status_t = st, t
        if self._descended_t is None and (st.descending or st.phase is Phase.FORCE_INSERT):
            self._descended_t = t
        if st.done:
            self._wakeup()

    # -- the action ---------------------------------------------------------------------------
    def _wakeup(self) -> None:
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)

    def _on_goal(self, goal: Insert.Goal) -> GoalResponse:
        if self._busy:
            self.get_logger().warn('insert_card: a goal is running; rejected')
            return GoalResponse.REJECT
        if goal.slave and goal.slave != self.p['rover']:
            return GoalResponse.REJECT
        if goal.master and goal.master != self.p['master']:
            self.get_logger().warn(f'insert_card: guided by {self.p["master"]} (parameter '
                                   f'master), not {goal.master}; rejected')
            return GoalResponse.REJECT
        for v in (goal.tolerance_m, goal.angle_tolerance_rad, goal.max_force_n, goal.timeout_s):
            if not (math.isfinite(v) and v >= 0):
                return GoalResponse.REJECT
        if goal.site.header.frame_id not in ('', self.map_frame):
            self.get_logger().warn(f'insert_card: the site must be in the map frame '
                                   f'{self.map_frame!r}, not '
                                   f'{goal.site.header.frame_id!r}; rejected')
            return GoalResponse.REJECT
        site = goal.site.pose
        if goal.site.header.frame_id and not all(math.isfinite(v) for v in (
                site.position.x, site.position.y, site.position.z, site.orientation.x,
                site.orientation.y, site.orientation.z, site.orientation.w)):
            self.get_logger().warn('insert_card: the site is not finite; rejected')
            return GoalResponse.REJECT
        q = site.orientation
        if goal.site.header.frame_id and (abs(math.hypot(q.x, q.y, q.z, q.w) - 1.0) > 1e-3 or
                                          math.hypot(q.x, q.y) > 1e-3):
            self.get_logger().warn('insert_card: the site must be a level pose (a unit '
                                   'quaternion about z); rejected')
            return GoalResponse.REJECT
        self._busy = True
        return GoalResponse.ACCEPT

    def _goal_site(self, goal: Insert.Goal) -> np.ndarray:
        """The site frame in the odometry frame: the goal's `site` when it gives one (the map
        frame taken as the odometry frame), else the site parameters."""
        site = goal.site
        if not site.header.frame_id:
            return _site_pose(self.p['site_position'], self.p['site_yaw'])
        q, pos = site.pose.orientation, site.pose.position
        return _site_pose([pos.x, pos.y, pos.z], yaw_of(q.x, q.y, q.z, q.w))

    async def _execute(self, handle) -> Insert.Result:
        t0 = time.monotonic()
        try:
            return await self._run(handle, t0)
        finally:
            self.ctl = None
            self._busy = False
            self.pub_cmd.publish(Twist())

    async def _run(self, handle, t0: float) -> Insert.Result:
        g = handle.request
        p = self.p
        master = p['master']
        model = TaskModel(slot_width_m=p['slot_width_m'])
        self.ctl = SlaveController(
            model, self.r2, tolerance_m=g.tolerance_m or p['tolerance_m'],
            angle_tolerance_rad=g.angle_tolerance_rad or p['angle_tolerance_rad'],
            max_force_n=g.max_force_n or p['max_force_n'],
            descent_speed_m_s=p['descent_speed_m_s'],
            contact_threshold_n=p['contact_threshold_n'], seat_verdict=p['seat_verdict'],
            site_in_odom=self._goal_site(g))
        self._timeout = g.timeout_s or p['timeout_s']
        self._goal_t0 = None
        given = g.stamp.sec + 1e-9 * g.stamp.nanosec
        self._given_t = given if given > 0 else -math.inf
        self._started = False
        self._last_cmd = -math.inf
        self._status = None
        self._descended_t = None
        self.get_logger().info(f'inserting: guided by {master}/markers, r_2 '
                               f'{np.round(self.r2, 4).tolist()} ({self.r2_source}), slot '
                               f'{model.slot_width_m * 1e3:.1f} mm')
        last_fb = -math.inf
        relocations = 0
        while True:
            self._wake = Future()
            await self._wake
            st = self._status
            if handle.is_cancel_requested:
                self.ctl.fail('canceled')
                self._publish_arm(self.ctl.hold_joints)
                self.pub_cmd.publish(Twist())
                handle.canceled()
                backed = self.ctl.hold_joints is not None
                return self._result(False, 'canceled' + (' (backed off)' if backed else ''),
                                    t0)
            if st is None:
                continue
            if self.ctl.relocations > relocations:
                relocations = self.ctl.relocations
                self.get_logger().info(
                    f'a fix {st.displacement_error_m * 1e3:.0f} mm and {st.angle_error_rad:.2f} '
                    f'rad from the card: the base relocates it ({relocations} of '
                    f'{self.ctl.max_relocations})')
            if time.monotonic() - last_fb > 0.2:
                last_fb = time.monotonic()
                fb = Insert.Feedback(phase=int(min(st.phase, Phase.DONE)) if st.phase !=
                                     Phase.READY else Insert.Feedback.PHASE_VISUAL_SERVO,
                                     displacement_error_m=st.displacement_error_m,
                                     angle_error_rad=st.angle_error_rad,
                                     awaiting_fix=bool(st.awaiting_fix),
                                     relocating=bool(st.relocating),
                                     descending=bool(st.descending))
                w = st.wrench
                fb.wrench.force.x, fb.wrench.force.y, fb.wrench.force.z = (float(v) for v in w[:3])
                fb.wrench.torque.x, fb.wrench.torque.y, fb.wrench.torque.z = \
                    (float(v) for v in w[3:])
                handle.publish_feedback(fb)
            if st.done:
                (handle.succeed if st.success else handle.abort)()
                self.get_logger().info(f'insertion {"done" if st.success else "failed"}: '
                                       f'{st.reason}')
                return self._result(st.success, st.reason, t0, st)

    def _result(self, ok: bool, reason: str, t0: float, st=None) -> Insert.Result:
        r = Insert.Result(success=bool(ok), reason=reason, duration_s=time.monotonic() - t0)
        r.ended = stamp(self._status_t)
        if self._descended_t is not None:
            r.descended = stamp(self._descended_t)
        if st is not None:
            r.displacement_error_m = float(st.displacement_error_m)
            r.angle_error_rad = float(st.angle_error_rad)
        r.peak_force_n = float(self.ctl.peak_force_n) if self.ctl is not None else math.nan
        return r


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion slave`."""
    return run_node(SlaveNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
