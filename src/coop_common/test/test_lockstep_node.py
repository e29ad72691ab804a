"""coop_common.lockstep_node.Lockstep against a stand-in simulator in one process: round 0
waits for both ends of every lockstep topic, a round's messages reach the callbacks in stamp
order whatever order they came in, the ack counts what was published, messages of a later round
wait for it, and a request held between rounds holds the next round until it is answered."""
from __future__ import annotations

import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.task import Future  # noqa: E402
from sensor_msgs.msg import JointState  # noqa: E402

from coop_common.lockstep_node import ACK_TOPIC, ROUND_QOS, TICK_TOPIC, Lockstep  # noqa: E402
from coop_common.node_util import stamp  # noqa: E402
from coop_common.qos import COMMAND_QOS, SENSOR_QOS  # noqa: E402
from coop_common.testing import isolate_ros_environment  # noqa: E402
from coop_msgs.msg import LockstepAck, LockstepTick  # noqa: E402


@pytest.fixture
def graph():
    isolate_ros_environment()
    rclpy.init()
    sim, part = Node('stand_in_sim'), Node('participant')
    ex = SingleThreadedExecutor()
    ex.add_node(sim)
    ex.add_node(part)
    yield sim, part, ex
    ex.shutdown()
    sim.destroy_node()
    part.destroy_node()
    rclpy.shutdown()


def spin_until(ex, cond, timeout_s=10.0):
    import time
    end = time.monotonic() + timeout_s
    while not cond():
        assert time.monotonic() < end, 'timed out'
        ex.spin_once(timeout_sec=0.02)


def test_rounds_acks_order_and_holds(graph):
    sim, part, ex = graph
    ls = Lockstep(part, True)
    seen, cmds, acks = [], [], []
    cmd_pub = ls.publisher(JointState, 'cmd', COMMAND_QOS)

    def on_state(m):
        seen.append((ls.round, m.header.stamp.nanosec))
        cmd_pub.publish(JointState())
    ls.subscription(JointState, 'state', on_state, SENSOR_QOS)
    rounds, held = [], {}

    def on_round():
        rounds.append(ls.round)
        if ls.round == 3:           # held while handing out round 3, as the rig holds the sim
            held[3] = ls.hold(Future())
    ls.on_round(on_round)
    tick_pub = sim.create_publisher(LockstepTick, TICK_TOPIC, ROUND_QOS)
    sim.create_subscription(LockstepAck, ACK_TOPIC, acks.append, ROUND_QOS)
    sim.create_subscription(JointState, 'cmd', cmds.append, ROUND_QOS)

    def tick(r, counts):
        tick_pub.publish(LockstepTick(round=r, stamp=stamp(0.01 * r), topics=list(counts),
                                      counts=list(counts.values())))

    # round 0 is answered once 'state' has a publisher: none yet
    spin_until(ex, lambda: tick_pub.get_subscription_count() > 0)
    tick(0, {})
    for _ in range(20):
        ex.spin_once(timeout_sec=0.02)
    assert acks == []
    state_pub = sim.create_publisher(JointState, 'state', ROUND_QOS)
    spin_until(ex, lambda: state_pub.get_subscription_count() > 0)
    tick(0, {})                               # the simulator repeats round 0
    spin_until(ex, lambda: len(acks) == 1)
    assert (acks[0].node, acks[0].round, list(acks[0].counts)) == ('/participant', 0, [])
    tick(0, {})                               # and again: acked again, not handed out again
    spin_until(ex, lambda: len(acks) == 2)
    assert acks[1].round == 0 and rounds == [0]
    del acks[1]

    # round 1: two states sent late first, one of round 2 already among them
    for ns in (10_000_000, 5_000_000, 15_000_000):
        msg = JointState()
        msg.header.stamp = stamp(ns * 1e-9)
        state_pub.publish(msg)
    tick(1, {'/state': 2, '/elsewhere': 3})
    spin_until(ex, lambda: len(acks) == 2)
    assert seen == [(1, 5_000_000), (1, 10_000_000)], 'handed out by stamp'
    assert (acks[1].round, list(acks[1].topics), list(acks[1].counts)) == (1, ['/cmd'], [2])
    spin_until(ex, lambda: len(cmds) == 2)

    # a request held between rounds holds round 2 until it is answered
    request = ls.hold(Future())
    tick(2, {'/state': 1})
    for _ in range(20):
        ex.spin_once(timeout_sec=0.02)
    assert len(acks) == 2 and seen[-1][0] == 1
    request.set_result(None)
    spin_until(ex, lambda: len(acks) == 3)
    assert seen[-1] == (2, 15_000_000) and acks[2].round == 2

    # a round held while the simulator repeats its tick is handed out once
    tick(3, {})
    spin_until(ex, lambda: 3 in held)
    tick(3, {})
    for _ in range(20):
        ex.spin_once(timeout_sec=0.02)
    assert len(acks) == 3
    held[3].set_result(None)
    spin_until(ex, lambda: len(acks) == 4)
    for _ in range(20):
        ex.spin_once(timeout_sec=0.02)
    assert rounds == [0, 1, 2, 3] and len(acks) == 4


def test_a_pacer_holds_the_sim_between_the_runs_it_allows(graph):
    from coop_common.lockstep_node import Pacer
    sim, part, ex = graph
    pacer = Pacer(Lockstep(part, True))
    acks = []
    tick_pub = sim.create_publisher(LockstepTick, TICK_TOPIC, ROUND_QOS)
    sim.create_subscription(LockstepAck, ACK_TOPIC, acks.append, ROUND_QOS)
    spin_until(ex, lambda: tick_pub.get_subscription_count() > 0)

    def step(r):          # the stand-in simulator: tick round r (after round r-1 was acked)
        tick_pub.publish(LockstepTick(round=r, stamp=stamp(0.01 * r)))

    step(0)
    spin_until(ex, lambda: pacer.paused)          # held at round 0: not answered
    for _ in range(10):
        ex.spin_once(timeout_sec=0.02)
    assert acks == []
    pacer.run(2)                                  # round 0 answered, then rounds 1 and 2
    for r in (1, 2, 3):
        spin_until(ex, lambda r=r: len(acks) == r)
        step(r)
    spin_until(ex, lambda: pacer.paused)
    for _ in range(10):
        ex.spin_once(timeout_sec=0.02)
    assert [a.round for a in acks] == [0, 1, 2]   # round 3 held
    pacer.run()                                   # until told
    for r in (4, 5):
        spin_until(ex, lambda r=r: len(acks) == r)
        step(r)
    pacer.stop()                                  # before round 5 is handed out: held there
    spin_until(ex, lambda: pacer.paused)
    for _ in range(10):
        ex.spin_once(timeout_sec=0.02)
    assert [a.round for a in acks] == [0, 1, 2, 3, 4]


def test_remap_args_point_a_namespaced_node_at_the_simulators_rounds():
    from coop_common.lockstep_node import remap_args
    assert remap_args() == ['-r', 'sim/lockstep/tick:=/sim/lockstep/tick',
                            '-r', 'sim/lockstep/ack:=/sim/lockstep/ack']
    assert remap_args('/team_a/') == ['-r', 'sim/lockstep/tick:=/team_a/sim/lockstep/tick',
                                      '-r', 'sim/lockstep/ack:=/team_a/sim/lockstep/ack']
