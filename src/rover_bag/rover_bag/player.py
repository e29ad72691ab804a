"""`play`: publish a bag into the live graph with its recorded timing (serialized bytes, never
deserialized), optionally publishing /clock so nodes with use_sim_time follow bag time.

    play bags/ident_run --ros-args -p rate:=2.0 -p loop:=true -p remap:="['/rover1/:=/rover2/']"

Latched (transient local) topics are published transient local again. With publish_clock the
bag's own /clock topic is not replayed (the player's ticks replace it). Exits when the bag ends
(unless loop), logging how late publications were behind the schedule.
"""
from __future__ import annotations

import argparse
import itertools
import sys
import threading
import time
from collections import deque
from typing import Any

import rclpy
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosgraph_msgs.msg import Clock

from coop_common.node_util import ParamSpec, declare_parameters
from coop_common.qos import CLOCK_QOS, overridable

from .bagio import bag_info, read_messages
from .cli import spin_until_stopped
from .playback import (
    parse_remaps,
    play_topic,
    publisher_qos,
    remap_topic,
    schedule,
    summarize_lateness,
)
from .recorder import message_class, qos_profile

PARAMS = {
    'bag': ParamSpec('', 'bag directory or .mcap file to play', read_only=True),
    'rate': ParamSpec(1.0, 'playback speed factor (2: twice as fast)', lo=0.01, hi=100.0,
                      read_only=True),
    'loop': ParamSpec(False, 'start over at the end', read_only=True),
    'start_offset_s': ParamSpec(0.0, 'skip this much bag time from the start', lo=0.0, hi=1e7,
                                read_only=True),
    'topics': ParamSpec([''], 'topics to play (exact names; empty list / [""]: all)',
                        read_only=True),
    'remap': ParamSpec([''], '"/from:=/to" rules; "/ns/:=/other/" renames a namespace',
                       read_only=True),
    'publish_clock': ParamSpec(True, 'publish /clock from bag time', read_only=True),
    'clock_rate_hz': ParamSpec(200.0, '/clock ticks per second of bag time', lo=1.0, hi=10000.0,
                               read_only=True),
    'wait_for_subscribers_s': ParamSpec(0.0, 'before playing, wait up to this long until every '
                                        'publisher has a subscriber (0: do not wait)', lo=0.0,
                                        hi=600.0, read_only=True),
}


class Player(Node):
    """Thin node: publishers from the bag's topics, a playback thread following `schedule`."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('rover_bag_player', **kwargs)
        p = declare_parameters(self, PARAMS)
        if not p['bag']:
            raise ValueError('no bag given (play BAG or -p bag:=BAG)')
        self.params = p
        self.info = bag_info(p['bag'])
        for problem in self.info.problems:
            self.get_logger().warn(f'{p["bag"]}: {problem}')
        if p['start_offset_s'] > 0 and p['start_offset_s'] >= self.info.duration_s:
            raise ValueError(f'start_offset_s {p["start_offset_s"]} is not within the bag '
                             f'({self.info.duration_s:.3f} s)')
        rules = parse_remaps([r for r in p['remap'] if r])
        wanted = [t for t in p['topics'] if t]
        absent = sorted(set(wanted) - set(self.info.topics))
        if absent:
            raise ValueError(f'topic(s) {absent} not in {p["bag"]}')
        self.clock_pub = (self.create_publisher(Clock, '/clock', CLOCK_QOS)
                          if p['publish_clock'] else None)
        self.pubs: dict[str, Any] = {}
        self.latched: set[str] = set()
        for name, topic in self.info.topics.items():
            if wanted and name not in wanted:
                continue
            if name == '/clock' and self.clock_pub is not None:
                continue
            choice = publisher_qos(topic.offered_qos)
            qos = qos_profile(choice)
            if choice.transient_local:
                self.latched.add(name)
            # QoS overrides (qos_overrides.<topic>.publisher.<policy>) may change it
            self.pubs[name] = self.create_publisher(message_class(topic.msgtype),
                                                    play_topic(remap_topic(name, rules)),
                                                    **overridable(qos))
        if not self.pubs:
            raise ValueError(f'nothing to play in {p["bag"]}')
        self.lateness: deque[float] = deque(maxlen=200_000)   # recent, bounded when looping
        self.published = 0
        self.done = threading.Event()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name='playback', daemon=True)
        self.get_logger().info(
            f'playing {p["bag"]}: {len(self.pubs)} topics, {self.info.duration_s:.2f} s at rate '
            f'{p["rate"]}{" (loop)" if p["loop"] else ""}')
        self._thread.start()

    def _wait_for_subscribers(self, timeout_s: float) -> None:
        """Until every non-latched publisher is matched (latched ones serve late joiners)."""
        pubs = {t: pub for t, pub in self.pubs.items() if t not in self.latched}
        deadline = time.monotonic() + timeout_s
        while not self._stop.is_set() and time.monotonic() < deadline:
            if all(pub.get_subscription_count() > 0 for pub in pubs.values()):
                return
            self._stop.wait(0.01)
        missing = [t for t, pub in pubs.items() if pub.get_subscription_count() == 0]
        if missing:
            self.get_logger().warn(f'no subscriber after {timeout_s} s on {missing}; playing')

    def _run(self) -> None:
        try:
            if self.params['wait_for_subscribers_s'] > 0:
                self._wait_for_subscribers(self.params['wait_for_subscribers_s'])
            while not self._stop.is_set():
                self._play_once()
                if not self.params['loop']:
                    break
        except Exception as exc:  # noqa: BLE001 - reported, then the node ends
            self.get_logger().error(f'playback failed: {exc}')
        finally:
            stats = summarize_lateness(self.lateness)
            self.get_logger().info(
                f'played {self.published} messages; lateness behind schedule median '
                f'{stats["median_ms"]:.3f} ms, p99 {stats["p99_ms"]:.3f} ms, '
                f'max {stats["max_ms"]:.3f} ms')
            self.done.set()

    def _play_once(self) -> None:
        p = self.params
        start_ns = self.info.start_ns + int(p['start_offset_s'] * 1e9)
        period = int(1e9 / p['clock_rate_hz']) if self.clock_pub is not None else 0
        msgs = ((m.topic, m.t_ns, m.msg) for m in read_messages(
            p['bag'], topics=list(self.pubs), raw=True, strict=False))
        events = schedule(msgs, start_ns=start_ns, rate=p['rate'], clock_period_ns=period,
                          latched=frozenset(self.latched))
        clock_msg = Clock()
        pubs = self.pubs
        first = next(events, None)      # opens the bag: not charged to the first deadline
        if first is None:
            return
        t0 = time.perf_counter()
        for ev in itertools.chain((first,), events):
            if self._stop.is_set():
                return
            wait = t0 + ev.due_s - time.perf_counter()
            # sleep, not spin: the CPU is shared; Linux wakes ~0.1 ms late
            if wait > 0 and self._stop.wait(wait):
                return
            self.lateness.append(max(0.0, time.perf_counter() - t0 - ev.due_s))
            if ev.topic is None:
                clock_msg.clock.sec, clock_msg.clock.nanosec = divmod(ev.t_ns, 1_000_000_000)
                self.clock_pub.publish(clock_msg)
            else:
                pubs[ev.topic].publish(ev.payload)
                self.published += 1

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)


def main(args: list[str] | None = None) -> int:
    """`ros2 run rover_bag play`."""
    argv = sys.argv if args is None else args
    cli = argparse.ArgumentParser(prog='play', description=__doc__.split('\n\n')[0])
    cli.add_argument('bag', nargs='?', help='bag directory or .mcap file (same as -p bag:=...)')
    ns = cli.parse_args(rclpy.utilities.remove_ros_args(argv)[1:])
    overrides = [Parameter('bag', value=ns.bag)] if ns.bag else []
    return spin_until_stopped(lambda: Player(parameter_overrides=overrides), argv,
                              logger='play', done=lambda node: node.done.is_set(),
                              before_destroy=lambda node: node.stop())

if __name__ == '__main__':
    sys.exit(main())
