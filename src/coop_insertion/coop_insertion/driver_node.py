"""Node `driver`: drives one rover to a pose on its odometry, an action (nav2's NavigateToPose
for this team).

Runs in the rover's namespace (`/rover1/driver`). Action `drive_to_pose`
(coop_msgs/action/DriveToPose): through the goal's waypoints to its pose
(coop_insertion.drive.Drive: turn where a leg needs it, drive with a heading correction, turn
to the heading), with feedback (pose, distance left, stage), a time limit from the path's
length, cancel (the rover stops) and a newer goal preempting the one under way. It reads `odom`
and commands `cmd_vel`. A goal whose pose or waypoints lie in an occupied cell of the team's
2-D map (`map/grid`, nav_msgs/OccupancyGrid, latched; remapped to the mapper's), or whose path
crosses one, ends at once with GOAL_OCCUPIED or NO_PATH and the cell; without a map the path is
driven as given. Goals are in the odometry's frame or the map (the team's odometry is expressed
in the map: `map -> <rover>/odom` is the identity the stereo node publishes).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from geometry_msgs.msg import PoseStamped, Twist
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.action.server import ServerGoalHandle
from rclpy.node import Node
from rclpy.task import Future

from coop_common.frames import FRAME_PARAMS, RoverFrames, check_frame_params
from coop_common.lockstep_node import Lockstep
from coop_common.node_util import BadInputCounter, declare_parameters, run_node, stamp
from coop_common.params import ParamSpec
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.rover_geometry import yaw_of
from coop_msgs.action import DriveToPose

from .drive import Drive, DriveEnd, GridSlice, grid_slice_of, obstruction
from .errors import InsertionError

PARAMS = {
    'max_speed_m_s': ParamSpec(0.2, 'Top speed when the goal gives none (m/s; app. D: 0.25)',
                               lo=0.01, hi=2.0),
    'max_yaw_rate_rad_s': ParamSpec(0.8, 'Top turn rate (rad/s)', lo=0.01, hi=5.0),
    'position_tolerance_m': ParamSpec(0.08, 'Arrived within this of the goal (m)', lo=0.001,
                                      hi=1.0),
    'yaw_tolerance_rad': ParamSpec(0.05, "Turned within this of the goal's heading (rad)",
                                   lo=0.001, hi=1.0),
    'time_margin_s': ParamSpec(30.0, 'Time limit when the goal gives none: this plus '
                               'time_slack x the path at the goal speed (s)', lo=1.0, hi=3600.0),
    'time_slack': ParamSpec(3.0, 'Time limit when the goal gives none: the path at the goal '
                            'speed times this, plus time_margin_s', lo=1.0, hi=100.0),
    'occupied_threshold': ParamSpec(65, 'A map/grid cell at or above this (%) is occupied',
                                    lo=1, hi=100),
    'start_clear_m': ParamSpec(0.3, "Occupied cells this close to the rover's start are its "
                               "own body as the team's cameras saw it, not obstacles (m)",
                               lo=0.0, hi=5.0),
    'feedback_period_s': ParamSpec(0.5, 'Feedback at most this often (s, the node clock)',
                                   lo=0.01, hi=60.0),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'lockstep': ParamSpec(False, "Answer rover_sim's lockstep rounds (a participant in its "
                          'lockstep_participants; remap sim/lockstep/tick and ack to the '
                          "simulator's): each round's odometry, then its command",
                          read_only=True),
}

Code = DriveToPose.Result


@dataclass
class _Goal:
    """A goal under way: its drive (None when it ended at once) and how it ended."""

    handle: ServerGoalHandle
    drive: Drive | None
    t0: float
    code: int = Code.NONE
    message: str = ''
    done: Future = field(default_factory=Future)
    remaining_m: float = math.nan
    driven_m: float = 0.0
    last_feedback: float = -math.inf

    def finish(self, code: int, message: str) -> None:
        if not self.done.done():
            self.code, self.message = code, message
            self.done.set_result(None)


class DriverNode(Node):
    """One rover's driver: the DriveToPose action on its odometry."""

    def __init__(self, **kwargs) -> None:
        super().__init__('driver', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params,
                                    check_all=check_frame_params)
        frames = RoverFrames.of_namespace(self.get_namespace(), self.p['frame_prefix'])
        self.frames = ('', frames.odom, frames.map)
        self.bad = BadInputCounter(self)
        self.pose: tuple[float, float, float] | None = None
        self.pose_t = math.nan
        self.grid: GridSlice | None = None
        self.goal: _Goal | None = None
        self.ls = Lockstep(self, self.p['lockstep'])
        self.ls.subscription(Odometry, 'odom', self._on_odom, SENSOR_QOS)
        self.pub_cmd = self.ls.publisher(Twist, 'cmd_vel', COMMAND_QOS)
        self.create_subscription(OccupancyGrid, 'map/grid', self._on_grid, LATCHED_QOS)
        self.server = ActionServer(self, DriveToPose, 'drive_to_pose',
                                   execute_callback=self._execute,
                                   goal_callback=lambda _g: GoalResponse.ACCEPT,
                                   handle_accepted_callback=self._accepted,
                                   cancel_callback=self._cancel)
        self.get_logger().info(f'driver ready: {self.resolve_topic_name("odom")} in, '
                               f'{self.resolve_topic_name("cmd_vel")} out, action '
                               f'{self.resolve_topic_name("drive_to_pose")}')

    def _on_params(self, changed: dict) -> None:
        self.p.update(changed)

    # -- inputs -------------------------------------------------------------------------------
    def _now(self) -> float:
        return self.ls.now_s(lambda: self.get_clock().now().nanoseconds * 1e-9)

    def _on_grid(self, msg: OccupancyGrid) -> None:
        if msg.header.frame_id not in self.frames:
            self.bad.reject('map/grid', f'frame {msg.header.frame_id!r}')
            return
        try:
            self.grid = grid_slice_of(msg)
        except InsertionError as exc:
            self.bad.reject('map/grid', str(exc))

    def _on_odom(self, msg: Odometry) -> None:
        p, q = msg.pose.pose.position, msg.pose.pose.orientation
        pose = (p.x, p.y, yaw_of(q.x, q.y, q.z, q.w))
        if not all(math.isfinite(v) for v in pose):
            self.bad.reject('odom', 'non-finite pose')
            return
        g = self.goal
        if g is not None and g.drive is not None and self.pose is not None:
            g.driven_m += math.hypot(pose[0] - self.pose[0], pose[1] - self.pose[1])
        self.pose = pose
        self.pose_t = msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec
        if g is None or g.drive is None or g.done.done():
            return
        now = self._now()
        st = g.drive.step(*pose, now)
        g.remaining_m = st.remaining_m
        tw = Twist()
        tw.linear.x, tw.angular.z = st.command.linear_x, st.command.angular_z
        self.pub_cmd.publish(tw)
        if st.end is DriveEnd.ARRIVED:
            g.finish(Code.NONE, f'arrived after {now - g.t0:.1f} s')
        elif st.end is DriveEnd.TIMEOUT:
            g.finish(Code.TIMEOUT, f'not there after {g.drive.limit_s:.0f} s, '
                                   f'{st.remaining_m:.2f} m left')
        elif now - g.last_feedback >= self.p['feedback_period_s']:
            g.last_feedback = now
            g.handle.publish_feedback(DriveToPose.Feedback(
                current_pose=self._pose_msg(), distance_remaining=float(st.remaining_m),
                navigation_time_s=float(now - g.t0), stage=str(st.command.stage)))

    # -- the action ---------------------------------------------------------------------------
    def _stop(self) -> None:
        self.pub_cmd.publish(Twist())

    def _plan(self, goal: DriveToPose.Goal) -> tuple[Drive | None, int, str]:
        """The goal's drive, or the code and reason it cannot be driven."""
        if goal.pose.header.frame_id not in self.frames:
            return None, Code.INVALID_GOAL, (f'frame {goal.pose.header.frame_id!r} is not one '
                                             f'of {[f for f in self.frames if f]}')
        if self.pose is None:
            return None, Code.NO_ODOMETRY, f'no {self.resolve_topic_name("odom")} yet'
        pos, q = goal.pose.pose.position, goal.pose.pose.orientation
        points = [(v.x, v.y) for v in goal.via] + [(pos.x, pos.y)]
        yaw = None if goal.ignore_heading else yaw_of(q.x, q.y, q.z, q.w)
        speed = goal.max_speed_m_s or self.p['max_speed_m_s']
        p = self.p
        try:
            drive = Drive(self.pose[:2], points, yaw, start_s=self._now(), max_speed_m_s=speed,
                          max_yaw_rate_rad_s=p['max_yaw_rate_rad_s'],
                          position_tolerance_m=p['position_tolerance_m'],
                          yaw_tolerance_rad=p['yaw_tolerance_rad'],
                          time_limit_s=goal.time_limit_s, time_margin_s=p['time_margin_s'],
                          time_slack=p['time_slack'])
            hit = None if self.grid is None else obstruction(
                np.vstack([self.pose[:2], points]), self.grid,
                threshold=p['occupied_threshold'], start_clear_m=p['start_clear_m'])
        except InsertionError as exc:
            return None, Code.INVALID_GOAL, str(exc)
        if hit is not None:
            where = f'({hit.xy[0]:.2f}, {hit.xy[1]:.2f})'
            if hit.kind == 'point':
                what = 'the goal' if hit.index == len(points) else f'waypoint {hit.index}'
                return None, Code.GOAL_OCCUPIED, f'{what} is in an occupied cell at {where}'
            return None, Code.NO_PATH, (f'leg {hit.index} of the path crosses an occupied '
                                        f'cell at {where}')
        return drive, Code.NONE, ''

    def _accepted(self, handle: ServerGoalHandle) -> None:
        """Called as the goal is accepted, before any other callback of this node: the drive
        starts with the next odometry (in lockstep, the next round's)."""
        old = self.goal
        if old is not None and not old.done.done():
            old.finish(Code.PREEMPTED, 'a newer goal took over')
        drive, code, message = self._plan(handle.request)
        g = self.goal = _Goal(handle, drive, self._now())
        if drive is None:
            g.finish(code, message)
            self.get_logger().warn(f'drive_to_pose: {message}')
        else:
            g.remaining_m = drive.length_m
            self.get_logger().info(f'driving {drive.length_m:.2f} m through '
                                   f'{len(handle.request.via)} waypoint(s), limit '
                                   f'{drive.limit_s:.0f} s')
        handle.execute()

    def _cancel(self, handle: ServerGoalHandle) -> CancelResponse:
        g = self.goal
        if g is not None and g.handle is handle and not g.done.done():
            self._stop()
            g.finish(Code.CANCELED, 'canceled')
        return CancelResponse.ACCEPT

    async def _execute(self, handle: ServerGoalHandle) -> DriveToPose.Result:
        g = self.goal
        if g is None or g.handle is not handle:         # preempted before it ran
            handle.abort()
            return DriveToPose.Result(error_code=Code.PREEMPTED,
                                      error_msg='a newer goal took over')
        await g.done
        if g.code != Code.NONE and g.drive is not None and self.goal is g:
            self._stop()
        if self.goal is g:
            self.goal = None
        if g.code == Code.NONE:
            handle.succeed()
        elif g.code == Code.CANCELED and handle.is_cancel_requested:
            handle.canceled()
        else:
            handle.abort()
        if g.drive is not None:
            self.get_logger().info(f'drive_to_pose: {g.message}')
        return DriveToPose.Result(error_code=g.code, error_msg=g.message,
                                  final_pose=self._pose_msg(),
                                  distance_remaining=float(g.remaining_m),
                                  distance_driven=float(g.driven_m),
                                  navigation_time_s=float(self._now() - g.t0))

    def _pose_msg(self) -> PoseStamped:
        msg = PoseStamped()
        msg.header.frame_id = self.frames[1]
        if self.pose is None:
            return msg
        msg.header.stamp = stamp(self.pose_t)
        x, y, yaw = self.pose
        msg.pose.position.x, msg.pose.position.y = float(x), float(y)
        msg.pose.orientation.z, msg.pose.orientation.w = math.sin(yaw / 2), math.cos(yaw / 2)
        return msg

    def destroy_node(self) -> None:
        g = self.goal
        if g is not None and not g.done.done():
            g.finish(Code.STOPPED, 'the driver shut down')
            self._stop()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion driver`."""
    return run_node(DriverNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
