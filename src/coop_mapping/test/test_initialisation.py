"""§3.2.2 initialisation wired into the stereo node: a rover whose dead reckoning is off by a
yaw and a shift finds rover_sim's insertion site (its two markers, rendered by the sim's own
PyBullet world) and from then on publishes its pose and clouds in the common `map` frame."""
import math

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header

from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import wait_for
from coop_mapping.render import look_at
from coop_mapping.ros_conv import msg_to_cloud, pose_to_rt
from coop_mapping.stereo import StereoCamera
from coop_mapping.stereo_node import StereoNode, _quat


@pytest.fixture
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    rclpy.try_shutdown(context=c)


def _image(a, stamp):
    m = Image()
    m.header = Header(stamp=stamp, frame_id='rover1/left_camera_optical_frame')
    m.height, m.width = a.shape
    m.encoding, m.step = 'mono8', a.shape[1]
    m.data = a.tobytes()
    return m


def _rot_err(R_true, R):
    E = R_true @ R.T
    return 0.5 * np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])


def test_stereo_node_initialises_on_the_sim_site_from_a_wrong_dead_reckoned_frame(ctx):
    pytest.importorskip('pybullet')
    from coop_common.dynparams import load_truth
    from rover_sim.config import SimConfig
    from rover_sim.world import World

    W, H = 640, 480
    cfg = SimConfig(rovers=1, stereo_rate_hz=4.0, image_width=W, image_height=H)
    with World(cfg, [load_truth()]) as world:
        K = world.intrinsics()
        cam = StereoCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.038, W, H)
        M = np.asarray(world.layout.site.markers)

        def render(R, eye):
            return world.render_stereo_at(eye, R)

        # true camera poses in map: 1.6 m from the markers (too far to accept), 1.0 m (fixes
        # the alignment), then a look past the site (markers out of view) after a move
        views = [(np.array([1.3, 0.0, 0.45]), M.mean(0)),
                 (np.array([1.9, 0.05, 0.5]), M.mean(0) + [0.0, 0.03, -0.02]),
                 (np.array([1.7, -0.2, 0.55]), np.array([3.0, 0.6, 0.1]))]
        truth = [(look_at(eye, tgt), eye) for eye, tgt in views]
        pairs = [render(R, eye) for R, eye in truth]

    # the rover's own dead-reckoned frame: 0.6 rad of yaw and (-2, 1.5, 0) m off `map`
    a = 0.6
    R_om = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0],
                     [0.0, 0.0, 1.0]])
    t_om = np.array([-2.0, 1.5, 0.0])
    own = [(R_om @ R, R_om @ eye + t_om) for R, eye in truth]

    node = StereoNode(context=ctx, namespace='rover1', parameter_overrides=[
        Parameter('initialise', value=True), Parameter('num_disparities', value=64)])
    peer = Node('peer', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(peer)
    spin = lambda t: ex.spin_once(timeout_sec=t)  # noqa: E731
    try:
        pubs = {k: peer.create_publisher(t, f'/rover1/{n}', SENSOR_QOS) for k, t, n in [
            ('l', Image, 'stereo/left/image_raw'), ('r', Image, 'stereo/right/image_raw'),
            ('li', CameraInfo, 'stereo/left/camera_info'),
            ('ri', CameraInfo, 'stereo/right/camera_info'),
            ('pose', PoseWithCovarianceStamped, 'stereo/pose')]}
        got = {'target': [], 'alignment': [], 'pose': [], 'cloud': []}
        for k, t, n, q in [('target', PoseWithCovarianceStamped, 'stereo/target_pose',
                            LATCHED_QOS),
                           ('alignment', PoseWithCovarianceStamped, 'stereo/alignment',
                            LATCHED_QOS),
                           ('pose', PoseWithCovarianceStamped, 'camera_pose', LATCHED_QOS),
                           ('cloud', PointCloud2, 'stereo/points', SENSOR_QOS)]:
            peer.create_subscription(t, f'/rover1/{n}', got[k].append, q)
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in pubs.values()), 10.0,
                 spin=spin, what='discovery')
        for side in ('li', 'ri'):
            info = CameraInfo()
            info.width, info.height = W, H
            tx = 0.0 if side == 'li' else -cam.fx * cam.baseline
            info.p = [cam.fx, 0.0, cam.cx, tx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
            pubs[side].publish(info)
        wait_for(lambda: len(node.info) == 2, 10.0, spin=spin, what='camera_info')
        base = peer.get_clock().now().to_msg()

        def send(i):
            stamp = base.__class__(sec=base.sec + i, nanosec=base.nanosec)
            R, t = own[i]
            pose = PoseWithCovarianceStamped()
            pose.header = Header(stamp=stamp, frame_id='rover1/odom')
            p = pose.pose.pose
            p.position.x, p.position.y, p.position.z = (float(v) for v in t)
            p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = _quat(R)
            pubs['pose'].publish(pose)
            pubs['l'].publish(_image(pairs[i][0], stamp))
            pubs['r'].publish(_image(pairs[i][1], stamp))

        # 1.6 m: the site is found but its predicted position sigma is above the threshold
        send(0)
        wait_for(lambda: got['target'], 20.0, spin=spin, what='target_pose 0')
        sig0 = np.sqrt(np.diag(np.reshape(got['target'][0].pose.covariance, (6, 6))))[:3]
        assert not node.initialiser.initialised and not got['pose'] and not got['cloud']
        # 1.0 m: accepted, the alignment is fixed; pose and cloud now come in `map`
        send(1)
        wait_for(lambda: got['alignment'] and got['cloud'], 20.0, spin=spin, what='frame 1')
        send(2)
        wait_for(lambda: len(got['cloud']) == 2 and len(got['pose']) == 2, 20.0, spin=spin,
                 what='frame 2')
        spin(0.2)
        assert len(got['target']) == 2 and len(got['alignment']) == 1
        fix_sigma = np.sqrt(np.diag(np.reshape(got['target'][1].pose.covariance, (6, 6))))[:3]
        print(f'target fix position sigma at 1.6 m {np.round(sig0, 3)} m (largest '
              f'{sig0.max():.3f} > 0.1: waits), at 1.0 m {np.round(fix_sigma, 3)} m')
        for k, msg in enumerate(got['pose']):
            i = k + 1
            assert msg.header.frame_id == 'map' and got['cloud'][k].header.frame_id == 'map'
            R, t = pose_to_rt(msg.pose.pose)
            R_true, t_true = truth[i]
            cov = np.reshape(msg.pose.covariance, (6, 6))
            sig = np.sqrt(np.diag(cov))
            err = np.r_[t_true - t, _rot_err(R_true, R)]
            dr_err = np.linalg.norm(own[i][1] - t_true)
            print(f'frame {i}: dead-reckoned position error {dr_err:.3f} m; common-frame '
                  f'position error {np.round(err[:3], 4)} m, rotation error '
                  f'{np.round(np.degrees(err[3:]), 2)} deg, predicted sigma '
                  f'{np.round(sig[:3], 4)} m / {np.round(np.degrees(sig[3:]), 2)} deg')
            assert dr_err > 1.0
            assert np.all(np.abs(err) < 3 * sig), (err, sig)
        # the last cloud (markers out of view) lies where the true pose puts it
        pts, _ = msg_to_cloud(got['cloud'][-1])
        ref = node.ranger.process(*pairs[2], *truth[2]).points   # same ranger, true pose
        d = np.linalg.norm(pts - ref, axis=1)
        print(f'frame 2 cloud: {len(pts)} points, median distance to the true-pose cloud '
              f'{np.median(d):.3f} m')
        assert len(pts) == len(ref) and np.median(d) < 0.05
    finally:
        ex.shutdown()
        node.destroy_node()
        peer.destroy_node()
