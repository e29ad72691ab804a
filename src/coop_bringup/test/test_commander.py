"""The Commander from a runner's thread, its node spun by an executor in another, against a real
driver node whose rover is a unicycle stepped by a timer in that executor."""
from __future__ import annotations

import math
import threading

import pytest
import rclpy
from coop_bringup.commander import Commander
from geometry_msgs.msg import Twist
from nav_msgs.msg import Odometry
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from coop_common.qos import COMMAND_QOS, SENSOR_QOS
from coop_common.testing import pick_domain_id, wait_for
from coop_insertion.driver_node import DriverNode
from coop_msgs.action import DriveToPose

DT = 0.01


class _Unicycle(Node):
    """rover1's base: cmd_vel integrated into odometry, sped up 5x (the node's clock is the
    driver's: both take `t`)."""

    def __init__(self, context: Context) -> None:
        super().__init__('unicycle', namespace='rover1', context=context)
        self.t, self.pose, self.cmd = 0.0, [0.0, 0.0, 0.0], (0.0, 0.0)
        self.create_subscription(Twist, 'cmd_vel', self._on_cmd, COMMAND_QOS)
        self.pub = self.create_publisher(Odometry, 'odom', SENSOR_QOS)
        self.create_timer(DT / 5, self._step)

    def _on_cmd(self, m: Twist) -> None:
        self.cmd = (m.linear.x, m.angular.z)

    def _step(self) -> None:
        v, w = self.cmd
        x, y, yaw = self.pose
        self.pose = [x + v * math.cos(yaw) * DT, y + v * math.sin(yaw) * DT, yaw + w * DT]
        self.t += DT
        m = Odometry()
        m.header.frame_id = 'rover1/odom'
        m.pose.pose.position.x, m.pose.pose.position.y = self.pose[:2]
        m.pose.pose.orientation.z = math.sin(self.pose[2] / 2)
        m.pose.pose.orientation.w = math.cos(self.pose[2] / 2)
        self.pub.publish(m)


@pytest.fixture
def team():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id() + 130)
    ex = SingleThreadedExecutor(context=ctx)
    base = _Unicycle(ctx)
    driver = DriverNode(context=ctx, namespace='rover1')
    driver._now = lambda: base.t
    client = Node('runner', context=ctx)
    for n in (base, driver, client):
        ex.add_node(n)
    spinner = threading.Thread(target=ex.spin, daemon=True)
    spinner.start()
    try:
        # a goal before the driver's first odometry ends at once (NO_ODOMETRY): on a loaded
        # machine the first messages can take a while
        wait_for(lambda: driver.pose is not None, 30.0, what="the driver's first odometry")
        yield Commander(client, ex, ['rover1']), base
    finally:
        ex.shutdown()
        spinner.join(timeout=10)
        for n in (client, driver, base):
            n.destroy_node()
        rclpy.shutdown(context=ctx)


def test_the_commander_drives_a_rover_and_cancels_a_drive(team):
    cmd, base = team
    assert cmd.missing(cmd.drivers, 10.0) == []
    seen: list[float] = []
    task = cmd.drive('rover1', (0.6, 0.3), yaw=math.pi / 2,
                     on_feedback=lambda f: seen.append(f.distance_remaining))
    wait_for(lambda: task.done, 60.0, what='the drive')
    assert task.accepted
    r = task.result()
    assert r.error_code == DriveToPose.Result.NONE, r.error_msg
    assert math.hypot(base.pose[0] - 0.6, base.pose[1] - 0.3) <= 0.08
    assert seen and task.feedback is not None
    # a drive cancelled on the way: the rover stops short
    task = cmd.drive('rover1', (3.0, 0.3), yaw=None)
    wait_for(lambda: task.accepted and base.cmd[0] > 0.05, 30.0, what='under way')
    task.cancel()
    wait_for(lambda: task.done, 30.0, what='the cancel')
    assert task.result().error_code == DriveToPose.Result.CANCELED
    wait_for(lambda: base.cmd == (0.0, 0.0), 5.0, what='the stop')
    x, t = base.pose[0], base.t
    wait_for(lambda: base.t > t + 0.5, 10.0, what='half a second of the rover at rest')
    assert base.pose[0] == pytest.approx(x) and x < 2.5
