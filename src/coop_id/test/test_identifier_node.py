"""Node test in-process: private Context + domain, synthetic sensor streams from modelsim."""
import math
import threading

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import WrenchStamped
from rclpy.action import ActionClient
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Imu
from trajectory_msgs.msg import JointTrajectory

from coop_common.dynparams import load_truth
from coop_common.node_util import in_executor
from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_common.testing import pick_domain_id, wait_for
from coop_id.excitation import Excitation, constant_excitation
from coop_id.identifier_node import IdentifierNode
from coop_id.modelsim import ThesisRover, stack_frames
from coop_msgs.action import Identify
from coop_msgs.msg import DynamicParameters, Inclinometer

MODE = 2  # the arm rotating about z


def _data(seconds: float):
    rover = ThesisRover(load_truth())
    exc = constant_excitation()
    frames = [rover.rest_frame()]
    for _ in range(int(seconds / 0.005)):
        frames.append(rover.step(exc(rover.t + 0.005)))
    return stack_frames(frames)


def _stamp(msg, t):
    msg.header.stamp.sec = int(t)
    msg.header.stamp.nanosec = round((t - int(t)) * 1e9)


def _send(peer, client, goal):
    """The goal sent from the executor's thread (the fixture spins it in another): rclpy's
    action client can lose the answer to a request made beside its executor (in_executor)."""
    return in_executor(peer.executor, lambda: client.send_goal_async(goal))


def _result(peer, handle):
    return in_executor(peer.executor, handle.get_result_async)


@pytest.fixture
def graph():
    ctx = Context()
    rclpy.init(context=ctx, domain_id=pick_domain_id() + 100)
    node = IdentifierNode(context=ctx, namespace='rover1', parameter_overrides=[
        Parameter('window_s', value=0.4), Parameter('mode_period_s', value=1.0)])
    peer = Node('peer', context=ctx, namespace='rover1')
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    ex.add_node(peer)
    th = threading.Thread(target=ex.spin, daemon=True)
    th.start()
    yield node, peer
    ex.shutdown()
    node.destroy_node()
    peer.destroy_node()
    rclpy.shutdown(context=ctx)
    th.join(timeout=5)


def test_identify_action_over_dds(graph):
    node, peer = graph
    pub_imu = peer.create_publisher(Imu, 'imu', SENSOR_QOS)
    pub_inc = peer.create_publisher(Inclinometer, 'inclinometer', SENSOR_QOS)
    pub_wr = peer.create_publisher(WrenchStamped, 'arm/wrench', SENSOR_QOS)
    estimates, commands = [], []
    peer.create_subscription(DynamicParameters, 'dynamic_parameters', estimates.append,
                             LATCHED_QOS)
    peer.create_subscription(JointTrajectory, 'arm/joint_command', commands.append, 10)
    client = ActionClient(peer, Identify, 'identifier/identify')
    assert client.wait_for_server(timeout_sec=10)
    wait_for(lambda: pub_imu.get_subscription_count() and pub_wr.get_subscription_count()
             and pub_inc.get_subscription_count(), 10, what='node subscriptions')
    # a bad goal is rejected
    bad = _send(peer, client, Identify.Goal(strategy='magic', duration_s=1.0))
    wait_for(bad.done, 10, what='bad goal answer')
    assert not bad.result().accepted
    fut = _send(peer, client, Identify.Goal(strategy='information', duration_s=2.0))
    wait_for(fut.done, 10, what='goal accepted')
    handle = fut.result()
    assert handle.accepted
    # one identification at a time: a second goal, sent at once, is turned down
    second = _send(peer, client, Identify.Goal(strategy='constant', duration_s=1.0))
    wait_for(second.done, 10, what='second goal answer')
    assert not second.result().accepted
    res_fut = _result(peer, handle)
    d = _data(2.6)
    t0 = 100.0
    for k in range(d['t'].size):
        if res_fut.done():
            break
        t = t0 + d['t'][k]
        imu = Imu()
        _stamp(imu, t)
        sf, g = d['specific_force'][k, MODE], d['gyro'][k, MODE]
        imu.linear_acceleration.x, imu.linear_acceleration.y, imu.linear_acceleration.z = sf
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = g
        if k == 50:   # one non-finite reading: skipped and counted
            imu.linear_acceleration.x = math.nan
        inc = Inclinometer(roll=float(d['incl'][k, MODE, 0]), pitch=float(d['incl'][k, MODE, 1]))
        _stamp(inc, t)
        wr = WrenchStamped()
        _stamp(wr, t if k != 60 else t - 1.0)   # one stale stamp: skipped and counted
        f, n = d['force'][k, MODE], d['torque'][k, MODE]
        wr.wrench.force.x, wr.wrench.force.y, wr.wrench.force.z = f
        wr.wrench.torque.x, wr.wrench.torque.y, wr.wrench.torque.z = n
        pub_wr.publish(wr)
        pub_inc.publish(inc)
        pub_imu.publish(imu)
        # best-effort sensor QoS: pace the stream by the node's consumption, not by sleeping
        t_ns = round(t * 1e9) - 1000
        wait_for(lambda t_ns=t_ns, k=k: node.pairer.last_stamp['imu'] >= t_ns or k == 50, 5,
                 poll_s=0.0005, what=f'sample {k} consumed')
    wait_for(res_fut.done, 30, what='action result')
    result = res_fut.result().result
    assert result.success, result.message
    est = result.estimate
    assert len(est.values) == 22 and est.physically_consistent
    assert est.header.frame_id == 'rover1/base_link'      # the rover's frame, as rover_sim's
    assert est.samples >= 350 and est.rejected_samples >= 2
    assert node.bad.counts['non-finite'] >= 1 and node.bad.counts['out-of-order stamp'] >= 1
    assert all(np.isfinite(est.values)) and all(s >= 0 for s in est.std_devs)
    # one mode only (about z) cannot see everything: some directions are flagged, not filled in
    assert not all(est.observable)
    wait_for(lambda: len(estimates) > 0 and len(commands) > 0, 10, what='outputs')
    assert commands[0].joint_names == ['arm_joint_1', 'arm_joint_2']
    assert estimates[-1].names[0] == 'mass'
    # the goal's end stops the arm: the last command, on the path of the one before it, blends
    # into standing still where the arm started (no joint_states here: at 0, 0)
    wait_for(lambda: not any(commands[-1].points[-1].velocities), 10, what='stop command')
    stop, prev = commands[-1], commands[-2]
    np.testing.assert_allclose(stop.points[-1].positions, [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(stop.points[-1].positions, commands[0].points[0].positions)

    def at(traj, k):
        t0 = traj.header.stamp.sec + traj.header.stamp.nanosec * 1e-9
        pt = traj.points[k]
        return t0 + pt.time_from_start.sec + pt.time_from_start.nanosec * 1e-9, pt

    t_stop, first = at(stop, 0)
    k = min(range(len(prev.points)), key=lambda j: abs(at(prev, j)[0] - t_stop))
    assert abs(at(prev, k)[0] - t_stop) < 1e-6
    # (the blend's old side is tabulated at 1 ms)
    np.testing.assert_allclose(first.positions, at(prev, k)[1].positions, atol=1e-6)
    np.testing.assert_allclose(first.velocities, at(prev, k)[1].velocities, atol=1e-4)


def test_bad_parameter_rejected(graph):
    node, _ = graph
    res = node.set_parameters([Parameter('mode_period_s', value=-1.0)])
    assert not res[0].successful
    res = node.set_parameters([Parameter('strategy', value='magic')])
    assert not res[0].successful
    assert res[0].reason == ("strategy must be one of ['constant', 'information', 'condition', "
                             "'d_optimal', 'a_optimal'], got 'magic'")


def test_a_goal_ends_when_the_sensors_fall_silent_or_time_jumps_back(graph):
    """No paired sample for silence_abort_s (wall clock): the goal is aborted with the reason,
    not left running for ever, and no sample is counted as rejected for it. Sensor time
    jumping back (a sim reset) during a goal aborts it too; pairing starts over."""
    node, peer = graph
    assert node.set_parameters([Parameter('silence_abort_s', value=1.0)])[0].successful
    client = ActionClient(peer, Identify, 'identifier/identify')
    assert client.wait_for_server(timeout_sec=10)
    fut = _send(peer, client, Identify.Goal(strategy='constant', duration_s=60.0))
    wait_for(fut.done, 10, what='goal answer')
    res = _result(peer, fut.result())
    wait_for(res.done, 10, what='the aborted result')
    r = res.result().result
    assert not r.success and 'no paired sensor samples' in r.message
    assert r.estimate.rejected_samples == 0
    # sensor time jumps back 100 s during the next goal
    assert node.set_parameters([Parameter('silence_abort_s', value=0.0)])[0].successful
    fut = _send(peer, client, Identify.Goal(strategy='constant', duration_s=60.0))
    wait_for(fut.done, 10, what='goal answer')
    res = _result(peer, fut.result())
    pub_imu = peer.create_publisher(Imu, 'imu', SENSOR_QOS)
    wait_for(pub_imu.get_subscription_count, 10, what='node subscription')
    for t in (100.0, 100.005, 0.0):
        m = Imu()
        _stamp(m, t)
        pub_imu.publish(m)
        wait_for(lambda t=t: node.pairer.last_stamp['imu'] == round(t * 1e9), 5,
                 what=f'imu {t} taken')
    wait_for(res.done, 10, what='the aborted result')
    r = res.result().result
    assert not r.success and 'jumped back' in r.message


def test_arm_commands_make_up_for_samples_that_lag_the_clock(graph):
    """A node behind its sample stream (its samples queued on a loaded machine) commands from
    a past instant: the trajectory still reaches 3 windows past the clock's present, and a
    new excitation departs from the old one only lead + lag after the last sample, where the
    arm can have it (not a hold at the old command's end, then a jump)."""
    node, _ = graph
    sent = []
    node.pub_cmd.publish = sent.append
    lag, window, lead = 1.0, node.p['window_s'], node.p['command_lead_s']
    now = node.get_clock().now().nanoseconds * 1e-9
    node._t0 = node._exc_t0 = node._t_now = now - lag
    node._current_exc = constant_excitation()
    node._command_arm()

    def span(traj):
        t0 = traj.header.stamp.sec + traj.header.stamp.nanosec * 1e-9
        return [t0 + p.time_from_start.sec + p.time_from_start.nanosec * 1e-9
                for p in traj.points]

    assert span(sent[-1])[-1] >= now + 3 * window - 0.02
    old = sent[-1]
    node._t_now += 0.4                           # the next window, still behind the clock
    node._exc_t0 = node._t_now                   # with a new excitation
    node._current_exc = Excitation(0.5, np.pi / 2, np.pi / 4)
    now = node.get_clock().now().nanoseconds * 1e-9
    node._command_arm()
    new = sent[-1]
    t_old, t_new = span(old), span(new)
    same = [k for k, t in enumerate(t_new) if t < now + lead - 0.01]
    assert len(same) > 100 * (now + lead - node._t_now) - 5
    for k in same:
        j = min(range(len(t_old)), key=lambda i: abs(t_old[i] - t_new[k]))
        np.testing.assert_allclose(new.points[k].positions, old.points[j].positions, atol=1e-5)
    assert not np.allclose(new.points[-1].positions, old.points[-1].positions)
