"""The power-line carrier that addresses BRAID's binary actuators (thesis §E.4, Figs. E-7/E-8):
one power line and ground to every actuator; a command is a pulse train piggybacked on the line;
each actuator's decoder counts the pulses into a binary word and latches its actuator when the
end-of-train flag arrives and the word is its own address.

Encoding (times in units of the bit period T, `Timing.period_s`):

- actuator address: a = 3 (stage - 1) + (leg - 1) for stage 1..n, leg 1..3 (0-based: 3 i + j);
  the word is w = 2 a + s, s the target state (0 short, 1 long), so the counter's low bit is the
  state line and the rest the actuator line (Fig. E-8's combinational decode);
- burst A: w + 1 address pulses (never empty), each T/2 wide at 2.0 V, gaps of T/2;
- separator: a gap of 2 T;
- burst B: W - w + 1 pulses, W = 2 N - 1 the largest word of N actuators, so that
  |A| + |B| = W + 2 for every command: the complement count is the train's check (a lost or
  extra pulse anywhere, the first one included, breaks it) and every train lasts the same;
- gap T/2, then the end-of-train flag: one pulse T/2 wide at 5.0 V (§E.4's voltage spike);
- between trains, at least `Timing.inter_train` (4 T) of quiet line.

Decoder model (every actuator's chip has the same front end; it sees the same line, so one model
of it serves all and each chip then compares the word with its own address, `ActuatorDecoder`):

- counter input: a pulse counts when its peak is above the TTL threshold 1.3 V (lower: the
  comparator does not see it);
- buffer input behind the 2.5:1 divider: a pulse is the flag when peak / 2.5 > 1.3 V
  (peak > 3.25 V); address pulses (2 V -> 0.8 V) stay below;
- de-bouncer: every pulse's width and every gap must lie in its window, pulses and normal gaps
  [0.25 T, 0.75 T], the separator [1.75 T, 2.25 T]; anything else marks the train malformed;
- on the flag: the counts are checked (one separator, both bursts non-empty, |A| + |B| = W + 2,
  word <= W); a valid train latches word w, a malformed one latches nothing; the flag resets the
  counter either way. A train that ends without its flag latches nothing.

Noise bound (`NOISE_BOUND`): every edge displaced by at most 0.1 T and every pulse's peak by at
most 0.5 V. Then each width and gap moves by at most 0.2 T, inside its 0.25 T window margin, and
address peaks stay in [1.5, 2.5] V, flag peaks in [4.5, 5.5] V, each on its side of both
thresholds: decoding is exact (no wrong actuator, no missed command) for any noise within it.
Beyond it a train may be read as malformed (nothing latched) but a single lost, extra or
misread pulse never makes another valid word, since the windows and the complement count
reject it.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from coop_braid.errors import BraidError
from coop_braid.stage import LegState

#: TTL threshold of the counter's comparator and of the buffer, V (§E.4)
TTL_THRESHOLD_V = 1.3
#: the divider between the signal line and the buffer (§E.4: 2.5:1)
BUFFER_DIVIDER = 2.5
#: peak of an address pulse and of the end-of-train flag on the signal line, V (§E.4)
ADDRESS_PEAK_V = 2.0
FLAG_PEAK_V = 5.0


class CarrierError(BraidError):
    """An actuator address or state out of range, or mismatched chain states."""


@dataclass(frozen=True)
class Timing:
    """The train's timing in units of the bit period `period_s`: pulse width, normal gap, the
    separator gap between bursts A and B, the quiet line between trains, and the de-bouncer's
    half-window around each nominal width or gap."""

    period_s: float = 100e-6
    width: float = 0.5
    gap: float = 0.5
    separator: float = 2.0
    inter_train: float = 4.0
    window: float = 0.25


@dataclass(frozen=True)
class NoiseBound:
    """The noise under which decoding is exact: each edge within +-`edge_jitter` T of its
    nominal time, each pulse's peak within +-`amplitude_v` of its nominal."""

    edge_jitter: float = 0.1
    amplitude_v: float = 0.5


#: the documented bound (module docstring)
NOISE_BOUND = NoiseBound()


@dataclass(frozen=True)
class Command:
    """Set the actuator at 0-based `address` (3 (stage - 1) + (leg - 1)) to `state`."""

    address: int
    state: LegState

    @property
    def stage(self) -> int:
        """1-based stage of the actuator."""
        return self.address // 3 + 1

    @property
    def leg(self) -> int:
        """1-based leg of the actuator in its stage."""
        return self.address % 3 + 1


@dataclass(frozen=True)
class PulseTrain:
    """Pulses on the signal line: rising and falling edge times (s) and peak voltages, in time
    order."""

    rise_s: NDArray[np.float64]
    fall_s: NDArray[np.float64]
    peak_v: NDArray[np.float64]

    def __len__(self) -> int:
        return int(self.rise_s.shape[0])

    def then(self, other: PulseTrain, *, timing: Timing = Timing()) -> PulseTrain:
        """`other` after this train, shifted to start `timing.inter_train` periods after this
        train's last edge."""
        if not len(self):
            return other
        shift = (float(self.fall_s[-1]) + timing.inter_train * timing.period_s
                 - (float(other.rise_s[0]) if len(other) else 0.0))
        return PulseTrain(np.concatenate([self.rise_s, other.rise_s + shift]),
                          np.concatenate([self.fall_s, other.fall_s + shift]),
                          np.concatenate([self.peak_v, other.peak_v]))


def max_word(n_actuators: int) -> int:
    """W = 2 N - 1: the largest word of N actuators."""
    if n_actuators < 1:
        raise CarrierError(f'{n_actuators} actuators: at least one')
    return 2 * n_actuators - 1


def encode(command: Command, *, n_actuators: int, timing: Timing = Timing()) -> PulseTrain:
    """The pulse train of one command (module docstring), starting at t = 0."""
    if not 0 <= command.address < n_actuators:
        raise CarrierError(f'address {command.address}: 0..{n_actuators - 1}')
    word = 2 * command.address + int(LegState(command.state))
    count_a, count_b = word + 1, max_word(n_actuators) - word + 1
    pitch = timing.width + timing.gap
    starts = [k * pitch for k in range(count_a)]
    t0 = starts[-1] + timing.width + timing.separator
    starts += [t0 + k * pitch for k in range(count_b)]
    starts.append(starts[-1] + pitch)                        # the flag
    rise = np.array(starts) * timing.period_s
    peaks = np.full(len(starts), ADDRESS_PEAK_V)
    peaks[-1] = FLAG_PEAK_V
    return PulseTrain(rise, rise + timing.width * timing.period_s, peaks)


def decode_stream(train: PulseTrain, *, n_actuators: int,
                  timing: Timing = Timing()) -> list[Command | None]:
    """The decoder front end on a stream of trains: one entry per end-of-train flag, the command
    latched or None (malformed train: nothing latched). Pulses after the last flag latch
    nothing."""
    big_w = max_word(n_actuators)
    period = timing.period_s
    seen = train.peak_v > TTL_THRESHOLD_V                     # the counter's comparator
    rise, fall, peak = train.rise_s[seen], train.fall_s[seen], train.peak_v[seen]
    flags = np.flatnonzero(peak / BUFFER_DIVIDER > TTL_THRESHOLD_V)
    out: list[Command | None] = []
    start = 0
    for f in flags:
        out.append(_decode_one(rise[start:f + 1], fall[start:f + 1], big_w, period, timing))
        start = int(f) + 1
    return out


def _decode_one(rise: NDArray[np.float64], fall: NDArray[np.float64], big_w: int,
                period: float, timing: Timing) -> Command | None:
    """One train ending in its flag (the last pulse): the command, or None when malformed."""
    widths = (fall - rise) / period
    if np.any(np.abs(widths - timing.width) > timing.window):
        return None
    gaps = (rise[1:] - fall[:-1]) / period
    normal = np.abs(gaps - timing.gap) <= timing.window
    separator = np.abs(gaps - timing.separator) <= timing.window
    if not np.all(normal | separator) or int(separator.sum()) != 1:
        return None
    count_a = int(np.flatnonzero(separator)[0]) + 1
    count_b = len(rise) - 1 - count_a                          # the flag is not counted
    if count_b < 1 or count_a + count_b != big_w + 2:
        return None
    word = count_a - 1
    return Command(address=word // 2, state=LegState(word % 2))


def decode(train: PulseTrain, *, n_actuators: int, timing: Timing = Timing()) -> Command | None:
    """The command one train latches, or None (malformed, or no flag)."""
    latched = decode_stream(train, n_actuators=n_actuators, timing=timing)
    return latched[0] if len(latched) == 1 else None


class ActuatorDecoder:
    """One actuator's decoder chip (Fig. E-8): latches its actuator to the commanded state only
    when a valid train's word names its own address."""

    def __init__(self, address: int) -> None:
        if address < 0:
            raise CarrierError(f'address {address}: >= 0')
        self.address = address
        self.state = LegState.SHORT
        self.latches = 0

    def offer(self, command: Command | None) -> bool:
        """Latch `command` when it is addressed here; whether it latched."""
        if command is None or command.address != self.address:
            return False
        self.state = command.state
        self.latches += 1
        return True


class Bus:
    """The power/control bus of an n-stage BRAID (Fig. E-7): one decoder per actuator (3n)."""

    def __init__(self, stages: int, *, timing: Timing = Timing()) -> None:
        if stages < 1:
            raise CarrierError(f'{stages} stages: at least one')
        self.n_actuators = 3 * stages
        self.timing = timing
        self.decoders = [ActuatorDecoder(a) for a in range(self.n_actuators)]

    def transmit(self, train: PulseTrain) -> list[list[int]]:
        """Put a stream of trains on the line; per end-of-train flag, the addresses of the
        decoders that latched."""
        out = []
        for cmd in decode_stream(train, n_actuators=self.n_actuators, timing=self.timing):
            out.append([d.address for d in self.decoders if d.offer(cmd)])
        return out

    def set_states(self, states: Sequence[int] | NDArray[np.integer]) -> None:
        """Put the actuators in the legs of stage states `states` (n,) (the mast as found)."""
        s = np.asarray(states)
        if s.shape != (self.n_actuators // 3,) or np.any((s < 0) | (s > 7)):
            raise CarrierError(f'states: {self.n_actuators // 3} stage states 0..7')
        for d in self.decoders:
            d.state = LegState(int(s[d.address // 3]) >> (d.address % 3) & 1)

    def leg_states(self) -> NDArray[np.int64]:
        """The chain's stage states (n,) the latched actuators give (bit j - 1: leg j long)."""
        bits = np.array([int(d.state) for d in self.decoders]).reshape(-1, 3)
        return bits @ np.array([1, 2, 4])


def commands_between(start: Sequence[int] | NDArray[np.integer],
                     goal: Sequence[int] | NDArray[np.integer]) -> list[Command]:
    """The commands that move the mast from stage states `start` to `goal` (n each, 0..7): one
    per leg that differs, base stage first, nothing for a leg already in its goal state."""
    a, b = np.asarray(start), np.asarray(goal)
    if a.shape != b.shape or a.ndim != 1 or not np.issubdtype(a.dtype, np.integer) \
            or not np.issubdtype(b.dtype, np.integer) or np.any((a < 0) | (a > 7)) \
            or np.any((b < 0) | (b > 7)):
        raise CarrierError('start and goal: stage states 0..7 of the same chain')
    out = []
    for i, (s, g) in enumerate(zip(a.tolist(), b.tolist(), strict=True)):
        for j in range(3):
            if (s ^ g) >> j & 1:
                out.append(Command(address=3 * i + j, state=LegState(g >> j & 1)))
    return out


def encode_sequence(commands: Sequence[Command], *, n_actuators: int,
                    timing: Timing = Timing()) -> PulseTrain:
    """The trains of `commands` one after another, `timing.inter_train` periods apart."""
    out = PulseTrain(np.empty(0), np.empty(0), np.empty(0))
    for c in commands:
        out = out.then(encode(c, n_actuators=n_actuators, timing=timing), timing=timing)
    return out


def add_noise(train: PulseTrain, rng: np.random.Generator, *,
              bound: NoiseBound = NOISE_BOUND, timing: Timing = Timing(),
              extreme: bool = False) -> PulseTrain:
    """`train` with every edge displaced and every peak changed, uniformly within `bound`
    (`extreme`: each by exactly +-the bound, signs random: the worst case)."""
    n = len(train)

    def draw(size: int, amp: float) -> NDArray[np.float64]:
        if extreme:
            return amp * rng.choice((-1.0, 1.0), size=size)
        return rng.uniform(-amp, amp, size=size)

    jit = bound.edge_jitter * timing.period_s
    return PulseTrain(train.rise_s + draw(n, jit), train.fall_s + draw(n, jit),
                      train.peak_v + draw(n, bound.amplitude_v))
