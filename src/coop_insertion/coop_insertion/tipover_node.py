"""Node `tipover_guard`: one rover's dynamic tip-over stability (app. A.3, Eq. A-5) watched and
kept, on its own sensors and model (coop_insertion.tipover).

Runs in the rover's namespace (`/rover2/tipover_guard`) between the commanders and the rover:

- `tipover` (coop_msgs/TipOver, at `rate_hz`): the zero-moment point of the rover's model (the
  identified base mass at its c.g., the arm's links and load where the encoders put them, the
  base accelerating as the IMU measures) and its margin inside the wheels' support polygon;
- `arm/joint_command_in` -> `arm/joint_command`: each arm trajectory checked along its plan
  (`limit_path`, the links' accelerations from the plan's own cubic) and passed on slowed by
  1 / sqrt(scale) where it would take the margin below `required_fraction`, or refused (not
  passed on, counted and logged) where a pose of it is below the margin standing still;
- `cmd_vel_in` -> `cmd_vel`: the drive command passed on at `rate_hz`, its speed ramped at the
  acceleration the margin allows at the arm's pose (at most `max_acceleration_m_s2`).

While the measured margin is below zero the rover is stopped: `cmd_vel` zero and arm
trajectories refused until it is back inside; the guard never commands through it. The base
model comes from `dynamic_parameters` (coop_id), taken as arm_feedforward takes it
(`accept_estimate`), the nominal one until then. Without the guard in the graph the
commanders publish to `arm/joint_command` and `cmd_vel` directly; with it, remap their outputs
to the `_in` topics.
"""
from __future__ import annotations

import itertools
import math

import numpy as np
from geometry_msgs.msg import Twist
from rclpy.duration import Duration
from rclpy.node import Node
from scipy.interpolate import CubicHermiteSpline, CubicSpline
from sensor_msgs.msg import Imu, JointState
from trajectory_msgs.msg import JointTrajectory

from coop_common.dynparams import BaseParameters
from coop_common.frames import FRAME_PARAMS, RoverFrames, check_frame_params
from coop_common.node_util import BadInputCounter, declare_parameters, run_node
from coop_common.params import ParamSpec
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.rover_geometry import ARM_JOINTS, BASE_HEIGHT_M
from coop_id.model import load_prior_ranges
from coop_msgs.msg import DynamicParameters, TipOver

from .feedforward_node import ESTIMATE_PARAMS, judge_estimate
from .tipover import RoverMasses, TipOverError, limit_path, zmp

PARAMS = {
    'required_fraction': ParamSpec(0.2, 'Keep the zero-moment point at least this fraction '
                                   "of the support polygon's depth inside", lo=0.0, hi=0.95),
    'load_kg': ParamSpec(0.01, "The load in the gripper (kg; the card's 0.01)", lo=0.0,
                         hi=10.0),
    'max_acceleration_m_s2': ParamSpec(2.0, 'The drive ramps its speed at most this fast, '
                                       'less where the margin needs it (m/s^2)', lo=0.01,
                                       hi=20.0),
    'rate_hz': ParamSpec(50.0, 'How often the margin is published and the drive command '
                         'stepped (Hz)', lo=1.0, hi=500.0, read_only=True),
    'plan_step_s': ParamSpec(0.01, 'An arm trajectory is checked at instants this far apart '
                             '(s)', lo=0.001, hi=0.2),
    **ESTIMATE_PARAMS,
    'cmd_timeout_s': ParamSpec(0.5, 'A drive command older than this is a stop (s)',
                               lo=0.01, hi=10.0),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
}


class TipOverNode(Node):
    """One rover's tip-over guard."""

    def __init__(self, **kwargs) -> None:
        super().__init__('tipover_guard', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params,
                                    check_all=check_frame_params)
        self.frame = RoverFrames.of_namespace(self.get_namespace(),
                                              self.p['frame_prefix']).base_link
        self.bad = BadInputCounter(self)
        self.params = BaseParameters.from_vector(load_prior_ranges().mean(axis=1))
        self.model = RoverMasses.of(self.params, load_kg=self.p['load_kg'])
        self.q: np.ndarray | None = None
        self.base_acc = np.zeros(3)
        self.target = (0.0, 0.0)
        self.target_t = -math.inf
        self.speed = 0.0
        self.scale = 1.0
        self.stopped = False
        self.margin = math.nan
        self.allowed_acc = self.p['max_acceleration_m_s2']
        self.create_subscription(JointState, 'joint_states', self._on_joints, SENSOR_QOS)
        self.create_subscription(Imu, 'imu', self._on_imu, SENSOR_QOS)
        self.create_subscription(DynamicParameters, 'dynamic_parameters', self._on_estimate,
                                 LATCHED_QOS)
        self.create_subscription(JointTrajectory, 'arm/joint_command_in', self._on_trajectory,
                                 COMMAND_QOS)
        self.create_subscription(Twist, 'cmd_vel_in', self._on_cmd, COMMAND_QOS)
        self.pub_arm = self.create_publisher(JointTrajectory, 'arm/joint_command', COMMAND_QOS)
        self.pub_cmd = self.create_publisher(Twist, 'cmd_vel', COMMAND_QOS)
        self.pub = self.create_publisher(TipOver, 'tipover', SENSOR_QOS)
        self.create_timer(1.0 / self.p['rate_hz'], self._tick)
        self.get_logger().info(f'tipover_guard ready: keeps {self.p["required_fraction"]:.2f} '
                               f'of the depth; {self.resolve_topic_name("tipover")} out')

    def _on_params(self, changed: dict) -> None:
        self.p.update(changed)
        if 'load_kg' in changed:
            self.model = RoverMasses.of(self.params, load_kg=self.p['load_kg'])

    # -- inputs ----------------------------------------------------------------------------
    def _on_joints(self, msg: JointState) -> None:
        names = list(msg.name)
        try:
            q = np.array([msg.position[names.index(j)] for j in ARM_JOINTS])
        except (ValueError, IndexError):
            self.bad.reject('joint_states', f'no positions for {list(ARM_JOINTS)}')
            return
        if not np.all(np.isfinite(q)):
            self.bad.reject('joint_states NaN')
            return
        self.q = q

    def _on_imu(self, msg: Imu) -> None:
        a = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y,
                      msg.linear_acceleration.z])
        if not np.all(np.isfinite(a)):
            self.bad.reject('imu NaN')
            return
        # the specific force less gravity (the base near level): the c.g.'s acceleration;
        # smoothed over a few samples (the sensor's noise is not the base's motion)
        self.base_acc = 0.8 * self.base_acc + 0.2 * (a - np.array([0.0, 0.0, 9.81]))

    def _on_estimate(self, msg: DynamicParameters) -> None:
        verdict = judge_estimate(self, msg, self.p)
        if not verdict.ok:
            self.bad.reject('estimate refused', verdict.reason)
            return
        self.params = BaseParameters.from_vector(np.array(msg.values))
        self.model = RoverMasses.of(self.params, load_kg=self.p['load_kg'])

    def _on_cmd(self, msg: Twist) -> None:
        if not (math.isfinite(msg.linear.x) and math.isfinite(msg.angular.z)):
            self.bad.reject('cmd_vel NaN')
            return
        self.target = (float(msg.linear.x), float(msg.angular.z))
        self.target_t = self._now()

    def _now(self) -> float:
        return self.get_clock().now().nanoseconds * 1e-9

    def _on_trajectory(self, msg: JointTrajectory) -> None:
        if self.q is None:
            self.bad.reject('trajectory before joint states')
            return
        if self.stopped:
            self.bad.reject('trajectory while stopped', 'the margin is below zero')
            self.scale = 0.0
            return
        try:
            qs = self._plan(msg)
            lim = limit_path(self.model.path(qs, self.p['plan_step_s']), self.model.footprint,
                             min_fraction=self.p['required_fraction'])
        except (TipOverError, ValueError) as exc:
            self.bad.reject('trajectory', str(exc))
            return
        if lim.stop:
            self.scale = 0.0
            self.bad.reject('trajectory refused', 'a pose of it is below the margin')
            return
        self.scale = lim.scale
        out = msg
        if lim.scale < 1.0:
            slow = 1.0 / math.sqrt(max(lim.scale, 1e-6))
            for pt in out.points:
                t = (pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9) * slow
                pt.time_from_start = Duration(seconds=t).to_msg()
                pt.velocities = [v / slow for v in pt.velocities]
            self.get_logger().info(f'arm trajectory slowed {slow:.2f}x for the margin')
        self.pub_arm.publish(out)

    def _plan(self, msg: JointTrajectory) -> np.ndarray:
        """The trajectory's arm joints every plan_step_s from the measured state, by the
        cubic the servo follows (through positions and speeds when every point has them)."""
        names = list(msg.joint_names)
        if not msg.points or any(n not in ARM_JOINTS for n in names):
            raise ValueError(f'joints {names} not a subset of {list(ARM_JOINTS)}')
        assert self.q is not None
        cols = [ARM_JOINTS.index(n) for n in names]
        t = [0.0] + [p.time_from_start.sec + p.time_from_start.nanosec * 1e-9
                     for p in msg.points]
        if any(b <= a for a, b in itertools.pairwise(t)):
            raise ValueError('time_from_start must increase from > 0')
        pos = np.tile(self.q, (len(t), 1))
        for k, p in enumerate(msg.points, start=1):
            pos[k, cols] = p.positions
        speeds = all(len(p.velocities) == len(names) for p in msg.points)
        if speeds:
            vel = np.zeros_like(pos)
            for k, p in enumerate(msg.points, start=1):
                vel[k, cols] = p.velocities
            spline = CubicHermiteSpline(t, pos, vel)
        else:
            spline = CubicSpline(t, pos, bc_type='clamped')
        step = self.p['plan_step_s']
        ts = np.arange(-step, t[-1] + 1.5 * step, step)
        return spline(np.clip(ts, 0.0, t[-1]))

    # -- the guard's period -----------------------------------------------------------------
    def _tick(self) -> None:
        if self.q is None:
            return
        now = self.model.loads(self.q, base_acceleration=self.base_acc)
        try:
            p = zmp(now)
        except TipOverError as exc:
            self.bad.reject('zmp', str(exc))
            return
        fp = self.model.footprint
        self.margin = fp.margin_fraction(p)
        was = self.stopped
        self.stopped = self.margin < 0.0
        if self.stopped and not was:
            self.get_logger().error(f'tip-over margin {self.margin:.2f} < 0: drive and arm '
                                    'held until it is back inside')
        # the drive: the acceleration the margin allows at this pose, either way
        allowed = self.model.drive_acceleration(self.q, top=self.p['max_acceleration_m_s2'],
                                                min_fraction=self.p['required_fraction'])
        self.allowed_acc = allowed
        dt = 1.0 / self.p['rate_hz']
        if self._now() - self.target_t > self.p['cmd_timeout_s']:
            self.target = (0.0, 0.0)              # a silent commander is a stop
        goal = 0.0 if self.stopped else self.target[0]
        step = allowed * dt
        self.speed += max(-step, min(step, goal - self.speed))
        if self.stopped:
            self.speed = 0.0
        cmd = Twist()
        cmd.linear.x = self.speed
        cmd.angular.z = 0.0 if self.stopped else self.target[1]
        self.pub_cmd.publish(cmd)
        out = TipOver()
        out.header.stamp = self.get_clock().now().to_msg()
        out.header.frame_id = self.frame
        out.zmp.x, out.zmp.y, out.zmp.z = float(p[0]), float(p[1]), -BASE_HEIGHT_M
        out.margin_m = fp.margin(p)
        out.margin_fraction = self.margin
        out.required_fraction = float(self.p['required_fraction'])
        out.command_scale = float(self.scale)
        out.max_acceleration_m_s2 = float(allowed)
        out.stopped = self.stopped
        self.pub.publish(out)


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion tipover_guard`."""
    return run_node(TipOverNode, args)
