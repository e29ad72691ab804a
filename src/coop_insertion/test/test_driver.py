"""The drive core (Drive, obstruction) and the driver node in-process: its action served to a
client in the same private Context, the rover a unicycle that integrates the node's cmd_vel
into the odometry the node is fed."""
from __future__ import annotations

import math

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import Point
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.action import ActionClient
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from coop_common.testing import pick_domain_id
from coop_insertion.drive import (
    Drive,
    DriveEnd,
    GridSlice,
    grid_slice_of,
    obstruction,
    path_length,
)
from coop_insertion.driver_node import DriverNode
from coop_insertion.errors import InsertionError
from coop_msgs.action import DriveToPose

Code = DriveToPose.Result
DT = 0.02


def _unicycle(drive: Drive, pose, t: float = 0.0, steps: int = 5000):
    x, y, yaw = pose
    for _ in range(steps):
        st = drive.step(x, y, yaw, t)
        if st.end is not None:
            return st.end, (x, y, yaw), t
        x += st.command.linear_x * math.cos(yaw) * DT
        y += st.command.linear_x * math.sin(yaw) * DT
        yaw += st.command.angular_z * DT
        t += DT
    return None, (x, y, yaw), t


def test_a_drive_arrives_through_its_waypoints_and_turns_to_the_heading():
    d = Drive((0.0, 0.0), [(1.0, 0.0), (1.0, 1.0)], math.pi, start_s=0.0)
    assert d.length_m == pytest.approx(2.0)
    assert d.limit_s == pytest.approx(30.0 + 3.0 * 2.0 / 0.2)
    end, (x, y, yaw), t = _unicycle(d, (0.0, 0.0, 0.0))
    assert end is DriveEnd.ARRIVED
    assert math.hypot(x - 1.0, y - 1.0) <= 0.08
    assert abs(math.remainder(yaw - math.pi, 2 * math.pi)) <= 0.05
    assert t < d.limit_s
    assert d.remaining(x, y) == 0.0


def test_a_drive_that_cannot_get_there_times_out_and_stops():
    d = Drive((0.0, 0.0), [(5.0, 0.0)], None, start_s=10.0, time_limit_s=1.0)
    assert d.step(0.0, 0.0, 0.0, 10.5).end is None
    st = d.step(0.0, 0.0, 0.0, 11.5)          # the rover did not move: stuck
    assert st.end is DriveEnd.TIMEOUT
    assert (st.command.linear_x, st.command.angular_z) == (0.0, 0.0)
    assert st.remaining_m == pytest.approx(5.0)


@pytest.mark.parametrize('kwargs', [{'max_speed_m_s': 0.0}, {'time_limit_s': -1.0},
                                    {'time_margin_s': math.nan}])
def test_a_drive_refuses_bad_limits(kwargs):
    with pytest.raises(InsertionError):
        Drive((0.0, 0.0), [(1.0, 0.0)], None, start_s=0.0, **kwargs)


def _grid(occupied_xy=(), res=0.1) -> GridSlice:
    occ = np.zeros((40, 40), np.int8)           # 4 x 4 m from (-2, -2)
    for x, y in occupied_xy:
        occ[int((y + 2) / res), int((x + 2) / res)] = 100
    return GridSlice(occ, (-2.0, -2.0), res)


def test_obstruction_names_the_occupied_goal_the_crossed_leg_and_ignores_the_rover_itself():
    g = _grid([(1.05, 0.05), (0.05, 0.05), (-1.05, 1.05)])
    assert obstruction([(0.0, 0.0), (1.05, 0.05)], g).kind == 'point'      # the goal
    hit = obstruction([(0.0, 0.0), (1.5, 0.0), (1.5, 1.5)], g)            # passes (1.05, 0.05)
    assert (hit.kind, hit.index) == ('leg', 1)
    assert hit.xy[0] == pytest.approx(1.05, abs=0.06)
    # (0.05, 0.05) is under the rover at the start: not an obstacle
    assert obstruction([(0.0, 0.0), (0.0, -1.5)], g) is None
    # unknown (-1) and outside the grid are free to drive
    assert obstruction([(0.0, 0.0), (0.0, 5.0)], _grid()) is None
    assert path_length([(0, 0), (3, 4), (3, 5)]) == pytest.approx(6.0)


def test_a_map_grid_message_is_the_slice_the_driver_checks_or_refused():
    msg = OccupancyGrid()
    msg.info.width, msg.info.height, msg.info.resolution = 3, 2, 0.5
    msg.info.origin.position.x, msg.info.origin.position.y = -1.0, 2.0
    msg.info.origin.orientation.w = 1.0
    msg.data = [0, 0, 100, -1, 0, 0]            # rows along y: (x 0..1 m, y 2..2.5 m) occupied
    g = grid_slice_of(msg)
    assert g.occupancy.shape == (2, 3) and g.origin_xy == (-1.0, 2.0)
    assert g.occupied(np.array([[0.2, 2.2], [-0.8, 2.2], [0.2, 2.7]]), 65).tolist() == \
        [True, False, False]
    msg.data = [0] * 5
    with pytest.raises(InsertionError, match='ragged'):
        grid_slice_of(msg)
    msg.data = [0] * 6
    msg.info.origin.orientation.z, msg.info.origin.orientation.w = 0.3826834, 0.9238795
    with pytest.raises(InsertionError, match='rotated'):
        grid_slice_of(msg)


class _Rover:
    """The driver node, an action client beside it, and a unicycle fed by its cmd_vel."""

    def __init__(self) -> None:
        self.ctx = Context()
        rclpy.init(context=self.ctx, domain_id=pick_domain_id() + 120)
        self.node = DriverNode(context=self.ctx, namespace='rover1')
        self.client_node = Node('drive_client', context=self.ctx)
        self.client = ActionClient(self.client_node, DriveToPose, '/rover1/drive_to_pose')
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.ex.add_node(self.client_node)
        self.t = 100.0
        self.node._now = lambda: self.t
        self.pose = [0.0, 0.0, 0.0]
        self.cmds: list[tuple[float, float]] = []
        self.node.pub_cmd.publish = lambda m: self.cmds.append((m.linear.x, m.angular.z))
        self.feedback: list[DriveToPose.Feedback] = []
        assert self.client.wait_for_server(timeout_sec=10.0)

    def odom(self) -> None:
        m = Odometry()
        m.header.stamp.sec = int(self.t)
        m.pose.pose.position.x, m.pose.pose.position.y = self.pose[:2]
        m.pose.pose.orientation.z = math.sin(self.pose[2] / 2)
        m.pose.pose.orientation.w = math.cos(self.pose[2] / 2)
        self.node._on_odom(m)

    def step(self) -> None:
        v, w = self.cmds[-1] if self.cmds else (0.0, 0.0)
        self.pose[0] += v * math.cos(self.pose[2]) * DT
        self.pose[1] += v * math.sin(self.pose[2]) * DT
        self.pose[2] += w * DT
        self.t += DT
        self.odom()
        self.ex.spin_once(timeout_sec=0.0)

    def spin_until(self, fut, steps: int = 10000, drive: bool = True) -> None:
        for _ in range(steps):
            if fut.done():
                return
            self.step() if drive else self.ex.spin_once(timeout_sec=0.01)
        raise AssertionError('not done')

    def send(self, x: float, y: float, yaw: float = 0.0, frame: str = 'map', **kw):
        g = DriveToPose.Goal(**kw)
        g.pose.header.frame_id = frame
        g.pose.pose.position.x, g.pose.pose.position.y = x, y
        g.pose.pose.orientation.z, g.pose.pose.orientation.w = math.sin(yaw / 2), \
            math.cos(yaw / 2)
        fut = self.client.send_goal_async(g, feedback_callback=lambda f: self.feedback.append(
            f.feedback))
        self.spin_until(fut, drive=False)
        handle = fut.result()
        assert handle.accepted
        return handle, handle.get_result_async()

    def close(self) -> None:
        self.ex.shutdown()
        self.client.destroy()
        self.client_node.destroy_node()
        self.node.destroy_node()
        rclpy.shutdown(context=self.ctx)


@pytest.fixture
def rover():
    r = _Rover()
    try:
        yield r
    finally:
        r.close()


def test_the_driver_drives_to_the_pose_with_feedback(rover):
    rover.odom()
    _, res = rover.send(1.0, 0.5, math.pi / 2, via=[Point(x=0.5, y=0.0)])
    rover.spin_until(res)
    r = res.result().result
    assert r.error_code == Code.NONE, r.error_msg
    assert math.hypot(rover.pose[0] - 1.0, rover.pose[1] - 0.5) <= 0.08
    assert r.final_pose.pose.position.x == pytest.approx(rover.pose[0], abs=0.01)
    assert r.distance_driven >= 1.0
    left = [f.distance_remaining for f in rover.feedback]
    assert len(left) >= 3 and left[0] > left[-1]
    assert rover.cmds[-1] == (0.0, 0.0)


def test_a_goal_without_odometry_or_in_a_foreign_frame_ends_at_once(rover):
    _, res = rover.send(1.0, 0.0)
    rover.spin_until(res, drive=False)
    assert res.result().result.error_code == Code.NO_ODOMETRY
    rover.odom()
    _, res = rover.send(1.0, 0.0, frame='rover2/odom')
    rover.spin_until(res, drive=False)
    r = res.result().result
    assert r.error_code == Code.INVALID_GOAL and 'rover2/odom' in r.error_msg
    _, res = rover.send(1.0, 0.0, frame='rover1/odom', max_speed_m_s=-1.0)
    rover.spin_until(res, drive=False)
    assert res.result().result.error_code == Code.INVALID_GOAL
    assert not rover.cmds                      # nothing was driven


def test_an_occupied_goal_or_a_blocked_leg_is_refused_with_the_cell(rover):
    g = OccupancyGrid()
    g.header.frame_id = 'map'
    g.info.resolution, g.info.width, g.info.height = 0.1, 40, 40
    g.info.origin.position.x = g.info.origin.position.y = -2.0
    g.info.origin.orientation.w = 1.0
    data = np.zeros((40, 40), np.int8)
    data[20, 30] = 100                          # the cell at (1.05, 0.05)
    g.data = data.ravel().tolist()
    rover.node._on_grid(g)
    rover.odom()
    _, res = rover.send(1.05, 0.05)
    rover.spin_until(res, drive=False)
    r = res.result().result
    assert r.error_code == Code.GOAL_OCCUPIED and '(1.05, 0.05)' in r.error_msg
    _, res = rover.send(1.5, 0.0)
    rover.spin_until(res, drive=False)
    r = res.result().result
    assert r.error_code == Code.NO_PATH and 'leg 1' in r.error_msg
    _, res = rover.send(1.5, 0.0, via=[Point(x=0.5, y=0.6), Point(x=1.5, y=0.6)],
                        ignore_heading=True)
    rover.spin_until(res)
    assert res.result().result.error_code == Code.NONE


def test_a_cancelled_drive_stops_the_rover(rover):
    rover.odom()
    handle, res = rover.send(2.0, 0.0)
    for _ in range(100):
        rover.step()
    assert rover.cmds[-1][0] > 0.05
    cancel = handle.cancel_goal_async()
    rover.spin_until(cancel, drive=False)
    rover.spin_until(res, drive=False)
    r = res.result()
    assert r.status == 5 and r.result.error_code == Code.CANCELED      # STATUS_CANCELED
    assert rover.cmds[-1] == (0.0, 0.0)
    x = rover.pose[0]
    for _ in range(20):
        rover.step()
    assert rover.pose[0] == pytest.approx(x)


def test_a_newer_goal_preempts_and_a_stuck_drive_times_out(rover):
    rover.odom()
    _, first = rover.send(2.0, 0.0)
    for _ in range(50):
        rover.step()
    _, second = rover.send(-1.0, 0.0, time_limit_s=1.0)
    rover.spin_until(first, drive=False)
    assert first.result().result.error_code == Code.PREEMPTED
    rover.node.pub_cmd.publish = lambda m: rover.cmds.append((0.0, 0.0))    # wheels stuck
    rover.spin_until(second)
    r = second.result().result
    assert r.error_code == Code.TIMEOUT and 'left' in r.error_msg
