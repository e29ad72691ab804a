#!/usr/bin/env python3
"""Simulator real-time factor: 2 rovers without rendering, with stereo at 4 Hz (320x240 and
640x480; TinyRenderer in the simulator, with a render worker, and PyBullet's EGL plugin), and
the node publishing everything over DDS; beside it, the peer: PyBullet stepping the
same bodies with no compliance or sensors (the engine's own ceiling), measured in the same run.

Usage: bench/sim_rate.py --json OUT [--seconds S]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import pybullet as pb

from coop_common.cli import number, output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from rover_sim.config import Integrator, SimConfig
from rover_sim.world import World


def world_rtf(seconds: float, **cfg) -> tuple[float, float, int]:
    """(wall-clock RTF, CPU-time RTF, sub-steps). CPU time is this process's own: it does not
    grow when other processes load the machine, so it is the figure compared with the target."""
    config = SimConfig(rovers=2, **cfg)
    with World(config, [load_truth()] * 2) as w:
        render_every = (round(config.physics_rate_hz / config.stereo_rate_hz)
                        if config.stereo_rate_hz > 0 else 0)
        w.command_velocity(0, 0.1, 0.1)
        w.command_arm(1, ['arm_joint_2'], [seconds], [[0.8]])
        steps = int(seconds * config.physics_rate_hz)
        if render_every:
            w.render_stereo(0)          # a render worker starts at the first picture
        t0, c0 = time.perf_counter(), time.process_time()
        for k in range(steps):
            w.step()
            for i in range(2):
                w.sense(i)
                if render_every and k % render_every == 0:
                    w.render_stereo(i)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        return seconds / wall, seconds / cpu, w.substeps


def renderer_agreement() -> dict:
    """The same 640x480 left image of the insertion site (rover 1 at the master's start) from
    TinyRenderer and from the EGL plugin: mean absolute grey-level difference, and the share of
    pixels more than 10 levels apart (None where EGL does not load)."""
    import numpy as np
    images = {}
    for renderer in ('tiny', 'egl'):
        config = SimConfig(rovers=2, image_width=640, image_height=480, renderer=renderer)
        with World(config, [load_truth()] * 2) as w:
            if w.renderer.value != renderer:
                return {'egl_loaded': False, 'note': w.renderer_note}
            w.place_rover(0, 2.2, 1.4, -1.0)
            images[renderer] = w.render_stereo(0)[0].astype(float)
    d = np.abs(images['tiny'] - images['egl'])
    return {'egl_loaded': True, 'mean_abs_diff': float(d.mean()),
            'share_over_10': float((d > 10).mean())}


def pair_cpu_without_obstacles() -> dict:
    """CPU seconds of one 640x480 TinyRenderer pair of the insertion site from rover 1 at the
    master's start, with every body, and with the obstacles (rocks, drums) out of the scene:
    the most that rendering only the bodies that can appear would save."""
    config = SimConfig(rovers=2, image_width=640, image_height=480)
    with World(config, [load_truth()] * 2) as w:
        w.place_rover(0, 2.2, 1.4, -1.0)

        def per_pair() -> float:
            w.render_stereo(0)
            c0 = time.process_time()
            for _ in range(3):
                w.render_stereo(0)
            return (time.process_time() - c0) / 3
        every = per_pair()
        for body in w.obstacle_bodies:
            pb.resetBasePositionAndOrientation(body, [0.0, 0.0, -100.0], [0, 0, 0, 1],
                                               physicsClientId=w.client)
        return {'pair_cpu_s': every, 'pair_cpu_s_no_obstacles': per_pair(),
                'obstacles': len(w.obstacle_bodies)}


def raw_pybullet_rtf(seconds: float, substeps: int) -> tuple[float, float]:
    """The peer: pb.stepSimulation alone on the same world at the same sub-step."""
    with World(SimConfig(rovers=2, stereo_rate_hz=0.0), [load_truth()] * 2) as w:
        n = int(seconds * w.config.physics_rate_hz) * substeps
        t0, c0 = time.perf_counter(), time.process_time()
        for _ in range(n):
            pb.stepSimulation(physicsClientId=w.client)
        return seconds / (time.perf_counter() - t0), seconds / (time.process_time() - c0)


def node_rtf(seconds: float, *, stereo_hz: float, every_topic: bool,
             lockstep: bool = False) -> float | None:
    """The installed node at real_time_factor 0 (stereo 320x240 at `stereo_hz`), from the sim
    time a subscriber of rover 2's 200 Hz joint states sees advance. every_topic: a subscriber
    on each of the rovers' sensor and stereo topics too (the node builds no message nobody
    takes); lockstep: in lockstep with the joint-state subscriber as its one participant (each
    round's states taken, the round acked)."""
    try:
        import rclpy
        from nav_msgs.msg import Odometry
        from rclpy.node import Node
        from sensor_msgs.msg import CameraInfo, Image, Imu, JointState

        from coop_common.lockstep_node import Lockstep
        from coop_common.qos import SENSOR_QOS
        from coop_common.testing import NodeProcess, isolate_ros_environment
    except ImportError:
        return None
    isolate_ros_environment()
    rclpy.init()
    node = Node('sim_rate_bench')
    ls = Lockstep(node, lockstep)
    stamps: list[tuple[float, float]] = []
    ls.subscription(JointState, 'rover2/joint_states', lambda m: stamps.append(
        (time.perf_counter(), m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)), SENSOR_QOS)
    if every_topic:
        for r in ('rover1', 'rover2'):
            for kind, topic in ((Imu, 'imu'), (Odometry, 'odom'), (JointState, 'joint_states'),
                                (Image, 'stereo/left/image_raw'),
                                (Image, 'stereo/right/image_raw'),
                                (CameraInfo, 'stereo/left/camera_info')):
                if (r, topic) != ('rover2', 'joint_states'):
                    node.create_subscription(kind, f'{r}/{topic}', lambda _m: None, SENSOR_QOS)
    args = ['-p', 'real_time_factor:=0.0', '-p', f'stereo_rate_hz:={stereo_hz}']
    if lockstep:
        args += ['-p', 'lockstep_participants:=[sim_rate_bench]']
    try:
        with NodeProcess('rover_sim', 'sim', args):
            deadline = time.perf_counter() + 60
            while (not stamps or stamps[-1][1] < 1.0) and time.perf_counter() < deadline:
                rclpy.spin_once(node, timeout_sec=0.05)
            start = len(stamps)
            t_end = time.perf_counter() + seconds
            while time.perf_counter() < t_end:
                rclpy.spin_once(node, timeout_sec=0.05)
            (w0, s0), (w1, s1) = stamps[start], stamps[-1]
            return (s1 - s0) / (w1 - w0)
    except (FileNotFoundError, IndexError, subprocess.SubprocessError):
        return None
    finally:
        node.destroy_node()
        rclpy.shutdown()


_CASES = (('rtf_no_render', 'world, 2 rovers, no rendering'),
          ('rtf_no_render_implicit', 'world, 2 rovers, no rendering, implicit 1 step'),
          ('rtf_stereo_4hz_320x240', 'world, 2 rovers, stereo 4 Hz 320x240'),
          ('rtf_stereo_4hz_640x480', 'world, 2 rovers, stereo 4 Hz 640x480'),
          ('rtf_stereo_4hz_640x480_worker', 'the same, right eye in a render worker (*)'),
          ('rtf_stereo_4hz_640x480_egl', 'the same, EGL plugin, one process'),
          ('rtf_peer_pybullet_only', 'peer: pb.stepSimulation only ({substeps} sub-steps)'))


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    lines = [f'{"case":<52} {"RTF (CPU)":>10} {"RTF (wall)":>11} {"target":>8}']
    for key, name in _CASES:
        if key not in result:
            continue
        target = result['targets'].get(key)
        tgt = f'>= {target:g}x' if target else '-'
        lines.append(f'{name.format(substeps=result["substeps"]):<52} {result[key]:>9.2f}x '
                     f'{result["wall"][key]:>10.2f}x {tgt:>8}')
    for key, name, target in (
            ('rtf_node_over_dds', 'node over DDS, stereo 4 Hz 320x240, every topic taken',
             '>= 1x'),
            ('rtf_node_no_render', 'node, no rendering, one 200 Hz subscriber', '-'),
            ('rtf_node_lockstep', 'the same in lockstep, the subscriber its participant',
             '-')):
        node = result['wall'].get(key)
        if node is not None:
            lines.append(f'{name:<52} {"-":>10} {node:>10.2f}x {target:>8}')
    lines.append(f'{"ours / peer, CPU (no rendering)":<52} {result["ratio_to_peer"]:>9.2f}')
    if 'rtf_stereo_4hz_640x480_worker' in result:
        lines.append('(*) its CPU figure leaves out the worker process: compare the wall column')
    tiny = result.get('renderers', {}).get('tinyrenderer', {})
    if 'pair_cpu_s_no_obstacles' in tiny:
        lines.append(f'TinyRenderer, one 640x480 pair of the site: {tiny["pair_cpu_s"]:.3f} CPU s '
                     f'with every body, {tiny["pair_cpu_s_no_obstacles"]:.3f} without its '
                     f'{tiny["obstacles"]} obstacles')
    egl = result.get('renderers', {}).get('egl')
    if egl and egl.get('egl_loaded'):
        lines.append(f'EGL against TinyRenderer, the same 640x480 view of the site: mean '
                     f'|difference| {egl["mean_abs_diff"]:.1f} grey levels, '
                     f'{100 * egl["share_over_10"]:.0f} % of pixels over 10 apart')
    elif egl:
        lines.append(f'EGL: {egl.get("note")}')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--seconds', type=number(float, lo=0.0, lo_open=True, hi=3600.0), default=5.0,
                    help='sim seconds per case')
    args = ap.parse_args()
    none = world_rtf(args.seconds, stereo_rate_hz=0.0)
    implicit = world_rtf(args.seconds, stereo_rate_hz=0.0, integrator=Integrator.IMPLICIT)
    substeps = none[2]
    s320 = world_rtf(args.seconds, stereo_rate_hz=4.0)
    s640 = world_rtf(args.seconds / 2, stereo_rate_hz=4.0, image_width=640, image_height=480)
    s640w = world_rtf(args.seconds / 2, stereo_rate_hz=4.0, image_width=640, image_height=480,
                      render_workers=1)
    s640egl = world_rtf(args.seconds / 2, stereo_rate_hz=4.0, image_width=640, image_height=480,
                        renderer='egl')
    agreement = renderer_agreement()
    culled = pair_cpu_without_obstacles()
    peer = raw_pybullet_rtf(args.seconds, substeps)
    node = node_rtf(args.seconds, stereo_hz=4.0, every_topic=True)
    node_free = node_rtf(args.seconds, stereo_hz=0.0, every_topic=False)
    node_lockstep = node_rtf(args.seconds, stereo_hz=0.0, every_topic=False, lockstep=True)
    result = {
        'rtf_no_render': none[1], 'rtf_no_render_implicit': implicit[1],
        'rtf_stereo_4hz_320x240': s320[1],
        'rtf_stereo_4hz_640x480': s640[1], 'rtf_stereo_4hz_640x480_worker': s640w[1],
        'rtf_stereo_4hz_640x480_egl': s640egl[1],
        'rtf_peer_pybullet_only': peer[1],
        'wall': {'rtf_no_render': none[0], 'rtf_no_render_implicit': implicit[0],
                 'rtf_stereo_4hz_320x240': s320[0],
                 'rtf_stereo_4hz_640x480': s640[0], 'rtf_stereo_4hz_640x480_worker': s640w[0],
                 'rtf_stereo_4hz_640x480_egl': s640egl[0],
                 'rtf_peer_pybullet_only': peer[0],
                 'rtf_node_over_dds': node, 'rtf_node_no_render': node_free,
                 'rtf_node_lockstep': node_lockstep},
        # the names for the same figures (CPU real-time factors; per renderer)
        'rtf_cpu': {'no_render': none[1], 'no_render_implicit': implicit[1],
                    'stereo_320': s320[1], 'stereo_640': s640[1]},
        'renderers': {'tinyrenderer': {'stereo_640': s640[1], 'stereo_640_wall': s640[0],
                                       **culled},
                      'tinyrenderer_worker': {'stereo_640_wall': s640w[0]},
                      'egl': {'stereo_640': s640egl[1], 'stereo_640_wall': s640egl[0],
                              **agreement}},
        'peer_ratio': none[1] / peer[1],
        'ratio_to_peer': none[1] / peer[1], 'substeps': substeps, 'sim_seconds': args.seconds,
        'clock': 'rtf_* are sim seconds per CPU second of this process (with the render worker: '
                 'not counting the worker); wall.* per wall second',
        'targets': {'rtf_no_render': 8.0, 'rtf_no_render_implicit': 8.0,
                    'rtf_stereo_4hz_320x240': 1.0, 'rtf_stereo_4hz_640x480': 2.0,
                    'rtf_stereo_4hz_640x480_worker': 2.0, 'rtf_stereo_4hz_640x480_egl': 2.0},
    }
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
