"""Plain record/play logic: QoS matching, topic selection, remapping, the playback schedule."""
from __future__ import annotations

import random

import pytest

from rover_bag.bagio import make_qos
from rover_bag.playback import (
    QosChoice,
    RemapError,
    bag_topic,
    parse_remaps,
    play_topic,
    publisher_qos,
    remap_topic,
    schedule,
    select_topics,
    subscription_qos,
    summarize_lateness,
)

BE = make_qos(reliable=False, transient_local=False, depth=5)
REL = make_qos(reliable=True, transient_local=False, depth=10)
LATCH = make_qos(reliable=True, transient_local=True, depth=1)


def test_subscription_qos_matches_every_publisher():
    assert subscription_qos([BE], depth=100) == QosChoice(False, False, 100)
    assert subscription_qos([REL, BE], depth=7) == QosChoice(False, False, 7)
    assert subscription_qos([LATCH], depth=3) == QosChoice(True, True, 3)
    assert subscription_qos([LATCH, REL], depth=3) == QosChoice(True, False, 3)
    assert subscription_qos([], depth=1) == QosChoice(True, False, 1)


def test_publisher_qos_keeps_durability_and_reliability():
    assert publisher_qos([LATCH]) == QosChoice(True, True, 1)
    assert publisher_qos([BE]) == QosChoice(False, False, 100)
    assert publisher_qos([REL]).reliable
    deep = make_qos(reliable=True, transient_local=True, depth=4)
    assert publisher_qos([LATCH, deep]) == QosChoice(True, True, 4)


def test_select_topics():
    names = ['/clock', '/rosout', '/rover1/imu', '/rover2/imu', '/rover1/stereo/left/image_raw']
    assert select_topics(names, exclude=['/rosout']) == sorted(set(names) - {'/rosout'})
    assert select_topics(names, include=['/rover1/*']) == ['/rover1/imu',
                                                           '/rover1/stereo/left/image_raw']
    assert select_topics(names, include=['/rover*/imu', '/clock'],
                         exclude=['/rover2/*']) == ['/clock', '/rover1/imu']


def test_remaps():
    rules = parse_remaps(['/rover1/:=/rover3/', '/rover1/imu:=/imu_raw', '/a/b/:=/c/'])
    assert remap_topic('/rover1/imu', rules) == '/imu_raw'           # exact rule first
    assert remap_topic('/rover1/arm/wrench', rules) == '/rover3/arm/wrench'
    assert remap_topic('/a/b/x', rules) == '/c/x'
    assert remap_topic('/rover2/imu', rules) == '/rover2/imu'
    longest = parse_remaps(['/r/:=/x/', '/r/s/:=/y/'])
    assert remap_topic('/r/s/t', longest) == '/y/t'
    for bad in ['/a=/b', 'a:=/b', '/a:=b', '/ns/:=/x']:
        with pytest.raises(RemapError):
            parse_remaps([bad])


def _msgs(n=10, dt=5_000_000, t0=1_000_000_000):
    return [('/imu', t0 + i * dt, i) for i in range(n)]


def test_schedule_timing_rate_and_order():
    ev = list(schedule(_msgs(), start_ns=1_000_000_000, rate=2.0))
    assert [e.payload for e in ev] == list(range(10))
    assert [e.due_s for e in ev] == pytest.approx([i * 0.0025 for i in range(10)])
    with pytest.raises(ValueError, match='rate'):
        list(schedule(_msgs(), start_ns=0, rate=0.0))


def test_schedule_start_offset_and_latched():
    msgs = [('/truth', 999_000_000, 'T0'), ('/truth', 1_010_000_000, 'T1')] + _msgs()
    msgs.sort(key=lambda m: m[1])
    ev = list(schedule(msgs, start_ns=1_012_000_000, latched=frozenset({'/truth'})))
    # the last latched message before the offset comes first, then 1.015 s onwards
    assert [(e.topic, e.payload) for e in ev][:2] == [('/truth', 'T1'), ('/imu', 3)]
    assert ev[1].due_s == pytest.approx(0.003)
    assert [e.payload for e in ev[1:]] == list(range(3, 10))
    only_latched = list(schedule([('/truth', 5, 'x')], start_ns=10, latched=frozenset({'/truth'})))
    assert [(e.topic, e.payload) for e in only_latched] == [('/truth', 'x')]


def test_schedule_clock_ticks_precede_messages():
    rng = random.Random(4)
    times = sorted(rng.randrange(0, 100_000_000) for _ in range(200))
    ev = list(schedule([('/x', t, t) for t in times], start_ns=0, clock_period_ns=5_000_000))
    clock = -1
    for e in ev:
        if e.topic is None:
            assert e.t_ns > clock
            clock = e.t_ns
        else:
            assert e.t_ns >= clock and e.t_ns - clock < 5_000_000   # clock never ahead, <1 tick
    due = [e.due_s for e in ev]
    assert due == sorted(due)
    assert sum(e.topic is None for e in ev) == times[-1] // 5_000_000 + 1


def test_summarize_lateness():
    s = summarize_lateness([0.001, 0.002, 0.0005, 0.010])
    assert s['n'] == 4 and s['median_ms'] == pytest.approx(2.0)
    assert s['max_ms'] == pytest.approx(10)
    assert summarize_lateness([])['n'] == 0


def test_names_relative_to_the_team_namespace():
    assert bag_topic('/team_a/rover1/imu', '/team_a') == '/rover1/imu'
    assert bag_topic('/team_b/rover1/imu', '/team_a') is None
    assert bag_topic('/team_ab/x', '/team_a') is None
    assert bag_topic('/clock', '/team_a') == '/clock'
    assert bag_topic('/rover1/imu', '/') == '/rover1/imu'
    assert play_topic('/rover1/imu') == 'rover1/imu' and play_topic('/clock') == '/clock'
