"""Lockstep rounds between the simulator and the nodes that close loops on it (no rclpy).

In lockstep mode (docs/design.md, "Lockstep") the simulator steps in rounds of one control
period. After a round it sends a tick: the round's number and stamp, and how many messages went
out on each topic for it (its own sensor streams, and what the participants published while
handling the round before). A participant takes exactly those messages from its topics, handles
them in one fixed order and answers with an ack that counts what it published. The simulator
steps the next round only when every participant has answered and the commands the acks count
have all arrived. What a node sees and when, in sim time, is then the same on an idle and on a
busy machine: the outcome does not depend on load.

`Gate` is the simulator's book of answers, `Inbox` a participant's (and the simulator's) store
of messages that arrived ahead of the round they belong to.
"""
from __future__ import annotations

import math
from collections import Counter, deque
from collections.abc import Iterable, Mapping
from typing import Any

from .errors import CoopCommonError


class LockstepError(CoopCommonError):
    """An answer that does not fit the rounds: an unknown participant, a round skipped."""


class Gate:
    """The simulator's side: who has answered which round, and what they published."""

    def __init__(self, participants: Iterable[str]) -> None:
        self.participants = tuple(sorted(set(participants)))
        if not self.participants:
            raise LockstepError('lockstep needs at least one participant')
        self._answered = dict.fromkeys(self.participants, -1)
        self._published: dict[int, Counter] = {}
        #: per topic, the participants that take it (their acks of round 0 say which)
        self.listeners: dict[str, set[str]] = {}

    def answer(self, node: str, round_: int, counts: Mapping[str, int],
               listens: Iterable[str] = ()) -> bool:
        """Record `node`'s ack of `round_` with the messages it published per topic (and, in
        round 0, the topics it takes); False for a repeated ack (round 0 is ticked until all
        have answered), LockstepError for a node that is not a participant or a round answered
        out of order."""
        if node not in self._answered:
            raise LockstepError(f'{node} is not a lockstep participant '
                                f'({", ".join(self.participants)})')
        last = self._answered[node]
        if round_ <= last:
            return False
        if round_ != last + 1:
            raise LockstepError(f'{node} answered round {round_} after round {last}')
        if any(c < 0 for c in counts.values()):
            raise LockstepError(f'{node} counted a negative number of messages')
        self._answered[node] = round_
        self._published.setdefault(round_, Counter()).update(counts)
        for topic in listens:
            self.listeners.setdefault(topic, set()).add(node)
        return True

    def waiting_for(self, round_: int) -> list[str]:
        """The participants that have not answered `round_` yet (sorted)."""
        return [p for p in self.participants if self._answered[p] < round_]

    def published(self, round_: int) -> dict[str, int]:
        """What the participants published while handling `round_` (once every one has
        answered it), forgotten from here on."""
        if self.waiting_for(round_):
            raise LockstepError(f'round {round_} is not answered by {self.waiting_for(round_)}')
        return dict(sorted(self._published.pop(round_, Counter()).items()))


class Inbox:
    """Messages of the topics one node listens to, kept until their round: a round takes the
    next `counts[topic]` of each, in arrival order per topic (a topic's messages come in the
    order they were sent), and hands them out sorted by stamp, then by the order the topics
    were listened to: the same order on every run."""

    def __init__(self) -> None:
        self._queues: dict[str, deque[tuple[float, Any]]] = {}

    @property
    def topics(self) -> tuple[str, ...]:
        return tuple(self._queues)

    def listen(self, topic: str) -> None:
        if topic in self._queues:
            raise LockstepError(f'{topic} is listened to twice')
        self._queues[topic] = deque()

    def put(self, topic: str, stamp_s: float, item: Any) -> None:
        """A message of `topic` arrived (`stamp_s`: its header's, -inf without one)."""
        self._queues[topic].append((stamp_s if math.isfinite(stamp_s) else -math.inf, item))

    def missing(self, counts: Mapping[str, int]) -> dict[str, int]:
        """Per topic listened to, how many of the round's messages have not arrived yet."""
        return {t: n - len(self._queues[t]) for t, n in counts.items()
                if t in self._queues and len(self._queues[t]) < n}

    def take(self, counts: Mapping[str, int]) -> list[tuple[str, Any]]:
        """The round's messages, (topic, item) in delivery order (LockstepError while some
        have not arrived)."""
        short = self.missing(counts)
        if short:
            raise LockstepError(f'messages still on their way: {short}')
        order = {t: k for k, t in enumerate(self._queues)}
        got = []
        for topic, n in counts.items():
            q = self._queues.get(topic)
            if q is None:
                continue
            for seq in range(n):
                stamp, item = q.popleft()
                got.append((stamp, order[topic], seq, topic, item))
        got.sort(key=lambda g: g[:3])
        return [(topic, item) for *_, topic, item in got]
