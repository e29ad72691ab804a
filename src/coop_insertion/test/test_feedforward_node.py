"""The arm_feedforward node in-process: sensor messages handed to its callbacks, its efforts
caught at the publisher; which estimates it takes, and what it does with bad input."""
from __future__ import annotations

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import Twist, WrenchStamped
from rclpy.context import Context
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, JointState

from coop_common.dynparams import PARAM_NAMES, load_truth
from coop_common.rover_geometry import ARM_JOINTS
from coop_common.testing import pick_domain_id
from coop_insertion.feedforward import ArmModel
from coop_insertion.feedforward_node import FeedForwardNode
from coop_msgs.msg import DynamicParameters

Q = [0.0, -0.6, 1.2, -0.6]
ARM_WEIGHT_N = 9.81 * 1.01


@pytest.fixture
def make_node():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id() + 115)
    made = []

    def make(source: str = 'identified') -> tuple[FeedForwardNode, list[JointState]]:
        node = FeedForwardNode(context=ctx, namespace='rover2', parameter_overrides=[
            Parameter('source', value=source)])
        out: list[JointState] = []
        node.pub.publish = out.append
        made.append(node)
        return node, out
    try:
        yield make
    finally:
        for node in made:
            node.destroy_node()
        rclpy.shutdown(context=ctx)


def feed(node: FeedForwardNode, n: int = 1, *, speed: float = 0.0) -> None:
    """n sensor periods of a rover at rest: the arm's weight on the F/T sensor."""
    js = JointState(name=[*ARM_JOINTS, 'mast_pan'], position=[*Q, 0.0], velocity=[0.0] * 5)
    w = WrenchStamped()
    w.wrench.force.z = ARM_WEIGHT_N
    imu = Imu()
    imu.linear_acceleration.z = 9.81
    cmd = Twist()
    cmd.linear.x = speed
    node._on_cmd(cmd)
    for _ in range(n):
        node._on_joints(js)
        node._on_wrench(w)
        node._on_imu(imu)


def estimate(node: FeedForwardNode, x: np.ndarray, *, consistent: bool = True
             ) -> DynamicParameters:
    msg = DynamicParameters(names=list(PARAM_NAMES), values=x.tolist(),
                            observable=[True] * 22, physically_consistent=consistent)
    msg.header.stamp = node.get_clock().now().to_msg()
    return msg


def test_at_rest_it_feeds_forward_the_arms_weight(make_node):
    node, out = make_node()
    feed(node, 20)
    assert len(out) == 20 and list(out[-1].name) == list(ARM_JOINTS)
    g = ArmModel.rover(np.zeros(3), load_kg=0.01).gravity(Q)
    np.testing.assert_allclose(out[-1].effort, g, atol=1e-3)
    assert node.model == 'nominal'


def test_it_takes_a_good_estimate_and_refuses_a_bad_one_keeping_the_last(make_node):
    node, _ = make_node()
    truth = load_truth().to_vector()
    bad = truth.copy()
    bad[PARAM_NAMES.index('Izz')] = 5.0                  # breaks the triangle inequality
    node._on_estimate(estimate(node, bad))
    assert node.model == 'nominal' and node.bad.counts['estimate refused'] == 1
    node._on_estimate(estimate(node, truth))
    assert node.model == 'identified'
    np.testing.assert_allclose(node.ff.params.to_vector(), truth)
    node._on_estimate(estimate(node, truth * 1.1, consistent=False))     # the flag is heeded
    np.testing.assert_allclose(node.ff.params.to_vector(), truth)
    assert node.bad.counts['estimate refused'] == 2


def test_a_drive_step_is_fed_forward_unless_the_source_is_none(make_node):
    changes = {}
    for source in ('identified', 'none'):
        node, out = make_node(source)
        feed(node, 10)
        before = np.array(out[-1].effort)
        feed(node, 1, speed=0.25)          # the base lags the wheels: a jolt on the arm
        changes[source] = np.abs(np.array(out[-1].effort) - before).max()
    assert changes['identified'] > 0.1
    assert changes['none'] < 1e-9


def test_bad_input_is_counted_and_skipped(make_node):
    node, out = make_node()
    node._on_joints(JointState(name=['arm_joint_1'], position=[0.0], velocity=[0.0]))
    assert node.bad.counts['joint_states'] == 1
    node._on_imu(Imu())                    # nothing to feed forward from yet
    assert out == []
    feed(node, 1)
    w = WrenchStamped()
    w.wrench.force.x = float('nan')
    node._on_wrench(w)
    node._on_imu(Imu())
    assert node.bad.counts['sensor NaN'] == 1 and len(out) == 1
