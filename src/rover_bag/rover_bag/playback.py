"""Plain pieces of record and play (no rclpy): QoS matching, topic selection, remapping and the
playback schedule. The recorder and player nodes only wire these to DDS."""
from __future__ import annotations

import fnmatch
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple

from rosbags.interfaces import Qos, QosDurability, QosReliability

from .errors import BagError


@dataclass(frozen=True)
class QosChoice:
    """The policies the recorder subscribes with / the player publishes with."""

    reliable: bool
    transient_local: bool
    depth: int


def subscription_qos(offered: Sequence[Qos], *, depth: int) -> QosChoice:
    """QoS that matches every publisher offering `offered` (rosbag2's adaptive choice).

    RELIABLE only if all publishers are reliable (a reliable reader does not match a best-effort
    writer); TRANSIENT_LOCAL only if all are transient local (same rule for durability). No
    publisher known: reliable + volatile, which matches reliable volatile publishers."""
    if not offered:
        return QosChoice(True, False, depth)
    reliable = all(q.reliability == QosReliability.RELIABLE for q in offered)
    latched = all(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    return QosChoice(reliable, latched, depth)


def publisher_qos(offered: Sequence[Qos], *, depth: int = 100) -> QosChoice:
    """QoS the player offers for a recorded topic: the recorded reliability and durability, so
    a latched topic stays TRANSIENT_LOCAL (depth = the recorded depth, so late joiners get what
    a late joiner of the original publisher got) and a sensor stream stays best effort."""
    if not offered:
        return QosChoice(True, False, depth)
    reliable = all(q.reliability == QosReliability.RELIABLE for q in offered)
    latched = any(q.durability == QosDurability.TRANSIENT_LOCAL for q in offered)
    if latched:
        return QosChoice(True, True, max(1, *(q.depth for q in offered)))
    return QosChoice(reliable, False, depth)


def select_topics(available: Iterable[str], *, include: Sequence[str] = (),
                  exclude: Sequence[str] = ()) -> list[str]:
    """Topics to record: `include` patterns (fnmatch; empty: all) minus `exclude` patterns."""
    out = []
    for name in available:
        if include and not any(fnmatch.fnmatchcase(name, p) for p in include):
            continue
        if any(fnmatch.fnmatchcase(name, p) for p in exclude):
            continue
        out.append(name)
    return sorted(out)


class RemapError(BagError, ValueError):
    """A remap rule is not 'from:=to' with absolute names."""


def bag_topic(topic: str, namespace: str) -> str | None:
    """The name a recorder running in `namespace` stores `topic` under: relative to that
    namespace (written with a leading '/', as rosbag2 stores names), so a team's bag replays
    into any team; `/clock`, the one global name, as it is; None for a topic outside it."""
    if topic == '/clock' or namespace in ('', '/'):
        return topic
    prefix = namespace.rstrip('/') + '/'
    return '/' + topic[len(prefix):] if topic.startswith(prefix) else None


def play_topic(name: str) -> str:
    """The name a recorded topic is published under: relative to the player's namespace (at
    the root namespace the recorded name itself), `/clock` absolute."""
    return name if name == '/clock' else name.lstrip('/')


def parse_remaps(rules: Sequence[str]) -> list[tuple[str, str]]:
    """'from:=to' rules. A rule whose `from` ends with '/' renames a namespace prefix
    ('/rover1/:=/rover3/'), any other rule one topic. Names must be absolute."""
    out = []
    for rule in rules:
        src, sep, dst = rule.partition(':=')
        if not sep or not src.startswith('/') or not dst.startswith('/'):
            raise RemapError(f'remap rule {rule!r} is not "/from:=/to"')
        if src.endswith('/') != dst.endswith('/'):
            raise RemapError(f'remap rule {rule!r}: a namespace rule needs "/" at both ends')
        out.append((src, dst))
    return out


def remap_topic(topic: str, rules: Sequence[tuple[str, str]]) -> str:
    """Apply the first matching rule (exact topic first, then the longest namespace prefix)."""
    for src, dst in rules:
        if not src.endswith('/') and topic == src:
            return dst
    best = max((r for r in rules if r[0].endswith('/') and topic.startswith(r[0])),
               key=lambda r: len(r[0]), default=None)
    return best[1] + topic[len(best[0]):] if best else topic


class Event(NamedTuple):
    """One publication of the playback: at `due_s` after playback start (wall time, rate
    applied) publish `payload` on `topic` (topic None: a /clock tick at bag time `t_ns`)."""

    due_s: float
    t_ns: int
    topic: str | None
    payload: Any


def schedule(messages: Iterable[tuple[str, int, Any]], *, start_ns: int, rate: float = 1.0,
             clock_period_ns: int = 0, latched: frozenset[str] = frozenset()
             ) -> Iterator[Event]:
    """The playback timeline of time-ordered (topic, t_ns, payload) from bag time `start_ns`.

    Messages before `start_ns` are skipped, except the last one of each `latched` topic, which
    is published at the start (what a late joiner of the original publisher would have got).
    With `clock_period_ns` > 0 a /clock tick is scheduled every period of bag time from
    `start_ns`, each tick before the messages of the same time, so nodes with use_sim_time never
    see a message stamped ahead of their clock.
    """
    if not rate > 0:
        raise ValueError(f'rate must be > 0, got {rate}')
    pending_latched: dict[str, tuple[int, Any]] = {}
    next_tick = start_ns
    started = False

    def due(t: int) -> float:
        return (t - start_ns) / 1e9 / rate

    for topic, t, payload in messages:
        if t < start_ns:
            if topic in latched:
                pending_latched[topic] = (t, payload)
            continue
        if not started:
            started = True
            if clock_period_ns > 0:
                yield Event(0.0, start_ns, None, None)
                next_tick = start_ns + clock_period_ns
            for ltopic, (_lt, lpayload) in pending_latched.items():
                yield Event(0.0, start_ns, ltopic, lpayload)
        while clock_period_ns > 0 and next_tick <= t:
            yield Event(due(next_tick), next_tick, None, None)
            next_tick += clock_period_ns
        yield Event(due(t), t, topic, payload)
    if not started:
        for ltopic, (_lt, lpayload) in pending_latched.items():
            yield Event(0.0, start_ns, ltopic, lpayload)


def summarize_lateness(late_s: Sequence[float]) -> dict[str, float]:
    """Median / p99 / max of publish lateness (s) behind the schedule, for the player's report."""
    if not late_s:
        return {'n': 0, 'median_ms': 0.0, 'p99_ms': 0.0, 'max_ms': 0.0}
    xs = sorted(late_s)
    n = len(xs)
    return {'n': n, 'median_ms': 1e3 * xs[n // 2], 'p99_ms': 1e3 * xs[min(n - 1, int(0.99 * n))],
            'max_ms': 1e3 * xs[-1]}
