#!/usr/bin/env python3
"""The live view's delivery and cost: the installed `coop_bringup live_view` fed at the
mission's rates and sizes (both rovers' 640x480 mono8 left images at 4 Hz, truth base poses at
50 Hz and camera poses at 4 Hz, a 100k-voxel map at 1 Hz, both identifiers' estimates at
2.5 Hz, the insertion's feedback at 10 Hz) by a publisher in this process; a WebSocket client
subscribed to every channel counts what it receives per channel (wall Hz, bytes), and the
live_view process's CPU time (user + system, every thread and child) is read from /proc, with
the client connected and without one. Targets (issue #23): map, both images and poses >= 2 Hz
to a connected client; <= 10 % of one core.

With `--mission`, the same client watches a real mission instead (`coop_bringup.mission`
with the live view on; `--near-start` etc. as the mission's flags): per phase, what each
channel delivered to the client beside what the graph published (a subscriber in the
mission's process counts the sources), and the live_view process's CPU. In a mission the
sources run on the simulator's clock, so an image channel can reach the client no faster than
the sim renders (4 Hz of sim time times the real-time factor).

Usage: bench/live_view.py --json OUT [--seconds S]
       bench/live_view.py --json OUT --mission [--near-start] [--slot-in IN] [--max-scans N]
"""
from __future__ import annotations

import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')     # before numpy: one BLAS thread

import argparse
import itertools
import socket
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import rclpy
from coop_bringup.live import channel_topics
from coop_bringup.live_view import FEEDBACK_QOS
from coop_bringup.ws_client import receive
from geometry_msgs.msg import PoseStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from sensor_msgs.msg import Image

from coop_common.cli import number, output_path
from coop_common.dynparams import PARAM_NAMES
from coop_common.files import write_json
from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import NodeProcess, isolate_ros_environment, wait_for
from coop_msgs.action import Insert
from coop_msgs.msg import DynamicParameters, VoxelMap

ROVERS = ('rover1', 'rover2')
#: source rates (Hz, wall) and sizes: the mission's
IMAGE_HZ, BASE_POSE_HZ, CAMERA_POSE_HZ, MAP_HZ, IDENT_HZ, FEEDBACK_HZ = 4.0, 50.0, 4.0, 1.0, \
    2.5, 10.0
WIDTH, HEIGHT, MAP_VOXELS, OCCUPIED_FRACTION = 640, 480, 100_000, 0.2
TARGET_HZ, TARGET_CPU = 2.0, 0.10
TARGETED = ('/map', '/rover1/camera/compressed', '/rover2/camera/compressed', '/rover1/pose',
            '/rover2/pose', '/rover1/camera_pose', '/rover2/camera_pose')


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of `pid` and its descendants (every thread), from /proc."""
    tick = os.sysconf('SC_CLK_TCK')
    stats = {}
    for d in Path('/proc').iterdir():
        if d.name.isdigit():
            try:
                f = (d / 'stat').read_text().rsplit(')', 1)[1].split()
            except OSError:
                continue
            stats[int(d.name)] = (int(f[1]), (int(f[11]) + int(f[12])) / tick)
    todo, total = [pid], 0.0
    while todo:
        p = todo.pop()
        total += stats.get(p, (0, 0.0))[1]
        todo += [c for c, (ppid, _) in stats.items() if ppid == p]
    return total


class Source:
    """Publishes the mission's streams at their rates from its own context and thread."""

    def __init__(self, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        n = self.node = Node('live_view_bench_source', context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(n)
        # a textured scene with sensor noise (JPEG sizes like the sim's frames, not a flat one)
        yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH]
        base = 120 + 60 * np.sin(xx / 23.0) * np.cos(yy / 17.0)
        self.images = []
        for r in ROVERS:
            img = np.clip(base + rng.normal(0, 12, base.shape), 0, 255).astype(np.uint8)
            m = Image(height=HEIGHT, width=WIDTH, encoding='mono8', step=WIDTH,
                      data=img.tobytes())
            m.header.frame_id = f'{r}/left_camera_optical_frame'
            self.images.append((n.create_publisher(Image, f'{r}/stereo/left/image_raw',
                                                   SENSOR_QOS), m))
        self.poses = {(r, k): n.create_publisher(PoseStamped, f'sim/{r}/{k}', SENSOR_QOS)
                      for r in ROVERS for k in ('base_pose', 'camera_pose')}
        keys = rng.integers(-200, 200, (MAP_VOXELS, 3)).astype(np.int32)
        vm = VoxelMap(resolution_m=0.1, sequence=1)
        vm.header.frame_id = 'map'
        vm.voxels.keys = keys.ravel()
        occ = np.where(rng.random(MAP_VOXELS) < OCCUPIED_FRACTION, 0.9, 0.2).astype(np.float32)
        vm.voxels.occupancy = occ
        vm.voxels.mean = (keys.astype(np.float32) * 0.1).ravel()
        vm.voxels.covariance = np.zeros(6 * MAP_VOXELS, np.float32)
        vm.voxels.hits = np.ones(MAP_VOXELS, np.uint32)
        self.map = (n.create_publisher(VoxelMap, 'map/voxels', LATCHED_QOS), vm)
        k = len(PARAM_NAMES)
        self.ident = [(n.create_publisher(DynamicParameters, f'{r}/dynamic_parameters',
                                          LATCHED_QOS),
                       DynamicParameters(names=list(PARAM_NAMES), values=[1.0] * k,
                                         std_devs=[0.1] * k, information_bits=[5.0] * k,
                                         samples=1, strategy='information')) for r in ROVERS]
        self.feedback = n.create_publisher(Insert.Impl.FeedbackMessage,
                                           'insert/_action/feedback', FEEDBACK_QOS)
        for hz, fn in ((IMAGE_HZ, self._images), (BASE_POSE_HZ, lambda: self._poses('base_pose')),
                       (CAMERA_POSE_HZ, lambda: self._poses('camera_pose')),
                       (MAP_HZ, self._map), (IDENT_HZ, self._ident),
                       (FEEDBACK_HZ, self._feedback)):
            n.create_timer(1.0 / hz, fn)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.05)

    def _stamp(self, header) -> None:
        header.stamp = self.node.get_clock().now().to_msg()

    def _images(self) -> None:
        for pub, m in self.images:
            self._stamp(m.header)
            pub.publish(m)

    def _poses(self, kind: str) -> None:
        for r in ROVERS:
            m = PoseStamped()
            m.header.frame_id = 'map'
            self._stamp(m.header)
            m.pose.position.x, m.pose.orientation.w = time.monotonic() % 10, 1.0
            self.poses[(r, kind)].publish(m)

    def _map(self) -> None:
        pub, m = self.map
        m.sequence += 1
        self._stamp(m.header)
        pub.publish(m)

    def _ident(self) -> None:
        for pub, m in self.ident:
            m.samples += 1
            pub.publish(m)

    def _feedback(self) -> None:
        fb = Insert.Impl.FeedbackMessage()
        fb.feedback.phase = Insert.Feedback.PHASE_VISUAL_SERVO
        fb.feedback.displacement_error_m = 0.01
        self.feedback.publish(fb)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result."""
    lines = [f'{"channel":<30} {"client Hz":>9} {"KB/msg":>7} {"target":>8}']
    for topic, r in result['channels'].items():
        tgt = f'>= {TARGET_HZ:.0f} Hz' if topic in TARGETED else ''
        lines.append(f'{topic:<30} {r["hz"]:>9.2f} {r["kb_per_msg"]:>7.1f} {tgt:>8}')
    c = result['cpu']
    lines += [f'live_view CPU, client connected: {100 * c["connected"]:.1f} % of one core '
              f'(target <= {100 * TARGET_CPU:.0f} %); no client: {100 * c["idle"]:.1f} %',
              f'source: {WIDTH}x{HEIGHT} mono8 images {IMAGE_HZ:g} Hz x 2, base poses '
              f'{BASE_POSE_HZ:g} Hz x 2, map {MAP_VOXELS} voxels ({OCCUPIED_FRACTION:.0%} '
              f'occupied) {MAP_HZ:g} Hz; {result["seconds"]:g} s each; '
              f'load average at start {result["loadavg"]}',
              f'targets met: {result["targets_met"]}']
    return '\n'.join(lines)


#: live view channel -> the graph topic it is made from (mission mode's source counts)
def _sources(rovers) -> dict[str, str]:
    out = {'/map': 'map/voxels', '/insertion': 'insert/_action/feedback'}
    for r in rovers:
        out |= {f'/{r}/camera/compressed': f'{r}/stereo/left/image_raw',
                f'/{r}/pose': f'sim/{r}/base_pose', f'/{r}/camera_pose': f'sim/{r}/camera_pose',
                f'/{r}/identification': f'{r}/dynamic_parameters'}
    return out


def _source_type(topic: str):
    """The message type and QoS of a source topic (as the live view subscribes)."""
    if topic == 'map/voxels':
        return VoxelMap, LATCHED_QOS
    if topic.startswith('insert/'):
        return Insert.Impl.FeedbackMessage, FEEDBACK_QOS
    if topic.endswith('image_raw'):
        return Image, SENSOR_QOS
    if topic.endswith('dynamic_parameters'):
        return DynamicParameters, LATCHED_QOS
    return PoseStamped, SENSOR_QOS


def _rate(times: list[float], t0: float, t1: float) -> float:
    return sum(t0 <= t < t1 for t in times) / (t1 - t0) if t1 > t0 else 0.0


def run_mission(args) -> dict:
    """A mission with the live view on and a client connected from the start (see the
    module's text); returns the JSON result."""
    from coop_bringup.mission import Mission, MissionConfig, Progress

    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    cfg = MissionConfig(seed=args.seed, slot_in=args.slot_in, near_start=args.near_start,
                        identify_s=args.identify_s, coverage_target=args.coverage,
                        max_scans=args.max_scans, live_port=port, bag=False)
    out = Path(tempfile.mkdtemp(prefix='live_view_mission_'))
    rovers = tuple(f'rover{i + 1}' for i in range(cfg.rovers))
    sources = _sources(rovers)
    marks: list[tuple[str, float]] = []
    arrivals: dict[str, list[float]] = {t: [] for t in sources.values()}
    cpu: list[tuple[float, float]] = []
    stop = threading.Event()
    got: dict = {}
    threads: list[threading.Thread] = []
    mission: Mission | None = None

    def count(topic: str):
        return lambda _m: arrivals[topic].append(time.monotonic())

    def watch(pid: int) -> None:
        while not stop.wait(1.0):
            if not Path(f'/proc/{pid}').exists():      # the graph stopped: no more samples
                return
            cpu.append((time.monotonic(), cpu_seconds(pid)))

    def client() -> None:
        while not stop.is_set():                    # until the server listens
            try:
                got['r'] = receive(f'ws://127.0.0.1:{port}', topics=channel_topics(rovers),
                                   duration_s=1e6, stop=stop)
                return
            except OSError:
                stop.wait(1.0)

    class Marks(Progress):
        def start(self, phase: str) -> None:
            marks.append((phase, time.monotonic()))
            if not threads:                         # the graph is up: counters and client
                rig = mission.rig
                node = Node('live_view_bench_counter', context=rig.ctx)
                for topic in sources.values():
                    msg_type, qos = _source_type(topic)
                    node.create_subscription(msg_type, topic, count(topic), qos, raw=True)
                rig.add_node(node)
                threads.extend([
                    threading.Thread(target=watch, args=(rig.graph.pid('live_view'),),
                                     daemon=True),
                    threading.Thread(target=client, daemon=True)])
                for t in threads:
                    t.start()
            super().start(phase)

    loadavg = os.getloadavg()
    mission = Mission(cfg, out, run_id='live', progress=Marks(), log=print)
    rep = mission.run()
    t_end = time.monotonic()
    stop.set()
    for t in threads:
        t.join(timeout=30)
    received = got.get('r')
    windows = []
    bounds = [*marks, ('end', t_end)]
    for (phase, t0), (_, t1) in itertools.pairwise(bounds):
        c = [(t, v) for t, v in cpu if t0 <= t <= t1]
        frac = (c[-1][1] - c[0][1]) / (c[-1][0] - c[0][0]) if len(c) > 1 and \
            c[-1][0] > c[0][0] else None
        chans = {}
        for ch, topic in sources.items():
            arr = [t for t, _ in received.arrivals.get(ch, [])] if received else []
            chans[ch] = {'client_hz': _rate(arr, t0, t1),
                         'source_hz': _rate(arrivals[topic], t0, t1)}
        windows.append({'phase': phase, 'wall_s': t1 - t0, 'cpu': frac, 'channels': chans})
    return {'mode': 'mission', 'config': {k: getattr(cfg, k) for k in (
                'seed', 'slot_in', 'near_start', 'identify_s', 'coverage_target',
                'max_scans', 'stereo_rate_hz')},
            'phases': rep['phases'], 'mission_success': rep['success'],
            'windows': windows, 'cpu_samples': cpu,
            'loadavg': [round(v, 2) for v in loadavg],
            'openblas_num_threads': os.environ.get('OPENBLAS_NUM_THREADS')}


def format_mission_table(result: dict) -> str:
    """The table `--mission` prints, from its JSON result: per phase, each targeted channel's
    rate at the client (and what the graph published, in brackets), and live_view's CPU."""
    short = {'/map': 'map'}
    for ch in TARGETED[1:]:
        r, kind = ch.strip('/').split('/', 1)
        short[ch] = f'{r[-1]}:' + {'camera/compressed': 'image', 'pose': 'pose',
                                   'camera_pose': 'cam pose'}[kind]
    head = f'{"phase":<9} {"wall s":>6} {"CPU":>6} ' + ' '.join(f'{short[c]:>14}'
                                                            for c in TARGETED)
    lines = ['client Hz (graph Hz) per phase; CPU: live_view, % of one core', head]
    for w in result['windows']:
        cells = []
        for c in TARGETED:
            x = w['channels'][c]
            cells.append(f'{x["client_hz"]:5.2f} ({x["source_hz"]:5.1f})')
        cpu = f'{100 * w["cpu"]:5.1f}%' if w['cpu'] is not None else '     -'
        lines.append(f'{w["phase"]:<9} {w["wall_s"]:>6.0f} {cpu:>6} ' +
                     ' '.join(f'{c:>14}' for c in cells))
    status = ', '.join(f'{p["name"]} {p["status"]}' for p in result['phases'])
    lines += [f'mission: {status}; seed {result["config"]["seed"]}, slot '
              f'{result["config"]["slot_in"]} in, near start {result["config"]["near_start"]}; '
              f'load average at start {result["loadavg"]}']
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--seconds', type=number(float, lo=2.0, hi=600.0), default=20.0,
                    help='wall seconds of each measurement (client connected; no client)')
    ap.add_argument('--mission', action='store_true',
                    help='watch a real mission (coop_bringup.mission) instead of the source')
    ap.add_argument('--seed', type=number(int, lo=0), default=1)
    ap.add_argument('--slot-in', type=number(float, lo=4.26, hi=6.0), default=4.5)
    ap.add_argument('--near-start', action='store_true')
    ap.add_argument('--identify-s', type=number(float, lo=1.0), default=20.0)
    ap.add_argument('--coverage', type=number(float, lo=0.0, hi=1.0), default=0.9)
    ap.add_argument('--max-scans', type=number(int, lo=0), default=8)
    args = ap.parse_args(argv)
    if args.mission:
        result = run_mission(args)
        write_json(args.json, result)
        print(format_mission_table(result))
        return 0
    isolate_ros_environment()
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        port = s.getsockname()[1]
    log = Path(tempfile.mkdtemp(prefix='live_view_bench_')) / 'live_view.log'
    source = Source()
    try:
        with NodeProcess('coop_bringup', 'live_view', ['-p', f'port:={port}'],
                         log_path=log) as live:
            wait_for(lambda: 'live view on ws://' in live.log_text() or not live.alive(), 60,
                     what='the live view up')
            assert live.alive(), live.log_text()
            loadavg = os.getloadavg()
            time.sleep(3.0)                                  # discovery, first map
            c0, t0 = cpu_seconds(live.proc.pid), time.monotonic()
            got = receive(f'ws://127.0.0.1:{port}', topics=channel_topics(ROVERS),
                          duration_s=args.seconds)
            connected = (cpu_seconds(live.proc.pid) - c0) / (time.monotonic() - t0)
            time.sleep(1.0)
            c0, t0 = cpu_seconds(live.proc.pid), time.monotonic()
            time.sleep(args.seconds)
            idle = (cpu_seconds(live.proc.pid) - c0) / (time.monotonic() - t0)
    finally:
        source.close()
    channels = {}
    for topic in channel_topics(ROVERS):
        arr = got.arrivals.get(topic, [])
        # rate over the span after the first message (the subscription's start is not counted)
        span = arr[-1][0] - arr[0][0] if len(arr) > 1 else 0.0
        channels[topic] = {'messages': len(arr), 'hz': (len(arr) - 1) / span if span else 0.0,
                           'kb_per_msg': float(np.mean([b for _, b in arr])) / 1e3 if arr
                           else 0.0}
    met = all(channels[t]['hz'] >= TARGET_HZ for t in TARGETED) and connected <= TARGET_CPU
    result = {'seconds': args.seconds, 'channels': channels,
              'cpu': {'connected': connected, 'idle': idle},
              'loadavg': [round(v, 2) for v in loadavg], 'targets_met': met,
              'openblas_num_threads': os.environ.get('OPENBLAS_NUM_THREADS'),
              'source': {'image': [WIDTH, HEIGHT, IMAGE_HZ], 'base_pose_hz': BASE_POSE_HZ,
                         'camera_pose_hz': CAMERA_POSE_HZ, 'map_voxels': MAP_VOXELS,
                         'map_hz': MAP_HZ}}
    write_json(args.json, result)
    print(format_table(result))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
