#!/usr/bin/env python3
"""Topic rates of the running simulator over DDS, in sim time (header stamps) and in wall time,
against the configured rates: the installed `rover_sim sim`, two rovers, stereo 4 Hz 320x240,
real_time_factor 1.

Usage: bench/sim_topic_rates.py --json OUT [--seconds S]
"""
from __future__ import annotations

import argparse
import sys
import time

import rclpy
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, Imu, JointState

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_common.testing import NodeProcess, isolate_ros_environment
from coop_msgs.msg import Inclinometer

# sensor QoS with a deep queue: a one-thread Python listener on ten topics must not be what
# drops samples
DEEP_BEST_EFFORT = QoSProfile(depth=500, reliability=ReliabilityPolicy.BEST_EFFORT)
TOPICS = (
    ('/clock', Clock, 200.0), ('/rover1/imu', Imu, 200.0),
    ('/rover1/inclinometer', Inclinometer, 200.0), ('/rover1/arm/wrench', WrenchStamped, 200.0),
    ('/rover1/joint_states', JointState, 200.0), ('/rover2/imu', Imu, 200.0),
    ('/rover1/stereo/left/image_raw', Image, 4.0), ('/rover2/stereo/right/image_raw', Image, 4.0),
    ('/rover1/odom', Odometry, 50.0), ('/sim/rover2/base_pose', PoseStamped, 50.0),
)


def stamp_of(msg) -> float:
    t = msg.clock if isinstance(msg, Clock) else msg.header.stamp
    return t.sec + t.nanosec * 1e-9


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    lines = [f'{"topic":<34} {"configured Hz":>13} {"sim-time Hz":>12} {"wall Hz":>9} '
             f'{"msgs":>6}']
    for topic, r in result['topics'].items():
        lines.append(f'{topic:<34} {r["configured_hz"]:>13.1f} {r["sim_hz"]:>12.2f} '
                     f'{r["wall_hz"]:>9.2f} {r["messages"]:>6}')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--seconds', type=number(float, lo=0.0, lo_open=True, hi=3600.0),
                    default=10.0, help='wall seconds of listening')
    args = ap.parse_args()
    isolate_ros_environment()
    rclpy.init()
    node = Node('sim_topic_rates')
    seen: dict[str, list[tuple[float, float]]] = {t: [] for t, _, _ in TOPICS}
    for topic, typ, _ in TOPICS:
        node.create_subscription(
            typ, topic, lambda m, t=topic: seen[t].append((time.monotonic(), stamp_of(m))),
            DEEP_BEST_EFFORT if typ is not Clock else 500)
    rows = {}
    try:
        with NodeProcess('rover_sim', 'sim', ['-p', 'real_time_factor:=1.0']):
            deadline = time.monotonic() + 60
            while len(seen['/rover1/stereo/left/image_raw']) < 2 and time.monotonic() < deadline:
                rclpy.spin_once(node, timeout_sec=0.05)
            for v in seen.values():
                v.clear()
            end = time.monotonic() + args.seconds
            while time.monotonic() < end:
                rclpy.spin_once(node, timeout_sec=0.01)
        for topic, _, expected in TOPICS:
            s = seen[topic]
            sim_hz = (len(s) - 1) / (s[-1][1] - s[0][1]) if len(s) > 1 else 0.0
            wall_hz = (len(s) - 1) / (s[-1][0] - s[0][0]) if len(s) > 1 else 0.0
            rows[topic] = {'configured_hz': expected, 'sim_hz': sim_hz, 'wall_hz': wall_hz,
                           'messages': len(s)}
    finally:
        node.destroy_node()
        rclpy.shutdown()
    result = {'seconds': args.seconds, 'topics': rows}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
