"""The installed `record` and `play` executables over DDS, against in-process test nodes."""
from __future__ import annotations

import os
import re
import signal
import time
from collections import defaultdict
from pathlib import Path

import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rclpy.serialization import serialize_message
from rosbags.interfaces import QosDurability, QosReliability
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Imu
from std_msgs.msg import String

from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import NodeProcess, wait_for
from coop_msgs.msg import Inclinometer
from rover_bag.bagio import (
    BagWriter,
    DamagedBagWarning,
    bag_info,
    make_qos,
    make_typestore,
    read_messages,
)

pytestmark = pytest.mark.graph
RELIABLE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
DEEP_BE = QoSProfile(depth=1000, reliability=ReliabilityPolicy.BEST_EFFORT)


@pytest.fixture
def ros():
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node('rover_bag_test', context=ctx,
                parameter_overrides=[Parameter('use_sim_time', value=True)])
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    yield node, ex
    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()


def spin_until(ex, pred, timeout_s, what, proc=None):
    """Spin the test node until pred(); fail at once with its log if `proc` died meanwhile."""

    def check():
        if proc is not None and not proc.alive() and not pred():
            raise AssertionError(f'{proc.cmd[0]} exited while waiting for {what}:\n'
                                 + proc.log_text())
        return pred()
    wait_for(check, timeout_s, spin=lambda dt: ex.spin_once(timeout_sec=dt), what=what)


def recorded(path: Path, topic: str, **kw):
    return [m for m in read_messages(path, [topic], **kw)]


# ----------------------------------------------------------------------------------------------
# record
# ----------------------------------------------------------------------------------------------

def test_record_round_trip(ros, tmp_path):
    node, ex = ros
    truth = node.create_publisher(String, '/sim/truth', LATCHED_QOS)
    truth.publish(String(data='table 2-1'))          # before the recorder exists: latched
    inc = node.create_publisher(Inclinometer, '/rover1/inclinometer', RELIABLE)
    imu = node.create_publisher(Imu, '/rover1/imu', SENSOR_QOS)
    other = node.create_publisher(String, '/not_recorded', RELIABLE)
    out = tmp_path / 'bag'
    args = ['-p', f'output:={out}', '-p', 'discovery_period_s:=0.1',
            '-p', "topics:=['/rover1/*', '/sim/*']"]
    with NodeProcess('rover_bag', 'record', args, log_path=tmp_path / 'rec.log') as rec:
        spin_until(ex, lambda: inc.get_subscription_count() and imu.get_subscription_count()
                   and truth.get_subscription_count(), 30, 'recorder subscriptions', rec)
        assert other.get_subscription_count() == 0
        t0 = time.perf_counter()
        for i in range(300):
            m = Inclinometer(roll=0.001 * i, pitch=-0.5, saturated=bool(i % 2))
            m.header.frame_id = f'f{i}'
            inc.publish(m)
            u = Imu()
            u.linear_acceleration.x = float(i)
            imu.publish(u)
            other.publish(String(data='x'))
            # paced at the sim's 200 Hz (a rate, not a wait)
            time.sleep(max(0.0, t0 + (i + 1) * 0.005 - time.perf_counter()))
        spin_until(ex, lambda: 'closed' in rec.log_text() or _recovered(out) >= 301, 30,
                   'recorder to receive everything')
        assert rec.stop() == 0, rec.log_text()
    log = rec.log_text()
    assert 'closed' in log and ' 0 lost' in log, log
    info = bag_info(out)
    assert info.problems == []
    assert f'closed {out}: {info.message_count} messages on 3 topics' in log
    assert set(info.topics) == {'/sim/truth', '/rover1/inclinometer', '/rover1/imu'}
    q = info.topics['/sim/truth'].offered_qos[0]
    assert (q.durability, q.reliability) == (QosDurability.TRANSIENT_LOCAL,
                                             QosReliability.RELIABLE)
    assert info.topics['/rover1/imu'].offered_qos[0].reliability == QosReliability.BEST_EFFORT
    incs = recorded(out, '/rover1/inclinometer')
    assert [(m.msg.roll, m.msg.saturated, m.msg.header.frame_id) for m in incs] == [
        (0.001 * i, bool(i % 2), f'f{i}') for i in range(300)]
    assert [m.msg.data for m in recorded(out, '/sim/truth')] == ['table 2-1']
    imus = [m.msg.linear_acceleration.x for m in recorded(out, '/rover1/imu')]
    # best effort: whatever arrived, in order, unaltered
    assert len(imus) >= 270 and imus == sorted(imus)
    assert set(imus) <= {float(i) for i in range(300)}
    t = [m.t_ns for m in incs]
    assert t == sorted(t)


def test_record_counts_what_a_burst_overflowed_from_sequence_numbers(ros, tmp_path):
    """A reliable burst faster than the recorder takes it, into a 10-deep queue: the middleware
    reports few or none of the messages lost (a reliable KEEP_LAST writer drops what it
    overwrites without a word; it says 'lost' only of a gap a reader saw), and the recorder with
    count_losses counts from the publication sequence numbers exactly the messages the bag
    lacks (after the first one it got, a sync message it has in the bag before the burst
    starts)."""
    node, ex = ros
    pub = node.create_publisher(String, '/burst', QoSProfile(
        depth=10, reliability=ReliabilityPolicy.RELIABLE))
    out = tmp_path / 'bag'
    args = ['-p', f'output:={out}', '-p', 'discovery_period_s:=0.1', '-p', 'queue_depth:=10',
            '-p', 'flush_period_s:=0.1', '-p', 'count_losses:=true', '-p', "topics:=['/burst']"]
    n = 20000
    with NodeProcess('rover_bag', 'record', args, log_path=tmp_path / 'rec.log') as rec:
        spin_until(ex, pub.get_subscription_count, 30, 'recorder subscription', rec)
        pub.publish(String(data='sync'))
        spin_until(ex, lambda: _recovered(out) >= 1, 30, 'the sync message in the bag', rec)
        for i in range(n):
            pub.publish(String(data=str(i)))
        # the last one comes (KEEP_LAST keeps the newest); then nothing more for the recorder
        spin_until(ex, lambda: any(m.msg.data == str(n - 1) for m in _tail(out)), 60,
                   'the last message in the bag', rec)
        assert rec.stop() == 0, rec.log_text()
    got = recorded(out, '/burst')
    missing = n + 1 - len(got)
    log = rec.log_text()
    assert missing > 0, 'the burst must overflow the queue for the test to mean anything'
    said = re.search(r'on 1 topics, (\d+) lost', log)
    assert said and int(said[1]) < missing, log     # what the middleware reports
    assert f'{missing} missed by sequence number' in log, log
    import yaml
    meta = yaml.safe_load((out / 'metadata.yaml').read_text())['rosbag2_bagfile_information']
    assert meta['custom_data']['messages_missed'] == f'/burst: {missing}'


def _tail(path: Path) -> list:
    import warnings
    if not path.exists() or not list(path.glob('*.mcap')):
        return []
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        try:
            return list(read_messages(path, ['/burst'], strict=False))[-3:]
        except Exception:  # noqa: BLE001 - file being written
            return []


def _recovered(path: Path) -> int:
    if not path.exists() or not list(path.glob('*.mcap')):
        return 0
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        try:
            return sum(1 for _ in read_messages(path, raw=True, strict=False))
        except Exception:  # noqa: BLE001 - file being written
            return 0


@pytest.mark.parametrize('sig', [signal.SIGTERM, signal.SIGKILL])
def test_record_signals(ros, tmp_path, sig):
    """SIGTERM closes the bag (metadata.yaml); SIGKILL leaves it readable up to the last flush."""
    node, ex = ros
    pub = node.create_publisher(String, '/chatter', RELIABLE)
    out = tmp_path / 'bag'
    args = ['-p', f'output:={out}', '-p', 'discovery_period_s:=0.1', '-p', 'flush_period_s:=0.1']
    with NodeProcess('rover_bag', 'record', args, log_path=tmp_path / 'rec.log') as rec:
        spin_until(ex, pub.get_subscription_count, 30, 'recorder subscription', rec)
        for i in range(200):
            pub.publish(String(data=f'm{i}'))
        # flushed to the file within a flush period: read it back while the recorder runs
        spin_until(ex, lambda: _recovered(out) == 200, 30, '200 flushed messages', rec)
        os.killpg(rec.proc.pid, sig)
        rc = rec.proc.wait(timeout=30)
    if sig == signal.SIGTERM:
        assert rc == 0, rec.log_text()
        assert (out / 'metadata.yaml').exists()
        assert bag_info(out).problems == []
        got = [m.msg.data for m in read_messages(out)]
    else:
        assert rc == -signal.SIGKILL
        assert not (out / 'metadata.yaml').exists()
        assert bag_info(out).recovered
        with pytest.warns(DamagedBagWarning, match='no metadata.yaml'):
            got = [m.msg.data for m in read_messages(out, strict=False)]
    assert got == [f'm{i}' for i in range(200)]


def test_record_refuses_existing_output(tmp_path):
    (tmp_path / 'bag').mkdir()
    with NodeProcess('rover_bag', 'record', ['-p', f'output:={tmp_path / "bag"}'],
                     log_path=tmp_path / 'rec.log') as rec:
        assert rec.proc.wait(timeout=30) == 1
    assert 'exists already' in rec.log_text()


# ----------------------------------------------------------------------------------------------
# play
# ----------------------------------------------------------------------------------------------

T0 = 1_700_000_000_000_000_000


@pytest.fixture
def sample_bag(tmp_path):
    """1 s of 200 Hz inclinometer (offered reliable), 100 Hz imu (best effort) and a latched
    truth string published first; CDR from rclpy's own serializer."""
    path = tmp_path / 'sample'
    with BagWriter(path, typestore=make_typestore()) as bag:
        bag.add_topic('/sim/truth', 'std_msgs/msg/String',
                      offered_qos=[make_qos(reliable=True, transient_local=True, depth=1)])
        bag.add_topic('/rover1/inclinometer', 'coop_msgs/msg/Inclinometer',
                      offered_qos=[make_qos(reliable=True, transient_local=False, depth=10)])
        bag.add_topic('/rover1/imu', 'sensor_msgs/msg/Imu',
                      offered_qos=[make_qos(reliable=False, transient_local=False, depth=5)])
        bag.write('/sim/truth', T0, serialize_message(String(data='truth')))
        for i in range(200):
            t = T0 + 1_000_000 + i * 5_000_000
            bag.write('/rover1/inclinometer', t, serialize_message(Inclinometer(roll=float(i))))
            if i % 2 == 0:
                u = Imu()
                u.linear_acceleration.x = float(i)
                bag.write('/rover1/imu', t + 1000, serialize_message(u))
    return path


def test_play_round_trip(ros, tmp_path, sample_bag):
    node, ex = ros
    got = defaultdict(list)
    node.create_subscription(Inclinometer, '/rover1/inclinometer',
                             lambda m: got['inc'].append((m.roll, time.perf_counter())), RELIABLE)
    # deep queues on this side: the test's executor must not be what drops messages
    node.create_subscription(Imu, '/rover1/imu',
                             lambda m: got['imu'].append(m.linear_acceleration.x), DEEP_BE)
    node.create_subscription(Clock, '/clock',
                             lambda m: got['clock'].append(m.clock.sec * 10**9
                                                           + m.clock.nanosec), RELIABLE)
    args = ['-p', f'bag:={sample_bag}', '-p', 'rate:=2.0', '-p', 'wait_for_subscribers_s:=20.0']
    with NodeProcess('rover_bag', 'play', args, log_path=tmp_path / 'play.log') as play:
        spin_until(ex, lambda: len(got['inc']) >= 20, 60, 'first played messages', play)
        # a late joiner still gets the latched truth (published at bag start)
        node.create_subscription(String, '/sim/truth',
                                 lambda m: got['truth'].append(m.data), LATCHED_QOS)
        spin_until(ex, lambda: not play.alive(), 60, 'player to finish')
        spin_until(ex, lambda: len(got['inc']) == 200 and got['truth'], 10, 'last messages')
        assert play.proc.returncode == 0, play.log_text()
    assert [r for r, _ in got['inc']] == [float(i) for i in range(200)]   # all, in order
    assert got['truth'] == ['truth']
    imu = got['imu']
    assert len(imu) >= 90 and imu == sorted(imu)
    # relative timing: never earlier than the recorded schedule at rate 2 (5 ms -> 2.5 ms), as
    # this side sees it: a message taken up to LATENCY_S after it was sent (a loaded machine:
    # `make test` runs the mission beside this) makes the ones after it look early by as much;
    # a player that did not pace would deliver all 200 within a few ms
    latency_s = 0.1
    r0 = got['inc'][0][1]
    for i, (_r, t) in enumerate(got['inc']):
        assert t - r0 >= i * 0.0025 - latency_s, (i, t - r0)
    clock = got['clock']
    assert clock == sorted(clock) and clock[0] >= T0 and clock[-1] <= T0 + 1_000_000_000
    assert len(clock) >= 150
    # this node has use_sim_time: its clock followed the bag
    assert T0 < node.get_clock().now().nanoseconds <= T0 + 1_000_000_000
    assert 'played 301 messages' in play.log_text()


def test_play_filter_remap_offset_loop(ros, tmp_path, sample_bag):
    node, ex = ros
    got = []
    node.create_subscription(Inclinometer, '/rover3/inclinometer',
                             lambda m: got.append(m.roll), RELIABLE)
    node.create_subscription(Imu, '/rover3/imu', lambda m: got.append(-1.0), SENSOR_QOS)
    args = ['-p', f'bag:={sample_bag}', '-p', 'rate:=5.0', '-p', 'loop:=true',
            '-p', 'start_offset_s:=0.5', '-p', "topics:=['/rover1/inclinometer']",
            '-p', "remap:=['/rover1/:=/rover3/']", '-p', 'publish_clock:=false',
            '-p', 'wait_for_subscribers_s:=20.0']
    with NodeProcess('rover_bag', 'play', args, log_path=tmp_path / 'play.log') as play:
        # messages at t >= start + 0.5 s are i = 100..199 (t = 1 ms + 5 ms i)
        spin_until(ex, lambda: len(got) >= 250, 60, 'two and a half loops', play)
        assert play.alive()
        assert play.stop() == 0
    assert got[:200] == [float(i) for i in range(100, 200)] * 2
    assert -1.0 not in got


def test_play_bad_input(tmp_path, sample_bag):
    cases = [
        (['-p', f'bag:={tmp_path / "nope"}'], 'does not exist'),
        ([], 'no bag given'),
        (['-p', f'bag:={sample_bag}', '-p', "topics:=['/nope']"], "['/nope'] not in"),
        (['-p', f'bag:={sample_bag}', '-p', "remap:=['nope']"], 'is not "/from:=/to"'),
        (['-p', f'bag:={sample_bag}', '-p', 'rate:=0.0'], 'Parameter rate out of range'),
        (['-p', f'bag:={sample_bag}', '-p', 'rate:=2'], "expecting type 'DOUBLE'"),
        # an offset past the end: refused (with loop it spun re-publishing the latched topics)
        (['-p', f'bag:={sample_bag}', '-p', 'loop:=true', '-p', 'start_offset_s:=1000.0'],
         'is not within the bag'),
    ]
    for i, (args, msg) in enumerate(cases):
        with NodeProcess('rover_bag', 'play', args, log_path=tmp_path / f'p{i}.log') as play:
            assert play.proc.wait(timeout=30) == 1, play.log_text()
        assert msg in play.log_text(), play.log_text()
