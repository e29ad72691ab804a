"""A node's part in rover_sim's lockstep rounds (coop_common.lockstep; docs/design.md).

`Lockstep(node, enabled)` stands between a node and the topics on which it closes a loop on the
simulator. Disabled (a live run, paced by the clock), `subscription` and `publisher` are
rclpy's own. Enabled, the node answers the simulator's `sim/lockstep/tick` once per round:

1. the round's messages (the tick counts them per topic) are taken from what arrived and handed
   to the node's callbacks sorted by stamp, then by the order of the `subscription` calls;
2. the `on_round` callbacks run (a node wakes its action coroutines there);
3. once the node is idle (its woken coroutines have run to their next wait, and every request
   passed to `hold` has its answer), it acks the round with the count of what it published.

The node's executor must be single-threaded (the order of 1-3 is the executor's), and every
message the simulator or another participant must count goes through `publisher`.
"""
from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Any

from rclpy.clock import Clock, ClockType
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.exceptions import InvalidHandle
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.task import Future

from coop_msgs.msg import LockstepAck, LockstepTick

from .lockstep import Inbox
from .qos import reliable

TICK_TOPIC = 'sim/lockstep/tick'
ACK_TOPIC = 'sim/lockstep/ack'
#: ticks and acks: none may be lost, a round's worth may queue
ROUND_QOS = QoSProfile(depth=100, history=HistoryPolicy.KEEP_LAST,
                       reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.VOLATILE)
#: no QoS-event handlers on the lockstep endpoints: rclpy's executor rebuilds its wait set
#: with every waitable at every message, and the default handlers (a warning on an
#: incompatible QoS or type) are two per endpoint; a lockstep end left unmatched is reported
#: by the round-0 wait instead (Lockstep._unconnected)
QUIET_SUB = SubscriptionEventCallbacks(use_default_callbacks=False)
QUIET_PUB = PublisherEventCallbacks(use_default_callbacks=False)


def remap_args(sim_namespace: str = '') -> list[str]:
    """The `--ros-args` remappings that point a participant in another namespace than the
    simulator's (a rover's node under /rover1) at the simulator's tick and ack topics."""
    base = '/' + sim_namespace.strip('/') if sim_namespace.strip('/') else ''
    return [a for topic in (TICK_TOPIC, ACK_TOPIC) for a in ('-r', f'{topic}:={base}/{topic}')]


def stamp_of(msg: Any) -> float:
    """The message header's stamp (s), -inf for a message without a header."""
    header = getattr(msg, 'header', None)
    if header is None:
        return -math.inf
    return header.stamp.sec + 1e-9 * header.stamp.nanosec


class CountingPublisher:
    """An rclpy publisher that counts what it sends for the next ack."""

    def __init__(self, publisher: Any, counts: Counter, lock: threading.Lock) -> None:
        self._pub, self._counts, self._lock = publisher, counts, lock

    @property
    def topic_name(self) -> str:
        return self._pub.topic_name

    def publish(self, msg: Any) -> None:
        with self._lock:
            self._pub.publish(msg)
            self._counts[self._pub.topic_name] += 1

    def get_subscription_count(self) -> int:
        return self._pub.get_subscription_count()


class Lockstep:
    """A node's side of the lockstep rounds (module docstring); rclpy's own when disabled."""

    def __init__(self, node: Node, enabled: bool, *, timeout_s: float = 10.0) -> None:
        self.node = node
        self.enabled = enabled
        self.timeout_s = timeout_s
        self.round = -1                      # the last round handed to the node
        self.stamp_s = math.nan              # its stamp (sim s)
        self._callbacks: dict[str, Callable[[Any], None]] = {}
        self._subscriptions: dict[str, Any] = {}
        self._publishers: list[CountingPublisher] = []
        self._on_round: list[Callable[[], None]] = []
        self._inbox = Inbox()
        self._ticks: deque[LockstepTick] = deque()
        self._holds: set[Future] = set()
        self._lock = threading.Lock()        # the counts: a publisher may be on another thread
        self._counts: Counter = Counter()
        self._unacked: int | None = None     # a round handed out, not acked yet
        self._last_ack: LockstepAck | None = None
        self._since = time.monotonic()       # when the node began to wait for what it lacks
        self._warned = 0.0
        if not enabled:
            return
        self._ack_pub = node.create_publisher(LockstepAck, ACK_TOPIC, ROUND_QOS,
                                              event_callbacks=QUIET_PUB)
        node.create_subscription(LockstepTick, TICK_TOPIC, self._on_tick, ROUND_QOS,
                                 event_callbacks=QUIET_SUB)
        # the ack goes out from a guard condition's callback: after the tasks the round woke
        self._idle = node.create_guard_condition(self._ack_when_idle)
        node.create_timer(1.0, self._check_stalled, clock=Clock(clock_type=ClockType.STEADY_TIME))
        node.get_logger().info(f'lockstep: answering {node.resolve_topic_name(TICK_TOPIC)}')

    # -- the node's side --------------------------------------------------------------------
    def subscription(self, msg_type: Any, topic: str, callback: Callable[[Any], None],
                     qos: QoSProfile) -> Any:
        """node.create_subscription, or in lockstep one whose messages wait for their round."""
        if not self.enabled:
            return self.node.create_subscription(msg_type, topic, callback, qos)
        name = self.node.resolve_topic_name(topic)
        self._inbox.listen(name)
        self._callbacks[name] = callback
        sub = self._subscriptions[name] = self.node.create_subscription(
            msg_type, topic, lambda m, n=name: self._arrived(n, m), reliable(qos),
            event_callbacks=QUIET_SUB)
        return sub

    def publisher(self, msg_type: Any, topic: str, qos: QoSProfile) -> Any:
        """node.create_publisher, or in lockstep a reliable one counted in the acks."""
        if not self.enabled:
            return self.node.create_publisher(msg_type, topic, qos)
        pub = CountingPublisher(self.node.create_publisher(msg_type, topic, reliable(qos),
                                                           event_callbacks=QUIET_PUB),
                                self._counts, self._lock)
        self._publishers.append(pub)
        return pub

    def on_round(self, callback: Callable[[], None]) -> None:
        """Call `callback` after each round's messages (lockstep only)."""
        self._on_round.append(callback)

    def hold(self, future: Future) -> Future:
        """Answer no round before `future` is done (a service or action request whose answer
        must act in the round it was asked in); returns `future`."""
        if self.enabled and not future.done():
            self._holds.add(future)
            future.add_done_callback(self._released)
        return future

    def now_s(self, fallback: Callable[[], float]) -> float:
        """The round's stamp in lockstep (what the node has been told of sim time), else
        `fallback()` (the node's clock)."""
        return self.stamp_s if self.enabled and math.isfinite(self.stamp_s) else fallback()

    # -- the rounds -------------------------------------------------------------------------
    def _released(self, future: Future) -> None:
        self._holds.discard(future)
        self._idle.trigger()

    def _arrived(self, topic: str, msg: Any) -> None:
        self._inbox.put(topic, stamp_of(msg), msg)
        self._advance()

    def _on_tick(self, tick: LockstepTick) -> None:
        last = self._last_ack
        if last is not None and tick.round == last.round:
            self._ack_pub.publish(last)         # round 0 again: the simulator missed the ack
        if tick.round <= self.round or (self._ticks and tick.round <= self._ticks[-1].round):
            # a repeated round 0, handed out already or waiting: never handed out twice (a
            # round held while the simulator repeats its tick would be), but its topics may
            # be connected now
            self._advance()
            return
        if not self._ticks and self._unacked is None:
            self._since = time.monotonic()
        self._ticks.append(tick)
        self._take_queued()
        self._advance()

    def _take_queued(self) -> None:
        """Move what has arrived on the lockstep topics into the inbox at once: the round's
        messages mostly come just before its tick, and rclpy's executor would otherwise wake,
        rebuild its wait set and dispatch once per message (the bulk of a participant's CPU
        time); one that arrives later still comes through its subscription's callback."""
        for name, sub in self._subscriptions.items():
            try:
                with sub.handle:
                    while (taken := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                        self._inbox.put(name, stamp_of(taken[0]), taken[0])
            except InvalidHandle:       # destroyed with its node (a shutdown under way)
                continue

    def _advance(self) -> None:
        """Hand out the next round once its messages are all here and the last one is acked."""
        if self._unacked is not None or self._holds or not self._ticks:
            return
        tick = self._ticks[0]
        counts = dict(zip(tick.topics, tick.counts, strict=False))
        if self._inbox.missing(counts) or (tick.round == 0 and self._unconnected()):
            return
        self._ticks.popleft()
        self.round = int(tick.round)
        self.stamp_s = tick.stamp.sec + 1e-9 * tick.stamp.nanosec
        self._unacked = self.round
        for topic, msg in self._inbox.take(counts):
            self._callbacks[topic](msg)
        for cb in self._on_round:
            cb()
        self._idle.trigger()

    def _unconnected(self) -> list[str]:
        """The lockstep topics with no one at the other end yet: round 0 is answered only
        once there is (a message sent before the two ends are matched would be counted in a
        tick and never arrive)."""
        return ([t for t in self._inbox.topics if not self.node.count_publishers(t)]
                + [p.topic_name for p in self._publishers if not p.get_subscription_count()])

    def _ack_when_idle(self) -> None:
        if self._holds:
            return
        if self._unacked is None:       # a hold between rounds ended: the next may be due
            self._advance()
            return
        with self._lock:
            counts = dict(self._counts)
            self._counts.clear()        # in place: the counting publishers hold this Counter
        ack = LockstepAck(node=self.node.get_fully_qualified_name(), round=self._unacked,
                          topics=list(counts), counts=[int(v) for v in counts.values()],
                          listens=list(self._inbox.topics) if self._unacked == 0 else [])
        self._unacked = None
        self._last_ack = ack
        self._since = time.monotonic()
        self._ack_pub.publish(ack)
        self._advance()

    def _check_stalled(self) -> None:
        """Say what the node waits for, once per timeout, while it waits."""
        waiting = self._unacked is not None or self._ticks
        now = time.monotonic()
        if not waiting or now - self._since < self.timeout_s or now - self._warned < \
                self.timeout_s:
            return
        self._warned = now
        if self._holds:
            what = f'{len(self._holds)} request(s) it holds the round for'
        elif self._unacked is not None:
            what = 'its own tasks to settle'
        elif self._ticks[0].round == 0 and self._unconnected():
            what = f'the other end of {", ".join(self._unconnected())}'
        else:
            tick = self._ticks[0]
            what = f'messages of round {tick.round}: ' + str(
                self._inbox.missing(dict(zip(tick.topics, tick.counts, strict=False))))
        self.node.get_logger().warn(f'lockstep: waiting {now - self._since:.0f} s for {what}')


class Pacer:
    """The participant that runs an experiment: it holds the simulator at a round until told
    to let it step `n` more (`run`), so that the experiment's own steps (a reset, a goal sent,
    a result read) fall between the same two rounds on any machine. Its `run` and `stop` may
    be called from another thread than the node's executor."""

    def __init__(self, ls: Lockstep) -> None:
        self._ls = ls
        self._left: float = 0                # rounds to answer before holding (inf: until told)
        self._pause: Future | None = None
        ls.on_round(self._on_round)

    def _on_round(self) -> None:
        if self._left > 0:
            self._left -= 1
        elif self._pause is None:
            self._pause = self._ls.hold(Future())

    @property
    def paused(self) -> bool:
        """The simulator stands at a round this participant has not answered."""
        return self._pause is not None

    def run(self, rounds: float = math.inf) -> None:
        """Let the simulator step `rounds` more rounds (math.inf: until `stop`), then hold."""
        self._left = rounds
        pause, self._pause = self._pause, None
        if pause is not None:
            pause.set_result(None)

    def stop(self) -> None:
        """Hold the simulator at its next round."""
        self._left = 0
