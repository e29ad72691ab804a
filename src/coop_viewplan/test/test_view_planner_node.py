"""The view_planner node in-process, with a private context and domain."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import Point
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter

from coop_common.qos import LATCHED_QOS
from coop_common.testing import wait_for
from coop_msgs.msg import TaskTarget, VoxelMap
from coop_msgs.srv import NextBestView, TaskView
from coop_viewplan.frames import optical_quaternion
from coop_viewplan.nbv import keep_out_cells
from coop_viewplan.view_planner_node import ViewPlannerNode


def _voxel_map(extra: tuple = ()) -> VoxelMap:
    """A 10 m x 10 m x 2 m room at 0.25 m: floor, the west half known free, a box; the
    occupancies the mapper gives (OctoMap's clamps: free 0.12, occupied 0.97); `extra` keys
    added occupied."""
    res = 0.25
    keys, occ = [], []
    for i in range(40):
        for j in range(40):
            keys.append((i, j, 0))
            occ.append(0.97)
            if i < 20:
                for k in range(1, 8):
                    box = 8 <= i < 12 and 20 <= j < 24
                    keys.append((i, j, k))
                    occ.append(0.97 if box else 0.1192)
    for k in extra:
        keys.append(k)
        occ.append(0.97)
    m = VoxelMap()
    m.header.frame_id = 'map'
    m.resolution_m = res
    m.sequence = 1
    m.voxels.keys = [int(v) for k in keys for v in k]
    m.voxels.occupancy = [float(o) for o in occ]
    return m


@pytest.fixture
def graph():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get('ROS_DOMAIN_ID', '0')))
    node = ViewPlannerNode(context=ctx, parameter_overrides=[
        Parameter('candidates', value=20), Parameter('pad_m', value=1.0),
        Parameter('camera_height_m', value=1.0), Parameter('task_far_m', value=4.0)])
    client = Node('vp_test_client', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(client)
    yield node, client, ex
    ex.shutdown()
    client.destroy_node()
    node.destroy_node()
    rclpy.try_shutdown(context=ctx)


def _call(client, ex, srv_type, name, req):
    cli = client.create_client(srv_type, name)
    wait_for(cli.service_is_ready, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
             what=f'{name} ready')
    fut = cli.call_async(req)
    wait_for(fut.done, 60.0, spin=lambda t: ex.spin_once(timeout_sec=t), what=f'{name} reply')
    return fut.result()


def _nbv_req(strategy='max_information'):
    req = NextBestView.Request()
    req.robot = 'rover1'
    req.strategy = strategy
    req.current_pose.header.frame_id = 'map'
    req.current_pose.pose.position.x, req.current_pose.pose.position.y = 1.1, 2.1
    req.current_pose.pose.position.z = 1.0
    q = optical_quaternion(0.0, 0.0)
    o = req.current_pose.pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)
    return req


def test_services_fail_cleanly_then_plan(graph):
    node, client, ex = graph
    # No map yet: a clear failure, not a crash.
    r = _call(client, ex, NextBestView, '/viewplan/next_best_view', _nbv_req())
    assert not r.success and 'empty map' in r.message
    pub = client.create_publisher(VoxelMap, '/map/voxels', LATCHED_QOS)
    pub.publish(_voxel_map())
    wait_for(lambda: node.grid is not None, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
             what='map received')
    r = _call(client, ex, NextBestView, '/viewplan/next_best_view', _nbv_req('teleport'))
    assert not r.success and 'strategy must be one of' in r.message
    r = _call(client, ex, NextBestView, '/viewplan/next_best_view', _nbv_req())
    assert r.success, r.message
    p = r.best.pose.pose.position
    assert 0 <= p.x < 5.0 and 0 <= p.y < 10.0            # on the known free half
    assert not (1.5 <= p.x < 3.5 and 4.5 <= p.y < 6.5)    # clear of the box + clearance
    assert r.best.new_information_bits > 0 and len(r.ranked) >= 1
    assert r.ranked[0].rating == pytest.approx(r.best.rating)
    assert math.isnan(r.best.field_visibility)
    # a teammate standing at that view: the next best lies out of its keep-out
    req = _nbv_req()
    req.teammates = [Point(x=p.x, y=p.y)]
    again = _call(client, ex, NextBestView, '/viewplan/next_best_view', req)
    keep = keep_out_cells(node.planner.config.clearance_m, node.grid.resolution) * \
        node.grid.resolution
    assert again.success, again.message
    q = again.best.pose.pose.position
    assert math.hypot(q.x - p.x, q.y - p.y) > keep, (again.best.pose, keep)
    assert all(math.hypot(v.pose.pose.position.x - p.x, v.pose.pose.position.y - p.y) > keep
               for v in again.ranked)

    req = TaskView.Request()
    req.robot = 'rover1'
    req.primary = TaskTarget()
    req.primary.header.frame_id = 'map'
    req.primary.position.x, req.primary.position.y, req.primary.position.z = 1.9, 5.5, 1.1
    req.primary.normal.x = -1.0
    req.primary.radius_m = 0.05
    req.tolerance = 0.1
    r = _call(client, ex, TaskView, '/viewplan/task_view', req)
    assert r.success, r.message
    p = r.best.pose.pose.position
    assert p.x < 1.9                                     # in front of the one-sided target
    assert p.z == pytest.approx(1.0)                     # on the rover's mast
    assert r.best.collision_probability < 0.2            # the map's free voxels are 0.12
    assert r.best.angular_visibility > 0 and r.best.depth_of_field == 1.0
    assert r.best.pose.header.frame_id == 'map'
    wide = np.array([p.x - 1.9, p.y - 5.5, p.z - 1.1])
    # the task's own depth of field (what its image processing resolves) narrows the search
    req.far_m = max(0.35, float(np.linalg.norm(wide)) - 0.1)
    r = _call(client, ex, TaskView, '/viewplan/task_view', req)
    q = r.best.pose.pose.position
    if r.success:
        assert np.linalg.norm([q.x - 1.9, q.y - 5.5, q.z - 1.1]) <= req.far_m + 1e-9
    else:
        assert 'candidate' in r.message or 'visible' in r.message, r.message
    req.near_m, req.far_m = 2.0, 1.0
    r = _call(client, ex, TaskView, '/viewplan/task_view', req)
    assert not r.success and 'empty' in r.message
    req.near_m = req.far_m = 0.0
    # the fair random placement: a draw from the same feasible poses, the seed's; within the
    # incidence limit asked for; a bad choice or limit refused with the reason
    req.choose, req.max_incidence_deg = TaskView.Request.CHOOSE_RANDOM, 30.0
    draws = []
    for seed in (1, 2, 1):
        req.seed = seed
        r = _call(client, ex, TaskView, '/viewplan/task_view', req)
        assert r.success and 'drawn from' in r.message, r.message
        q = r.best.pose.pose.position
        draws.append((q.x, q.y, q.z))
        rel = np.array([q.x - 1.9, q.y - 5.5, q.z - 1.1])
        assert np.degrees(np.arccos(-rel[0] / np.linalg.norm(rel))) <= 30.0 + 1e-6
        assert r.best.rating > 0 and r.feasible > 1
    assert draws[0] == draws[2] and draws[0] != draws[1]
    for choose, inc, why in ((7, 0.0, 'choose'), (0, 95.0, 'max_incidence_deg'),
                             (0, math.nan, 'max_incidence_deg')):
        req.choose, req.max_incidence_deg = choose, inc
        r = _call(client, ex, TaskView, '/viewplan/task_view', req)
        assert not r.success and why in r.message, r.message
    req.choose, req.max_incidence_deg, req.seed = 0, 0.0, 0
    # a secondary target in unobserved space (and one against the box) is not rated; the
    # primary is still watched
    for x, y in ((7.5, 5.0), (1.95, 5.1)):
        sec = TaskTarget()
        sec.header.frame_id = 'map'
        sec.position.x, sec.position.y, sec.position.z = x, y, 1.0
        sec.normal.x, sec.radius_m, sec.weight = -1.0, 0.2, 5.0
        req.secondary = [sec]
        r = _call(client, ex, TaskView, '/viewplan/task_view', req)
        assert r.success and 'primary' in r.message, r.message
    req.secondary = []
    # a frame the planner cannot transform from: refused, not relabelled
    req.primary.header.frame_id = 'rover1/base_link'
    r = _call(client, ex, TaskView, '/viewplan/task_view', req)
    assert not r.success and 'transform' in r.message
    req.primary.header.frame_id = 'map'
    nbv = _nbv_req()
    nbv.current_pose.header.frame_id = 'rover1/odom'
    r = _call(client, ex, NextBestView, '/viewplan/next_best_view', nbv)
    assert not r.success and 'transform' in r.message
    # A target inside the box: refused with the reason.
    req.primary.position.x, req.primary.position.y, req.primary.position.z = 2.5, 5.5, 1.1
    r = _call(client, ex, TaskView, '/viewplan/task_view', req)
    assert not r.success and 'inside' in r.message
    assert np.isfinite(node.sequence)
    # the map grows 4 m west: the grid's origin moves, the camera's scan position stays put
    cam = node.cameras['rover1']
    before = node.grid.to_world(np.r_[cam.visited[0], 0])[:2]
    msg = _voxel_map(extra=((-16, 20, 0),))
    msg.sequence = 2
    pub.publish(msg)
    wait_for(lambda: node.sequence == 2, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
             what='the second map')
    np.testing.assert_allclose(node.grid.to_world(np.r_[cam.visited[0], 0])[:2], before)
    np.testing.assert_allclose(before, [1.125, 2.125])
    # one outlier voxel 100 km away would make a 400,000-cell-long grid: rejected, counted,
    # the last map kept
    grid = node.grid
    msg = _voxel_map(extra=((400_000, 20, 0),))
    msg.sequence = 3
    pub.publish(msg)
    wait_for(lambda: node.bad.counts['bad map'] == 1, 10.0,
             spin=lambda t: ex.spin_once(timeout_sec=t), what='the outlier map rejected')
    assert node.grid is grid and node.sequence == 2


def test_depth_of_field_limits_are_checked_together(graph):
    """task_near_m must stay below task_far_m: a change that breaks it is refused with the
    reason and the placer keeps its camera; one that keeps it is taken."""
    node, _, _ = graph
    r = node.set_parameters([Parameter('task_near_m', value=4.5)])[0]   # far is 4.0 here
    assert not r.successful and 'task_far_m' in r.reason
    assert node.p['task_near_m'] == 0.3 and node.placer.camera.near_m == 0.3
    r = node.set_parameters_atomically([Parameter('task_near_m', value=4.5),
                                        Parameter('task_far_m', value=6.0)])
    assert r.successful and node.placer.camera.near_m == 4.5
    with pytest.raises(ValueError, match='task_far_m'):
        ViewPlannerNode(context=node.context, parameter_overrides=[
            Parameter('task_near_m', value=5.0), Parameter('task_far_m', value=5.0)])


def test_hostile_targets_maps_and_parameters(graph):
    """An audit's cases: a map of a tiny resolution is counted and skipped (its pad overflowed
    int64 and the exception killed the node); a huge radius is inside everything (its reach
    overflowed the occluder box, and nothing occluded); a huge weight is refused (the rating
    overflowed to inf); a huge normal is a direction (its norm overflowed); a secondary
    outside the map is skipped like one in unobserved space; a new seed takes effect; an
    empty map is told apart from no map."""
    node, client, ex = graph
    pub = client.create_publisher(VoxelMap, '/map/voxels', LATCHED_QOS)
    tiny = _voxel_map()
    tiny.resolution_m, tiny.sequence = 1e-19, 5
    pub.publish(tiny)
    wait_for(lambda: 'refused' in node.map_state, 10.0,
             spin=lambda t: ex.spin_once(timeout_sec=t), what='the tiny-resolution map')
    r = _call(client, ex, NextBestView, '/viewplan/next_best_view', _nbv_req())
    assert not r.success and 'refused (bad map' in r.message, r.message
    empty = _voxel_map()
    empty.voxels.keys, empty.voxels.occupancy = [], []
    pub.publish(empty)
    wait_for(lambda: 'no voxels' in node.map_state, 10.0,
             spin=lambda t: ex.spin_once(timeout_sec=t), what='the empty map')
    r = _call(client, ex, NextBestView, '/viewplan/next_best_view', _nbv_req())
    assert not r.success and 'has no voxels' in r.message
    pub.publish(_voxel_map())
    wait_for(lambda: node.grid is not None, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
             what='map received')
    pub.publish(tiny)
    wait_for(lambda: node.bad.counts['bad map'] == 2, 10.0,
             spin=lambda t: ex.spin_once(timeout_sec=t), what='the tiny-resolution map')
    assert node.grid is not None and node.sequence == 1

    def task(radius=0.05, normal=(-1.0, 0.0, 0.0), secondary=()):
        req = TaskView.Request()
        req.primary.header.frame_id = 'map'
        req.primary.position.x, req.primary.position.y, req.primary.position.z = 1.9, 5.5, 1.1
        req.primary.normal.x, req.primary.normal.y, req.primary.normal.z = normal
        req.primary.radius_m = radius
        req.secondary = list(secondary)
        return _call(client, ex, TaskView, '/viewplan/task_view', req)

    ok = task()
    assert ok.success, ok.message
    for radius in (1e19, 1e300):
        r = task(radius=radius)
        assert not r.success and 'inside' in r.message, (radius, r.message)
    r = task(normal=(-1e300, 0.0, 0.0))
    assert r.success and r.best.pose.pose.position == ok.best.pose.pose.position
    sec = TaskTarget()
    sec.header.frame_id = 'map'
    sec.position.x, sec.position.y, sec.position.z = 1.9, 5.5, 1.1
    sec.normal.x, sec.radius_m, sec.weight = -1.0, 0.05, 1e308
    r = task(secondary=[sec])
    assert not r.success and 'weight' in r.message
    sec.weight, sec.position.x = 1.0, 500.0                 # outside the map
    r = task(secondary=[sec])
    assert r.success and 'primary' in r.message, r.message
    node.rng.random()
    assert node.set_parameters([Parameter('seed', value=7)])[0].successful
    assert node.rng.random() == np.random.default_rng(7).random()   # a new generator


def test_task_stations_in_unknown_space_only_when_unknown_is_free(graph):
    """task_unknown_occludes false takes unknown space as free for the task: the mast camera
    may also stand where its voxel is unknown (the room's unseen east half), at P = p_empty / 2;
    by default only over voxels seen free (the west half)."""
    node, client, ex = graph
    pub = client.create_publisher(VoxelMap, '/map/voxels', LATCHED_QOS)
    pub.publish(_voxel_map())
    wait_for(lambda: node.grid is not None, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
             what='map received')
    seen = node._task_stations(node.grid)
    assert len(seen.positions) and seen.positions[:, 0].max() < 5.0
    assert node.set_parameters([Parameter('task_unknown_occludes', value=False)])[0].successful
    both = node._task_stations(node.grid)
    east = both.positions[:, 0] > 5.0
    assert east.any() and len(both.positions) > len(seen.positions)
    np.testing.assert_allclose(both.collision_p[east], 0.5 * node.p['p_empty'])
    before = {tuple(np.round(x, 6)): p
              for x, p in zip(seen.positions, seen.collision_p, strict=False)}
    after = {tuple(np.round(x, 6)): p
             for x, p in zip(both.positions, both.collision_p, strict=False)}
    assert all(after.get(x) == p for x, p in before.items())    # the seen ones unchanged


def test_braid_mast_views_are_reachable_and_commanded():
    """mast:=braid: the next best view is one the BRAID's IK reaches (its camera at one of the
    reached views' heights and pitches) and its chain state goes to rover1/mast/braid_command."""
    from std_msgs.msg import UInt8MultiArray

    from coop_viewplan.mast import braid_views
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(os.environ.get('ROS_DOMAIN_ID', '0')))
    node = ViewPlannerNode(context=ctx, parameter_overrides=[
        Parameter('candidates', value=20), Parameter('pad_m', value=1.0),
        Parameter('mast', value='braid'), Parameter('braid_heights_m', value=[0.85, 0.95]),
        Parameter('braid_pitches_deg', value=[0.0])])
    client = Node('vp_braid_client', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(client)
    got = []
    client.create_subscription(UInt8MultiArray, '/rover1/mast/braid_command',
                               lambda m: got.append(list(m.data)), LATCHED_QOS)
    try:
        bv = braid_views(10, heights_m=(0.85, 0.95), pitches_deg=(0.0,))
        assert len(bv.views) >= 2
        pub = client.create_publisher(VoxelMap, '/map/voxels', LATCHED_QOS)
        pub.publish(_voxel_map())
        wait_for(lambda: node.grid is not None, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='map received')
        r = _call(client, ex, NextBestView, '/viewplan/next_best_view', _nbv_req())
        assert r.success, r.message
        assert 'BRAID state' in r.message and 'commanded on rover1' in r.message
        wait_for(lambda: bool(got), 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
                 what='the BRAID command')
        (view,) = [i for i, s in enumerate(bv.states) if list(s) == got[0]]
        z = r.best.pose.pose.position.z
        assert z == pytest.approx(bv.views[view].height_m, abs=1e-9)
        q = r.best.pose.pose.orientation
        fwd_z = 1 - 2 * (q.x * q.x + q.y * q.y)   # the optical axis' z: -sin(pitch)
        assert -math.asin(fwd_z) == pytest.approx(bv.views[view].pitch_rad, abs=1e-6)
    finally:
        ex.shutdown()
        client.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
