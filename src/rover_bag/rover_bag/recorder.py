"""`record`: subscribe (serialized, never deserializing) to all or chosen topics with QoS matched
to their publishers and write a rosbag2 MCAP bag (rover_bag.bagio.BagWriter).

    record -o bags/run1 --ros-args -p topics:="['/rover1/*', '/clock']" -p max_bag_size_mb:=100

Topics are (re)discovered every `discovery_period_s`. Messages the middleware reports lost are
counted per topic, logged and written into the bag's custom_data. SIGINT/SIGTERM close the bag;
a killed recorder leaves everything up to the last periodic flush readable.
"""
from __future__ import annotations

import argparse
import datetime
import importlib
import sys
from collections import Counter
from typing import Any

import rclpy
from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.executors import SingleThreadedExecutor
from rclpy.experimental.events_executor import EventsExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from coop_common.node_util import ParamSpec, declare_parameters
from coop_common.seqgaps import SequenceGaps

from .bagio import COMPRESSIONS, BagWriter, UnknownTypeError, make_qos, make_typestore
from .cli import spin_until_stopped
from .playback import QosChoice, bag_topic, select_topics, subscription_qos

PARAMS = {
    'output': ParamSpec('', 'bag directory to create (must not exist); empty: '
                        'rosbag2_<UTC date_time> in the working directory', read_only=True),
    'topics': ParamSpec([''], 'topics to record, fnmatch patterns (empty list / [""]: all)',
                        read_only=True),
    'exclude': ParamSpec(['/rosout', '/parameter_events'], 'topics never recorded (fnmatch)',
                         read_only=True),
    'discovery_period_s': ParamSpec(1.0, 'period of topic re-discovery', lo=0.05, hi=60.0,
                                    read_only=True),
    'max_bag_size_mb': ParamSpec(0.0, 'split the bag into a new file after this many MB '
                                 '(0: never)', lo=0.0, hi=1e6, read_only=True),
    'max_bag_duration_s': ParamSpec(0.0, 'split after this much recorded time (0: never)',
                                    lo=0.0, hi=1e7, read_only=True),
    'flush_period_s': ParamSpec(1.0, 'finish the current split file at this period (the next '
                                'message starts a new one), so a killed recorder loses at most '
                                'this much', lo=0.05, hi=60.0, read_only=True),
    'compression': ParamSpec('none', 'MCAP chunk compression', choices=COMPRESSIONS,
                             read_only=True),
    'queue_depth': ParamSpec(1000, 'subscription history depth (KEEP_LAST)', lo=1, hi=100000,
                             read_only=True),
    'count_losses': ParamSpec(False, "count the messages that never reached the bag from each "
                              "topic's publication sequence numbers (the middleware reports "
                              'none when a reliable KEEP_LAST queue overflows): exact for a '
                              'topic with one publisher, counted from the first message '
                              'received; spins a SingleThreadedExecutor, which costs more CPU '
                              'per message than the default EventsExecutor', read_only=True),
}


def message_class(msgtype: str) -> Any:
    """The rclpy message class of 'pkg/msg/Name' (raw subscriptions still need the type)."""
    pkg, kind, name = msgtype.split('/')
    try:
        return getattr(importlib.import_module(f'{pkg}.{kind}'), name)
    except (ImportError, AttributeError) as exc:
        raise UnknownTypeError(f'no Python message class for {msgtype!r}: {exc}') from None


def qos_profile(choice: QosChoice) -> QoSProfile:
    """The rclpy profile of a QosChoice (KEEP_LAST of its depth)."""
    return QoSProfile(
        depth=choice.depth, history=HistoryPolicy.KEEP_LAST,
        reliability=(ReliabilityPolicy.RELIABLE if choice.reliable
                     else ReliabilityPolicy.BEST_EFFORT),
        durability=(DurabilityPolicy.TRANSIENT_LOCAL if choice.transient_local
                    else DurabilityPolicy.VOLATILE))


def _rosbags_qos(profile: QoSProfile):
    return make_qos(reliable=profile.reliability == ReliabilityPolicy.RELIABLE,
                    transient_local=profile.durability == DurabilityPolicy.TRANSIENT_LOCAL,
                    depth=int(profile.depth),
                    keep_all=profile.history == HistoryPolicy.KEEP_ALL)


class Recorder(Node):
    """Thin node around BagWriter: discovery, raw subscriptions, drop counting, flushing."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__('rover_bag_recorder', **kwargs)
        p = declare_parameters(self, PARAMS)
        out = p['output'] or datetime.datetime.now(datetime.UTC).strftime(
            'rosbag2_%Y_%m_%d-%H_%M_%S')
        self._include = [t for t in p['topics'] if t]
        self._exclude = list(p['exclude'])
        self._queue_depth = int(p['queue_depth'])
        self.bag = BagWriter(out, typestore=make_typestore(),
                             max_bytes=int(p['max_bag_size_mb'] * 1e6),
                             max_duration_s=float(p['max_bag_duration_s']),
                             compression=p['compression'])
        self.lost: Counter[str] = Counter()
        self.received: Counter[str] = Counter()
        self.count_losses = bool(p['count_losses'])
        #: per topic: messages missing between the ones received (publication sequence numbers)
        self.gaps = SequenceGaps()
        self._several_publishers: set[str] = set()     # not countable from sequence numbers
        self._subs: dict[str, Any] = {}
        self._skipped: set[str] = set()
        self.get_logger().info(f'recording to {self.bag.path} '
                               f'(topics: {self._include or "all"})')
        self.discover()
        # wall-clock timers: with use_sim_time a ROS-clock timer waits for /clock, so a recorder
        # started before the time source (e.g. before `play -p wait_for_subscribers_s:=...`,
        # which publishes no /clock until it has subscribers) would never subscribe, and a
        # paused sim would stop the flushes
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(p['discovery_period_s'], self.discover, clock=steady)
        self.create_timer(p['flush_period_s'], self.bag.flush, clock=steady)

    def discover(self) -> None:
        """Subscribe to every new matching topic that has a publisher."""
        # under a namespace only its topics, named relative to it (playback.bag_topic)
        ns = self.get_namespace()
        full: dict[str, str] = {}
        names_types: dict[str, list[str]] = {}
        for name, types in self.get_topic_names_and_types():
            if (local := bag_topic(name, ns)) is not None:
                full[local], names_types[local] = name, types
        for topic in select_topics(names_types, include=self._include, exclude=self._exclude):
            if topic in self._subs and self.count_losses and \
                    topic not in self._several_publishers and \
                    self.count_publishers(full[topic]) > 1:
                # each writer numbers its own messages, and rclpy's message info does not say
                # whose a message is
                self._several_publishers.add(topic)
                self.get_logger().warn(f'{topic}: several publishers, its losses are not '
                                       'counted')
            if topic in self._subs or topic in self._skipped:
                continue
            types = names_types[topic]
            if len(types) != 1:
                self._skip(topic, f'published with several types {types}')
                continue
            infos = self.get_publishers_info_by_topic(full[topic])
            if not infos:
                continue      # only subscribers so far: no QoS to match yet
            msgtype = types[0]
            offered = [_rosbags_qos(i.qos_profile) for i in infos]
            try:
                cls = message_class(msgtype)
                self.bag.add_topic(topic, msgtype, offered_qos=offered)
            except UnknownTypeError as exc:
                self._skip(topic, str(exc))
                continue
            choice = subscription_qos(offered, depth=self._queue_depth)
            qos = qos_profile(choice)
            events = SubscriptionEventCallbacks(
                message_lost=lambda info, t=topic: self._on_lost(t, info))
            self._subs[topic] = self.create_subscription(
                cls, full[topic], self._make_callback(topic), qos, raw=True,
                event_callbacks=events)
            self.get_logger().info(
                f'subscribed {topic} [{msgtype}] '
                f'{"reliable" if choice.reliable else "best effort"}'
                f'{" transient local" if choice.transient_local else ""}')

    def _skip(self, topic: str, reason: str) -> None:
        self._skipped.add(topic)
        self.get_logger().warn(f'not recording {topic}: {reason}')

    def _make_callback(self, topic: str):
        """The raw callback of `topic`: one message, written as it came. The recorder spins an
        EventsExecutor (`main`), which hands over each message as an event; rclpy's
        SingleThreadedExecutor would rebuild its wait set from every subscription and QoS
        event handler for each message (~1 ms with the ~50 topics and their handlers of a
        mission), and took the recorder to a quarter of the graph's CPU time."""
        write = self.bag.write
        received = self.received
        clock = self.get_clock()

        def on_message(data: bytes) -> None:
            # stamped by the node's clock when taken (rosbag2's way): the sim's with
            # use_sim_time, else the system's (the EventsExecutor passes no message info)
            write(topic, clock.now().nanoseconds, data)
            received[topic] += 1
        if not self.count_losses:
            return on_message
        seen = self.gaps.seen

        def on_message_counted(data: bytes, info: dict) -> None:
            on_message(data)
            seq = info.get('publication_sequence_number')
            if seq is not None:
                seen(topic, seq)
        return on_message_counted

    def _on_lost(self, topic: str, info: Any) -> None:
        self.lost[topic] += int(info.total_count_change)
        self.get_logger().warn(f'{topic}: {self.lost[topic]} message(s) lost so far',
                               throttle_duration_sec=2.0)

    def close(self) -> None:
        """Close the bag (metadata.yaml written), report counts and losses."""
        if self.lost:
            self.bag.custom_data['messages_lost'] = ', '.join(
                f'{t}: {n}' for t, n in sorted(self.lost.items()))
        missed = {t: n for t, n in self.gaps.missed.items()
                  if t not in self._several_publishers}
        if self.count_losses:
            self.bag.custom_data['messages_missed'] = ', '.join(
                f'{t}: {n}' for t, n in sorted(missed.items())) or 'none'
            if self._several_publishers:
                self.bag.custom_data['messages_missed_not_counted'] = ', '.join(
                    sorted(self._several_publishers))
        self.bag.close()
        total = sum(self.received.values())
        # after SIGINT the context is gone and the node logger's /rosout publisher with it
        logger = (self.get_logger() if self.context.ok()
                  else rclpy.logging.get_logger('record'))
        logger.info(
            f'closed {self.bag.path}: {total} messages on {len(self.received)} topics, '
            f'{sum(self.lost.values())} lost'
            + (f' ({dict(self.lost)})' if self.lost else '')
            + (f', {sum(missed.values())} missed by sequence number'
               + (f' ({missed})' if missed else '') if self.count_losses else ''))

    def destroy_node(self) -> None:
        try:
            self.close()
        finally:
            super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run rover_bag record`."""
    argv = sys.argv if args is None else args
    cli = argparse.ArgumentParser(prog='record', description=__doc__.split('\n\n')[0])
    cli.add_argument('-o', '--output', help='bag directory (same as -p output:=...)')
    cli.add_argument('topics', nargs='*', help='topics to record (same as -p topics:=[...])')
    ns = cli.parse_args(rclpy.utilities.remove_ros_args(argv)[1:])
    overrides = []

    if ns.output:
        overrides.append(Parameter('output', value=ns.output))
    if ns.topics:
        overrides.append(Parameter('topics', value=ns.topics))
    # a KeyboardInterrupt raised in the middle of a write callback would leave the bag's
    # counts one message off: signals only set a flag (cli.spin_until_stopped)
    made: list[Recorder] = []

    def make() -> Recorder:
        made.append(Recorder(parameter_overrides=overrides))
        return made[0]

    def executor() -> Any:
        # the EventsExecutor passes no message info (a callback that takes it fails)
        return SingleThreadedExecutor() if made[0].count_losses else EventsExecutor()
    return spin_until_stopped(make, argv, logger='record', executor_factory=executor)


if __name__ == '__main__':
    sys.exit(main())
