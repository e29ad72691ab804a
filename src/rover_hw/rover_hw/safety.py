"""The bridge's safety rules, no rclpy: command watchdog, device heartbeat, latched e-stop and
command limits. Time comes from an injectable clock (seconds), so tests drive it by hand."""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from coop_common.rover_geometry import (
    ARM_JOINTS,
    ARM_LIMITS_RAD,
    MAST_JOINTS,
    MAST_TILT_LIMITS_RAD,
)

from .errors import HardwareError

WHEEL_NAMES = ('wheel_fl', 'wheel_fr', 'wheel_rl', 'wheel_rr')


class CommandRefused(HardwareError):
    """A command the bridge will not pass on; the message is the reason."""


@dataclass(frozen=True)
class Limits:
    """Joint ranges (rad), speeds and duty the bridge lets through (app. D rover)."""

    joints: tuple[tuple[str, float, float], ...] = (
        *((n, lo, hi) for n, (lo, hi) in zip(ARM_JOINTS, ARM_LIMITS_RAD, strict=False)),
        (MAST_JOINTS[0], -3.1, 3.1), (MAST_JOINTS[1], *MAST_TILT_LIMITS_RAD))
    max_linear_m_s: float = 0.25
    max_yaw_rad_s: float = 1.0
    max_pwm: float = 1.0
    track_m: float = 0.30
    wheel_radius_m: float = 0.06

    def joint_range(self, name: str) -> tuple[float, float]:
        for n, lo, hi in self.joints:
            if n == name:
                return lo, hi
        raise CommandRefused(f'unknown joint {name!r}')


def check_trajectory(names: Sequence[str], positions: Sequence[Sequence[float]],
                     known: Sequence[str], limits: Limits) -> None:
    """CommandRefused unless every joint is known, once, and every position finite and in
    range."""
    if not names or len(set(names)) != len(names):
        raise CommandRefused(f'joint names empty or repeated: {list(names)}')
    unknown = [n for n in names if n not in known]
    if unknown:
        raise CommandRefused(f'unknown joints {unknown} (expected a subset of {list(known)})')
    for point in positions:
        if len(point) != len(names):
            raise CommandRefused(f'{len(point)} positions for {len(names)} joints')
        for n, q in zip(names, point, strict=False):
            if not math.isfinite(q):
                raise CommandRefused(f'{n}: position {q} is not finite')
            lo, hi = limits.joint_range(n)
            if not lo <= q <= hi:
                raise CommandRefused(f'{n}: {q:.3f} rad beyond [{lo:g}, {hi:g}]')


def twist_to_wheels(v: float, w: float, limits: Limits) -> tuple[float, float, float, float]:
    """Skid-steer wheel speeds (fl, fr, rl, rr) in rad/s for body speed v (m/s) and yaw rate w
    (rad/s), clipped to the rover's speed limits (as rover_sim does). NaN is refused."""
    if not (math.isfinite(v) and math.isfinite(w)):
        raise CommandRefused(f'cmd_vel ({v}, {w}) is not finite')
    v = max(-limits.max_linear_m_s, min(limits.max_linear_m_s, v))
    w = max(-limits.max_yaw_rad_s, min(limits.max_yaw_rad_s, w))
    left = (v - 0.5 * limits.track_m * w) / limits.wheel_radius_m
    right = (v + 0.5 * limits.track_m * w) / limits.wheel_radius_m
    return (left, right, left, right)


def wheels_to_twist(wheels: Sequence[float], limits: Limits) -> tuple[float, float]:
    """Body speed and yaw rate from the four wheel speeds (rad/s): skid-steer odometry."""
    left = 0.5 * (wheels[0] + wheels[2]) * limits.wheel_radius_m
    right = 0.5 * (wheels[1] + wheels[3]) * limits.wheel_radius_m
    return 0.5 * (left + right), (right - left) / limits.track_m


class Safety:
    """Who may move: a stop always wins.

    * e-stop: latched by `engage_estop` until `clear_estop`;
    * device heartbeat: every motor stops when none came within `heartbeat_timeout_s`;
    * command watchdog: the wheels stop when no drive command came within
      `command_timeout_s` (the arm and mast hold their last set-points; their trajectories are
      commanded once and run for seconds);
    * fault: the link is down or a transition left the bridge inactive (`set_fault`).
    """

    def __init__(self, *, command_timeout_s: float, heartbeat_timeout_s: float,
                 clock: Callable[[], float]) -> None:
        if not (command_timeout_s > 0 and heartbeat_timeout_s > 0):
            raise ValueError('timeouts must be > 0')
        self.command_timeout_s = command_timeout_s
        self.heartbeat_timeout_s = heartbeat_timeout_s
        self._clock = clock
        self._last_cmd = -math.inf
        self._last_heartbeat = -math.inf
        self._estop = False
        self.estop_reason = ''
        self._fault = 'not started'

    def drive_command(self) -> None:
        self._last_cmd = self._clock()

    def heartbeat(self) -> None:
        self._last_heartbeat = self._clock()

    def engage_estop(self, reason: str = 'e-stop') -> None:
        self._estop = True
        self.estop_reason = reason

    def clear_estop(self) -> None:
        self._estop = False
        self.estop_reason = ''

    @property
    def estopped(self) -> bool:
        return self._estop

    def set_fault(self, reason: str | None) -> None:
        """A reason stops everything until `set_fault(None)`."""
        self._fault = reason or ''

    def motors_stop_reason(self) -> str:
        """Why no motor may move now ('' : they may)."""
        if self._estop:
            return f'e-stop latched ({self.estop_reason})'
        if self._fault:
            return self._fault
        if self._clock() - self._last_heartbeat > self.heartbeat_timeout_s:
            return 'no device heartbeat'
        return ''

    def drive_stop_reason(self) -> str:
        """Why the wheels must stand ('' : they may follow the last drive command)."""
        why = self.motors_stop_reason()
        if why:
            return why
        if self._clock() - self._last_cmd > self.command_timeout_s:
            return 'command timeout'
        return ''
