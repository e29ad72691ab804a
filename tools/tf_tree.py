"""Print the transform tree a running graph publishes (/tf, /tf_static) and each moving frame's
rate by its stamps (the sim clock under a simulator): what tf2_tools' view_frames tells, in text.

Usage: . tools/env.sh && . .ros2-tools/install/local_setup.bash
       python tools/tf_tree.py [--seconds 10]
"""
from __future__ import annotations

import argparse
import collections
import time

import rclpy
from rclpy.node import Node
from tf2_msgs.msg import TFMessage

from coop_common.tf_tree import TF_QOS, TF_STATIC_LISTENER_QOS


def main() -> int:
    """Listen to /tf and /tf_static for `--seconds` and print the frame tree."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--seconds', type=float, default=10.0, help='how long to listen (wall s)')
    a = ap.parse_args()
    rclpy.init()
    node = Node('tf_tree_probe')
    stamps: dict[str, list[float]] = collections.defaultdict(list)
    parents: dict[str, set[str]] = collections.defaultdict(set)
    static: set[str] = set()

    def take(msg, is_static: bool) -> None:
        for t in msg.transforms:
            parents[t.child_frame_id].add(t.header.frame_id)
            if is_static:
                static.add(t.child_frame_id)
            else:
                stamps[t.child_frame_id].append(t.header.stamp.sec + 1e-9 * t.header.stamp.nanosec)

    node.create_subscription(TFMessage, '/tf', lambda m: take(m, False), TF_QOS)
    node.create_subscription(TFMessage, '/tf_static', lambda m: take(m, True),
                             TF_STATIC_LISTENER_QOS)
    end = time.monotonic() + a.seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    node.destroy_node()
    rclpy.shutdown()

    children = collections.defaultdict(list)
    for child, ps in parents.items():
        for p in ps:
            children[p].append(child)
    roots = sorted(p for p in children if p not in parents)

    def show(frame: str, depth: int) -> None:
        for c in sorted(children.get(frame, [])):
            s = stamps.get(c, [])
            if c in static:
                how = 'static'
            elif len(s) > 1 and max(s) > min(s):
                how = f'{(len(s) - 1) / (max(s) - min(s)):.1f} Hz'
            else:
                how = f'{len(s)} seen'
            print(f'{"  " * depth}{c}  ({how})')
            show(c, depth + 1)

    for r in roots:
        print(r)
        show(r, 1)
    two = {c: sorted(p) for c, p in parents.items() if len(p) > 1}
    print(f'{len(parents)} frames, {len(roots)} root(s)'
          + (f'; with two parents: {two}' if two else ''))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
