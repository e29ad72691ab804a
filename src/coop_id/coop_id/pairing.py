"""The identifier's sample stream: each IMU sample paired with the inclinometer and F/T samples
of its instant (no rclpy). The `identifier` node feeds it its three topics as they arrive;
`offline.bag_samples` feeds it a bag's messages in their recorded order, so a bag is identified
from the samples the node would have taken.

Stamps are integer nanoseconds (the header's sec * 1e9 + nanosec: exact, whatever the epoch).
Each stream's stamps must increase; a sample with a non-finite value or a stamp not after its
stream's last is rejected, unless it is more than `reset_after_ns` before it: then time has
jumped back (a simulator reset, a looped bag) and the pairer starts over from that sample
(`on_reset`), rather than rejecting every sample until the old time comes back. A saturated
inclinometer or F/T sample is rejected too, but its stamp counts as heard (its instant is
lost, the IMU sample there need not wait for it).

Pairing: an IMU sample at t waits until both partner streams have reached t (whatever the
order or latency in which the three topics arrive: the first samples of a replay come in one
burst, in any order), then takes the partner of each stream nearest to t within the
tolerance; if one has none the sample is dropped ('unpaired sample'). Only a full queue (a
silent partner stream) drops a sample that is still waiting ('silent sensor').
"""
from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

#: the three streams, in row order: IMU (specific force 3, gyro 3), inclinometer (roll, pitch),
#: F/T (force 3, torque 3)
STREAMS = ('imu', 'inclinometer', 'wrench')
#: Sensor seconds an IMU sample may wait for its inclinometer / F/T partners (the capacity is
#: this times the sample rate)
QUEUE_S = 5.0


def stamp_ns(header: Any) -> int:
    """A std_msgs/Header's stamp in integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


class SamplePairer:
    """Pairs the three streams into rows (see the module docstring).

    capacity: IMU samples that may wait for their partners (and partner samples kept);
    tolerance_ns: largest stamp difference of a pair; force_limit / torque_limit: F/T
    saturation (an axis beyond it rejects the sample). on_sample(t_ns, row (14,)) gets each
    pair in stamp order; on_reject(reason, detail) each rejected or dropped sample. The
    tolerance and limits are attributes: a node's parameter change sets them."""

    def __init__(self, capacity: int, *, tolerance_ns: int,
                 on_sample: Callable[[int, np.ndarray], None],
                 on_reject: Callable[[str, str], None],
                 force_limit: float = math.inf, torque_limit: float = math.inf,
                 reset_after_ns: int = 1_000_000_000,
                 on_reset: Callable[[int, int], None] | None = None) -> None:
        if capacity < 1:
            raise ValueError('capacity must be >= 1')
        self.capacity = capacity
        self.tolerance_ns = int(tolerance_ns)
        self.reset_after_ns = int(reset_after_ns)
        self._on_reset = on_reset
        self.force_limit = force_limit
        self.torque_limit = torque_limit
        self._on_sample = on_sample
        self._on_reject = on_reject
        self._queues: dict[str, deque[tuple[int, Sequence[float]]]] = {
            s: deque(maxlen=capacity) for s in STREAMS}
        self.last_stamp = dict.fromkeys(STREAMS, -math.inf)

    def _accept(self, name: str, t: int, values: Sequence[float]) -> bool:
        if not all(math.isfinite(v) for v in values):
            self._on_reject('non-finite', name)
            return False
        if t < self.last_stamp[name] - self.reset_after_ns:
            old = self.last_stamp[name]
            self.reset()
            if self._on_reset is not None:
                self._on_reset(int(old), t)     # a stamp, finite: t is below it
        if t <= self.last_stamp[name]:
            self._on_reject('out-of-order stamp', f'{name} {t * 1e-9:.4f} <= '
                            f'{self.last_stamp[name] * 1e-9:.4f}')
            return False
        self.last_stamp[name] = t
        return True

    def reset(self) -> None:
        """Forget every queued sample and stamp (time starts over)."""
        for q in self._queues.values():
            q.clear()
        self.last_stamp = dict.fromkeys(STREAMS, -math.inf)

    def imu(self, t: int, specific_force: Sequence[float], gyro: Sequence[float]) -> bool:
        """Adds an IMU sample; False if it was rejected."""
        values = [*specific_force, *gyro]
        if not self._accept('imu', t, values):
            return False
        self._queues['imu'].append((t, values))
        self._assemble()
        return True

    def inclinometer(self, t: int, roll: float, pitch: float, saturated: bool = False) -> bool:
        """Adds an inclinometer sample; False if it was rejected (non-finite, out of order,
        saturated)."""
        if not self._accept('inclinometer', t, [roll, pitch]):
            return False
        ok = not saturated
        if ok:
            self._queues['inclinometer'].append((t, [roll, pitch]))
        else:         # after _accept: its stamp tells the waiting IMU sample it is lost
            self._on_reject('saturated inclinometer', '')
        self._assemble()
        return ok

    def wrench(self, t: int, force: Sequence[float], torque: Sequence[float]) -> bool:
        """Adds an F/T sample; False if it was rejected (non-finite, out of order, beyond the
        limits)."""
        values = [*force, *torque]
        if not self._accept('wrench', t, values):
            return False
        ok = (max(abs(v) for v in values[:3]) <= self.force_limit
              and max(abs(v) for v in values[3:]) <= self.torque_limit)
        if ok:
            self._queues['wrench'].append((t, values))
        else:
            self._on_reject('saturated F/T', '')
        self._assemble()
        return ok

    def flush(self) -> None:
        """The end of the streams (a bag's end): the waiting IMU samples pair with what came."""
        self._assemble(final=True)

    def _assemble(self, final: bool = False) -> None:
        imu, incl, wrench = (self._queues[s] for s in STREAMS)
        tol = self.tolerance_ns
        while imu:
            t, values = imu[0]
            # partners older than the waiting sample can never pair: trimming them (not the
            # queue's bound) keeps every partner a lagging IMU stream still needs
            _trim(incl, t - tol)
            _trim(wrench, t - tol)
            if not final and min(self.last_stamp['inclinometer'],
                                 self.last_stamp['wrench']) < t:
                if len(imu) < self.capacity:
                    return        # the partners of this instant may still come: wait
                imu.popleft()
                self._on_reject('silent sensor', 'inclinometer or wrench')
                continue
            a = _nearest(incl, t, tol)
            b = _nearest(wrench, t, tol)
            imu.popleft()
            if a is None or b is None:        # the partner will never come: drop it
                self._on_reject('unpaired sample', f'imu {t * 1e-9:.4f}')
                continue
            self._on_sample(t, np.array([*values, *a, *b], dtype=np.float64))


def _trim(buf: deque, t_min: int) -> None:
    """Drop the entries of `buf` (stamp-ordered) stamped before t_min."""
    while buf and buf[0][0] < t_min:
        buf.popleft()


def _nearest(buf: deque, t: int, tol: int) -> tuple[int, Sequence[float]] | None:
    """The values of `buf` (stamp-ordered) nearest to t within tol, searched from the newest
    (of two equally near, the older)."""
    best, best_dt = None, tol
    for tb, values in reversed(buf):
        if tb < t - tol:
            break
        dt = abs(tb - t)
        if dt <= best_dt:
            best, best_dt = values, dt
    return best
