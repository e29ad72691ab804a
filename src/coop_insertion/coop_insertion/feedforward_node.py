"""Node `arm_feedforward`: one rover's base motion fed forward into its arm's joint control
(app. A, Eq. A-4; coop_insertion.feedforward).

Runs in the rover's namespace (`/rover2/arm_feedforward`). Each `imu` sample, with the latest
`arm/wrench`, `joint_states` and the drive command on `cmd_vel`, goes through the base observer
on the rover's identified model (`dynamic_parameters`, coop_id's identifier) and out on
`arm/feedforward` as joint efforts (sensor_msgs/JointState, effort only): F d'' + f d' + G, which
the arm's servo adds to its PD (rover_sim does; it drops efforts older than its
`feedforward_timeout_s`, so a silent node leaves the PD alone). The rest tilt is the
inclinometer's mean over its first second.

An identified set is taken when it is a physical body, recent and observed enough
(`accept_estimate`), blended in over `blend_s`; until then, and whenever one is refused (the
reason logged), the last good set stays, the nominal one (the prior ranges' centres) at first.
`source: nominal` never takes an estimate; `source: none` feeds forward gravity alone. The
simulator's true parameters are not offered: no node that closes a loop reads the truth.
"""
from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import Twist, WrenchStamped
from rclpy.node import Node
from sensor_msgs.msg import Imu, JointState

from coop_common.dynparams import BaseParameters
from coop_common.node_util import BadInputCounter, declare_parameters, run_node
from coop_common.params import ParamSpec, choice
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.rover_geometry import ARM_JOINTS
from coop_id.model import load_prior_ranges
from coop_msgs.msg import DynamicParameters, Inclinometer

from .feedforward import (
    Acceptance,
    FeedForward,
    FeedForwardError,
    ParameterSource,
    accept_estimate,
)

#: which coop_id estimates a node takes (judge_estimate); tipover_guard's too
ESTIMATE_PARAMS = {
    'max_estimate_age_s': ParamSpec(600.0, 'Refuse an estimate stamped longer ago than this '
                                    '(s, the node clock)', lo=0.1, hi=1e6),
    'min_observable': ParamSpec(20, 'Refuse an estimate with fewer of its 22 parameters '
                                'observable', lo=1, hi=22),
}
PARAMS = {
    'source': ParamSpec('identified', 'Base model fed forward: the identified estimates '
                        '(nominal until one is accepted), the nominal set only, or none '
                        '(gravity compensation alone)', choices=list(ParameterSource),
                        read_only=True),
    'blend_s': ParamSpec(0.5, 'A newly accepted parameter set takes over over this long (s)',
                         lo=0.0, hi=10.0),
    **ESTIMATE_PARAMS,
    'load_kg': ParamSpec(0.01, "The load in the gripper (kg; the card's 0.01)", lo=0.0, hi=5.0),
    'sample_period_s': ParamSpec(0.005, 'The IMU period the observer integrates over (s; '
                                 "rover_sim's sensor_rate_hz 200)", lo=1e-4, hi=0.1,
                                 read_only=True),
}
#: inclinometer readings averaged into the rest tilt
REST_SAMPLES = 200


def judge_estimate(node: Node, msg: DynamicParameters, values: dict) -> Acceptance:
    """accept_estimate on a coop_id estimate, its age on the node's clock, the limits from
    the node's ESTIMATE_PARAMS values."""
    now = node.get_clock().now().nanoseconds * 1e-9
    age = now - (msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9)
    return accept_estimate(np.array(msg.values), observable=list(msg.observable),
                           physically_consistent=msg.physically_consistent, age_s=age,
                           max_age_s=values['max_estimate_age_s'],
                           min_observable=values['min_observable'])


class FeedForwardNode(Node):
    """One rover's arm feed-forward: sensors in, joint efforts out."""

    def __init__(self, **kwargs) -> None:
        super().__init__('arm_feedforward', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params)
        self.bad = BadInputCounter(self)
        self.source = choice(ParameterSource, self.p['source'], 'source')
        self.nominal = BaseParameters.from_vector(load_prior_ranges().mean(axis=1))
        self.ff = FeedForward(self.nominal, dt=self.p['sample_period_s'],
                              source=self.source, load_kg=self.p['load_kg'],
                              blend_s=self.p['blend_s'])
        self.model = 'nominal'
        self._refusal = ''
        self._wrench: WrenchStamped | None = None
        self._joints: tuple[np.ndarray, np.ndarray] | None = None
        self._cmd = (0.0, 0.0)
        self._tilt: list[tuple[float, float]] = []
        self.published = 0
        self.create_subscription(Imu, 'imu', self._on_imu, SENSOR_QOS)
        self.create_subscription(WrenchStamped, 'arm/wrench', self._on_wrench, SENSOR_QOS)
        self.create_subscription(JointState, 'joint_states', self._on_joints, SENSOR_QOS)
        self.create_subscription(Inclinometer, 'inclinometer', self._on_incl, SENSOR_QOS)
        self.create_subscription(Twist, 'cmd_vel', self._on_cmd, COMMAND_QOS)
        self.create_subscription(DynamicParameters, 'dynamic_parameters', self._on_estimate,
                                 LATCHED_QOS)
        self.pub = self.create_publisher(JointState, 'arm/feedforward', COMMAND_QOS)
        self.get_logger().info(f'arm_feedforward ready ({self.source.value}): '
                               f'{self.resolve_topic_name("arm/feedforward")} out')

    def _on_params(self, changed: dict) -> None:
        self.p.update(changed)
        self.ff.blend_s = self.p['blend_s']

    # -- inputs ----------------------------------------------------------------------------
    def _on_wrench(self, msg: WrenchStamped) -> None:
        self._wrench = msg

    def _on_joints(self, msg: JointState) -> None:
        names = list(msg.name)
        try:
            cols = [names.index(j) for j in ARM_JOINTS]
            q = np.array([msg.position[c] for c in cols])
            qd = np.array([msg.velocity[c] for c in cols])
        except (ValueError, IndexError):
            self.bad.reject('joint_states', f'no position and velocity for {list(ARM_JOINTS)}')
            return
        if not (np.all(np.isfinite(q)) and np.all(np.isfinite(qd))):
            self.bad.reject('joint_states NaN')
            return
        self._joints = (q, qd)

    def _on_incl(self, msg: Inclinometer) -> None:
        if len(self._tilt) < REST_SAMPLES and math.isfinite(msg.roll) and \
                math.isfinite(msg.pitch) and not msg.saturated:
            self._tilt.append((msg.roll, msg.pitch))

    def _on_cmd(self, msg: Twist) -> None:
        if math.isfinite(msg.linear.x) and math.isfinite(msg.angular.z):
            self._cmd = (float(msg.linear.x), float(msg.angular.z))
        else:
            self.bad.reject('cmd_vel NaN')

    def _on_estimate(self, msg: DynamicParameters) -> None:
        if self.source is not ParameterSource.IDENTIFIED:
            return
        verdict = judge_estimate(self, msg, self.p)
        if not verdict.ok:
            if verdict.reason != self._refusal:
                self.get_logger().warn(f'estimate not used ({verdict.reason}); keeping the '
                                       f'{self.model} set')
                self._refusal = verdict.reason
            self.bad.counts['estimate refused'] += 1
            return
        try:
            self.ff.set_parameters(BaseParameters.from_vector(np.array(msg.values)))
        except FeedForwardError as exc:          # accept_estimate checked the same: defensive
            self.bad.reject('estimate', str(exc))
            return
        if self.model != 'identified':
            self.get_logger().info('feeding forward the identified base model')
        self.model, self._refusal = 'identified', ''

    def _on_imu(self, msg: Imu) -> None:
        if self._wrench is None or self._joints is None:
            return
        gyro = np.array([msg.angular_velocity.x, msg.angular_velocity.y,
                         msg.angular_velocity.z])
        sf = np.array([msg.linear_acceleration.x, msg.linear_acceleration.y,
                       msg.linear_acceleration.z])
        w = self._wrench.wrench
        force = np.array([w.force.x, w.force.y, w.force.z])
        torque = np.array([w.torque.x, w.torque.y, w.torque.z])
        if not all(np.all(np.isfinite(a)) for a in (gyro, sf, force, torque)):
            self.bad.reject('sensor NaN')
            return
        roll, pitch = (np.mean(self._tilt, axis=0) if self._tilt else (0.0, 0.0))
        q, qd = self._joints
        t0 = time.perf_counter()
        tau = self.ff.torque(q=q, qd=qd, force=force, torque=torque, gyro=gyro,
                             specific_force=sf, roll=float(roll), pitch=float(pitch),
                             anchor_speed=self._cmd[0], anchor_yaw_rate=self._cmd[1])
        self.compute_s = time.perf_counter() - t0
        out = JointState()
        out.header.stamp = msg.header.stamp
        out.name = list(ARM_JOINTS)
        out.effort = [float(t) for t in tau]
        self.pub.publish(out)
        self.published += 1


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion arm_feedforward`."""
    return run_node(FeedForwardNode, args)
