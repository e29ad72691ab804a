"""The serial protocol between the bridge and a rover's on-board controller (thesis app. D). No
rclpy: bytes in, typed frames out, and back.

Wire format: every frame is COBS-encoded and ends with one 0x00 byte, so a receiver finds the
next frame boundary after any damage. Decoded, a frame is

    version u8 | type u8 | seq u16 | length u16 | payload (length bytes) | crc32 u32

little endian, CRC-32 (zlib) over everything before it. Each sender numbers its frames with its
own 16-bit sequence counter; a receiver counts the gaps.
"""
from __future__ import annotations

import enum
import math
import struct
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass

from cobs import cobs

from .errors import HardwareError

VERSION = 2
DELIMITER = b'\x00'
HEADER = struct.Struct('<BBHH')
CRC = struct.Struct('<I')
#: the longest frame a receiver buffers before it gives up waiting for a delimiter
MAX_FRAME_BYTES = 512

DEG = math.pi / 180.0


class ProtocolError(HardwareError):
    """A frame or value that cannot be encoded or decoded; the message says why."""


class FrameType(enum.IntEnum):
    """A frame's type byte."""

    SENSORS = 0x01      # device -> host, every sensor at one instant (200 Hz)
    ARM = 0x10          # host -> device, arm joint set-points
    MAST = 0x11         # host -> device, mast pan/tilt set-points
    DRIVE = 0x12        # host -> device, wheel velocity or PWM duty
    ESTOP = 0x20        # host -> device, engage (1) or clear (0) the latched stop; acked
    HEARTBEAT = 0x21    # both ways, 10 Hz
    ACK = 0x30          # device -> host, the answer to an ESTOP or a refused command


class DriveMode(enum.IntEnum):
    """How DriveCommand.wheels are read."""

    VELOCITY = 0        # wheel speeds, rad/s
    PWM = 1             # duty cycle -1..1 of the supply (app. D PWM amplifier)


class AckStatus(enum.IntEnum):
    """An Ack's verdict."""

    OK = 0
    REFUSED = 1         # out of limits, NaN, or e-stop latched


class Flags(enum.IntFlag):
    """Status bits of a sensor frame and a device heartbeat."""

    NONE = 0
    INCL_SATURATED = 0x01     # inclinometer outside its +-20 deg linear range
    FT_SATURATED = 0x02       # an F/T channel at its converter's rail
    IMU_SATURATED = 0x04
    ESTOP = 0x08              # the device's stop is latched
    MOTORS_ENABLED = 0x10     # the device drives its motors (host alive, no stop)


# ----------------------------------------------------------------------- scaling (SI per count)
ENCODER_RAD = 2.0 * math.pi / 65536        # 16-bit per revolution, i32 multi-turn
ENCODER_RATE_RAD_S = 1e-6
TACH_RAD_S = 1e-3
POT_RAD = 1e-4
INCL_VOLTS = 1e-4
FT_FORCE_N = 100.0 / 32767                 # JR3-like 16-bit, 100 N / 25 N m full scale
FT_TORQUE_NM = 25.0 / 32767
ACCEL_M_S2 = 1e-6
GYRO_RAD_S = 1e-8

I16 = 32767
I32 = 2 ** 31 - 1

_SENSORS = struct.Struct('<Q6i6i4hh2H6h3i3iB')
_ARM = struct.Struct('<Q4f4f')
_MAST = struct.Struct('<Q2f2f')
_DRIVE = struct.Struct('<B4f')
_ESTOP = struct.Struct('<B')
_HEARTBEAT = struct.Struct('<BI')
_ACK = struct.Struct('<BHB')


@dataclass(frozen=True)
class Sensors:
    """One sample of every sensor, in counts as the controller reads them (see the scales)."""

    t_us: int
    encoders: tuple[int, ...]         # arm_joint_1..4, mast_pan, mast_tilt
    encoder_rates: tuple[int, ...]
    tachometers: tuple[int, ...]      # wheel_fl, fr, rl, rr
    pot: int                          # articulation
    incl: tuple[int, int]             # roll, pitch volts
    ft: tuple[int, ...]               # Fx Fy Fz Tx Ty Tz
    accel: tuple[int, int, int]
    gyro: tuple[int, int, int]
    flags: Flags = Flags.NONE


@dataclass(frozen=True)
class ArmCommand:
    """A set-point for device time `t_us` (0: at once). The controller passes through its timed
    set-points by cubic (position + velocity) interpolation at its own control instants, so
    when a set-point arrives, within its lead, changes nothing in the path."""

    positions: tuple[float, float, float, float]
    velocities: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    t_us: int = 0


@dataclass(frozen=True)
class MastCommand:
    """As ArmCommand, for the camera mast (pan, tilt)."""

    positions: tuple[float, float]
    velocities: tuple[float, float] = (0.0, 0.0)
    t_us: int = 0


@dataclass(frozen=True)
class DriveCommand:
    """The four wheels, as speeds or duty cycles (`mode`)."""

    mode: DriveMode
    wheels: tuple[float, float, float, float]     # fl, fr, rl, rr


@dataclass(frozen=True)
class EStop:
    """Engage or clear the latched stop."""

    engage: bool


@dataclass(frozen=True)
class Heartbeat:
    """The 10 Hz keep-alive: status flags and uptime."""

    flags: Flags
    uptime_ms: int


@dataclass(frozen=True)
class Ack:
    """The answer to the frame of `frame_type` and `seq`."""

    frame_type: int
    seq: int
    status: AckStatus


Payload = Sensors | ArmCommand | MastCommand | DriveCommand | EStop | Heartbeat | Ack


@dataclass(frozen=True)
class Frame:
    """A decoded frame: type, sequence number and payload."""

    type: FrameType
    seq: int
    payload: Payload


# ----------------------------------------------------------------------- payloads
def _pack(p: Payload) -> tuple[FrameType, bytes]:
    try:
        if isinstance(p, Sensors):
            return FrameType.SENSORS, _SENSORS.pack(
                p.t_us, *p.encoders, *p.encoder_rates, *p.tachometers, p.pot, *p.incl, *p.ft,
                *p.accel, *p.gyro, int(p.flags))
        if isinstance(p, ArmCommand):
            return FrameType.ARM, _ARM.pack(p.t_us, *p.positions, *p.velocities)
        if isinstance(p, MastCommand):
            return FrameType.MAST, _MAST.pack(p.t_us, *p.positions, *p.velocities)
        if isinstance(p, DriveCommand):
            return FrameType.DRIVE, _DRIVE.pack(int(p.mode), *p.wheels)
        if isinstance(p, EStop):
            return FrameType.ESTOP, _ESTOP.pack(1 if p.engage else 0)
        if isinstance(p, Heartbeat):
            return FrameType.HEARTBEAT, _HEARTBEAT.pack(int(p.flags), p.uptime_ms & 0xFFFFFFFF)
        if isinstance(p, Ack):
            return FrameType.ACK, _ACK.pack(p.frame_type, p.seq, int(p.status))
    except struct.error as exc:
        raise ProtocolError(f'{type(p).__name__}: {exc}') from exc
    raise ProtocolError(f'not a payload: {type(p).__name__}')


def _unpack(ftype: FrameType, data: bytes) -> Payload:
    """ProtocolError on a wrong size or a field out of its enum."""
    try:
        if ftype is FrameType.SENSORS:
            v = _SENSORS.unpack(data)
            return Sensors(v[0], v[1:7], v[7:13], v[13:17], v[17], v[18:20], v[20:26], v[26:29],
                           v[29:32], Flags(v[32]))
        if ftype is FrameType.ARM:
            v = _ARM.unpack(data)
            return ArmCommand(v[1:5], v[5:], v[0])
        if ftype is FrameType.MAST:
            v = _MAST.unpack(data)
            return MastCommand(v[1:3], v[3:], v[0])
        if ftype is FrameType.DRIVE:
            v = _DRIVE.unpack(data)
            return DriveCommand(DriveMode(v[0]), v[1:])
        if ftype is FrameType.ESTOP:
            (v,) = _ESTOP.unpack(data)
            if v not in (0, 1):
                raise ProtocolError(f'e-stop value {v}')
            return EStop(bool(v))
        if ftype is FrameType.HEARTBEAT:
            f, up = _HEARTBEAT.unpack(data)
            return Heartbeat(Flags(f), up)
        if ftype is FrameType.ACK:
            t, s, st = _ACK.unpack(data)
            return Ack(t, s, AckStatus(st))
    except (struct.error, ValueError) as exc:
        raise ProtocolError(f'{ftype.name} payload: {exc}') from exc
    raise ProtocolError(f'unhandled frame type {ftype!r}')


def encode(payload: Payload, seq: int, *, version: int = VERSION) -> bytes:
    """One frame on the wire: COBS(header + payload + CRC-32) + 0x00."""
    ftype, data = _pack(payload)
    body = HEADER.pack(version, int(ftype), seq & 0xFFFF, len(data)) + data
    return cobs.encode(body + CRC.pack(zlib.crc32(body))) + DELIMITER


class Encoder:
    """Numbers the frames of one sender (16-bit sequence, wrapping)."""

    def __init__(self, *, start_seq: int = 0) -> None:
        self.seq = start_seq & 0xFFFF

    def encode(self, payload: Payload) -> bytes:
        out = encode(payload, self.seq)
        self.seq = (self.seq + 1) & 0xFFFF
        return out


# ----------------------------------------------------------------------- decoding
class Bad(enum.Enum):
    """Kinds of bad input a Decoder counts (sequence gaps are counted apart: no frame is bad)."""

    BAD_COBS = 'bad_cobs'
    SHORT = 'short'
    BAD_CRC = 'bad_crc'
    BAD_VERSION = 'bad_version'
    UNKNOWN_TYPE = 'unknown_type'
    BAD_LENGTH = 'bad_length'      # length field or payload size wrong for the type
    OVERSIZE = 'oversize'          # no delimiter within MAX_FRAME_BYTES


class Decoder:
    """Streaming decoder: feed it byte chunks of any size, get whole, CRC-valid frames.

    Anything else is dropped and counted in `bad` by kind; decoding resumes at the next 0x00.
    `seq_gaps` counts the gaps in the sender's sequence, `lost` the frames they add up to.
    """

    def __init__(self, *, max_frame_bytes: int = MAX_FRAME_BYTES, version: int = VERSION) -> None:
        self._buf = bytearray()
        self._max = max_frame_bytes
        self._version = version
        self._skipping = False        # inside an oversize run: drop until the next delimiter
        self.bad: Counter[Bad] = Counter()
        self.frames = 0
        self.seq_gaps = 0
        self.lost = 0
        self.last_bad_version: int | None = None
        self._expect: int | None = None

    @property
    def bad_total(self) -> int:
        return sum(self.bad.values())

    def resync(self) -> None:
        """Forget a partial frame and the sequence (after a reconnect)."""
        self._buf.clear()
        self._skipping = False
        self._expect = None

    def feed(self, data: bytes) -> Iterator[Frame]:
        buf = self._buf
        start = 0
        while True:
            end = data.find(0, start)
            if end < 0:
                chunk = data[start:]
                if self._skipping:
                    return
                buf += chunk
                if len(buf) > self._max:
                    self.bad[Bad.OVERSIZE] += 1
                    buf.clear()
                    self._skipping = True
                return
            if self._skipping:
                self._skipping = False
                buf.clear()
            else:
                buf += data[start:end]
                if buf:
                    frame = self._frame(bytes(buf))
                    buf.clear()
                    if frame is not None:
                        yield frame
            start = end + 1

    def _frame(self, raw: bytes) -> Frame | None:
        if len(raw) > self._max:
            self.bad[Bad.OVERSIZE] += 1
            return None
        try:
            body = cobs.decode(raw)
        except cobs.DecodeError:
            self.bad[Bad.BAD_COBS] += 1
            return None
        if len(body) < HEADER.size + CRC.size:
            self.bad[Bad.SHORT] += 1
            return None
        (crc,) = CRC.unpack_from(body, len(body) - CRC.size)
        if zlib.crc32(memoryview(body)[:-CRC.size]) != crc:
            self.bad[Bad.BAD_CRC] += 1
            return None
        version, ftype, seq, length = HEADER.unpack_from(body)
        if version != self._version:
            self.bad[Bad.BAD_VERSION] += 1
            self.last_bad_version = version
            return None
        try:
            kind = FrameType(ftype)
        except ValueError:
            self.bad[Bad.UNKNOWN_TYPE] += 1
            return None
        data = body[HEADER.size:-CRC.size]
        if length != len(data):
            self.bad[Bad.BAD_LENGTH] += 1
            return None
        try:
            payload = _unpack(kind, data)
        except ProtocolError:
            self.bad[Bad.BAD_LENGTH] += 1
            return None
        if self._expect is not None and seq != self._expect:
            self.seq_gaps += 1
            self.lost += (seq - self._expect) & 0xFFFF
        self._expect = (seq + 1) & 0xFFFF
        self.frames += 1
        return Frame(kind, seq, payload)

    def counts(self) -> dict[str, int]:
        """Every counter by name (for logs, diagnostics and the benchmark's table)."""
        out = {b.value: self.bad.get(b, 0) for b in Bad}
        out.update(frames=self.frames, seq_gaps=self.seq_gaps, lost=self.lost)
        return out


# ----------------------------------------------------------------------- Eq. D-1
#: Table D-1: (zero volts, sensitivity V/deg) for (roll, pitch), per robot, room temperature
TABLE_D1 = {
    1: ((2.406, 2.381), (0.033631, 0.034733)),
    2: ((2.447, 2.392), (0.029338, 0.034905)),
}
INCL_LINEAR_RANGE_RAD = 20.0 * DEG


def incl_angle(volts: float, zero_volts: float, sensitivity_v_per_deg: float) -> float:
    """Eq. D-1: theta = (V_out - V~) / S, in radians (S in V/deg as Table D-1 gives it)."""
    if not sensitivity_v_per_deg > 0.0:
        raise ProtocolError(f'inclinometer sensitivity must be > 0, got {sensitivity_v_per_deg}')
    return (volts - zero_volts) / sensitivity_v_per_deg * DEG


def calibrate_axis(angle1_rad: float, volts1: float, angle2_rad: float, volts2: float
                   ) -> tuple[float, float]:
    """Two-point calibration of one axis (app. D): two known tilts and the volts read at each,
    solved for Eq. D-1's (zero volts, sensitivity V/deg). ProtocolError if the points do not
    determine a positive sensitivity (tilts too close, or volts not rising with the angle)."""
    values = (angle1_rad, volts1, angle2_rad, volts2)
    if not all(math.isfinite(v) for v in values):
        raise ProtocolError('calibration points must be finite')
    if abs(angle2_rad - angle1_rad) < 1.0 * DEG:
        raise ProtocolError('calibration tilts must differ by at least 1 deg')
    sens = (volts2 - volts1) / ((angle2_rad - angle1_rad) / DEG)
    if not sens > 0.0:
        raise ProtocolError(f'calibration gives sensitivity {sens * 1e3:.3f} mV/deg (not > 0)')
    return volts1 - sens * angle1_rad / DEG, sens


def to_count(value: float, scale: float, limit: int) -> int:
    """SI value -> count, clipped to the converter's rail (+-limit)."""
    return max(-limit, min(limit, round(value / scale)))
