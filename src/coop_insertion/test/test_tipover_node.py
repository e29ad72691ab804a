"""The tipover_guard node in-process: its margin, the arm trajectories it slows or refuses and
the drive it ramps, its callbacks fed directly and its outputs caught at the publishers."""
from __future__ import annotations

import math

import numpy as np
import pytest
import rclpy
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import Twist
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.dynparams import load_truth
from coop_common.rover_geometry import ARM_JOINTS
from coop_common.testing import pick_domain_id
from coop_insertion.tipover_node import TipOverNode
from coop_msgs.msg import DynamicParameters

START = [0.0, -0.6, 1.2, 0.0]


@pytest.fixture
def guard():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id() + 125)
    node = TipOverNode(context=ctx, namespace='rover2',
                       parameter_overrides=[Parameter('load_kg', value=0.5)])
    out: dict[str, list] = {'arm': [], 'cmd': [], 'tip': []}
    node.pub_arm.publish = out['arm'].append
    node.pub_cmd.publish = out['cmd'].append
    node.pub.publish = out['tip'].append
    # identified: the Table 2-1 rover (the nominal set's arm mount is at the c.g.)
    est = DynamicParameters(values=load_truth().to_vector().tolist(), observable=[True] * 22,
                            physically_consistent=True)
    est.header.stamp = node.get_clock().now().to_msg()
    node._on_estimate(est)
    node._on_joints(JointState(name=list(ARM_JOINTS), position=START))
    imu = Imu()
    imu.linear_acceleration.z = 9.81
    node._on_imu(imu)
    try:
        yield node, out
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def swing(target: list[float], seconds: float) -> JointTrajectory:
    return JointTrajectory(joint_names=list(ARM_JOINTS), points=[JointTrajectoryPoint(
        positions=target, time_from_start=Duration(sec=int(seconds),
                                                   nanosec=int(seconds % 1 * 1e9)))])


def test_it_publishes_the_margin_of_its_model(guard):
    node, out = guard
    node._tick()
    tip = out['tip'][-1]
    assert tip.header.frame_id == 'rover2/base_link'
    # the arm and a 0.5 kg part on the mount 0.3 m to the left: the point 0.1 m left of the
    # c.g., a third of the way from the centre line to the wheels' edge (0.15 m)
    assert tip.zmp.y == pytest.approx(0.1, abs=0.01)
    assert tip.margin_fraction == pytest.approx(1 / 3, abs=0.02)
    assert not tip.stopped and tip.max_acceleration_m_s2 > 0.0


def test_a_fast_swing_is_slowed_and_one_that_tips_is_refused(guard):
    node, out = guard
    # a quick turn to the right: starting it throws the point left, toward the near edge
    node._on_trajectory(swing([-0.8, -0.6, 1.2, 0.0], 0.25))
    assert len(out['arm']) == 1 and 0.0 < node.scale < 1.0
    t = out['arm'][0].points[-1].time_from_start
    assert t.sec + t.nanosec * 1e-9 == pytest.approx(0.25 / math.sqrt(node.scale), rel=1e-6)
    node._on_trajectory(swing([math.pi / 2, -0.3, 0.6, 0.0], 5.0))   # out to the left: tips
    assert len(out['arm']) == 1 and node.scale == 0.0
    assert node.bad.counts['trajectory refused'] == 1
    node._on_trajectory(swing(START, 4.0))              # slow and safe: as given
    assert len(out['arm']) == 2 and node.scale == 1.0


def test_the_drive_ramps_at_what_the_margin_allows_and_stops_below_zero(guard):
    node, out = guard
    cmd = Twist()
    cmd.linear.x = 0.25
    node._on_cmd(cmd)
    for _ in range(3):
        node._tick()
    speeds = [c.linear.x for c in out['cmd']]
    step = node.allowed_acc / node.p['rate_hz']
    assert 0.0 < node.allowed_acc <= node.p['max_acceleration_m_s2']
    np.testing.assert_allclose(speeds, [step, 2 * step, 3 * step])
    # a shove the margin cannot take: everything held
    imu = Imu()
    imu.linear_acceleration.y = 60.0
    imu.linear_acceleration.z = 9.81
    for _ in range(30):
        node._on_imu(imu)
    node._tick()
    assert out['tip'][-1].stopped and out['cmd'][-1].linear.x == 0.0
    node._on_trajectory(swing(START, 4.0))
    assert node.bad.counts['trajectory while stopped'] == 1


def test_a_silent_commander_is_a_stop(guard):
    node, out = guard
    cmd = Twist()
    cmd.linear.x = 0.25
    node._on_cmd(cmd)
    node.target_t -= 10.0                                 # as if sent 10 s ago
    node.speed = 0.2
    node._tick()
    assert out['cmd'][-1].linear.x < 0.2 and node.target == (0.0, 0.0)
