"""Node `identifier`: on-line identification of this rover's base dynamics (thesis ch. 2).

Thin wrapper over coop_id.identifier_core.Identifier. Subscribes to the rover's `imu`,
`inclinometer`, `arm/wrench` (and `joint_states` for the arm's current pose), drives the arm
excitation on `arm/joint_command` while an `identify` action goal runs, publishes the latched
`dynamic_parameters`. Run under the rover's namespace: `--ros-args -r __ns:=/rover1`.
Time base: the sensor stamps (sim time, wall time or a replayed bag alike).
"""
from __future__ import annotations

import math
import time

import numpy as np
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import WrenchStamped
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import Imu, JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.dynparams import PARAM_NAMES
from coop_common.frames import FRAME_PARAMS, RoverFrames, check_frame_params
from coop_common.lockstep_node import Lockstep
from coop_common.node_util import (
    BadInputCounter,
    ParamSpec,
    declare_parameters,
    run_node,
)
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS, with_depth
from coop_msgs.action import Identify
from coop_msgs.msg import DynamicParameters, Inclinometer

from .excitation import STRATEGIES, ArmReference, Excitation, Strategy
from .identifier_core import Identifier, IdentifierConfig
from .offline import FT_FORCE_LIMIT_N, FT_TORQUE_LIMIT_NM, SYNC_TOLERANCE_S, sensor_noise
from .pairing import QUEUE_S, SamplePairer, stamp_ns

#: Arm base joints and the three rotation modes of §2.2: (joint driven, (joint1, joint2) hold).
MODES = (('arm_joint_1', 0.0, None), ('arm_joint_2', 0.0, None),
         ('arm_joint_2', math.pi / 2, None))   # about z, about y, about x (joint 1 = pi/2)

#: Spacing of the arm trajectory points (>= 20 points per period up to 30 rad/s).
TRAJECTORY_STEP_S = 0.01
#: Seconds of samples each sensor subscription queues (its depth at rate_hz): the largest
#: lag behind the clock the node catches up from, and makes up for in its arm commands
SAMPLE_QUEUE_S = 10.0

SPECS = {
    'strategy': ParamSpec(Strategy.INFORMATION.value, 'default excitation strategy (goal may '
                          'override)', choices=STRATEGIES),
    'rate_hz': ParamSpec(200.0, 'sensor sample rate the filters are designed for',
                         lo=20.0, hi=2000.0, read_only=True),
    'window_s': ParamSpec(0.4, 'information / excitation re-optimisation period (§2.6.1)',
                          lo=0.1, hi=5.0, read_only=True),
    'decimation': ParamSpec(4, 'filter update every N-th sample', lo=1, hi=50, read_only=True),
    'information_bits': ParamSpec(10, 'n of the n-bit information metric (Eq. 2-12)',
                                  lo=2, hi=16, read_only=True),
    'use_accelerometer': ParamSpec(True, 'false: rotational subset only (§2.6.2)',
                                   read_only=True),
    'drift_per_s': ParamSpec(0.0, 'random walk of the drifting parameters (the mass: a rock '
                             'picked up), fraction of range per sqrt(s); 0 = fixed',
                             lo=0.0, hi=1.0, read_only=True),
    'mode_period_s': ParamSpec(2.0, 'seconds per arm rotation mode (z, y, x cycle)',
                               lo=0.4, hi=60.0),
    'command_lead_s': ParamSpec(0.3, 'a new arm trajectory departs from the old one this long '
                                'after the last sample (covers processing + transport delay), '
                                'plus the lag of the samples behind the clock',
                                lo=0.0, hi=2.0),
    'sync_tolerance_s': ParamSpec(SYNC_TOLERANCE_S, 'max stamp difference when pairing '
                                  'sensors (below half the sample period)', lo=0.0005, hi=0.1),
    'stale_timeout_s': ParamSpec(0.1, 'a sensor silent this long stops the sample stream',
                                 lo=0.01, hi=10.0),
    'silence_abort_s': ParamSpec(30.0, 'a running goal is aborted after this long (wall '
                                 'clock) without a paired sample (0 = wait for ever)',
                                 lo=0.0, hi=3600.0),
    'ft_force_limit_n': ParamSpec(FT_FORCE_LIMIT_N, 'F/T force saturation (samples beyond '
                                  'are skipped)', lo=1.0, hi=1e4),
    'ft_torque_limit_nm': ParamSpec(FT_TORQUE_LIMIT_NM, 'F/T torque saturation', lo=0.1, hi=1e4),
    'ft_force_noise_std_n': ParamSpec(0.0, 'F/T force noise 1-sigma (datasheet; WrenchStamped '
                                      'has no covariance); 0 = unknown', lo=0.0, hi=100.0),
    'inclinometer_weight': ParamSpec(0.0, 'share of the inclinometer in the roll/pitch angle '
                                     '(rest: integrated gyro); 0: its step is coarser than the '
                                     'dynamic tilt (10 bits over +-20 deg, app. D)',
                                     lo=0.0, hi=1.0, read_only=True),
    'bias_compensation': ParamSpec(True, 'remove the errors-in-variables bias using the sensor '
                                   'noise covariances of the messages', read_only=True),
    'base_frame': ParamSpec('', "frame id of the estimates; empty: "
                            "'<frame_prefix><rover>/base_link' with <rover> the last part of "
                            "the node's namespace", read_only=True),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'lockstep': ParamSpec(False, "answer rover_sim's lockstep rounds (a participant in its "
                          'lockstep_participants; remap sim/lockstep/tick and ack to the '
                          "simulator's): each round's samples, then the arm's commands, so the "
                          'excitation does not depend on load', read_only=True),
}


class IdentifierNode(Node):
    """The identifier: pairs the rover's IMU, inclinometer and F/T samples, excites its arm and
    estimates the base's dynamic parameters (the Identify action)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('identifier', **kwargs)
        self.p = declare_parameters(self, SPECS, on_change=self._on_change,
                                    check_all=check_frame_params)
        self.base_frame = self.p['base_frame'] or RoverFrames.of_namespace(
            self.get_namespace(), self.p['frame_prefix']).base_link
        self.bad = BadInputCounter(self)
        # The sample stream: an IMU sample waits for its partners however the three streams
        # interleave (a replay's burst, DDS or callback latency), up to QUEUE_S of samples
        self.pairer = SamplePairer(
            int(QUEUE_S * self.p['rate_hz']), tolerance_ns=_ns(self.p['sync_tolerance_s']),
            force_limit=self.p['ft_force_limit_n'], torque_limit=self.p['ft_torque_limit_nm'],
            on_sample=lambda t, row: self._on_sample(1e-9 * t, row), on_reject=self.bad.reject,
            on_reset=self._on_time_reset)
        self._time_reset = False   # sensor time jumped back during the running goal
        self._buffer: list[tuple[float, np.ndarray]] = []
        self._last_sample: tuple[float, np.ndarray] | None = None
        self.ident: Identifier | None = None
        self._current_exc: Excitation | None = None
        self._active = False       # samples go to the running goal's estimator
        self._busy = False         # a goal is accepted or running
        self._wake: Future | None = None    # the running goal awaits it (window done, poke)
        self._t0 = None
        # the running goal's stamp: its excitation starts with the first sample after it (in
        # lockstep a goal and the round it was given in can reach the node in either order)
        self._goal_stamp = -math.inf
        self._t_now = 0.0
        self._t_estimate = 0.0     # stamp of the last sample in the estimate
        self._windows = 0
        self._exc_t0 = 0.0
        self._ref = ArmReference(MODES)
        # best effort as the publishers, but a deep queue: a window's processing (the excitation
        # optimisation), or a loaded machine that starves this process, must not drop the
        # samples that arrive meanwhile
        # In lockstep (docs/design.md) each round's samples are handed over before the round is
        # answered, and the arm's commands act in the next round, on an idle or a busy machine
        deep = with_depth(SENSOR_QOS, int(SAMPLE_QUEUE_S * self.p['rate_hz']))
        self.ls = Lockstep(self, self.p['lockstep'])
        # in lockstep the running goal looks at every round's end (whether its time is up), so
        # it ends at the same round on any machine, not at whichever one a wall-clock poke hits
        self.ls.on_round(self._poke)
        self.ls.subscription(Imu, 'imu', self._on_imu, deep)
        self.ls.subscription(Inclinometer, 'inclinometer', self._on_incl, deep)
        self.ls.subscription(WrenchStamped, 'arm/wrench', self._on_wrench, deep)
        # only the latest joint positions matter (the pose an excitation starts from): a
        # backlog of them would only cost callbacks
        self.ls.subscription(JointState, 'joint_states', self._on_joints,
                             with_depth(SENSOR_QOS, 1))
        self.pub_params = self.create_publisher(DynamicParameters, 'dynamic_parameters',
                                                LATCHED_QOS)
        self.pub_cmd = self.ls.publisher(JointTrajectory, 'arm/joint_command', COMMAND_QOS)
        # One thread runs every callback, in arrival order (the pairing needs each stream in
        # stamp order): the goal is a coroutine that awaits windows; a steady-clock timer wakes
        # it to see a cancel or a silent stream when no window comes (sim time may stand still).
        self._action = ActionServer(
            self, Identify, '~/identify', execute_callback=self._execute,
            goal_callback=self._on_goal, cancel_callback=lambda _g: CancelResponse.ACCEPT)
        self.create_timer(0.5, self._poke, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.joint_positions: dict[str, float] = {}
        self._noise_var = {'acc': np.zeros(3), 'gyro': np.zeros(3), 'incl': np.zeros(2)}
        self.get_logger().info('identifier ready (action ~/identify)')

    # -- parameters ----------------------------------------------------------------------------
    def _on_change(self, changed: dict) -> None:
        self.p.update(changed)
        self.pairer.tolerance_ns = _ns(self.p['sync_tolerance_s'])
        self.pairer.force_limit = self.p['ft_force_limit_n']
        self.pairer.torque_limit = self.p['ft_torque_limit_nm']

    # -- sensors -------------------------------------------------------------------------------
    def _on_imu(self, msg: Imu) -> None:
        a, w = msg.linear_acceleration, msg.angular_velocity
        if self.pairer.imu(stamp_ns(msg.header), [a.x, a.y, a.z], [w.x, w.y, w.z]):
            self._noise_var['acc'] = np.array(msg.linear_acceleration_covariance)[[0, 4, 8]]
            self._noise_var['gyro'] = np.array(msg.angular_velocity_covariance)[[0, 4, 8]]

    def _on_incl(self, msg: Inclinometer) -> None:
        if self.pairer.inclinometer(stamp_ns(msg.header), msg.roll, msg.pitch, msg.saturated):
            self._noise_var['incl'] = np.array([msg.roll_variance, msg.pitch_variance])

    def _on_wrench(self, msg: WrenchStamped) -> None:
        f, n = msg.wrench.force, msg.wrench.torque
        self.pairer.wrench(stamp_ns(msg.header), [f.x, f.y, f.z], [n.x, n.y, n.z])

    def _on_joints(self, msg: JointState) -> None:
        for name, pos in zip(msg.name, msg.position, strict=False):
            if math.isfinite(pos):
                self.joint_positions[name] = pos

    def _on_sample(self, t: float, row: np.ndarray) -> None:
        if not self._active or self.ident is None or t <= self._goal_stamp:
            return
        last = self._last_sample
        if last is not None and t - last[0] > self.p['stale_timeout_s']:
            self.bad.reject('gap in sample stream', f'{t - last[0]:.3f} s')
        elif last is not None:
            # The filter bank assumes a uniform sample stream (its integrators would lose the
            # missing samples' area): fill a short gap of lost (best-effort) samples linearly.
            missing = round((t - last[0]) * self.p['rate_hz']) - 1
            for j in range(1, missing + 1):
                u = j / (missing + 1)
                self._buffer.append((last[0] + u * (t - last[0]), (1 - u) * last[1] + u * row))
            if missing > 0:
                self.bad.reject('lost samples filled', f'{missing}')
        self._last_sample = (t, row)
        self._buffer.append((t, row))
        self._t_now = t
        if self._t0 is None:   # first sample of a goal: the rover is at rest, start the arm
            self._t0 = t
            self._exc_t0 = t
            self._command_arm()
        per_window = round(self.p['window_s'] * self.p['rate_hz'])
        if len(self._buffer) >= per_window + (1 if self._windows == 0 else 0):
            self._process_window()

    def _process_window(self) -> None:
        data = np.stack([r for _, r in self._buffer])
        self._t_estimate = self._buffer[-1][0]
        self._buffer.clear()
        ident = self.ident
        ident.add_samples(0, specific_force=data[:, 0:3], gyro=data[:, 3:6], incl=data[:, 6:8],
                          force=data[:, 8:11], torque=data[:, 11:14])
        ident.end_window()
        self._windows += 1
        self._publish_estimate()
        if ident.excitation is not self._current_exc:
            self._current_exc = ident.excitation
            self._exc_t0 = self._t_now
        self._command_arm()
        self._poke()

    def _on_time_reset(self, old_ns: int, new_ns: int) -> None:
        self.get_logger().warn(f'sensor time jumped back from {old_ns * 1e-9:.3f} s to '
                               f'{new_ns * 1e-9:.3f} s: pairing starts over'
                               + (', the running identification is aborted'
                                  if self._active else ''))
        if self._active:
            self._time_reset = True
            self._poke()

    def _poke(self) -> None:
        """Resume the goal coroutine awaiting the next window (if one runs)."""
        wake = self._wake
        if wake is not None and not wake.done():
            wake.set_result(None)
            if self.executor is not None:
                self.executor.wake()    # resume it now, not at the next message

    # -- outputs -------------------------------------------------------------------------------
    def _estimate_msg(self) -> DynamicParameters:
        rep = self.ident.report
        msg = DynamicParameters()
        # stamped with the data instant it holds for (the last sample absorbed: sensor time,
        # the same live, on sim time and on a replayed bag), the clock only before any window
        if self._windows:
            msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(
                round(self._t_estimate * 1e9), 10**9)
        else:
            msg.header.stamp = self.get_clock().now().to_msg()
        msg.header.frame_id = self.base_frame
        msg.names = list(PARAM_NAMES)
        msg.values = rep.values.tolist()
        msg.std_devs = rep.std.tolist()
        msg.ci95_low = rep.ci_low.tolist()
        msg.ci95_high = rep.ci_high.tolist()
        msg.information_bits = rep.information_bits.tolist()
        msg.observable = [bool(o) for o in rep.observable]
        msg.max_information_bits = float(self.ident.cfg.bits)
        msg.physically_consistent = bool(rep.consistent)
        msg.strategy = self.ident.cfg.strategy.value
        exc = self.ident.excitation
        msg.excitation_amplitude_rad = float(exc.amplitude_rad)
        msg.excitation_frequency_rad_s = float(exc.frequency_rad_s)
        msg.excitation_offset_rad = float(exc.offset_rad)
        msg.samples = int(self.ident.samples)
        msg.rejected_samples = int(self.bad.total)
        return msg

    def _publish_estimate(self) -> None:
        self.pub_params.publish(self._estimate_msg())

    def _command_arm(self) -> None:
        """Send the next window (+ margin) of f(t) for the current rotation mode.

        A new mode or excitation never steps the command: the arm blends from the trajectory
        it follows into the new one with a quintic smoothstep, slow enough for the joint speed
        limit. (A step makes the effort-limited PD whip the arm at tens of rad/s: base loads of
        ~100 N for a few ms, far outside the small-motion model of Eq. 2-1.)"""
        now = self._t_now
        mode = int((now - self._t0) // self.p['mode_period_s']) % 3
        exc: Excitation = self._current_exc
        # A node that has fallen behind its sample stream (a loaded machine: the samples wait
        # in the queue) commands from a past instant. The new reference leaves the old one only
        # after the arm can have it (lead + lag), and reaches as far past the present as ever:
        # otherwise the arm holds at the old command's last point, and then jumps to the new
        # one (a whip, far outside the model) when it comes.
        lag = self._lag()
        horizon = 3.0 * self.p['window_s'] + lag     # margin for a late next window
        self._ref.update(now, mode, exc, self._exc_t0, self._joints_here(), horizon,
                         lead_s=self.p['command_lead_s'] + lag)
        self._send_reference(now, horizon)

    def _lag(self) -> float:
        """Seconds the last sample absorbed lies behind the node's clock (sim time on
        use_sim_time), capped at SAMPLE_QUEUE_S; 0 where the clock is not the sensors' time base
        (ahead of it, or further behind than any queue)."""
        lag = self.ls.now_s(lambda: self.get_clock().now().nanoseconds * 1e-9) - self._t_now
        if not 0.0 < lag < SAMPLE_QUEUE_S:
            return 0.0
        if lag > self.p['command_lead_s']:
            self.get_logger().warn(f'the samples lag the clock by {lag:.2f} s (more than '
                                   f'command_lead_s): arm commands lead by that much more',
                                   throttle_duration_sec=5.0)
        return lag

    def _stop_arm(self) -> None:
        """At a goal's end: blend the arm from its excitation into standing still at the pose
        it started from (ArmReference.rest); the trajectory's last point holds it there."""
        if self._t0 is None:
            return                              # never commanded
        now = self._t_now
        t_rest = self._ref.rest(now, self._joints_here(),
                                lead_s=self.p['command_lead_s'] + self._lag())
        self._send_reference(now, t_rest - now + 2 * TRAJECTORY_STEP_S)

    def _joints_here(self) -> np.ndarray:
        return np.array([self.joint_positions.get('arm_joint_1', 0.0),
                         self.joint_positions.get('arm_joint_2', 0.0)])

    def _send_reference(self, now: float, horizon: float) -> None:
        """Publish self._ref from about `now` to `horizon` s later."""
        traj = JointTrajectory()
        # The controller interpolates the points linearly and takes the segment slopes as speed
        # references. Points on one global time grid (every trajectory starts at the grid point
        # at or before the last sample, stamped with that sim time) make a new trajectory
        # repeat the segment the arm is on: no speed step when it replaces the old one, however
        # late it arrives (processing + transport delay), and no shift of the reference in time.
        # The grid sits half a sample period off the sample instants: the controller reads its
        # target at its control instants, which must never fall on a point (where rounding
        # picks either segment).
        step, off = TRAJECTORY_STEP_S, 0.5 / self.p['rate_hz']
        g0 = math.floor((now - off) / step) * step + off
        traj.header.stamp.sec, traj.header.stamp.nanosec = divmod(round(g0 * 1e9), 10**9)
        traj.joint_names = ['arm_joint_1', 'arm_joint_2']
        for k in range(int(horizon / step) + 2):
            tk = k * step
            q, qd = self._ref(g0 + tk)
            pt = JointTrajectoryPoint()
            pt.positions = [float(v) for v in q]
            pt.velocities = [float(v) for v in qd]
            sec, nsec = divmod(round(tk * 1e9), 10**9)
            pt.time_from_start = Duration(sec=sec, nanosec=nsec)
            traj.points.append(pt)
        self.pub_cmd.publish(traj)

    # -- action --------------------------------------------------------------------------------
    def _on_goal(self, goal: Identify.Goal) -> GoalResponse:
        strategy = goal.strategy or self.p['strategy']
        if strategy not in STRATEGIES:
            self.get_logger().warn(f'rejected goal: strategy {goal.strategy!r} is not one of '
                                   f'{[s.value for s in Strategy]}')
            return GoalResponse.REJECT
        if not (0 < goal.duration_s <= 3600):
            self.get_logger().warn(f'rejected goal: duration {goal.duration_s} s is not in '
                                   '(0, 3600]')
            return GoalResponse.REJECT
        if self._busy:
            self.get_logger().warn('rejected goal: an identification is running')
            return GoalResponse.REJECT
        self._busy = True      # from acceptance on: a second goal cannot slip in before it runs
        return GoalResponse.ACCEPT

    def _sensor_noise(self) -> dict | None:
        """Sensor noise sigmas from the message covariances (datasheet values), for the
        errors-in-variables correction; None when not enabled or not published."""
        if not self.p['bias_compensation']:
            return None
        v = self._noise_var
        return sensor_noise(v['acc'], v['gyro'], v['incl'], self.p['ft_force_noise_std_n'])

    async def _execute(self, handle) -> Identify.Result:
        try:
            return await self._identify(handle)
        finally:
            self._active = False
            self._busy = False
            self._wake = None

    async def _identify(self, handle) -> Identify.Result:
        goal = handle.request
        cfg = identifier_config(self.p, goal.strategy or self.p['strategy'])
        self.ident = Identifier(cfg, sensor_noise=self._sensor_noise())
        self._current_exc = self.ident.excitation
        self._buffer.clear()
        self._last_sample = None
        self._t0 = None
        self._windows = 0
        self._ref = ArmReference(MODES)
        given = goal.stamp.sec + 1e-9 * goal.stamp.nanosec
        self._goal_stamp = given if given > 0 else -math.inf
        self.get_logger().info(f'identifying with {cfg.strategy} for {goal.duration_s} s')
        self._active = True
        self._time_reset = False
        result = Identify.Result()
        last_t, last_wall = None, time.monotonic()
        while True:
            self._wake = Future()
            await self._wake
            silent = 0.0
            if self._t_now != last_t:
                last_t, last_wall = self._t_now, time.monotonic()
            else:
                silent = time.monotonic() - last_wall
                if silent > max(1.0, 10 * self.p['stale_timeout_s']):
                    self.get_logger().warn(f'no paired sensor samples for {silent:.1f} s',
                                           throttle_duration_sec=5.0)
            if handle.is_cancel_requested:
                handle.canceled()
                result.success, result.message = False, 'canceled'
                break
            abort = self.p['silence_abort_s']
            if self._time_reset or (abort > 0 and silent > abort):
                handle.abort()
                result.success = False
                result.message = ('aborted: sensor time jumped back' if self._time_reset else
                                  f'aborted: no paired sensor samples for {silent:.1f} s')
                break
            elapsed = 0.0 if self._t0 is None else self._t_now - self._t0
            if self._windows:
                fb = Identify.Feedback(estimate=self._estimate_msg(), elapsed_s=elapsed)
                handle.publish_feedback(fb)
            if elapsed >= goal.duration_s:
                handle.succeed()
                rep = self.ident.report
                result.success = True
                result.message = (f'{int(rep.observable.sum())}/22 observable, '
                                  f'{self.bad.total} rejected samples')
                break
        self._active = False
        if not self._time_reset:     # after a jump back (a sim reset) the arm has moved on
            self._stop_arm()
        result.estimate = self._estimate_msg()
        self.get_logger().info(f'identification done: {result.message}')
        return result


def identifier_config(p: dict, strategy: Strategy | str) -> IdentifierConfig:
    """The core's configuration from the node's parameters (`SPECS` names) and a strategy
    (a goal's or the parameter's string: the config takes it as the Strategy, IdentifierError
    naming them otherwise); `{k: s.default for k, s in SPECS.items()}` gives the node's
    defaults (offline replays)."""
    return IdentifierConfig(
        strategy=strategy, rate_hz=p['rate_hz'], window_s=p['window_s'],
        decimation=p['decimation'], bits=p['information_bits'],
        accelerometer=p['use_accelerometer'], drift_per_s=p['drift_per_s'],
        incl_weight=p['inclinometer_weight'])


def _ns(seconds: float) -> int:
    return round(seconds * 1e9)


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_id identifier`."""
    return run_node(IdentifierNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
