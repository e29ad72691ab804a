"""sim_node pieces in-process: the clock stamp, the reset request's defaults, a dying
simulation thread."""
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter

from coop_msgs.srv import SimScenario
from rover_sim.sim_node import SimNode, stamp


def test_stamp_carries_into_seconds():
    """A time just below a whole second (steps * dt at 98 Hz) is not sent 1 s back."""
    t = 98 * (1.0 / 98)
    assert t < 1.0
    s = stamp(t)
    assert (s.sec, s.nanosec) == (1, 0)
    s = stamp(99 * (1.0 / 98))
    assert (s.sec, s.nanosec) == (1, 10204082)
    assert (stamp(0.0).sec, stamp(0.0).nanosec) == (0, 0)


def test_a_default_reset_request_keeps_the_scenario():
    """`ros2 service call /sim/reset coop_msgs/srv/SimScenario` sends the defaults: the same
    seed and obstacles, not seed 0 without obstacles; a field set explicitly is taken."""
    ctx = Context()
    rclpy.init(context=ctx)
    node = SimNode(context=ctx, parameter_overrides=[
        Parameter('rovers', value=1), Parameter('stereo_rate_hz', value=0.0),
        Parameter('seed', value=5), Parameter('real_time_factor', value=0.0)])
    try:
        n_obstacles = len(node.world.layout.obstacles)
        assert n_obstacles > 0
        resp = node._on_reset(SimScenario.Request(), SimScenario.Response())
        assert resp.success, resp.message
        assert node.config.seed == 5 and len(node.world.layout.obstacles) == n_obstacles
        resp = node._on_reset(SimScenario.Request(occlusion_density=0.0), SimScenario.Response())
        assert resp.success and node.config.seed == 5
        assert node.config.occlusion_density == 0.0 and not node.world.layout.obstacles
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_a_dying_simulation_thread_stops_the_node():
    """An exception in the simulation thread shuts the node's context down (run_node then
    exits 1), instead of leaving a node that spins on and publishes nothing."""
    import threading

    from coop_common.testing import wait_for
    ctx = Context()
    rclpy.init(context=ctx)
    node = SimNode(context=ctx, parameter_overrides=[
        Parameter('rovers', value=1), Parameter('stereo_rate_hz', value=0.0),
        Parameter('real_time_factor', value=0.0)])

    def broken():
        raise RuntimeError('physics server lost')
    errors = []
    hook, threading.excepthook = threading.excepthook, errors.append
    try:
        node.world.step = broken
        wait_for(lambda: not rclpy.ok(context=ctx), 20, what='the context shut down')
        node._thread.join(timeout=10)
        assert isinstance(node.fatal_error, RuntimeError)
        assert errors and errors[0].exc_type is RuntimeError     # the traceback is not lost
    finally:
        threading.excepthook = hook
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_rendering_is_chosen_while_running():
    """stereo_rate_hz and stereo_rovers are set while the sim runs (a mission renders only
    while someone looks): validated first (an unknown rover is refused, nothing changes),
    applied after."""
    ctx = Context()
    rclpy.init(context=ctx)
    node = SimNode(context=ctx, parameter_overrides=[
        Parameter('rovers', value=2), Parameter('stereo_rate_hz', value=0.0),
        Parameter('image_width', value=64), Parameter('image_height', value=48),
        Parameter('real_time_factor', value=0.0)])
    try:
        assert node._stereo_hz == 0.0 and node._renders('rover1') and node._renders('rover2')
        res = node.set_parameters([Parameter('stereo_rate_hz', value=4.0),
                                   Parameter('stereo_rovers', value=['rover1'])])
        assert all(r.successful for r in res), res
        assert node._stereo_hz == 4.0
        assert node._renders('rover1') and not node._renders('rover2')
        res = node.set_parameters([Parameter('stereo_rovers', value=['rover3'])])
        assert not res[0].successful and 'rover3' in res[0].reason
        assert not node._renders('rover2')                       # unchanged
        res = node.set_parameters([Parameter('stereo_rovers', value=[''])])
        assert res[0].successful and node._renders('rover2')     # [''] is all again
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_unknown_modes_are_refused_naming_the_allowed_values():
    """The integrator and renderer parameters are refused at start (read only) with the
    allowed values named; an obstacle kind that is neither rock nor drum never enters a
    layout."""
    import pytest

    from rover_sim.errors import SimError
    from rover_sim.worldgen import Obstacle, ObstacleKind
    ctx = Context()
    rclpy.init(context=ctx)
    try:
        for name, bad, allowed in (('integrator', 'rk4', "['implicit', 'explicit']"),
                                   ('renderer', 'vulkan', "['tiny', 'egl']")):
            with pytest.raises(ValueError) as exc:
                SimNode(context=ctx, parameter_overrides=[Parameter(name, value=bad)])
            assert str(exc.value) == f"{name} must be one of {allowed}, got '{bad}'"
    finally:
        rclpy.shutdown(context=ctx)
    assert Obstacle('drum', (0.0, 0.0, 0.4), 0.3, 0.8, 0.5).kind is ObstacleKind.DRUM
    with pytest.raises(SimError, match=r"kind must be one of \['rock', 'drum'\], got 'tree'"):
        Obstacle('tree', (0.0, 0.0, 0.0), 0.3, 0.8, 0.5)


def test_braid_mast_commands_are_checked_applied_and_put_in_the_tree():
    """mast:=braid: `mast/braid_command` takes one stage state 0..7 per stage (anything else is
    refused, nothing applied); the state takes effect in the world, and the tree's tilt link
    puts the optical frame where the chain's forward kinematics of that state put it."""
    import numpy as np
    from std_msgs.msg import UInt8MultiArray

    from coop_common.testing import wait_for
    from rover_sim.rover_model import CAMERA_OFFSET, OPTICAL_IN_TILT
    ctx = Context()
    rclpy.init(context=ctx)
    node = SimNode(context=ctx, parameter_overrides=[
        Parameter('rovers', value=1), Parameter('stereo_rate_hz', value=0.0),
        Parameter('real_time_factor', value=0.0), Parameter('mast', value='braid'),
        Parameter('braid_stages', value=3), Parameter('braid_settle_s', value=0.0)])
    try:
        assert node.world.braid is not None and node.world.braid.n == 3
        assert node._on_braid(0, UInt8MultiArray(data=[1, 2])) is None
        assert node._on_braid(0, UInt8MultiArray(data=[1, 2, 8])) is None
        assert node.bad.counts['braid state'] == 2
        item = node._on_braid(0, UInt8MultiArray(data=[1, 6, 3]))
        assert item is not None and item.states == (1, 6, 3)
        with node._lock:
            node._pending.append(item)
        wait_for(lambda: list(node.world.braid_state(0)) == [1, 6, 3], 20,
                 what='the BRAID state in effect')
        t = node._braid_tilt_link(0)
        m = np.eye(4)
        x, y, z, w = t.rotation
        m[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
        m[:3, 3] = t.translation
        tilt_opt = np.eye(4)
        tilt_opt[:3, :3], tilt_opt[:3, 3] = OPTICAL_IN_TILT, CAMERA_OFFSET
        np.testing.assert_allclose(m @ tilt_opt, node.world.braid.optical_in_pan([1, 6, 3]),
                                   atol=1e-9)
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_round_1_waits_for_writers_to_match_every_reader_and_listening_participant():
    """A reliable writer sends a round's messages only to the readers it has matched: round 1
    waits (and a stalled round's log names) each counted topic whose writer knows fewer
    readers than the graph shows, or than the participants that said in round 0 they take it
    where the graph does not show them yet."""
    from types import SimpleNamespace

    class Pub:
        def __init__(self, topic, matched):
            self.topic_name, self.matched = topic, matched

        def get_subscription_count(self):
            return self.matched

    def reader(ns, name):
        return SimpleNamespace(node_namespace=ns, node_name=name)
    graph = {'/rover1/joint_states': [reader('/rover1', 'identifier'), reader('/', 'recorder')],
             '/rover1/odom': [reader('/rover1', 'driver'), reader('/', 'recorder')],
             '/rover2/odom': [reader('/rover2', 'driver'), reader('/', 'recorder')]}
    listeners = {'/rover1/joint_states': {'/rover1/identifier', '/master'},
                 '/rover1/odom': {'/rover1/driver'}}
    node = SimpleNamespace(
        _counted=[Pub('/rover1/joint_states', 2), Pub('/rover1/odom', 2),
                  Pub('/rover2/odom', 1)],
        _gate=SimpleNamespace(listeners=listeners),
        get_subscriptions_info_by_topic=graph.__getitem__)
    # /master takes joint_states, the graph does not show it yet: 3 needed; rover2's odom has
    # 2 readers in the graph, 1 matched
    assert SimNode._unmatched_writers(node) == {'/rover1/joint_states': (2, 3),
                                                '/rover2/odom': (1, 2)}
