"""§3.2.2 initialisation wired into the stereo node: a rover whose dead reckoning is off by a
yaw and a shift finds rover_sim's insertion site (its two markers, rendered by the sim's own
PyBullet world) and from then on publishes its pose and clouds in the common `map` frame."""
import math

import numpy as np
import pytest
from geometry_msgs.msg import PoseWithCovarianceStamped
from sensor_msgs.msg import PointCloud2

from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import wait_for
from coop_mapping.figures import initialisation_lines
from coop_mapping.render import look_at
from coop_mapping.ros_conv import msg_to_cloud, pose_to_rt
from coop_mapping.stereo import StereoCamera


def _rot_err(R_true, R):
    E = R_true @ R.T
    return 0.5 * np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])


def test_stereo_node_initialises_on_the_sim_site_from_a_wrong_dead_reckoned_frame(stereo_rig,
                                                                                  figures):
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

    rig = stereo_rig(cam, initialise=True, num_disparities=64)
    node, spin = rig.node, rig.spin
    got = {k: rig.listen(t, n, q) for k, t, n, q in [
        ('target', PoseWithCovarianceStamped, 'stereo/target_pose', LATCHED_QOS),
        ('alignment', PoseWithCovarianceStamped, 'stereo/alignment', LATCHED_QOS),
        ('pose', PoseWithCovarianceStamped, 'camera_pose', LATCHED_QOS),
        ('cloud', PointCloud2, 'stereo/points', SENSOR_QOS)]}
    rig.start()
    base = rig.peer.get_clock().now().to_msg()

    def send(i):
        rig.send(*pairs[i], base.__class__(sec=base.sec + i, nanosec=base.nanosec), *own[i],
                 frame='rover1/odom')

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
    frames = []
    for k, msg in enumerate(got['pose']):
        i = k + 1
        assert msg.header.frame_id == 'map' and got['cloud'][k].header.frame_id == 'map'
        R, t = pose_to_rt(msg.pose.pose)
        R_true, t_true = truth[i]
        cov = np.reshape(msg.pose.covariance, (6, 6))
        sig = np.sqrt(np.diag(cov))
        err = np.r_[t_true - t, _rot_err(R_true, R)]
        dr_err = np.linalg.norm(own[i][1] - t_true)
        frames.append({'frame': i, 'dead_reckoned_m': dr_err, 'position_error_m': err[:3],
                       'rotation_error_deg': np.degrees(err[3:]), 'sigma_m': sig[:3],
                       'sigma_deg': np.degrees(sig[3:])})
        assert dr_err > 1.0
        assert np.all(np.abs(err) < 3 * sig), (err, sig)
    # the last cloud (markers out of view) lies where the true pose puts it
    pts, _ = msg_to_cloud(got['cloud'][-1])
    ref = node.ranger.process(*pairs[2], *truth[2]).points   # same ranger, true pose
    d = np.linalg.norm(pts - ref, axis=1)
    print(initialisation_lines(figures.add('initialisation', {
        'far_sigma_m': sig0, 'fix_sigma_m': fix_sigma,
        'threshold_m': node.p['init_max_position_sigma_m'], 'frames': frames,
        'cloud_points': len(pts), 'cloud_median_m': float(np.median(d))})))
    assert len(pts) == len(ref) and np.median(d) < 0.05
