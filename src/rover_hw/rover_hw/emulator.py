"""A rover's on-board controller, emulated: speaks `rover_hw.protocol` on a pseudo-terminal,
backed by rover_sim's world core (one rover), with fault injection. No rclpy.

`Device` is the controller's logic (bytes in, bytes out, one `tick` per 5 ms control period);
`PtyEmulator` puts it on a pty in real time, with a stable symlink to the pty's slave side so a
bridge finds it again after an unplug (`--link`, like /dev/serial/by-id/...).
"""
from __future__ import annotations

import argparse
import contextlib
import math
import os
import random
import select
import signal
import sys
import termios
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, assert_never

from coop_common.rover_geometry import GROUP_JOINTS, JointGroup
from rover_sim.rover_model import ARM_JOINTS, MAST_JOINTS

from . import protocol as p
from .protocol import Flags

if TYPE_CHECKING:    # for annotations only: the world imports PyBullet
    from rover_sim.world import World
from .safety import Limits, wheels_to_twist

ENCODERS = 6
#: timed set-points a joint group holds ahead (2.5 s at 200 Hz; the bridge sends 0.1 s ahead)
MAX_SETPOINTS = 500


@dataclass(frozen=True)
class Faults:
    """Fault injection, per frame sent (probabilities) and on a schedule (seconds of run time)."""

    garble: float = 0.0           # one random byte of the encoded frame replaced
    bad_crc: float = 0.0          # a valid frame with its CRC flipped
    drop: float = 0.0             # frame not sent (the receiver sees a sequence gap)
    partial: float = 0.0          # only the first part of the frame sent, then its delimiter
    seq_gap: float = 0.0          # sequence number jumps ahead
    bad_version: float = 0.0      # a frame of another protocol version
    stall_at_s: float = -1.0      # the device stops sending (and stops its motors) ...
    stall_s: float = 0.0          # ... for this long
    unplug_at_s: float = -1.0     # the pty is closed ...
    unplug_s: float = 0.0         # ... and reopened this much later
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ('garble', 'bad_crc', 'drop', 'partial', 'seq_gap', 'bad_version'):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f'{name} must be a probability in [0, 1], got {v}')


class FaultInjector:
    """Turns payloads into wire bytes with the configured damage; counts what it did."""

    def __init__(self, faults: Faults) -> None:
        self.faults = faults
        self.rng = random.Random(faults.seed)
        self.encoder = p.Encoder()
        self.counts = {k: 0 for k in ('sent', 'garble', 'bad_crc', 'drop', 'partial',
                                      'seq_gap', 'bad_version')}

    def frame(self, payload: p.Payload) -> bytes:
        f, rng = self.faults, self.rng
        if f.seq_gap and rng.random() < f.seq_gap:
            self.encoder.seq = (self.encoder.seq + rng.randint(1, 5)) & 0xFFFF
            self.counts['seq_gap'] += 1
        if f.drop and rng.random() < f.drop:
            self.encoder.seq = (self.encoder.seq + 1) & 0xFFFF
            self.counts['drop'] += 1
            return b''
        self.counts['sent'] += 1
        r = rng.random()
        if r < f.bad_version:
            self.counts['bad_version'] += 1
            out = p.encode(payload, self.encoder.seq, version=p.VERSION + 1)
            self.encoder.seq = (self.encoder.seq + 1) & 0xFFFF
            return out
        out = self.encoder.encode(payload)
        r -= f.bad_version
        if r < f.garble:
            self.counts['garble'] += 1
            return corrupt(out, rng)
        r -= f.garble
        if r < f.bad_crc:
            self.counts['bad_crc'] += 1
            body = bytearray(p.cobs.decode(out[:-1]))
            body[-1] ^= 1 + rng.randrange(255)
            return p.cobs.encode(bytes(body)) + p.DELIMITER
        r -= f.bad_crc
        if r < f.partial:
            self.counts['partial'] += 1
            return out[:rng.randint(1, len(out) - 2)] + p.DELIMITER
        return out

    @property
    def damaged(self) -> int:
        """Frames sent that a receiver must reject."""
        c = self.counts
        return c['garble'] + c['bad_crc'] + c['partial'] + c['bad_version']


def corrupt(frame: bytes, rng: random.Random) -> bytes:
    """The frame with one byte before its delimiter changed to another non-zero value (a
    garbled byte inside a frame; a zero would split it into two pieces, both still rejected)."""
    b = bytearray(frame)
    i = rng.randrange(len(b) - 1)
    b[i] = (b[i] + rng.randint(1, 254)) % 256 or 1
    return bytes(b)


def make_world(*, seed: int = 1, noise_fraction: float = 0.1, truth_yaml: str = '') -> World:
    """One rover in rover_sim's world (its sensors, noise and truth). Imports PyBullet."""
    from coop_common.dynparams import load_truth  # noqa: PLC0415 - only with a world
    from rover_sim.config import NoiseConfig, SimConfig  # noqa: PLC0415 - only with a world
    from rover_sim.world import World  # noqa: PLC0415 - PyBullet, only with a world

    config = SimConfig(rovers=1, seed=seed, stereo_rate_hz=0.0,
                       noise=NoiseConfig(fraction=noise_fraction))
    return World(config, [load_truth(truth_yaml or None)])


class Device:
    """The controller: steps the world one control period per `tick`, sends a sensor frame each
    tick and a heartbeat every 10th of a second, follows the host's commands, and stops every
    motor when the host falls silent for `host_timeout_s` or the e-stop is latched."""

    def __init__(self, world: World, *, faults: Faults | None = None, host_timeout_s: float = 0.25,
                 heartbeat_hz: float = 10.0) -> None:
        self.world = world
        self.dt = world.dt
        self.inject = FaultInjector(faults or Faults())
        self.decoder = p.Decoder()
        self.host_timeout_s = host_timeout_s
        # timed set-points not yet reached, per group: [(t_s, positions, velocities)]
        self._setpoints: dict[JointGroup, list[tuple[float, tuple, tuple]]] = {'arm': [],
                                                                               'mast': []}
        self.late_setpoints = 0         # timed set-points that came at or after their time
        self._hb_every = max(1, round(1.0 / (heartbeat_hz * self.dt)))
        self.estop = False
        self.last_host_s = -math.inf
        self.motors_enabled = False
        self.refused = 0
        self._drive_mode = p.DriveMode.VELOCITY

    @property
    def time_s(self) -> float:
        return self.world.time_s

    def receive(self, data: bytes) -> bytes:
        """Host bytes in; acknowledgements out."""
        out = bytearray()
        for frame in self.decoder.feed(data):
            self.last_host_s = self.time_s
            out += self._handle(frame)
        return bytes(out)

    def _handle(self, frame: p.Frame) -> bytes:
        pl = frame.payload
        if isinstance(pl, p.EStop):
            self.estop = pl.engage
            if pl.engage:
                self._stop_motors()
            return self.inject.frame(p.Ack(int(frame.type), frame.seq, p.AckStatus.OK))
        if isinstance(pl, (p.ArmCommand, p.MastCommand, p.DriveCommand)):
            values = [*getattr(pl, 'positions', ()), *getattr(pl, 'velocities', ()),
                      *getattr(pl, 'wheels', ())]
            stop = isinstance(pl, p.DriveCommand) and not any(pl.wheels)
            # a stop is never refused, not even while the e-stop is latched
            if (self.estop and not stop) or not all(math.isfinite(v) for v in values):
                self.refused += 1
                return self.inject.frame(p.Ack(int(frame.type), frame.seq, p.AckStatus.REFUSED))
            self._apply(pl)
        return b''

    def _apply(self, pl: p.Payload) -> None:
        w = self.world
        if isinstance(pl, p.ArmCommand):
            self._follow('arm', pl)
        elif isinstance(pl, p.MastCommand):
            self._follow('mast', pl)
        elif isinstance(pl, p.DriveCommand):
            wheels = list(pl.wheels)
            if pl.mode is p.DriveMode.PWM:
                # no-load speed proportional to duty (app. D: 49 rpm at 12 V)
                top = 49.0 * 2 * math.pi / 60.0
                wheels = [max(-1.0, min(1.0, d)) * top for d in wheels]
            v, yaw_rate = wheels_to_twist(wheels, Limits())
            w.command_velocity(0, v, yaw_rate)

    def _follow(self, group: JointGroup, pl: p.ArmCommand | p.MastCommand) -> None:
        """A position-velocity-time set-point stream: the joint references pass through the
        timed set-points still ahead, by cubic interpolation from where the reference is now.
        Re-planned from the reference's own value and speed, the path is the same however a
        set-point's arrival falls between control instants. A set-point at or past its time
        is dropped while later ones are queued (the path goes on through them); otherwise it,
        like an untimed one (t_us 0), is the target of the next control instant."""
        now, w = self.time_s, self.world
        t = pl.t_us * 1e-6
        queue = self._setpoints[group]
        if t <= now + 1e-9:
            if pl.t_us:
                self.late_setpoints += 1
                if any(sp[0] > now for sp in queue):
                    return
            t = now + self.dt
            queue.clear()
        queue[:] = [sp for sp in queue if now < sp[0] < t]
        if len(queue) >= MAX_SETPOINTS:
            self.refused += 1           # a host that runs this far ahead: the nearest are kept
            return
        queue.append((t, tuple(pl.positions), tuple(pl.velocities)))
        times = [sp[0] - now for sp in queue]
        positions = [list(sp[1]) for sp in queue]
        match group:
            case 'arm':
                w.command_arm(0, GROUP_JOINTS[group], times, positions,
                              velocities=[list(sp[2]) for sp in queue])
            case 'mast':
                w.command_mast(0, GROUP_JOINTS[group], times, positions)
            case _:
                assert_never(group)

    def _stop_motors(self) -> None:
        w = self.world
        for queue in self._setpoints.values():
            queue.clear()
        w.command_velocity(0, 0.0, 0.0)
        # hold where the joints are (their encoders), not where the last set-point was
        w.command_arm(0, ARM_JOINTS, [self.dt], [list(w.joint_positions(0, ARM_JOINTS))])
        w.command_mast(0, MAST_JOINTS, [self.dt], [list(w.joint_positions(0, MAST_JOINTS))])

    def tick(self, *, send: bool = True) -> bytes:
        """One control period: watchdog, physics step, the sensor frame (and a heartbeat)."""
        alive = self.time_s - self.last_host_s <= self.host_timeout_s
        enabled = alive and not self.estop
        if self.motors_enabled and not enabled:
            self._stop_motors()
        self.motors_enabled = enabled
        self.world.step()
        if not send:
            return b''
        out = self.inject.frame(self.sensors())
        if self.world.steps % self._hb_every == 0:
            out += self.inject.frame(p.Heartbeat(self._flags(), int(self.time_s * 1000)))
        return out

    def _flags(self) -> Flags:
        f = Flags.NONE
        if self.estop:
            f |= Flags.ESTOP
        if self.motors_enabled:
            f |= Flags.MOTORS_ENABLED
        return f

    def sensors(self) -> p.Sensors:
        """The world's readings in the controller's counts (protocol scales, clipped to rails)."""
        s = self.world.sense(0)
        c = p.to_count
        pos, vel = s.joint_positions, s.joint_velocities
        flags = self._flags()
        if s.incl_saturated:
            flags |= Flags.INCL_SATURATED
        ft = ([c(v, p.FT_FORCE_N, p.I16) for v in s.force]
              + [c(v, p.FT_TORQUE_NM, p.I16) for v in s.torque])
        if any(abs(v) >= p.I16 for v in ft):
            flags |= Flags.FT_SATURATED
        accel = [c(v, p.ACCEL_M_S2, p.I32) for v in s.specific_force]
        gyro = [c(v, p.GYRO_RAD_S, p.I32) for v in s.angular_velocity]
        if any(abs(v) >= p.I32 for v in accel + gyro):
            flags |= Flags.IMU_SATURATED
        return p.Sensors(
            t_us=round(s.stamp_s * 1e6),
            encoders=tuple(c(v, p.ENCODER_RAD, p.I32) for v in pos[:ENCODERS]),
            encoder_rates=tuple(c(v, p.ENCODER_RATE_RAD_S, p.I32) for v in vel[:ENCODERS]),
            tachometers=tuple(c(v, p.TACH_RAD_S, p.I16) for v in vel[ENCODERS:ENCODERS + 4]),
            pot=c(float(pos[ENCODERS + 4]), p.POT_RAD, p.I16),
            incl=tuple(max(0, min(65535, round(v / p.INCL_VOLTS))) for v in s.incl_volts),
            ft=tuple(ft), accel=(accel[0], accel[1], accel[2]),
            gyro=(gyro[0], gyro[1], gyro[2]), flags=flags)


class PtyEmulator:
    """A Device on a pseudo-terminal, paced in real time (`rate` x), faults on schedule."""

    def __init__(self, device: Device, *, link: str | Path | None = None, rate: float = 1.0,
                 log: Callable[[str], None] | None = None) -> None:
        self.device = device
        self.link = Path(link) if link else None
        self.rate = rate
        self._log = log or (lambda msg: print(f'[{time.time():.6f}] {msg}', file=sys.stderr,
                                              flush=True))
        self.master: int | None = None
        self.slave: int | None = None
        self.slave_path = ''

    def open(self) -> str:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave, termios.TCSANOW)
        os.set_blocking(self.master, False)
        self.slave_path = os.ttyname(self.slave)
        if self.link is not None:
            tmp = self.link.with_name(self.link.name + '.tmp')
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
            tmp.symlink_to(self.slave_path)
            tmp.replace(self.link)
        self._log(f'emulator: device on {self.slave_path}'
                  + (f' (link {self.link})' if self.link else ''))
        return self.slave_path

    def close(self) -> None:
        for fd in (self.master, self.slave):
            if fd is not None:
                with contextlib.suppress(OSError):
                    os.close(fd)
        self.master = self.slave = None

    def _write(self, data: bytes) -> None:
        if not data or self.master is None:
            return
        # nobody reading: the pty buffer is full, as a real UART overruns
        with contextlib.suppress(BlockingIOError, OSError):
            os.write(self.master, data)

    def run(self, duration_s: float = math.inf) -> None:
        """Run until duration_s of device time have passed (or forever)."""
        d, f = self.device, self.device.inject.faults
        if self.master is None:
            self.open()
        t0 = time.monotonic()
        sim0 = d.time_s
        stall_end = unplug_end = -1.0
        while d.time_s - sim0 < duration_s:
            now_dev = d.time_s - sim0
            if f.unplug_at_s >= 0 and unplug_end < 0 and now_dev >= f.unplug_at_s:
                self._log('emulator: unplugged')
                self.close()
                unplug_end = now_dev + f.unplug_s
            if self.master is None and 0 <= unplug_end <= now_dev:
                self.open()
                self._log('emulator: plugged in again')
            if f.stall_at_s >= 0 and stall_end < 0 and now_dev >= f.stall_at_s:
                self._log('emulator: stalled')
                stall_end = now_dev + f.stall_s
            stalled = stall_end >= 0 and now_dev < stall_end
            if self.master is not None:
                try:
                    while select.select([self.master], [], [], 0)[0]:
                        data = os.read(self.master, 4096)
                        if not data:
                            break
                        if not stalled:
                            self._write(d.receive(data))
                except OSError:
                    pass        # no slave side open yet: nothing to read (EIO)
            if stalled:
                d.last_host_s = -math.inf       # a stalled controller drives nothing
            self._write(d.tick(send=not stalled and self.master is not None))
            if self.rate > 0:
                ahead = (d.time_s - sim0) / self.rate - (time.monotonic() - t0)
                if ahead > 0:
                    time.sleep(ahead)
                elif ahead < -0.5:
                    t0 = time.monotonic() - (d.time_s - sim0) / self.rate


def main(argv: list[str] | None = None) -> int:
    """`ros2 run rover_hw emulator`: a simulated controller on a pseudo-terminal."""
    ap = argparse.ArgumentParser(
        prog='emulator', description="A rover's on-board controller on a pseudo-terminal "
        "(rover_hw protocol), backed by rover_sim's world.")
    ap.add_argument('--link', default='', help='symlink kept pointing at the pty (stable path)')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--noise-fraction', type=float, default=0.1)
    ap.add_argument('--truth-yaml', default='')
    ap.add_argument('--rate', type=float, default=1.0, help='real-time factor (0: flat out)')
    ap.add_argument('--duration', type=float, default=math.inf, help='device seconds to run')
    for name in ('garble', 'bad-crc', 'drop', 'partial', 'seq-gap', 'bad-version'):
        ap.add_argument(f'--{name}', type=float, default=0.0, help='probability per frame')
    for name in ('stall-at', 'unplug-at'):
        ap.add_argument(f'--{name}', type=float, default=-1.0, help='seconds into the run')
    ap.add_argument('--stall-for', type=float, default=0.0)
    ap.add_argument('--unplug-for', type=float, default=0.0)
    ap.add_argument('--fault-seed', type=int, default=0)
    args = ap.parse_args(argv if argv is not None else _strip_ros_args(sys.argv[1:]))
    try:
        faults = Faults(garble=args.garble, bad_crc=args.bad_crc, drop=args.drop,
                        partial=args.partial, seq_gap=args.seq_gap, bad_version=args.bad_version,
                        stall_at_s=args.stall_at, stall_s=args.stall_for,
                        unplug_at_s=args.unplug_at, unplug_s=args.unplug_for,
                        seed=args.fault_seed)
    except ValueError as exc:
        ap.error(str(exc))
    # a stop on SIGINT and SIGTERM, also when started in the background (SIGINT ignored)
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)
    world = make_world(seed=args.seed, noise_fraction=args.noise_fraction,
                       truth_yaml=args.truth_yaml)
    emu = PtyEmulator(Device(world, faults=faults), link=args.link or None, rate=args.rate)
    try:
        emu.run(args.duration)
    except KeyboardInterrupt:
        pass
    finally:
        emu.close()
        if emu.link is not None:
            with contextlib.suppress(OSError):
                emu.link.unlink()
        world.close()
        print(f'emulator: sent {emu.device.inject.counts}, late set-points '
              f'{emu.device.late_setpoints}, refused {emu.device.refused}', file=sys.stderr,
              flush=True)
    return 0


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def _strip_ros_args(argv: list[str]) -> list[str]:
    """`ros2 run` passes --ros-args ... through; the emulator is no ROS node."""
    if '--ros-args' in argv:
        argv = argv[:argv.index('--ros-args')]
    return argv


if __name__ == '__main__':
    raise SystemExit(main())
