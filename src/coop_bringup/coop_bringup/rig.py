"""The insertion through the whole graph (the graph test and `table_5_1` share it): the
installed `rover_sim sim` with the insertion site, rover 1's `coop_mapping stereo`, the team's
`mapper` and `view_planner`, and `coop_insertion master` / `slave`, on a private ROS domain.

`InsertionRig.survey()` builds the map the master plans on with the mapping pipeline (rover 1
looks over the site from its start, panning its mast); `attempt()` resets the sim to a slot
width and start poses, sends one `insert` goal and returns its result with the simulator's truth
(seated, deepest penetration into the jaws while the goal ran) and the curves of Figs. 5-13 /
5-14 (displacement and angular error against time, the F/T force after contact).
"""
from __future__ import annotations

import contextlib
import math
import re
import shutil
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path

import numpy as np
import rclpy
import yaml
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.parameter_client import AsyncParameterClient
from rosgraph_msgs.msg import Clock
from scipy.spatial.transform import Rotation
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.dynparams import load_truth
from coop_common.lockstep_node import Lockstep, Pacer, stamp_of
from coop_common.params import choice
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.rover_geometry import MAST_JOINTS, joint2_in_base
from coop_common.testing import isolate_ros_environment, wait_for
from coop_msgs.action import Insert
from coop_msgs.msg import ContactState, VoxelMap
from coop_msgs.srv import SimScenario
from coop_viewplan.frames import optical_quaternion
from rover_sim.config import is_truth_topic

from .commander import Commander
from .graph import LaunchedGraph, mission_launch_file
from .report import MissionError

#: the nodes that one `coop_bringup compose` process runs with composed=True (mission.launch.py)
COMPOSED = ('master', 'slave', 'mapper', 'view_planner')

INCH = 0.0254
SITE_XY = (3.0, 0.0)            # rover_sim's site: the near jaw's inner face at x = 3.0
SITE_TOP_M = 0.40
#: the slave's arm mount from its c.g. (r_2) as a calibration of the rover gives it: the truth
#: with this 1-sigma error per axis (m), drawn per rig from its seed (the rig runs no
#: identifier; the mission's slave takes r_2 from its own)
CALIBRATION_SIGMA_M = 0.005
#: the master is told the slot is within this far (m) either side of a centre drawn per attempt
#: uniformly within as far of the slot's true mouth (along x and y: the site stands on the
#: ground, its top at SITE_TOP_M)
ROUGH_SITE_M = 0.3
#: the slave starts with its card this far short of the slot (the arm outstretched clears the
#: near jaw), its base a little off the slot's line and heading
SLAVE_START_SHORT_M = 0.55
#: the master's start, beside the site on the markers' side, looking at it
MASTER_START = (2.2, 1.4, -1.0)


#: an attempt counts as seated when the simulator's truth said so within the goal's last
#: this many sim seconds
SEATED_WINDOW_S = 0.5
#: lockstep: the sim time of one round (the sim's lockstep_period_s); the launch file makes
#: the master and the slave participants, and this rig's client is one (it holds the sim
#: between its steps)
ROUND_S = 0.01
CLIENT = 'insertion_rig'
#: lockstep: the survey's frames are all in the map once it has not changed for this long (s)
MAP_QUIET_S = 3.0
#: lockstep: the longest wall time the survey waits for the stereo node to range one frame (s)
FRAME_WAIT_S = 30.0
#: the longest wall time the rig waits for one insert goal's result (s)
RESULT_WALL_S = 4 * 3600.0
#: the sim counts as stalled when its /clock has not advanced for this many wall seconds (a
#: loaded machine runs the rendering sim at a real-time factor near 0.1: the clock still moves)
STALL_S = 90.0
#: the longest wall time a recorder has to close its bag at the end (s)
STOP_RECORD_S = 60.0


#: a team's namespace (mission.launch.py's team:=)
TEAM_NAME = re.compile(r'[A-Za-z]\w*(/[A-Za-z]\w*)*')
def team_namespace(team: str) -> str:
    """A team's namespace as mission.launch.py's team:= takes it (no leading or trailing /;
    '' for the root), or MissionError with the rule."""
    name = team.strip('/')
    if name and not TEAM_NAME.fullmatch(name):
        raise MissionError(f'team {team!r}: a namespace of letters, digits and _ (each level '
                           'starting with a letter)')
    return name


#: the names every node has outside its namespace: ROS 2's own, and the transform tree, one
#: for the whole graph as tf2 has it (a team's frames carry the team's prefix)
SHARED_NAMES = ('/rosout', '/parameter_events', '/tf', '/tf_static')

def team_nodes(node: Node, team: str) -> list[tuple[str, str]]:
    """(name, namespace) of every node `node` discovers in namespace `team` or below it (the
    root, '/' or '': every node of the domain)."""
    team = team.rstrip('/')
    return [(n, ns) for n, ns in node.get_node_names_and_namespaces()
            if not team or ns == team or ns.startswith(f'{team}/')]


def names_of(node: Node, name: str, ns: str, *, publishers: bool = False) -> list[str] | None:
    """The topics one node subscribes to (and with `publishers`, publishes), sorted; None when
    it left the graph meanwhile."""
    try:
        got = node.get_subscriber_names_and_types_by_node(name, ns)
        if publishers:
            got += node.get_publisher_names_and_types_by_node(name, ns)
    except Exception:  # noqa: BLE001 - rclpy's NodeNameNonExistentError: it left
        return None
    return sorted({t for t, _ in got})


def stray_names(node: Node, team: str) -> dict[str, list[str]]:
    """Of the nodes in namespace `team` (full name), the topics each publishes or subscribes
    to outside it (SHARED_NAMES aside): empty when no name crosses to another team in the
    domain, or at the root, where none can."""
    team = team.rstrip('/')
    if not team:
        return {}
    out = {}
    for name, ns in team_nodes(node, team):
        stray = [t for t in names_of(node, name, ns, publishers=True) or ()
                 if not t.startswith(f'{team}/') and t not in SHARED_NAMES]
        if stray:
            out[f'{ns.rstrip("/")}/{name}'] = stray
    return out


#: the nodes that close the insertion's and the mission's loops (by their names, in any
#: namespace): none may read the simulator's truth (truth_readers)
LOOP_NODES = ('master', 'slave', 'identifier', 'driver', 'stereo', 'mapper', 'view_planner')


def loop_nodes(names) -> list[str]:
    """Of nodes' full names, those of loop nodes (LOOP_NODES), sorted."""
    return sorted(n for n in names if n.rsplit('/', 1)[-1] in LOOP_NODES)


def truth_readers(subscriptions: dict[str, list[str]]) -> dict[str, list[str]]:
    """Of a graph's subscriptions (node's full name -> topics, InsertionRig.subscriptions),
    the loop nodes' subscriptions to the simulator's truth (rover_sim.config.is_truth_topic)
    and to /tf (which carries it with the simulator's truth_tf): empty when truth only judges."""
    out = {}
    for node in loop_nodes(subscriptions):
        truth = [t for t in subscriptions[node] if is_truth_topic(t) or t == '/tf']
        if truth:
            out[node] = truth
    return out


def slot_centre_x(slot_in: float) -> float:
    """The slot's centre line in the map (x, m) for a slot `slot_in` inches wide: rover_sim's
    site, its near jaw's inner face at SITE_XY."""
    return SITE_XY[0] + slot_in * INCH / 2


class SimStalled(MissionError):
    """The simulator's clock stopped advancing; `stack_file` holds its threads' stacks when
    gdb could read them."""

    def __init__(self, message: str, stack_file: Path | None = None) -> None:
        super().__init__(message)
        self.stack_file = stack_file


def mast_sweep(seconds: float) -> JointTrajectory:
    """A mast trajectory over `seconds` that pans across the view twice: looking down (the
    ground and the site) and nearly level (the layer a master's camera stands in, in front of
    the site), for the map a camera is placed in."""
    tr = JointTrajectory(joint_names=list(MAST_JOINTS))
    n = 6
    sweep = [(-0.8 + 1.6 * k / n, 0.35) for k in range(n + 1)] + \
        [(0.8 - 1.6 * k / n, 0.08) for k in range(n + 1)]
    for k, pos in enumerate(sweep):
        pt = JointTrajectoryPoint(positions=list(pos))
        t = seconds * (k + 0.5) / len(sweep)
        pt.time_from_start.sec, pt.time_from_start.nanosec = int(t), int((t % 1) * 1e9)
        tr.points.append(pt)
    return tr


def rough_site(slot_in: float, seed: int, half_width_m: float = ROUGH_SITE_M) -> list[float]:
    """The centre of the region the master is told the slot's mouth is in, for an attempt's
    `seed`: the true mouth moved by a uniform draw within `half_width_m` along x and y."""
    d = np.random.default_rng([seed, 3]).uniform(-half_width_m, half_width_m, 2)
    return [round(slot_centre_x(slot_in) + float(d[0]), 4), round(SITE_XY[1] + float(d[1]), 4),
            SITE_TOP_M]


def calibrated_r2(seed: int) -> list[float]:
    """The slave's r_2 as a calibration gives it (CALIBRATION_SIGMA_M), for the rig's `seed`."""
    rng = np.random.default_rng([seed, 2])
    return [round(float(v), 5) for v in
            load_truth().cg_to_arm + rng.normal(0.0, CALIBRATION_SIGMA_M, 3)]


def staging_poses(slot_in: float, rng: np.random.Generator | None = None, *,
                  master: tuple[float, float, float] = MASTER_START,
                  slave_short_m: float = SLAVE_START_SHORT_M
                  ) -> dict[str, tuple[float, float, float]]:
    """Where an insertion starts, (x, y, heading) per rover: the master at `master` (beside
    the site), the slave with its card `slave_short_m` short of the slot; with `rng`,
    perturbed (the slave by up to 3 cm along, 2 cm across and 0.05 rad)."""
    j2 = joint2_in_base(load_truth().cg_to_arm)
    sx = slot_centre_x(slot_in)
    d = rng.uniform([-0.03, -0.02, -0.05], [0.03, 0.02, 0.05]) if rng is not None \
        else np.zeros(3)
    return {'rover1': master,
            'rover2': (float(sx - 0.30 - j2[0] - slave_short_m + d[0]),
                       float(SITE_XY[1] - j2[1] + d[1]), float(d[2]))}


class Placement(StrEnum):
    """The placements an attempt can ask the master for (coop_msgs/action/Insert's
    PLACEMENT_*): 'given' pins the camera pose an attempt names."""

    OPTIMAL = 'optimal'
    RANDOM = 'random'
    RANDOM_FIXED = 'random_fixed'
    GIVEN = 'given'


#: each placement's constant in the Insert goal
PLACEMENTS = {Placement.OPTIMAL: Insert.Goal.PLACEMENT_OPTIMAL,
              Placement.RANDOM: Insert.Goal.PLACEMENT_RANDOM,
              Placement.RANDOM_FIXED: Insert.Goal.PLACEMENT_RANDOM_FIXED,
              Placement.GIVEN: Insert.Goal.PLACEMENT_GIVEN}


@dataclass
class Attempt:
    """One insertion attempt on the rig: the truth's verdict, the action's result, what vision
    saw, and the curves."""

    slot_in: float
    placement: Placement
    seed: int
    success: bool                  # the simulator's truth: seated, penetration within limit
    action_success: bool
    reason: str
    seated: bool
    max_penetration_mm: float
    peak_force_n: float
    duration_s: float
    sim_s: float
    frames: int = 0                # stereo pairs the master looked at while the slave ran
    fixes: int = 0                 # of them, those with a labelled fix
    replacements: int = 0
    #: the truth when the slave began its descent (aligned by vision), or when it touched
    #: first if it never descended: the card's centre across the slot from the slot's centre
    #: line (mm) and its tilt in the insertion plane (deg); None: it got to neither
    align_mm: float | None = None
    align_tilt_deg: float | None = None
    #: the region's centre the master was given (map, m), the views it looked for the slot
    #: from, and how far the site it located lay from the true mouth (mm; None: not located)
    rough_site: list | None = None
    search_views: int = 0
    site_error_mm: float | None = None
    curves: dict = field(default_factory=dict)

    @property
    def fix_rate(self) -> float | None:
        return self.fixes / self.frames if self.frames else None


class _Client(Node):
    def __init__(self, ctx: Context, lockstep: bool) -> None:
        super().__init__('insertion_rig', context=ctx)
        self.clock = 0.0
        self.clock_wall = time.monotonic()      # when the clock last advanced
        self.elapsed = 0.0                      # sim s the clock advanced, across resets
        # the truth while an attempt runs: (stamp, seated, deepest penetration m)
        self.contact: list[tuple[float, bool, float]] = []
        self.recording = False
        self.map_voxels = 0
        # the stamp of the last frame rover 1's stereo node ranged (its camera pose's)
        self.ranged_t = -math.inf
        self.ls = Lockstep(self, lockstep)
        # lockstep: the rig holds the sim between the steps of an experiment
        self.pacer = Pacer(self.ls)
        self.create_subscription(Clock, '/clock', self._on_clock, 10)
        self.ls.subscription(ContactState, 'sim/rover2/contact', self._on_contact, SENSOR_QOS)
        # the card's true pose while an attempt runs: (stamp, centre x, tilt in the insertion
        # plane, rad)
        self.card: list[tuple[float, float, float]] = []
        self.ls.subscription(PoseStamped, 'sim/rover2/card_pose', self._on_card, SENSOR_QOS)
        self.create_subscription(VoxelMap, 'map/voxels', self._on_map, LATCHED_QOS)
        self.create_subscription(PoseWithCovarianceStamped, 'rover1/camera_pose',
                                 self._on_ranged, LATCHED_QOS)
        self.reset = self.create_client(SimScenario, 'sim/reset')
        self.mast = self.ls.publisher(JointTrajectory, 'rover1/mast/command', COMMAND_QOS)

    def _on_clock(self, m: Clock) -> None:
        t = m.clock.sec + 1e-9 * m.clock.nanosec
        if t > self.clock:
            self.clock_wall = time.monotonic()
            self.elapsed += t - self.clock
        self.clock = t          # a reset starts the clock again from 0

    def _on_ranged(self, m: PoseWithCovarianceStamped) -> None:
        self.ranged_t = stamp_of(m)

    def _on_map(self, m: VoxelMap) -> None:
        self.map_voxels = int(sum(m.contributions))

    def _on_card(self, m: PoseStamped) -> None:
        if self.recording:
            q = m.pose.orientation
            # the card's width axis (its x) in the map: its tilt out of the horizontal
            axis = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()[:, 0]
            self.card.append((stamp_of(m), m.pose.position.x,
                              math.atan2(axis[2], abs(axis[0]))))

    def _on_contact(self, m: ContactState) -> None:
        if self.recording:
            self.contact.append((stamp_of(m), bool(m.seated), float(m.max_penetration_m)))


class InsertionRig(contextlib.AbstractContextManager):
    """The graph for insertion attempts. real_time_factor: the sim's pace, sim seconds per wall
    second (1: the nodes see the sensors' streams as a rover's; a sim let run faster than the
    nodes keep up with, 0, drops their samples: the identifier's excitation and the slave's
    200 Hz servo then answer late in sim time); image size: the master's stereo (the 0.25 in
    slot markers need 640 x 480)."""

    def __init__(self, *, seed: int = 1, occlusion_density: float = 0.05,
                 slot_in: float = 5.0, log_dir: Path | None = None, domain_id: int | None = None,
                 image_width: int = 640, image_height: int = 480, stereo_rate_hz: float = 4.0,
                 real_time_factor: float = 1.0, site_map: Path | None = None,
                 overrides: dict[str, dict] | None = None, planner: bool = True,
                 stereo_rovers: tuple[str, ...] = ('rover1',), rovers: int = 2,
                 render_workers: int = 1, lockstep: bool = True, round_s: float = ROUND_S,
                 master_start: tuple[float, float, float] = MASTER_START,
                 slave_start_short_m: float = SLAVE_START_SHORT_M,
                 composed: bool = False, clients: tuple[str, ...] = (),
                 launch_args: dict[str, str] | None = None,
                 rough_site_m: float = ROUGH_SITE_M, attach: bool = False,
                 team: str = '') -> None:
        """The graph is coop_bringup's mission.launch.py (its nodes' settings in
        config/mission.yaml), started through launch's Python API (coop_bringup.graph) with
        this rig's scenario as its arguments. stereo_rovers: whose stereo pairs the sim
        renders and (with the planner: the mapper and the view planner) a `stereo` node
        ranges into the map; overrides: node name -> parameters over the file's (tests);
        render_workers: the sim's (1: the right eye drawn by a second process); lockstep: the
        sim steps no round before the master, the slave and this rig have answered the last
        (docs/design.md): the same attempt on an idle and on a busy machine, in rounds of
        round_s (the slave's command period by default); master_start, slave_start_short_m:
        where place() stands the rovers (staging_poses); composed: the master, the slave, the
        mapper and the view planner in one process (`coop_bringup compose`), not one each;
        clients: lockstep participants besides the graph's nodes and this rig (the nodes of
        other clients in this process); launch_args: more of the launch file's arguments (the
        mission's identifiers, recorder, live view); rough_site_m: the master's region
        (rough_site), its centre drawn per attempt; attach: start nothing and stop nothing,
        but use the graph already launched on this ROS domain (`ros2 launch coop_bringup
        mission.launch.py` with the same scenario: its simulator's seed and lockstep
        participants are checked), the rig's changes to it (the sim's rendering, the stereo
        nodes' ranging) left as they are at the end; team: the namespace of the whole graph
        and of this rig's own nodes, on the team's own clock (mission.launch.py's team:= and
        clock:=team): teams side by side in one domain."""
        self.team = team_namespace(team)
        # the team's map frame: mission.launch.py's frame_prefix for team:= ('team_a/')
        self.map_frame = f'{self.team}/map' if self.team else 'map'
        self.seed = seed
        self.stereo_rate_hz = stereo_rate_hz
        self.rough_site_m = rough_site_m
        self.lockstep = lockstep
        self.round_s = round_s
        self.starts = {'master': master_start, 'slave_short_m': slave_start_short_m}
        self.log_dir = Path(log_dir) if log_dir else Path(tempfile.mkdtemp(prefix='insert_'))
        self.log_dir.mkdir(parents=True, exist_ok=True)
        self.attach = attach
        if not attach:
            isolate_ros_environment(domain_id)
        self.clients = (CLIENT, *clients)
        self.slot_in = slot_in
        self.graph: LaunchedGraph | None = None
        self._extra_nodes: list[Node] = []
        self.feedback: Insert.Feedback | None = None    # the running goal's last feedback
        args = {'seed': seed, 'occlusion_density': occlusion_density, 'slot_in': slot_in,
                'rovers': rovers, 'stereo_rovers': ' '.join(stereo_rovers),
                'image_width': image_width, 'image_height': image_height,
                'stereo_rate_hz': stereo_rate_hz, 'render_workers': render_workers,
                'rate': real_time_factor, 'identify': False, 'driving': False,
                'mapping': planner,
                'insertion': True, 'cg_to_arm': calibrated_r2(seed), 'lockstep': lockstep,
                'lockstep_period_s': round_s, 'clients': ' '.join((CLIENT, *clients)),
                'composed': composed, 'output': 'own_log'}
        if site_map is not None and planner:
            # the scenario's map, built by the mapping pipeline (coop_viewplan.fig_3_25 with
            # save_map); a copy, since the mapper autosaves to the file it loaded
            local = self.log_dir / 'site.cmap'
            local.write_bytes(Path(site_map).read_bytes())
            args['site_map'] = local
        if overrides:
            path = self.log_dir / 'overrides.yaml'
            path.write_text(yaml.safe_dump({f'/**/{node}': {'ros__parameters': values}
                                            for node, values in overrides.items()}))
            args['overrides'] = path
        if self.team:
            args |= {'team': self.team, 'clock': 'team'}
        args |= launch_args or {}
        self.launch_args = {k: (str(v).lower() if isinstance(v, bool) else str(v))
                            for k, v in args.items()}
        self.expected = ['rover_sim', 'master', 'slave'] + (
            ['mapper', 'view_planner', *(f'{r}/stereo' for r in stereo_rovers)]
            if planner else [])
        if composed:
            self.expected = [n for n in self.expected if n not in COMPOSED] + ['compose']

    def __enter__(self) -> InsertionRig:
        try:
            if not self.attach:
                self.graph = LaunchedGraph(mission_launch_file(), self.launch_args,
                                           log_dir=self.log_dir).__enter__()
                self.graph.wait_started(self.expected, timeout_s=60)
            self.ctx = Context()
            # the team's namespace and clock for every node of this context (the rig's, a
            # mission runner's)
            rclpy.init(context=self.ctx, args=['--ros-args', '-r', f'__ns:=/{self.team}',
                                               '-r', f'/clock:=/{self.team}/clock']
                       if self.team else None)
            self.node = _Client(self.ctx, self.lockstep)
            self.ex = SingleThreadedExecutor(context=self.ctx)
            self.ex.add_node(self.node)
            self._stop = threading.Event()
            self._thread = threading.Thread(target=self._spin, daemon=True)
            self._thread.start()
            self.commander = Commander(self.node, self.ex, [], map_frame=self.map_frame)
            if self.attach:
                self._check_attached()
            if not self.commander.inserter.wait_for_server(timeout_sec=60):
                raise MissionError(f'no insert action server (logs in {self.log_dir})')
            if not self.node.reset.wait_for_service(timeout_sec=30):
                raise MissionError('no sim/reset service')
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def add_node(self, node: Node) -> None:
        """Spin another node of this rig's context with its executor; destroyed on exit,
        after the spinning stopped."""
        self._extra_nodes.append(node)
        self.ex.add_node(node)

    def dead(self) -> list[str]:
        """The processes of the graph that have ended (a node that died); attached, the
        expected nodes that left the ROS graph (looked up at most once a second)."""
        if self.graph is not None:
            return self.graph.dead()
        if not self.attach or getattr(self, 'node', None) is None:
            return []
        now = time.monotonic()
        if now - self._gone_at >= 1.0:
            self._gone_at = now
            self._gone = [n for n in self.expected if not self.has_node(n)]
        return self._gone

    def has_node(self, name: str) -> bool:
        """A node `name` (relative to the graph's root: 'master', 'rover1/stereo') runs."""
        if self.graph is not None:
            return bool(self.graph.find(name))
        ns = self.node.get_namespace().rstrip('/')
        full = f'{ns}/{name}'
        return any(f'{n_ns.rstrip("/")}/{n}' == full
                   for n, n_ns in self.node.get_node_names_and_namespaces())

    def _check_attached(self) -> None:
        """The launched graph is this rig's: its nodes run, and its simulator has this rig's
        seed and slot and, in lockstep, this rig's clients among its participants
        (MissionError naming the launch argument otherwise)."""
        self._gone_at, self._gone = -math.inf, []
        wait_for(lambda: all(self.has_node(n) for n in self.expected), 60.0,
                 what=f'the launched graph ({", ".join(self.expected)})')
        seed, participants, gap = self.get_parameters('rover_sim', 'seed',
                                                      'lockstep_participants', 'slot_gap_m')
        if seed != self.seed:
            raise MissionError(f'the launched simulator has seed {seed}, not {self.seed}: '
                               f'launch with seed:={self.seed}')
        if abs(gap - self.slot_in * INCH) > 1e-6:
            raise MissionError(f"the launched simulator's slot is {gap / INCH:g} in, not "
                               f'{self.slot_in:g}: launch with slot_in:={self.slot_in:g}')
        ours = [c for c in self.clients if c not in participants]
        if self.lockstep and ours:
            raise MissionError(f"the launched simulator's lockstep does not wait for "
                               f"{', '.join(ours)}: launch with lockstep:=true "
                               f"clients:='{' '.join(self.clients)}'")
        if not self.lockstep and [p for p in participants if p]:
            raise MissionError('the launched simulator runs in lockstep: run the client '
                               'with --lockstep, or launch with lockstep:=false')

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.ex.spin_once(timeout_sec=0.05)

    def __exit__(self, *exc) -> None:
        if getattr(self, '_thread', None) is not None:
            self._stop.set()
            self._thread.join(timeout=5)
        if getattr(self, 'ctx', None) is not None:
            self.ex.shutdown()
            for n in self._extra_nodes:
                n.destroy_node()
            self.node.destroy_node()
            rclpy.try_shutdown(context=self.ctx)
        if self.graph is not None:
            # a recorder first, so that its bag is closed while the graph still runs
            self.graph.stop('record', timeout_s=STOP_RECORD_S)
            self.graph.__exit__(None, None, None)

    def _wait(self, predicate, timeout_s: float, *, what: str, held: bool = False) -> None:
        """wait_for(predicate), failing early when a node of the graph died (MissionError)
        or the sim's clock stood still for STALL_S (SimStalled, with the sim's stacks); `held`:
        this rig holds the sim while it waits (lockstep), so a still clock is no stall."""
        def done() -> bool:
            if predicate():
                return True
            if held and self.lockstep:
                dead = self.dead()
                if dead:
                    raise MissionError(f'{", ".join(dead)} died while waiting for {what} '
                                         f'(logs in {self.log_dir})')
                return False
            self.check_alive(what)
            return False
        wait_for(done, timeout_s, what=what)

    def check_alive(self, what: str = 'the graph') -> None:
        dead = self.dead()
        if dead:
            raise MissionError(f'{", ".join(dead)} died while waiting for {what} (logs in '
                                 f'{self.log_dir})')
        idle = time.monotonic() - self.node.clock_wall
        if idle > STALL_S:
            stack = self.dump_stack('rover_sim')
            raise SimStalled(f'the sim clock stood still for {idle:.0f} s while waiting for '
                             f'{what}' + (f' (its stacks: {stack})' if stack else ''), stack)

    def dump_stack(self, name: str) -> Path | None:
        """Every thread's native and Python stack of process `name` into the log directory
        (gdb, when installed), for the post-mortem of a stall."""
        pid = self.graph.pid(name) if self.graph is not None else None
        gdb = shutil.which('gdb')
        if pid is None or gdb is None:
            return None
        path = self.log_dir / f'{name}_stack_{time.strftime("%H%M%S")}.txt'
        with open(path, 'wb') as out:
            try:
                subprocess.run([gdb, '-p', str(pid), '-batch', '-ex',
                                'thread apply all bt', '-ex', 'thread apply all py-bt'],
                               stdout=out, stderr=subprocess.STDOUT, timeout=120, check=False)
            except subprocess.TimeoutExpired:
                return None
        return path

    def _call(self, client, req, timeout_s: float = 30.0):
        fut = client.call_async(req)
        self._wait(fut.done, timeout_s, what=f"{client.srv_name}'s answer")
        return fut.result()

    def sim_sleep(self, seconds: float) -> None:
        """Wait `seconds` of sim time (up to 60 s + 20x that of wall time: a loaded machine
        runs the rendering sim at a real-time factor near 0.1), and at least long enough for
        a clock that stands still to be told a stall (SimStalled), not a timeout. In lockstep:
        let the sim step that many rounds, then hold it, however long the rounds take (a
        stall or a node that died still ends the wait): a bound in wall time would make the
        outcome the load's (two lockstep missions side by side beside other work ran their
        rendering sims at a real-time factor below 0.04)."""
        timeout = max(60.0 + 20.0 * seconds, STALL_S + 10.0)
        if self.lockstep:
            self.node.pacer.run(math.ceil(seconds / self.round_s - 1e-9))
            self._wait(lambda: self.node.pacer.paused, math.inf, what='sim time')
            return
        t0 = self.node.elapsed      # not the clock: a reset may not have reached us yet
        self._wait(lambda: self.node.elapsed >= t0 + seconds, timeout, what='sim time')

    def hold(self) -> None:
        """Lockstep: hold the sim at its next round (the world changes between rounds)."""
        if self.lockstep:
            self.node.pacer.stop()
            self._wait(lambda: self.node.pacer.paused, STALL_S, what='the sim held')

    def subscriptions(self) -> dict[str, list[str]]:
        """Every node of the team's graph this rig's client discovers (its full name) and the
        topics it subscribes to."""
        team = self.node.get_namespace()
        out = {}
        for name, ns in team_nodes(self.node, team):
            topics = names_of(self.node, name, ns)
            if topics is not None:
                out[f'{ns.rstrip("/")}/{name}'] = topics
        return out

    def stray_names(self) -> dict[str, list[str]]:
        """The topics of this rig's team's nodes outside its namespace (module stray_names)."""
        return stray_names(self.node, self.node.get_namespace())

    def get_parameters(self, node: str, *names: str) -> list:
        """Parameters of one node of the graph, as Python values."""
        client = AsyncParameterClient(self.node, node)
        if not client.wait_for_services(timeout_sec=10.0):
            raise MissionError(f'no {node} parameter services')
        fut = client.get_parameters(list(names))
        wait_for(fut.done, 10.0, what=f"{node}'s {', '.join(names)}")
        return [parameter_value_to_python(v) for v in fut.result().values]

    def set_parameters(self, node: str, **values) -> None:
        """Set parameters of one node of the graph (MissionError with the node's reason
        when it refuses one)."""
        client = AsyncParameterClient(self.node, node)
        if not client.wait_for_services(timeout_sec=10.0):
            raise MissionError(f'no {node} parameter services')
        fut = client.set_parameters([Parameter(k, value=v) for k, v in values.items()])
        self._wait(fut.done, 10.0, what=f"{node}'s {', '.join(values)}")
        for name, res in zip(values, fut.result().results, strict=False):
            if not res.successful:
                raise MissionError(f'{node}: {name} refused: {res.reason}')

    def set_slot(self, slot_in: float) -> None:
        """The task given for the next attempts, to the master and the slave: the slot's
        width."""
        for node in ('master', 'slave'):
            self.set_parameters(node, slot_width_m=slot_in * INCH)

    def render(self, rovers: tuple[str, ...], rate_hz: float) -> None:
        """Which rovers' stereo pairs the sim renders, at what rate (rendering is most of the
        sim's cost: off while no one looks). `rovers` empty with rate 0: none."""
        self.set_parameters('rover_sim', stereo_rate_hz=float(rate_hz),
                            stereo_rovers=list(rovers) or [''])

    def place(self, slot_in: float, rng: np.random.Generator) -> None:
        """Reset the sim to the slot width with the rovers at their (perturbed) starts."""
        poses = staging_poses(slot_in, rng, **self.starts)
        self.hold()
        req = SimScenario.Request(slot_gap_m=slot_in * INCH, place_rovers=list(poses),
                                  place_x=[p[0] for p in poses.values()],
                                  place_y=[p[1] for p in poses.values()],
                                  place_yaw=[p[2] for p in poses.values()])
        resp = self._call(self.node.reset, req)
        if not resp.success:
            raise MissionError(f'sim/reset: {resp.message}')
        self.sim_sleep(0.5)

    def survey(self, *, seconds: float = 20.0) -> int:
        """Rover 1 pans its mast over the site from its start so that the mapper builds the map
        the view planner places the camera in. Returns the map's voxel count. In lockstep the
        sim steps one stereo frame at a time and is held until rover 1's stereo node has
        ranged it (it and the mapper are not participants: a busy machine's stereo node would
        drop the frames it is behind on, and the map, and the camera placed in it, differ)."""
        self.node.mast.publish(mast_sweep(seconds))
        if not self.lockstep or not self.has_node('rover1/stereo'):
            self.sim_sleep(seconds + 1.0)
            return self.node.map_voxels
        node, period = self.node, 1.0 / self.stereo_rate_hz
        frames = math.ceil((seconds + 1.0) / period)
        late = 0
        for _ in range(frames):
            self.sim_sleep(period)
            # the last frame rendered is stamped within one period before the held clock
            due = node.clock - period + 1e-6
            try:
                self._wait(lambda d=due: node.ranged_t >= d, FRAME_WAIT_S, held=True,
                           what='the stereo node to range the survey frame')
            except TimeoutError:
                late += 1      # a frame the stereo node rejected: logged there
        if late:
            node.get_logger().warning(f'survey: {late} of {frames} frames not ranged within '
                                      f'{FRAME_WAIT_S:g} s')
        return node.map_voxels

    def stop_mapping(self) -> None:
        """End the stereo ranging into the map (the map keeps what it has): the site is
        mapped, and what the master's camera sees next is the slave's arm and card over the
        slot, which a map kept live would remember there as an obstacle at the task. In
        lockstep the sim is held until the map has taken in every frame already rendered (the
        stereo node and the mapper are not participants: stopped early, a busy machine's map
        would lack the frames they had not reached, and the camera placed in it differ)."""
        if self.lockstep:
            self.hold()
            seen = [self.node.map_voxels, time.monotonic()]

            def settled() -> bool:
                if self.node.map_voxels != seen[0]:
                    seen[:] = [self.node.map_voxels, time.monotonic()]
                return time.monotonic() - seen[1] >= MAP_QUIET_S
            self._wait(settled, STALL_S, what='the map to take in the survey')
        if self.graph is not None:
            self.graph.stop('stereo')
            return
        for name in self.expected:       # attached: not ours to stop, told to range no more
            if name.endswith('/stereo'):
                self.set_parameters(name, ranging=False)

    def attempt(self, *, slot_in: float, placement: Placement | str, seed: int,
                timeout_s: float = 120.0, max_force_n: float = 25.0,
                penetration_limit_mm: float = 0.5,
                camera: tuple[tuple[float, float], float, float] | None = None) -> Attempt:
        rng = np.random.default_rng(seed)
        self.place(slot_in, rng)
        return self.insert(slot_in=slot_in, placement=placement, seed=seed,
                           timeout_s=timeout_s, max_force_n=max_force_n,
                           penetration_limit_mm=penetration_limit_mm, camera=camera)

    def insert(self, *, slot_in: float, placement: Placement | str, seed: int = 0,
               timeout_s: float = 120.0, max_force_n: float = 25.0,
               penetration_limit_mm: float = 0.5,
               camera: tuple[tuple[float, float], float, float] | None = None) -> Attempt:
        """One `insert` goal from wherever the rovers stand, judged by the simulator's
        truth. placement: a Placement or its name ('given': the camera's (xy, yaw, pitch) in
        `camera`); the master's random draws are the attempt's seed's."""
        placement = choice(Placement, placement, 'placement', error=MissionError)
        if (placement is Placement.GIVEN) != (camera is not None):
            raise MissionError("a camera pose goes with the 'given' placement, and only")
        node = self.node
        self.hold()
        rough = rough_site(slot_in, seed, self.rough_site_m)
        self.set_parameters('master', seed=int(seed), site_position=rough,
                            site_search_m=float(self.rough_site_m))
        node.contact = []
        self.feedback = None
        curves = {'t': [], 'phase': [], 'displacement_m': [], 'angle_rad': [], 'force': []}
        t_start = node.ls.now_s(lambda: node.clock)
        node.card = []

        def on_fb(f: Insert.Feedback) -> None:
            self.feedback = f
            curves['t'].append(node.clock - t_start)
            curves['phase'].append(int(f.phase))
            curves['displacement_m'].append(float(f.displacement_error_m))
            curves['angle_rad'].append(float(f.angle_error_rad))
            w = f.wrench.force
            curves['force'].append([float(w.x), float(w.y), float(w.z)])

        goal = Insert.Goal(master='rover1', slave='rover2', tolerance_m=0.0,
                           placement=PLACEMENTS[placement],
                           max_force_n=float(max_force_n), timeout_s=float(timeout_s))
        if camera is not None:
            xy, yaw, pitch = camera
            goal.camera_pose.header.frame_id = self.map_frame
            pos, q = goal.camera_pose.pose.position, goal.camera_pose.pose.orientation
            pos.x, pos.y = float(xy[0]), float(xy[1])
            q.x, q.y, q.z, q.w = (float(v) for v in optical_quaternion(yaw, pitch))
        w0 = time.monotonic()
        task = self.commander.insert(goal, on_feedback=on_fb)
        # the master answers from an executor busy with 640x480 marker tracking: on a loaded
        # machine that took over 30 s of wall time
        self._wait(lambda: task.answered, 120, what="the insert goal's acceptance", held=True)
        if not task.accepted:
            raise MissionError('insert goal rejected')
        node.recording = True
        if self.lockstep:
            node.pacer.run()
        # the goal is bounded in sim time (the master's search and placement, the slave's
        # timeout), and a sim whose clock stops is told apart (SimStalled): the wall-clock bound
        # is a last resort only (a search of several views on a loaded machine took 15 min)
        self._wait(lambda: task.done, RESULT_WALL_S, what='the insert result')
        res = task.result()
        # the goal's end by the stamp of the state it ended on (the sim may have run on while
        # the result came), else by this client's clock
        ended = res.ended.sec + 1e-9 * res.ended.nanosec
        t_end = ended if ended > 0 else node.clock
        node.pacer.stop()
        node.recording = False
        # seated: the truth said so within the goal's last SEATED_WINDOW_S (the slave ends the
        # goal the moment it judges the card seated, and relaxes its push after; the truth's
        # last message may predate the seating by a contact period)
        during = [c for c in node.contact if c[0] <= t_end]
        # the alignment vision reached: the truth at the slave's descent (or first touch)
        aligned = (None, None)
        descended = res.descended.sec + 1e-9 * res.descended.nanosec
        at = [c for c in node.card if c[0] >= descended] if descended > 0 else []
        if at:
            aligned = (1e3 * (at[0][1] - slot_centre_x(slot_in)), math.degrees(at[0][2]))
        seated = any(s for t, s, _ in during if t >= t_end - SEATED_WINDOW_S)
        pen_mm = max((p for *_, p in during), default=0.0) * 1e3
        ok = bool(res.success and seated and pen_mm <= penetration_limit_mm)
        located = np.array([res.site.x, res.site.y, res.site.z])
        truth = np.array([slot_centre_x(slot_in), SITE_XY[1], SITE_TOP_M])
        site_mm = float(1e3 * np.linalg.norm(located - truth)) \
            if np.all(np.isfinite(located)) else None
        return Attempt(slot_in, placement, seed, ok, bool(res.success), res.reason,
                       seated, pen_mm, float(res.peak_force_n),
                       time.monotonic() - w0, t_end - t_start, int(res.frames),
                       int(res.fixes), int(res.replacements), *aligned, rough,
                       int(res.search_views), site_mm, curves=curves)


def as_row(a: Attempt) -> dict:
    """The attempt as a JSON row: its fields but the curves, non-finite numbers as None."""
    row = {k: (v if not isinstance(v, float) or math.isfinite(v) else None)
           for k, v in a.__dict__.items() if k != 'curves'}
    row['fix_rate'] = a.fix_rate
    return row
