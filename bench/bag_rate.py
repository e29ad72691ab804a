#!/usr/bin/env python3
"""rover_bag: record throughput and playback timing, side by side with the peer (rosbags' own
Writer / AnyReader) in the same run. Ratios matter, not absolute times (2 shared cores).

1. core write: the sim's message mix (pre-serialized CDR of the 200 Hz sensor topics) written
   by the raw rosbags Writer (peer) and by rover_bag.bagio.BagWriter (unsplit, split every 8 MB);
   read back by AnyReader (peer) and read_messages, raw and deserialized. Best of --repeats.
2. live record over DDS: this process publishes the sim's full load (2 rovers x 4 sensor topics
   at 200 Hz + /clock 200 Hz + 4 stereo images 640x480 mono8 at 4 Hz) for --seconds; the
   installed `record` executable records it; counted: published vs recorded vs reported lost.
   Then a burst: 20k small reliable messages as fast as this process can publish them.
3. playback timing: a 200 Hz topic (--seconds long) played by the installed `play` executable;
   this process receives it; jitter = |inter-arrival - recorded interval| per message, and the
   player's own lateness behind its schedule (from its log).

    bench/bag_rate.py --json out/bench/bag_rate.json
"""
from __future__ import annotations

import argparse
import ast
import json
import os
import re
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')

try:
    import rover_bag  # noqa: F401
except ImportError:  # a source checkout before the package is built
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'src' / 'rover_bag'))

import numpy as np
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer

from coop_common.cli import number, output_path
from coop_common.files import write_json
from rover_bag.bagio import BagWriter, bag_info, make_qos, make_typestore, read_messages

SENSOR = [make_qos(reliable=False, transient_local=False, depth=5)]


def sim_mix(ts, n: int, seed: int = 0) -> list[tuple[str, str, int, bytes]]:
    """N messages of the sim's 200 Hz topics (2 rovers x imu, inclinometer, wrench, joints)."""
    rng = np.random.default_rng(seed)
    from geometry_msgs.msg import WrenchStamped
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu, JointState

    from coop_msgs.msg import Inclinometer
    kinds = []
    for r in ('rover1', 'rover2'):
        imu = Imu()
        imu.linear_acceleration.z = 9.81
        js = JointState(name=[f'j{i}' for i in range(9)], position=rng.normal(size=9).tolist(),
                        velocity=rng.normal(size=9).tolist(), effort=rng.normal(size=9).tolist())
        kinds += [(f'/{r}/imu', 'sensor_msgs/msg/Imu', serialize_message(imu)),
                  (f'/{r}/inclinometer', 'coop_msgs/msg/Inclinometer',
                   serialize_message(Inclinometer(roll=0.1))),
                  (f'/{r}/arm/wrench', 'geometry_msgs/msg/WrenchStamped',
                   serialize_message(WrenchStamped())),
                  (f'/{r}/joint_states', 'sensor_msgs/msg/JointState', serialize_message(js))]
    out = []
    for i in range(n):
        topic, msgtype, data = kinds[i % len(kinds)]
        out.append((topic, msgtype, 1_000_000_000 + (i // len(kinds)) * 5_000_000, data))
    return out


def best_rate(fn, n: int, repeats: int) -> float:
    best = float('inf')
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return n / best


def bench_core(n: int, repeats: int, tmp: Path) -> dict:
    ts = make_typestore()
    msgs = sim_mix(ts, n)
    topics = sorted({(m[0], m[1]) for m in msgs})
    counter = iter(range(10**6))

    def peer_write():
        path = tmp / f'peer{next(counter)}'
        with Writer(path, version=9, storage_plugin=StoragePlugin.MCAP) as w:
            conns = {t: w.add_connection(t, mt, typestore=ts, offered_qos_profiles=SENSOR)
                     for t, mt in topics}
            for topic, _mt, t, data in msgs:
                w.write(conns[topic], t, data)
        return path

    def ours_write(**kw):
        path = tmp / f'ours{next(counter)}'
        with BagWriter(path, typestore=ts, **kw) as bag:
            for t, mt in topics:
                bag.add_topic(t, mt, offered_qos=SENSOR)
            write = bag.write
            for topic, _mt, t, data in msgs:
                write(topic, t, data)
        return path

    res = {'messages': n}
    res['peer_write_msgs_s'] = best_rate(peer_write, n, repeats)
    res['ours_write_msgs_s'] = best_rate(ours_write, n, repeats)
    res['ours_write_split8MB_msgs_s'] = best_rate(lambda: ours_write(max_bytes=8_000_000), n,
                                                  repeats)
    bag = ours_write()
    res['split_files_8MB'] = len(bag_info(ours_write(max_bytes=8_000_000)).files)

    def peer_read(deser: bool):
        with AnyReader([bag], default_typestore=ts) as r:
            for c, _t, d in r.messages():
                if deser:
                    r.deserialize(d, c.msgtype)

    res['peer_read_raw_msgs_s'] = best_rate(lambda: peer_read(False), n, repeats)
    res['ours_read_raw_msgs_s'] = best_rate(
        lambda: sum(1 for _ in read_messages(bag, raw=True)), n, repeats)
    res['peer_read_deser_msgs_s'] = best_rate(lambda: peer_read(True), n, repeats)
    res['ours_read_deser_msgs_s'] = best_rate(
        lambda: sum(1 for _ in read_messages(bag, typestore=ts)), n, repeats)
    return res


# ----------------------------------------------------------------------------------------------
def _ros():
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node('bag_rate_bench', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    return ctx, node, ex


def bench_live_record(seconds: float, tmp: Path, count_losses: bool = False) -> dict:
    from geometry_msgs.msg import WrenchStamped
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock
    from sensor_msgs.msg import Image, Imu, JointState
    from std_msgs.msg import String

    from coop_common.qos import CLOCK_QOS, SENSOR_QOS
    from coop_common.testing import NodeProcess, wait_for
    from coop_msgs.msg import Inclinometer

    ctx, node, ex = _ros()
    pubs = {}
    for r in ('rover1', 'rover2'):
        pubs[f'/{r}/imu'] = (node.create_publisher(Imu, f'/{r}/imu', SENSOR_QOS), Imu())
        pubs[f'/{r}/inclinometer'] = (node.create_publisher(
            Inclinometer, f'/{r}/inclinometer', SENSOR_QOS), Inclinometer())
        pubs[f'/{r}/arm/wrench'] = (node.create_publisher(
            WrenchStamped, f'/{r}/arm/wrench', SENSOR_QOS), WrenchStamped())
        pubs[f'/{r}/joint_states'] = (node.create_publisher(
            JointState, f'/{r}/joint_states', SENSOR_QOS),
            JointState(name=[f'j{i}' for i in range(9)], position=[0.1] * 9))
    img = Image(height=480, width=640, encoding='mono8', step=640,
                data=np.random.default_rng(1).integers(0, 255, 640 * 480, dtype=np.uint8)
                .tobytes())
    for r in ('rover1', 'rover2'):
        for side in ('left', 'right'):
            topic = f'/{r}/stereo/{side}/image_raw'
            pubs[topic] = (node.create_publisher(Image, topic, SENSOR_QOS), img)
    clock_pub = node.create_publisher(Clock, '/clock', CLOCK_QOS)
    burst_qos = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
    burst = node.create_publisher(String, '/burst', burst_qos)
    out = tmp / 'live'
    published = {t: 0 for t in pubs}
    published['/clock'] = 0
    res = {}
    with NodeProcess('rover_bag', 'record',
                     ['-p', f'output:={out}', '-p', 'discovery_period_s:=0.2',
                      '-p', f'count_losses:={str(count_losses).lower()}'],
                     log_path=tmp / 'record.log') as rec:
        wait_for(lambda: all(p.get_subscription_count() for p, _ in pubs.values())
                 and burst.get_subscription_count(), 60,
                 spin=lambda dt: ex.spin_once(timeout_sec=dt), what='recorder subscriptions')
        # one burst message long before the burst: the recorder's first of the topic, from
        # which count_losses counts (a writer's earlier messages are not the recorder's to miss)
        burst.publish(String(data='first'))
        published['/burst'] = 1
        t0 = time.perf_counter()
        steps = int(seconds * 200)
        clock = Clock()
        for k in range(steps):
            clock.clock.sec, clock.clock.nanosec = divmod(k * 5_000_000, 10**9)
            clock_pub.publish(clock)
            published['/clock'] += 1
            for topic, (pub, msg) in pubs.items():
                if 'image' in topic and k % 50:
                    continue
                if hasattr(msg, 'header'):
                    msg.header.stamp.sec = k     # step index: where losses fall
                pub.publish(msg)
                published[topic] += 1
            time.sleep(max(0.0, t0 + (k + 1) * 0.005 - time.perf_counter()))
        res['live_wall_s'] = time.perf_counter() - t0
        # burst: as fast as this process can publish (reliable, so every message must arrive)
        n_burst = 20000
        msg = String(data='x' * 64)
        t1 = time.perf_counter()
        for _ in range(n_burst):
            burst.publish(msg)
        res['burst_publish_msgs_s'] = n_burst / (time.perf_counter() - t1)
        published['/burst'] += n_burst
        # caught up: every burst message in the file, or no new one for 2 s (it dropped some)
        seen = [-1, time.perf_counter()]

        def settled() -> bool:
            c = _count_flushed(out, '/burst')
            if c != seen[0]:
                seen[:] = [c, time.perf_counter()]
            return c >= n_burst + 1 or time.perf_counter() - seen[1] > 2.0
        wait_for(settled, 300, poll_s=0.5, what='recorder to catch up with the burst')
        rec.stop()
    log = rec.log_text()
    info = bag_info(out)
    recorded = {t: info.topics[t].count if t in info.topics else 0 for t in published}
    stamps = [m.t_ns for m in read_messages(out, ['/burst'], raw=True)]
    res['burst_recorded'] = len(stamps)
    # the recorder stamps with the middleware's reception time: its own sustained rate (from
    # the burst's first message on: the first of the topic came before the live load)
    burst_t = stamps[1:]
    res['burst_record_msgs_s'] = (len(burst_t) - 1) / ((burst_t[-1] - burst_t[0]) / 1e9)
    res['live_published'] = published
    res['live_recorded'] = recorded
    res['live_missing_total'] = sum(published[t] - recorded[t] for t in published)
    steps = {m.msg.header.stamp.sec for m in read_messages(out, ['/rover1/imu'])}
    res['live_rover1_imu_missing_steps'] = sorted(set(range(int(seconds * 200))) - steps)
    m = re.search(r'(\d+) lost', log)
    res['recorder_reported_lost'] = int(m.group(1)) if m else None
    if count_losses:
        m = re.search(r'(\d+) missed by sequence number(?: \((\{.*\})\))?', log)
        res['recorder_reported_missed'] = int(m.group(1)) if m else None
        res['recorder_reported_missed_per_topic'] = (
            ast.literal_eval(m.group(2)) if m and m.group(2) else {})
    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    return res


def _count_flushed(path: Path, topic: str) -> int:
    import warnings
    if not list(path.glob('*.mcap')):
        return 0
    with warnings.catch_warnings():
        warnings.simplefilter('ignore')
        try:
            return sum(1 for m in read_messages(path, raw=True, strict=False)
                       if m.topic == topic)
        except Exception:  # noqa: BLE001 - being written
            return 0


def bench_play_jitter(seconds: float, tmp: Path) -> dict:
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import Imu

    from coop_common.testing import NodeProcess, wait_for

    n = int(seconds * 200)
    path = tmp / 'play200'
    with BagWriter(path) as bag:
        bag.add_topic('/rover1/imu', 'sensor_msgs/msg/Imu',
                      offered_qos=[make_qos(reliable=True, transient_local=False)])
        for i in range(n):
            m = Imu()
            m.header.stamp.nanosec = i
            bag.write('/rover1/imu', 10**18 + i * 5_000_000, serialize_message(m))
    ctx, node, ex = _ros()
    arrivals = []
    lock = threading.Lock()

    def on_msg(m, info):
        with lock:
            arrivals.append((m.header.stamp.nanosec, info['received_timestamp']))
    node.create_subscription(Imu, '/rover1/imu', on_msg,
                             QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    with NodeProcess('rover_bag', 'play',
                     ['-p', f'bag:={path}', '-p', 'wait_for_subscribers_s:=30.0',
                      '-p', 'publish_clock:=false'], log_path=tmp / 'play.log') as play:
        wait_for(lambda: not play.alive() and len(arrivals) >= n, seconds * 5 + 60,
                 spin=lambda dt: ex.spin_once(timeout_sec=dt), what='playback')
    ex.shutdown()
    node.destroy_node()
    ctx.try_shutdown()
    idx = np.array([a[0] for a in arrivals])
    rt = np.array([a[1] for a in arrivals], dtype=np.int64)
    in_order = bool(np.all(np.diff(idx) > 0))
    d_rec = np.diff(idx) * 5_000_000
    jitter_ms = np.abs(np.diff(rt) - d_rec) / 1e6
    late_ms = (rt - rt[0] - (idx - idx[0]) * 5_000_000) / 1e6
    log = play.log_text()
    m = re.search(r'median ([\d.]+) ms, p99 ([\d.]+) ms, max ([\d.]+) ms', log)
    return {
        'play_messages': n, 'play_received': len(arrivals), 'play_in_order': in_order,
        'play_interarrival_jitter_median_ms': float(np.median(jitter_ms)),
        'play_interarrival_jitter_p99_ms': float(np.percentile(jitter_ms, 99)),
        'play_arrival_vs_schedule_median_ms': float(np.median(late_ms - late_ms.min())),
        'player_lateness_median_ms': float(m.group(1)) if m else None,
        'player_lateness_p99_ms': float(m.group(2)) if m else None,
    }


LARGE_SHM_PROFILE = (Path(__file__).resolve().parents[1] / 'src' / 'rover_bag' / 'config'
                     / 'fastdds_large_shm.xml')


def live_in_child(seconds: float, profile: Path | None, tmp: Path,
                  count_losses: bool = False) -> dict:
    """Fast DDS reads its XML profile once per process: each transport setting in a child."""
    import subprocess
    env = dict(os.environ)
    env.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    if profile is not None:
        env['FASTRTPS_DEFAULT_PROFILES_FILE'] = str(profile)
    out = tmp / f'live_{"large" if profile else "default"}{"_counted" * count_losses}.json'
    subprocess.run([sys.executable, __file__, '--live-only', str(out), '--seconds',
                    str(seconds), *(['--count-losses'] if count_losses else [])], env=env,
                   check=True)
    return json.loads(out.read_text())


def format_table(res: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    out: list[str] = []
    rows = [
        ('write, raw rosbags Writer (peer)', res['peer_write_msgs_s'], ''),
        ('write, BagWriter', res['ours_write_msgs_s'],
         f'{res["ours_write_msgs_s"] / res["peer_write_msgs_s"]:.2f}x peer; target >= 50k'),
        ('write, BagWriter split every 8 MB', res['ours_write_split8MB_msgs_s'],
         f'{res["ours_write_split8MB_msgs_s"] / res["peer_write_msgs_s"]:.2f}x peer'),
        ('read raw, AnyReader (peer)', res['peer_read_raw_msgs_s'], ''),
        ('read raw, read_messages', res['ours_read_raw_msgs_s'],
         f'{res["ours_read_raw_msgs_s"] / res["peer_read_raw_msgs_s"]:.2f}x peer'),
        ('read+deserialize, AnyReader (peer)', res['peer_read_deser_msgs_s'], ''),
        ('read+deserialize, read_messages', res['ours_read_deser_msgs_s'],
         f'{res["ours_read_deser_msgs_s"] / res["peer_read_deser_msgs_s"]:.2f}x peer'),
    ]
    out.append(f'{"figure":42s} {"msgs/s":>10s}  note')
    for name, val, note in rows:
        out.append(f'{name:42s} {val:10.0f}  {note}')
    if 'live_fastdds_default' in res:
        lives = [('Fast DDS defaults (0.5 MB SHM segment)', res['live_fastdds_default']),
                 ('16 MB SHM segment (config/fastdds_large_shm.xml)', res['live_large_shm'])]
        out.append(f'\nlive record, sim load for {res["seconds"]:g} s, recorded / published:')
        out.append(f'{"topic":34s} ' + ' '.join(f'{n.split(" (")[0]:>24s}' for n, _ in lives))
        for t in lives[0][1]['live_published']:
            out.append(f'{t:34s} ' + ' '.join(
                f'{str(r["live_recorded"][t]) + " / " + str(r["live_published"][t]):>24s}'
                for _n, r in lives))
        if 'live_counted' in res:
            r = res['live_counted']
            missing = {t: r['live_published'][t] - r['live_recorded'][t]
                       for t in r['live_published']}
            reported = r['recorder_reported_missed_per_topic']
            out.append(f'\n16 MB SHM, record count_losses:=true: missing {r["live_missing_total"]}'
                       f', counted from sequence numbers {r["recorder_reported_missed"]}, '
                       f'reported lost {r["recorder_reported_lost"]}; burst of 20000 reliable: '
                       f'recorded {r["burst_recorded"]} of 20001, missing '
                       f'{missing["/burst"]}, counted {reported.get("/burst", 0)}')
            out.append('per topic, missing / counted: ' + ', '.join(
                f'{t} {missing[t]} / {reported.get(t, 0)}' for t in missing
                if missing[t] or reported.get(t, 0)))
        for name, r in lives:
            out.append(f'{name}: missing {r["live_missing_total"]} (recorder reported lost '
                       f'{r["recorder_reported_lost"]}); /rover1/imu steps missing '
                       f'{r["live_rover1_imu_missing_steps"][:12]}; burst of 20000 reliable '
                       f'published at {r["burst_publish_msgs_s"]:.0f} msgs/s: recorded '
                       f'{r["burst_recorded"]} at {r["burst_record_msgs_s"]:.0f} msgs/s')
        out.append(f'\nplayback 200 Hz, {res["play_messages"]} msgs: received '
                   f'{res["play_received"]}, in order {res["play_in_order"]}')
        out.append(f'inter-arrival jitter median '
                   f'{res["play_interarrival_jitter_median_ms"]:.3f} ms, p99 '
                   f'{res["play_interarrival_jitter_p99_ms"]:.3f} ms (target median <= 1 ms)')
        out.append(f'arrival behind schedule median '
                   f'{res["play_arrival_vs_schedule_median_ms"]:.3f} ms; player lateness median '
                   f'{res["player_lateness_median_ms"]} ms, '
                   f'p99 {res["player_lateness_p99_ms"]} ms')
    return '\n'.join(out)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--json', type=output_path, help='write the figures here')
    ap.add_argument('--messages', type=number(int, lo=1, hi=10 ** 8), default=100_000)
    ap.add_argument('--repeats', type=number(int, lo=1, hi=100), default=3)
    ap.add_argument('--seconds', type=number(float, lo=0.0, lo_open=True, hi=3600.0), default=10.0,
                    help='live record / play duration')
    ap.add_argument('--skip-live', action='store_true', help='core figures only (no DDS)')
    ap.add_argument('--live-only', type=Path, help=argparse.SUPPRESS)
    ap.add_argument('--count-losses', action='store_true', help=argparse.SUPPRESS)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix='bag_rate_'))
    try:
        if args.live_only:
            write_json(args.live_only, bench_live_record(args.seconds, tmp,
                                                         args.count_losses))
            return 0
        res = bench_core(args.messages, args.repeats, tmp)
        if not args.skip_live:
            res['live_fastdds_default'] = live_in_child(args.seconds, None, tmp)
            res['live_large_shm'] = live_in_child(args.seconds, LARGE_SHM_PROFILE, tmp)
            res['live_counted'] = live_in_child(args.seconds, LARGE_SHM_PROFILE, tmp,
                                                count_losses=True)
            res.update(bench_play_jitter(args.seconds, tmp))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res['seconds'] = args.seconds
    print(format_table(res))
    if args.json:
        write_json(args.json, res, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
