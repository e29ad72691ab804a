"""A launch file's graph run for a client that drives it (the mission, the insertion rig):
launch's own `LaunchService` runs the file in a child process (launch runs only in a main
thread, and the client's is its own), and tells the client which node runs in which process
through a state file it rewrites at every process start and exit.

    with LaunchedGraph(share / 'launch' / 'mission.launch.py', {'lockstep': 'true'},
                       log_dir=Path('out/logs')) as graph:
        graph.wait_started(['/rover_sim', '/master'], timeout_s=60)
        ...
        graph.stop('/rover1/stereo')

`python -m coop_bringup.graph --state STATE.json [--log-dir DIR] FILE [name:=value ...]` is
the child. Each process's output goes where the launch file's `output` argument sends it
(`own_log`: `<process>.log` in the log directory, beside launch's own `launch.log`).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

import yaml
from ament_index_python.packages import get_package_share_directory

from coop_common.files import write_json

from .report import MissionError

#: how long a stopped graph's launch has to end its processes before they are killed (s)
STOP_S = 30.0


class GraphError(MissionError):
    """The launched graph could not start, or a process of it is not there."""


class LaunchedGraph(contextlib.AbstractContextManager):
    """The graph of `launch_file` with `arguments` (name -> value), run by launch in a child
    process of its own session; every process it started is gone after __exit__."""

    def __init__(self, launch_file: str | Path, arguments: dict[str, str], *,
                 log_dir: Path) -> None:
        self.launch_file = Path(launch_file)
        if not self.launch_file.is_file():
            raise GraphError(f'no launch file {self.launch_file}')
        bad = [k for k in arguments if not k or ':=' in k]
        if bad:
            raise GraphError(f'launch arguments {bad}: give plain names')
        self.arguments = dict(arguments)
        self.log_dir = Path(log_dir)
        self.state_file = self.log_dir / 'graph.json'
        self.proc: subprocess.Popen | None = None
        self._log: IO[bytes] | None = None
        self._stopped: set[str] = set()

    # -- the child ------------------------------------------------------------------------
    def __enter__(self) -> LaunchedGraph:
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.state_file.unlink(missing_ok=True)
        cmd = [sys.executable, '-m', 'coop_bringup.graph', '--state', str(self.state_file),
               '--log-dir', str(self.log_dir), str(self.launch_file),
               *(f'{k}:={v}' for k, v in self.arguments.items())]
        self._log = open(self.log_dir / 'launch_output.log', 'wb')
        self.proc = subprocess.Popen(cmd, stdout=self._log, stderr=subprocess.STDOUT,
                                     start_new_session=True)
        return self

    def __exit__(self, *exc: object) -> None:
        """SIGINT to launch, which stops its processes (escalating as it does); whatever is
        left after STOP_S is killed with the whole session."""
        if self.proc is not None:
            if self.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(self.proc.pid, signal.SIGINT)
                with contextlib.suppress(subprocess.TimeoutExpired):
                    self.proc.wait(timeout=STOP_S)
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.proc.wait(timeout=10)
        for pid in self._pids():
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.kill(pid, signal.SIGKILL)    # a node that left launch's session
        if self._log is not None:
            self._log.close()
            self._log = None

    # -- what runs ------------------------------------------------------------------------
    def processes(self) -> dict[str, dict]:
        """Node (full name, or the process's name for a process of several nodes) -> its
        `pid`, `process` name and `returncode` (None while it runs), as launch reported."""
        try:
            return json.loads(self.state_file.read_text())['processes']
        except (OSError, ValueError, KeyError):
            return {}

    def _pids(self) -> list[int]:
        return [p['pid'] for p in self.processes().values() if p.get('returncode') is None]

    def find(self, name: str) -> list[str]:
        """The processes' keys whose last name segments are `name` ('stereo' finds
        /rover1/stereo and /team_a/rover2/stereo; 'rover1/stereo' the first)."""
        want = name.strip('/').split('/')
        return sorted(k for k in self.processes() if k.strip('/').split('/')[-len(want):] == want)

    def pid(self, name: str) -> int | None:
        """The pid of the one running process `name` finds, else None."""
        procs = self.processes()
        keys = [k for k in self.find(name) if procs[k].get('returncode') is None]
        return procs[keys[0]]['pid'] if len(keys) == 1 else None

    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def dead(self) -> list[str]:
        """What ended that was not stopped: the processes that exited, and 'launch' when
        launch itself did (a launch file's error: its output is in the log directory)."""
        out = [k for k, p in self.processes().items()
               if p.get('returncode') is not None and k not in self._stopped]
        if self.proc is not None and self.proc.poll() is not None:
            out.append('launch')
        return out

    def wait_started(self, names: Iterable[str], *, timeout_s: float) -> None:
        """Until a process of each of `names` (as find() takes them) has started (GraphError
        when launch ended first or the time is up, with launch's output)."""
        names = list(names)
        end = time.monotonic() + timeout_s
        while True:
            missing = [n for n in names if not self.find(n)]
            if not missing:
                return
            if not self.running() or time.monotonic() > end:
                raise GraphError(f'{", ".join(missing)} did not start'
                                 f'{"" if self.running() else " (launch ended)"}: '
                                 f'{self.launch_output()[-2000:]}')
            time.sleep(0.05)

    def stop(self, name: str, *, timeout_s: float = 10.0) -> None:
        """SIGINT to the process(es) of `name`, SIGKILL after timeout_s; launch carries on."""
        procs = self.processes()
        for key in self.find(name):
            pid = procs[key].get('pid')
            self._stopped.add(key)
            if pid is None or procs[key].get('returncode') is not None:
                continue
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGINT)
            end = time.monotonic() + timeout_s
            while self.processes().get(key, {}).get('returncode') is None:
                if time.monotonic() > end:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(pid, signal.SIGKILL)
                    break
                time.sleep(0.05)

    def launch_output(self) -> str:
        path = self.log_dir / 'launch_output.log'
        return path.read_text(errors='replace') if path.exists() else ''


#: the launch files whose arguments a README shows (launch_arguments_table)
MISSION_LAUNCH = 'mission.launch.py'
TEAM_LAUNCH = 'team.launch.py'


def launch_arguments_table(file_name: str) -> str:
    """The arguments coop_bringup's launch file `file_name` declares, as a Markdown table
    (name, default, description), read by launch from the file itself: a README shows the
    file's own list, so the two cannot drift."""
    from launch.actions import DeclareLaunchArgument  # noqa: PLC0415 - launch only here
    from launch.launch_description_sources import (  # noqa: PLC0415 - launch only here
        get_launch_description_from_python_launch_file,
    )
    path = Path(__file__).resolve().parents[1] / 'launch' / file_name
    if not path.exists():       # installed, not run from the source tree
        path = mission_launch_file().with_name(file_name)
    rows = ['| argument | default | meaning |', '|---|---|---|']
    seen = set()
    for entity in get_launch_description_from_python_launch_file(str(path)).entities:
        if isinstance(entity, DeclareLaunchArgument) and entity.name not in seen:
            seen.add(entity.name)
            default = ''.join(getattr(d, 'text', '?') for d in entity.default_value or [])
            shown = f'`{default}`' if default and entity.name != 'params_file' else \
                ('`share/coop_bringup/config/mission.yaml`' if default else '(empty)')
            rows.append(f'| `{entity.name}` | {shown} | {entity.description} |')
    return '\n'.join(rows)


def node_logs(log_dir: Path) -> dict[str, Path]:
    """Node (as LaunchedGraph.processes keys them) -> its output's log file, for a graph run
    with output:=own_log into `log_dir` (read back from its state file: also after the run)."""
    try:
        procs = json.loads((Path(log_dir) / 'graph.json').read_text())['processes']
    except (OSError, ValueError, KeyError):
        return {}
    return {k: Path(log_dir) / f'{p["process"]}.log' for k, p in procs.items()}


def mission_launch_file() -> Path:
    """coop_bringup's launch/mission.launch.py, as installed."""
    return Path(get_package_share_directory('coop_bringup')) / 'launch' / 'mission.launch.py'


def node_settings(node: str, params_file: Path | None = None) -> dict:
    """What the graph's parameter file (default: coop_bringup's config/mission.yaml) sets for
    `node` under `/**/<node>`: for a client that plans as the node does (the mission's paths
    on the view planner's grid)."""
    if params_file is None:
            params_file = Path(get_package_share_directory('coop_bringup')) / 'config' / \
            'mission.yaml'
    try:
        doc = yaml.safe_load(Path(params_file).read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise GraphError(f'{params_file}: {exc}') from None
    return dict((doc.get(f'/**/{node}') or {}).get('ros__parameters') or {})


def _key(event: Any) -> str:
    """A started or exited process's key: its node's full name, or for a process of no one
    named node (`coop_bringup compose`) its executable's name."""
    with contextlib.suppress(Exception):   # a plain process, or a node without a name
        action = event.action
        if action.is_node_name_fully_specified():
            return action.node_name
    name, _, count = event.process_name.rpartition('-')
    return name if name and count.isdigit() else event.process_name


def main(argv: list[str] | None = None) -> int:
    """The child: run a launch file with its arguments, writing the state file."""
    p = argparse.ArgumentParser(prog='python -m coop_bringup.graph',
                                description=__doc__.split('\n\n')[0])
    p.add_argument('launch_file', type=Path)
    p.add_argument('--state', type=Path, required=True,
                   help='the JSON the processes are written to')
    p.add_argument('--log-dir', type=Path, default=None, help="launch's log directory")
    p.add_argument('arguments', nargs='*', metavar='name:=value')
    a = p.parse_intermixed_args(argv)
    bad = [x for x in a.arguments if ':=' not in x]
    if bad:
        p.error(f'launch arguments are name:=value, not {bad}')
    import launch  # noqa: PLC0415 - launch only here
    import launch.logging  # noqa: PLC0415 - launch only here
    from launch.actions import IncludeLaunchDescription, RegisterEventHandler  # noqa: PLC0415 - launch only here
    from launch.event_handlers import OnProcessExit, OnProcessStart  # noqa: PLC0415 - launch only here
    from launch.launch_description_sources import PythonLaunchDescriptionSource  # noqa: PLC0415 - launch only here
    if a.log_dir is not None:
        a.log_dir.mkdir(parents=True, exist_ok=True)
        launch.logging.launch_config.log_dir = str(a.log_dir)
    state: dict[str, dict] = {}

    def save() -> None:
        write_json(a.state, {'launch_file': str(a.launch_file), 'processes': state})

    def started(event: Any, _context: Any) -> None:
        state[_key(event)] = {'pid': event.pid, 'process': event.process_name,
                              'returncode': None}
        save()

    def exited(event: Any, _context: Any) -> None:
        state.setdefault(_key(event), {'pid': event.pid, 'process': event.process_name})
        state[_key(event)]['returncode'] = event.returncode
        save()

    save()
    # (mypy takes `launch` for coop_bringup's launch/ directory of launch files)
    service = launch.LaunchService(noninteractive=True)  # type: ignore[attr-defined]
    service.include_launch_description(launch.LaunchDescription([  # type: ignore[attr-defined]
        RegisterEventHandler(OnProcessStart(on_start=started)),
        RegisterEventHandler(OnProcessExit(on_exit=exited)),
        IncludeLaunchDescription(PythonLaunchDescriptionSource(str(a.launch_file.resolve())),
                                 launch_arguments=[tuple(x.split(':=', 1))
                                                   for x in a.arguments]),
    ]))
    return service.run()


if __name__ == '__main__':
    raise SystemExit(main())
