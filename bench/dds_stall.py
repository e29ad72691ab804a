#!/usr/bin/env python3
"""A reader that stalls, and what Fast DDS's shared memory then drops: one process publishes
`--topics` best-effort sensor_msgs/Imu topics at 200 Hz (the sim's rate; 16 is the sample
streams a recorder of two rovers takes in), another subscribes to all of them (depth 4000) and is
stopped (SIGSTOP) for `--stall` s every second, as a loaded 2-core machine starves a process
of the mission's 12. Run with the project's profile (src/rover_bag/config/fastdds_large_shm.xml)
and with the same profile without its port queue capacity (Fast DDS's default, 512 per port);
lost = stamps missing in the reader's count of one topic.

Usage: bench/dds_stall.py --json OUT [--topics N] [--stall S] [--seconds S]
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import itertools

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_common.testing import pick_domain_id

PROFILE = Path(__file__).resolve().parents[1] / 'src' / 'rover_bag' / 'config' / \
    'fastdds_large_shm.xml'
RATE_HZ = 200


def publish(topics: int, seconds: float) -> None:
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import Imu

    from coop_common.qos import SENSOR_QOS
    rclpy.init()
    node = Node('stall_pub')
    pubs = [node.create_publisher(Imu, f'stall_{i}', SENSOR_QOS) for i in range(topics)]
    msg, k, t0 = Imu(), 0, time.monotonic()
    while time.monotonic() - t0 < seconds:
        k += 1
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(k, RATE_HZ)
        msg.header.stamp.nanosec *= 10 ** 9 // RATE_HZ
        for p in pubs:
            p.publish(msg)
        wait = t0 + k / RATE_HZ - time.monotonic()
        if wait > 0:
            time.sleep(wait)
    print(f'published {k}', flush=True)


def subscribe(topics: int, seconds: float) -> None:
    import rclpy
    from rclpy.node import Node
    from sensor_msgs.msg import Imu

    from coop_common.qos import SENSOR_QOS, with_depth
    rclpy.init()
    node = Node('stall_sub')
    got: set[int] = set()

    def first(m: Imu) -> None:
        got.add(m.header.stamp.sec * RATE_HZ + m.header.stamp.nanosec * RATE_HZ // 10 ** 9)
    for i in range(topics):
        node.create_subscription(Imu, f'stall_{i}', first if i == 0 else (lambda _m: None),
                                 with_depth(SENSOR_QOS, 4000))
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        rclpy.spin_once(node, timeout_sec=0.05)
    s = sorted(got)
    lost = sum(b - a - 1 for a, b in itertools.pairwise(s))
    print(f'received {len(s)} first {s[0] if s else -1} lost {lost}', flush=True)


def run(profile: Path, topics: int, stall: float, seconds: float, domain: int) -> dict:
    env = {**os.environ, 'FASTRTPS_DEFAULT_PROFILES_FILE': str(profile),
           'ROS_DOMAIN_ID': str(domain), 'ROS_AUTOMATIC_DISCOVERY_RANGE': 'LOCALHOST'}
    me = [sys.executable, __file__]
    pub = None
    sub = subprocess.Popen([*me, '--role', 'sub', '--topics', str(topics), '--seconds',
                            str(seconds + 5)], env=env, stdout=subprocess.PIPE, text=True)
    try:
        time.sleep(3.0)           # the subscriber up and discovered before the stream starts
        pub = subprocess.Popen([*me, '--role', 'pub', '--topics', str(topics), '--seconds',
                                str(seconds)], env=env, stdout=subprocess.PIPE, text=True)
        time.sleep(1.0)
        stalls = 0
        while pub.poll() is None and stalls < seconds - 2:
            os.kill(sub.pid, signal.SIGSTOP)
            time.sleep(stall)
            os.kill(sub.pid, signal.SIGCONT)
            stalls += 1
            time.sleep(1.0 - stall)
        pub_out = pub.communicate(timeout=60)[0]
        sub_out = sub.communicate(timeout=60)[0]
    finally:
        for p in (sub, pub):
            if p is not None and p.poll() is None:
                os.kill(p.pid, signal.SIGCONT)
                p.kill()
                p.wait()
    published = int(re.search(r'published (\d+)', pub_out).group(1))
    m = re.search(r'received (\d+) first (-?\d+) lost (\d+)', sub_out)
    return {'published': published, 'received': int(m.group(1)), 'lost': int(m.group(3)),
            'stalls': stalls}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path)
    ap.add_argument('--topics', type=number(int, lo=1, hi=64), default=16)
    ap.add_argument('--stall', type=number(float, lo=0.01, hi=0.9), default=0.3)
    ap.add_argument('--seconds', type=number(float, lo=4.0, hi=120.0), default=10.0)
    ap.add_argument('--role', choices=['pub', 'sub'], help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.role == 'pub':
        publish(args.topics, args.seconds)
        return 0
    if args.role == 'sub':
        subscribe(args.topics, args.seconds)
        return 0
    if args.json is None:
        ap.error('--json is required')
    text = PROFILE.read_text()
    default_port = re.sub(r'\s*<port_queue_capacity>\d+</port_queue_capacity>', '', text)
    domain = pick_domain_id()
    res = {}
    with tempfile.TemporaryDirectory() as tmp:
        plain = Path(tmp) / 'default_port_queue.xml'
        plain.write_text(default_port)
        for name, profile in (('port queue 512 (Fast DDS default)', plain),
                              ('project profile', PROFILE)):
            res[name] = run(profile, args.topics, args.stall, args.seconds, domain)
    out = {'topics': args.topics, 'rate_hz': RATE_HZ, 'stall_s': args.stall,
           'seconds': args.seconds, 'runs': res}
    print(format_table(out))
    write_json(args.json, out)
    return 0


def format_table(res: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    lines = [f'{res["topics"]} topics x {res["rate_hz"]} Hz, the reader stopped '
             f'{res["stall_s"]:g} s every second',
             f'{"profile":36s} {"published":>9s} {"received":>9s} {"lost":>6s} {"stalls":>6s}']
    for name, r in res['runs'].items():
        lines.append(f'{name:36s} {r["published"]:9d} {r["received"]:9d} {r["lost"]:6d} '
                     f'{r["stalls"]:6d}')
    return '\n'.join(lines)


if __name__ == '__main__':
    raise SystemExit(main())
