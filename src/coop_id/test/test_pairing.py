"""The identifier's sample pairing (coop_id.pairing), by hand-made streams."""
import math

import numpy as np
import pytest

from coop_id.pairing import SamplePairer

MS = 1_000_000


def make(capacity: int = 100, tol_ms: float = 2.0, **kw):
    rows, rejects = [], []
    p = SamplePairer(capacity, tolerance_ns=int(tol_ms * MS),
                     on_sample=lambda t, r: rows.append((t, r)),
                     on_reject=lambda reason, _d: rejects.append(reason), **kw)
    return p, rows, rejects


def imu(p, t_ms, v=1.0):
    return p.imu(int(t_ms * MS), [v, 0.0, 9.81], [0.0, 0.0, v])


def test_a_sample_waits_for_partners_that_arrive_late_and_in_any_order():
    p, rows, rejects = make()
    p.wrench(10 * MS, [1, 2, 3], [4, 5, 6])
    imu(p, 10)
    assert rows == []                           # the inclinometer has not reached 10 ms yet
    p.inclinometer(10 * MS, 0.1, 0.2)
    assert len(rows) == 1 and rejects == []
    t, row = rows[0]
    assert t == 10 * MS
    np.testing.assert_array_equal(row, [1, 0, 9.81, 0, 0, 1, 0.1, 0.2, 1, 2, 3, 4, 5, 6])


def test_partners_pair_within_the_tolerance_and_the_nearest_wins():
    p, rows, rejects = make(tol_ms=2.0)
    p.inclinometer(9 * MS, 0.9, 0.0)            # 1 ms early
    p.inclinometer(int(10.5 * MS), 1.05, 0.0)   # 0.5 ms late: nearer
    p.wrench(int(11.9 * MS), [0, 0, 0], [0, 0, 0])
    imu(p, 10)
    assert len(rows) == 1 and rows[0][1][6] == 1.05 and rejects == []
    # a partner 3 ms off never pairs: once both streams have passed the instant, it is dropped
    imu(p, 20)
    p.inclinometer(23 * MS, 0.0, 0.0)
    p.wrench(20 * MS, [0, 0, 0], [0, 0, 0])
    assert len(rows) == 1 and rejects == ['unpaired sample']


def test_a_saturated_partner_loses_its_instant_without_a_wait():
    p, rows, rejects = make(force_limit=100.0, torque_limit=10.0)
    imu(p, 10)
    p.inclinometer(10 * MS, 0.0, 0.0, saturated=True)
    assert rows == [] and rejects == ['saturated inclinometer']
    p.wrench(10 * MS, [0, 0, 0], [0, 0, 0])     # the instant is complete: dropped, not queued
    assert rejects == ['saturated inclinometer', 'unpaired sample']
    imu(p, 15)
    p.inclinometer(15 * MS, 0.0, 0.0)
    assert not p.wrench(15 * MS, [0, 0, 150.0], [0, 0, 0])
    assert rejects[-2:] == ['saturated F/T', 'unpaired sample'] and rows == []


def test_bad_values_and_stamps_are_rejected():
    p, _rows, rejects = make()
    assert not p.imu(5 * MS, [math.nan, 0, 0], [0, 0, 0])
    assert imu(p, 5)
    assert not imu(p, 5)                        # not after the stream's last stamp
    assert not p.inclinometer(5 * MS, math.inf, 0.0)
    assert rejects == ['non-finite', 'out-of-order stamp', 'non-finite']


def test_a_silent_partner_stream_drops_the_oldest_sample_at_capacity_and_flush_pairs():
    p, rows, rejects = make(capacity=3)
    for t in (5, 10):
        imu(p, t)
        p.wrench(t * MS, [0, 0, 0], [0, 0, 0])
    assert rejects == []                        # waiting for the inclinometer
    imu(p, 15)                                  # the queue is full: 5 ms goes
    assert rejects == ['silent sensor']
    p.inclinometer(10 * MS, 0.0, 0.0)           # 10 ms pairs; 15 waits for both
    assert [t // MS for t, _ in rows] == [10]
    p.flush()                                   # the end: nothing more will come
    assert [t // MS for t, _ in rows] == [10]
    assert rejects == ['silent sensor', 'unpaired sample']


def test_capacity_is_validated():
    with pytest.raises(ValueError):
        make(capacity=0)


def test_time_jumping_back_starts_the_pairer_over():
    """A stamp more than reset_after_ns before its stream's last (a sim reset, a looped bag):
    the queues are dropped and pairing resumes from the new time; a small step back is still
    an out-of-order rejection."""
    resets = []
    p, rows, rejects = make(reset_after_ns=1000 * MS, on_reset=lambda a, b: resets.append(b))
    for t in (5000, 5005):
        imu(p, t)
        p.inclinometer(t * MS, 0.0, 0.0)
        p.wrench(t * MS, [0, 0, 0], [0, 0, 0])
    imu(p, 5010)                               # waits for partners that will never come
    assert not imu(p, 4500) and rejects == ['out-of-order stamp']
    for t in (5, 10):                          # time starts over
        imu(p, t)
        p.inclinometer(t * MS, 0.0, 0.0)
        p.wrench(t * MS, [0, 0, 0], [0, 0, 0])
    assert resets == [5 * MS] and [t // MS for t, _ in rows] == [5000, 5005, 5, 10]
    assert rejects == ['out-of-order stamp']   # the stranded 5010 sample went with the reset
