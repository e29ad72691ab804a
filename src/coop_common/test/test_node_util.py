"""coop_common.node_util.BadInputCounter: counts every rejection, warns once per period per
reason (a flood of one reason does not hide the first of another)."""
import signal

import pytest

from coop_common import node_util
from coop_common.node_util import BadInputCounter


@pytest.fixture(autouse=True)
def _stop_signals_restored():
    """run_node leaves SIGINT and SIGTERM ignored (its clean-up): put back what the test
    session had, or every process a later test starts would inherit them ignored."""
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    yield
    for s, handler in before.items():
        signal.signal(s, handler)


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

    class InterruptedWhileBuilding(Node):    # Ctrl-C before the node's action server exists
        def __init__(self):
            super().__init__('building')
            self.context.try_shutdown()
            from rclpy.action import ActionServer

            from coop_msgs.action import Identify
            ActionServer(self, Identify, 'identify', lambda goal: None)

    class BadParameter(Node):
        def __init__(self):
            super().__init__('bad')
            raise ValueError('rate must be > 0')

    assert run_node(Dies, []) == 1
    assert run_node(InterruptedWhileBuilding, []) == 0
    assert run_node(BadParameter, []) == 1
    assert run_node(Stops, []) == 0
    assert run_node(PublishesAfterShutdown, []) == 0
    with pytest.raises(RuntimeError, match='a real bug'):
        run_node(Fails, [])


def test_run_node_stops_on_sigterm_when_started_with_the_stop_signals_ignored():
    """Started from the background of a script, a node inherits SIGINT ignored: run_node gives
    SIGINT and SIGTERM a Python handler (rclpy chains to it) that raises KeyboardInterrupt."""
    import os
    import time

    from rclpy.node import Node

    from coop_common.node_util import run_node
    from coop_common.testing import isolate_ros_environment
    isolate_ros_environment()
    seen = {}

    class Terminated(Node):
        def __init__(self):
            super().__init__('terminated')
            seen.update({s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)})
            self.create_timer(0.01, lambda: os.kill(os.getpid(), signal.SIGTERM))

    class InterruptedInsideRclpy(Node):      # the signal lands inside a pybind11 call
        def __init__(self):
            super().__init__('inside')
            self.create_timer(0.01, self._stop)

        def _stop(self):
            try:
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(1.0)
            except KeyboardInterrupt:
                raise RuntimeError('Unable to convert call argument') from None

    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_IGN)
    assert run_node(Terminated, []) == 0
    assert run_node(InterruptedInsideRclpy, []) == 0
    for s, handler in seen.items():
        with pytest.raises(KeyboardInterrupt, match=signal.Signals(s).name):
            handler(s, None)


def _param_node(name, specs, check_all=None, reject_also=None):
    """A node in a private context with `specs` declared; returns (node, context, applied),
    applied: the on_change calls. reject_also: another on-set callback, registered before
    declare_parameters, so rclpy runs it after the validator (it inserts at the front)."""
    import rclpy
    from rclpy.node import Node

    from coop_common.node_util import declare_parameters
    from coop_common.testing import isolate_ros_environment
    isolate_ros_environment()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node(name, context=ctx)
    if reject_also is not None:
        node.add_on_set_parameters_callback(reject_also)
    applied = []
    state = declare_parameters(node, specs, on_change=lambda ch: (applied.append(dict(ch)),
                                                                  state.update(ch)),
                               check_all=check_all)
    return node, ctx, state, applied


def test_parameters_are_validated_then_applied_after_the_set():
    """A rejected value (range, the rule between parameters) is refused with its reason and
    leaves the node's state as it was; an accepted one is stored and then applied."""
    from rclpy.parameter import Parameter

    from coop_common.node_util import ParamSpec
    specs = {'near_m': ParamSpec(0.3, 'near', lo=0.0, hi=10.0),
             'far_m': ParamSpec(5.0, 'far', lo=0.1, hi=100.0),
             'mode': ParamSpec('a', 'mode', choices=('a', 'b'))}

    def rule(p):
        return None if p['near_m'] < p['far_m'] else 'near_m must be below far_m'

    node, ctx, state, applied = _param_node('params_apply', specs, rule)
    try:
        before = dict(state)
        # (the range: rclpy refuses it from the descriptor before any callback)
        for bad, why in ((Parameter('far_m', value=500.0), 'far_m out of range'),
                         (Parameter('near_m', value=6.0), 'near_m must be below far_m'),
                         (Parameter('mode', value='c'), "mode must be one of ['a', 'b']")):
            res = node.set_parameters([bad])[0]
            assert not res.successful and why in res.reason
        assert state == before and applied == []
        assert node.get_parameter('far_m').value == 5.0
        res = node.set_parameters_atomically([Parameter('far_m', value=8.0),
                                              Parameter('near_m', value=6.0)])
        assert res.successful
        assert applied == [{'far_m': 8.0, 'near_m': 6.0}]
        assert state['near_m'] == 6.0 and state['far_m'] == 8.0
        assert node.get_parameter('near_m').value == 6.0
    finally:
        node.destroy_node()
        ctx.try_shutdown()


def test_a_change_another_callback_rejects_is_not_applied():
    """Applying happens after the whole set succeeded: a value our validator accepts but another
    on-set callback of the node rejects changes nothing (applied in the on-set callback, it
    would have been half applied)."""
    from rcl_interfaces.msg import SetParametersResult
    from rclpy.parameter import Parameter

    from coop_common.node_util import ParamSpec

    def veto(params):
        ok = all(p.name != 'rate_hz' or p.value != 7.0 for p in params)
        return SetParametersResult(successful=ok, reason='' if ok else 'vetoed')

    node, ctx, state, applied = _param_node('params_veto', {
        'rate_hz': ParamSpec(1.0, 'rate', lo=0.1, hi=100.0)}, reject_also=veto)
    try:
        res = node.set_parameters([Parameter('rate_hz', value=7.0)])[0]
        assert not res.successful and res.reason == 'vetoed'
        assert state['rate_hz'] == 1.0 and applied == []
        assert node.set_parameters([Parameter('rate_hz', value=8.0)])[0].successful
        assert state['rate_hz'] == 8.0 and applied == [{'rate_hz': 8.0}]
    finally:
        node.destroy_node()
        ctx.try_shutdown()


def test_a_repeated_stop_signal_does_not_interrupt_the_stop_under_way():
    """launch signals the process group, then each child: the second SIGINT, landing between
    the first's KeyboardInterrupt and the clean-up's SIG_IGN, must not raise again (it broke
    a team launch's Ctrl-C: a traceback from signal.signal, exit -2); SIGTERM after it still
    raises, as launch's escalation."""
    node_util._STOP_SIGNALS.clear()
    with pytest.raises(KeyboardInterrupt, match='SIGINT'):
        node_util._interrupt(signal.SIGINT, None)
    assert node_util._interrupt(signal.SIGINT, None) is None
    with pytest.raises(KeyboardInterrupt, match='SIGTERM'):
        node_util._interrupt(signal.SIGTERM, None)
    node_util._STOP_SIGNALS.clear()


def test_a_stop_signal_never_lands_inside_an_rclpy_task_being_built():
    """Ctrl-C under load landed inside rclpy's Task.__init__: the half-made Task printed a
    traceback from its __del__ ('no attribute _exception') and the launch test failed. A
    signal landing in a constructor of rclpy/task.py is raised again a moment later, from
    wherever the main thread is then."""
    import sys
    import time
    src = ('class Task:\n'
           '    def __init__(self, interrupt):\n'
           '        interrupt(2, sys._getframe())\n'
           '        self.built = True\n')
    ns = {'sys': sys}
    exec(compile(src, '/opt/ros/jazzy/lib/python3.12/site-packages/rclpy/task.py', 'exec'),
         ns)
    node_util._STOP_SIGNALS.clear()
    previous = signal.signal(signal.SIGINT, node_util._interrupt)
    try:
        with pytest.raises(KeyboardInterrupt, match='SIGINT'):
            task = ns['Task'](node_util._interrupt)     # not raised in there ...
            assert task.built
            deadline = time.monotonic() + 5.0
            while time.monotonic() < deadline:           # ... but soon after
                time.sleep(0.001)
    finally:
        signal.signal(signal.SIGINT, previous)
        node_util._STOP_SIGNALS.clear()
        node_util._STOP_REQUESTED.clear()
    assert not node_util._in_constructor(sys._getframe())


def test_a_stop_signal_in_a_finalizer_is_raised_after_it(monkeypatch):
    """A SIGINT that lands while the garbage collector runs a `__del__` (rclpy's Future has
    one) is not raised inside it, where the interpreter prints 'Exception ignored in ...' with
    a traceback and drops it (the node would not stop), but sent again a moment later."""
    import sys
    import threading

    resent = threading.Event()
    monkeypatch.setattr(node_util._thread, 'interrupt_main',
                        lambda signum: resent.set() if signum == signal.SIGINT else None)
    dropped: list = []
    monkeypatch.setattr(sys, 'unraisablehook', dropped.append)

    class Finalized:
        def __del__(self):
            node_util._interrupt(signal.SIGINT, sys._getframe())

    node_util._STOP_SIGNALS.clear()
    try:
        Finalized()              # collected at once: its __del__ runs here
        assert resent.wait(5.0)
    finally:
        node_util._STOP_SIGNALS.clear()
        node_util._STOP_REQUESTED.clear()
    assert dropped == []


def test_a_request_made_in_the_executor_completes_for_another_thread():
    """in_executor makes the call in the spinning executor's thread (not the caller's) and hands
    its result to a future the caller waits on."""
    import threading

    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from rclpy.task import Future

    from coop_common.node_util import in_executor
    from coop_common.testing import isolate_ros_environment, wait_for
    isolate_ros_environment()
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    node = Node('in_executor', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    spin = threading.Thread(target=ex.spin, daemon=True)
    spin.start()
    try:
        answer, threads = Future(), []

        def request() -> Future:
            threads.append(threading.current_thread())
            return answer
        fut = in_executor(ex, request)
        wait_for(lambda: threads, 5, what='the request made')
        assert threads == [spin] and not fut.done()
        # the answer comes in the executor's thread (as a response to the request does)
        ex.create_task(lambda: answer.set_result('accepted'))
        wait_for(fut.done, 5, what='the answer handed on')
        assert fut.result() == 'accepted'
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.shutdown(context=ctx)
        spin.join(timeout=5)
