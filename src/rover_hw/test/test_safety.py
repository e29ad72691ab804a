"""Watchdog, heartbeat, e-stop and limits with a hand-driven clock."""
from __future__ import annotations

import math

import pytest

from rover_hw.safety import (
    CommandRefused,
    Limits,
    Safety,
    check_trajectory,
    twist_to_wheels,
    wheels_to_twist,
)


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def make(timeout=0.1, hb=0.3):
    clock = Clock()
    s = Safety(command_timeout_s=timeout, heartbeat_timeout_s=hb, clock=clock)
    s.set_fault(None)
    s.heartbeat()
    return s, clock


def test_command_watchdog_stops_wheels_within_the_timeout():
    s, clock = make(timeout=0.1)
    assert s.drive_stop_reason() == 'command timeout'     # no command yet
    s.drive_command()
    clock.t += 0.099
    assert s.drive_stop_reason() == ''
    clock.t += 0.002
    assert s.drive_stop_reason() == 'command timeout'
    assert s.motors_stop_reason() == ''                    # arm and mast may hold/move


def test_heartbeat_loss_stops_everything():
    s, clock = make(hb=0.3)
    s.drive_command()
    clock.t += 0.31
    s.drive_command()
    assert s.motors_stop_reason() == 'no device heartbeat'
    assert s.drive_stop_reason() == 'no device heartbeat'
    s.heartbeat()
    assert s.drive_stop_reason() == ''


def test_estop_latches_until_cleared_and_wins_over_commands():
    s, clock = make()
    s.engage_estop('test')
    for _ in range(10):
        clock.t += 0.01
        s.drive_command()
        s.heartbeat()
        assert s.drive_stop_reason().startswith('e-stop latched')
        assert s.motors_stop_reason().startswith('e-stop latched')
    s.clear_estop()
    assert s.drive_stop_reason() == ''


def test_fault_stops_until_cleared():
    s, _ = make()
    s.drive_command()
    s.set_fault('device unplugged')
    assert s.motors_stop_reason() == 'device unplugged'
    s.set_fault(None)
    assert s.motors_stop_reason() == ''


@pytest.mark.parametrize('names, pts, why', [
    (['arm_joint_1'], [[math.nan]], 'not finite'),
    (['arm_joint_9'], [[0.0]], 'unknown joints'),
    (['arm_joint_2'], [[2.5]], 'beyond'),
    (['arm_joint_1', 'arm_joint_1'], [[0.0, 0.0]], 'repeated'),
    (['arm_joint_1'], [[0.0, 1.0]], 'positions for'),
    (['mast_tilt'], [[0.0]], 'unknown joints'),
])
def test_bad_arm_commands_are_refused_with_a_reason(names, pts, why):
    arm = ('arm_joint_1', 'arm_joint_2', 'arm_joint_3', 'arm_joint_4')
    with pytest.raises(CommandRefused, match=why):
        check_trajectory(names, pts, arm, Limits())


def test_twist_clipped_to_limits_and_nan_refused():
    lim = Limits()
    fl, fr, rl, rr = twist_to_wheels(1.0, 0.0, lim)
    assert fl == pytest.approx(0.25 / 0.06) and fl == fr == rl == rr
    assert wheels_to_twist(twist_to_wheels(0.1, 0.5, lim), lim) == pytest.approx((0.1, 0.5))
    with pytest.raises(CommandRefused):
        twist_to_wheels(math.nan, 0.0, lim)
