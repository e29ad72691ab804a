"""Node plumbing shared by every node: declared + validated parameters, throttled bad-input
counting, and the Jazzy main() idiom. No algorithm lives here."""
from __future__ import annotations

import _thread
import math
import signal
import threading
import time
from collections import Counter
from collections.abc import Callable
from typing import Any

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import Pose, WrenchStamped
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    SetParametersResult,
)
from rclpy.exceptions import InvalidParameterValueException, ParameterException
from rclpy.executors import Executor, ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.task import Future

from .errors import CoopCommonError
from .params import ParamSpec, check_values
from .rover_geometry import yaw_of

__all__ = [
    'BadInputCounter',
    'NodeFailed',
    'ParamSpec',
    'declare_parameters',
    'finite_wrench',
    'in_executor',
    'planar_pose',
    'run_node',
    'run_nodes',
    'stamp',
]


def stamp(t_s: float) -> Time:
    """Seconds -> builtin_interfaces/Time, rounded to the nanosecond (a time just below a
    whole second carries into sec rather than wrapping nanosec to 0)."""
    ns = round(t_s * 1e9)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def in_executor(executor: Executor, call: Callable[[], Future]) -> Future:
    """The result of `call()`, an rclpy request (an action client's send_goal_async,
    get_result_async, cancel_goal_async), made in `executor`'s thread, as a future another
    thread can wait on. Made from another thread while the executor spins, the request can be
    answered and its answer taken by the executor before rclpy's action client has filed the
    future for it: the answer is dropped and the future never completes (ros2/rclpy#1123;
    seen with this project's rclpy 7.1). In the executor's thread the request is filed before
    the executor looks for its answer."""
    async def request():
        return await call()
    return executor.create_task(request)


def _descriptor(spec: ParamSpec) -> ParameterDescriptor:
    d = ParameterDescriptor(description=spec.description, read_only=spec.read_only)
    if spec.choices:
        d.additional_constraints = 'one of: ' + ', '.join(spec.choices)
    if spec.lo is not None and spec.hi is not None:
        if isinstance(spec.default, bool):
            pass
        elif isinstance(spec.default, int):
            d.integer_range = [IntegerRange(from_value=int(spec.lo), to_value=int(spec.hi),
                                            step=0)]
        elif isinstance(spec.default, float):
            d.floating_point_range = [FloatingPointRange(from_value=float(spec.lo),
                                                         to_value=float(spec.hi), step=0.0)]
    return d


def declare_parameters(node: Node, specs: dict[str, ParamSpec],
                       on_change: Callable[[dict[str, Any]], None] | None = None,
                       check_all: Callable[[dict[str, Any]], str | None] | None = None
                       ) -> dict[str, Any]:
    """Declare every spec with its descriptor, validate the initial values (raising ValueError with
    the reason, so a bad --params-file stops the node at start), and install the Jazzy pair of
    parameter callbacks (ros2/demos `demo_nodes_py/parameters/set_parameters_callback.py`).

    * an on-set callback that only validates: each value against its spec, then `check_all`, a
      rule between parameters (e.g. near < far) given all values as they would be, returning
      the reason they are not acceptable or None; a bad value is rejected with that reason and
      nothing changes;
    * a post-set callback that applies: `on_change` gets the accepted values by name, after
      rclpy has stored them. Applying in the on-set callback would change the node's state
      before the change is certain (another on-set callback may still reject it).

    Returns the current values."""
    for name, spec in specs.items():
        node.declare_parameter(name, spec.default, _descriptor(spec))
    values = {name: node.get_parameter(name).value for name in specs}
    bad = check_values(specs, values, check_all)
    if bad:
        raise ValueError('; '.join(bad))

    def _validate(params):
        for p in params:
            spec = specs.get(p.name)
            if spec is None:
                continue
            reason = spec.check(p.name, p.value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        if check_all is not None:
            now = {name: node.get_parameter(name).value for name in specs}
            now.update({p.name: p.value for p in params if p.name in specs})
            reason = check_all(now)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
        return SetParametersResult(successful=True)

    def _apply(params) -> None:
        changed = {p.name: p.value for p in params if p.name in specs}
        if changed:
            on_change(changed)

    node.add_on_set_parameters_callback(_validate)
    if on_change is not None:
        node.add_post_set_parameters_callback(_apply)
    return values


class BadInputCounter:
    """Counts skipped inputs by reason and warns at most once per `period_s` per reason."""

    def __init__(self, node: Node, period_s: float = 5.0) -> None:
        self._node = node
        self._period = period_s
        self.counts: Counter[str] = Counter()
        # rclpy throttles per call site, which would make one reason hide the others
        self._last_warn: dict[str, float] = {}

    def reject(self, reason: str, detail: str = '') -> None:
        self.counts[reason] += 1
        now = time.monotonic()
        if now - self._last_warn.get(reason, -math.inf) < self._period:
            return
        self._last_warn[reason] = now
        suffix = f': {detail}' if detail else ''
        self._node.get_logger().warn(
            f'skipped input ({reason}, {self.counts[reason]} so far){suffix}')

    @property
    def total(self) -> int:
        return sum(self.counts.values())


def finite_wrench(msg: WrenchStamped, bad: BadInputCounter) -> np.ndarray | None:
    """An F/T reading as (fx, fy, fz, tx, ty, tz); None, counted in `bad` as 'wrench', when a
    component is not finite."""
    f, m = msg.wrench.force, msg.wrench.torque
    w = np.array([f.x, f.y, f.z, m.x, m.y, m.z])
    if np.all(np.isfinite(w)):
        return w
    bad.reject('wrench', 'non-finite')
    return None


def planar_pose(pose: Pose) -> tuple[float, float, float]:
    """(x, y, yaw) of a pose on the ground plane (an odometry message's `pose.pose`)."""
    q = pose.orientation
    return pose.position.x, pose.position.y, yaw_of(q.x, q.y, q.z, q.w)


#: set once SIGINT or SIGTERM arrived: whatever a callback raises after it is the stop (a
#: KeyboardInterrupt raised inside a pybind11 call comes out as a RuntimeError)
_STOP_REQUESTED = threading.Event()
#: the stop signals this run_node has already raised for
_STOP_SIGNALS: set[int] = set()


#: the constructors an asynchronous KeyboardInterrupt must not land in: rclpy's Future and
#: Task (a Task half-made by one prints 'Exception ignored in Future.__del__ ... no attribute
#: _exception' when collected, seen at a Ctrl-C under load)
_UNINTERRUPTIBLE = ('rclpy/task.py',)
#: how long after such a landing the interrupt is raised again (s)
_RETRY_S = 0.005


def _in_constructor(frame, files: tuple[str, ...] = _UNINTERRUPTIBLE, depth: int = 6) -> bool:
    """Whether `frame` or one of its `depth` callers is an `__init__` of one of `files`."""
    f = frame
    for _ in range(depth):
        if f is None:
            return False
        if f.f_code.co_name == '__init__' and \
                f.f_code.co_filename.replace('\\', '/').endswith(files):
            return True
        f = f.f_back
    return False


def _in_finalizer(frame) -> bool:
    """Whether `frame` is a `__del__` (a garbage collection the signal landed in): an
    exception raised there is printed and dropped ('Exception ignored in ...'), and the stop
    with it."""
    return frame is not None and frame.f_code.co_name == '__del__'


def _interrupt(signum: int, frame) -> None:
    _STOP_REQUESTED.set()
    if signum in _STOP_SIGNALS:
        # the same signal again: `ros2 launch` signals the process group, then each child, and
        # the second can land between the first's KeyboardInterrupt and the clean-up's
        # SIG_IGN, where raising would break the clean-up (a traceback, exit -2). The stop is
        # under way; a SIGTERM after a SIGINT still raises (launch's escalation)
        return
    if _in_constructor(frame) or _in_finalizer(frame):
        # raised here it would leave the object half-made, or be dropped by the interpreter
        # with a traceback: again in a moment, from wherever the main thread is then
        threading.Timer(_RETRY_S, _thread.interrupt_main, (signum,)).start()
        return
    _STOP_SIGNALS.add(signum)
    raise KeyboardInterrupt(signal.Signals(signum).name)


def _python_stop_handlers() -> None:
    """SIGINT and SIGTERM raise KeyboardInterrupt in the main thread, before rclpy.init.

    rclpy's own handler (installed by init) stops the node from a helper thread that shuts the
    context down, and chains to the handler it found. A process started with SIGINT ignored
    (launched from the background of a script) has no Python handler to chain to, and that
    helper alone now and then leaves a node spinning after Ctrl-C. With these, the executor's
    wake-up (rclpy triggers its guard condition) returns into Python, which raises: the path a
    terminal's Ctrl-C takes, for SIGTERM too (launch's escalation, a service manager's stop)."""
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _interrupt)


def run_node(factory: Callable[[], Node], args: list[str] | None = None,
             executor_factory: Callable[[], Any] | None = None) -> int:
    """The Jazzy main() idiom: init, spin, clean shutdown on Ctrl-C or external shutdown.

    A node whose construction fails (bad parameter, bad file) logs the reason and returns 1; so
    does one that shut its context down itself after setting `fatal_error` (a worker thread it
    cannot run without died).
    """
    return run_nodes([factory], args, executor_factory)


class NodeFailed(CoopCommonError):
    """A callback of one node of a composed process raised: `node` names it."""

    def __init__(self, node: str, exc: BaseException) -> None:
        super().__init__(f'{node}: {type(exc).__name__}: {exc}')
        self.node = node


def _raised_in(exc: BaseException, nodes: list[Node]) -> Node | None:
    """The node of `nodes` whose method the traceback of `exc` passed through last (the
    innermost frame whose `self` is one of them), None when none."""
    found = None
    tb = exc.__traceback__
    while tb is not None:
        owner = tb.tb_frame.f_locals.get('self')
        if any(owner is n for n in nodes):
            found = owner
        tb = tb.tb_next
    return found


def run_nodes(factories: list[Callable[[], Node]], args: list[str] | None = None,
              executor_factory: Callable[[], Any] | None = None) -> int:
    """run_node for several nodes in one process and one executor (a composed bring-up):
    built in order, spun together, destroyed in reverse. Parameters and remappings aimed at
    one node use ROS's own forms (a `--params-file` keyed `/**/<node>:`, `-r <node>:a:=b`).

    One node that cannot be built stops the process with that node's reason (return 1);
    one whose callback raises stops it with that node's name and the exception (NodeFailed,
    after the clean-up)."""
    _STOP_REQUESTED.clear()
    _STOP_SIGNALS.clear()
    _python_stop_handlers()
    rclpy.init(args=args)
    nodes: list[Node] = []
    # the executor first: built after a Ctrl-C has shut the context down, rclpy's Executor fails
    # half-made and its __del__ prints a traceback ('no attribute _sigint_gc')
    executor = executor_factory() if executor_factory is not None else SingleThreadedExecutor()
    try:
        for factory in factories:
            try:
                nodes.append(factory())
            except (ValueError, InvalidParameterValueException, ParameterException) as exc:
                if not rclpy.ok():
                    # Ctrl-C while the node was still being built (its next rcl call found the
                    # context shut down): a clean stop, not a failed start
                    return 0
                what = getattr(factory, '__name__', 'node')
                rclpy.logging.get_logger('startup').fatal(
                    f'cannot start{"" if len(factories) == 1 else " " + what}: {exc}')
                return 1
            executor.add_node(nodes[-1])
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as exc:
        # Ctrl-C shuts the context down under a callback in flight, whose next publish then
        # raises (RCLError: the publisher's context is invalid), or interrupts a call into
        # rclpy's C++ (RuntimeError): that is a clean stop too
        if rclpy.ok() and not _STOP_REQUESTED.is_set():
            culprit = _raised_in(exc, nodes) if len(nodes) > 1 else None
            if culprit is None:
                raise
            name = culprit.get_fully_qualified_name()
            culprit.get_logger().fatal(f'stops the process: {type(exc).__name__}: {exc}')
            raise NodeFailed(name, exc) from exc
    finally:
        # `ros2 launch` signals the whole process group and then each child: a second SIGINT
        # in the middle of the clean-up would raise inside destroy_node (a traceback, exit -2);
        # its SIGTERM, 5 s on, would kill a process still exiting (rclpy has put the default
        # action back by then: exit -15) on a loaded machine. Stopping already, it ignores
        # both; SIGKILL stays the last word.
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, signal.SIG_IGN)
        for node in reversed(nodes):
            node.destroy_node()
        rclpy.try_shutdown()
        _STOP_SIGNALS.clear()
    return 1 if any(getattr(n, 'fatal_error', None) is not None for n in nodes) else 0
