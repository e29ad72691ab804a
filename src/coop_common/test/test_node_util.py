"""coop_common.node_util.BadInputCounter: counts every rejection, warns once per period per
reason (a flood of one reason does not hide the first of another)."""
import pytest

from coop_common import node_util
from coop_common.node_util import BadInputCounter


class _Logger:
    def __init__(self):
        self.lines = []

    def warn(self, msg, **kw):
        assert not kw, 'no rclpy throttling: it is per call site, not per reason'
        self.lines.append(msg)


class _Node:
    def __init__(self):
        self.logger = _Logger()

    def get_logger(self):
        return self.logger


def test_warns_once_per_period_per_reason(monkeypatch):
    clock = [100.0]
    monkeypatch.setattr(node_util.time, 'monotonic', lambda: clock[0])
    node = _Node()
    bad = BadInputCounter(node, period_s=5.0)
    for _ in range(10):
        bad.reject('nan')
    bad.reject('unknown_frame', 'odom')
    bad.reject('too_large')
    assert bad.counts == {'nan': 10, 'unknown_frame': 1, 'too_large': 1} and bad.total == 12
    assert node.logger.lines == ['skipped input (nan, 1 so far)',
                                 'skipped input (unknown_frame, 1 so far): odom',
                                 'skipped input (too_large, 1 so far)']
    clock[0] += 5.0
    bad.reject('nan')
    assert node.logger.lines[-1] == 'skipped input (nan, 11 so far)'


def test_run_node_exits_1_when_the_node_shut_itself_down_for_a_fatal_error():
    from rclpy.node import Node

    from coop_common.node_util import run_node
    from coop_common.testing import isolate_ros_environment
    isolate_ros_environment()

    class Dies(Node):
        def __init__(self):
            super().__init__('dies')
            self.fatal_error = None
            self.create_timer(0.01, self._die)

        def _die(self):
            self.fatal_error = RuntimeError('worker died')
            self.context.try_shutdown()

    class Stops(Node):
        def __init__(self):
            super().__init__('stops')
            self.create_timer(0.01, self.context.try_shutdown)

    class PublishesAfterShutdown(Node):      # Ctrl-C under a callback in flight
        def __init__(self):
            super().__init__('late')
            from std_msgs.msg import Empty
            self.msg = Empty()
            self.pub = self.create_publisher(Empty, 'x', 1)
            self.create_timer(0.01, self._late)

        def _late(self):
            self.context.try_shutdown()
            self.pub.publish(self.msg)

    class Fails(Node):
        def __init__(self):
            super().__init__('fails')
            self.create_timer(0.01, self._fail)

        def _fail(self):
            raise RuntimeError('a real bug')

    assert run_node(Dies, []) == 1
    assert run_node(Stops, []) == 0
    assert run_node(PublishesAfterShutdown, []) == 0
    with pytest.raises(RuntimeError, match='a real bug'):
        run_node(Fails, [])


def test_rover_frame_takes_the_last_part_of_the_namespace():
    assert node_util.rover_frame('/rover1', 'base_link') == 'rover1/base_link'
    assert node_util.rover_frame('/team_a/rover2', 'base_link') == 'rover2/base_link'
    assert node_util.rover_frame('/', 'base_link') == 'base_link'
