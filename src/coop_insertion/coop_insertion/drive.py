"""Driving a skid-steer rover to a pose on its odometry (turn, drive, turn; or through
waypoints), one drive goal with its time limit and distance left (`Drive`, the `driver` node's
core), and the check of a path against a 2-D occupancy grid (`obstruction`). No rclpy here."""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from coop_common.rover_geometry import yaw_of

from .errors import InsertionError

__all__ = ['Drive', 'DriveCommand', 'DriveEnd', 'DriveStep', 'FollowPath', 'GoToPose',
           'GridSlice', 'Obstruction', 'Stage', 'obstruction', 'path_length', 'wrap']


class Stage(StrEnum):
    """What a drive command does: turn to face the goal, drive to it, turn to its heading, or
    nothing (arrived)."""

    FACE = 'face'
    DRIVE = 'drive'
    TURN = 'turn'
    ARRIVED = 'arrived'


def wrap(a: float) -> float:
    """Angle into [-pi, pi)."""
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass(frozen=True)
class DriveCommand:
    """One drive step: the twist to send, whether the goal is reached, and the stage."""

    linear_x: float
    angular_z: float
    arrived: bool
    stage: Stage


class GoToPose:
    """Turn on the spot to face the goal, drive to it (steering on the bearing), turn to the
    goal's heading. Options (keyword-only): max_speed_m_s (app. D: 0.25), max_yaw_rate_rad_s,
    gain (1/s, on distance and on heading), position_tolerance_m, yaw_tolerance_rad."""

    def __init__(self, goal_xy: ArrayLike, goal_yaw: float, *, max_speed_m_s: float = 0.2,
                 max_yaw_rate_rad_s: float = 0.6, gain: float = 1.5,
                 position_tolerance_m: float = 0.02, yaw_tolerance_rad: float = 0.02) -> None:
        g = np.asarray(goal_xy, float)
        if g.shape != (2,) or not np.all(np.isfinite(g)) or not math.isfinite(goal_yaw):
            raise InsertionError('goal must be a finite (x, y) and heading')
        for name, v in (('max_speed_m_s', max_speed_m_s), ('max_yaw_rate_rad_s',
                        max_yaw_rate_rad_s), ('gain', gain), ('position_tolerance_m',
                        position_tolerance_m), ('yaw_tolerance_rad', yaw_tolerance_rad)):
            if not (math.isfinite(v) and v > 0):
                raise InsertionError(f'{name} must be finite and > 0, got {v}')
        self.goal = g
        self.goal_yaw = float(goal_yaw)
        self.v_max, self.w_max, self.k = max_speed_m_s, max_yaw_rate_rad_s, gain
        self.tol_p, self.tol_yaw = position_tolerance_m, yaw_tolerance_rad
        self.stage = Stage.FACE

    def command(self, x: float, y: float, yaw: float) -> DriveCommand:
        d = self.goal - np.array([x, y])
        dist = float(np.hypot(*d))
        if self.stage != Stage.TURN and dist <= self.tol_p:
            self.stage = Stage.TURN
        if self.stage == Stage.TURN:
            e = wrap(self.goal_yaw - yaw)
            if abs(e) <= self.tol_yaw:
                return DriveCommand(0.0, 0.0, True, Stage.ARRIVED)
            return DriveCommand(0.0, float(np.clip(self.k * e, -self.w_max, self.w_max)),
                                False, Stage.TURN)
        bearing = math.atan2(d[1], d[0])
        e = wrap(bearing - yaw)
        if self.stage == Stage.FACE:
            if abs(e) <= 0.05:
                self.stage = Stage.DRIVE
            else:
                return DriveCommand(0.0, float(np.clip(self.k * e, -self.w_max, self.w_max)),
                                    False, Stage.FACE)
        v = float(np.clip(self.k * dist * max(0.0, math.cos(e)), 0.0, self.v_max))
        w = float(np.clip(2 * self.k * e, -self.w_max, self.w_max))
        return DriveCommand(v, w, False, Stage.DRIVE)


class FollowPath:
    """Drive through waypoints (map xy) on odometry: turn on the spot while the bearing to the
    next one is off by more than `turn_above_rad`, else drive with a proportional heading
    correction; intermediate waypoints count as passed within `pass_m`, the last within
    `position_tolerance_m`, then (if given) turn to `final_yaw`."""

    def __init__(self, waypoints: ArrayLike, final_yaw: float | None = None, *,
                 max_speed_m_s: float = 0.2, max_yaw_rate_rad_s: float = 0.8,
                 turn_above_rad: float = math.radians(20), pass_m: float = 0.25,
                 position_tolerance_m: float = 0.08, yaw_tolerance_rad: float = 0.05) -> None:
        w = np.asarray(waypoints, float).reshape(-1, 2)
        if not len(w) or not np.all(np.isfinite(w)):
            raise InsertionError('a path needs at least one finite (x, y) waypoint')
        if final_yaw is not None and not math.isfinite(final_yaw):
            raise InsertionError('final_yaw must be finite')
        self.todo = list(w)
        self.final_yaw = final_yaw
        self.v_max, self.w_max = max_speed_m_s, max_yaw_rate_rad_s
        self.turn_above, self.pass_m = turn_above_rad, pass_m
        self.tol_p, self.tol_yaw = position_tolerance_m, yaw_tolerance_rad

    def command(self, x: float, y: float, yaw: float) -> DriveCommand:
        xy = np.array([x, y])
        while self.todo and np.linalg.norm(self.todo[0] - xy) < (
                self.tol_p if len(self.todo) == 1 else self.pass_m):
            self.todo.pop(0)
        if not self.todo:
            if self.final_yaw is None:
                return DriveCommand(0.0, 0.0, True, Stage.ARRIVED)
            e = wrap(self.final_yaw - yaw)
            if abs(e) <= self.tol_yaw:
                return DriveCommand(0.0, 0.0, True, Stage.ARRIVED)
            return DriveCommand(0.0, float(np.clip(1.5 * e, -self.w_max, self.w_max)), False,
                                Stage.TURN)
        d = self.todo[0] - xy
        e = wrap(math.atan2(d[1], d[0]) - yaw)
        if abs(e) > self.turn_above:
            return DriveCommand(0.0, float(np.clip(2.5 * e, -self.w_max, self.w_max)), False,
                                Stage.FACE)
        dist = float(np.linalg.norm(d)) + self.pass_m * (len(self.todo) - 1)
        v = min(self.v_max, 0.8 * dist + 0.05)
        return DriveCommand(v, float(np.clip(2.0 * e, -self.w_max, self.w_max)), False,
                            Stage.DRIVE)


def path_length(points: ArrayLike) -> float:
    """Length (m) of the polyline through `points` (n x 2)."""
    p = np.asarray(points, float).reshape(-1, 2)
    return float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1))) if len(p) > 1 else 0.0


class DriveEnd(StrEnum):
    """How a drive goal ended on its own (a cancel or a newer goal is the caller's)."""

    ARRIVED = 'arrived'
    TIMEOUT = 'timeout'


@dataclass(frozen=True)
class DriveStep:
    """One step of a drive goal: the twist to send, the path left (m), and the end if this
    step ended the goal (the twist is then a stop)."""

    command: DriveCommand
    remaining_m: float
    end: DriveEnd | None


class Drive:
    """One drive goal on odometry: FollowPath through `waypoints` (map xy; the last is the
    goal) to `final_yaw` (None: any heading), from `start_xy` at time `start_s`, ended by
    arrival or by the time limit: `time_limit_s` if > 0, else `time_margin_s` plus
    `time_slack` times the path's length at `max_speed_m_s`. `step` takes the odometry's pose
    at time `t_s` (the same clock as start_s)."""

    def __init__(self, start_xy: ArrayLike, waypoints: ArrayLike, final_yaw: float | None, *,
                 start_s: float, max_speed_m_s: float = 0.2, max_yaw_rate_rad_s: float = 0.8,
                 position_tolerance_m: float = 0.08, yaw_tolerance_rad: float = 0.05,
                 time_limit_s: float = 0.0, time_margin_s: float = 30.0,
                 time_slack: float = 3.0) -> None:
        start = np.asarray(start_xy, float)
        if start.shape != (2,) or not np.all(np.isfinite(start)) or not math.isfinite(start_s):
            raise InsertionError('a drive starts from a finite (x, y) at a finite time')
        for name, v in (('max_speed_m_s', max_speed_m_s), ('time_margin_s', time_margin_s),
                        ('time_slack', time_slack)):
            if not (math.isfinite(v) and v > 0):
                raise InsertionError(f'{name} must be finite and > 0, got {v}')
        if not (math.isfinite(time_limit_s) and time_limit_s >= 0):
            raise InsertionError(f'time_limit_s must be finite and >= 0, got {time_limit_s}')
        self.follow = FollowPath(waypoints, final_yaw, max_speed_m_s=max_speed_m_s,
                                 max_yaw_rate_rad_s=max_yaw_rate_rad_s,
                                 position_tolerance_m=position_tolerance_m,
                                 yaw_tolerance_rad=yaw_tolerance_rad)
        self.length_m = path_length(np.vstack([start, *self.follow.todo]))
        self.limit_s = time_limit_s or time_margin_s + time_slack * self.length_m / max_speed_m_s
        self.start_s = float(start_s)
        self.end: DriveEnd | None = None

    def remaining(self, x: float, y: float) -> float:
        """The path left from (x, y): to the next waypoint, then along the rest."""
        todo = self.follow.todo
        return path_length(np.vstack([[x, y], *todo])) if todo else 0.0

    def step(self, x: float, y: float, yaw: float, t_s: float) -> DriveStep:
        if self.end is not None:
            return DriveStep(DriveCommand(0.0, 0.0, self.end is DriveEnd.ARRIVED,
                                          Stage.ARRIVED), self.remaining(x, y), None)
        c = self.follow.command(x, y, yaw)
        if c.arrived:
            self.end = DriveEnd.ARRIVED
        elif t_s - self.start_s > self.limit_s:
            self.end = DriveEnd.TIMEOUT
            c = DriveCommand(0.0, 0.0, False, c.stage)
        return DriveStep(c, self.remaining(x, y), self.end)


@dataclass(frozen=True)
class GridSlice:
    """A 2-D occupancy grid (nav_msgs/OccupancyGrid's convention): `occupancy` rows along y,
    columns along x, -1 unknown, else 0-100 (%); cell (0, 0)'s corner at `origin_xy`, level."""

    occupancy: np.ndarray
    origin_xy: tuple[float, float]
    resolution_m: float

    def __post_init__(self) -> None:
        if self.occupancy.ndim != 2 or not (math.isfinite(self.resolution_m)
                                            and self.resolution_m > 0):
            raise InsertionError('a grid slice is a 2-D array with a resolution > 0')
        if not all(math.isfinite(v) for v in self.origin_xy):
            raise InsertionError('the grid slice origin must be finite')

    def occupied(self, xy: np.ndarray, threshold: int) -> np.ndarray:
        """For points (n x 2): in the grid and at or above `threshold` %."""
        ij = np.floor((np.asarray(xy, float) - self.origin_xy) / self.resolution_m).astype(int)
        h, w = self.occupancy.shape
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.zeros(len(ij), bool)
        out[inside] = self.occupancy[ij[inside, 1], ij[inside, 0]] >= threshold
        return out


def grid_slice_of(msg: Any) -> GridSlice:
    """A nav_msgs/OccupancyGrid message as a GridSlice; InsertionError for a grid that is
    rotated or whose data does not fill width x height."""
    info = msg.info
    q = info.origin.orientation
    if abs(yaw_of(q.x, q.y, q.z, q.w)) > 1e-6 or len(msg.data) != info.width * info.height:
        raise InsertionError('a rotated or ragged grid')
    return GridSlice(np.asarray(msg.data, np.int8).reshape(info.height, info.width),
                     (info.origin.position.x, info.origin.position.y), info.resolution)


@dataclass(frozen=True)
class Obstruction:
    """Why a path cannot be driven: a `point` of it (a waypoint or the goal, index `index`)
    in an occupied cell, or a `leg` (from point index-1 to index) crossing one at `xy`."""

    kind: Literal['point', 'leg']
    index: int
    xy: tuple[float, float]


def obstruction(points: ArrayLike, grid: GridSlice, *, threshold: int = 65,
                start_clear_m: float = 0.3) -> Obstruction | None:
    """The first obstruction of the path through `points` (n x 2, the first the rover's
    position) on `grid`, or None. Cells within `start_clear_m` of the start are not counted
    (the rover itself, seen by the others' cameras); legs are sampled every half cell."""
    p = np.asarray(points, float).reshape(-1, 2)
    if len(p) < 2 or not np.all(np.isfinite(p)):
        raise InsertionError('a path is a start and at least one finite (x, y) point')
    clear = np.linalg.norm(p - p[0], axis=1) <= start_clear_m
    hit = grid.occupied(p, threshold) & ~clear
    for i in range(1, len(p)):
        if hit[i]:
            return Obstruction('point', i, (float(p[i, 0]), float(p[i, 1])))
        n = max(2, math.ceil(2 * np.linalg.norm(p[i] - p[i - 1]) / grid.resolution_m) + 1)
        s = p[i - 1] + np.linspace(0.0, 1.0, n)[:, None] * (p[i] - p[i - 1])
        bad = grid.occupied(s, threshold) & (np.linalg.norm(s - p[0], axis=1) > start_clear_m)
        if np.any(bad):
            k = int(np.argmax(bad))
            return Obstruction('leg', i, (float(s[k, 0]), float(s[k, 1])))
    return None
