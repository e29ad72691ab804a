"""Driving a skid-steer rover to a pose on its odometry (turn, drive, turn; or through
waypoints). No rclpy here."""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike

from .errors import InsertionError

__all__ = ['DriveCommand', 'FollowPath', 'GoToPose', 'Stage', 'wrap']


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
