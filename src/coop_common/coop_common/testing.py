"""Test isolation for node and whole-graph tests: a private ROS domain per test run, starting the
installed executables the way `ros2 run` finds them, and waiting on conditions, not sleeping."""
from __future__ import annotations

import contextlib
import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

from ament_index_python.packages import get_package_prefix


def pick_domain_id(pid: int | None = None) -> int:
    """A domain id for this test run (1..100), from the pid so parallel runs do not cross-talk."""
    return 1 + (pid if pid is not None else os.getpid()) % 100


#: RTPS's well-known ports (DDSI-RTPS 2.2, 9.6.1.1): a participant of domain d binds its
#: discovery and user unicast ports at PB + DG * d + 10 + 2 * participant (+ 1)
_RTPS_PB, _RTPS_DG = 7400, 250
_UDP_TABLES = ('/proc/net/udp', '/proc/net/udp6')


def domains_in_use(tables: Sequence[str] = _UDP_TABLES) -> set[int]:
    """The domain ids 1..100 in which a DDS participant runs in this network namespace: those
    with a UDP port bound in their RTPS range (Linux's /proc/net/udp tables; none where they
    cannot be read). The ranges of 1..100 end at port 32649, below the kernel's ephemeral
    ports, so nothing else binds there by chance."""
    used = set()
    for table in tables:
        try:
            lines = Path(table).read_text().splitlines()[1:]
        except OSError:
            continue
        for line in lines:
            fields = line.split()
            if len(fields) < 2:
                continue
            port = int(fields[1].rsplit(':', 1)[-1], 16)
            domain, offset = divmod(port - _RTPS_PB, _RTPS_DG)
            if 1 <= domain <= 100 and offset >= 10:
                used.add(domain)
    return used


def free_domain_id(start: int | None = None, *, nth: int = 0,
                   in_use: set[int] | None = None) -> int:
    """The `nth` (0: first) domain id of 1..100, from `start` on (default: this process's
    pid), in which no DDS participant runs yet (domains_in_use): a run that picks its domain
    apart from others on the machine. Workers of one test run give the same start and each
    its own nth. Where every domain is taken, pick_domain_id's."""
    base = os.getpid() if start is None else start
    busy = domains_in_use() if in_use is None else in_use
    free = [d for d in (1 + (base + i) % 100 for i in range(100)) if d not in busy]
    return free[nth % len(free)] if free else pick_domain_id(base)


def isolate_ros_environment(domain_id: int | None = None) -> int:
    """Set ROS_DOMAIN_ID / localhost discovery for this process and its children; without a
    domain_id, a free one (free_domain_id)."""
    domain = free_domain_id() if domain_id is None else domain_id
    os.environ['ROS_DOMAIN_ID'] = str(domain)
    os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    os.environ.setdefault('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp')
    return domain


def executable_path(package: str, executable: str) -> Path:
    """Where `ros2 run <package> <executable>` would find it: <prefix>/lib/<package>/<executable>,
    prefix from the ament index on AMENT_PREFIX_PATH."""
    path = Path(get_package_prefix(package)) / 'lib' / package / executable
    if not (path.is_file() and os.access(path, os.X_OK)):
        raise FileNotFoundError(f'no executable {executable!r} in package {package!r} ({path})')
    return path


def ros2_tools() -> str:
    """The `ros2` command (a ROS 2 Jazzy install's, or in the pinned venv the one `make
    ros2-tools` installs from the bundle ROS2_TOOLS_SRC names) with launch_ros beside it: its
    path. Without them a test skips with the reason, or fails when COOP_REQUIRE_ROS2_TOOLS=1
    (CI installs them and requires them)."""
    import pytest  # noqa: PLC0415 - a test helper; the nodes never import this function

    exe = shutil.which('ros2')
    if exe and importlib.util.find_spec('launch_ros') is not None:
        return exe
    why = ('no ros2 / launch_ros here: a ROS 2 Jazzy install has them (docs/install.md); in the '
           'pinned venv, make ros2-tools ROS2_TOOLS_SRC=<ros2-tools bundle> && '
           '. .ros2-tools/install/local_setup.bash')
    if os.environ.get('COOP_REQUIRE_ROS2_TOOLS') == '1':
        pytest.fail(f'COOP_REQUIRE_ROS2_TOOLS=1 but {why}')
    pytest.skip(why)


def usage_error(main: Callable[[list[str]], object], argv: Sequence[str], capsys) -> str:
    """Run a CLI's `main(argv)` expecting argparse's usage error (SystemExit 2) and return
    what it wrote to stderr (`capsys`: pytest's fixture)."""
    try:
        main(list(argv))
    except SystemExit as exc:
        if exc.code != 2:
            raise AssertionError(f'{argv}: exit {exc.code}, not a usage error') from None
        return capsys.readouterr().err
    raise AssertionError(f'{argv}: ran without a usage error')


@contextlib.contextmanager
def busy_core(on: bool = True) -> Iterator[None]:
    """A process spinning on one core while the block runs (nothing when `on` is False): the
    load under which lockstep's outcomes must not change."""
    if not on:
        yield
        return
    proc = subprocess.Popen([sys.executable, '-c', 'while True: pass'])
    try:
        yield
    finally:
        proc.kill()
        proc.wait()


def wait_for(predicate: Callable[[], bool], timeout_s: float, *, poll_s: float = 0.02,
             spin: Callable[[float], None] | None = None, what: str = 'condition') -> None:
    """Wait until predicate() holds, spinning `spin(poll_s)` (or sleeping) between checks.

    Raises TimeoutError naming `what`."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise TimeoutError(f'timed out after {timeout_s:.1f} s waiting for {what}')
        if spin is not None:
            spin(poll_s)
        else:
            time.sleep(poll_s)


class NodeProcess:
    """Start an installed executable with `--ros-args ...` as a subprocess; stop it on exit.

    with NodeProcess('rover_sim', 'sim', ['-p', 'seed:=3']) as proc: ...
    """

    def __init__(self, package: str, executable: str, ros_args: Sequence[str] = (),
                 args: Sequence[str] = (), env: dict[str, str] | None = None,
                 log_path: Path | None = None) -> None:
        self.cmd = [str(executable_path(package, executable)), *args]
        if ros_args:
            self.cmd += ['--ros-args', *ros_args]
        self.env = {**os.environ, **(env or {})}
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None
        self._log = None

    def __enter__(self) -> NodeProcess:
        if self.log_path is not None:
            self._log = open(self.log_path, 'wb')  # closed in __exit__
        out = self._log if self._log is not None else subprocess.DEVNULL
        self.proc = subprocess.Popen(self.cmd, env=self.env, stdout=out, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        return self

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout_s: float = 10.0) -> int | None:
        if self.proc is None:
            return None
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGINT)
            try:
                self.proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait()
        return self.proc.returncode

    def log_text(self) -> str:
        if self.log_path is None or not self.log_path.exists():
            return ''
        return self.log_path.read_text(errors='replace')

    def __exit__(self, *exc) -> None:
        self.stop()
        if self._log is not None:
            self._log.close()


class Probe:
    """A node in its own context that keeps the messages of chosen topics, for whole-graph
    tests (a context of its own, so it shuts down apart from the process under test)."""

    def __init__(self, name: str = 'probe', **node_kwargs) -> None:

        import rclpy  # noqa: PLC0415 - rclpy only for a Probe: the other helpers serve ROS-free tests
        from rclpy.context import Context  # noqa: PLC0415 - see import rclpy
        from rclpy.executors import SingleThreadedExecutor  # noqa: PLC0415 - see import rclpy
        from rclpy.node import Node  # noqa: PLC0415 - see import rclpy

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = Node(name, context=self.context, **node_kwargs)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.msgs: dict[str, list] = {}
        self._lock = threading.Lock()

    def listen(self, msg_type, topic: str, qos=None) -> None:
        """Keep every message of `topic` in `msgs[topic]` (sensor QoS unless told)."""
        if qos is None:
            from .qos import SENSOR_QOS  # noqa: PLC0415 - qos imports rclpy
            qos = SENSOR_QOS
        self.msgs[topic] = []

        def cb(m, topic=topic):
            with self._lock:
                self.msgs[topic].append(m)
        self.node.create_subscription(msg_type, topic, cb, qos)

    def count(self, topic: str) -> int:
        return len(self.msgs[topic])

    def spin_until(self, predicate: Callable[[], bool], timeout_s: float, what: str,
                   procs: Sequence[NodeProcess] = ()) -> None:
        """Spin until predicate() holds; fail at once, with its log, if one of `procs` exits."""
        def check() -> bool:
            for p in procs:
                if not p.alive():
                    raise AssertionError(f'{p.cmd[0]} exited while waiting for {what}:\n'
                                         + p.log_text())
            return predicate()
        wait_for(check, timeout_s, spin=lambda s: self.executor.spin_once(timeout_sec=s),
                 what=what)

    def spin_for(self, seconds: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            self.executor.spin_once(timeout_sec=0.02)

    def close(self) -> None:
        import rclpy  # noqa: PLC0415 - rclpy only for a Probe: the other helpers serve ROS-free tests

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)

    def __enter__(self) -> Probe:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
