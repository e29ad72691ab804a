#!/usr/bin/env python3
"""Bridge latency, serial frame in -> ROS message out: sensor frames written into a pty at the
device's 200 Hz, the `rover_hw` bridge (in process, its own context and executor) reading the
other end; latency per frame (a) inside the bridge, bytes read -> all five messages published,
(b) end to end, frame written -> the Imu in a subscriber's callback in another context (pty,
decode, publish, DDS, the subscriber's executor). Target of issue #24: p99 <= 2 ms.

Usage: bench/hw_latency.py --json OUT [--frames N]
"""
from __future__ import annotations

import argparse
import os
import sys
import threading
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

import numpy as np
import rclpy
from lifecycle_msgs.msg import State
from rclpy.context import Context
from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_common.qos import SENSOR_QOS
from coop_common.testing import isolate_ros_environment
from rover_hw import protocol as p
from rover_hw.bridge_node import BridgeNode


def pct(ns: list[int]) -> dict:
    a = np.asarray(ns, dtype=float) * 1e-3
    return {'n': int(a.size), 'p50_us': float(np.percentile(a, 50)),
            'p99_us': float(np.percentile(a, 99)), 'max_us': float(a.max())}


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result."""
    lines = [f'{"path":<46} {"n":>6} {"p50 us":>8} {"p99 us":>8} {"max us":>8}']
    for name, r in result['latency'].items():
        lines.append(f'{name:<46} {r["n"]:>6} {r["p50_us"]:>8.0f} {r["p99_us"]:>8.0f} '
                     f'{r["max_us"]:>8.0f}')
    lines.append(f'frames written {result["frames"]}, published {result["published"]}, '
                 f'bad {result["decoder"]["bad_crc"] + result["decoder"]["bad_cobs"]}; '
                 f'target p99 <= 2000 us')
    if 'load_average' in result:
        la = result['load_average']
        lines.append(f'load average at the end {la[0]:.1f}, {la[1]:.1f}, {la[2]:.1f} '
                     f'(1, 5, 15 min), {result.get("cpus", "?")} cores')
    return '\n'.join(lines)


def sensors(i: int) -> p.Sensors:
    return p.Sensors(t_us=5000 * i, encoders=(0,) * 6, encoder_rates=(0,) * 6,
                     tachometers=(0,) * 4, pot=0, incl=(24060, 23810), ft=(0,) * 6,
                     accel=(i, 0, 9_810_000), gyro=(0, 0, 0))


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--frames', type=number(int, lo=100, hi=1_000_000), default=2000)
    ap.add_argument('--no-subscriber', action='store_true',
                    help='measure the bridge alone (the subscriber shares this process: GIL)')
    args = ap.parse_args()
    isolate_ros_environment()
    master, slave = os.openpty()
    import termios
    import tty
    tty.setraw(slave, termios.TCSANOW)
    path = os.ttyname(slave)
    os.set_blocking(master, False)

    ctx_b, ctx_s = Context(), Context()
    rclpy.init(context=ctx_b)
    rclpy.init(context=ctx_s)
    bridge = BridgeNode(context=ctx_b, parameter_overrides=[
        Parameter('port', value=path), Parameter('stereo_pose_rate_hz', value=0.0)])
    ex_b = MultiThreadedExecutor(num_threads=2, context=ctx_b)
    ex_b.add_node(bridge)
    spin_b = threading.Thread(target=ex_b.spin, daemon=True)
    spin_b.start()
    sub = Node('latency_probe', context=ctx_s)
    ex_s = SingleThreadedExecutor(context=ctx_s)
    ex_s.add_node(sub)
    written: dict[int, int] = {}
    e2e: list[int] = []

    def on_imu(msg: Imu) -> None:
        t = time.monotonic_ns()
        i = round(msg.linear_acceleration.x / p.ACCEL_M_S2)
        if i in written:
            e2e.append(t - written.pop(i))
    if not args.no_subscriber:
        sub.create_subscription(Imu, 'imu', on_imu, SENSOR_QOS)
    try:
        bridge.trigger_configure()
        bridge.trigger_activate()
        enc = p.Encoder()
        # matching, then warm-up frames (not measured)
        t_end = time.monotonic() + 10.0
        while (not args.no_subscriber and not sub.count_publishers('imu')
               and time.monotonic() < t_end):
            ex_s.spin_once(timeout_sec=0.05)
        warm = 200
        period = 0.005
        t0 = time.monotonic()
        for i in range(warm + args.frames):
            if i == warm:
                bridge.latency_ns.clear()
                bridge.latency_first_ns.clear()
                e2e.clear()
            written[i] = time.monotonic_ns()
            os.write(master, enc.encode(sensors(i)))
            try:                 # the device side reads the bridge's commands, as a device does
                while os.read(master, 65536):
                    pass
            except BlockingIOError:
                pass
            # spin the subscriber until the next frame is due
            while True:
                left = t0 + (i + 1) * period - time.monotonic()
                if left <= 0:
                    break
                if args.no_subscriber:
                    time.sleep(left)
                else:
                    ex_s.spin_once(timeout_sec=left)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            ex_s.spin_once(timeout_sec=0.01)
        inside = list(bridge.latency_ns)
        result = {
            'frames': args.frames, 'published': len(inside),
            'latency': {'bridge: bytes read -> Imu published': pct(list(bridge.latency_first_ns)),
                        'bridge: bytes read -> 5 messages published': pct(inside),
                        **({'end to end: pty write -> Imu callback': pct(e2e)} if e2e else {})},
            'subscriber_in_process': not args.no_subscriber,
            'decoder': bridge.decoder.counts(),
            'openblas_num_threads': os.environ.get('OPENBLAS_NUM_THREADS'),
            'load_average': os.getloadavg(),
            'cpus': os.cpu_count(),
        }
    finally:
        if bridge._state_machine.current_state[0] == State.PRIMARY_STATE_ACTIVE:
            bridge.trigger_deactivate()
        ex_b.shutdown()
        bridge.destroy_node()
        sub.destroy_node()
        ex_s.shutdown()
        rclpy.shutdown(context=ctx_b)
        rclpy.shutdown(context=ctx_s)
        os.close(master)
        os.close(slave)
    print(format_table(result))
    write_json(args.json, result, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
