"""Whole graph: rover_sim + a stereo node per rover + the mapper, as installed executables over
DDS; the fused map is checked against the sim's ground truth (/sim/world)."""
import math

import numpy as np
import pytest
import rclpy
from rclpy.executors import SingleThreadedExecutor
from visualization_msgs.msg import Marker, MarkerArray

from coop_common.qos import LATCHED_QOS
from coop_common.testing import NodeProcess, executable_path, wait_for
from coop_msgs.msg import VoxelMap as VoxelMapMsg

pytestmark = pytest.mark.graph


def _have(pkg, exe):
    try:
        executable_path(pkg, exe)
        return True
    except Exception:  # noqa: BLE001 - package not built / not installed
        return False


def surface_distance(p: np.ndarray, markers: list[Marker]) -> np.ndarray:
    """Distance of each point to the nearest true surface: the ground z = 0 and every
    obstacle / site marker (spheres, vertical cylinders, boxes)."""
    d = np.abs(p[:, 2])
    for m in markers:
        c = np.array([m.pose.position.x, m.pose.position.y, m.pose.position.z])
        if m.type == Marker.SPHERE:
            dm = np.abs(np.linalg.norm(p - c, axis=1) - m.scale.x / 2)
        elif m.type == Marker.CYLINDER and m.ns != 'site_marker':
            r = m.scale.x / 2
            h = m.scale.z / 2
            radial = np.linalg.norm(p[:, :2] - c[:2], axis=1) - r
            axial = np.abs(p[:, 2] - c[2]) - h
            out = np.hypot(np.maximum(radial, 0), np.maximum(axial, 0))
            dm = np.where((radial < 0) & (axial < 0), -np.maximum(radial, axial), out)
        elif m.type == Marker.CUBE:
            q = np.abs(p - c) - np.array([m.scale.x, m.scale.y, m.scale.z]) / 2
            dm = np.linalg.norm(np.maximum(q, 0), axis=1) + np.minimum(q.max(1), 0) * -1
        else:
            continue
        d = np.minimum(d, dm)
    return d


@pytest.mark.skipif(not (_have('rover_sim', 'sim') and _have('coop_mapping', 'mapper')),
                    reason='rover_sim / coop_mapping not installed')
def test_two_rovers_map_the_sim_scene(tmp_path):
    common = ['-p', 'use_sim_time:=true']
    procs = [
        NodeProcess('rover_sim', 'sim', ['-p', 'seed:=3', '-p', 'stereo_rate_hz:=2.0',
                                         '-p', 'sensor_rate_hz:=20.0'],
                    log_path=tmp_path / 'sim.log'),
        NodeProcess('coop_mapping', 'stereo', ['-r', '__ns:=/rover1', *common],
                    log_path=tmp_path / 'stereo1.log'),
        NodeProcess('coop_mapping', 'stereo', ['-r', '__ns:=/rover2', *common],
                    log_path=tmp_path / 'stereo2.log'),
        NodeProcess('coop_mapping', 'mapper', ['-p', 'publish_period_s:=0.5',
                                               '-p', f'map_file:={tmp_path / "team.cmap"}',
                                               '-p', 'autosave_period_s:=2.0', *common],
                    log_path=tmp_path / 'mapper.log'),
    ]
    rclpy.init()
    node = rclpy.create_node('graph_test')
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    maps, world = [], []
    node.create_subscription(VoxelMapMsg, '/map/voxels', maps.append, LATCHED_QOS)
    node.create_subscription(MarkerArray, '/sim/world', world.append, LATCHED_QOS)
    try:
        for p in procs:
            p.__enter__()

        def enough():
            if not maps:
                return False
            c = dict(zip(maps[-1].contributors, maps[-1].contributions, strict=False))
            return c.get('rover1', 0) >= 3 and c.get('rover2', 0) >= 3

        wait_for(enough, 120.0, spin=lambda t: ex.spin_once(timeout_sec=t),
                 what='a map with 3 clouds from each rover')
        wait_for(lambda: world, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
                 what='/sim/world')
        assert all(p.alive() for p in procs)
        m = maps[-1]
        vs = m.voxels
        occ = np.asarray(vs.occupancy)
        hits = np.asarray(vs.hits)
        mean = np.asarray(vs.mean).reshape(-1, 3)
        known = len(occ)
        occupied = (occ >= 0.5) & (hits > 0)
        markers = [mk for mk in world[-1].markers if mk.action == Marker.ADD]
        d = surface_distance(mean[occupied], markers)
        print(f'known {known}, occupied {occupied.sum()}, surface distance median '
              f'{np.median(d):.3f} m, p90 {np.percentile(d, 90):.3f} m')
        # coverage: both rovers' views carved and hit a useful part of the scene
        assert known > 2000 and occupied.sum() > 300
        # accuracy: the occupied voxels' means lie on the true surfaces
        assert np.median(d) < 0.1
        assert np.mean(d < 0.3) > 0.8
        assert math.isclose(m.resolution_m, 0.1)
        # kill the mapper and start it again: nothing older than the last autosave is lost
        from coop_mapping.voxelmap import VoxelMap
        mapfile = tmp_path / 'team.cmap'
        wait_for(mapfile.exists, 20.0, spin=lambda t: ex.spin_once(timeout_sec=t),
                 what='an autosave')
        procs[3].stop()
        saved = VoxelMap.load(mapfile)
        maps.clear()
        procs[3] = NodeProcess('coop_mapping', 'mapper', procs[3].cmd[procs[3].cmd.index(
            '--ros-args') + 1:], log_path=tmp_path / 'mapper2.log').__enter__()
        wait_for(lambda: maps and maps[0].sequence >= saved.sequence, 30.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='the restarted map')
        assert len(maps[0].voxels.occupancy) >= len(saved)
    finally:
        for p in reversed(procs):
            p.__exit__(None, None, None)
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown()
