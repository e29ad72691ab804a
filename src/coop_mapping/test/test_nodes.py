"""mapper and stereo nodes in-process with a private context: fusion, services, bad input."""
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Point, PoseWithCovarianceStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import wait_for
from coop_mapping.mapper_node import MapperNode
from coop_mapping.ros_conv import cloud_to_msg, msg_to_cloud
from coop_msgs.msg import VoxelMap as VoxelMapMsg
from coop_msgs.msg import VoxelMapUpdate
from coop_msgs.srv import MapFile, QueryMap


def _pose(stamp, xyz, frame='map'):
    m = PoseWithCovarianceStamped()
    m.header = Header(stamp=stamp, frame_id=frame)
    m.pose.pose.position.x, m.pose.pose.position.y, m.pose.pose.position.z = map(float, xyz)
    m.pose.pose.orientation.w = 1.0
    return m


def _call(ex, client, req, timeout=10.0):
    assert client.wait_for_service(timeout_sec=timeout)
    fut = client.call_async(req)
    wait_for(fut.done, timeout, spin=lambda t: ex.spin_once(timeout_sec=t), what='service')
    return fut.result()


def _mapper_and_peer(ctx, **params):
    """A mapper for rover1 and rover2 (publishing at once, no autosave, `params` over that), a
    peer node and an executor spinning both."""
    over = {'rovers': ['rover1', 'rover2'], 'publish_period_s': 0.0, 'autosave_period_s': 0.0,
            **params}
    node = MapperNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                        for k, v in over.items()])
    peer = Node('peer', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(peer)
    return node, peer, ex


def test_mapper_fuses_queries_saves_and_rejects(ctx, tmp_path):
    mapfile = str(tmp_path / 'team.cmap')
    node, peer, ex = _mapper_and_peer(ctx, map_file=mapfile, max_points=5000)
    try:
        pose_pub = {r: peer.create_publisher(PoseWithCovarianceStamped, f'/{r}/camera_pose',
                                             LATCHED_QOS) for r in ('rover1', 'rover2')}
        cloud_pub = {r: peer.create_publisher(PointCloud2, f'/{r}/stereo/points', SENSOR_QOS)
                     for r in ('rover1', 'rover2')}
        updates, maps = [], []
        peer.create_subscription(VoxelMapUpdate, '/map/updates', updates.append, 10)
        peer.create_subscription(VoxelMapMsg, '/map/voxels', maps.append, LATCHED_QOS)
        wait_for(lambda: peer.count_subscribers('/rover1/stereo/points') > 0
                 and peer.count_subscribers('/rover2/stereo/points') > 0
                 and peer.count_subscribers('/rover2/camera_pose') > 0, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='discovery')
        rng = np.random.default_rng(0)
        origin = np.array([0.05, 0.05, 1.05])
        # a wall at x = 2.03 seen by both rovers
        wall = np.column_stack([np.full(2000, 2.03), rng.uniform(-1, 1, 2000),
                                rng.uniform(0, 2, 2000)])
        cov = np.tile([1e-4, 0, 0, 1e-4, 0, 1e-4], (2000, 1))
        for i, r in enumerate(('rover1', 'rover2')):
            stamp = peer.get_clock().now().to_msg()
            stamp.sec += i
            pose_pub[r].publish(_pose(stamp, origin))
            cloud_pub[r].publish(cloud_to_msg(wall, cov, Header(stamp=stamp, frame_id='map')))
        wait_for(lambda: node.fused == 2 and len(updates) == 2, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='two fused clouds')
        assert {u.source for u in updates} == {'rover1', 'rover2'}
        assert updates[1].base_sequence == updates[0].sequence
        wait_for(lambda: maps and maps[-1].sequence == 2, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='latched map')
        m = maps[-1]
        assert sorted(m.contributors) == ['rover1', 'rover2'] and list(m.contributions) == [1, 1]
        assert len(m.voxels.keys) == 3 * len(m.voxels.occupancy)
        # query: the wall is occupied, the space in front free, far away unknown
        q = QueryMap.Request()
        q.points = [Point(x=2.05, y=0.05, z=1.05), Point(x=1.0, y=0.05, z=1.05),
                    Point(x=-5.0, y=0.0, z=0.0)]
        q.box_min, q.box_max = Point(x=0.0, y=0.0, z=1.0), Point(x=1.0, y=0.1, z=1.1)
        resp = _call(ex, peer.create_client(QueryMap, '/map/query'), q)
        assert resp.success and resp.occupancy[0] > 0.6 and resp.occupancy[1] < 0.4
        assert resp.occupancy[2] == 0.5
        assert resp.box_free == 10 and resp.box_occupied == 0
        # bad input: NaN, wrong frame, empty, absurd range, too large
        stamp = peer.get_clock().now().to_msg()
        stamp.sec += 10
        pose_pub['rover1'].publish(_pose(stamp, origin))
        nan = wall.copy()
        nan[0, 0] = np.nan
        bad = [cloud_to_msg(nan, cov, Header(stamp=stamp, frame_id='map')),
               cloud_to_msg(wall, cov, Header(stamp=stamp, frame_id='odom')),
               cloud_to_msg(wall[:0], cov[:0], Header(stamp=stamp, frame_id='map')),
               cloud_to_msg(wall * 100, cov, Header(stamp=stamp, frame_id='map')),
               cloud_to_msg(np.tile(wall, (3, 1)), np.tile(cov, (3, 1)),
                            Header(stamp=stamp, frame_id='map'))]
        wait_for(lambda: stamp.sec * 10**9 + stamp.nanosec in node.poses['rover1'], 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='pose')
        for b in bad:
            cloud_pub['rover1'].publish(b)
        want = {'nan', 'unknown_frame', 'empty', 'absurd_range', 'too_large'}
        wait_for(lambda: want <= set(node.bad.counts), 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='rejections')
        assert node.fused == 2
        # save, a corrupted file is refused and the map kept, reload, reset
        save = _call(ex, peer.create_client(MapFile, '/map/save'), MapFile.Request())
        assert save.success and save.voxels == len(node.map)
        (tmp_path / 'bad.cmap').write_bytes(Path(mapfile).read_bytes()[:100])
        load = peer.create_client(MapFile, '/map/load')
        r = _call(ex, load, MapFile.Request(path=str(tmp_path / 'bad.cmap')))
        assert not r.success and 'kept' in r.message and r.voxels == save.voxels
        assert _call(ex, peer.create_client(Trigger, '/map/reset'), Trigger.Request()).success
        assert len(node.map) == 0
        r = _call(ex, load, MapFile.Request())
        assert r.success and r.voxels == save.voxels and node.map.sequence == 2
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


def test_mapper_publishes_surface_points_once_somebody_listens(ctx):
    """/map/surface: nothing is computed while nobody subscribes; a late subscriber gets the
    occupied voxels' surface points (on a wall at x = 2.03, where the voxel centres of
    /map/occupied are at 2.05), one per occupied voxel."""
    node, peer, ex = _mapper_and_peer(ctx)
    try:
        pose_pub = peer.create_publisher(PoseWithCovarianceStamped, '/rover1/camera_pose',
                                         LATCHED_QOS)
        cloud_pub = peer.create_publisher(PointCloud2, '/rover1/stereo/points', SENSOR_QOS)
        wait_for(lambda: peer.count_subscribers('/rover1/stereo/points') > 0, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='discovery')
        rng = np.random.default_rng(1)
        wall = np.column_stack([np.full(2000, 2.03), rng.uniform(-1, 1, 2000),
                                rng.uniform(0, 2, 2000)])
        stamp = peer.get_clock().now().to_msg()
        pose_pub.publish(_pose(stamp, (0.05, 0.05, 1.05)))
        cov = np.tile([1e-4, 0, 0, 1e-4, 0, 1e-4], (2000, 1))
        cloud_pub.publish(cloud_to_msg(wall, cov, Header(stamp=stamp, frame_id='map')))
        occupied, surface = [], []
        peer.create_subscription(PointCloud2, '/map/occupied', occupied.append, LATCHED_QOS)
        wait_for(lambda: node.fused == 1 and occupied, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='the occupied voxels')
        assert node._surface_dirty                  # published for nobody: not computed
        peer.create_subscription(PointCloud2, '/map/surface', surface.append, LATCHED_QOS)
        wait_for(lambda: surface, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
                 what='the surface points')
        centres, _ = msg_to_cloud(occupied[-1])
        pts, cov = msg_to_cloud(surface[-1])
        assert cov is None and len(pts) == len(centres) > 100
        np.testing.assert_allclose(centres[:, 0], 2.05, atol=1e-6)
        # ~5 points per voxel against the voxel-extent prior at its centre (voxelmap): 4 mm
        np.testing.assert_allclose(pts[:, 0], 2.03, atol=5e-3)
        assert surface[-1].header.frame_id == 'map'
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


def test_mapper_drops_a_teammate_body(ctx):
    """rover1 sees a wall 3 m ahead and rover2's body 1 m ahead; rover2's camera pose, taken
    before rover1's cloud, is known: the body's points are not fused (counted), the wall is."""
    node, peer, ex = _mapper_and_peer(ctx)
    try:
        pose_pub = {r: peer.create_publisher(PoseWithCovarianceStamped, f'/{r}/camera_pose',
                                             LATCHED_QOS) for r in ('rover1', 'rover2')}
        cloud_pub = peer.create_publisher(PointCloud2, '/rover1/stereo/points', SENSOR_QOS)
        wait_for(lambda: peer.count_subscribers('/rover1/stereo/points') > 0
                 and peer.count_subscribers('/rover2/camera_pose') > 0, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='discovery')
        rng = np.random.default_rng(1)
        wall = np.column_stack([np.full(1000, 3.03), rng.uniform(-1, 1, 1000),
                                rng.uniform(0, 2, 1000)])
        body = np.array([1.0, 0.0, 0.3]) + rng.uniform(-0.2, 0.2, (300, 3))
        pts = np.vstack([wall, body])
        cov = np.tile([1e-4, 0, 0, 1e-4, 0, 1e-4], (len(pts), 1))
        t2 = peer.get_clock().now().to_msg()
        pose_pub['rover2'].publish(_pose(t2, (1.05, 0.0, 0.8)))
        wait_for(lambda: node.poses['rover2'], 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what="rover2's pose")
        t1 = peer.get_clock().now().to_msg()
        t1.sec += 1
        pose_pub['rover1'].publish(_pose(t1, (0.0, 0.0, 0.8)))
        cloud_pub.publish(cloud_to_msg(pts, cov, Header(stamp=t1, frame_id='map')))
        wait_for(lambda: node.fused == 1, 10.0, spin=lambda t: ex.spin_once(timeout_sec=t),
                 what='the fused cloud')
        assert node.body_points == len(body)
        p = node.map.probability_at(np.array([[1.0, 0.0, 0.3], [3.05, 0.05, 1.05]]))
        assert p[0] <= 0.5 and p[1] > 0.6
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


def test_mapper_loads_last_save_on_restart(ctx, tmp_path):
    from coop_mapping.voxelmap import VoxelMap
    path = tmp_path / 'team.cmap'
    vm = VoxelMap(0.1)
    vm.insert_scan(np.array([[1.05, 0.05, 0.05]]), np.array([0.05, 0.05, 0.05]),
                   source='rover1')
    vm.save(path)
    node = MapperNode(context=ctx, parameter_overrides=[Parameter('map_file', value=str(path))])
    try:
        assert len(node.map) == len(vm) and node.map.contributions == {'rover1': 1}
    finally:
        node.destroy_node()


def test_mapper_saves_on_a_clean_stop_when_autosave_is_on(ctx, tmp_path):
    """destroy_node (run_node's clean stop) saves what came after the last autosave; with
    autosave off it writes nothing."""
    from coop_mapping.voxelmap import VoxelMap
    for period, expect_file in ((3600.0, True), (0.0, False)):
        path = tmp_path / f'team_{period:g}.cmap'
        node = MapperNode(context=ctx, parameter_overrides=[
            Parameter('map_file', value=str(path)),
            Parameter('autosave_period_s', value=period)])
        node.map.insert_scan(np.array([[1.05, 0.05, 0.05], [1.05, 1.05, 0.05]]),
                             np.array([0.05, 0.05, 0.05]), source='rover2')
        node.destroy_node()
        assert path.exists() is expect_file
        if expect_file:
            saved = VoxelMap.load(path)
            assert len(saved) == len(node.map) and saved.sequence == node.map.sequence
            assert saved.contributions == {'rover2': 1}


def test_mapper_moves_a_save_it_cannot_take_aside(ctx, tmp_path):
    """A last save of another resolution (or corrupt, or another version) is not loaded and
    not overwritten by the next autosave: it is moved to <map_file>.refused."""
    from coop_mapping.voxelmap import VoxelMap
    path = tmp_path / 'team.cmap'
    vm = VoxelMap(0.05)
    vm.insert_scan(np.array([[1.05, 0.05, 0.05]]), np.zeros(3), source='rover1')
    vm.save(path)
    raw = path.read_bytes()
    (tmp_path / 'team.cmap.refused').write_bytes(b'an older refused file')
    node = MapperNode(context=ctx, parameter_overrides=[Parameter('map_file', value=str(path))])
    try:
        assert len(node.map) == 0 and not path.exists()
        assert (tmp_path / 'team.cmap.refused.1').read_bytes() == raw
        assert (tmp_path / 'team.cmap.refused').read_bytes() == b'an older refused file'
        node.map.insert_scan(np.array([[1.05, 0.05, 0.05]]), np.zeros(3), source='rover1')
        assert node._save(str(path)) is None and VoxelMap.load(path).resolution == 0.1
        # max_points may be raised at run time: the map takes it too
        assert node.set_parameters([Parameter('max_points', value=7)])[0].successful
        assert node.map.max_points == 7
    finally:
        node.destroy_node()


@pytest.mark.parametrize('subpixel,full_width', [('sgbm', False), ('equalise', False),
                                                 ('shift4', False), ('shift4', True)])
def test_stereo_node_publishes_cloud_with_covariance(stereo_rig, subpixel, full_width):
    pytest.importorskip('pybullet')
    from coop_mapping.render import TexturedScene, look_at
    from coop_mapping.stereo import StereoCamera
    cam = StereoCamera.from_fov(320, 240, np.radians(41.2), 0.038)
    eye = np.array([0.0, 0.0, 1.0])
    R = look_at(eye, np.array([2.5, 0.0, 0.2]))
    with TexturedScene(cam, seed=2) as scene:
        left, right, _depth = scene.render(R, eye)
    rig = stereo_rig(cam, num_disparities=32, subpixel=subpixel, full_width=full_width)
    clouds = rig.listen(PointCloud2, 'stereo/points', SENSOR_QOS)
    rig.start()
    rig.send(left, right, rig.peer.get_clock().now().to_msg(), R, eye)
    wait_for(lambda: clouds, 20.0, spin=rig.spin, what='stereo/points')
    assert rig.node.ranger.subpixel == subpixel        # the parameters reached the ranger
    assert rig.node.ranger.full_width == full_width
    pts, cov = msg_to_cloud(clouds[0])
    # full width ranges the left 32 columns (the search range) too
    u = np.asarray(rig.node.ranger.disparity(left, right))[:, :32]
    assert np.isfinite(u).any() == full_width
    assert clouds[0].header.frame_id == 'map' and cov is not None
    assert len(pts) > 0.4 * cam.width * cam.height
    # the map-frame points lie on the true surfaces: most are at or above the ground
    assert np.median(pts[:, 2]) > -0.05 and np.percentile(pts[:, 2], 5) > -0.3
    assert np.all(cov[:, 0] > 0) and np.all(cov[:, 5] > 0)


def test_stereo_node_corrects_dead_reckoning_with_fiducials(stereo_rig):
    pytest.importorskip('pybullet')
    from coop_mapping.render import TexturedScene, look_at
    from coop_mapping.stereo import StereoCamera
    cam = StereoCamera.from_fov(320, 240, np.radians(41.2), 0.038)
    R = look_at(np.zeros(3), np.array([1.0, 0.0, -0.3]))
    true_eyes = [np.array([0.8, 0.0, 0.6]), np.array([0.8, 0.06, 0.6])]
    # the dead reckoning gets the second step 40 % wrong sideways and 2 cm forward
    dr_eyes = [true_eyes[0], true_eyes[1] + np.array([0.02, 0.024, 0.0])]
    with TexturedScene(cam, seed=4) as scene:
        pairs = [scene.render(R, e)[:2] for e in true_eyes]
    rig = stereo_rig(cam, num_disparities=32, fiducial_correction='pnp', scene_distance_m=2.0)
    poses = rig.listen(PoseWithCovarianceStamped, 'camera_pose', LATCHED_QOS)
    rig.start()
    for i, ((left, right), eye) in enumerate(zip(pairs, dr_eyes, strict=False)):
        stamp = rig.peer.get_clock().now().to_msg()
        stamp.sec += i
        rig.send(left, right, stamp, R, eye)
        wait_for(lambda i=i: len(poses) == i + 1, 20.0, spin=rig.spin, what=f'camera_pose {i}')
    p = poses[-1].pose.pose.position
    corrected = np.array([p.x, p.y, p.z])
    err_dr = np.linalg.norm(dr_eyes[1] - true_eyes[1])
    err_fc = np.linalg.norm(corrected - true_eyes[1])
    print(f'dead-reckoned error {err_dr:.4f} m, corrected {err_fc:.4f} m')
    assert err_fc < 0.5 * err_dr
    # the filter's pose covariance (ROS order), not the one-frame Eq. 3-19 sample covariance
    # (identically 0) pasted into the dead reckoning's
    cov = np.array(poses[-1].pose.covariance).reshape(6, 6)
    assert np.allclose(cov, cov.T) and np.linalg.eigvalsh(cov).min() >= -1e-12
    assert np.all(np.diag(cov)[:3] > 0) and np.sqrt(np.diag(cov)[:3]).max() < 0.5
    # a pair of another size than camera_info is rejected before the filter sees it, and the
    # next good pair is corrected as before
    for k, (pair, eye) in enumerate((((pairs[1][0][::2, ::2], pairs[1][1][::2, ::2]),
                                      dr_eyes[1]), (pairs[1], dr_eyes[1]))):
        stamp = rig.peer.get_clock().now().to_msg()
        stamp.sec += 2 + k
        rig.send(pair[0], pair[1], stamp, R, eye)
    wait_for(lambda: len(poses) == 3 and rig.node.bad.counts['stereo'] == 1, 20.0,
             spin=rig.spin, what='the bad pair rejected, the good one published')


def test_stereo_node_counts_frames_that_never_complete(ctx):
    """A frame missing its right image, pose or left image is dropped and counted once when a
    later frame completes, or when it is the oldest of more than 10 waiting; a complete frame
    is not."""
    from builtin_interfaces.msg import Time

    from coop_mapping.stereo_node import StereoNode
    node = StereoNode(context=ctx)

    def put(kind, sec):
        m = PoseWithCovarianceStamped()       # _put reads the header only
        m.header = Header(stamp=Time(sec=sec), frame_id='map')
        node._put(kind, m)
    try:
        put('left', 1)                          # right and pose never come
        put('left', 2)
        put('pose', 2)                          # right never comes
        for kind in ('pose', 'right', 'left'):  # complete: the ones before it are dropped
            put(kind, 3)
        assert node.bad.counts['unmatched'] == 2 and all(not b for b in node.buf.values())
        assert len(node._waiting) == 1          # no camera_info yet: held, not dropped
        for sec in range(10, 22):               # 12 lone left images: the oldest two go
            put('left', sec)
        assert node.bad.counts['unmatched'] == 4 and list(node.buf['left']) == [
            int(sec * 1e9) for sec in range(12, 22)]
    finally:
        node.destroy_node()


def test_stereo_node_checks_its_ranges_together(ctx):
    """min_range_m below max_range_m (and the marker radii likewise), at start and on a change."""
    from coop_mapping.stereo_node import StereoNode
    with pytest.raises(ValueError, match='max_range_m'):
        StereoNode(context=ctx, parameter_overrides=[Parameter('min_range_m', value=12.0)])
    with pytest.raises(ValueError, match='marker_max_radius_px'):
        StereoNode(context=ctx, parameter_overrides=[Parameter('marker_min_radius_px',
                                                               value=30.0)])
    node = StereoNode(context=ctx)
    try:
        r = node.set_parameters([Parameter('min_range_m', value=20.0)])[0]
        assert not r.successful and 'max_range_m' in r.reason and node.p['min_range_m'] == 0.2
        r = node.set_parameters([Parameter('num_disparities', value=24)])[0]
        assert not r.successful and 'multiple of 16' in r.reason
        assert node.set_parameters([Parameter('min_range_m', value=0.5)])[0].successful
        r = node.set_parameters([Parameter('subpixel', value='shift8')])[0]
        assert not r.successful and r.reason == (
            "subpixel must be one of ['sgbm', 'equalise', 'shift2', 'shift4'], got 'shift8'")
        assert node.fiducial_method is None          # fiducial_correction 'none'
    finally:
        node.destroy_node()
    with pytest.raises(ValueError, match=r"fiducial_correction must be one of \['none', "
                       r"'linear', 'linear_so3', 'rigid', 'pnp'\], got 'icp'"):
        StereoNode(context=ctx, parameter_overrides=[Parameter('fiducial_correction',
                                                               value='icp')])


def test_mapper_autosaves_a_reset_or_loaded_map_whatever_its_sequence(ctx, tmp_path):
    """The map_file holds the map the mapper has: after /map/reset (the sequence starts again
    at 0) or a /map/load of another file, the next autosave writes even when the sequence has
    come back to the one last saved; a save elsewhere does not count as saved."""
    from coop_mapping.voxelmap import VoxelMap
    path, other = tmp_path / 'team.cmap', tmp_path / 'other.cmap'

    stamps = iter(range(1000, 2000))

    def scan(node, x):                  # a cloud of a wall at x and its camera pose
        st = Time(sec=next(stamps))
        node.on_pose('rover1', _pose(st, [0.05, 0.05, 1.05]))
        yz = np.stack(np.meshgrid(np.arange(-1, 1, 0.05), np.arange(0, 2, 0.05)), -1)
        pts = np.column_stack([np.full(len(yz.reshape(-1, 2)), x), yz.reshape(-1, 2)])
        node.on_cloud('rover1', cloud_to_msg(pts, None, Header(stamp=st, frame_id='map')))

    def autosave(node):
        node._last_save = -np.inf
        node.on_timer()

    def wall_x(p):
        return float(VoxelMap.load(p).occupied_centres()[:, 0].mean())

    node, peer, ex = _mapper_and_peer(ctx, map_file=str(path), autosave_period_s=3600.0)
    try:
        scan(node, 2.05)
        autosave(node)
        assert VoxelMap.load(path).sequence == 1 and wall_x(path) == pytest.approx(2.05, abs=0.05)
        assert _call(ex, peer.create_client(Trigger, '/map/reset'), Trigger.Request()).success
        scan(node, -3.05)                                   # sequence 1 again
        autosave(node)
        assert node.map.sequence == 1 and wall_x(path) == pytest.approx(-3.05, abs=0.05)
        # a map loaded from another file is not what map_file holds
        vm = VoxelMap(0.1)
        vm.insert_scan(np.array([[5.05, 0.05, 0.05]]), np.zeros(3), source='rover2')
        vm.save(other)
        req = MapFile.Request()
        req.path = str(other)
        assert _call(ex, peer.create_client(MapFile, '/map/load'), req).success
        req.path = str(tmp_path / 'copy.cmap')
        assert _call(ex, peer.create_client(MapFile, '/map/save'), req).success
        autosave(node)
        assert wall_x(path) == pytest.approx(5.05, abs=0.05)
        # map_file reached through a symlinked directory is map_file: saved, nothing to autosave
        scan(node, 1.05)
        assert node.unsaved
        (tmp_path / 'alias').symlink_to(tmp_path, target_is_directory=True)
        req.path = str(tmp_path / 'alias' / 'team.cmap')
        assert _call(ex, peer.create_client(MapFile, '/map/save'), req).success
        assert not node.unsaved
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


@pytest.mark.parametrize('params,reason', [
    ({'rovers': ['rover1', 'rover1']}, 'listed twice'),
    ({'rovers': ['rover 1']}, 'not a namespace'),
    ({'rovers': ['']}, 'not a namespace'),
    ({'rovers': ['1abc']}, 'not a namespace'),
    ({'map_frame': ''}, 'map_frame'),
])
def test_mapper_refuses_bad_rover_names_and_frames_at_start(ctx, params, reason):
    """A rover listed twice would have each cloud fused twice; a name that is no namespace
    would fail deep in create_subscription: both are a clear ValueError (run_node: one FATAL
    line, exit 1)."""
    with pytest.raises(ValueError, match=reason):
        MapperNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                     for k, v in params.items()])


def test_mapper_refuses_a_map_file_that_is_a_directory(ctx, tmp_path):
    """map_file naming a directory stops the start with the reason; the directory is not
    moved aside as a refused save."""
    (tmp_path / 'maps').mkdir()
    with pytest.raises(ValueError, match='not a file'):
        MapperNode(context=ctx, parameter_overrides=[
            Parameter('map_file', value=str(tmp_path / 'maps'))])
    assert (tmp_path / 'maps').is_dir() and not list(tmp_path.glob('maps.refused*'))


def test_mapper_fuses_each_contribution_once_across_resends_and_restarts(ctx, tmp_path):
    """Contributions (map_input contributions): fused once whatever comes again (a resent
    backlog, an old session), with the missing counted; a teammate's body dropped voxel by
    voxel; the wrong source or settings refused; a mapper restarted from its save skips what
    it had fused."""
    from coop_common.qos import CONTRIBUTION_QOS
    from coop_mapping.ros_conv import contribution_to_msg
    from coop_mapping.voxelmap import VoxelMap
    from coop_msgs.msg import MapContribution
    mapfile = tmp_path / 'team.cmap'
    node, peer, ex = _mapper_and_peer(ctx, map_input='contributions', map_file=str(mapfile),
                                      autosave_period_s=3600.0, silent_after_s=1.0)
    spin = {'spin': lambda t: ex.spin_once(timeout_sec=t)}
    rng = np.random.default_rng(3)
    maker = VoxelMap(0.1)

    def contribution(seq, *, session=100, source='rover1', org=(0.0, 0.0, 0.8), body=False,
                     vm=maker, sec=10):
        wall = np.column_stack([np.full(500, 3.03), rng.uniform(-1, 1, 500),
                                rng.uniform(0, 2, 500)])
        pts = np.vstack([wall, np.array([1.0, 0.0, 0.3]) + rng.uniform(-0.2, 0.2, (200, 3))]) \
            if body else wall
        cov = np.tile([1e-4, 0, 0, 1e-4, 0, 1e-4], (len(pts), 1))
        c = vm.contribution(pts, np.array(org), covariances=cov)
        return contribution_to_msg(c, vm, Header(stamp=Time(sec=sec + seq), frame_id='map'),
                                   source=source, session=session, sequence=seq)
    try:
        pub = {r: peer.create_publisher(MapContribution, f'/{r}/map_contribution',
                                        CONTRIBUTION_QOS) for r in ('rover1', 'rover2')}
        wait_for(lambda: all(peer.count_subscribers(f'/{r}/map_contribution') for r in pub),
                 10.0, what='discovery', **spin)
        pub['rover1'].publish(contribution(1))
        pub['rover1'].publish(contribution(3))
        pub['rover1'].publish(contribution(1))                 # resent
        wait_for(lambda: node.fused == 2 and node.bad.counts['duplicate'] == 1, 10.0,
                 what='two fused, one duplicate', **spin)
        assert node.map.ledger.missing('rover1') == 1          # 2 has not come
        pub['rover1'].publish(contribution(1, session=200))    # rover1's stereo restarted
        pub['rover1'].publish(contribution(4))                 # its old session, late
        pub['rover1'].publish(contribution(5, source='rover2'))
        pub['rover2'].publish(contribution(1, vm=VoxelMap(0.2), source='rover2'))
        wait_for(lambda: node.fused == 3 and node.bad.counts['old_session'] == 1
                 and node.bad.counts['source'] == 1 and node.bad.counts['format'] == 1, 10.0,
                 what='the restart and the refusals', **spin)
        # rover2 stands 1 m ahead of rover1 (its camera known from its contribution): rover1's
        # view of it is not fused, the wall behind is
        pub['rover2'].publish(contribution(1, source='rover2', org=(1.05, 0.0, 0.8), sec=20))
        wait_for(lambda: node.fused == 4, 10.0, what="rover2's contribution", **spin)
        pub['rover1'].publish(contribution(2, session=200, body=True, sec=21))
        wait_for(lambda: node.fused == 5, 10.0, what="rover1's view of rover2", **spin)
        assert node.body_points >= 150
        p = node.map.probability_at(np.array([[1.0, 0.0, 0.3], [3.05, 0.05, 1.05]]))
        assert p[0] <= 0.5 and p[1] > 0.6
        assert node.map.contributions == {'rover1': 4, 'rover2': 1}
        # rovers that stop sending are reported; the map keeps what they sent
        wait_for(lambda: node._reported_silent == {'rover1', 'rover2'}, 10.0,
                 what='the silent rovers reported', **spin)
        assert node.map.contributions == {'rover1': 4, 'rover2': 1}
    finally:
        ex.shutdown()
        node.destroy_node()             # saves the map and its ledger
        peer.destroy_node()
    node, peer, ex = _mapper_and_peer(ctx, map_input='contributions', map_file=str(mapfile),
                                      autosave_period_s=3600.0)
    try:
        pub = peer.create_publisher(MapContribution, '/rover1/map_contribution',
                                    CONTRIBUTION_QOS)
        wait_for(lambda: peer.count_subscribers('/rover1/map_contribution'), 10.0,
                 what='discovery', **spin)
        pub.publish(contribution(2, session=200))           # fused before the restart
        pub.publish(contribution(3, session=200))
        wait_for(lambda: node.fused == 1 and node.bad.counts['duplicate'] == 1, 10.0,
                 what='the replay after the restart', **spin)
        assert node.map.contributions == {'rover1': 5, 'rover2': 1}
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()


def test_mapper_counts_the_clouds_the_middleware_dropped(ctx):
    """Gaps in a cloud writer's sequence numbers are clouds lost on the way (best effort); a
    sequence that starts again is a restarted stereo node, not a loss. And over DDS, clouds
    published one by one arrive with consecutive numbers: none counted."""
    node, peer, ex = _mapper_and_peer(ctx)
    try:
        for seq in (1, 2, 5, 6, 1, 2, 4):
            node._count_missed('rover1', seq)
        assert node.clouds_missed == {'rover1': 3}
        pub = peer.create_publisher(PointCloud2, '/rover2/stereo/points', SENSOR_QOS)
        wait_for(lambda: peer.count_subscribers('/rover2/stereo/points') > 0, 10.0,
                 spin=lambda t: ex.spin_once(timeout_sec=t), what='discovery')
        pts = np.array([[3.0, 0.0, 0.5]])
        for k in range(3):
            pub.publish(cloud_to_msg(pts, None, Header(stamp=Time(sec=k + 1), frame_id='map')))
            wait_for(lambda k=k: node.cloud_seq.get('rover2') == k + 1, 10.0,
                     spin=lambda t: ex.spin_once(timeout_sec=t), what=f'cloud {k + 1}')
        assert node.clouds_missed['rover2'] == 0
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()
