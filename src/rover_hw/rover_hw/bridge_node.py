"""Lifecycle node `bridge`: one real rover (its on-board controller on a serial port) as the graph
sees rover_sim's rover: the same topics, types, frames and units, under the rover's namespace.

configure opens the port, activate publishes and drives, deactivate stops the motors and the
publishing, cleanup closes the port. A reader thread decodes the port and publishes as each
frame arrives (no executor hop in between); the executor runs the command timer, the command
subscriptions and the services. A stop always wins: see rover_hw.safety.
"""
from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from typing import assert_never

import numpy as np
import serial
from builtin_interfaces.msg import Time
from geometry_msgs.msg import PoseWithCovarianceStamped, Twist, WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from rclpy.lifecycle import Node as LifecycleNode
from rclpy.lifecycle import State, TransitionCallbackReturn
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu, JointState
from std_srvs.srv import SetBool
from trajectory_msgs.msg import JointTrajectory

from coop_common.frames import (
    FRAME_PARAMS,
    FrameError,
    RoverFrames,
    check_frame_params,
    mast_transforms,
    odom_transform,
    static_transforms,
)
from coop_common.node_util import (
    BadInputCounter,
    ParamSpec,
    declare_parameters,
    run_node,
)
from coop_common.qos import COMMAND_QOS, SENSOR_QOS
from coop_common.rover_geometry import (
    ARM_JOINTS,
    GROUP_JOINTS,
    MAST_JOINTS,
    JointGroup,
    camera_in_map,
)
from coop_common.tf_tree import TreeBroadcaster
from coop_msgs.msg import Inclinometer
from coop_msgs.srv import CalibrateInclinometer
from rover_sim.compliance import matrix_to_quat
from rover_sim.trajectory import JointTrajectoryFollower, TrajectoryError

from . import protocol as p
from .safety import (
    WHEEL_NAMES,
    CommandRefused,
    Limits,
    Safety,
    check_trajectory,
    twist_to_wheels,
    wheels_to_twist,
)

SEED_SAMPLES = 40        # encoder readings averaged into the state commands re-start from
JOINT_NAMES = ARM_JOINTS + MAST_JOINTS + WHEEL_NAMES + ('articulation',)
(V1, V2), (S1, S2) = p.TABLE_D1[1]
# rover_sim's noise model at its default 10 %: the covariances the sim publishes (NoiseConfig)
ACCEL_VAR = (0.1 * 0.16) ** 2 / 3
GYRO_VAR = (0.1 * 0.001) ** 2 / 3
INCL_VAR = (0.1 * 0.0004) ** 2 / 3 + (40.0 / 1024 * p.DEG) ** 2 / 12

#: pyserial URL schemes that reach a serial server over the network
NETWORK_SCHEMES = ('rfc2217', 'socket')


def is_network_port(port: str) -> bool:
    """Whether a pyserial port names a serial server on the network."""
    return port.split('://', 1)[0].lower() in NETWORK_SCHEMES if '://' in port else False


PARAMS = {
    'port': ParamSpec('', 'Device path or pyserial URL of the on-board controller (e.g. '
                      '/dev/ttyUSB0, /dev/serial/by-id/..., a pty, loop://); read at configure'),
    'allow_network_port': ParamSpec(False, 'accept a port that is a network URL (rfc2217://, '
                                    'socket://): such serial servers take any client on the '
                                    'network, with no authentication', read_only=True),
    'baudrate': ParamSpec(921600, 'Serial baud rate (a USB CDC or pty port ignores it)',
                          lo=9600, hi=4000000),
    'command_timeout_s': ParamSpec(0.5, 'Wheels stop when no cmd_vel came within this long (s)',
                                   lo=0.02, hi=10.0),
    'heartbeat_timeout_s': ParamSpec(0.3, 'Every motor stops (and the link counts as down) when '
                                     'the device sent nothing valid for this long (s)',
                                     lo=0.05, hi=5.0),
    'command_rate_hz': ParamSpec(200.0, 'Command frames per second and the grid of device '
                                 'instants arm and mast set-points are for (the control rate '
                                 'of the device)', lo=10.0, hi=500.0, read_only=True),
    'setpoint_lead_s': ParamSpec(0.1, 'Arm and mast set-points are sent this long ahead of the '
                                 'device instant they are for (s): more than link delay and '
                                 'host jitter, so each arrives in time', lo=0.005, hi=0.5),
    'odom_rate_hz': ParamSpec(50.0, 'Odometry rate (Hz), as rover_sim', lo=1.0, hi=200.0,
                              read_only=True),
    'stereo_pose_rate_hz': ParamSpec(4.0, 'stereo/pose rate (Hz): odometry + mast encoders; 0 '
                                     'leaves it to the camera driver', lo=0.0, hi=30.0,
                                     read_only=True),
    'reconnect_backoff_max_s': ParamSpec(0.5, 'Reconnect attempts back off up to this period (s)',
                                         lo=0.01, hi=5.0),
    'incl_roll_zero_v': ParamSpec(V1, 'Eq. D-1 zero-angle volts, roll (Table D-1 robot 1; '
                                  'robot 2: 2.447)', lo=0.0, hi=5.0),
    'incl_pitch_zero_v': ParamSpec(V2, 'Eq. D-1 zero-angle volts, pitch (robot 2: 2.392)',
                                   lo=0.0, hi=5.0),
    'incl_roll_sensitivity_v_per_deg': ParamSpec(S1, 'Eq. D-1 sensitivity, roll (V/deg; robot '
                                                 '2: 0.029338)', lo=0.001, hi=1.0),
    'incl_pitch_sensitivity_v_per_deg': ParamSpec(S2, 'Eq. D-1 sensitivity, pitch (V/deg; robot '
                                                  '2: 0.034905)', lo=0.001, hi=1.0),
    'accel_variance': ParamSpec(ACCEL_VAR, 'Accelerometer variance published (m^2/s^4)',
                                lo=0.0, hi=100.0),
    'gyro_variance': ParamSpec(GYRO_VAR, 'Gyro variance published (rad^2/s^2)', lo=0.0, hi=1.0),
    'incl_variance': ParamSpec(INCL_VAR, 'Inclinometer variance published (rad^2)', lo=0.0,
                               hi=1.0),
    'map_frame': ParamSpec('map', 'Frame of stereo/pose (REP 105), after frame_prefix',
                           read_only=True),
    **FRAME_PARAMS,
}


def _stamp(t_ns: int):
    return Time(sec=t_ns // 1_000_000_000, nanosec=t_ns % 1_000_000_000)


class ClockMap:
    """Device time (us) <-> the stamps' time (ns): device time plus the smallest offset seen
    since the link came up (transport delay only ever adds), so stamps keep the device's own
    spacing exactly; the offset only moves when a faster frame shows it too large. A device
    clock slower than the host's makes stamps lag the host clock slowly (re-anchored on each
    reconnect); commands are therefore timed on the stamps' clock, never on the host's, so
    what the graph commands for a stamp happens at the device instant of that stamp."""

    def __init__(self) -> None:
        self._min: int | None = None
        self._last: tuple[int, int] | None = None     # (device us, host ns) of the last frame

    def reset(self) -> None:
        self._min = None
        self._last = None

    def map(self, device_us: int, now_ns: int) -> int:
        off = now_ns - device_us * 1000
        if self._min is None or off < self._min:
            self._min = off
        self._last = (device_us, now_ns)
        return device_us * 1000 + self._min

    def now(self, now_ns: int) -> int | None:
        """The stamps' clock now (ns): the last frame's stamp plus the host time since it came
        (None before the first frame)."""
        if self._min is None or self._last is None:
            return None
        device_us, host_ns = self._last
        return device_us * 1000 + self._min + max(0, now_ns - host_ns)

    def to_device_us(self, stamp_ns: int) -> int:
        """The device time (us) of a time on the stamps' clock (after the first frame)."""
        assert self._min is not None
        return (stamp_ns - self._min) // 1000

    def to_stamp_ns(self, device_us: int) -> int:
        """The stamp of a device time (after the first frame)."""
        assert self._min is not None
        return device_us * 1000 + self._min


class BridgeNode(LifecycleNode):
    """The hardware bridge: a lifecycle node between the ROS topics and a rover's serial link."""

    def __init__(self, **kwargs) -> None:
        super().__init__('bridge', **kwargs)
        self.values = declare_parameters(self, PARAMS, on_change=self._on_param_change,
                                         check_all=check_frame_params)
        self.bad = BadInputCounter(self)
        self.limits = Limits()
        self.safety = Safety(command_timeout_s=self.values['command_timeout_s'],
                             heartbeat_timeout_s=self.values['heartbeat_timeout_s'],
                             clock=time.monotonic)
        fr = self.rover_frames = RoverFrames.of_namespace(
            self.get_namespace(), self.values['frame_prefix'], self.values['map_frame'])
        self.frames = {'base_link': fr.base_link, 'ft_sensor_link': fr.ft_sensor,
                       'odom': fr.odom}
        # the rover's part of the tree; sent while active (statics at activation)
        self.tree = TreeBroadcaster(self, enabled=self.values['publish_tf'], owned=fr.body(),
                                    check_s=self.values['frame_check_s'])
        self._lock = threading.Lock()          # state shared by the reader thread and executor
        self._write_lock = threading.Lock()
        self._port: serial.SerialBase | None = None
        self._reader: threading.Thread | None = None
        self._stop = threading.Event()
        self._active = False
        self.connected = False
        self._link_fault = False
        self._samples = 0              # sensor frames decoded (the services wait on it)
        self.decoder = p.Decoder()
        self.encoder = p.Encoder()
        self.clock_map = ClockMap()
        self._ack = threading.Condition()
        self._acks: dict[int, p.Ack] = {}
        self._measured: np.ndarray | None = None     # arm + mast encoder angles (mean)
        self._enc_hist: deque = deque(maxlen=SEED_SAMPLES)
        self._seeded = False
        self._live: dict[JointGroup, bool] = {'arm': False, 'mast': False}
        self._next_us: dict[JointGroup, int | None] = {'arm': None, 'mast': None}
        self._arm = JointTrajectoryFollower(ARM_JOINTS, np.zeros(4))
        self._mast = JointTrajectoryFollower(MAST_JOINTS, np.zeros(2))
        self._wheels = (0.0, 0.0, 0.0, 0.0)
        self._odom = [0.0, 0.0, 0.0]
        self._last_t_us: int | None = None
        self._next_odom_us = 0
        self._next_pose_us = 0
        self._incl_hist: deque = deque(maxlen=2000)
        self._ft_hist: deque = deque(maxlen=2000)
        self._ft_bias = np.zeros(6)
        self._calib: dict[str, tuple[float, float]] = {}
        self.published = 0
        self.last_publish_ns = 0       # monotonic ns of the last sensor publish (benchmark)
        self.last_frame_in_ns = 0
        self.latency_ns: deque[int] = deque(maxlen=100_000)      # bytes read -> all published
        self.latency_first_ns: deque[int] = deque(maxlen=100_000)  # bytes read -> imu published
        self._pubs: dict = {}
        self._entities: list = []
        self.get_logger().info('bridge ready (unconfigured); port '
                               f'{self.values["port"] or "<unset>"}')

    # ------------------------------------------------------------------ parameters
    def _on_param_change(self, changed: dict) -> None:
        self.values.update(changed)
        if 'command_timeout_s' in changed:
            self.safety.command_timeout_s = float(changed['command_timeout_s'])
        if 'heartbeat_timeout_s' in changed:
            self.safety.heartbeat_timeout_s = float(changed['heartbeat_timeout_s'])

    # ------------------------------------------------------------------ lifecycle
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        port = self.values['port']
        if not port:
            self.get_logger().error('configure: parameter port is empty')
            return TransitionCallbackReturn.FAILURE
        if is_network_port(port) and not self.values['allow_network_port']:
            self.get_logger().error(
                f'configure: {port} is a network port (no authentication: anyone on the '
                'network can drive the rover); set allow_network_port to use it')
            return TransitionCallbackReturn.FAILURE
        try:
            self._open()
        except (serial.SerialException, OSError, ValueError) as exc:
            self.get_logger().error(f'configure: cannot open {port}: {exc}')
            return TransitionCallbackReturn.FAILURE
        self._make_interfaces()
        self.safety.set_fault('inactive')
        self._stop.clear()
        self._reader = threading.Thread(target=self._read_loop, name='serial', daemon=True)
        self._reader.start()
        self.get_logger().info(f'configured: {port} open')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        with self._lock:
            self._reseed()
            self._active = True
        self.tree.send_static(static_transforms(self.rover_frames),
                              self.get_clock().now().to_msg())
        self.safety.set_fault('device unplugged' if self._link_fault else None)
        self.get_logger().info('active: publishing, commands accepted')
        return super().on_activate(state)

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        self.safety.set_fault('inactive')
        self._send_stop()
        self.get_logger().info('inactive: motors stopped, publishing stopped')
        return super().on_deactivate(state)

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self._shutdown_io()
        self.get_logger().info('cleaned up: port closed')
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        self.safety.set_fault('shut down')
        self._send_stop()
        self._shutdown_io()
        return TransitionCallbackReturn.SUCCESS

    def on_error(self, state: State) -> TransitionCallbackReturn:
        self._active = False
        self.safety.set_fault('error')
        self._send_stop()
        self._shutdown_io()
        return TransitionCallbackReturn.SUCCESS

    def _shutdown_io(self) -> None:
        self._stop.set()
        if self._reader is not None and self._reader is not threading.current_thread():
            self._reader.join(timeout=2.0)
        self._reader = None
        self._close()
        for e in self._entities:
            kind, obj = e
            getattr(self, f'destroy_{kind}')(obj)
        self._entities.clear()
        self._pubs.clear()

    def _make_interfaces(self) -> None:
        # the services wait for the device (acks, readings): never in the command stream's way
        slow = MutuallyExclusiveCallbackGroup()
        def pub(key, typ, name):
            self._pubs[key] = self.create_publisher(typ, name, SENSOR_QOS)
            self._entities.append(('publisher', self._pubs[key]))
        pub('imu', Imu, 'imu')
        pub('incl', Inclinometer, 'inclinometer')
        pub('wrench', WrenchStamped, 'arm/wrench')
        pub('joints', JointState, 'joint_states')
        pub('odom', Odometry, 'odom')
        if self.values['stereo_pose_rate_hz'] > 0:
            pub('pose', PoseWithCovarianceStamped, 'stereo/pose')
        for kind, obj in (
                ('subscription', self.create_subscription(
                    JointTrajectory, 'arm/joint_command',
                    lambda m: self._on_traj(m, 'arm'), COMMAND_QOS)),
                ('subscription', self.create_subscription(
                    JointTrajectory, 'mast/command', lambda m: self._on_traj(m, 'mast'),
                    COMMAND_QOS)),
                ('subscription', self.create_subscription(Twist, 'cmd_vel', self._on_twist,
                                                          COMMAND_QOS)),
                ('service', self.create_service(SetBool, 'estop', self._on_estop,
                                                callback_group=slow)),
                ('service', self.create_service(SetBool, 'arm/ft_bias', self._on_ft_bias,
                                                callback_group=slow)),
                ('service', self.create_service(CalibrateInclinometer, 'inclinometer/calibrate',
                                                self._on_calibrate, callback_group=slow)),
                ('timer', self.create_timer(1.0 / self.values['command_rate_hz'],
                                            self._on_control))):
            self._entities.append((kind, obj))

    # ------------------------------------------------------------------ port
    def _open(self) -> None:
        self._port = serial.serial_for_url(self.values['port'], baudrate=self.values['baudrate'],
                                           timeout=0.01, write_timeout=0.01)
        self.decoder.resync()
        self.clock_map.reset()
        self._last_t_us = None
        self.connected = True

    def _close(self) -> None:
        port, self._port = self._port, None
        self.connected = False
        if port is not None:
            with contextlib.suppress(serial.SerialException, OSError):
                port.close()

    def _send(self, payload: p.Payload) -> int | None:
        """Write one frame; its sequence number, or None when the link is down."""
        port = self._port
        if port is None:
            return None
        with self._write_lock:
            seq = self.encoder.seq
            try:
                port.write(self.encoder.encode(payload))
            except (serial.SerialException, OSError) as exc:
                self.bad.reject('write failed', str(exc))
                return None
        return seq

    def _send_stop(self) -> None:
        """Wheels to zero, arm and mast held where they are measured to be."""
        self._send(p.DriveCommand(p.DriveMode.VELOCITY, (0.0, 0.0, 0.0, 0.0)))
        with self._lock:
            self._wheels = (0.0, 0.0, 0.0, 0.0)
            if self._measured is not None:
                # hold where the joints are measured to be, if the bridge was moving them
                live = dict(self._live)
                self._reseed()
                m = self._measured
                if live['arm']:
                    self._send(p.ArmCommand(tuple(m[:4])))
                if live['mast']:
                    self._send(p.MastCommand(tuple(m[4:6])))

    def _reseed(self) -> None:
        """Commands start again from the measured state (no jump): hold the encoders' angles,
        wheels at rest. Caller holds _lock."""
        self._wheels = (0.0, 0.0, 0.0, 0.0)
        if self._measured is None:
            self._seeded = False
            return
        m = self._measured
        self._arm = JointTrajectoryFollower(ARM_JOINTS, m[:4])
        self._mast = JointTrajectoryFollower(MAST_JOINTS, m[4:6])
        self._seeded = True
        # set-points stream again only once a trajectory comes: until then the device holds
        # its joints itself (a set-point from noisy encoders would nudge the arm); their grid
        # starts again from the device's time then (a device that rebooted counts from 0)
        self._live = {'arm': False, 'mast': False}
        self._next_us = {'arm': None, 'mast': None}

    def _read_loop(self) -> None:
        backoff = 0.02
        while not self._stop.is_set():
            port = self._port
            if port is None:
                self._stop.wait(backoff)
                backoff = min(2 * backoff, self.values['reconnect_backoff_max_s'])
                try:
                    self._open()
                except (serial.SerialException, OSError, ValueError):
                    continue
                backoff = 0.02
                with self._lock:
                    self._measured = None
                    self._enc_hist.clear()
                    self._seeded = False      # re-seeded from the first sensor frame
                self.get_logger().info(f'reconnected to {self.values["port"]}')
                continue
            try:
                data = port.read(max(1, port.in_waiting))
            except (serial.SerialException, OSError, TypeError) as exc:
                if self._stop.is_set():
                    return
                self.get_logger().warn(f'device lost ({exc}); motors stopped, reconnecting')
                self._link_fault = True
                self.safety.set_fault('device unplugged')
                self._close()
                continue
            if not data:
                continue
            t_in = time.monotonic_ns()
            for frame in self.decoder.feed(data):
                self._on_frame(frame, t_in)
            self._report_bad()

    def _report_bad(self) -> None:
        d = self.decoder
        total = d.bad_total + d.seq_gaps
        if total != getattr(self, '_bad_seen', 0):
            self._bad_seen = total
            extra = (f' (device speaks version {d.last_bad_version}, not {p.VERSION})'
                     if d.bad.get(p.Bad.BAD_VERSION) else '')
            self.bad.reject('bad frames', f'{d.counts()}{extra}')

    # ------------------------------------------------------------------ device -> graph
    def _on_frame(self, frame: p.Frame, t_in: int) -> None:
        self.safety.heartbeat()
        if self._link_fault:
            self._link_fault = False
            self.safety.set_fault(None if self._active else 'inactive')
        pl = frame.payload
        if isinstance(pl, p.Sensors):
            self._on_sensors(pl, t_in)
        elif isinstance(pl, p.Ack):
            with self._ack:
                self._acks[pl.seq] = pl
                self._ack.notify_all()
            if pl.status is not p.AckStatus.OK:
                self.bad.reject('device refused a command',
                                f'{p.FrameType(pl.frame_type).name} seq {pl.seq}')
        elif isinstance(pl, p.Heartbeat) and (pl.flags & p.Flags.ESTOP) \
                and not self.safety.estopped:
            self.safety.engage_estop('device reports its stop latched')
            self.get_logger().warn('device reports e-stop latched')

    def _on_sensors(self, s: p.Sensors, t_in: int) -> None:
        enc = np.array(s.encoders, dtype=float) * p.ENCODER_RAD
        with self._lock:
            # the measured state commands re-start from: the mean of the last readings (one
            # noisy reading would make the arm jump by its noise and kick the base)
            self._enc_hist.append(enc)
            if len(self._enc_hist) >= SEED_SAMPLES:
                self._measured = np.mean(self._enc_hist, axis=0)
                if not self._seeded:
                    self._reseed()
        dt = 0.0 if self._last_t_us is None else (s.t_us - self._last_t_us) * 1e-6
        self._last_t_us = s.t_us
        tach = [v * p.TACH_RAD_S for v in s.tachometers]
        v, w = wheels_to_twist(tach, self.limits)
        if 0.0 < dt < 1.0:
            o = self._odom
            o[2] += w * dt
            o[0] += v * dt * math.cos(o[2])
            o[1] += v * dt * math.sin(o[2])
        volts = (s.incl[0] * p.INCL_VOLTS, s.incl[1] * p.INCL_VOLTS)
        self._incl_hist.append(volts)
        ft_raw = np.array([*(c * p.FT_FORCE_N for c in s.ft[:3]),
                           *(c * p.FT_TORQUE_NM for c in s.ft[3:])])
        self._ft_hist.append(ft_raw)
        self._samples += 1
        if not self._active:
            return
        stamp = _stamp(self.clock_map.map(s.t_us, self.get_clock().now().nanoseconds))
        pubs = self._pubs
        base = self.frames['base_link']
        vals = self.values
        imu_bad = bool(s.flags & p.Flags.IMU_SATURATED) or any(
            abs(c) >= p.I32 for c in (*s.accel, *s.gyro))
        if imu_bad:
            self.bad.reject('imu out of range', 'reading at the converter rail not published')
        else:
            imu = Imu()
            imu.header.stamp, imu.header.frame_id = stamp, base
            imu.orientation_covariance[0] = -1.0
            a, g = imu.linear_acceleration, imu.angular_velocity
            a.x, a.y, a.z = (c * p.ACCEL_M_S2 for c in s.accel)
            g.x, g.y, g.z = (c * p.GYRO_RAD_S for c in s.gyro)
            for k in range(3):
                imu.angular_velocity_covariance[4 * k] = vals['gyro_variance']
                imu.linear_acceleration_covariance[4 * k] = vals['accel_variance']
            pubs['imu'].publish(imu)
            self.latency_first_ns.append(time.monotonic_ns() - t_in)
        inc = Inclinometer()
        inc.header.stamp, inc.header.frame_id = stamp, base
        inc.roll = p.incl_angle(volts[0], vals['incl_roll_zero_v'],
                                vals['incl_roll_sensitivity_v_per_deg'])
        inc.pitch = p.incl_angle(volts[1], vals['incl_pitch_zero_v'],
                                 vals['incl_pitch_sensitivity_v_per_deg'])
        inc.roll_variance = inc.pitch_variance = vals['incl_variance']
        inc.raw_roll_volts, inc.raw_pitch_volts = volts
        # out of the linear range: flagged, as the sim does (the angle there is not good)
        inc.saturated = bool(s.flags & p.Flags.INCL_SATURATED) or max(
            abs(inc.roll), abs(inc.pitch)) > p.INCL_LINEAR_RANGE_RAD + 1e-9
        pubs['incl'].publish(inc)
        if (s.flags & p.Flags.FT_SATURATED) or any(abs(c) >= p.I16 for c in s.ft):
            self.bad.reject('F/T out of range', 'reading at the converter rail not published')
        else:
            f = ft_raw - self._ft_bias
            wr = WrenchStamped()
            wr.header.stamp, wr.header.frame_id = stamp, self.frames['ft_sensor_link']
            wr.wrench.force.x, wr.wrench.force.y, wr.wrench.force.z = (float(x) for x in f[:3])
            wr.wrench.torque.x, wr.wrench.torque.y, wr.wrench.torque.z = (
                float(x) for x in f[3:])
            pubs['wrench'].publish(wr)
        js = JointState()
        js.header.stamp = stamp
        js.name = list(JOINT_NAMES)
        js.position = [*(float(x) for x in enc), math.nan, math.nan, math.nan, math.nan,
                       s.pot * p.POT_RAD]
        js.velocity = [*(c * p.ENCODER_RATE_RAD_S for c in s.encoder_rates), *tach, 0.0]
        pubs['joints'].publish(js)
        if s.t_us >= self._next_odom_us:
            self._next_odom_us = s.t_us + round(1e6 / vals['odom_rate_hz']) - 500
            self._publish_odom(stamp, v, w, js)
        rate = vals['stereo_pose_rate_hz']
        if rate > 0 and s.t_us >= self._next_pose_us:
            self._next_pose_us = s.t_us + round(1e6 / rate) - 500
            self._publish_pose(stamp, enc)
        self.published += 1
        now = time.monotonic_ns()
        self.last_publish_ns = now
        self.latency_ns.append(now - t_in)

    def _publish_odom(self, stamp, v: float, w: float, js: JointState) -> None:
        x, y, yaw = self._odom
        pose = odom_transform(self.rover_frames, x, y, yaw)
        od = Odometry()
        od.header.stamp, od.header.frame_id = stamp, self.frames['odom']
        od.child_frame_id = self.frames['base_link']
        od.pose.pose.position.x, od.pose.pose.position.y, od.pose.pose.position.z = (
            pose.translation)
        od.pose.pose.orientation.z, od.pose.pose.orientation.w = math.sin(yaw / 2), math.cos(
            yaw / 2)
        od.twist.twist.linear.x, od.twist.twist.angular.z = v, w
        self._pubs['odom'].publish(od)
        if self.tree.listened:
            tree = [pose]
            try:
                tree += mast_transforms(self.rover_frames, js.name, js.position)
            except FrameError as exc:
                self.bad.reject('mast transform', str(exc))
            self.tree.send(tree, stamp)

    def _publish_pose(self, stamp, enc: np.ndarray) -> None:
        """Dead-reckoned left optical frame in the map (odometry + mast encoders; rover_sim's
        stereo/pose, blind to the compliance)."""
        x, y, yaw = self._odom
        t = camera_in_map(x, y, yaw, float(enc[4]), float(enc[5]))
        q = matrix_to_quat(t[:3, :3])
        msg = PoseWithCovarianceStamped()
        msg.header.stamp, msg.header.frame_id = stamp, self.rover_frames.map
        pp = msg.pose.pose
        pp.position.x, pp.position.y, pp.position.z = (float(c) for c in t[:3, 3])
        pp.orientation.x, pp.orientation.y, pp.orientation.z, pp.orientation.w = (
            float(c) for c in q)
        travelled = math.hypot(x, y) + 0.01
        cov = np.diag([travelled ** 2 * 0.25] * 2 + [1e-4] + [(2 * p.DEG) ** 2] * 3)
        msg.pose.covariance = [float(c) for c in cov.ravel()]
        self._pubs['pose'].publish(msg)

    # ------------------------------------------------------------------ graph -> device
    def _on_traj(self, msg: JointTrajectory, group: JointGroup) -> None:
        known = GROUP_JOINTS[group]
        names = list(msg.joint_names)
        try:
            if not self._active:
                raise CommandRefused('bridge not active')
            if self.safety.estopped:
                raise CommandRefused(f'e-stop latched ({self.safety.estop_reason})')
            if not msg.points:
                raise CommandRefused('trajectory without points')
            if msg.header.frame_id not in ('', self.frames['base_link']):
                raise CommandRefused(f'frame {msg.header.frame_id!r} is not '
                                     f'{self.frames["base_link"]}')
            positions = [list(pt.positions) for pt in msg.points]
            check_trajectory(names, positions, known, self.limits)
            times = [pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9
                     for pt in msg.points]
            vels = ([list(pt.velocities) for pt in msg.points]
                    if all(len(pt.velocities) == len(names) for pt in msg.points) else None)
            start = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            now = self._stamp_now_s()
            with self._lock:
                if not self._seeded:
                    raise CommandRefused('no measured state yet (device not streaming)')
                follower = self._follower(group)
                q, qd = follower.target(now)
                follower.set(names, times, positions, start if start > 0 else now, q,
                             velocities=vels, current_velocity=qd)
                self._live[group] = True
        except (CommandRefused, TrajectoryError) as exc:
            self.bad.reject(f'{group} command refused', str(exc))

    def _on_twist(self, msg: Twist) -> None:
        try:
            if not self._active:
                raise CommandRefused('bridge not active')
            if self.safety.estopped:
                raise CommandRefused(f'e-stop latched ({self.safety.estop_reason})')
            wheels = twist_to_wheels(msg.linear.x, msg.angular.z, self.limits)
        except CommandRefused as exc:
            self.bad.reject('cmd_vel refused', str(exc))
            return
        with self._lock:
            self._wheels = wheels
        self.safety.drive_command()

    def _follower(self, group: JointGroup) -> JointTrajectoryFollower:
        match group:
            case 'arm':
                return self._arm
            case 'mast':
                return self._mast
            case _:
                assert_never(group)

    def _stamp_now_s(self) -> float:
        """Now on the stamps' clock (the device's, see ClockMap), the time base of trajectories;
        the host clock before the first frame."""
        host = self.get_clock().now().nanoseconds
        t = self.clock_map.now(host)
        return (host if t is None else t) * 1e-9

    def _on_control(self) -> None:
        """The command stream (command_rate_hz): set-points while allowed, a stop otherwise."""
        if self._port is None:
            return
        tick = getattr(self, '_ticks', 0) + 1
        self._ticks = tick
        if tick % max(1, int(self.values['command_rate_hz'] / 10)) == 0:
            self._send(p.Heartbeat(p.Flags.NONE, int(time.monotonic() * 1000)))
        if not self._active:
            return
        why = self.safety.motors_stop_reason()
        if why:
            # the wheels told to stand (the device's own e-stop holds everything else)
            self._send(p.DriveCommand(p.DriveMode.VELOCITY, (0.0, 0.0, 0.0, 0.0)))
            return
        lead_ns = round(self.values['setpoint_lead_s'] * 1e9)
        period_us = round(1e6 / self.values['command_rate_hz'])
        frames: list[p.Payload] = []
        with self._lock:
            if not self._seeded:
                return
            # set-points on a grid of device instants, every one from the last sent up to
            # `lead` ahead, each sent with the device time it is for: a late or skipped timer
            # call sends the instants it missed, so the device's path never depends on when
            # this callback ran (seeded means frames came, so the clock map has its offset)
            now = self.clock_map.now(self.get_clock().now().nanoseconds)
            if now is None:
                return
            first = -(-self.clock_map.to_device_us(now) // period_us) * period_us
            last = self.clock_map.to_device_us(now + lead_ns)
            for group, follower, kind in (('arm', self._arm, p.ArmCommand),
                                          ('mast', self._mast, p.MastCommand)):
                if not self._live[group]:
                    self._next_us[group] = None
                    continue
                t_us = max(first, self._next_us[group] or first)
                while t_us <= last:
                    q, qd = follower.target(self.clock_map.to_stamp_ns(t_us) * 1e-9)
                    frames.append(kind(tuple(float(x) for x in q),
                                       tuple(float(x) for x in qd), t_us))
                    t_us += period_us
                self._next_us[group] = t_us
            if self.safety.drive_stop_reason():
                self._wheels = (0.0, 0.0, 0.0, 0.0)
            frames.append(p.DriveCommand(p.DriveMode.VELOCITY, self._wheels))
        for frame in frames:
            self._send(frame)

    # ------------------------------------------------------------------ services
    def _wait_ack(self, seq: int | None, timeout_s: float = 0.25) -> p.Ack | None:
        if seq is None:
            return None
        deadline = time.monotonic() + timeout_s
        with self._ack:
            while seq not in self._acks:
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._ack.wait(left)
            return self._acks.pop(seq)

    def _on_estop(self, req: SetBool.Request, res: SetBool.Response) -> SetBool.Response:
        if req.data:
            # stop first, ask questions later: latched before the device is even told
            self.safety.engage_estop('service')
            with self._lock:
                self._wheels = (0.0, 0.0, 0.0, 0.0)
            ack = None
            for _ in range(3):
                ack = self._wait_ack(self._send(p.EStop(True)))
                if ack is not None:
                    break
            res.success = True
            res.message = ('e-stop latched; device acknowledged' if ack is not None else
                           'e-stop latched here; the device did not acknowledge (link down?)')
            self.get_logger().warn(res.message)
            return res
        ack = self._wait_ack(self._send(p.EStop(False)))
        if ack is None or ack.status is not p.AckStatus.OK:
            res.success = False
            res.message = 'e-stop kept: the device did not acknowledge the clear'
            return res
        with self._lock:
            self._reseed()
            self.safety.clear_estop()
        res.success, res.message = True, 'e-stop cleared; commands re-seeded from the encoders'
        self.get_logger().info(res.message)
        return res

    def _recent(self, hist: deque, n: int, timeout_s: float = 3.0) -> list | None:
        """The next n readings appended to hist (None if they do not come in time)."""
        target = self._samples + n
        deadline = time.monotonic() + timeout_s
        while self._samples < target:
            if time.monotonic() > deadline:
                return None
            time.sleep(0.01)
        return list(hist)[-n:]

    def _on_ft_bias(self, req: SetBool.Request, res: SetBool.Response) -> SetBool.Response:
        if not req.data:
            self._ft_bias = np.zeros(6)
            res.success, res.message = True, 'F/T bias cleared'
            return res
        got = self._recent(self._ft_hist, 100)
        if got is None:
            res.success, res.message = False, 'no F/T readings from the device'
            return res
        self._ft_bias = np.mean(got, axis=0)
        res.success = True
        res.message = 'F/T biased: ' + ' '.join(f'{x:.4g}' for x in self._ft_bias)
        self.get_logger().info(res.message)
        return res

    def _on_calibrate(self, req, res):
        axis = req.axis
        k = {'roll': 0, 'pitch': 1}.get(axis)
        if k is None:
            res.success, res.message = False, f'axis must be roll or pitch, not {axis!r}'
            return res
        if req.reset:
            self._calib.pop(axis, None)
            res.success, res.message, res.points = True, f'{axis}: point dropped', 0
            return res
        if not (math.isfinite(req.angle_rad) and abs(req.angle_rad) <= p.INCL_LINEAR_RANGE_RAD):
            res.success, res.message = False, 'angle_rad must be within the +-20 deg range'
            return res
        got = self._recent(self._incl_hist, req.samples or 100)
        if got is None:
            res.success, res.message = False, 'no inclinometer readings from the device'
            return res
        volts = float(np.mean([g[k] for g in got]))
        res.volts = volts
        first = self._calib.get(axis)
        if first is None:
            self._calib[axis] = (req.angle_rad, volts)
            res.success, res.points = True, 1
            res.message = f'{axis}: {volts:.4f} V at {req.angle_rad:.4f} rad kept; tilt again'
            return res
        try:
            zero, sens = p.calibrate_axis(first[0], first[1], req.angle_rad, volts)
        except p.ProtocolError as exc:
            res.success, res.message, res.points = False, str(exc), 1
            return res
        self._calib.pop(axis)
        result = self.set_parameters([
            Parameter(f'incl_{axis}_zero_v', value=zero),
            Parameter(f'incl_{axis}_sensitivity_v_per_deg', value=sens)])
        if not all(r.successful for r in result):
            res.success = False
            res.message = '; '.join(r.reason for r in result if not r.successful)
            return res
        res.success, res.points = True, 2
        res.zero_volts, res.sensitivity_v_per_deg = zero, sens
        res.message = f'{axis}: V~ = {zero:.4f} V, S = {sens * 1e3:.3f} mV/deg (Eq. D-1)'
        self.get_logger().info(res.message)
        return res

    def destroy_node(self) -> None:
        self._active = False
        if self._port is not None:
            self._send_stop()
        self._shutdown_io()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run rover_hw bridge`."""
    return run_node(BridgeNode, args,
                    executor_factory=lambda: MultiThreadedExecutor(num_threads=2))


if __name__ == '__main__':
    raise SystemExit(main())
