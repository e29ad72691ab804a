"""`ros2 run coop_bringup mission` (and `make demo`): the thesis's whole cooperative mission
(ch. 5.1, Fig. 4-2) through the nodes, judged by the simulator's truth.

Brings up, on a private ROS domain, the simulator with the insertion site among rocks and drums,
each rover's `identifier` and `stereo`, the team's `mapper` and `view_planner`, and the
`master` and `slave` of `coop_insertion` (`coop_bringup.rig.InsertionRig`), then runs:

1. identify: every rover identifies its base's dynamic parameters (`identify` action,
   information-optimal excitation);
2. map: the rovers map the work site together, each driving (on a path planned on the shared
   map) to the camera pose the view planner's `next_best_view` answers (maximum information)
   and looking from there, until the site's coverage reaches the target or `max_scans`;
3. place and 4. insert: the staging poses are driven to, then one `insert` goal: the master
   places its camera by `task_view` (phase 3) and the slave inserts the card (phase 4, the
   slave's arm model from its identified parameters).

Writes `report.md`, `report.json` and plots under `OUT/<run-id>/` (`coop_bringup.report`), with
every node's log in `logs/` and an MCAP bag of the run in `bag/` (`rover_bag record`; images,
stereo clouds and map snapshots only with `--bag-all`). `--live [PORT]` adds `coop_bringup
live_view`, a Foxglove WebSocket server (connect Foxglove to ws://localhost:8765).
"""
from __future__ import annotations

import argparse
import math
import os
import signal
import socket
import sys
import threading
import time
from dataclasses import asdict, dataclass, replace
from enum import StrEnum
from pathlib import Path
from typing import assert_never

import numpy as np
from geometry_msgs.msg import Point, PoseStamped
from nav_msgs.msg import OccupancyGrid, Odometry
from rclpy.node import Node
from scipy.spatial.transform import Rotation
from sensor_msgs.msg import JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_bringup.rig import (
    SITE_XY,
    InsertionRig,
    loop_nodes,
    mast_sweep,
    staging_poses,
    team_namespace,
    truth_readers,
)
from coop_common.cli import enum_choices, number
from coop_common.dynparams import PARAM_NAMES
from coop_common.lockstep_node import Lockstep
from coop_common.node_util import stamp
from coop_common.params import choice
from coop_common.provenance import source_revision
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.rover_geometry import (
    MAST_JOINTS,
    ReachError,
    camera_in_map,
    camera_mount,
    yaw_of,
)
from coop_common.testing import free_domain_id, isolate_ros_environment
from coop_id.excitation import Strategy
from coop_insertion.drive import GridSlice, grid_slice_of, path_length
from coop_insertion.driver_node import PARAMS as DRIVER_PARAMS
from coop_insertion.errors import InsertionError
from coop_msgs.action import DriveToPose, Identify, Insert
from coop_msgs.msg import DynamicParameters, ViewRating, VoxelMap
from coop_msgs.srv import MapFile, NextBestView
from coop_viewplan.frames import camera_pose
from coop_viewplan.grid import MapError, planning_grid
from coop_viewplan.nbv import (
    NextBestViewPlanner,
    PlanningError,
    StrategyName,
)
from coop_viewplan.offline import nbv_config
from coop_viewplan.params import PARAMS as VP_PARAMS

from .commander import Commander
from .graph import node_settings
from .mission_seeds import format_table as format_seeds
from .mission_seeds import parse_seeds, run_seeds
from .report import (
    MissionError,
    PhaseStatus,
    identification_errors,
    site_coverage,
    top_view,
    write_report,
)
from .routes import DriverRule, drivable_route


class PhaseName(StrEnum):
    """The mission's phases, in the order they run (place and insert: one insert goal)."""

    IDENTIFY = 'identify'
    MAP = 'map'
    PLACE = 'place'
    INSERT = 'insert'


PHASES = tuple(PhaseName)
#: a goal within an obstacle's clearance is reached by a straight last leg of at most this (m)
SNAP_M = 1.0
MASTER, SLAVE = 'rover1', 'rover2'
LIVE_PORT = 8765


@dataclass(frozen=True)
class MissionConfig:
    """The scenario and the phases' settings (the CLI flags of the same names)."""

    seed: int = 1
    occlusion_density: float = 0.05
    slot_in: float = 4.5
    rovers: int = 2
    phases: tuple[PhaseName, ...] = PHASES
    identify_s: float = 20.0
    identify_strategy: Strategy = Strategy.INFORMATION
    strategy: StrategyName = StrategyName.MAX_INFORMATION
    coverage_target: float = 0.9
    max_scans: int = 8
    sweep_s: float = 8.0              # scan 0: each rover sweeps its mast over its view (sim s)
    survey_s: float = 20.0            # the master's sweep over the site from its staging pose
    #                                   before the map is final (sim s; the table's rig's)
    site_half_m: float = 1.5
    insert_timeout_s: float = 120.0     # sim s, with room for the slave to relocate its card
    rough_site_m: float = 0.3         # the master's region: this far either side of a centre
    #                                   drawn from the seed (coop_bringup.rig.rough_site)
    max_force_n: float = 25.0
    stereo_rate_hz: float = 4.0
    near_start: bool = False          # the rovers start at their staging poses (short missions)
    bag: bool = True                  # record the run into OUT/<run-id>/bag (rover_bag record)
    bag_all: bool = False             # ... with the bulk streams too (mission.launch.py)
    live_port: int | None = None      # serve the live view (Foxglove WebSocket) on this port
    lockstep: bool = False            # the sim in lockstep with the nodes that close loops
    attach: bool = False              # the graph already launched on this domain, not ours
    team: str = ''                    # the namespace of the whole graph, on its own clock

    def __post_init__(self) -> None:
        if self.attach and (self.bag or self.live_port is not None):
            raise MissionError('an attached mission records and serves nothing itself: the '
                               "launch's record:= and live_view:= arguments do (give --no-bag, "
                               'no --live)')
        object.__setattr__(self, 'identify_strategy', choice(
            Strategy, self.identify_strategy, 'identify_strategy', error=MissionError))
        object.__setattr__(self, 'strategy', choice(StrategyName, self.strategy, 'strategy',
                                                    error=MissionError))
        object.__setattr__(self, 'team', team_namespace(self.team))
        bad = [p for p in self.phases if p not in PHASES]
        if bad:
            raise MissionError(f'unknown phases {bad}; choose from {", ".join(PHASES)}')
        object.__setattr__(self, 'phases', tuple(PhaseName(p) for p in self.phases))
        if self.rovers < 2:
            raise MissionError('the mission needs a master and a slave: rovers >= 2')
        if (PhaseName.INSERT in self.phases) != (PhaseName.PLACE in self.phases):
            raise MissionError("'place' and 'insert' run as one insert goal: both or neither")


@dataclass
class Phase:
    """One phase's row of the report: its status, why it is not ok, its wall and sim time."""

    name: PhaseName
    status: PhaseStatus = PhaseStatus.SKIPPED
    reason: str = ''
    wall_s: float | None = None
    sim_s: float | None = None


class Progress:
    """Phase, percent and ETA: a tqdm bar on a terminal, plain lines in a log."""

    def __init__(self, *, stream=sys.stderr) -> None:
        self.stream = stream
        self.tty = hasattr(stream, 'isatty') and stream.isatty()
        self.bar = None
        self._last = (None, -1)

    def start(self, phase: str) -> None:
        self.close()
        if self.tty:
            from tqdm import tqdm  # noqa: PLC0415 - only on a terminal
            self.bar = tqdm(total=100, desc=phase, file=self.stream, unit='%',
                            bar_format='{desc:>9}: {percentage:3.0f}%|{bar}| {postfix} '
                                       '[{elapsed}<{remaining}]')
        self._phase, self._t0 = phase, time.monotonic()

    def update(self, fraction: float, note: str = '') -> None:
        pct = round(100 * min(max(fraction, 0.0), 1.0))
        if self.bar is not None:
            self.bar.n = pct
            self.bar.set_postfix_str(note, refresh=True)
            return
        if (self._phase, pct // 10) == self._last:
            return
        self._last = (self._phase, pct // 10)
        el = time.monotonic() - self._t0
        eta = f'{el * (100 - pct) / pct:.0f} s' if pct > 0 else '?'
        print(f'[{self._phase}] {pct:3d} % (ETA {eta}) {note}', file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


class _MissionClient(Node):
    """The runner's view of the graph: odometry, masts, the map, truth (to judge by); the
    actions go through a Commander on this node."""

    def __init__(self, ctx, rovers: list[str], lockstep: bool = False, *,
                 map_frame: str = 'map') -> None:
        super().__init__('mission', context=ctx)
        self.map_frame = map_frame
        # in lockstep the masts' commands act in the simulator's rounds (docs/design.md)
        self.ls = Lockstep(self, lockstep)
        self.rovers = rovers
        self.lock = threading.Lock()
        self.odom: dict[str, tuple[float, float, float]] = {}
        self.mast: dict[str, tuple[float, float]] = {}
        self.paths: dict[str, list] = {r: [] for r in rovers}
        self.distance: dict[str, float] = dict.fromkeys(rovers, 0.0)
        self.truth: dict[str, DynamicParameters] = {}
        self.map: VoxelMap | None = None
        self.grid: GridSlice | None = None     # the drivers' map/grid (what they refuse)
        self.placement: ViewRating | None = None
        self.mast_cmd = {r: self.ls.publisher(JointTrajectory, f'{r}/mast/command',
                                              COMMAND_QOS) for r in rovers}
        self.save_map = self.create_client(MapFile, 'map/save')
        for r in rovers:
            self.ls.subscription(Odometry, f'{r}/odom', lambda m, r=r: self._on_odom(r, m),
                                 SENSOR_QOS)
            self.ls.subscription(JointState, f'{r}/joint_states',
                                 lambda m, r=r: self._on_joints(r, m), SENSOR_QOS)
            self.create_subscription(DynamicParameters, f'sim/{r}/parameters',
                                     lambda m, r=r: self.truth.__setitem__(r, m), LATCHED_QOS)
        self.create_subscription(VoxelMap, 'map/voxels', self._on_map, LATCHED_QOS)
        self.create_subscription(OccupancyGrid, 'map/grid', self._on_grid, LATCHED_QOS)
        self.create_subscription(ViewRating, f'{MASTER}/camera_placement',
                                 lambda m: setattr(self, 'placement', m), LATCHED_QOS)

    def _on_map(self, m: VoxelMap) -> None:
        self.map = m

    def _on_grid(self, m: OccupancyGrid) -> None:
        try:
            self.grid = grid_slice_of(m)
        except InsertionError as exc:
            self.get_logger().warning(f'map/grid: {exc}; skipped')

    def _on_joints(self, r: str, m: JointState) -> None:
        idx = {n: i for i, n in enumerate(m.name)}
        if all(n in idx for n in MAST_JOINTS) and len(m.position) == len(m.name):
            self.mast[r] = tuple(float(m.position[idx[n]]) for n in MAST_JOINTS)

    def _on_odom(self, r: str, m: Odometry) -> None:
        q = m.pose.pose.orientation
        yaw = yaw_of(q.x, q.y, q.z, q.w)
        x, y = m.pose.pose.position.x, m.pose.pose.position.y
        with self.lock:
            if r in self.odom:
                self.distance[r] += math.hypot(x - self.odom[r][0], y - self.odom[r][1])
            self.odom[r] = (x, y, yaw)
            p = self.paths[r]
            if not p or math.hypot(x - p[-1][0], y - p[-1][1]) > 0.05:
                p.append((x, y))

    def camera_pose(self, r: str) -> PoseStamped:
        """The camera's optical pose in the map from the rover's odometry and mast encoders."""
        cam = camera_in_map(*self.odom[r], *self.mast.get(r, (0.0, 0.0)))
        msg = PoseStamped()
        msg.header.frame_id = self.map_frame
        p, q = msg.pose.position, msg.pose.orientation
        p.x, p.y, p.z = (float(v) for v in cam[:3, 3])
        q.x, q.y, q.z, q.w = (float(v) for v in Rotation.from_matrix(cam[:3, :3]).as_quat())
        return msg

    def aim(self, r: str, pan: float, tilt: float, seconds: float = 0.6) -> None:
        tr = JointTrajectory(joint_names=list(MAST_JOINTS))
        pt = JointTrajectoryPoint(positions=[float(pan), float(tilt)])
        pt.time_from_start.sec, pt.time_from_start.nanosec = int(seconds), \
            int((seconds % 1) * 1e9)
        tr.points = [pt]
        self.mast_cmd[r].publish(tr)


class Mission:
    """One run of the mission; `run()` returns the report's dict (also written to disk)."""

    def __init__(self, cfg: MissionConfig, out: Path, *, run_id: str | None = None,
                 domain_id: int | None = None, progress: Progress | None = None,
                 log=print) -> None:
        self.cfg = cfg
        self.run_id = run_id or time.strftime('%Y%m%d-%H%M%S') + f'-{os.getpid()}'
        self.out = Path(out) / self.run_id
        self.out.mkdir(parents=True, exist_ok=False)
        self.domain_id = domain_id if domain_id is not None else free_domain_id()
        self.progress = progress or Progress()
        self.log = log
        self.rovers = [f'rover{i + 1}' for i in range(cfg.rovers)]
        # the view planner's settings, as the graph's node has them: the runner plans its
        # paths on the same grid
        self.view_planner = node_settings('view_planner')
        # the drivers refuse a path across a cell of map/grid they take for occupied: the
        # mission's paths keep off those cells by the drivers' own rule
        driver = {k: s.default for k, s in DRIVER_PARAMS.items()} | node_settings('driver')
        self.driver_rule = DriverRule(int(driver['occupied_threshold']),
                                      float(driver['start_clear_m']))
        self.phases = [Phase(p) for p in PHASES]
        self.rep: dict = {'run_id': self.run_id, 'config': {**asdict(cfg),
                                                           'phases': list(cfg.phases)},
                          'domain_id': self.domain_id, 'source': source_revision(),
                          'targets': {'identification_error': 0.15,
                                      'coverage': cfg.coverage_target, 'penetration_mm': 0.5},
                          'identification': {'mean_abs_rel_error': None},
                          'mapping': {'coverage': None},
                          'insertion': {'success': False, 'reason': 'not run'}}
        self.extras: dict = {}
        self.rig: InsertionRig | None = None

    # -- plumbing -----------------------------------------------------------------------------
    def _sim_t(self) -> float:
        return self.rig.node.clock

    def _wait(self, pred, timeout_s: float, what: str, tick=None, *, run: bool = True) -> None:
        """Wait (wall time) for pred(), failing at once when a node of the graph died. In
        lockstep the sim steps on meanwhile unless `run` is False (it stays where it is, held
        or running)."""
        if run and self.cfg.lockstep:
            self.rig.node.pacer.run()
        deadline = time.monotonic() + timeout_s
        while not pred():
            dead = self.rig.dead()
            if dead:
                raise MissionError(f'node {", ".join(dead)} died (logs in '
                                   f'{self.out / "logs"})')
            if time.monotonic() > deadline:
                raise MissionError(f'timed out after {timeout_s:.0f} s waiting for {what}')
            if tick is not None:
                tick()
            time.sleep(0.05)

    def _sim_wait(self, seconds: float, what: str = 'sim time') -> None:
        """Let `seconds` of sim time pass; in lockstep that many rounds, then hold the sim."""
        if self.cfg.lockstep:
            self.rig.sim_sleep(seconds)
            return
        t0 = self._sim_t()
        self._wait(lambda: self._sim_t() >= t0 + seconds, 60 + 20 * seconds, what)

    def _hold(self) -> None:
        """In lockstep: hold the sim while the runner decides (its next goal, a view)."""
        if self.cfg.lockstep:
            self.rig.hold()

    # -- the run ------------------------------------------------------------------------------
    def run(self) -> dict:
        cfg = self.cfg
        if cfg.attach:      # the launched graph's domain (tools/env.sh, ROS_DOMAIN_ID)
            self.domain_id = int(os.environ.get('ROS_DOMAIN_ID', '0'))
            self.rep['domain_id'] = self.domain_id
        else:
            isolate_ros_environment(self.domain_id)
        launch_args = self._launch_args()
        t_all = time.monotonic()
        failed = None
        interrupted = []

        def on_sigint(_sig, _frame) -> None:
            # the first Ctrl-C stops the mission; more while the graph shuts down are ignored,
            # so that every process started is stopped and the report written
            if not interrupted:
                interrupted.append(True)
                raise KeyboardInterrupt
            self.log('stopping the graph; the report follows')

        main_thread = threading.current_thread() is threading.main_thread()
        # SIGTERM (`timeout`, a supervisor) as Ctrl-C: the nodes run in their own sessions and
        # would outlive the runner, and the bag would stay unclosed
        previous = {s: signal.signal(s, on_sigint) for s in (signal.SIGINT, signal.SIGTERM)} \
            if main_thread else {}
        try:
            self.log(f'mission {self.run_id}: bringing up the graph (domain {self.domain_id}, '
                     f'logs in {self.out / "logs"})')
            with InsertionRig(seed=cfg.seed, occlusion_density=cfg.occlusion_density,
                              slot_in=cfg.slot_in, log_dir=self.out / 'logs',
                              domain_id=self.domain_id, stereo_rate_hz=cfg.stereo_rate_hz,
                              stereo_rovers=tuple(self.rovers), rovers=cfg.rovers,
                              launch_args=launch_args, lockstep=cfg.lockstep,
                              clients=('mission',), attach=cfg.attach,
                              rough_site_m=cfg.rough_site_m, team=cfg.team) as rig:
                self.rig = rig
                self.client = _MissionClient(rig.ctx, self.rovers, cfg.lockstep,
                                             map_frame=rig.map_frame)
                rig.add_node(self.client)
                self.commander = Commander(self.client, rig.ex, self.rovers,
                                           map_frame=rig.map_frame)
                if cfg.near_start:
                    rig.place(cfg.slot_in, np.random.default_rng(cfg.seed))
                if cfg.lockstep:
                    # rounds, not a wait that lets the sim run until the runner has seen the
                    # odometry: a phase starts at the same round on an idle or a busy machine
                    self._sim_wait(0.1, "every rover's odometry")
                self._wait(lambda: all(r in self.client.odom for r in self.rovers), 60,
                           "every rover's odometry", run=False)
                for ph in self.phases:
                    if ph.name not in cfg.phases:
                        ph.reason = 'not asked for'
                        continue
                    if failed is not None:
                        ph.reason = f'after {failed} failed'
                        continue
                    if ph.name is PhaseName.INSERT:
                        continue               # run with 'place' as one goal
                    self._run_phase(ph)
                    if ph.status is PhaseStatus.FAILED:
                        failed = ph.name
        except KeyboardInterrupt:
            for ph in self.phases:
                if ph.status is PhaseStatus.RUNNING:
                    ph.status, ph.reason = PhaseStatus.FAILED, 'interrupted (Ctrl-C)'
                elif (ph.status is PhaseStatus.SKIPPED and ph.name in cfg.phases
                      and not ph.reason):
                    ph.reason = 'interrupted (Ctrl-C)'
            self.rep['interrupted'] = True
        except (InsertionError, MissionError, TimeoutError) as exc:
            self.rep['error'] = str(exc)
            self.log(f'mission {self.run_id} stopped: {exc}')
            for ph in self.phases:
                if ph.status is PhaseStatus.RUNNING:
                    ph.status, ph.reason = PhaseStatus.FAILED, str(exc)
        finally:
            self.progress.close()
        self.rep['phases'] = [asdict(p) for p in self.phases]
        try:
            return self._finish(t_all)
        finally:
            if main_thread:
                for sig, handler in previous.items():
                    signal.signal(sig, handler)

    def _launch_args(self) -> dict[str, str]:
        """mission.launch.py's arguments beyond the rig's: the identifiers, the drivers, the
        recorder (stopped first, so that its bag is closed while the graph still runs) and the
        live view."""
        cfg = self.cfg
        args = {'identify': str(PhaseName.IDENTIFY in cfg.phases).lower(), 'driving': 'true'}
        if cfg.bag:
            args |= {'record': str((self.out / 'bag').resolve()),
                     'record_all': str(cfg.bag_all).lower()}
        if cfg.live_port is not None:
            args |= {'live_view': 'true', 'live_port': str(cfg.live_port)}
            self.log(f'live view: connect Foxglove to ws://localhost:{cfg.live_port}')
            self.rep['live_view'] = {'url': f'ws://localhost:{cfg.live_port}'}
        return args

    def _bag_summary(self) -> dict | None:
        """What the recorder left in bag/ (read back with rover_bag.bagio), for the report."""
        if not self.cfg.bag:
            return None
        path = self.out / 'bag'
        if not path.exists():
            return {'path': 'bag', 'error': "no bag written (see the recorder's log in logs/)"}
        from rover_bag.bagio import bag_info  # noqa: PLC0415 - only with a bag
        try:
            info = bag_info(path)
        except Exception as exc:  # noqa: BLE001 - a broken bag is reported, not raised
            return {'path': 'bag', 'error': f'{type(exc).__name__}: {exc}'}
        size = sum(f.stat().st_size for f in path.rglob('*') if f.is_file())
        return {'path': 'bag', 'closed': (path / 'metadata.yaml').exists(),
                'size_mb': size / 1e6, 'messages': info.message_count,
                'topics': sorted(info.topics), 'duration_s': info.duration_s,
                'all': self.cfg.bag_all, 'problems': list(info.problems)}

    def _finish(self, t_all: float) -> dict:
        cfg = self.cfg
        bag = self._bag_summary()
        if bag is not None:
            self.rep['bag'] = bag
        self.rep['wall_s'] = time.monotonic() - t_all
        self.rep['success'] = all(p.status is PhaseStatus.OK for p in self.phases
                                  if p.name in cfg.phases)
        md, _ = write_report(self.rep, self.out, **self.extras)
        self.log(f'report: {md}')
        return self.rep

    def _run_phase(self, ph: Phase) -> None:
        ph.status = PhaseStatus.RUNNING
        self.progress.start(ph.name)
        w0, s0 = time.monotonic(), self._sim_t()
        try:
            match ph.name:
                case PhaseName.IDENTIFY:
                    self._identify()
                case PhaseName.MAP:
                    self._map()
                case PhaseName.PLACE:
                    self._place_and_insert(ph)
                case PhaseName.INSERT:
                    raise AssertionError("'insert' runs with 'place', as one insert goal")
                case _:
                    assert_never(ph.name)
            ph.status = ph.status if ph.status is PhaseStatus.FAILED else PhaseStatus.OK
        except (MissionError, InsertionError, TimeoutError) as exc:
            ph.status, ph.reason = PhaseStatus.FAILED, str(exc)
            self.log(f'{ph.name} failed: {exc}')
        finally:
            self.progress.close()
            if ph.name is not PhaseName.PLACE:
                ph.wall_s, ph.sim_s = time.monotonic() - w0, self._sim_t() - s0

    # -- phase 1: identification ---------------------------------------------------------------
    def _identify(self) -> None:
        cfg, c = self.cfg, self.client
        cmd = self.commander
        missing = cmd.missing(cmd.identifiers, 60)
        if missing:
            raise MissionError(f'no {", ".join(missing)} identifier/identify action server')
        self._wait(lambda: all(r in c.truth for r in self.rovers), 60, "the sim's truth",
                   run=False)                     # latched: no round needed
        self.rig.render((), 0.0)                  # no one looks while the arms shake
        self._sim_wait(2.0, 'the rovers at rest')
        goal = Identify.Goal(strategy=cfg.identify_strategy, duration_s=cfg.identify_s)
        if cfg.lockstep:    # the round the rig holds the sim at: the goals are given there
            goal.stamp = stamp(self.rig.node.ls.stamp_s)
        tasks = {r: cmd.identify(r, goal) for r in self.rovers}
        self._wait(lambda: all(t.answered for t in tasks.values()), 30, 'the goals accepted',
                   run=False)
        for r, t in tasks.items():
            if not t.accepted:
                raise MissionError(f'{r}: identify goal rejected')
        t0 = self._sim_t()
        self._wait(lambda: all(t.done for t in tasks.values()), 120 + 40 * cfg.identify_s,
                   'the identification', tick=lambda: self.progress.update(
                       (self._sim_t() - t0) / cfg.identify_s,
                       f'{self._sim_t() - t0:.0f} of {cfg.identify_s:.0f} sim s'))
        out, errs = {}, []
        for r in self.rovers:
            result = tasks[r].result()
            t, e = c.truth[r], result.estimate
            row = identification_errors(
                dict(zip(t.names, t.values, strict=False)),
                dict(zip(e.names, e.values, strict=False)),
                dict(zip(e.names, e.std_devs, strict=False)),
                dict(zip(e.names, e.information_bits, strict=False)))
            row.update(success=bool(result.success), message=result.message,
                       samples=int(e.samples))
            out[r] = row
            if not result.success:
                raise MissionError(f'{r}: identification failed: {result.message}')
            errs.append(row['mean_abs_rel_error'])
        mean = float(np.mean(errs))
        self.rep['identification'] = {'rovers': out, 'mean_abs_rel_error': mean,
                                      'duration_s': cfg.identify_s,
                                      'strategy': cfg.identify_strategy,
                                      'parameters': list(PARAM_NAMES)}
        self.log('identify: mean abs. rel. error ' + ', '.join(
            f'{r} {100 * out[r]["mean_abs_rel_error"]:.1f} %' for r in self.rovers))

    # -- phase 2: mapping ----------------------------------------------------------------------
    def _grid(self):
        m = self.client.map
        p = {k: s.default for k, s in VP_PARAMS.items()} | self.view_planner
        keys = np.asarray(m.voxels.keys, np.int64)
        grid = planning_grid(keys, np.asarray(m.voxels.occupancy), m.resolution_m,
                             pad_m=p['pad_m'], ceiling_m=p['ceiling_m'],
                             camera_height_m=p['camera_height_m'],
                             max_cells=p['max_grid_cells'])
        return grid, NextBestViewPlanner(nbv_config(p)).traversability(grid), p

    def _coverage(self) -> float:
        m = self.client.map
        if m is None:
            return 0.0
        return site_coverage(np.asarray(m.voxels.keys), np.asarray(m.voxels.occupancy),
                             m.resolution_m,
                             centre_xy=SITE_XY, half_m=self.cfg.site_half_m)

    def _path(self, r: str, goal_xy, grid, trav, others: list, *, moving: tuple | list = (),
              last_leg: bool = True) -> list:
        """Waypoints from rover r's base to goal_xy on the map, round the other rovers, that
        its driver accepts (`coop_bringup.routes.drivable_route`)."""
        return drivable_route(trav, grid, self.client.odom[r][:2], goal_xy,
                              seen=self.client.grid, rule=self.driver_rule, others=others,
                              moving=moving, clearance_m=self.view_planner['clearance_m'],
                              snap_m=SNAP_M, last_leg=last_leg)

    def _drive(self, paths: dict[str, tuple[list, float]], what: str) -> list[str]:
        """Drive rovers along (waypoints, final heading) at once: a drive_to_pose goal each,
        given while the sim is held (in lockstep every driver starts at the same round); the
        rovers whose drive ended short (logged)."""
        c, cmd = self.client, self.commander
        missing = cmd.missing({r: cmd.drivers[r] for r in paths}, 60)
        if missing:
            raise MissionError(f'no {", ".join(missing)} drive_to_pose action server')
        self._hold()
        length = max(path_length(np.vstack([c.odom[r][:2], *wps]))
                     for r, (wps, _) in paths.items())
        tasks = {r: cmd.drive(r, wps[-1], yaw, via=wps[:-1]) for r, (wps, yaw) in paths.items()}
        try:
            self._wait(lambda: all(t.answered for t in tasks.values()), 30,
                       f'{what}: the goals accepted', run=False)
            refused = [r for r, t in tasks.items() if not t.accepted]
            if refused:
                raise MissionError(f'{what}: {", ".join(refused)} refused the drive goal')
            # the drivers' own limit is 30 s + 3x the path at 0.2 m/s of sim time
            self._wait(lambda: all(t.done for t in tasks.values()),
                       120 + 30 * (30.0 + 3 * length / 0.2), what)
        finally:
            for t in tasks.values():
                if not t.done:
                    t.cancel()
        for r, t in tasks.items():
            res = t.result()
            self.rep.setdefault('drives', []).append({
                'what': what, 'rover': r, 'error_code': int(res.error_code),
                'message': res.error_msg, 'driven_m': float(res.distance_driven),
                'remaining_m': float(res.distance_remaining),
                'sim_s': float(res.navigation_time_s)})
            if res.error_code != DriveToPose.Result.NONE:
                self.log(f'{what}: {r}: {res.error_msg}')
        return [r for r, t in tasks.items() if t.result().error_code != DriveToPose.Result.NONE]

    def _map(self) -> None:
        cfg, c = self.cfg, self.client
        if not self.commander.nbv.wait_for_service(timeout_sec=60):
            raise MissionError('no viewplan/next_best_view service')
        # both cameras range from here on, while the rovers drive too: with the pairs off on
        # the drives, three next-best-view scans of the default mission added nothing to the
        # site's coverage (75.9 % after scan 0, 1, 2 and 3): the views chosen look away from
        # the site, and what the site's coverage gained came from the drives past it
        self.rig.render(tuple(self.rovers), cfg.stereo_rate_hz)
        for r in self.rovers:             # scan 0: sweep the mast across the view at the start
            c.mast_cmd[r].publish(mast_sweep(cfg.sweep_s))
        self._sim_wait(cfg.sweep_s + 1.0, 'the first sweep')
        self._wait(lambda: c.map is not None, 60, 'the first map')
        scans = [{'scan': 0, 'coverage': self._coverage(),
                  'distance_m': float(sum(c.distance.values())),
                  'voxels': len(c.map.voxels.occupancy)}]
        self.progress.update(scans[0]['coverage'] / cfg.coverage_target, 'scan 0')
        for k in range(1, cfg.max_scans + 1):
            if scans[-1]['coverage'] >= cfg.coverage_target:
                break
            grid, trav, _ = self._grid()
            plans: dict[str, tuple[list, float]] = {}
            aims: dict[str, tuple[float, float]] = {}
            goals: list = []
            self._hold()
            for r in self.rovers:
                # the teammates where they stand and where this scan sends them: no view beside
                # one (the route would refuse it, and the rover would pan instead)
                others = [c.odom[o][:2] for o in self.rovers if o != r] + goals
                req = NextBestView.Request(robot=r, strategy=cfg.strategy,
                                           current_pose=c.camera_pose(r),
                                           teammates=[Point(x=float(xy[0]), y=float(xy[1]))
                                                      for xy in others])
                fut = self.commander.next_best_view(req)
                self._wait(fut.done, 120, f'{r} next best view', run=False)
                resp = fut.result()
                if not resp.success:
                    self.log(f'scan {k} {r}: no view ({resp.message}); panning')
                    pan, tilt = c.mast.get(r, (0.0, 0.2))
                    aims[r] = (pan + 0.7, tilt)
                    continue
                pos = resp.best.pose.pose.position
                q = resp.best.pose.pose.orientation
                xyz, yaw, pitch = camera_pose([pos.x, pos.y, pos.z], [q.x, q.y, q.z, q.w])
                try:
                    mount = camera_mount(xyz[:2], yaw, pitch)
                    wps = self._path(r, mount.base_xy, grid, trav, others)
                except (ReachError, PlanningError, MapError) as exc:
                    self.log(f'scan {k} {r}: view not reachable ({exc}); panning')
                    pan, tilt = c.mast.get(r, (0.0, 0.2))
                    aims[r] = (pan + 0.7, tilt)
                    continue
                goals.append(np.asarray(mount.base_xy))
                plans[r] = (wps, mount.base_yaw)
                aims[r] = (mount.pan, mount.tilt)
            if plans:
                self._drive(plans, f'scan {k} drive')
            for r, (pan, tilt) in aims.items():
                c.aim(r, pan, tilt)
            seq = c.map.sequence
            self._sim_wait(2.0, 'the scans')
            self._wait(lambda s=seq: c.map.sequence > s, 60, 'the map fused')
            scans.append({'scan': k, 'coverage': self._coverage(),
                          'distance_m': float(sum(c.distance.values())),
                          'voxels': len(c.map.voxels.occupancy)})
            self.progress.update(scans[-1]['coverage'] / cfg.coverage_target,
                                 f'scan {k}: {100 * scans[-1]["coverage"]:.0f} % seen')
            self.log(f'map: scan {k}: coverage {100 * scans[-1]["coverage"]:.1f} %, '
                     f'{scans[-1]["distance_m"]:.1f} m driven')
        cov = scans[-1]['coverage']
        m = c.map
        self.rep['mapping'] = {'coverage': cov, 'target': cfg.coverage_target,
                               'scans': scans, 'scans_taken': len(scans) - 1,
                               'distance_m': scans[-1]['distance_m'],
                               'strategy': cfg.strategy, 'site_centre': list(SITE_XY),
                               'site_half_m': cfg.site_half_m, 'voxels': len(m.voxels.occupancy)}
        keys = np.asarray(m.voxels.keys, np.int64).reshape(-1, 3)
        occ = np.asarray(m.voxels.occupancy)
        self.extras['top_view'] = top_view(keys, occ, m.resolution_m, centre_xy=SITE_XY,
                                           half_m=cfg.site_half_m)
        self.extras['occupied_points'] = (keys[occ >= 0.5] + 0.5) * m.resolution_m
        fut = c.save_map.call_async(MapFile.Request(path=str((self.out / 'team.cmap')
                                                             .resolve())))
        self._wait(fut.done, 60, 'the map saved')
        if not fut.result().success:
            self.log(f'map/save: {fut.result().message}')
        if cov < cfg.coverage_target:
            raise MissionError(f'coverage {100 * cov:.1f} % after {cfg.max_scans} scans, '
                               f'below the {100 * cfg.coverage_target:.0f} % target')

    # -- phases 3 and 4: placement and insertion -----------------------------------------------
    def _stage(self) -> None:
        """Drive the slave to its start short of the slot and the master beside the site."""
        c, rig = self.client, self.rig
        if c.map is None:
            raise MissionError('no map to plan the approach on (run the map phase)')
        grid, trav, _ = self._grid()
        poses = staging_poses(self.cfg.slot_in)
        slave_xy, master_xy = poses[SLAVE][:2], poses[MASTER][:2]
        # a straight last leg to a staging pose close to the site may cross a cell map/grid
        # holds occupied (planned so, or found so by the driver): then to the nearest navigable
        # cell, from which the slave's approach (the master's placement) goes on
        short = [SLAVE, MASTER]
        for last_leg in (True, False):
            # the slave's path keeps off where the master stands now, not its goal: the master
            # leaves for its own staging pose meanwhile
            targets = {SLAVE: (slave_xy, [master_xy], [c.odom[MASTER][:2]], poses[SLAVE][2]),
                       MASTER: (master_xy, [slave_xy], [], poses[MASTER][2])}
            plans = {}
            for r in short:
                xy, others, moving, yaw = targets[r]
                for leg in dict.fromkeys((last_leg, False)):   # the last leg, then without
                    try:
                        plans[r] = (self._path(r, xy, grid, trav, others, moving=moving,
                                               last_leg=leg), yaw)
                        break
                    except PlanningError as exc:
                        why = exc
                        if leg:
                            self.log(f'to the staging poses: {r}: {exc}; to the navigable '
                                     'cell nearest its staging pose')
                else:
                    raise MissionError(f'no path for {r} from {np.round(c.odom[r][:2], 2)} '
                                       f'to its staging pose {np.round(xy, 2)}: {why}') from why
            short = self._drive(plans, 'to the staging poses' if last_leg else
                                'to the navigable cells nearest the staging poses')
            if not short:
                break
            grid, trav, _ = self._grid()
        rig.set_slot(self.cfg.slot_in)

    def _place_and_insert(self, place: Phase) -> None:
        insert = next(p for p in self.phases if p.name is PhaseName.INSERT)
        w0, s0 = time.monotonic(), self._sim_t()        # the place phase: staging onwards
        self.progress.update(0.0, 'to the staging poses')
        self.rig.render((), 0.0)
        self._stage()
        # the master looks over the site from its staging pose before the map is final, as
        # the table's rig does: the exploration sees the site from afar, and its front, where
        # the camera is placed, can stay unknown (then task_view finds no free pose within
        # the markers' range of any search point, and the slot is not found)
        self.progress.update(0.2, 'surveying the site')
        self.rig.render((MASTER,), self.cfg.stereo_rate_hz)
        self.rig.survey(seconds=self.cfg.survey_s)
        # every node of the graph is up (the stereo nodes until the next line): the loop
        # nodes' subscriptions to the simulator's truth, none when truth only judges
        subs = self.rig.subscriptions()
        self.rep['truth_apart'] = {'nodes': len(subs), 'loop_nodes': loop_nodes(subs),
                                   'truth_readers': truth_readers(subs)}
        # and, in a team's namespace, no name of the team's nodes crosses to another's
        self.rep['names_apart'] = {'team': self.cfg.team, 'stray': self.rig.stray_names()}
        # the map is final: ranging on would map the slave's arm and card over the slot as an
        # obstacle at the task (the master's re-placement asks task_view again mid-insertion)
        self.rig.stop_mapping()
        self.rig.render((MASTER,), self.cfg.stereo_rate_hz)      # the master watches the task
        phase = {'insert_at': None}

        def watch() -> None:
            fb = self.rig.feedback
            if fb is None:
                return
            if phase['insert_at'] is None and fb.phase > Insert.Feedback.PHASE_PLACE_CAMERA:
                phase['insert_at'] = (time.monotonic(), self._sim_t())
                self.progress.start('insert')
            if phase['insert_at'] is None:
                self.progress.update(0.5, 'placing the camera')
            else:
                self.progress.update(fb.phase / Insert.Feedback.PHASE_DONE,
                                     f'error {1e3 * fb.displacement_error_m:.0f} mm')

        attempt = self._run_insert(watch)
        ins_w, ins_s = phase['insert_at'] or (time.monotonic(), self._sim_t())
        place.wall_s, place.sim_s = ins_w - w0, ins_s - s0
        insert.wall_s, insert.sim_s = time.monotonic() - ins_w, self._sim_t() - ins_s
        pl = self.client.placement
        if pl is not None:
            p, q = pl.pose.pose.position, pl.pose.pose.orientation
            _, yaw, pitch = camera_pose([p.x, p.y, p.z], [q.x, q.y, q.z, q.w])
            target = np.array([3.0572, 0.15, 0.5])
            self.rep['placement'] = {
                'position': [p.x, p.y, p.z], 'yaw_deg': math.degrees(yaw),
                'pitch_deg': math.degrees(pitch),
                'distance_to_target_m': float(np.linalg.norm(np.array([p.x, p.y, p.z]) -
                                                             target)),
                **{k: _finite(getattr(pl, k)) for k in (
                    'rating', 'depth_of_field', 'resolution', 'field_visibility',
                    'angular_visibility', 'collision_probability')}}
        self.rep['insertion'] = {
            'success': bool(attempt.success), 'action_success': attempt.action_success,
            'reason': attempt.reason, 'seated': attempt.seated,
            'max_penetration_mm': attempt.max_penetration_mm,
            'peak_force_n': attempt.peak_force_n, 'sim_s': attempt.sim_s,
            'frames': attempt.frames, 'fixes': attempt.fixes,
            'replacements': attempt.replacements, 'align_mm': attempt.align_mm,
            'align_tilt_deg': attempt.align_tilt_deg, 'rough_site': attempt.rough_site,
            'search_views': attempt.search_views, 'site_error_mm': attempt.site_error_mm}
        self.extras['insertion_curves'] = attempt.curves
        self.extras['paths'] = {r: list(p) for r, p in self.client.paths.items()}
        reached = phase['insert_at'] is not None
        place.status = PhaseStatus.OK if reached else PhaseStatus.FAILED
        place.reason = '' if reached else attempt.reason
        insert.status = PhaseStatus.OK if attempt.success else (
            PhaseStatus.FAILED if reached else PhaseStatus.SKIPPED)
        insert.reason = '' if attempt.success else (attempt.reason if reached else
                                                    'after place failed')

    def _run_insert(self, tick):
        stop = threading.Event()

        def ticker() -> None:
            while not stop.wait(0.5):
                tick()

        th = threading.Thread(target=ticker, daemon=True)
        th.start()
        try:
            return self.rig.insert(slot_in=self.cfg.slot_in, placement='optimal',
                                   seed=self.cfg.seed,
                                   timeout_s=self.cfg.insert_timeout_s,
                                   max_force_n=self.cfg.max_force_n)
        finally:
            stop.set()
            th.join(timeout=2)


def _finite(v: float) -> float | None:
    return float(v) if math.isfinite(v) else None


def _port_free(port: int) -> bool:
    with socket.socket() as s:
        try:
            s.bind(('127.0.0.1', port))
        except OSError:
            return False
    return True


def main(argv: list[str] | None = None) -> int:
    """`ros2 run coop_bringup mission`: run the mission (or its seeds) and write the report."""
    p = argparse.ArgumentParser(
        prog='mission', description=__doc__.split('\n\n')[0],
        formatter_class=argparse.RawDescriptionHelpFormatter)
    d = MissionConfig()
    p.add_argument('--out', type=Path, default=Path('out'),
                   help='the report goes to OUT/<run-id>/ (default out)')
    p.add_argument('--run-id', default=None, help='default: date-time-pid')
    p.add_argument('--seed', type=number(int, lo=0), default=d.seed)
    p.add_argument('--seeds', default=None, metavar='A-B[,C]',
                   help='run the mission once per seed (OUT/<run-id>/seed_<k>/, the run id '
                        "'seeds' by default; seeds already reported are read back) and print "
                        'their table (coop_bringup.mission_seeds)')
    p.add_argument('--occlusion-density', type=number(float, lo=0.0, hi=0.5),
                   default=d.occlusion_density)
    p.add_argument('--slot-in', type=number(float, lo=4.26, hi=6.0), default=d.slot_in,
                   help='slot width (in): 5.0 easy, 4.5 medium, 4.375 hard')
    p.add_argument('--rovers', type=number(int, lo=2, hi=4), default=d.rovers)
    p.add_argument('--phases', default=','.join(d.phases),
                   help=f'comma-separated, of {",".join(PHASES)} (place and insert together)')
    p.add_argument('--identify-s', type=number(float, lo=1.0), default=d.identify_s)
    p.add_argument('--coverage', type=number(float, lo=0.0, hi=1.0),
                   default=d.coverage_target, help='work-site coverage target')
    p.add_argument('--max-scans', type=number(int, lo=0), default=d.max_scans)
    p.add_argument('--strategy', default=d.strategy.value,
                   choices=enum_choices(StrategyName),
                   help='exploration strategy of next_best_view')
    p.add_argument('--survey-s', type=number(float, lo=1.0, hi=120.0), default=d.survey_s,
                   help="the master's sweep over the site before the map is final (sim s)")
    p.add_argument('--insert-timeout', type=number(float, lo=1.0), default=d.insert_timeout_s)
    p.add_argument('--rough-site', type=number(float, lo=0.0, hi=2.0), default=d.rough_site_m,
                   help="the master's region: this far (m) either side of a centre drawn "
                        'from the seed within as far of the slot')
    p.add_argument('--near-start', action='store_true',
                   help='start the rovers at their staging poses by the site (a short mission)')
    p.add_argument('--no-bag', dest='bag', action='store_false',
                   help='do not record the run into OUT/<run-id>/bag')
    p.add_argument('--bag-all', action='store_true',
                   help='record the images, stereo clouds and map snapshots too (tens of MB '
                        'per sim second)')
    p.add_argument('--live', nargs='?', type=number(int, lo=1, hi=65535), const=LIVE_PORT,
                   default=None, metavar='PORT',
                   help=f'serve the live view for Foxglove on ws://localhost:PORT '
                        f'(default {LIVE_PORT})')
    p.add_argument('--lockstep', action='store_true',
                   help='the simulator in lockstep with the nodes that close loops on it: the '
                        'same outcome on an idle and on a busy machine (docs/design.md)')
    p.add_argument('--attach', action='store_true',
                   help='run the phases against the graph already launched on this ROS domain '
                        '(ros2 launch coop_bringup mission.launch.py with the same seed and '
                        "slot, and with --lockstep: lockstep:=true clients:='insertion_rig "
                        "mission'); implies --no-bag")
    p.add_argument('--domain-id', type=number(int, lo=0, hi=232), default=None,
                   help='the ROS domain of the run (default: one of 1..100 that no DDS '
                   'participant on this machine holds)')
    p.add_argument('--team', default=d.team, metavar='NAME',
                   help="the graph's namespace, on the team's own clock (mission.launch.py's "
                        'team:= and clock:=team): missions side by side in one domain '
                        '(--domain-id)')
    a = p.parse_args(argv)
    if a.attach:
        if a.domain_id is not None or a.seeds is not None or a.live is not None:
            p.error('--attach runs on the launched graph: no --domain-id, --seeds or --live')
        a.bag = False
    if a.live is not None and not _port_free(a.live):
        p.error(f'--live: port {a.live} is in use (another live view?); give another PORT')
    try:
        cfg = MissionConfig(seed=a.seed, occlusion_density=a.occlusion_density,
                            slot_in=a.slot_in, rovers=a.rovers,
                            phases=tuple(x for x in a.phases.split(',') if x),
                            identify_s=a.identify_s, coverage_target=a.coverage,
                            max_scans=a.max_scans, strategy=a.strategy,
                            survey_s=a.survey_s,
                            insert_timeout_s=a.insert_timeout, near_start=a.near_start,
                            rough_site_m=a.rough_site,
                            bag=a.bag, bag_all=a.bag_all, live_port=a.live,
                            lockstep=a.lockstep, attach=a.attach, team=a.team)
        if a.seeds is not None:
            return _run_seeds(cfg, parse_seeds(a.seeds), a.out / (a.run_id or 'seeds'),
                              domain_id=a.domain_id)
        mission = Mission(cfg, a.out, run_id=a.run_id, domain_id=a.domain_id)
    except (MissionError, FileExistsError) as exc:
        p.error(str(exc))
    rep = mission.run()
    return 0 if rep['success'] else 1


def _run_seeds(cfg: MissionConfig, seeds: list[int], out: Path, *,
               domain_id: int | None) -> int:
    def run_one(seed: int, run_id: str) -> dict:
        return Mission(replace(cfg, seed=seed), out, run_id=run_id, domain_id=domain_id).run()

    out.mkdir(parents=True, exist_ok=True)
    rows = run_seeds(seeds, run_one, out, log=lambda m: print(m, file=sys.stderr, flush=True))
    print(format_seeds(rows))
    return 0 if all(r['all'] for r in rows) else 1


if __name__ == '__main__':
    raise SystemExit(main())
