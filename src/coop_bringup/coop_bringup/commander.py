"""A small commander over the team's actions and services (after nav2_simple_commander): drive
a rover to a pose, identify a rover's base, ask for the next best view or the task's view, run
an insertion. One client node, spun by an executor in another thread than the caller's: every
request is made in the executor's thread (coop_common.node_util.in_executor), and the caller
polls or waits on what comes back (`GoalTask`), so a runner in the main thread (the mission,
the insertion rig, a test) drives the team the same way.

    cmd = Commander(node, executor, ['rover1', 'rover2'])
    task = cmd.drive('rover1', (2.0, 0.5), yaw=1.57, via=[(1.0, 0.0)])
    ...   # task.answered, task.accepted, task.feedback, task.done, task.cancel()
    task.result().error_code == DriveToPose.Result.NONE
"""
from __future__ import annotations

import math
import threading
from collections.abc import Callable, Sequence
from typing import Any

from rclpy.action import ActionClient
from rclpy.client import Client
from rclpy.executors import Executor
from rclpy.node import Node
from rclpy.task import Future

from coop_common.node_util import in_executor
from coop_msgs.action import DriveToPose, Identify, Insert
from coop_msgs.srv import NextBestView, TaskView

__all__ = ['Commander', 'GoalTask']


class GoalTask:
    """One action goal: sent, answered (accepted or not), its feedback, its result."""

    def __init__(self, executor: Executor, client: ActionClient, goal: Any,
                 on_feedback: Callable[[Any], None] | None = None) -> None:
        self._ex = executor
        self._lock = threading.Lock()
        self.feedback: Any = None           # the last feedback message
        self._result: Future | None = None
        self._cancel: Future | None = None

        def fb(msg: Any) -> None:
            self.feedback = msg.feedback
            if on_feedback is not None:
                on_feedback(msg.feedback)

        self.sent = in_executor(executor, lambda: client.send_goal_async(
            goal, feedback_callback=fb))
        self.sent.add_done_callback(self._answered)

    def _answered(self, fut: Future) -> None:
        # in the executor's thread (rclpy runs a done callback as a task of the executor,
        # after the future is done: `done` waits for it)
        handle = fut.result()
        if handle is not None and handle.accepted:
            with self._lock:
                self._result = handle.get_result_async()

    @property
    def handle(self) -> Any:
        """rclpy's ClientGoalHandle once answered, else None."""
        return self.sent.result() if self.sent.done() else None

    @property
    def answered(self) -> bool:
        return self.sent.done()

    @property
    def accepted(self) -> bool:
        """Accepted by the server (False before the answer, see `answered`)."""
        h = self.handle
        return h is not None and bool(h.accepted)

    @property
    def done(self) -> bool:
        """The result is in (or the goal was refused)."""
        if not self.answered:
            return False
        with self._lock:
            return not self.accepted or (self._result is not None and self._result.done())

    @property
    def status(self) -> int | None:
        """The goal's final status (action_msgs GoalStatus), None before the result."""
        with self._lock:
            r = self._result
        return r.result().status if r is not None and r.done() else None

    def result(self) -> Any:
        """The action's result message (None for a refused goal); call once `done`."""
        if not self.done:
            raise RuntimeError('the goal has no result yet')
        with self._lock:
            return self._result.result().result if self._result is not None else None

    def cancel(self) -> Future | None:
        """Ask the server to cancel (a goal not answered yet is cancelled once accepted: None
        is returned then, the cancel goes out with the answer)."""
        def go() -> Future:
            return self.handle.cancel_goal_async()
        if self.accepted and not self.done:
            self._cancel = in_executor(self._ex, go)
            return self._cancel
        if not self.answered:
            def when_answered(_f: Future) -> None:     # in the executor's thread
                if self.accepted:
                    self._cancel = self.handle.cancel_goal_async()
            self.sent.add_done_callback(when_answered)
        return None


class Commander:
    """The team's actions from `node` (spun by `executor` in another thread): per rover
    `<r>/drive_to_pose` and `<r>/identifier/identify`, the team's `viewplan/next_best_view`,
    `viewplan/task_view` and the master's `insert` (names relative to the node's
    namespace: a commander under /team_a commands team_a)."""

    def __init__(self, node: Node, executor: Executor, rovers: Sequence[str], *,
                 map_frame: str = 'map') -> None:
        """map_frame: the team's map frame (team_a/map under mission.launch.py's team:=), the
        frame of the drive goals."""
        self.node, self.ex, self.rovers = node, executor, list(rovers)
        self.map_frame = map_frame
        # made on first use: each client's endpoints join the wait set of an executor that may
        # be a lockstep participant's, woken by every message
        self._drivers: dict[str, ActionClient] = {}
        self._identifiers: dict[str, ActionClient] = {}
        self._inserter: ActionClient | None = None
        self._nbv: Client | None = None
        self._task_view: Client | None = None

    @property
    def drivers(self) -> dict[str, ActionClient]:
        """Each rover's `<r>/drive_to_pose` client."""
        if not self._drivers:
            self._drivers = {r: ActionClient(self.node, DriveToPose, f'{r}/drive_to_pose')
                             for r in self.rovers}
        return self._drivers

    @property
    def identifiers(self) -> dict[str, ActionClient]:
        """Each rover's `<r>/identifier/identify` client."""
        if not self._identifiers:
            self._identifiers = {r: ActionClient(self.node, Identify, f'{r}/identifier/identify')
                                 for r in self.rovers}
        return self._identifiers

    @property
    def inserter(self) -> ActionClient:
        """The master's `insert` client."""
        if self._inserter is None:
            self._inserter = ActionClient(self.node, Insert, 'insert')
        return self._inserter

    @property
    def nbv(self) -> Client:
        """The view planner's `viewplan/next_best_view` client."""
        if self._nbv is None:
            self._nbv = self.node.create_client(NextBestView, 'viewplan/next_best_view')
        return self._nbv

    @property
    def task_view(self) -> Client:
        """The view planner's `viewplan/task_view` client."""
        if self._task_view is None:
            self._task_view = self.node.create_client(TaskView, 'viewplan/task_view')
        return self._task_view

    @staticmethod
    def missing(clients: dict[str, ActionClient], timeout_s: float) -> list[str]:
        """The names among `clients` whose server did not show within `timeout_s` (wall)."""
        return [k for k, c in clients.items() if not c.wait_for_server(timeout_sec=timeout_s)]

    # -- actions ------------------------------------------------------------------------------
    def drive(self, rover: str, xy: Sequence[float], yaw: float | None = None, *,
              via: Sequence[Sequence[float]] = (), max_speed_m_s: float = 0.0,
              time_limit_s: float = 0.0, frame: str | None = None,
              on_feedback: Callable[[DriveToPose.Feedback], None] | None = None) -> GoalTask:
        """Drive `rover` through `via` to `xy`, then to heading `yaw` (None: any heading), in
        `frame` (default: the team's map frame)."""
        g = DriveToPose.Goal(ignore_heading=yaw is None, max_speed_m_s=float(max_speed_m_s),
                             time_limit_s=float(time_limit_s))
        g.pose.header.frame_id = self.map_frame if frame is None else frame
        g.pose.pose.position.x, g.pose.pose.position.y = float(xy[0]), float(xy[1])
        h = 0.0 if yaw is None else float(yaw)
        g.pose.pose.orientation.z, g.pose.pose.orientation.w = math.sin(h / 2), math.cos(h / 2)
        for p in via:
            pt = type(g.pose.pose.position)()
            pt.x, pt.y = float(p[0]), float(p[1])
            g.via.append(pt)
        return GoalTask(self.ex, self.drivers[rover], g, on_feedback)

    def identify(self, rover: str, goal: Identify.Goal) -> GoalTask:
        return GoalTask(self.ex, self.identifiers[rover], goal)

    def insert(self, goal: Insert.Goal,
               on_feedback: Callable[[Insert.Feedback], None] | None = None) -> GoalTask:
        return GoalTask(self.ex, self.inserter, goal, on_feedback)

    # -- services -----------------------------------------------------------------------------
    def next_best_view(self, request: NextBestView.Request) -> Future:
        return in_executor(self.ex, lambda: self.nbv.call_async(request))

    def view_for_task(self, request: TaskView.Request) -> Future:
        return in_executor(self.ex, lambda: self.task_view.call_async(request))
