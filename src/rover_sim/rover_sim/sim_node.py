"""rclpy node publishing the PyBullet world (`rover_sim.world.World`).

A dedicated thread steps the physics and publishes (paced by `real_time_factor`, 0 = as fast as
possible, and in lockstep mode by the participants' answers); the executor thread only receives
commands and services, which are handed to the sim thread and applied between steps, so the
physics never races a callback.
"""
from __future__ import annotations

import math
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import assert_never

import numpy as np
import rclpy
from builtin_interfaces.msg import Time
from geometry_msgs.msg import (
    PoseStamped,
    PoseWithCovarianceStamped,
    Twist,
    Vector3,
    WrenchStamped,
)
from nav_msgs.msg import Odometry
from rclpy.node import Node
from rosgraph_msgs.msg import Clock
from sensor_msgs.msg import CameraInfo, Image, Imu, JointState
from std_msgs.msg import UInt8MultiArray
from trajectory_msgs.msg import JointTrajectory
from visualization_msgs.msg import Marker, MarkerArray

from coop_braid.mast import MastKind
from coop_common.dynparams import PARAM_NAMES, BaseParameters, TruthFileError, load_truth
from coop_common.frames import (
    FRAME_PARAMS,
    FrameError,
    RoverFrames,
    Transform,
    check_frame_params,
    mast_transforms,
    odom_transform,
    static_transforms,
    truth_transforms,
)
from coop_common.lockstep import Gate, Inbox, LockstepError
from coop_common.lockstep_node import (
    ACK_TOPIC,
    ROUND_QOS,
    TICK_TOPIC,
    CountingPublisher,
    stamp_of,
)
from coop_common.node_util import BadInputCounter, ParamSpec, declare_parameters, run_node, stamp
from coop_common.qos import CLOCK_QOS, COMMAND_QOS, LATCHED_QOS, SENSOR_QOS, reliable
from coop_common.rover_geometry import GROUP_JOINTS, JointGroup
from coop_common.tf_tree import TreeBroadcaster
from coop_msgs.msg import (
    ContactState,
    DynamicParameters,
    Inclinometer,
    LockstepAck,
    LockstepTick,
    SegmentTruth,
)
from coop_msgs.srv import SimScenario

from .compliance import matrix_to_quat, rpy_to_matrix
from .config import (
    MAX_BRAID_STAGES,
    SEGMENT_TRUTH_TOPIC,
    WORLD_TOPIC,
    ConfigError,
    Integrator,
    NoiseConfig,
    Renderer,
    SimConfig,
    load_config,
    truth_topic,
)
from .errors import SimError
from .render_worker import RenderWorker
from .rover_model import ARM_JOINTS, CAMERA_OFFSET, OPTICAL_IN_TILT, STEREO_BASELINE_M
from .segment import Scenario, SegmentSpec, carry_segment
from .segment import SegmentTruth as SegmentTruth_
from .trajectory import TrajectoryError
from .world import World
from .worldgen import TABLE_5_1_GAPS_M, ObstacleKind


def _shortfall(short: dict[str, tuple[int, int]]) -> str:
    """`_unmatched_writers` for a log line: each topic's matched readers of those needed."""
    return ', '.join(f'{t} {m} of {k}' for t, (m, k) in sorted(short.items()))


@dataclass(frozen=True)
class _Trajectory:
    """A checked JointTrajectory for rover `index`'s arm or mast, applied between steps."""

    index: int
    group: JointGroup
    names: list[str]
    times: list[float]
    positions: list[list[float]]
    velocities: list[list[float]] | None
    start_s: float


@dataclass(frozen=True)
class _Braid:
    """A checked BRAID state (one 0..7 per stage, base first) for rover `index`'s mast."""

    index: int
    states: tuple[int, ...]


@dataclass(frozen=True)
class _Velocity:
    """A checked cmd_vel for rover `index`."""

    index: int
    linear: float
    angular: float


@dataclass(frozen=True)
class _Effort:
    """A checked arm feed-forward (N m per arm joint, ARM_JOINTS order) for rover `index`."""

    index: int
    torques: tuple[float, ...]


@dataclass(frozen=True)
class _Reset:
    """sim/reset's new world, built by the sim thread; `done` is set once it stands."""

    config: SimConfig
    truth: BaseParameters
    truth_yaml: str
    places: list[tuple[str, float, float, float]]
    done: threading.Event


#: what the executor hands the sim thread
_Pending = _Trajectory | _Velocity | _Effort | _Braid | _Reset


def _listened(pub) -> bool:
    """Someone subscribes to `pub`: a message nobody takes is not built (the world's readings
    are still taken, so their noise does not depend on who listens)."""
    return pub.get_subscription_count() > 0


def _pose(msg_pose, position: np.ndarray, rotation: np.ndarray) -> None:
    msg_pose.position.x, msg_pose.position.y, msg_pose.position.z = (float(v) for v in position)
    q = matrix_to_quat(rotation)
    o = msg_pose.orientation
    o.x, o.y, o.z, o.w = (float(v) for v in q)


PARAMS = {
    'world_yaml': ParamSpec('', 'World/params YAML overlaid on the defaults (fields of '
                            'rover_sim.config.SimConfig); empty: defaults', read_only=True),
    'truth_yaml': ParamSpec('', 'True base parameters of every rover (YAML, the 22 fields of '
                            'coop_common.dynparams); empty: Table 2-1', read_only=True),
    'rovers': ParamSpec(2, 'Number of rovers (namespaces rover1..roverN)', lo=1, hi=8,
                        read_only=True),
    'seed': ParamSpec(1, 'Seed of the world generator and of all sensor noise', lo=0,
                      hi=2 ** 31 - 1, read_only=True),
    'occlusion_density': ParamSpec(0.08, 'Obstacle footprint fraction of the site', lo=0.0,
                                   hi=0.5, read_only=True),
    'slot_gap_m': ParamSpec(TABLE_5_1_GAPS_M[1], "The insertion slot's gap between its jaws "
                            "along the 4.25 in card's width (m); Table 5-1: 5.0, 4.5, 4.375 in",
                            lo=0.108, hi=0.25, read_only=True),
    'contact_friction': ParamSpec(0.4, 'Coulomb friction coefficient of the card on the site, '
                                  'obstacles and ground', lo=0.0, hi=2.0, read_only=True),
    'integrator': ParamSpec(Integrator.EXPLICIT.value, 'How the base compliance and arm PD are '
                            'integrated: explicit forces at every sub-step, or implicit, solved '
                            'with the mass matrix once per engine step (faster, less faithful: '
                            'docs/results/simulator.md)',
                            choices=[i.value for i in Integrator], read_only=True),
    'render_workers': ParamSpec(1, 'Processes beside the simulator that render (1: the right eye '
                                'of each stereo pair in a second process, the same images in '
                                'about half the wall time where a core is free; 0: none)',
                                lo=0, hi=1, read_only=True),
    'renderer': ParamSpec(Renderer.TINY.value, "Who draws the stereo pairs: PyBullet's "
                          'TinyRenderer, or its EGL plugin (a GPU, or Mesa on the CPU; '
                          'TinyRenderer where it cannot load: docs/results/simulator.md)',
                          choices=[r.value for r in Renderer], read_only=True),
    'physics_substeps': ParamSpec(0, 'Physics sub-steps per 5 ms step; 0 = the stability minimum '
                                  '(explicit; implicit: 1) (more: closer to the continuous '
                                  'Eq. B-3 dynamics, slower)', lo=0, hi=200, read_only=True),
    'sensor_rate_hz': ParamSpec(200.0, 'IMU, inclinometer, F/T and joint state rate (Hz)',
                                lo=1.0, hi=200.0, read_only=True),
    'stereo_rate_hz': ParamSpec(4.0, 'Stereo pair rate (Hz); 0 pauses rendering (settable '
                                'while running: rendering is most of the cost, so a mission '
                                'turns it off while no one looks)', lo=0.0, hi=30.0),
    'stereo_rovers': ParamSpec([''], 'Rovers whose stereo pair is rendered and published '
                               "(e.g. [rover1]: the master watching an insertion); [''] or "
                               'empty: all; settable while running'),
    'clock_rate_hz': ParamSpec(100.0, '/clock rate (Hz): every node on sim time takes each one, '
                               'so it costs the graph more than any sensor stream; 100 is the '
                               "lockstep round and the slave's control period, a clock tick "
                               'between two is one no loop can act on', lo=1.0, hi=200.0,
                               read_only=True),
    'odom_rate_hz': ParamSpec(50.0, 'Odometry, stereo/pose-free truth pose rate (Hz)', lo=1.0,
                              hi=200.0, read_only=True),
    'image_width': ParamSpec(320, 'Image width (px)', lo=32, hi=1920, read_only=True),
    'image_height': ParamSpec(240, 'Image height (px)', lo=24, hi=1440, read_only=True),
    'supersample': ParamSpec(1, 'Render n x n samples per pixel and average them (pixel '
                             'integration: less aliasing of fine texture between the two images; '
                             'n^2 times the rendering cost); 1, 3, 5 or 7', lo=1, hi=7,
                             read_only=True),
    'noise_fraction': ParamSpec(0.10, "White noise bound as a fraction of each sensor's maximum "
                                'sensed value (thesis 2.6.1)', lo=0.0, hi=1.0, read_only=True),
    'real_time_factor': ParamSpec(1.0, 'Sim seconds per wall second; 0 = as fast as possible',
                                  lo=0.0, hi=100.0),
    'cmd_vel_timeout_s': ParamSpec(0.5, 'Stop a rover whose cmd_vel is older than this (sim s)',
                                   lo=0.05, hi=10.0),
    'feedforward_timeout_s': ParamSpec(0.05, "Drop a rover's arm feed-forward torques older "
                                       'than this (sim s): a silent host leaves the PD alone',
                                       lo=0.005, hi=10.0),
    'scenario': ParamSpec(Scenario.CARD.value, "What the rovers hold: 'card' (rover2 the "
                          "card of ch. 5) or 'segment' (rover1 and rover2 one truss segment and "
                          'a truss stage ahead of them, app. A.4; the explicit integrator)',
                          choices=[c.value for c in Scenario], read_only=True),
    'segment_mass_kg': ParamSpec(0.5, "Segment scenario: the segment's mass (kg)", lo=0.01,
                                 hi=3.0, read_only=True),
    'stage_behind_grasp_m': ParamSpec(0.05, "Segment scenario: the stage channel's centre this "
                                      'far behind the grasp line (m, along -x)', lo=-0.1,
                                      hi=0.2, read_only=True),
    'stage_top_z_m': ParamSpec(0.28, "Segment scenario: the stage's mouth above the ground (m)",
                               lo=0.1, hi=0.4, read_only=True),
    'stage_clearance_m': ParamSpec(0.004, "Segment scenario: the channel's width less the "
                                   "segment's (m)", lo=0.0005, hi=0.05, read_only=True),
    'mast': ParamSpec(MastKind.PAN_TILT.value, "The rovers' camera mast: the pan/tilt head, or "
                      'a BRAID chain on the pan turntable (app. E; `mast/braid_command` sets its '
                      'state, the camera renders from its forward kinematics)',
                      choices=[m.value for m in MastKind], read_only=True),
    'braid_stages': ParamSpec(10, 'Stages of the BRAID mast (3 binary legs each)', lo=1,
                              hi=MAX_BRAID_STAGES, read_only=True),
    'braid_settle_s': ParamSpec(1.0, 'A new BRAID state takes effect this long after its '
                                'command (sim s: the legs switching)', lo=0.0, hi=60.0,
                                read_only=True),
    'map_frame': ParamSpec('map', 'Common world frame id (REP 105), after frame_prefix',
                           read_only=True),
    **FRAME_PARAMS,
    'truth_tf': ParamSpec(False, "Also publish each rover's true base and camera poses on /tf "
                          'as <prefix>truth/<rover>/... children of the map (for viewing and '
                          'scoring; no loop reads them)', read_only=True),
    'lockstep_participants': ParamSpec(
        [''], 'Lockstep mode: the nodes (relative names resolve in this namespace) that close '
        'loops on the simulator; it steps no round before each has answered the last one '
        "(docs/design.md). [''] or empty: none, real-time pacing alone", read_only=True),
    'lockstep_period_s': ParamSpec(0.01, 'Lockstep: sim time per round (rounded to whole '
                                   'physics steps)', lo=0.005, hi=1.0, read_only=True),
    'lockstep_timeout_s': ParamSpec(10.0, 'Lockstep: say which nodes have not answered after '
                                    'this long (wall s), and again as often; it keeps waiting '
                                    '(for its writers to match, round 1 waits this long at most)',
                                    lo=0.5, hi=600.0),
}


def _unknown_rovers(chosen: list[str], rovers: int) -> str | None:
    known = [f'rover{i + 1}' for i in range(rovers)]
    unknown = [r for r in chosen if r and r not in known]
    return f'stereo_rovers: {unknown} not among {known}' if unknown else None


class SimNode(Node):
    """The simulator node: rover_sim's world on the ROS graph (sensors out, commands in,
    lockstep)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('rover_sim', **kwargs)
        self.values = declare_parameters(self, PARAMS, on_change=self._on_param_change,
                                         check_all=self._check_params)
        self._rtf = float(self.values['real_time_factor'])
        self._cmd_timeout = float(self.values['cmd_vel_timeout_s'])
        self._effort_timeout = float(self.values['feedforward_timeout_s'])
        self.config = self._make_config()         # raises ValueError (logged by run_node)
        # what the sim thread renders, changed while running (_on_param_change)
        self._stereo_hz = self.config.stereo_rate_hz
        self._stereo_rovers = tuple(r for r in self.values['stereo_rovers'] if r)
        self.truth_path = self.values['truth_yaml'] or None
        try:
            truth = load_truth(self.truth_path)
        except TruthFileError as exc:
            raise ValueError(str(exc)) from exc
        self.scenario = Scenario(self.values['scenario'])
        self.world = self._make_world(self.config, [truth] * self.config.rovers)
        self.frames = [RoverFrames(r.name, self.values['frame_prefix'], self.values['map_frame'])
                       for r in self.world.rovers]
        self.map_frame = self.frames[0].map
        # each rover's last joint state as published (names, positions): the mast's transforms
        self._joints: list[tuple[list[str], list[float]] | None] = [None] * len(self.frames)
        self.bad = BadInputCounter(self)
        self._pending: deque = deque()
        self._lock = threading.Lock()
        # lockstep (docs/design.md): the participants' answers, and the commands that came
        # ahead of the round they act in; both under _round_cv, which the sim thread waits on
        participants = [n if n.startswith('/') else
                        f'{self.get_namespace().rstrip("/")}/{n}'
                        for n in self.values['lockstep_participants'] if n]
        self._gate = Gate(participants) if participants else None
        self._inbox = Inbox()
        self._round_cv = threading.Condition()
        self._counts: Counter = Counter()       # what the sim published in this round
        self._count_lock = threading.Lock()
        self._counted: list[CountingPublisher] = []   # its publishers counted in the ticks
        self._lockstep_timeout = float(self.values['lockstep_timeout_s'])
        self._last_cmd_vel: dict[int, float] = {}
        self._last_effort: dict[int, float] = {}
        self._render_note_logged: str | None = None   # the world's render_note, logged once
        # per rover, the BRAID state last published on mast/braid_state (None: not yet)
        self._braid_sent: list[tuple[int, ...] | None] = [None] * self.config.rovers
        self._make_interfaces()
        self._publish_latched()
        self._stop = threading.Event()
        self.fatal_error: Exception | None = None     # what stopped the simulation thread
        self._thread = threading.Thread(target=self._run, name='sim', daemon=True)
        if self.world.renderer_note:
            self.get_logger().warn(self.world.renderer_note)
        self.get_logger().info(
            f'{self.config.rovers} rovers, seed {self.config.seed}, '
            f'{len(self.world.layout.obstacles)} obstacles, '
            f'physics {self.config.physics_rate_hz:g} '
            f'Hz x {self.world.substeps} {self.config.integrator.value} sub-steps, '
            f'stereo {self.config.stereo_rate_hz:g} Hz '
            f'{self.config.image_width}x{self.config.image_height} '
            f'({self.world.renderer.value})'
            + (f' ({self.config.supersample}x{self.config.supersample} samples per pixel)'
               if self.config.supersample > 1 else '') + f', rtf {self._rtf:g}'
            + (f', lockstep with {", ".join(self._gate.participants)} every '
               f'{self._round_steps()} steps' if self._gate else ''))
        self._thread.start()

    # ------------------------------------------------------------------ set-up
    #: node parameter -> SimConfig field
    _CONFIG_PARAMS = ('rovers', 'seed', 'occlusion_density', 'slot_gap_m', 'contact_friction',
                      'integrator', 'physics_substeps', 'sensor_rate_hz', 'stereo_rate_hz',
                      'image_width', 'image_height', 'supersample', 'mast', 'braid_stages',
                      'braid_settle_s')

    def _make_world(self, config: SimConfig, truths: list[BaseParameters],
                    worker: RenderWorker | None = None) -> World:
        """The world of the scenario: in 'segment', rovers 1 and 2 settle and grasp the
        segment (rover_sim.segment.carry_segment) before the first message goes out."""
        card = self.scenario is Scenario.CARD
        world = World(config, truths, render_worker=worker, card=card)
        if not card:
            v = self.values
            try:
                carry_segment(world, SegmentSpec(mass_kg=v['segment_mass_kg']),
                              behind_m=v['stage_behind_grasp_m'], top_z=v['stage_top_z_m'],
                              clearance_m=v['stage_clearance_m'])
            except (SimError, ValueError) as exc:
                world.close()
                raise ValueError(f'scenario segment: {exc}') from exc
        return world

    def _make_config(self) -> SimConfig:
        """Defaults <- world_yaml <- every parameter set away from its default."""
        v = self.values
        try:
            base = load_config(v['world_yaml']) if v['world_yaml'] else SimConfig()
            changes = {k: v[k] for k in self._CONFIG_PARAMS if v[k] != PARAMS[k].default}
            if v['noise_fraction'] != PARAMS['noise_fraction'].default:
                changes['noise'] = NoiseConfig(**{**base.noise.__dict__,
                                                  'fraction': v['noise_fraction']})
            # how it renders is the process's, not the world's: always the node's parameter
            config = base.replace(real_time_factor=self._rtf,
                                  render_workers=v['render_workers'],
                                  renderer=v['renderer'], **changes)
            reason = _unknown_rovers(v['stereo_rovers'], config.rovers)
            if reason:
                raise ConfigError(reason)
            return config
        except ConfigError as exc:
            raise ValueError(str(exc)) from exc

    def _publisher(self, msg_type, topic: str, qos):
        """A publisher; in lockstep a reliable one, counted in the round's tick."""
        if self._gate is None:
            return self.create_publisher(msg_type, topic, qos)
        counted = CountingPublisher(self.create_publisher(msg_type, topic, reliable(qos, 20)),
                                    self._counts, self._count_lock)
        self._counted.append(counted)
        return counted

    def _unmatched_writers(self) -> dict[str, tuple[int, int]]:
        """The counted publishers whose writer has matched fewer readers than it must reach
        ({topic: (matched, needed)}): every reader this node's graph shows on the topic, and
        the participants that take it (their acks of round 0) where the graph does not show
        them yet. A reliable writer sends nothing to a reader it has not matched, so a
        participant that counts on that topic would wait for the round's messages for ever:
        round 1 waits for these, and a stalled round logs them."""
        listeners = self._gate.listeners if self._gate is not None else {}
        short = {}
        for pub in self._counted:
            topic = pub.topic_name
            readers = self.get_subscriptions_info_by_topic(topic)
            shown = {f'{r.node_namespace.rstrip("/")}/{r.node_name}' for r in readers}
            needed = len(readers) + len(listeners.get(topic, set()) - shown)
            matched = pub.get_subscription_count()
            if matched < needed:
                short[topic] = (matched, needed)
        return short

    def _command(self, msg_type, topic: str, handler, base_qos=COMMAND_QOS) -> None:
        """Subscribe to a command topic: `handler(msg)` gives the pending item or None (a
        rejected message); in lockstep the item waits in the inbox for its round."""
        qos = base_qos if self._gate is None else reliable(base_qos)
        name = self.resolve_topic_name(topic)
        if self._gate is not None:
            self._inbox.listen(name)

        def on_msg(msg) -> None:
            item = handler(msg)
            if self._gate is not None:
                with self._round_cv:
                    self._inbox.put(name, stamp_of(msg), item)
                    self._round_cv.notify_all()
            elif item is not None:
                with self._lock:
                    self._pending.append(item)
        self.create_subscription(msg_type, topic, on_msg, qos)

    def _make_interfaces(self) -> None:
        pub = self._publisher
        self.clock_pub = pub(Clock, '/clock', CLOCK_QOS)
        self.pubs = []
        for i, r in enumerate(self.world.rovers):
            n = r.name
            pubs = {
                'imu': pub(Imu, f'{n}/imu', SENSOR_QOS),
                'incl': pub(Inclinometer, f'{n}/inclinometer', SENSOR_QOS),
                'wrench': pub(WrenchStamped, f'{n}/arm/wrench', SENSOR_QOS),
                'joints': pub(JointState, f'{n}/joint_states', SENSOR_QOS),
                'left': pub(Image, f'{n}/stereo/left/image_raw', SENSOR_QOS),
                'right': pub(Image, f'{n}/stereo/right/image_raw', SENSOR_QOS),
                'left_info': pub(CameraInfo, f'{n}/stereo/left/camera_info', SENSOR_QOS),
                'right_info': pub(CameraInfo, f'{n}/stereo/right/camera_info', SENSOR_QOS),
                'cam_est': pub(PoseWithCovarianceStamped, f'{n}/stereo/pose', SENSOR_QOS),
                'odom': pub(Odometry, f'{n}/odom', SENSOR_QOS),
                'truth_base': pub(PoseStamped, truth_topic(n, 'base_pose'), SENSOR_QOS),
                'truth_cam': pub(PoseStamped, truth_topic(n, 'camera_pose'), SENSOR_QOS),
                'card_pose': pub(PoseStamped, truth_topic(n, 'card_pose'), SENSOR_QOS),
                'contact': pub(ContactState, truth_topic(n, 'contact'), SENSOR_QOS),
                'truth_params': pub(DynamicParameters, truth_topic(n, 'parameters'), LATCHED_QOS),
            }
            self.pubs.append(pubs)
            self._command(JointTrajectory, f'{n}/arm/joint_command',
                          lambda m, i=i: self._on_traj(i, m, 'arm'))
            self._command(JointTrajectory, f'{n}/mast/command',
                          lambda m, i=i: self._on_traj(i, m, 'mast'))
            self._command(Twist, f'{n}/cmd_vel', lambda m, i=i: self._on_twist(i, m))
            if self.world.braid is not None:
                # latched: a state, the last one commanded reaches a simulator that joins late
                self._command(UInt8MultiArray, f'{n}/mast/braid_command',
                              lambda m, i=i: self._on_braid(i, m), LATCHED_QOS)
                pubs['braid_state'] = pub(UInt8MultiArray, f'{n}/mast/braid_state',
                                          LATCHED_QOS)
            self._command(JointState, f'{n}/arm/feedforward',
                          lambda m, i=i: self._on_effort(i, m))
        self.world_pub = pub(MarkerArray, WORLD_TOPIC, LATCHED_QOS)
        self.segment_pub = pub(SegmentTruth, SEGMENT_TRUTH_TOPIC, SENSOR_QOS)
        self.create_service(SimScenario, 'sim/reset', self._on_reset)
        if self._gate is not None:
            self.tick_pub = self.create_publisher(LockstepTick, TICK_TOPIC, ROUND_QOS)
            self.create_subscription(LockstepAck, ACK_TOPIC, self._on_ack, ROUND_QOS)
        # the tree (no loop reads it: not counted in lockstep rounds)
        self.tree = TreeBroadcaster(
            self, enabled=self.values['publish_tf'],
            owned=[f for fr in self.frames for f in fr.body()],
            check_s=self.values['frame_check_s'])

    def _check_params(self, values: dict) -> str | None:
        """Between parameters: a frame prefix; while running, the rendered rovers exist."""
        world = getattr(self, 'world', None)
        return check_frame_params(values) or (
            _unknown_rovers(values['stereo_rovers'], len(world.rovers)) if world else None)

    def _on_param_change(self, changed: dict) -> None:
        if 'stereo_rate_hz' in changed:
            self._stereo_hz = float(changed['stereo_rate_hz'])
        if 'stereo_rovers' in changed:
            self._stereo_rovers = tuple(r for r in changed['stereo_rovers'] if r)
        if 'real_time_factor' in changed:
            with self._lock:       # the sim thread reads both together (_pace)
                self._rtf = float(changed['real_time_factor'])
                self._pace_origin = None
        if 'cmd_vel_timeout_s' in changed:
            self._cmd_timeout = float(changed['cmd_vel_timeout_s'])
        if 'feedforward_timeout_s' in changed:
            self._effort_timeout = float(changed['feedforward_timeout_s'])
        if 'lockstep_timeout_s' in changed:
            self._lockstep_timeout = float(changed['lockstep_timeout_s'])

    # ------------------------------------------------------------------ commands (executor)
    def _on_traj(self, index: int, msg: JointTrajectory, group: JointGroup
                 ) -> _Trajectory | None:
        known = GROUP_JOINTS[group]
        base = self.frames[index].base_link
        if msg.header.frame_id not in ('', base):
            self.bad.reject('trajectory frame', f'{msg.header.frame_id!r} is not {base}')
            return None
        names = list(msg.joint_names)
        if not names or any(n not in known for n in names) or len(set(names)) != len(names):
            self.bad.reject('trajectory joints', f'{names} not a subset of {list(known)}')
            return None
        if not msg.points:
            self.bad.reject('trajectory empty')
            return None
        times, positions = [], []
        for p in msg.points:
            if len(p.positions) != len(names):
                self.bad.reject('trajectory joint count',
                                f'{len(p.positions)} positions for {len(names)} joints')
                return None
            times.append(p.time_from_start.sec + p.time_from_start.nanosec * 1e-9)
            positions.append(list(p.positions))
        # cubic when every point carries velocities (joint_trajectory_controller semantics)
        velocities = ([list(p.velocities) for p in msg.points]
                      if all(len(p.velocities) == len(names) for p in msg.points) else None)
        if not (np.all(np.isfinite(positions)) and np.all(np.isfinite(times))
                and (velocities is None or np.all(np.isfinite(velocities)))):
            self.bad.reject('trajectory NaN')
            return None
        start = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        return _Trajectory(index, group, names, times, positions, velocities, start)

    def _on_braid(self, index: int, msg: UInt8MultiArray) -> _Braid | None:
        """A BRAID state: one stage state 0..7 per stage (bit j - 1: leg j extended)."""
        assert self.world.braid is not None
        n = self.world.braid.n
        data = list(msg.data)
        if len(data) != n or any(v > 7 for v in data):
            self.bad.reject('braid state', f'{len(data)} values {data[:8]}: need {n} stage '
                            'states in 0..7')
            return None
        return _Braid(index, tuple(int(v) for v in data))

    def _on_twist(self, index: int, msg: Twist) -> _Velocity | None:
        v, w = msg.linear.x, msg.angular.z
        if not (math.isfinite(v) and math.isfinite(w)):
            self.bad.reject('cmd_vel NaN')
            return None
        return _Velocity(index, v, w)

    def _on_effort(self, index: int, msg: JointState) -> _Effort | None:
        """Torques added to the arm's PD (coop_insertion's arm_feedforward): efforts by joint
        name, joints not named get none."""
        names = list(msg.name)
        if (len(msg.effort) != len(names) or len(set(names)) != len(names)
                or any(n not in ARM_JOINTS for n in names)):
            self.bad.reject('feedforward joints', f'{names} with {len(msg.effort)} efforts: '
                            f'need a subset of {list(ARM_JOINTS)}, one effort each')
            return None
        if not all(math.isfinite(e) for e in msg.effort):
            self.bad.reject('feedforward NaN')
            return None
        by_name = dict(zip(names, msg.effort, strict=True))
        return _Effort(index, tuple(float(by_name.get(j, 0.0)) for j in ARM_JOINTS))

    def _on_reset(self, request: SimScenario.Request, response: SimScenario.Response):
        changes = {}
        if request.seed >= 0:
            changes['seed'] = int(request.seed)
        if request.occlusion_density >= 0:
            changes['occlusion_density'] = float(request.occlusion_density)
        if request.slot_gap_m > 0:
            changes['slot_gap_m'] = float(request.slot_gap_m)
        try:
            config = self.config.replace(**changes)
            truth = load_truth(request.truth_yaml or self.truth_path)
            places = self._placements(request, config.rovers)
        except (ConfigError, TruthFileError, ValueError) as exc:
            response.success, response.message = False, str(exc)
            return response
        done = threading.Event()
        with self._lock:
            self._pending.append(_Reset(config, truth, request.truth_yaml, places, done))
        if not done.wait(timeout=30.0):
            response.success, response.message = False, 'simulator did not reset within 30 s'
            return response
        response.success = True
        response.message = (f'reset: seed {config.seed}, occlusion {config.occlusion_density:g}, '
                            f'slot gap {config.slot_gap_m:g} m'
                            + ''.join(f', {r} at ({x:g}, {y:g}, {a:g})' for r, x, y, a in places))
        return response

    @staticmethod
    def _placements(request: SimScenario.Request, rovers: int
                    ) -> list[tuple[str, float, float, float]]:
        """The request's rover placements, checked: ValueError names what is wrong."""
        names = list(request.place_rovers)
        cols = (list(request.place_x), list(request.place_y), list(request.place_yaw))
        if any(len(c) != len(names) for c in cols):
            raise ValueError('place_rovers, place_x, place_y and place_yaw must be of one length')
        known = [f'rover{i + 1}' for i in range(rovers)]
        out = []
        for name, x, y, yaw in zip(names, *cols, strict=False):
            if name not in known:
                raise ValueError(f'place_rovers: {name!r} is not one of {known}')
            if not all(math.isfinite(v) for v in (x, y, yaw)):
                raise ValueError(f'place_rovers: {name} at a non-finite pose')
            out.append((name, float(x), float(y), float(yaw)))
        return out

    # ------------------------------------------------------------------ sim thread
    def _apply_pending(self) -> bool:
        """Apply what the executor handed over; True when the world was reset."""
        with self._lock:
            items = list(self._pending)
            self._pending.clear()
        return self._apply(items)

    def _apply(self, items: list[_Pending]) -> bool:
        reset = False
        for item in items:
            match item:
                case _Trajectory():
                    self._apply_trajectory(item)
                case _Velocity(index=i, linear=v, angular=w):
                    self.world.command_velocity(i, v, w)
                    self._last_cmd_vel[i] = self.world.time_s
                case _Effort(index=i, torques=tau):
                    self.world.command_arm_feedforward(i, tau)
                    self._last_effort[i] = self.world.time_s
                case _Braid(index=i, states=st):
                    self.world.command_braid(i, np.array(st, dtype=np.int64))
                    self._braid_sent[i] = None          # publish once it takes effect
                case _Reset():
                    self._apply_reset(item)
                    reset = True
                case _:
                    assert_never(item)
        return reset

    def _apply_trajectory(self, t: _Trajectory) -> None:
        try:
            match t.group:
                case 'arm':
                    self.world.command_arm(t.index, t.names, t.times, t.positions,
                                           start_s=t.start_s, velocities=t.velocities)
                case 'mast':
                    self.world.command_mast(t.index, t.names, t.times, t.positions,
                                            start_s=t.start_s)
                case _:
                    assert_never(t.group)
        except TrajectoryError as exc:
            self.bad.reject('trajectory', str(exc))

    def _apply_reset(self, r: _Reset) -> None:
        config = r.config
        # the same scene (an insertion rig's next attempt: the rovers placed anew): the render
        # worker stays, rather than a new process building its copy
        truths = [r.truth] * config.rovers
        worker = self.world.hand_over_renderer(config, truths)
        self.world.close()
        self.config = config
        if r.truth_yaml:
            self.truth_path = r.truth_yaml
        self.world = self._make_world(config, truths, worker)
        for name, x, y, yaw in r.places:
            self.world.place_rover(self.world.rover_index(name), x, y, yaw)
        self._last_cmd_vel.clear()
        self._last_effort.clear()
        self._pace_origin = None
        self._publish_latched()
        self.get_logger().info(f'reset to seed {config.seed}')
        r.done.set()

    def _running(self) -> bool:
        return not self._stop.is_set() and rclpy.ok(context=self.context)

    def _step(self) -> None:
        w = self.world
        for i, t in list(self._last_cmd_vel.items()):
            if w.time_s - t > self._cmd_timeout:
                w.command_velocity(i, 0.0, 0.0)
                del self._last_cmd_vel[i]
        for i, t in list(self._last_effort.items()):
            if w.time_s - t > self._effort_timeout:
                w.command_arm_feedforward(i, np.zeros(len(ARM_JOINTS)))
                del self._last_effort[i]
        w.step()
        self._publish_step()
        self._pace()

    def _run(self) -> None:
        self._pace_origin = None
        try:
            if self._gate is not None:
                self._run_rounds()
            while self._running():
                self._apply_pending()
                self._step()
        except Exception as exc:  # the node must report, not die silently
            # on Ctrl-C the context goes invalid under a publish in flight: a clean stop
            if self._stop.is_set() or not rclpy.ok(context=self.context):
                return
            # a node without its simulation would spin on, publishing nothing: stop the
            # process instead (run_node exits 1), so a supervisor sees it and can respawn it
            self.fatal_error = exc
            self.get_logger().fatal(f'simulation thread stopped: {exc!r}; shutting down')
            self.context.try_shutdown()
            raise

    # ------------------------------------------------------------------ lockstep
    def _round_steps(self) -> int:
        return max(1, round(self.values['lockstep_period_s'] * self.config.physics_rate_hz))

    def _on_ack(self, msg: LockstepAck) -> None:
        try:
            with self._round_cv:
                self._gate.answer(msg.node, int(msg.round),
                                  dict(zip(msg.topics, msg.counts, strict=False)), msg.listens)
                self._round_cv.notify_all()
        except LockstepError as exc:
            self.bad.reject('lockstep ack', str(exc))

    def _tick(self, round_: int, forwarded: dict[str, int]) -> None:
        """Round `round_` is stepped: tell the participants what went out for it."""
        with self._count_lock:
            counts = {} if round_ == 0 else dict(self._counts)
            self._counts.clear()
        counts.update(forwarded)
        self.tick_pub.publish(LockstepTick(round=round_, stamp=stamp(self.world.time_s),
                                           topics=list(counts),
                                           counts=[int(c) for c in counts.values()]))

    def _run_rounds(self) -> None:
        """Lockstep: step a round, tick, wait for every participant's answer and for the
        commands they count, apply those, step the next round (docs/design.md)."""
        n = self._round_steps()
        m = 0
        self._tick(0, {})
        while self._running():
            answer = self._await_answers(m)
            if answer is None:
                return
            due, reset = answer
            with self._round_cv:
                items = self._inbox.take(due)
            if not reset:       # a reset drops the round's commands: meant for the old world
                self._apply([item for _, item in items if item is not None])
            for _ in range(n):
                self._step()
            m += 1
            self._tick(m, due)

    def _await_answers(self, round_: int) -> tuple[dict[str, int], bool] | None:
        """What the participants published for `round_`, once all have answered it and the
        commands among it have arrived, and whether the world was reset meanwhile (a
        participant holds the round while it resets the world); every lockstep_timeout_s the
        wait is logged with the nodes or messages it waits for. Round 0 is over once, besides,
        the simulator's writers have matched the readers they must reach
        (`_unmatched_writers`), or lockstep_timeout_s after the answers. None when the node
        stops."""
        due: dict[str, int] | None = None
        reset = False
        since = last_tick = time.monotonic()
        warned = since
        answered = math.inf
        first_short: dict[str, tuple[int, int]] = {}
        while self._running():
            with self._round_cv:
                waiting = self._gate.waiting_for(round_)
                if not waiting and due is None:
                    due = self._gate.published(round_)
                    answered = time.monotonic()
                missing = self._inbox.missing(due) if due is not None else {}
                if due is not None and not missing:
                    short = self._unmatched_writers() if round_ == 0 else {}
                    first_short = first_short or short
                    if not short:
                        if first_short:     # what the wait held back, for a run's record
                            self.get_logger().info(
                                f'lockstep: round 1 waited {time.monotonic() - answered:.2f} s '
                                'for writers to match their readers: ' + _shortfall(first_short))
                        return due, reset
                    if time.monotonic() - answered > self._lockstep_timeout:
                        self.get_logger().warn(
                            'lockstep: stepping round 1 with writers short of their readers '
                            f'after {self._lockstep_timeout:.0f} s: ' + _shortfall(short))
                        return due, reset
                self._round_cv.wait(0.05)
            reset = self._apply_pending() or reset
            now = time.monotonic()
            if round_ == 0 and now - last_tick > 0.5:
                self._tick(0, {})          # a participant that came up late has missed it
                last_tick = now
            if now - warned > self._lockstep_timeout:
                warned = now
                what = (f'no answer to round {round_} from {", ".join(waiting)}' if waiting
                        else f'commands of round {round_} still on their way: {missing}')
                short = self._unmatched_writers()
                if short:
                    what += '; writers short of their readers: ' + _shortfall(short)
                self.get_logger().warn(f'lockstep: {what} after {now - since:.0f} s; waiting')
        return None

    def _pace(self) -> None:
        with self._lock:           # a parameter change sets both on the executor thread
            rtf, origin = self._rtf, self._pace_origin
            now = time.monotonic()
            if rtf <= 0.0:
                return
            if origin is None:
                origin = self._pace_origin = (now, self.world.time_s)
            wall0, sim0 = origin
            ahead = (self.world.time_s - sim0) / rtf - (now - wall0)
            if ahead < -0.5:          # fell behind (rendering, load): do not try to catch up
                self._pace_origin = (now, self.world.time_s)
        if ahead > 0:
            time.sleep(ahead)

    def _every(self, rate_hz: float) -> bool:
        if rate_hz <= 0:
            return False
        n = max(1, round(self.config.physics_rate_hz / rate_hz))
        return self.world.steps % n == 0

    def _publish_step(self) -> None:
        w = self.world
        t = stamp(w.time_s)
        if self._every(self.values['clock_rate_hz']):
            self.clock_pub.publish(Clock(clock=t))
        sensors = self._every(self.config.sensor_rate_hz)
        odom = self._every(self.values['odom_rate_hz'])
        stereo = self._every(self._stereo_hz)
        for i, r in enumerate(w.rovers):
            pubs = self.pubs[i]
            if sensors:
                self._publish_sensors(i, pubs, t)
                if r.card_index is not None:
                    self._publish_card(i, pubs, t)
            if odom:
                self._publish_odom(i, pubs, t)
            if stereo and self._renders(r.name):
                self._publish_stereo(i, pubs, t)
        if odom and w.segment is not None and w.segment.last is not None:
            self._publish_segment(w.segment.last, t)

    def _publish_segment(self, st: SegmentTruth_, t: Time) -> None:
        msg = SegmentTruth()
        msg.header.stamp, msg.header.frame_id = t, self.map_frame
        _pose(msg.pose, st.position, st.rotation)
        msg.grasp_force = [Vector3(x=float(f[0]), y=float(f[1]), z=float(f[2]))
                           for f in st.grasp_force]
        c = st.contact_force
        msg.contact_force = Vector3(x=float(c[0]), y=float(c[1]), z=float(c[2]))
        msg.internal_force_n = float(np.linalg.norm(st.internal_force))
        msg.max_penetration_m = float(st.max_penetration_m)
        msg.seated = bool(st.seated)
        self.segment_pub.publish(msg)

    def _renders(self, name: str) -> bool:
        chosen = self._stereo_rovers
        return not chosen or name in chosen

    def _publish_sensors(self, i: int, pubs: dict, t: Time) -> None:
        s = self.world.sense(i)       # always: its noise draws do not depend on who listens
        fr = self.frames[i]
        self._joints[i] = (list(s.joint_names), [float(v) for v in s.joint_positions])
        if _listened(pubs['imu']):
            self._publish_imu(s, fr.base_link, pubs['imu'], t)
        if _listened(pubs['incl']):
            inc = Inclinometer()
            inc.header.stamp, inc.header.frame_id = t, fr.base_link
            inc.roll, inc.pitch = float(s.incl_angles[0]), float(s.incl_angles[1])
            inc.roll_variance = inc.pitch_variance = float(s.incl_variance)
            inc.raw_roll_volts, inc.raw_pitch_volts = (float(s.incl_volts[0]),
                                                       float(s.incl_volts[1]))
            inc.saturated = s.incl_saturated
            pubs['incl'].publish(inc)
        if _listened(pubs['wrench']):
            wr = WrenchStamped()
            wr.header.stamp, wr.header.frame_id = t, fr.ft_sensor
            wr.wrench.force.x, wr.wrench.force.y, wr.wrench.force.z = (float(v) for v in s.force)
            wr.wrench.torque.x, wr.wrench.torque.y, wr.wrench.torque.z = (float(v)
                                                                          for v in s.torque)
            pubs['wrench'].publish(wr)
        if _listened(pubs['joints']):
            js = JointState()
            js.header.stamp = t
            js.name, js.position = self._joints[i]
            js.velocity = [float(v) for v in s.joint_velocities]
            pubs['joints'].publish(js)

    def _publish_imu(self, s, frame: str, pub, t: Time) -> None:
        imu = Imu()
        imu.header.stamp, imu.header.frame_id = t, frame
        imu.orientation_covariance[0] = -1.0
        imu.angular_velocity.x, imu.angular_velocity.y, imu.angular_velocity.z = (
            float(v) for v in s.angular_velocity)
        a = imu.linear_acceleration
        a.x, a.y, a.z = (float(v) for v in s.specific_force)
        nz = self.world._noise
        for k in range(3):
            imu.angular_velocity_covariance[4 * k] = nz['gyro'].variance
            imu.linear_acceleration_covariance[4 * k] = nz['accel'].variance
        pub.publish(imu)

    def _publish_card(self, i: int, pubs: dict, t: Time) -> None:
        frame = self.map_frame
        if _listened(pubs['card_pose']):
            ps = PoseStamped()
            ps.header.stamp, ps.header.frame_id = t, frame
            _pose(ps.pose, *self.world.card_pose(i))
            pubs['card_pose'].publish(ps)
        cs = self.world.contact(i)
        if cs is None or not _listened(pubs['contact']):
            return
        msg = ContactState()
        msg.header.stamp, msg.header.frame_id = t, frame
        f, m = msg.wrench.force, msg.wrench.torque
        f.x, f.y, f.z = (float(v) for v in cs.force)
        m.x, m.y, m.z = (float(v) for v in cs.torque)
        msg.points = cs.points
        msg.max_penetration_m = float(cs.max_penetration_m)
        msg.insertion_depth_m = self.world.insertion_depth(i)
        msg.seated = self.world.seated(i)
        msg.bodies = list(cs.bodies)
        pubs['contact'].publish(msg)

    def _publish_odom(self, i: int, pubs: dict, t: Time) -> None:
        xy, yaw, v, w = self.world.odometry(i)
        fr = self.frames[i]
        braid = self.world.braid_state(i)
        if braid is not None and tuple(braid) != self._braid_sent[i]:
            self._braid_sent[i] = tuple(int(b) for b in braid)
            pubs['braid_state'].publish(UInt8MultiArray(data=list(self._braid_sent[i])))
        if _listened(pubs['odom']):
            self._send_odom(fr, pubs['odom'], t, xy, yaw, v, w)
        if self.tree.listened:
            self._send_tree(i, t, xy, yaw)
        frame = self.map_frame
        if _listened(pubs['truth_base']):
            tr = self.world.truth(i)
            ps = PoseStamped()
            ps.header.stamp, ps.header.frame_id = t, frame
            _pose(ps.pose, tr.base_position, tr.base_rotation)
            pubs['truth_base'].publish(ps)
        # the camera's truth at the odometry's rate, rendered or not (a viewer shows where
        # each camera looks while the sim renders no pair)
        if _listened(pubs['truth_cam']):
            cp, cr = self.world.camera_pose(i)
            ps = PoseStamped()
            ps.header.stamp, ps.header.frame_id = t, frame
            _pose(ps.pose, cp, cr)
            pubs['truth_cam'].publish(ps)

    def _send_tree(self, i: int, t: Time, xy, yaw: float) -> None:
        """The rover's moving transforms: odometry, the mast from the last joint state (none,
        with a throttled warning, when it lacks a mast joint or holds NaN), the truth if asked."""
        fr = self.frames[i]
        out = [odom_transform(fr, float(xy[0]), float(xy[1]), float(yaw))]
        if self._joints[i] is not None:
            try:
                mast = mast_transforms(fr, *self._joints[i])
                if self.world.braid is not None:
                    mast[1] = self._braid_tilt_link(i)
                out += mast
            except FrameError as exc:
                self.bad.reject('mast transform', str(exc))
        if self.values['truth_tf']:
            tr = self.world.truth(i)
            base = np.eye(4)
            base[:3, :3], base[:3, 3] = tr.base_rotation, tr.base_position
            cp, cr = self.world.camera_pose(i)
            cam = np.eye(4)
            cam[:3, :3], cam[:3, 3] = cr, cp
            out += truth_transforms(fr, base, cam)
        self.tree.send(out, t)

    def _braid_tilt_link(self, i: int) -> Transform:
        """With a BRAID mast, the tilt link (the parent of the camera's optical frames) in the
        pan link where the chain's nominal forward kinematics of the commanded state put the
        optical frame: T_pan,tilt = T_pan,optical(s) T_tilt,optical^-1."""
        assert self.world.braid is not None
        state = self.world.braid_state(i)
        tilt_opt = np.eye(4)
        tilt_opt[:3, :3], tilt_opt[:3, 3] = OPTICAL_IN_TILT, CAMERA_OFFSET
        m = self.world.braid.optical_in_pan(state) @ np.linalg.inv(tilt_opt)
        fr = self.frames[i]
        return Transform.from_matrix(fr.mast_pan, fr.mast_tilt, m)

    @staticmethod
    def _send_odom(fr: RoverFrames, pub, t: Time, xy, yaw: float, v: float, w: float) -> None:
        od = Odometry()
        od.header.stamp, od.header.frame_id = t, fr.odom
        od.child_frame_id = fr.base_link
        pose = odom_transform(fr, float(xy[0]), float(xy[1]), float(yaw))
        _pose(od.pose.pose, np.array(pose.translation), rpy_to_matrix(0.0, 0.0, yaw))
        od.twist.twist.linear.x, od.twist.twist.angular.z = float(v), float(w)
        pub.publish(od)

    def _camera_info(self, t: Time, frame: str, right: bool) -> CameraInfo:
        k = self.world.intrinsics()
        info = CameraInfo()
        info.header.stamp, info.header.frame_id = t, frame
        info.width, info.height = self.config.image_width, self.config.image_height
        info.distortion_model = 'plumb_bob'
        info.d = [0.0] * 5
        info.k = [float(v) for v in k.ravel()]
        info.r = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
        p = np.hstack([k, np.zeros((3, 1))])
        if right:
            p[0, 3] = -k[0, 0] * STEREO_BASELINE_M     # Tx = -fx * baseline (ROS convention)
        info.p = [float(v) for v in p.ravel()]
        return info

    def _publish_stereo(self, i: int, pubs: dict, t: Time) -> None:
        if not any(_listened(pubs[k]) for k in ('left', 'right', 'left_info', 'right_info',
                                                  'cam_est')):
            return          # rendering is most of the cost; its picture draws no noise
        left, right = self.world.render_stereo(i)
        note = self.world.render_note
        if note is not None and note != self._render_note_logged:
            self._render_note_logged = note
            self.get_logger().warn(note)
        for key, img, frame, is_right in (('left', left, 'left', False),
                                          ('right', right, 'right', True)):
            msg = Image()
            msg.header.stamp = t
            msg.header.frame_id = self.frames[i].optical(frame)
            msg.height, msg.width = img.shape
            msg.encoding, msg.step = 'mono8', img.shape[1]
            msg.data = img.tobytes()
            pubs[key].publish(msg)
            pubs[f'{key}_info'].publish(self._camera_info(t, msg.header.frame_id, is_right))
        pos, rot, cov = self.world.estimated_camera_pose(i)
        est = PoseWithCovarianceStamped()
        est.header.stamp, est.header.frame_id = t, self.map_frame
        _pose(est.pose.pose, pos, rot)
        est.pose.covariance = [float(v) for v in cov.ravel()]
        pubs['cam_est'].publish(est)

    def _publish_latched(self) -> None:
        t = stamp(self.world.time_s)
        for i, r in enumerate(self.world.rovers):
            dp = DynamicParameters()
            dp.header.stamp, dp.header.frame_id = t, self.frames[i].base_link
            dp.names = list(PARAM_NAMES)
            dp.values = [float(v) for v in r.params.to_vector()]
            n = len(PARAM_NAMES)
            dp.std_devs = [0.0] * n
            dp.ci95_low = list(dp.values)
            dp.ci95_high = list(dp.values)
            dp.information_bits = [10.0] * n
            dp.observable = [True] * n
            dp.max_information_bits = 10.0
            dp.physically_consistent = True
            dp.strategy = 'truth'
            self.pubs[i]['truth_params'].publish(dp)
        self.world_pub.publish(self._world_markers(t))
        self.tree.send_static([s for fr in self.frames for s in static_transforms(fr)], t)

    def _world_markers(self, t: Time) -> MarkerArray:
        arr = MarkerArray()
        frame = self.map_frame
        clear = Marker(action=Marker.DELETEALL)
        clear.header.frame_id = frame
        arr.markers.append(clear)
        for k, ob in enumerate(self.world.layout.obstacles):
            m = Marker()
            m.header.stamp, m.header.frame_id = t, frame
            m.ns, m.id = ob.kind.value, k
            match ob.kind:
                case ObstacleKind.ROCK:
                    m.type, m.scale.z = Marker.SPHERE, 2 * ob.radius
                case ObstacleKind.DRUM:
                    m.type, m.scale.z = Marker.CYLINDER, ob.height
                case _:
                    assert_never(ob.kind)
            m.pose.position.x, m.pose.position.y, m.pose.position.z = ob.position
            m.pose.orientation.w = 1.0
            m.scale.x = m.scale.y = 2 * ob.radius
            m.color.r = m.color.g = m.color.b = float(ob.shade)
            m.color.a = 1.0
            arr.markers.append(m)
        site = self.world.layout.site
        for ns, centres, radius, q in (
                ('site_marker', site.markers, site.marker_radius_m, (0.0, math.sqrt(0.5))),
                ('slot_marker', site.slot_markers, site.slot_marker_radius_m,
                 (math.sqrt(0.5), 0.0))):
            for k, (x, y, z) in enumerate(centres):
                m = Marker()
                m.header.stamp, m.header.frame_id = t, frame
                m.ns, m.id, m.type = ns, k, Marker.CYLINDER
                m.pose.position.x, m.pose.position.y, m.pose.position.z = x, y, z
                m.pose.orientation.x, m.pose.orientation.y = q
                m.pose.orientation.w = math.sqrt(0.5)
                m.scale.x = m.scale.y = 2 * radius
                m.scale.z = 0.002
                m.color.r = m.color.g = m.color.b = m.color.a = 1.0
                arr.markers.append(m)
        for k, (name, box) in enumerate(zip(('jaw_near', 'jaw_far', 'floor'), site.jaws,
                                            strict=False)):
            m = Marker()
            m.header.stamp, m.header.frame_id = t, frame
            m.ns, m.id, m.type = 'site', k, Marker.CUBE
            m.pose.position.x, m.pose.position.y, m.pose.position.z = box.centre
            m.pose.orientation.w = 1.0
            m.scale.x, m.scale.y, m.scale.z = (2 * h for h in box.half_extents)
            m.color.r = m.color.g = 0.25
            m.color.b, m.color.a = 0.3, 1.0
            m.text = f'{name}; slot_gap_m={site.gap_m:g}'
            arr.markers.append(m)
        return arr

    def destroy_node(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self.world.close()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """`ros2 run rover_sim sim`."""
    # one executor thread: rclpy's multi-threaded executor hands a callback over to its pool
    # through the GIL that the sim thread holds while it steps (a lockstep ack took 4-650 ms
    # to reach its callback, 0.7 ms with this one)
    return run_node(SimNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
