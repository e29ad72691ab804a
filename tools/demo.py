#!/usr/bin/env python3
"""`make demo`: the two-rover graph over DDS. Starts the installed simulator (`rover_sim sim`),
one `coop_mapping stereo` node per rover and the team's `coop_mapping mapper`; drives both arms
and camera masts through a short scripted motion (rover 1 shakes its arm with the thesis's
Eq. 2-21 excitation, rover 2 drives an arc, both pan their cameras), prints what each rover senses
and how the shared map grows, and writes under OUT/: a stereo pair (PNG) per rover, a plot of base
tilt and arm-base force, the shared map (`team.cmap`) and its occupancy slice with each rover's
camera and next best view (`map_grid.png`)."""
from __future__ import annotations

import argparse
import contextlib
import sys
import threading
from pathlib import Path

import cv2
import numpy as np
import rclpy
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Twist, WrenchStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import Image, Imu, JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.files import save_figure
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.testing import NodeProcess, isolate_ros_environment, wait_for
from coop_msgs.msg import Inclinometer, VoxelMap
from coop_msgs.srv import MapFile, NextBestView
from coop_viewplan.frames import yaw_pitch_from_optical

ROVERS = ('rover1', 'rover2')


def traj(names, times, positions) -> JointTrajectory:
    msg = JointTrajectory(joint_names=list(names))
    for t, p in zip(times, positions):
        pt = JointTrajectoryPoint(positions=[float(v) for v in p])
        pt.time_from_start.sec, pt.time_from_start.nanosec = int(t), int(round((t % 1) * 1e9))
        msg.points.append(pt)
    return msg


class DemoNode(Node):
    def __init__(self) -> None:
        super().__init__('demo')
        self.sim_time = 0.0
        self.log = {r: {'t': [], 'roll': [], 'pitch': [], 'fx': [], 'fy': [], 'fz': []}
                    for r in ROVERS}
        self.last: dict[str, dict] = {r: {} for r in ROVERS}
        self.images: dict[tuple[str, str], np.ndarray] = {}
        self.lock = threading.Lock()
        self.create_subscription(Clock, '/clock', self._on_clock, 10)
        self.map: VoxelMap | None = None
        self.grid: OccupancyGrid | None = None
        self.create_subscription(VoxelMap, '/map/voxels', lambda m: setattr(self, 'map', m),
                                 LATCHED_QOS)
        self.create_subscription(OccupancyGrid, '/map/grid', lambda m: setattr(self, 'grid', m),
                                 LATCHED_QOS)
        self.pubs = {}
        for r in ROVERS:
            self.create_subscription(Inclinometer, f'/{r}/inclinometer',
                                     lambda m, r=r: self._incl(r, m), SENSOR_QOS)
            self.create_subscription(WrenchStamped, f'/{r}/arm/wrench',
                                     lambda m, r=r: self._wrench(r, m), SENSOR_QOS)
            self.create_subscription(Imu, f'/{r}/imu', lambda m, r=r: self._keep(r, 'imu', m),
                                     SENSOR_QOS)
            self.create_subscription(JointState, f'/{r}/joint_states',
                                     lambda m, r=r: self._keep(r, 'joints', m), SENSOR_QOS)
            self.create_subscription(PoseWithCovarianceStamped, f'/{r}/stereo/pose',
                                     lambda m, r=r: self._cam_pose(r, m), SENSOR_QOS)
            for side in ('left', 'right'):
                self.create_subscription(Image, f'/{r}/stereo/{side}/image_raw',
                                         lambda m, r=r, s=side: self._image(r, s, m), SENSOR_QOS)
            self.pubs[r] = {
                'arm': self.create_publisher(JointTrajectory, f'/{r}/arm/joint_command',
                                             COMMAND_QOS),
                'mast': self.create_publisher(JointTrajectory, f'/{r}/mast/command', COMMAND_QOS),
                'cmd_vel': self.create_publisher(Twist, f'/{r}/cmd_vel', COMMAND_QOS),
            }

    def _on_clock(self, m: Clock) -> None:
        self.sim_time = m.clock.sec + m.clock.nanosec * 1e-9

    def _cam_pose(self, r: str, m: PoseWithCovarianceStamped) -> None:
        self.last[r]['cam_pose'] = PoseStamped(header=m.header, pose=m.pose.pose)

    def _keep(self, r: str, key: str, m) -> None:
        self.last[r][key] = m

    def _incl(self, r: str, m: Inclinometer) -> None:
        self.last[r]['incl'] = m
        with self.lock:
            log = self.log[r]
            log['t'].append(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)
            log['roll'].append(np.degrees(m.roll))
            log['pitch'].append(np.degrees(m.pitch))

    def _wrench(self, r: str, m: WrenchStamped) -> None:
        self.last[r]['wrench'] = m
        with self.lock:
            f = m.wrench.force
            log = self.log[r]
            log['fx'].append(f.x)
            log['fy'].append(f.y)
            log['fz'].append(f.z)

    def _image(self, r: str, side: str, m: Image) -> None:
        self.images[(r, side)] = np.frombuffer(bytes(m.data), np.uint8).reshape(m.height,
                                                                                m.width)

    def report(self, r: str) -> str:
        d = self.last[r]
        if not {'incl', 'wrench', 'imu', 'joints'} <= set(d):
            return f'{r}: waiting for sensors'
        inc, w, imu, js = d['incl'], d['wrench'].wrench, d['imu'], d['joints']
        pos = dict(zip(js.name, js.position))
        vel = dict(zip(js.name, js.velocity))
        a = imu.linear_acceleration
        return (f'{r}: tilt roll {np.degrees(inc.roll):+6.2f} pitch {np.degrees(inc.pitch):+6.2f} '
                f'deg | accel ({a.x:+5.2f} {a.y:+5.2f} {a.z:+5.2f}) m/s^2 | F ({w.force.x:+5.2f} '
                f'{w.force.y:+5.2f} {w.force.z:+5.2f}) N  '
                f'T ({w.torque.x:+5.2f} {w.torque.y:+5.2f} '
                f'{w.torque.z:+5.2f}) N m | arm j2 {pos["arm_joint_2"]:+5.2f} rad | mast pan '
                f'{pos["mast_pan"]:+5.2f} rad | wheel fl {vel["wheel_fl"]:+5.2f} rad/s')


def script(node: DemoNode) -> None:
    """The scripted motion, in sim time from now."""
    t = np.arange(0.05, 12.0, 0.05)
    amp = 2 * np.pi / 9 * np.minimum(1.0, t / 0.5)
    eq_2_21 = np.pi / 4 + amp * np.sin(np.pi / 2 * t)          # Eq. 2-21 with a soft start
    node.pubs['rover1']['arm'].publish(
        traj(['arm_joint_1', 'arm_joint_2'], [1.5], [[0.0, np.pi / 4]]))
    node.pubs['rover1']['arm'].publish(traj(['arm_joint_2'], 1.5 + t, eq_2_21[:, None]))
    node.pubs['rover2']['arm'].publish(
        traj(['arm_joint_1', 'arm_joint_2', 'arm_joint_3'], [3.0, 6.0, 9.0],
             [[0.8, 0.3, 0.6], [-0.8, 0.0, 1.0], [0.0, -0.4, 1.2]]))
    for r, pan in (('rover1', 0.5), ('rover2', -0.6)):
        node.pubs[r]['mast'].publish(traj(['mast_pan', 'mast_tilt'], [4.0, 8.0, 12.0],
                                          [[pan, 0.25], [-pan, 0.35], [0.0, 0.3]]))


def map_summary(node: DemoNode) -> str:
    m = node.map
    if m is None:
        return 'shared map: nothing fused yet'
    occ = np.asarray(m.voxels.occupancy)
    per = ', '.join(f'{r} {n} scans' for r, n in zip(m.contributors, m.contributions))
    return (f'shared map: {occ.size} known voxels at {m.resolution_m:g} m, '
            f'{int((occ > 0.5).sum())} occupied, {int((occ < 0.5).sum())} free ({per})')


def _xy_yaw(pose) -> tuple[float, float, float]:
    """(x, y, heading of the optical axis) of a camera pose in the map frame."""
    q = pose.orientation
    yaw, _ = yaw_pitch_from_optical(np.array([q.x, q.y, q.z, q.w]))
    return pose.position.x, pose.position.y, yaw


def next_views(node: DemoNode, spin) -> dict[str, tuple[float, float, float]]:
    """Ask the view planner where each rover's camera should look next on the shared map
    (Eq. 3-15, maximum information), print its answer and return (x, y, yaw) per rover."""
    client = node.create_client(NextBestView, '/viewplan/next_best_view')
    if not client.wait_for_service(timeout_sec=10.0):
        print('demo: no view planner')
        return {}
    views = {}
    for r in ROVERS:
        req = NextBestView.Request(robot=r, strategy='max_information', max_candidates=0)
        est = node.last[r].get('cam_pose')
        req.current_pose = est if est is not None else PoseStamped()
        future = client.call_async(req)
        wait_for(future.done, 60.0, spin=spin, what='the next best view')
        res = future.result()
        if not res.success:
            print(f'demo: next best view for {r}: none ({res.message})')
            continue
        b = res.best
        p = b.pose.pose.position
        views[r] = _xy_yaw(b.pose.pose)
        print(f'demo: next best view for {r} (max information, Eq. 3-15): camera at '
              f'({p.x:+.2f}, {p.y:+.2f}, {p.z:+.2f}) m, NI {b.new_information_bits:.2f} bits, '
              f'distance {b.distance:.2f}, RF {b.rating:.1f}')
    return views


def save_map_figure(grid: OccupancyGrid, cameras: dict, views: dict, path: Path) -> Path:
    """`draw_map` on a figure of its own, written to `path`."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 7))
    draw_map(ax, grid, cameras, views)
    return save_figure(fig, path, dpi=100)


def draw_map(ax, grid: OccupancyGrid, cameras: dict, views: dict) -> None:
    """The mapper's occupancy slice (/map/grid) in map-frame metres, seen from above (REP 103:
    +x right, +y up): unknown grey, free white, occupied black; each rover's camera where it
    is (its last stereo/pose, (x, y, yaw) in `cameras`) and where the view planner sends it
    next (`views`)."""
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    info = grid.info
    data = np.asarray(grid.data, dtype=np.int16).reshape(info.height, info.width)
    state = np.where(data < 0, 1, np.where(data >= 50, 2, 0))       # free, unknown, occupied
    x0, y0 = info.origin.position.x, info.origin.position.y
    extent = (x0, x0 + info.width * info.resolution, y0, y0 + info.height * info.resolution)
    ax.imshow(state, origin='lower', extent=extent, interpolation='nearest', vmin=0, vmax=2,
              cmap=ListedColormap(['white', '0.6', 'black']))
    handles = [Patch(facecolor=c, edgecolor='0.3', label=t) for c, t in
               (('white', 'free'), ('0.6', 'unknown'), ('black', 'occupied'))]
    for r, colour in zip(ROVERS, ('tab:blue', 'tab:orange')):
        arrow = 0.08 * max(extent[1] - extent[0], extent[3] - extent[2])
        for pose, marker, what in ((cameras.get(r), 'o', 'camera now'),
                                   (views.get(r), '*', 'next best view')):
            if pose is None:
                continue
            x, y, yaw = pose
            ax.plot(x, y, marker, color=colour, ms=12 if marker == '*' else 8,
                    mec='k', label=f'{r}: {what}')
            ax.annotate('', (x + arrow * np.cos(yaw), y + arrow * np.sin(yaw)), (x, y),
                        arrowprops={'arrowstyle': '->', 'color': colour, 'lw': 1.5})
        if r in cameras and r in views:
            ax.plot([cameras[r][0], views[r][0]], [cameras[r][1], views[r][1]], ':',
                    color=colour)
    pts = np.array([extent[:2], extent[2:]]).T.tolist() + [p[:2] for p in
                                                            (*cameras.values(), *views.values())]
    lo, hi = np.min(pts, axis=0) - 0.5, np.max(pts, axis=0) + 0.5
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_xlabel(f'x (m, {grid.header.frame_id!r} frame; {info.resolution:g} m cells)')
    ax.set_ylabel('y (m)')
    ax.set_title('shared map, occupancy slice (/map/grid), cameras and next best views')
    ax.legend(handles=handles + ax.get_legend_handles_labels()[0], loc='upper left',
              fontsize=8, framealpha=0.9)
    ax.set_aspect('equal')


def save_outputs(node: DemoNode, out: Path, views: dict) -> list[Path]:
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    written = []
    for r in ROVERS:
        for side in ('left', 'right'):
            img = node.images.get((r, side))
            if img is not None:
                path = out / f'{r}_stereo_{side}.png'
                cv2.imwrite(str(path), img)
                written.append(path)
    fig, axes = plt.subplots(2, 2, figsize=(11, 6), sharex=True)
    with node.lock:
        for col, r in enumerate(ROVERS):
            log = node.log[r]
            n = min(len(log['t']), len(log['fz']))
            t = np.array(log['t'][:n])
            axes[0, col].plot(t, log['roll'][:n], label='roll')
            axes[0, col].plot(t, log['pitch'][:n], label='pitch')
            axes[0, col].set_title(f'{r}: inclinometer tilt (deg)')
            axes[0, col].legend(loc='upper right')
            for k in ('fx', 'fy', 'fz'):
                axes[1, col].plot(t, np.array(log[k][:n]) - np.mean(log[k][:n]),
                                  label=f'{k} - mean', lw=0.8)
            axes[1, col].set_title(f'{r}: arm-base force F_12 (N, mean removed)')
            axes[1, col].set_xlabel('sim time (s)')
            axes[1, col].legend(loc='upper right')
    written.append(save_figure(fig, out / 'tilt_and_force.png', dpi=90))
    if node.grid is not None:
        cams = {r: _xy_yaw(node.last[r]['cam_pose'].pose) for r in ROVERS
                if 'cam_pose' in node.last[r]}
        written.append(save_map_figure(node.grid, cams, views, out / 'map_grid.png'))
    return written


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', type=Path, default=Path('out'))
    ap.add_argument('--seconds', type=float, default=14.0, help='sim seconds of scripted motion')
    args = ap.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    isolate_ros_environment()
    log_path = args.out / 'sim.log'
    print(f'demo: starting rover_sim (2 rovers, stereo 4 Hz), two stereo nodes and the mapper; '
          f'logs in {args.out}/')
    map_file = (args.out / 'team.cmap').resolve()
    map_file.unlink(missing_ok=True)        # the mapper loads its file at start: begin empty
    with contextlib.ExitStack() as stack:
        sim = stack.enter_context(NodeProcess('rover_sim', 'sim', ['-p', 'real_time_factor:=0.0'],
                                              log_path=log_path))
        for r in ROVERS:
            stack.enter_context(NodeProcess('coop_mapping', 'stereo',
                                            ['-r', f'__ns:=/{r}', '-p', 'use_sim_time:=true'],
                                            log_path=args.out / f'stereo_{r}.log'))
        # the rovers' cameras sit 0.78 m up (rover_sim): plan in the slab they sweep
        stack.enter_context(NodeProcess('coop_viewplan', 'view_planner',
                                        ['-p', 'use_sim_time:=true',
                                         '-p', 'camera_height_m:=0.75'],
                                        log_path=args.out / 'view_planner.log'))
        stack.enter_context(NodeProcess('coop_mapping', 'mapper',
                                        ['-p', 'use_sim_time:=true', '-p', f'map_file:={map_file}',
                                         '-p', 'autosave_period_s:=0.0'],
                                        log_path=args.out / 'mapper.log'))
        rclpy.init()
        node = DemoNode()
        ex = SingleThreadedExecutor()
        ex.add_node(node)
        try:
            def spin(s):
                ex.spin_once(timeout_sec=s)
                if not sim.alive():
                    raise RuntimeError(f'the simulator exited:\n{sim.log_text()[-2000:]}')
            wait_for(lambda: node.pubs['rover2']['arm'].get_subscription_count() > 0
                     and all('wrench' in node.last[r] for r in ROVERS), 60.0, spin=spin,
                     what='the simulator')
            start = node.sim_time
            script(node)
            print(f'demo: scripted motion for {args.seconds:g} s of sim time')
            next_report = start
            drive = Twist()
            while node.sim_time < start + args.seconds:
                # rover 2 drives an arc (re-sent: the sim stops a rover after 0.5 s of silence)
                drive.linear.x, drive.angular.z = 0.15, 0.2 * np.sin(0.5 * (node.sim_time - start))
                node.pubs['rover2']['cmd_vel'].publish(drive)
                spin(0.05)
                if node.sim_time >= next_report:
                    pct = 100 * (node.sim_time - start) / args.seconds
                    print(f'[{pct:5.1f}%] sim t = {node.sim_time:6.2f} s')
                    for r in ROVERS:
                        print('   ' + node.report(r))
                    print('   ' + map_summary(node))
                    next_report += 2.0
            # let the last scans reach the map, then save it
            wait_for(lambda: node.map is not None, 30.0, spin=spin, what='the shared map')
            client = node.create_client(MapFile, '/map/save')
            if client.wait_for_service(timeout_sec=10.0):
                future = client.call_async(MapFile.Request(path=str(map_file)))
                wait_for(future.done, 30.0, spin=spin, what='the map save')
                res = future.result()
                print(f'demo: /map/save -> {res.message} ({res.voxels} voxels)')
            print('demo: ' + map_summary(node))
            views = next_views(node, spin)
            for path in save_outputs(node, args.out, views):
                print(f'demo: wrote {path}')
        finally:
            ex.shutdown()
            node.destroy_node()
            rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
