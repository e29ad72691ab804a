#!/usr/bin/env python3
"""Regenerate the sample bags in bags/ from the simulator (rover_sim `sim` + rover_bag `record`).

    . tools/env.sh && python tools/record_sample_bags.py [--out bags] [--only NAME ...]

Each run starts the installed `sim` (fixed seed), records chosen topics with the installed
`record` (use_sim_time: bag time = sim time; zstd MCAP chunks), drives the rovers from this script
for a fixed span of sim time, stops both and checks the bag. The sim's physics and noise are
seeded, so the sensor values of a run depend only on the seed and the command sequence; the
moment commands take effect depends on DDS timing, so two recordings agree closely, not bit for
bit. Needs the workspace built (`make build`). Writes bags/README.md's table of runs.
"""
from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import tempfile
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
ROOT = Path(__file__).resolve().parents[1]
# 4 stereo streams: a 16 MB shared-memory segment so no image is dropped (rover_bag README)
os.environ.setdefault('FASTRTPS_DEFAULT_PROFILES_FILE',
                      str(ROOT / 'src' / 'rover_bag' / 'config' / 'fastdds_large_shm.xml'))

import rclpy  # noqa: E402
from builtin_interfaces.msg import Duration  # noqa: E402
from geometry_msgs.msg import PoseStamped, Twist, Vector3  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint  # noqa: E402

from coop_common.qos import COMMAND_QOS, SENSOR_QOS  # noqa: E402
from coop_common.testing import NodeProcess, wait_for  # noqa: E402
from rover_bag.bagio import bag_info  # noqa: E402

SITE_FACE = (2.9, 0.0, 0.25)       # rover_sim worldgen: slot markers on the face x = 2.9 m


class Driver:
    """This script's node: sim time from /clock, commands to the rovers."""

    def __init__(self) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx)
        self.node = Node('sample_bag_driver', context=self.ctx,
                         parameter_overrides=[Parameter('use_sim_time', value=True)])
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        self.pubs: dict[str, object] = {}
        self.poses: dict[str, PoseStamped] = {}

    def now(self) -> float:
        return self.node.get_clock().now().nanoseconds / 1e9

    def pub(self, msg_type, topic: str):
        if topic not in self.pubs:
            self.pubs[topic] = self.node.create_publisher(msg_type, topic, COMMAND_QOS)
        return self.pubs[topic]

    def track_pose(self, rover: str) -> None:
        self.node.create_subscription(PoseStamped, f'/sim/{rover}/base_pose',
                                      lambda m: self.poses.__setitem__(rover, m), SENSOR_QOS)

    def trajectory(self, topic: str, names: list[str], times: list[float],
                   positions: list[list[float]]) -> None:
        msg = JointTrajectory(joint_names=names)
        for t, p in zip(times, positions, strict=False):
            sec = int(t)
            msg.points.append(JointTrajectoryPoint(
                positions=[float(x) for x in p],
                time_from_start=Duration(sec=sec, nanosec=int((t - sec) * 1e9))))
        self.pub(JointTrajectory, topic).publish(msg)

    def spin_for(self, sim_s: float, every: Callable[[float], None] | None = None,
                 period_s: float = 0.1) -> None:
        """Spin for `sim_s` of sim time, calling every(t) each `period_s` of sim time."""
        start = self.now()
        next_t = start

        def step() -> bool:
            t = self.now()
            nonlocal next_t
            if every is not None and t >= next_t:
                every(t - start)
                next_t = t + period_s
            return t - start >= sim_s
        wait_for(step, 600.0, spin=lambda dt: self.ex.spin_once(timeout_sec=dt), poll_s=0.01,
                 what=f'{sim_s} s of sim time')

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        self.ctx.try_shutdown()


# --------------------------------------------------------------------------------------------
# the runs
# --------------------------------------------------------------------------------------------

def drive_ident(d: Driver, seconds: float) -> None:
    """A live identification: the `identifier` node (strategy information) shakes rover1's arm
    with its re-optimised excitation for `seconds` of sim time; the bag keeps the sensors, the
    arm commands and every estimate the node published."""
    from rclpy.action import ActionClient  # noqa: PLC0415

    from coop_msgs.action import Identify  # noqa: PLC0415
    client = ActionClient(d.node, Identify, '/rover1/identifier/identify')
    spin = lambda dt: d.ex.spin_once(timeout_sec=dt)  # noqa: E731
    wait_for(client.server_is_ready, 60.0, spin=spin, what='the identify action')
    d.spin_for(0.5)          # at rest first: the node takes the sensor variances from messages
    fut = client.send_goal_async(Identify.Goal(strategy='information', duration_s=seconds))
    wait_for(fut.done, 30.0, spin=spin, what='the goal response')
    handle = fut.result()
    if not handle.accepted:
        raise RuntimeError('identify goal rejected')
    result = handle.get_result_async()
    wait_for(result.done, 600.0, spin=spin, what='the identification result')
    print(f'identifier: {result.result().result.message}')
    d.spin_for(0.3)          # the last estimate reaches the recorder


def _aim_mast(d: Driver, rover: str, target: tuple[float, float, float]) -> None:
    pose = d.poses.get(rover)
    if pose is None:
        return
    p, q = pose.pose.position, pose.pose.orientation
    yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
    dx, dy, dz = target[0] - p.x, target[1] - p.y, target[2] - (p.z + 0.5)
    pan = math.atan2(dy, dx) - yaw
    pan = math.atan2(math.sin(pan), math.cos(pan))
    tilt = math.atan2(-dz, math.hypot(dx, dy))     # +y rotation pitches the optical axis down
    d.trajectory(f'/{rover}/mast/command', ['mast_pan', 'mast_tilt'], [0.3], [[pan, tilt]])


def drive_mapping(d: Driver, seconds: float, rovers: tuple[str, ...] = ('rover1', 'rover2')
                  ) -> None:
    """The rovers scan: mast pan sweeps -0.6..0.6 rad (in opposite phase from rover to rover)
    while the rovers creep forward."""

    def every(t: float) -> None:
        for i, rover in enumerate(rovers):
            d.pub(Twist, f'/{rover}/cmd_vel').publish(Twist(linear=_v(0.15)))
            pan = 0.6 * math.sin(2 * math.pi * t / seconds + i * math.pi)
            d.trajectory(f'/{rover}/mast/command', ['mast_pan', 'mast_tilt'], [0.2],
                         [[pan, 0.15]])
    d.spin_for(seconds, every, period_s=0.1)


def drive_mapping_four(d: Driver, seconds: float) -> None:
    """drive_mapping with four rovers (two pairs)."""
    drive_mapping(d, seconds, ('rover1', 'rover2', 'rover3', 'rover4'))


def _go_to(d: Driver, rover: str, goal: tuple[float, float], v_max: float = 0.5) -> None:
    """A proportional go-to-point on the true pose: turn towards the goal, slow down near it."""
    pose = d.poses.get(rover)
    twist = Twist()
    if pose is not None:
        p, q = pose.pose.position, pose.pose.orientation
        yaw = math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))
        dx, dy = goal[0] - p.x, goal[1] - p.y
        dist = math.hypot(dx, dy)
        err = math.atan2(math.sin(math.atan2(dy, dx) - yaw), math.cos(math.atan2(dy, dx) - yaw))
        if dist > 0.05:
            twist.linear.x = min(v_max, dist) * max(0.0, math.cos(err))
            twist.angular.z = max(-1.0, min(1.0, 2.0 * err))
    d.pub(Twist, f'/{rover}/cmd_vel').publish(twist)


def drive_insertion(d: Driver, seconds: float) -> None:
    """rover2 (the slave, carrying the card) drives up to the slot; rover1 (the master) stops
    short of it, its mast on the point between the card and the slot so both are in its view;
    rover2's mast on the slot markers."""
    for rover in ('rover1', 'rover2'):
        d.track_pose(rover)

    def every(t: float) -> None:
        _go_to(d, 'rover2', (1.6, 0.15))
        _go_to(d, 'rover1', (0.2, -0.6))
        card = d.poses.get('rover2')
        if card is not None:
            c = card.pose.position
            _aim_mast(d, 'rover1', ((c.x + 0.4 + SITE_FACE[0]) / 2, (c.y + SITE_FACE[1]) / 2,
                                    0.3))
        _aim_mast(d, 'rover2', SITE_FACE)
    d.spin_for(seconds, every, period_s=0.1)


def _v(x: float):
    return Vector3(x=x)


PER_ROVER_SENSORS = ['imu', 'inclinometer', 'arm/wrench', 'joint_states']
STEREO = ['stereo/left/image_raw', 'stereo/right/image_raw', 'stereo/left/camera_info',
          'stereo/right/camera_info', 'stereo/pose', 'odom']


@dataclass
class Run:
    """One sample bag: its name and README line, the simulator's arguments, the topics
    recorded, how long and how the rovers are driven, and other nodes started with it."""

    name: str
    what: str
    sim_args: list[str]
    topics: list[str]
    seconds: float
    drive: Callable[[Driver, float], None]
    notes: str = ''
    extra: dict = field(default_factory=dict)
    nodes: list[tuple[str, str, list[str]]] = field(default_factory=list)   # also started


RUNS = [
    Run('ident_rover1', 'a live identification: the `identifier` node (information strategy) '
        "shakes rover1's arm for 10 sim-s; 200 Hz IMU, inclinometer, F/T, joint states, the "
        'arm commands, every published estimate; Table 2-1 truth latched',
        ['-p', 'rovers:=1', '-p', 'seed:=1', '-p', 'stereo_rate_hz:=0.0'],
        ['/clock', '/sim/rover1/parameters', '/rover1/arm/joint_command',
         '/rover1/dynamic_parameters'] + [f'/rover1/{t}' for t in PER_ROVER_SENSORS], 10.0,
        drive_ident, nodes=[('coop_id', 'identifier',
                             ['-r', '__ns:=/rover1', '-p', 'use_sim_time:=true'])]),
    Run('mapping_two_rovers', 'two-rover stereo mapping: both rovers creep forward, masts '
        'sweeping; 320x240 stereo pairs at 4 Hz + camera_info, stereo/pose, odom, true poses',
        ['-p', 'rovers:=2', '-p', 'seed:=1', '-p', 'stereo_rate_hz:=4.0'],
        ['/clock', '/sim/world', '/sim/rover1/camera_pose', '/sim/rover2/camera_pose',
         '/sim/rover1/base_pose', '/sim/rover2/base_pose']
        + [f'/{r}/{t}' for r in ('rover1', 'rover2') for t in STEREO], 5.0, drive_mapping),
    Run('mapping_four_rovers', 'four-rover stereo mapping (two pairs), as '
        '`mapping_two_rovers`: every rover creeps forward, masts sweeping; 320x240 stereo '
        'pairs at 4 Hz + camera_info, stereo/pose, odom, true poses',
        ['-p', 'rovers:=4', '-p', 'seed:=1', '-p', 'stereo_rate_hz:=4.0'],
        ['/clock', '/sim/world']
        + [f'/sim/rover{i}/{t}' for i in range(1, 5) for t in ('camera_pose', 'base_pose')]
        + [f'/rover{i}/{t}' for i in range(1, 5) for t in STEREO], 5.0, drive_mapping_four),
    Run('insertion_site', 'insertion site: rover2 (slave, carries the card) drives up to the '
        'slot, rover1 (master) stops short with card and slot in its stereo view; stereo 4 Hz, '
        'rover2 arm F/T + joints, true poses',
        ['-p', 'rovers:=2', '-p', 'seed:=1', '-p', 'stereo_rate_hz:=4.0',
         '-p', 'occlusion_density:=0.0'],
        ['/clock', '/sim/world', '/sim/rover1/camera_pose', '/sim/rover2/camera_pose',
         '/sim/rover1/base_pose', '/sim/rover2/base_pose', '/rover2/arm/wrench',
         '/rover2/joint_states']
        + [f'/{r}/{t}' for r in ('rover1', 'rover2') for t in STEREO], 14.0, drive_insertion),
]


def record_run(run: Run, out_dir: Path, tmp: Path) -> Path:
    """Record `run` into `out_dir`/<name> (replacing it), logs in `tmp`; the bag's path."""
    out = out_dir / run.name
    if out.exists():
        shutil.rmtree(out)
    topics = '[' + ', '.join(f"'{t}'" for t in run.topics) + ']'
    driver = Driver()
    try:
        with NodeProcess('rover_sim', 'sim', run.sim_args,
                         log_path=tmp / f'{run.name}.sim.log') as sim, ExitStack() as nodes:
            for pkg, exe, args in run.nodes:
                nodes.enter_context(NodeProcess(pkg, exe, args,
                                                log_path=tmp / f'{run.name}.{exe}.log'))
            rec_args = ['-p', f'output:={out}', '-p', 'use_sim_time:=true',
                        '-p', 'discovery_period_s:=0.2', '-p', 'compression:=zstd',
                        '-p', f'topics:={topics}']
            with NodeProcess('rover_bag', 'record', rec_args,
                             log_path=tmp / f'{run.name}.rec.log') as rec:
                # command topics exist once this script publishes: create them now, so the
                # recorder has subscribed before the first command
                for t in run.topics:
                    if t.endswith('/joint_command'):
                        driver.pub(JointTrajectory, t)
                want = run.topics
                wait_for(lambda: all(f'subscribed {t} ' in rec.log_text() for t in want)
                         and driver.now() > 0, 120,
                         spin=lambda dt: driver.ex.spin_once(timeout_sec=dt),
                         what=f'{run.name}: recorder subscribed to every topic')
                run.drive(driver, run.seconds)
                if rec.stop() != 0:
                    raise RuntimeError(f'{run.name}: recorder failed:\n{rec.log_text()}')
            if not sim.alive():
                raise RuntimeError(f'{run.name}: sim died:\n{sim.log_text()}')
        print(rec.log_text().strip().splitlines()[-1])
    finally:
        driver.close()
    return out


def main() -> int:
    """Record the runs asked for (all by default) and write bags/README.md's table."""
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--out', type=Path, default=ROOT / 'bags')
    ap.add_argument('--only', nargs='*', help='run names (default: all)')
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix='sample_bags_'))
    lines = []
    for run in RUNS:
        if args.only and run.name not in args.only:
            continue
        path = record_run(run, args.out, tmp)
        info = bag_info(path)
        size = sum(f.stat().st_size for f in info.files) / 1e6
        print(f'{run.name}: {info.message_count} messages, {len(info.topics)} topics, '
              f'{info.duration_s:.1f} s, {size:.1f} MB')
        lines.append((run, info, size))
    if not args.only:
        write_readme(args.out, lines)
    shutil.rmtree(tmp, ignore_errors=True)
    return 0


def write_readme(out: Path, lines) -> None:
    """Write the table of runs into `out`/README.md."""
    rows = '\n'.join(
        f'| `{run.name}/` | {run.what} | {info.duration_s:.1f} | {info.message_count} | '
        f'{size:.1f} | `python tools/record_sample_bags.py --only {run.name}` (sim '
        f'`{" ".join(a for a in run.sim_args if a != "-p")}`'
        + ''.join(f', with `{p} {e} {" ".join(a for a in ar if a != "-p")}`'
                  for p, e, ar in run.nodes)
        + f', {run.seconds:g} sim-s) |'
        for run, info, size in lines)
    (out / 'README.md').write_text(f"""# Sample bags

rosbag2 bags (metadata version 9, MCAP storage, zstd chunks) recorded from `rover_sim` by
`rover_bag record` with `use_sim_time` (bag time = sim time). Regenerate all of them with

    . tools/env.sh && python tools/record_sample_bags.py

Replay one into the graph: `ros2 run rover_bag play bags/<name> --ros-args -p rate:=1.0`
(publishes /clock; run the consumers with `-p use_sim_time:=true`). Read one offline:
`rover_bag.bagio.read_messages('bags/<name>')`.

| bag | what | sim-s | messages | MB | how it was recorded |
|---|---|---|---|---|---|
{rows}
""")


if __name__ == '__main__':
    sys.exit(main())
