"""Whole-graph tests of `rover_hw bridge` against `rover_hw emulator` over a pseudo-terminal:
lifecycle transitions, the topics rover_sim publishes for one rover (names, types, frames,
rates), commands, the watchdog, the e-stop, fault injection and unplug / re-plug."""
from __future__ import annotations

import itertools
import math
import re
import time
from pathlib import Path

import numpy as np
import pytest
from builtin_interfaces.msg import Duration
from geometry_msgs.msg import PoseWithCovarianceStamped, Twist, WrenchStamped
from lifecycle_msgs.msg import Transition
from lifecycle_msgs.srv import ChangeState, GetState
from nav_msgs.msg import Odometry
from sensor_msgs.msg import Imu, JointState
from std_srvs.srv import SetBool
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.qos import COMMAND_QOS, SENSOR_QOS
from coop_common.testing import NodeProcess, Probe, wait_for
from coop_msgs.msg import Inclinometer
from coop_msgs.srv import CalibrateInclinometer
from rover_hw.figures import imu_line, rates_table, replug_line, unplug_line, watchdog_line

pytestmark = pytest.mark.graph

NS = '/rover1'
TOPICS = {
    f'{NS}/imu': (Imu, 'rover1/base_link'),
    f'{NS}/inclinometer': (Inclinometer, 'rover1/base_link'),
    f'{NS}/arm/wrench': (WrenchStamped, 'rover1/ft_sensor_link'),
    f'{NS}/joint_states': (JointState, ''),
    f'{NS}/odom': (Odometry, 'rover1/odom'),
    f'{NS}/stereo/pose': (PoseWithCovarianceStamped, 'map'),
}


def t_of(header) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


class Rig:
    """emulator + bridge processes, and a probe that drives the bridge's lifecycle."""

    def __init__(self, tmp_path: Path, emu_args=(), bridge_args=()) -> None:
        self.link = tmp_path / 'rover1_hw'
        self.emu = NodeProcess('rover_hw', 'emulator', args=['--link', str(self.link),
                                                            *emu_args],
                               log_path=tmp_path / 'emulator.log')
        self.bridge = NodeProcess('rover_hw', 'bridge',
                                  ['-r', f'__ns:={NS}', '-p', f'port:={self.link}',
                                   *bridge_args], log_path=tmp_path / 'bridge.log')
        self.probe = Probe('hw_probe')

    def __enter__(self) -> Rig:
        try:
            self.emu.__enter__()
            wait_for(self.link.exists, 30.0, what='the emulator pty')
            self.bridge.__enter__()
            for topic, (typ, _) in TOPICS.items():
                self.probe.listen(typ, topic)
            n = self.probe.node
            self.change = n.create_client(ChangeState, f'{NS}/bridge/change_state')
            self.get = n.create_client(GetState, f'{NS}/bridge/get_state')
            self.estop = n.create_client(SetBool, f'{NS}/estop')
            self.calib = n.create_client(CalibrateInclinometer, f'{NS}/inclinometer/calibrate')
            self.cmd = n.create_publisher(Twist, f'{NS}/cmd_vel', COMMAND_QOS)
            self.arm = n.create_publisher(JointTrajectory, f'{NS}/arm/joint_command',
                                          COMMAND_QOS)
            # (estop and calibrate come with configure)
            self.probe.spin_until(lambda: all(c.service_is_ready() for c in (
                self.change, self.get)), 30.0, "the bridge's lifecycle services")
        except BaseException:
            self.__exit__()
            raise
        return self

    def call(self, client, request, timeout_s: float = 10.0):
        fut = client.call_async(request)
        self.probe.spin_until(fut.done, timeout_s, f'{client.srv_name}')
        return fut.result()

    def transition(self, tid: int) -> bool:
        return self.call(self.change, ChangeState.Request(
            transition=Transition(id=tid))).success

    def state(self) -> str:
        return self.call(self.get, GetState.Request()).current_state.label

    def spin(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.probe.executor.spin_once(timeout_sec=0.01)

    def msgs(self, topic: str) -> list:
        return self.probe.msgs[f'{NS}/{topic}']

    def clear(self) -> None:
        for v in self.probe.msgs.values():
            v.clear()

    def __exit__(self, *exc) -> None:
        self.probe.close()
        self.bridge.__exit__()
        self.emu.__exit__()


def forward(v: float = 0.2) -> Twist:
    msg = Twist()
    msg.linear.x = v
    return msg


def wheel_speed(js: JointState) -> float:
    return js.velocity[js.name.index('wheel_fl')]


def test_lifecycle_topics_commands_watchdog_estop(tmp_path, figures):
    with Rig(tmp_path, bridge_args=['-p', 'command_timeout_s:=0.1']) as rig:
        assert rig.state() == 'unconfigured'
        assert rig.transition(Transition.TRANSITION_CONFIGURE)
        rig.spin(0.5)
        assert rig.state() == 'inactive' and not rig.msgs('imu')      # nothing until active
        assert rig.transition(Transition.TRANSITION_ACTIVATE)
        rig.probe.spin_until(lambda: len(rig.msgs('odom')) > 5, 10.0, 'odometry')
        rig.clear()
        t0 = time.monotonic()
        rig.spin(2.0)
        wall = time.monotonic() - t0
        # names, types, frames: the sim's contract for one rover
        for topic, (_, frame) in TOPICS.items():
            got = rig.probe.msgs[topic]
            assert got, f'nothing on {topic}'
            head = got[-1].header
            assert head.frame_id == frame, topic
        imu = rig.msgs('imu')
        stamps = [t_of(m.header) for m in imu]
        dts = sorted(b - a for a, b in itertools.pairwise(stamps))
        rate = 1.0 / dts[len(dts) // 2]
        assert abs(rate - 200.0) < 10.0, rate                   # device rate, within 5 %
        # the device's frames reach the graph (the emulator may run slower than real time on
        # a loaded machine: count against the device's own clock, not the wall's; the probe,
        # one Python subscriber to 6 best-effort streams, drops some under load: 63.8 % on a
        # machine at load 10; the bridge's own count is the fuzz test's and the bench's)
        delivered = len(imu) / ((stamps[-1] - stamps[0]) * 200.0)
        print('\n' + imu_line(figures.add('hw_imu', {
            'rate_hz': rate, 'delivered': delivered, 'frames': len(imu), 'wall_s': wall})))
        assert delivered >= 0.5
        assert abs(imu[-1].linear_acceleration.z - 9.81) < 0.5
        js = rig.msgs('joint_states')[-1]
        assert js.name[:6] == ['arm_joint_1', 'arm_joint_2', 'arm_joint_3', 'arm_joint_4',
                               'mast_pan', 'mast_tilt'] and js.name[-1] == 'articulation'
        assert all(math.isnan(js.position[k]) for k in range(6, 10))
        inc = rig.msgs('inclinometer')[-1]
        assert abs(inc.roll) < 0.02 and 2.3 < inc.raw_roll_volts < 2.5
        # drive: the tachometers follow, then the watchdog stops the wheels
        for _ in range(20):
            rig.cmd.publish(forward())
            rig.spin(0.05)
        assert wheel_speed(rig.msgs('joint_states')[-1]) > 2.0
        t_last = time.monotonic()
        rig.clear()
        rig.spin(0.4)
        moving = [t_of(m.header) for m in rig.msgs('joint_states') if wheel_speed(m) > 1.5]
        first = t_of(rig.msgs('joint_states')[0].header)
        # command_timeout_s 0.1 s + one command period + one device cycle, in device time
        stopped_after = (moving[-1] - first) if moving else 0.0
        print('\n' + watchdog_line(figures.add('hw_watchdog', {
            'stopped_after_s': stopped_after, 'observed_s': time.monotonic() - t_last})))
        assert stopped_after <= 0.1 + 0.05
        # e-stop: latched, commands refused, cleared
        assert rig.call(rig.estop, SetBool.Request(data=True)).success
        for _ in range(10):
            rig.cmd.publish(forward())
            rig.spin(0.05)
        assert abs(wheel_speed(rig.msgs('joint_states')[-1])) < 1.0
        res = rig.call(rig.estop, SetBool.Request(data=False))
        assert res.success, res.message
        for _ in range(10):
            rig.cmd.publish(forward())
            rig.spin(0.05)
        assert wheel_speed(rig.msgs('joint_states')[-1]) > 2.0
        # the arm follows a trajectory through the bridge; a bad one is refused with a reason
        traj = JointTrajectory(joint_names=['arm_joint_1'], points=[JointTrajectoryPoint(
            positions=[0.5], time_from_start=Duration(sec=0, nanosec=500_000_000))])
        rig.arm.publish(traj)
        rig.arm.publish(JointTrajectory(joint_names=['arm_joint_9'], points=[
            JointTrajectoryPoint(positions=[0.1])]))
        rig.spin(1.5)
        q1 = [m.position[0] for m in rig.msgs('joint_states')[-20:]]
        assert abs(sum(q1) / len(q1) - 0.5) < 0.05, q1
        # calibration: two tilts on the flat ground cannot both be true -> refused or solved;
        # here only the service's answer and the volts are checked
        res = rig.call(rig.calib, CalibrateInclinometer.Request(axis='roll', angle_rad=0.0,
                                                                samples=50))
        assert res.success and res.points == 1 and 2.3 < res.volts < 2.5
        res = rig.call(rig.calib, CalibrateInclinometer.Request(axis='yaw'))
        assert not res.success
        # deactivate: publishing stops, motors stopped
        assert rig.transition(Transition.TRANSITION_DEACTIVATE)
        rig.spin(0.2)
        rig.clear()
        rig.spin(0.5)
        assert not rig.msgs('imu')
        assert rig.transition(Transition.TRANSITION_CLEANUP)
        assert rig.state() == 'unconfigured'
        assert rig.bridge.alive()
    assert 'arm command refused' in rig.bridge.log_text()


def test_fault_injection_publishes_no_corrupt_reading(tmp_path):
    emu = ['--garble', '0.04', '--bad-crc', '0.03', '--partial', '0.02', '--drop', '0.01',
           '--fault-seed', '5']
    with Rig(tmp_path, emu_args=emu) as rig:
        assert rig.transition(Transition.TRANSITION_CONFIGURE)
        assert rig.transition(Transition.TRANSITION_ACTIVATE)
        rig.spin(3.0)
        imu = rig.msgs('imu')
        assert len(imu) > 100
        # every published reading is a whole one: a frame that got through damaged would carry
        # random 32-bit counts (thousands of m/s^2); the physics itself stays within a few m/s^2
        # of g (the arm's PD transients when the device's own watchdog fires under load)
        off = [(t_of(m.header), m.linear_acceleration.z) for m in imu
               if not abs(m.linear_acceleration.z - 9.81) < 5.0
               or not abs(m.angular_velocity.x) < 1.0]
        assert not off, off[:5]
        js = rig.msgs('joint_states')
        assert all(len(m.position) == 11 and all(math.isfinite(v) for v in m.position[:6])
                   for m in js)
        assert rig.bridge.alive()
    assert 'bad frames' in rig.bridge.log_text()


@pytest.mark.known_issue
def test_unplug_replug_reconnects_within_a_second_without_a_jump(tmp_path, figures):
    """The device unplugged mid-trajectory: reconnected, stopped while down, no jump.

    known_issue: on a loaded 2-core host, beside other graph tests, the arm was found 0.05 and
    0.10 rad past the last reading before the unplug, against 0.02: either the last readings
    this process sees are stale, or the device follows set-points queued before the unplug
    until its watchdog fires. Idle it passes; the cause is not found yet.

    The device is unplugged while the arm follows a slow trajectory and the wheels turn:
    the bridge reconnects within a second, the motors were stopped while it was down, and the
    arm holds where it is measured to be (the old trajectory is not resumed) until a new one
    comes, which starts from there."""
    def mean(msgs, f=lambda m: m.position[0]) -> float:     # the encoders' noise averaged
        return sum(f(m) for m in msgs) / len(msgs)

    with Rig(tmp_path, emu_args=['--unplug-at', '8', '--unplug-for', '1.5']) as rig:
        assert rig.transition(Transition.TRANSITION_CONFIGURE)
        assert rig.transition(Transition.TRANSITION_ACTIVATE)
        arrivals: list[float] = []
        rig.probe.node.create_subscription(
            Imu, f'{NS}/imu', lambda m: arrivals.append(time.monotonic()), SENSOR_QOS)
        rig.probe.spin_until(lambda: len(rig.msgs('joint_states')) > 50, 30.0, 'joint states')
        rig.arm.publish(JointTrajectory(joint_names=['arm_joint_1'], points=[
            JointTrajectoryPoint(positions=[0.8], time_from_start=Duration(sec=12))]))
        # drive until the device goes away (the emulator says so: on a loaded machine this
        # process sees the last readings late, and a command sent after the unplug is one the
        # bridge may rightly pass on at the re-plug), then stop commanding
        t0 = time.monotonic()
        while 'emulator: unplugged' not in rig.emu.log_text():
            assert time.monotonic() - t0 < 60.0, rig.emu.log_text()
            rig.cmd.publish(forward())
            rig.spin(0.05)
        rig.probe.spin_until(lambda: time.monotonic() - arrivals[-1] > 0.5, 30.0,
                             'the readings to stop')
        before = list(rig.msgs('joint_states'))
        rig.clear()
        rig.probe.spin_until(lambda: time.monotonic() - arrivals[-1] < 0.1, 60.0,
                             'data after the re-plug')
        rig.spin(1.0)
        held = list(rig.msgs('joint_states'))
        # a new trajectory to the same goal starts from the measured state
        rig.clear()
        rig.arm.publish(JointTrajectory(joint_names=['arm_joint_1'], points=[
            JointTrajectoryPoint(positions=[0.8], time_from_start=Duration(sec=2))]))
        # until it has arrived (wall time under load is not the device's: wait for the state)
        rig.probe.spin_until(lambda: len(rig.msgs('joint_states')) > 40 and abs(
            mean(rig.msgs('joint_states')[-40:]) - 0.8) < 0.06, 30.0, 'the arm at 0.8 rad')
        resumed = list(rig.msgs('joint_states'))
        assert rig.bridge.alive()
        assert rig.state() == 'active'
    n = 40
    q_start, q_unplug = mean(before[:n]), mean(before[-n:])
    q_back, q_held = mean(held[:n]), mean(held[-n:])
    spin_back = mean(held[:20], lambda m: abs(wheel_speed(m)))
    speed = peak_speed(resumed, window_s=0.5)
    low = min(mean(resumed[k:k + 20]) for k in range(0, len(resumed) - 20, 10))
    q_end = mean(resumed[-n:])
    print('\n' + replug_line(figures.add('hw_replug', {
        'n': n, 'q_start': q_start, 'q_unplug': q_unplug, 'q_back': q_back, 'q_held': q_held,
        'held': len(held), 'spin_back': spin_back, 'low': low, 'speed': speed,
        'q_end': q_end})))
    assert q_unplug - q_start > 0.05                      # the arm was moving at the unplug
    assert abs(q_back - q_unplug) < 0.02                  # stopped while down
    assert abs(q_held - q_back) < 0.02                    # held: the old trajectory dropped
    assert spin_back < 0.5                                # the wheels stood while down
    # (0.8 - q) / 2 s is about 0.25 rad/s on average and 0.37 at the cubic's peak. Measured
    # over half a second of device time: a set-point the loaded host sends late is a short
    # step the PD takes in a few readings (0.94 rad/s over 20 readings seen beside a busy
    # test worker), while a trajectory that did not start from the measured state would step
    # the set-point and the arm would run at its limit for the whole jump, or first away
    # from the goal (one started from the old origin, 0 rad, dips to it)
    assert low > q_held - 0.03
    # the arm's PD ends 0.04 short of its goal (0.759-0.763 rad seen), held by its own weight
    assert speed < 0.6 and abs(q_end - 0.8) < 0.06
    # wall times from both logs: the emulator's [unix time] and the bridge's ROS log stamp
    log = rig.bridge.log_text()
    emu = re.search(r'\[(\d+\.\d+)\] emulator: plugged in again', rig.emu.log_text())
    lost = re.search(r'\[(\d+\.\d+)\] \[rover1\.bridge\]: device lost', log)
    back = re.search(r'\[(\d+\.\d+)\] \[rover1\.bridge\]: reconnected', log)
    assert emu and lost and back, log[-2000:]
    delay = float(back.group(1)) - float(emu.group(1))
    print(unplug_line(figures.add('hw_unplug', {'delay_s': delay})))
    assert 0.0 <= delay < 1.0


def peak_speed(msgs: list, *, window_s: float) -> float:
    """The largest speed of arm_joint_1 over `window_s` of the device's stamps: the slope of
    a straight line fitted to each window's encoder readings (their noise, a few hundredths
    of a radian, averaged out; the rate counts come in 0.24 rad/s steps), 0 when none fits."""
    tq = np.array(sorted((t_of(m.header), m.position[0]) for m in msgs)).reshape(-1, 2)
    t, q = tq[:, 0], tq[:, 1]
    ends = np.searchsorted(t, t + window_s)
    return max((abs(np.polyfit(t[i:j] - t[i], q[i:j], 1)[0])
                for i, j in enumerate(ends) if j < len(t) and j - i >= 10), default=0.0)


#: stamps per topic a rate is taken over, waited for: taken as soon as the topic list
#: settles, on a loaded machine the sim's 4 Hz pose had fewer than 5 stamps (a rate of 0)
#: and the bridge's IMU so few that stamp_rate's period, the shortest 5 % of the
#: intervals, was one short interval (the first after the link came up is shortened when the
#: stamps' clock settles on a smaller transport delay, 2.855 ms of 5 in one run: ClockMap)
RATE_STAMPS = 40


def enough(msgs: dict) -> bool:
    return all(len(msgs[t]) >= RATE_STAMPS for t in TOPICS)


def stamp_rate(msgs: list) -> float:
    """A topic's rate by its stamps (0 with fewer than 5): one over the median interval, each
    interval first divided by the whole number of periods it spans (the shortest intervals,
    the 5th percentile, stand for one period). A best-effort subscriber on a loaded machine
    can drop every other message for long stretches, which doubles the plain median; the
    division undoes it, and keeps a topic's own jitter (a stamp a tick early) in the median."""
    stamps = sorted(t_of(m.header) for m in msgs)
    dts = sorted(b - a for a, b in itertools.pairwise(stamps) if b > a)
    if len(dts) < 4:
        return 0.0
    period = dts[len(dts) // 20]
    per = sorted(dt / max(1, round(dt / period)) for dt in dts)
    return 1.0 / per[len(per) // 2]


def _rover_topics(node, timeout_s: float, executor) -> dict[str, list[str]]:
    """Topics under /rover1/ (published or subscribed) with their types, once they stop
    changing."""
    last: dict = {}
    stable_since = time.monotonic()
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.1)
        # an action's topics are another node's (a previous test's identifier, still in the
        # domain's discovery cache), never the sim's or the bridge's
        now = {t: sorted(ty) for t, ty in node.get_topic_names_and_types()
               if t.startswith(f'{NS}/') and '/_action/' not in t}
        if now != last:
            last, stable_since = now, time.monotonic()
        elif now and time.monotonic() - stable_since > 2.0:
            break
    return last


def test_topics_and_frames_match_rover_sim(tmp_path, figures):
    """The sim's topic table is the contract: the same names and types under the rover's
    namespace (stereo images excepted: a camera driver's), the same frames, and the same rates
    by the stamps within 5 %."""
    with Rig(tmp_path) as rig:
        assert rig.transition(Transition.TRANSITION_CONFIGURE)
        assert rig.transition(Transition.TRANSITION_ACTIVATE)
        rig.probe.spin_until(lambda: all(rig.probe.msgs[t] for t in TOPICS), 30.0, 'topics')
        hw = _rover_topics(rig.probe.node, 15.0, rig.probe.executor)
        hw_frames = {t: rig.probe.msgs[t][-1].header.frame_id for t in TOPICS}
        rig.probe.spin_until(lambda: enough(rig.probe.msgs), 60.0, 'the stamps of a rate')
        hw_rates = {t: stamp_rate(rig.probe.msgs[t]) for t in TOPICS}
    with NodeProcess('rover_sim', 'sim', ['-p', 'rovers:=1', '-p', 'stereo_rate_hz:=4.0'],
                     log_path=tmp_path / 'sim.log'):
        probe = Probe('sim_probe')
        try:
            for topic, (typ, _) in TOPICS.items():
                probe.listen(typ, topic)
            probe.spin_until(lambda: all(probe.msgs[t] for t in TOPICS), 60.0, 'sim topics')
            sim = _rover_topics(probe.node, 15.0, probe.executor)
            sim_frames = {t: probe.msgs[t][-1].header.frame_id for t in TOPICS}
            probe.spin_until(lambda: enough(probe.msgs), 60.0, 'the stamps of a rate')
            sim_rates = {t: stamp_rate(probe.msgs[t]) for t in TOPICS}
        finally:
            probe.close()
    images = {t for t in sim if '/image_raw' in t or '/camera_info' in t}
    assert images, sim
    # the arm's torque feed-forward is the simulator's alone: the device's serial protocol
    # carries set-points, no torques (mission.launch.py refuses arm_feedforward with hw)
    sim_only = {f'{NS}/arm/feedforward'}
    assert sim_only <= set(sim), sim
    # the lifecycle node's own ~/transition_event is the one addition
    assert {t: ty for t, ty in sim.items() if t not in images | sim_only} == {
        t: ty for t, ty in hw.items() if not t.startswith(f'{NS}/bridge/')}
    assert sim_frames == hw_frames
    print('\n' + rates_table(figures.add('hw_rates', {
        'rates': {t: (sim_rates[t], hw_rates[t]) for t in TOPICS}})))
    assert all(abs(hw_rates[t] / sim_rates[t] - 1.0) <= 0.05 for t in TOPICS), (sim_rates,
                                                                               hw_rates)
