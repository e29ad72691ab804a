"""Whole-graph tests of the installed `rover_sim sim` executable over DDS: rates, units and
frames, /clock and use_sim_time, determinism, F/T and inclinometer physics, namespaces,
parameter files, bad input and bad configuration."""
from __future__ import annotations

import math
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest
from geometry_msgs.msg import PoseStamped, WrenchStamped
from nav_msgs.msg import Odometry
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint
from visualization_msgs.msg import MarkerArray

from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import NodeProcess, Probe, executable_path, wait_for
from coop_msgs.msg import ContactState, DynamicParameters, Inclinometer
from coop_msgs.srv import SimScenario

pytestmark = pytest.mark.graph


def t_of(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def sim_process(tmp_path: Path, *ros_args: str, name: str = 'sim') -> NodeProcess:
    return NodeProcess('rover_sim', 'sim', ros_args, log_path=tmp_path / f'{name}.log')


@pytest.fixture(scope='module')
def soft_truth(tmp_path_factory) -> Path:
    """A rover with a soft roll/pitch suspension, so the tilt is far above the 10-bit step."""
    import yaml

    from coop_common.dynparams import load_truth
    d = load_truth().to_dict()
    d.update(k_roll=250.0, k_pitch=200.0)
    path = tmp_path_factory.mktemp('truth') / 'soft.yaml'
    path.write_text(yaml.safe_dump(d))
    return path


@pytest.fixture(scope='module')
def live(tmp_path_factory, soft_truth):
    """One simulator (seed 3, soft suspension, rtf 1) and a probe subscribed to its topics."""
    tmp = tmp_path_factory.mktemp('live')
    proc = sim_process(tmp, '-p', 'seed:=3', '-p', f'truth_yaml:={soft_truth}',
                       '-p', 'real_time_factor:=1.0', '-p', 'image_width:=160',
                       '-p', 'image_height:=120')
    with proc:
        probe = Probe()
        for topic, typ in (('/clock', Clock), ('/rover1/imu', Imu),
                           ('/rover1/inclinometer', Inclinometer),
                           ('/rover1/arm/wrench', WrenchStamped),
                           ('/rover1/joint_states', JointState),
                           ('/rover2/stereo/left/image_raw', Image),
                           ('/rover2/stereo/right/camera_info', CameraInfo),
                           ('/sim/rover1/base_pose', PoseStamped)):
            # deep queues: a one-thread Python probe on eight 200 Hz topics must not be what
            # drops samples (the rates below are the publisher's)
            probe.listen(typ, topic, QoSProfile(depth=500,
                                                reliability=ReliabilityPolicy.BEST_EFFORT)
                         if topic != '/clock' else 500)
        probe.listen(DynamicParameters, '/sim/rover1/parameters', LATCHED_QOS)
        probe.listen(MarkerArray, '/sim/world', LATCHED_QOS)
        probe.spin_until(lambda: probe.count('/rover2/stereo/left/image_raw') >= 2, 60.0,
                         'the first stereo images')
        yield proc, probe
        probe.close()


def test_topic_rates_within_10_percent(live):
    _, probe = live
    start = {k: len(v) for k, v in probe.msgs.items()}
    clock0 = probe.msgs['/clock'][-1].clock
    probe.spin_until(lambda: (probe.msgs['/clock'][-1].clock.sec - clock0.sec) >= 4, 30.0,
                     '4 s of sim time')
    span = {}
    for topic, expected in (('/rover1/imu', 200.0), ('/rover1/inclinometer', 200.0),
                            ('/rover1/arm/wrench', 200.0), ('/rover1/joint_states', 200.0),
                            ('/rover2/stereo/left/image_raw', 4.0),
                            ('/sim/rover1/base_pose', 50.0)):
        new = probe.msgs[topic][start[topic]:]
        stamps = [t_of(m.header) for m in new]
        span[topic] = stamps[-1] - stamps[0]
        rate = (len(stamps) - 1) / span[topic]
        assert rate == pytest.approx(expected, rel=0.10), (topic, rate)
    clocks = probe.msgs['/clock'][start['/clock']:]
    ticks = [c.clock.sec + c.clock.nanosec * 1e-9 for c in clocks]
    # clock_rate_hz: 100 Hz, the lockstep round
    assert (len(ticks) - 1) / (ticks[-1] - ticks[0]) == pytest.approx(100.0, rel=0.10)


def test_units_and_frames(live):
    _, probe = live
    imu = probe.msgs['/rover1/imu'][-1]
    assert imu.header.frame_id == 'rover1/base_link'
    assert imu.linear_acceleration.z == pytest.approx(9.81, abs=0.1)     # REP 103/145: z up
    assert imu.orientation_covariance[0] == -1.0
    wrench = probe.msgs['/rover1/arm/wrench'][-1]
    assert wrench.header.frame_id == 'rover1/ft_sensor_link'
    img = probe.msgs['/rover2/stereo/left/image_raw'][-1]
    assert (img.encoding, img.width, img.height) == ('mono8', 160, 120)
    assert img.header.frame_id == 'rover2/left_camera_optical_frame'
    info = probe.msgs['/rover2/stereo/right/camera_info'][-1]
    fx = info.k[0]
    assert fx == pytest.approx(80 / np.tan(np.radians(41.2) / 2), rel=1e-6)
    assert info.p[3] == pytest.approx(-fx * 0.038)                   # Tx = -fx * baseline
    assert info.header.frame_id == 'rover2/right_camera_optical_frame'
    pose = probe.msgs['/sim/rover1/base_pose'][-1]
    assert pose.header.frame_id == 'map'
    js = probe.msgs['/rover1/joint_states'][-1]
    assert {'arm_joint_1', 'arm_joint_2', 'wheel_fl', 'articulation', 'mast_tilt'} <= set(js.name)
    truth = probe.msgs['/sim/rover1/parameters'][-1]
    # the truth_yaml took
    assert dict(zip(truth.names, truth.values, strict=False))['k_pitch'] == 200.0
    probe.listen(Odometry, '/rover2/odom')
    probe.spin_until(lambda: probe.count('/rover2/odom') > 0, 10.0, 'odometry')
    odom = probe.msgs['/rover2/odom'][-1]
    assert (odom.header.frame_id, odom.child_frame_id) == ('rover2/odom', 'rover2/base_link')


def test_stamps_follow_clock_and_use_sim_time(live):
    _, probe = live
    user = Probe('sim_time_user', parameter_overrides=[Parameter('use_sim_time', value=True)])
    try:
        user.listen(Clock, '/clock', 10)
        user.spin_until(lambda: user.count('/clock') >= 20, 20.0, '/clock at the user node')
        last = user.msgs['/clock'][-1].clock
        now = user.node.get_clock().now().nanoseconds * 1e-9
        sim = last.sec + last.nanosec * 1e-9
        assert abs(now - sim) < 0.5
        assert abs(now - time.time()) > 1e6          # sim time, not the epoch
    finally:
        user.close()
    # the sensors are stamped on the clock's time line: /clock ticks every other sensor
    # reading (clock_rate_hz 100, sensors 200 Hz), each at a reading's stamp
    imu_t = [t_of(m.header) for m in probe.msgs['/rover1/imu'][-10:]]
    clock_t = [c.clock.sec + c.clock.nanosec * 1e-9 for c in probe.msgs['/clock'][-400:]]
    on_clock = [min(abs(t - c) for c in clock_t) < 1e-9 for t in imu_t]
    assert 4 <= sum(on_clock) <= 6, (imu_t, clock_t[-10:])


def _move_arm(probe: Probe, positions: list[float], duration: float) -> None:
    """Command arm joints 1, 2 and wait until the encoders show them there (re-sending, since a
    fresh publisher's first message can be lost while the match completes), then 2 s to settle."""
    if not hasattr(probe, 'arm_pub'):
        probe.arm_pub = probe.node.create_publisher(JointTrajectory, '/rover1/arm/joint_command',
                                                    10)
    pub = probe.arm_pub
    wait_for(lambda: pub.get_subscription_count() > 0, 10.0, what='sim arm subscriber')
    traj = JointTrajectory(joint_names=['arm_joint_1', 'arm_joint_2'])
    pt = JointTrajectoryPoint(positions=positions)
    pt.time_from_start.sec, pt.time_from_start.nanosec = int(duration), int(
        (duration % 1) * 1e9)
    traj.points = [pt]

    def there() -> bool:
        recent = probe.msgs['/rover1/joint_states'][-40:]
        q = np.mean([[dict(zip(m.name, m.position, strict=False))[j] for j in traj.joint_names]
                     for m in recent], axis=0)
        return bool(np.all(np.abs(q - positions) < 0.05))

    deadline = time.monotonic() + 60.0
    while not there():
        assert time.monotonic() < deadline, 'the arm never reached its target'
        pub.publish(traj)
        try:
            probe.spin_until(there, 5.0, 'the arm at its target')
        except TimeoutError:
            continue
    clock0 = probe.msgs['/clock'][-1].clock.sec
    probe.spin_until(lambda: probe.msgs['/clock'][-1].clock.sec >= clock0 + 2, 30.0,
                     'the arm to settle')


def _mean_after(probe: Probe, topic: str, n: int, fn):
    start = probe.count(topic)
    probe.spin_until(lambda: probe.count(topic) >= start + n, 30.0, f'{n} msgs on {topic}')
    return np.mean([fn(m) for m in probe.msgs[topic][start:start + n]], axis=0)


def test_ft_reads_the_arm_reaction_and_inclinometer_follows_the_compliance(live):
    _, probe = live
    readings = {}
    for label, target in (('up', [0.0, 1.2]), ('front', [0.0, 0.0]), ('left', [1.5708, 0.0])):
        _move_arm(probe, target, 1.0)
        force = _mean_after(probe, '/rover1/arm/wrench', 200,
                            lambda m: [m.wrench.force.x, m.wrench.force.y, m.wrench.force.z])
        incl = _mean_after(probe, '/rover1/inclinometer', 200, lambda m: [m.roll, m.pitch])
        readings[label] = (force, incl)
    for force, (roll, pitch) in readings.values():
        # static reaction = the arm's weight seen in the tilted base axes: m g R^T e_z
        expected = 1.001 * 9.81 * np.array([-np.sin(pitch), np.sin(roll) * np.cos(pitch),
                                            np.cos(roll) * np.cos(pitch)])
        np.testing.assert_allclose(force, expected, atol=0.03)
    up, front, left = (readings[k][1] for k in ('up', 'front', 'left'))
    assert front[1] - up[1] > 0.005          # arm out front: nose down, pitch grows (REP 103)
    assert left[0] - up[0] < -0.005          # arm to the left: left side down, roll falls


def test_bad_commands_are_skipped_and_the_sim_keeps_running(live):
    proc, probe = live
    pub = probe.node.create_publisher(JointTrajectory, '/rover1/arm/joint_command', 10)
    wait_for(lambda: pub.get_subscription_count() > 0, 10.0, what='sim arm subscriber')
    bad = [JointTrajectory(joint_names=['arm_joint_2'],
                           points=[JointTrajectoryPoint(positions=[float('nan')])]),
           JointTrajectory(joint_names=['arm_joint_2'],
                           points=[JointTrajectoryPoint(positions=[0.1, 0.2])]),
           JointTrajectory(joint_names=['elbow_of_nobody'],
                           points=[JointTrajectoryPoint(positions=[0.1])])]
    bad.append(JointTrajectory(joint_names=['arm_joint_2'],
                               points=[JointTrajectoryPoint(positions=[0.1])]))
    bad[-1].header.frame_id = 'rover2/base_link'
    for msg in bad:
        pub.publish(msg)
    n = probe.count('/rover1/imu')
    probe.spin_until(lambda: probe.count('/rover1/imu') > n + 200, 20.0, 'imu after bad input')
    assert proc.alive()
    wait_for(lambda: 'skipped input' in proc.log_text(), 10.0, what='a bad-input warning')


def test_reset_service_changes_the_world(live):
    _, probe = live
    before = len(probe.msgs['/sim/world'][-1].markers)
    client = probe.node.create_client(SimScenario, '/sim/reset')
    assert client.wait_for_service(timeout_sec=10.0)
    req = SimScenario.Request(seed=11, occlusion_density=0.3, slot_gap_m=0.0, truth_yaml='')
    future = client.call_async(req)
    probe.spin_until(future.done, 30.0, 'the reset response')
    assert future.result().success, future.result().message
    probe.spin_until(lambda: len(probe.msgs['/sim/world'][-1].markers) != before, 10.0,
                     'the new world markers')
    bad = client.call_async(SimScenario.Request(seed=-1, occlusion_density=0.9,
                                                slot_gap_m=0.0, truth_yaml=''))
    probe.spin_until(bad.done, 10.0, 'the rejected reset')
    assert not bad.result().success and 'occlusion_density' in bad.result().message
    for places, why in ((dict(place_rovers=['rover9'], place_x=[0.0], place_y=[0.0],
                              place_yaw=[0.0]), 'rover9'),
                        (dict(place_rovers=['rover2'], place_x=[0.0], place_y=[], place_yaw=[]),
                         'one length'),
                        (dict(place_rovers=['rover2'], place_x=[float('nan')], place_y=[0.0],
                              place_yaw=[0.0]), 'non-finite')):
        bad = client.call_async(SimScenario.Request(**places))
        probe.spin_until(bad.done, 10.0, 'the rejected placement')
        assert not bad.result().success and why in bad.result().message


def test_reset_places_a_rover_and_the_card_is_published(live):
    _, probe = live
    probe.listen(PoseStamped, '/sim/rover2/card_pose', SENSOR_QOS)
    probe.listen(ContactState, '/sim/rover2/contact', SENSOR_QOS)
    probe.listen(PoseStamped, '/sim/rover2/base_pose', SENSOR_QOS)
    client = probe.node.create_client(SimScenario, '/sim/reset')
    assert client.wait_for_service(timeout_sec=10.0)
    req = SimScenario.Request(occlusion_density=0.0, slot_gap_m=0.127,
                              place_rovers=['rover2'], place_x=[1.5],
                              place_y=[-1.0], place_yaw=[0.5])
    future = client.call_async(req)
    probe.spin_until(future.done, 30.0, 'the reset response')
    assert future.result().success, future.result().message
    poses = probe.msgs['/sim/rover2/base_pose']
    poses.clear()
    probe.spin_until(lambda: len(poses) > 0, 10.0, 'the placed rover')
    p = poses[-1].pose.position
    assert math.hypot(p.x - 1.5, p.y + 1.0) < 0.05
    probe.spin_until(lambda: probe.count('/sim/rover2/card_pose') > 0
                     and probe.count('/sim/rover2/contact') > 0, 10.0, 'card pose and contact')
    c = probe.msgs['/sim/rover2/card_pose'][-1].pose.position
    assert math.hypot(c.x - 1.5, c.y + 1.0) < 0.8           # the card is in the rover's hand
    contact = probe.msgs['/sim/rover2/contact'][-1]
    assert contact.points == 0 and not contact.seated and contact.max_penetration_m == 0.0


def _first_imus(tmp_path: Path, seeds: list[int], n: int = 100, name: str = 'det') -> list:
    """IMU readings keyed by stamp for the first n steps after each /sim/reset to one of
    `seeds`, in turn, in one simulator process: a late subscriber misses the start of a run, so
    every run is restarted at t = 0 once connected."""
    # its own namespace: the module's live simulator publishes /rover1/imu meanwhile
    with sim_process(tmp_path, '-r', '__ns:=/det', '-p', 'seed:=1', '-p', 'stereo_rate_hz:=0.0',
                     '-p', 'real_time_factor:=0.5', '-p', 'frame_prefix:=det/', name=name):
        probe = Probe()
        probe.listen(Imu, '/det/rover1/imu', QoSProfile(depth=1000,
                                                        reliability=ReliabilityPolicy.BEST_EFFORT))
        try:
            probe.spin_until(lambda: probe.count('/det/rover1/imu') >= 300, 60.0, 'imu messages')
            client = probe.node.create_client(SimScenario, '/det/sim/reset')
            assert client.wait_for_service(timeout_sec=10.0)
            out = []
            for seed in seeds:
                future = client.call_async(SimScenario.Request(
                    seed=seed, occlusion_density=-1.0, slot_gap_m=0.0, truth_yaml=''))
                probe.spin_until(future.done, 30.0, 'the reset')
                assert future.result().success
                msgs = probe.msgs['/det/rover1/imu']
                msgs.clear()
                probe.spin_until(lambda msgs=msgs: sum(t_of(m.header) < 1.0 for m in msgs) >= n,
                                 60.0, 'imu messages after the reset')
                out.append({round(t_of(m.header), 4): (m.linear_acceleration.x,
                                                       m.angular_velocity.y)
                            for m in msgs if t_of(m.header) < 1.0})
            return out
        finally:
            probe.close()


def test_same_seed_gives_identical_readings(tmp_path):
    # two processes, and within one a reset to seed 5 after one to seed 6: a run depends on
    # its seed, not on the process or on what ran before it
    a, c, a_again = _first_imus(tmp_path, [5, 6, 5], name='a')
    (b,) = _first_imus(tmp_path, [5], name='b')
    for other in (b, a_again):
        common = sorted(set(a) & set(other))
        assert len(common) >= 50
        assert all(a[t] == other[t] for t in common)
    different = sorted(set(a) & set(c))
    assert any(a[t] != c[t] for t in different)


def test_namespace_and_params_file(tmp_path):
    params = tmp_path / 'p.yaml'
    params.write_text('/**:\n  ros__parameters:\n    rovers: 1\n    seed: 9\n'
                      '    stereo_rate_hz: 0.0\n')
    with sim_process(tmp_path, '-r', '__ns:=/team_a', '--params-file', str(params),
                     '-p', 'occlusion_density:=0.2', '-p', 'frame_prefix:=team_a/') as proc:
        probe = Probe()
        try:
            probe.listen(Imu, '/team_a/rover1/imu')
            probe.listen(MarkerArray, '/team_a/sim/world', LATCHED_QOS)
            probe.spin_until(lambda: probe.count('/team_a/rover1/imu') >= 5
                             and probe.count('/team_a/sim/world') >= 1, 30.0,
                             'namespaced topics')
            names = [n for n, _ in probe.node.get_topic_names_and_types()]
            assert '/team_a/rover2/imu' not in names       # rovers: 1 from the params file
            wait_for(lambda: 'seed 9' in proc.log_text(), 10.0, what='the params-file seed')
        finally:
            probe.close()


def _run_to_exit(tmp_path: Path, *ros_args: str) -> tuple[int, str]:
    exe = executable_path('rover_sim', 'sim')
    out = subprocess.run([str(exe), '--ros-args', *ros_args], check=False, capture_output=True,
                         text=True, timeout=60)
    return out.returncode, out.stdout + out.stderr


def test_malformed_world_yaml_names_the_field_and_exits_non_zero(tmp_path):
    bad = tmp_path / 'world.yaml'
    bad.write_text('occlusion_density: 0.1\nimage_widht: 640\n')
    code, text = _run_to_exit(tmp_path, '-p', f'world_yaml:={bad}')
    assert code != 0 and 'image_widht' in text


def test_out_of_range_parameter_is_rejected_with_a_reason(tmp_path):
    code, text = _run_to_exit(tmp_path, '-p', 'occlusion_density:=0.9')
    assert code != 0 and 'occlusion_density' in text


def test_truth_is_in_the_tree_only_when_asked_and_apart(tmp_path):
    """truth_tf: the true base and camera under <prefix>truth/, children of the map, beside
    the estimated tree; the odometry's transform the same as the odom topic."""
    tf2_msgs = pytest.importorskip('tf2_msgs.msg', reason='tf2_msgs comes with make ros2-tools')
    from coop_common.tf_tree import TF_QOS
    with sim_process(tmp_path, '-r', '__ns:=/tt', '-p', 'rovers:=1', '-p', 'stereo_rate_hz:=0.0',
                     '-p', 'frame_prefix:=tt/', '-p', 'truth_tf:=true'):
        probe = Probe('truth_tf_probe')
        try:
            probe.listen(tf2_msgs.TFMessage, '/tf', TF_QOS)
            probe.listen(Odometry, '/tt/rover1/odom')
            probe.listen(PoseStamped, '/tt/sim/rover1/base_pose')

            def tree() -> dict:
                return {t.child_frame_id: t for m in probe.msgs['/tf'] for t in m.transforms}
            want = {'tt/truth/rover1/base_link', 'tt/truth/rover1/left_camera_optical_frame',
                    'tt/rover1/base_link', 'tt/rover1/mast_tilt_link'}
            probe.spin_until(lambda: want <= set(tree()) and probe.msgs['/tt/rover1/odom']
                             and probe.msgs['/tt/sim/rover1/base_pose'], 30.0, 'the tree')
            t = tree()
            assert t['tt/truth/rover1/base_link'].header.frame_id == 'tt/map'
            assert t['tt/rover1/base_link'].header.frame_id == 'tt/rover1/odom'
            true_z = probe.msgs['/tt/sim/rover1/base_pose'][-1].pose.position.z
            assert t['tt/truth/rover1/base_link'].transform.translation.z == pytest.approx(
                true_z, abs=0.02)
            od = probe.msgs['/tt/rover1/odom'][-1]
            assert (od.header.frame_id, od.child_frame_id) == ('tt/rover1/odom',
                                                              'tt/rover1/base_link')
            assert od.pose.pose.position.z == t['tt/rover1/base_link'].transform.translation.z
        finally:
            probe.close()
