"""The PyBullet world: rovers on their base compliance, arms, masts, stereo cameras, obstacles,
the card and the insertion site. No rclpy: `World` steps, senses and renders; the node publishes.
"""
from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import math
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import assert_never

import cv2
import numpy as np
import pybullet as pb

from coop_braid.mast import BraidMast, MastKind
from coop_common.dynparams import BaseParameters
from coop_common.rendering import fine_intrinsics, pixel_average, projection_matrix
from coop_common.rover_geometry import BASE_HEIGHT_M, CARD_OFFSET_M, TRACK_M

from .compliance import (
    FastCompliance,
    cross3,
    deflection,
    matrix_to_quat,
    matrix_to_rpy,
    quat_rotate,
    quat_rotate_inverse,
    quat_to_matrix,
    relative_rotation_vector,
    rotation_vector,
    rpy_to_matrix,
    static_preload,
)
from .config import Integrator, Renderer, SimConfig
from .implicit import BaseKinematics, ImplicitSolver
from .render_worker import RenderWorker, RenderWorkerError
from .rover_model import (
    ARM_EFFORT_NM,
    ARM_JOINTS,
    CAMERA_OFFSET,
    MAST_JOINTS,
    MAST_POSITION,
    OPTICAL_IN_TILT,
    STEREO_BASELINE_M,
    TILT_ABOVE_PAN_M,
    WHEELS,
    arm_joint_inertias,
    base_link_inertial,
    rover_urdf,
)
from .segment import SegmentCarry, SegmentSpec, StageSpec
from .sensors import (
    DEG,
    InclinometerModel,
    WhiteNoise,
    odometry_step,
    specific_force,
    wheel_speeds,
)
from .trajectory import JointTrajectoryFollower, TrajectoryError
from .worldgen import ObstacleKind, WorldLayout, generate_world

NOMINAL_HEIGHT_M = BASE_HEIGHT_M    # base c.g. above the ground at rest
GRAVITY_VEC = np.array([0.0, 0.0, -9.81])
WHEEL_RADIUS_M = 0.06
ARM_HOME = np.array([0.0, -0.6, 1.2, 0.0])
# Arm joint PD: about 15 Hz bandwidth, critically damped, gains scheduled on the inertia each
# joint drives (arm_joint_inertias); explicit at the physics sub-step, inside its stability limit
# for every configuration.
PD_OMEGA = 2 * np.pi * 15.0
PD_HOLD = 2
# The mast's motors (the engine's velocity constraint, reference speed fed forward) correct a
# position error at this rate (1/s), whatever the engine's step
MAST_BANDWIDTH = 100.0


@dataclass
class Readings:
    """One rover's sensor outputs at one instant (noisy unless noise fraction is 0)."""

    stamp_s: float
    specific_force: np.ndarray        # base frame, m/s^2
    angular_velocity: np.ndarray      # base frame, rad/s
    incl_angles: np.ndarray           # roll, pitch (rad)
    incl_volts: np.ndarray
    incl_saturated: bool
    incl_variance: float
    force: np.ndarray                 # F_12 at the sensor, sensor (= base) axes, N
    torque: np.ndarray                # N_12 about the sensor origin, N m
    joint_names: tuple[str, ...]
    joint_positions: np.ndarray       # NaN where a sensor gives no position (tachometers)
    joint_velocities: np.ndarray


@dataclass
class Truth:
    """Ground truth of one rover (published only under /sim)."""

    stamp_s: float
    base_position: np.ndarray         # c.g., map frame
    base_rotation: np.ndarray         # base_link in map
    dr: np.ndarray                    # compliance deflection, anchor frame
    dtheta: np.ndarray
    camera_position: np.ndarray       # left optical frame origin, map frame
    camera_rotation: np.ndarray
    anchor_position: np.ndarray
    anchor_yaw: float


@dataclass(frozen=True)
class ArmMomentum:
    """Momentum of the links beyond the F/T sensor at the end of a control step (world frame):
    the state from which the sensor's wrench over the step is differenced."""

    momentum: np.ndarray          # P = sum m_i v_i
    ang_momentum: np.ndarray      # H_p = sum I_i w_i + (c_i - p) x m_i v_i, about the sensor p
    gravity_moment: np.ndarray    # sum (c_i - p) x m_i g, half a sub-step back (see _arm_momentum)
    transport: np.ndarray         # p_dot x P
    sensor_rotation: np.ndarray   # F/T sensor frame in the world


@dataclass(frozen=True)
class ContactState:
    """The card's contacts over the last control step (ground truth, ch. 5 / app. A.4)."""

    stamp_s: float
    force: np.ndarray             # mean contact force on the card over the step, world, N
    torque: np.ndarray            # its mean moment about the card's centre, world, N m
    points: int                   # contact points at the end of the step
    max_penetration_m: float      # deepest overlap of the card into anything during the step
    bodies: tuple[str, ...]       # what it touched: 'jaw_near', 'jaw_far', 'floor', 'ground',
    #                               'obstacle'


@dataclass
class _Contact:
    """Per-step accumulators of a card's contact forces (sums over the sub-steps)."""

    force: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    moment: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))  # about origin
    penetration: float = 0.0
    points: int = 0
    bodies: set = dataclasses.field(default_factory=set)


@dataclass
class _Rover:
    name: str
    body: int
    params: BaseParameters
    joint_index: dict[str, int]
    ft_index: int
    tilt_index: int
    inertial_rot: np.ndarray          # principal-axes frame in the link frame
    com_offset: np.ndarray            # base link c.o.m. in the link frame (mast compensation)
    arm: JointTrajectoryFollower
    mast: JointTrajectoryFollower
    anchor_xy: np.ndarray
    anchor_yaw: float
    cmd: tuple[float, float]
    preload: np.ndarray
    prev_velocity: np.ndarray
    accel: np.ndarray
    wheel_rates: np.ndarray
    odom_xy: np.ndarray
    odom_yaw: float
    fast: FastCompliance | None = None
    implicit: ImplicitSolver | None = None
    movable: list[int] | None = None      # every non-fixed joint, in the mass matrix's order
    # base + arm rows of the mass matrix (mast locked); the arm's and the mast's joints
    mass_index: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, int))
    actuated: list[int] = dataclasses.field(default_factory=list)
    mast_joints: list[int] = dataclasses.field(default_factory=list)
    tau: list[float] = dataclasses.field(default_factory=lambda: [0.0] * 4)
    #: joint torques added to the arm's PD (a feed-forward the host commands), N m
    tau_ff: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(4))
    # base link orientation (quaternion x, y, z, w) at the end of the last control step, and
    # at the start of the last sub-step of the current / previous control step (the gyro)
    prev_quat: tuple = (0.0, 0.0, 0.0, 1.0)
    last_sub_quat: tuple = (0.0, 0.0, 0.0, 1.0)
    prev_sub_quat: tuple = (0.0, 0.0, 0.0, 1.0)
    gyro_mean: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    ft_mean: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(6))
    # the links beyond the F/T sensor (sensor link first): masses, principal inertias, and
    # their momentum state at the end of the last control step (ArmMomentum)
    arm_links: list[int] = dataclasses.field(default_factory=list)
    arm_masses: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    arm_inertias: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    arm_prev: ArmMomentum | None = None
    card_index: int | None = None     # the card's link (the one link that collides), if carried
    probe_body: int | None = None     # its copy in the implicit step's probe world
    gravity_start: np.ndarray | None = None  # the arm's gravity moment at the period's start
    contact: _Contact = dataclasses.field(default_factory=_Contact)
    last_contact: ContactState | None = None
    # BRAID mast (config.mast braid): the state in effect, the commanded one and when it takes
    # effect
    braid_states: np.ndarray | None = None
    braid_pending: tuple[float, np.ndarray] | None = None
    pan_index: int = -1


def substeps_for(params: Sequence[BaseParameters], dt: float) -> int:
    """Physics sub-steps per control step so that the explicit spring-damper of Eq. B-3 is stable:
    b_i dt_sub / I_ii <= 1 and sqrt(k_i / I_ii) dt_sub <= 0.5 on every axis."""
    rate = 0.0
    for p in params:
        inertia = np.array([p.inertia[0, 0], p.inertia[1, 1], p.inertia[2, 2]])
        masses = np.full(3, p.mass)
        diag = np.concatenate([masses, inertia])
        rate = max(rate, float(np.max(p.damping / diag)),
                   float(np.max(2.0 * np.sqrt(p.stiffness / diag))))
    return max(1, math.ceil(rate * dt))


def load_egl(client: int) -> tuple[int, str | None]:
    """PyBullet's EGL renderer plugin (in the pybullet wheel) into physics client `client`:
    (plugin id, None), or (-1, why it did not load)."""
    spec = importlib.util.find_spec('eglRenderer')
    if spec is None or spec.origin is None:
        return -1, 'EGL renderer: no eglRenderer module in the pybullet wheel; TinyRenderer draws'
    plugin = pb.loadPlugin(spec.origin, '_eglRendererPlugin', physicsClientId=client)
    if plugin < 0:
        return -1, ('EGL renderer: the plugin did not load (no EGL: install libegl1, '
                    'libegl-mesa0 and libgl1-mesa-dri, or a GPU driver); TinyRenderer draws')
    return plugin, None


class World:
    """The simulated site. Deterministic for a given config (seed) and command sequence."""

    def __init__(self, config: SimConfig, truths: Sequence[BaseParameters], *,
                 render_worker: RenderWorker | None = None, card: bool = True) -> None:
        """render_worker: one that an earlier world of the same scene handed over
        (`hand_over_renderer`), kept rather than started again. card: rover 2 carries the
        card (ch. 5); False: no rover holds anything (app. A.4's segment is grasped later,
        `grasp_segment`)."""
        if len(truths) != config.rovers:
            raise ValueError(f'expected {config.rovers} truth parameter sets, got {len(truths)}')
        self.config = config
        self._truths = list(truths)
        # the right eye's renderer in a second process (config.render_workers), started at the
        # first picture; None: both eyes here. render_note: why it stopped, if it did
        self._render_worker: RenderWorker | None = render_worker
        self.render_note: str | None = None
        self.dt = 1.0 / config.physics_rate_hz
        self.integrator = config.integrator
        if self.integrator is Integrator.IMPLICIT:
            self.substeps = max(1, config.physics_substeps)
        else:
            # never below the stability minimum; more buys accuracy (README: sub-steps vs
            # fidelity)
            self.substeps = max(substeps_for(truths, self.dt), config.physics_substeps)
        self.time_s = 0.0
        self.steps = 0
        self.rng = np.random.default_rng(config.seed)
        self._tmp = Path(tempfile.mkdtemp(prefix='rover_sim_'))
        self.client = pb.connect(pb.DIRECT)
        pb.resetSimulation(physicsClientId=self.client)
        # EGL: loaded before any body is made (the plugin draws the shapes made after it);
        # where it cannot load, TinyRenderer, and renderer_note says why
        self.renderer, self.renderer_note = Renderer.TINY, None
        self._egl_plugin = -1
        if config.renderer is Renderer.EGL:
            self._egl_plugin, self.renderer_note = load_egl(self.client)
            if self._egl_plugin >= 0:
                self.renderer = Renderer.EGL
        pb.setGravity(0, 0, -9.81, physicsClientId=self.client)
        pb.setPhysicsEngineParameter(fixedTimeStep=self.dt / self.substeps, numSubSteps=0,
                                     deterministicOverlappingPairs=1,
                                     physicsClientId=self.client)
        # implicit: a world of the rovers alone, in which each step is first taken without the
        # stiff forces, for the velocity change of everything else (rover_sim.implicit)
        self.probe_client: int | None = None
        if self.integrator is Integrator.IMPLICIT:
            self.probe_client = pb.connect(pb.DIRECT)
            pb.setGravity(0, 0, -9.81, physicsClientId=self.probe_client)
            pb.setPhysicsEngineParameter(fixedTimeStep=self.dt / self.substeps, numSubSteps=0,
                                         deterministicOverlappingPairs=1,
                                         physicsClientId=self.probe_client)
        n = config.rovers
        starts = [(-2.0, 1.5 * (i - (n - 1) / 2.0)) for i in range(n)]
        self.layout: WorldLayout = generate_world(
            seed=config.seed, occlusion_density=config.occlusion_density,
            extent_m=config.extent_m, slot_gap_m=config.slot_gap_m,
            keep_clear=tuple((x, y, 0.9) for x, y in starts))
        self._textures = self._make_textures()
        self._build_static()
        noise = config.noise
        self.incl_model = InclinometerModel(
            noise=WhiteNoise(noise.fraction, noise.inclinometer_rad))
        self._noise = {
            'accel': WhiteNoise(noise.fraction, noise.accel_m_s2),
            'gyro': WhiteNoise(noise.fraction, noise.gyro_rad_s),
            'force': WhiteNoise(noise.fraction, noise.force_n),
            'torque': WhiteNoise(noise.fraction, noise.torque_nm),
            'encoder': WhiteNoise(noise.fraction, noise.encoder_rad),
            'tach': WhiteNoise(noise.fraction, noise.tach_rad_s),
            'pot': WhiteNoise(noise.fraction, noise.pot_rad),
        }
        nz = self._noise
        self._noise_bounds = np.concatenate([
            np.full(3, nz['accel'].bound), np.full(3, nz['gyro'].bound),
            np.full(3, nz['force'].bound), np.full(3, nz['torque'].bound),
            np.full(6, nz['encoder'].bound), np.full(4, nz['tach'].bound), [nz['pot'].bound]])
        #: the BRAID mast every rover carries (config.mast braid), else None: its nominal
        #: kinematics are also the truth (the chain is built as designed)
        self.braid: BraidMast | None = (BraidMast.rover(config.braid_stages)
                                        if config.mast is MastKind.BRAID else None)
        self.rovers: list[_Rover] = []
        self.substep_s = self.dt / self.substeps
        for i, (params, (x, y)) in enumerate(zip(truths, starts, strict=False)):
            self.rovers.append(self._spawn(f'rover{i + 1}', params, x, y,
                                           with_card=(i == 1 and card)))
        #: app. A.4's segment in the first two rovers' grippers (grasp_segment), if held
        self.segment: SegmentCarry | None = None

    # ----------------------------------------------------------------- construction
    def _make_textures(self) -> dict[str, int]:
        rng = np.random.default_rng(self.config.seed + 7919)
        out = {}
        for name, size, blur in (('ground', 1024, 3), ('rock', 256, 3)):
            img: np.ndarray = rng.integers(0, 256, size=(size, size), dtype=np.uint8)
            img = cv2.GaussianBlur(img, (blur, blur), 0)
            # (OpenCV's stubs want an array for dst; None returns a new one)
            img = cv2.normalize(img, None, 40, 230, cv2.NORM_MINMAX)  # type: ignore[call-overload]
            path = self._tmp / f'{name}.png'
            cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
            out[name] = pb.loadTexture(str(path), physicsClientId=self.client)
        return out

    def _static_body(self, shape: int, position: Sequence[float] | np.ndarray,
                     orientation: Sequence[float] = (0, 0, 0, 1), *, collision: int = -1) -> int:
        body = pb.createMultiBody(baseMass=0, baseVisualShapeIndex=shape,
                                  baseCollisionShapeIndex=collision, basePosition=position,
                                  baseOrientation=orientation, physicsClientId=self.client)
        if collision >= 0:
            pb.changeDynamics(body, -1, lateralFriction=self.config.contact_friction,
                              physicsClientId=self.client)
        return body

    def _build_static(self) -> None:
        """Ground, obstacles and the insertion site, each with a collision shape (only the card
        touches them: no other link of a rover has one), and the site's markers (visual)."""
        c = self.client
        half = self.config.extent_m
        ground = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[half, half, 0.005],
                                      rgbaColor=[0.75, 0.7, 0.6, 1], physicsClientId=c)
        self.ground = self._static_body(
            ground, [0, 0, -0.005], collision=pb.createCollisionShape(
                pb.GEOM_BOX, halfExtents=[half, half, 0.005], physicsClientId=c))
        pb.changeVisualShape(self.ground, -1, textureUniqueId=self._textures['ground'],
                             physicsClientId=c)
        self._body_kind: dict[int, str] = {self.ground: 'ground'}
        self.obstacle_bodies = []
        for ob in self.layout.obstacles:
            s = ob.shade
            match ob.kind:
                case ObstacleKind.ROCK:
                    vis = pb.createVisualShape(pb.GEOM_SPHERE, radius=ob.radius,
                                               rgbaColor=[s, s * 0.9, s * 0.8, 1],
                                               physicsClientId=c)
                    col = pb.createCollisionShape(pb.GEOM_SPHERE, radius=ob.radius,
                                                  physicsClientId=c)
                case ObstacleKind.DRUM:
                    vis = pb.createVisualShape(pb.GEOM_CYLINDER, radius=ob.radius,
                                               length=ob.height,
                                               rgbaColor=[s * 0.6, s * 0.7, s, 1],
                                               physicsClientId=c)
                    col = pb.createCollisionShape(pb.GEOM_CYLINDER, radius=ob.radius,
                                                  height=ob.height, physicsClientId=c)
                case _:
                    assert_never(ob.kind)
            body = self._static_body(vis, ob.position, collision=col)
            pb.changeVisualShape(body, -1, textureUniqueId=self._textures['rock'],
                                 physicsClientId=c)
            self.obstacle_bodies.append(body)
            self._body_kind[body] = 'obstacle'
        site = self.layout.site
        self.site_bodies = []
        for kind, box in zip(('jaw_near', 'jaw_far', 'floor'), site.jaws, strict=False):
            vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=list(box.half_extents),
                                       rgbaColor=[0.25, 0.25, 0.3, 1], physicsClientId=c)
            col = pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(box.half_extents),
                                          physicsClientId=c)
            body = self._static_body(vis, list(box.centre), collision=col)
            self.site_bodies.append(body)
            self._body_kind[body] = kind
        # fiducials face -x (disc axis along x, 2 mm discs half in the face); the slot markers
        # face +y as painted discs (0.4 mm, 0.3 mm proud of the face: a thicker disc shows its
        # rim at an oblique view, which at 3 px radius is not an ellipse any more)
        for centres, radius, rpy, length, out in (
                (site.markers, site.marker_radius_m, (0, math.pi / 2, 0), 0.002, (0, 0, 0)),
                (site.slot_markers, site.slot_marker_radius_m, (math.pi / 2, 0, 0), 0.0004,
                 (0, 0.0001, 0))):
            for m in centres:
                vis = pb.createVisualShape(pb.GEOM_CYLINDER, radius=radius, length=length,
                                           rgbaColor=[1, 1, 1, 1], physicsClientId=c)
                self._static_body(vis, np.add(m, out), pb.getQuaternionFromEuler(rpy))

    def _spawn(self, name: str, params: BaseParameters, x: float, y: float,
               with_card: bool) -> _Rover:
        c = self.client
        urdf = self._tmp / f'{name}.urdf'
        # the engine's base inertia carries the h/2 lag of the explicit rotational damper
        # (rover_model.base_link_inertial), the translational damper is evaluated at t_n
        # (FastCompliance midpoint_damper): the simulated body's effective mass, inertia and
        # damping are the truth's
        explicit = self.integrator is Integrator.EXPLICIT
        urdf.write_text(rover_urdf(name, params, with_card=with_card,
                                   damper_lag_s=0.5 * self.substep_s if explicit else 0.0,
                                   head=self.braid is None))
        body = pb.loadURDF(str(urdf), [x, y, NOMINAL_HEIGHT_M], [0, 0, 0, 1],
                           flags=pb.URDF_USE_INERTIA_FROM_FILE, physicsClientId=c)
        joints = {}
        for j in range(pb.getNumJoints(body, physicsClientId=c)):
            info = pb.getJointInfo(body, j, physicsClientId=c)
            joints[info[1].decode()] = j
            pb.changeDynamics(body, j, linearDamping=0, angularDamping=0, jointDamping=0,
                              physicsClientId=c)
        pb.changeDynamics(body, -1, linearDamping=0, angularDamping=0, physicsClientId=c)
        card = joints.get('card_joint')
        if card is not None:
            pb.changeDynamics(body, card, lateralFriction=self.config.contact_friction,
                              physicsClientId=c)
        q_in = pb.getDynamicsInfo(body, -1, physicsClientId=c)[4]
        ft = joints['ft_sensor_joint']
        parents = {j: pb.getJointInfo(body, j, physicsClientId=c)[16] for j in joints.values()}

        def beyond_sensor(j: int) -> bool:
            while j >= 0:
                if j == ft:
                    return True
                j = parents[j]
            return False
        arm_links = [ft] + sorted(j for j in joints.values() if j != ft and beyond_sensor(j))
        dyn = [pb.getDynamicsInfo(body, j, physicsClientId=c) for j in arm_links]
        for k, jn in enumerate(ARM_JOINTS):
            pb.resetJointState(body, joints[jn], ARM_HOME[k], physicsClientId=c)
        rover = _Rover(
            name=name, body=body, params=params, joint_index=joints, ft_index=ft,
            tilt_index=joints['mast_tilt'], inertial_rot=quat_to_matrix(q_in),
            com_offset=base_link_inertial(params)[1], arm_links=arm_links, card_index=card,
            arm_masses=np.array([d[0] for d in dyn]),
            arm_inertias=np.array([d[2] for d in dyn]),
            arm=JointTrajectoryFollower(ARM_JOINTS, ARM_HOME),
            mast=JointTrajectoryFollower(MAST_JOINTS, np.zeros(2)),
            anchor_xy=np.array([x, y]), anchor_yaw=0.0, cmd=(0.0, 0.0),
            preload=np.zeros(6), prev_velocity=np.zeros(3), accel=np.zeros(3),
            wheel_rates=np.zeros(4), odom_xy=np.array([x, y]), odom_yaw=0.0)
        self._set_base_pose(rover, np.array([x, y, NOMINAL_HEIGHT_M]), np.eye(3))
        rover.preload = self._preload(rover)
        rover.actuated = [joints[j] for j in ARM_JOINTS]
        rover.mast_joints = [joints[j] for j in MAST_JOINTS]
        rover.pan_index = joints[MAST_JOINTS[0]]
        if self.braid is not None:
            # the chain starts straight and retracted (kinematic: its few tens of grams ride on
            # the mast links' masses, held at home; neither it nor the camera is drawn)
            rover.braid_states = np.zeros(self.braid.n, dtype=np.int64)
        # Arm joints are driven by explicit PD torques (TORQUE_CONTROL), gains scheduled on the
        # inertia each joint drives; PyBullet's POSITION_CONTROL motors act as velocity
        # constraints whose impulses no joint torque shows. Free the default velocity motors.
        pb.setJointMotorControlArray(body, rover.actuated, pb.VELOCITY_CONTROL,
                                     forces=[0.0] * len(rover.actuated), physicsClientId=c)
        rover.fast = FastCompliance(params.stiffness, params.damping, rover.preload, q_in,
                                    rover.com_offset, midpoint_damper=True)
        rover.movable = [j for j in sorted(joints.values())
                         if pb.getJointInfo(body, j, physicsClientId=c)[2] != pb.JOINT_FIXED]
        rover.mass_index = np.array(list(range(6))
                                    + [6 + rover.movable.index(j) for j in rover.actuated])
        rover.arm_prev = self._arm_momentum(rover)
        if self.probe_client is not None:
            rover.implicit = ImplicitSolver(params.stiffness, params.damping, rover.preload,
                                            len(rover.actuated))
            pc = self.probe_client
            rover.probe_body = pb.loadURDF(str(urdf), [x, y, NOMINAL_HEIGHT_M], [0, 0, 0, 1],
                                           flags=pb.URDF_USE_INERTIA_FROM_FILE,
                                           physicsClientId=pc)
            for j in [-1, *joints.values()]:
                pb.changeDynamics(rover.probe_body, j, linearDamping=0, angularDamping=0,
                                  physicsClientId=pc)
                if j >= 0:
                    pb.changeDynamics(rover.probe_body, j, jointDamping=0, physicsClientId=pc)
            pb.setJointMotorControlArray(rover.probe_body, rover.actuated, pb.VELOCITY_CONTROL,
                                         forces=[0.0] * len(rover.actuated), physicsClientId=pc)
        q0 = pb.getBasePositionAndOrientation(body, physicsClientId=c)[1]
        rover.prev_quat = rover.last_sub_quat = rover.prev_sub_quat = q0
        # at rest: the sensor carries the arm's weight
        st = rover.arm_prev
        rover.ft_mean = np.concatenate([
            st.sensor_rotation.T @ (-rover.arm_masses.sum() * GRAVITY_VEC),
            st.sensor_rotation.T @ (-st.gravity_moment)])
        return rover

    # ----------------------------------------------------------------- kinematics
    def _base_state(self, r: _Rover) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Base link origin (= c.g. of the sprung body) position, rotation, velocity, angular
        velocity, all world frame. PyBullet reports the base link's own c.o.m. and principal
        axes; both are moved back to the link frame here."""
        c = self.client
        com, orn = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)
        vel, ang = pb.getBaseVelocity(r.body, physicsClientId=c)
        rot = quat_to_matrix(orn) @ r.inertial_rot.T
        ox, oy, oz = rot @ r.com_offset
        wx, wy, wz = ang
        # v_origin = v_com - w x off (np.cross costs ~50 us on 3-vectors)
        v = (vel[0] - (wy * oz - wz * oy), vel[1] - (wz * ox - wx * oz),
             vel[2] - (wx * oy - wy * ox))
        return np.array((com[0] - ox, com[1] - oy, com[2] - oz)), rot, np.array(v), np.array(ang)

    def _set_base_pose(self, r: _Rover, pos: np.ndarray, rot: np.ndarray) -> None:
        q = matrix_to_quat(rot @ r.inertial_rot)
        pb.resetBasePositionAndOrientation(r.body, (pos + rot @ r.com_offset).tolist(),
                                           q.tolist(), physicsClientId=self.client)
        pb.resetBaseVelocity(r.body, [0, 0, 0], [0, 0, 0], physicsClientId=self.client)

    def _anchor(self, r: _Rover) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        v, w = r.cmd
        rot = rpy_to_matrix(0.0, 0.0, r.anchor_yaw)
        p = np.array([r.anchor_xy[0], r.anchor_xy[1], NOMINAL_HEIGHT_M])
        return p, rot, rot @ np.array([v, 0.0, 0.0]), np.array([0.0, 0.0, w])

    def _preload(self, r: _Rover) -> np.ndarray:
        c = self.client
        pos, _, _, _ = self._base_state(r)
        masses, coms = [], []
        for j in range(pb.getNumJoints(r.body, physicsClientId=c)):
            masses.append(pb.getDynamicsInfo(r.body, j, physicsClientId=c)[0])
            coms.append(pb.getLinkState(r.body, j, computeForwardKinematics=1,
                                        physicsClientId=c)[0])
        masses.append(pb.getDynamicsInfo(r.body, -1, physicsClientId=c)[0])
        coms.append(pos + self._base_state(r)[1] @ r.com_offset)
        _, rot_a, _, _ = self._anchor(r)
        return static_preload(np.array(masses), np.array(coms), pos, rot_a)

    def _arm_momentum(self, r: _Rover, *, probe: bool = False) -> ArmMomentum:
        """Momentum state of the links beyond the F/T sensor (positions at the end of the last
        sub-step, velocities of that sub-step: the engine's semi-implicit update). Scalar
        Python: numpy's per-call overhead on a handful of 3-vectors costs ~5x more here.

        probe: of the rover's copy in the probe world, posed by _probe_kick_state (the
        implicit step: positions of the last kick, its velocities), no shift of the gravity
        moment (it is the kick's own)."""
        client, body = (self.probe_client, r.probe_body) if probe else (self.client, r.body)
        sts = pb.getLinkStates(body, r.arm_links, computeLinkVelocity=1,
                               computeForwardKinematics=1, physicsClientId=client)
        px, py, pz = sts[0][4]                   # sensor origin (= its link's c.o.m.)
        qx, qy, qz = sts[0][6]                   # its velocity
        half = 0.0 if probe else 0.5 * self.substep_s
        g = GRAVITY_VEC[2]
        mom = [0.0, 0.0, 0.0]
        ang = [0.0, 0.0, 0.0]
        grav = [0.0, 0.0, 0.0]
        for st, m, inertia in zip(sts, r.arm_masses, r.arm_inertias, strict=False):
            (cx, cy, cz), quat, (vx, vy, vz), w = st[0], st[1], st[6], st[7]
            # spin I w, the principal inertia in the link's inertial frame
            bx, by, bz = quat_rotate_inverse(quat, w)
            sx, sy, sz = quat_rotate(quat, (inertia[0] * bx, inertia[1] * by, inertia[2] * bz))
            ax, ay, az = cx - px, cy - py, cz - pz
            mvx, mvy, mvz = m * vx, m * vy, m * vz
            mom[0] += mvx
            mom[1] += mvy
            mom[2] += mvz
            ang[0] += sx + ay * mvz - az * mvy
            ang[1] += sy + az * mvx - ax * mvz
            ang[2] += sz + ax * mvy - ay * mvx
            # the gravity moment averaged over a control step must be centred like the
            # differenced momenta, on the sub-step instants t_n: positions half a sub-step
            # back, moved by the velocities that moved them
            bx, by = ax - half * (vx - qx), ay - half * (vy - qy)
            grav[0] += by * m * g
            grav[1] -= bx * m * g
        return ArmMomentum(
            momentum=np.array(mom), ang_momentum=np.array(ang), gravity_moment=np.array(grav),
            transport=np.array([qy * mom[2] - qz * mom[1], qz * mom[0] - qx * mom[2],
                                qx * mom[1] - qy * mom[0]]),
            sensor_rotation=quat_to_matrix(sts[0][5]))

    def _link_rate(self, r: _Rover, qa: tuple, qb: tuple) -> np.ndarray:
        """Mean body rate (link axes) over one control period from two PyBullet base
        orientations (principal axes) a period apart."""
        return r.inertial_rot @ relative_rotation_vector(qa, qb) / self.dt

    def _arm_wrench(self, r: _Rover) -> np.ndarray:
        """Eq. B-1: the wrench (F_12, N_12) the base exerted on the arm at the sensor over the last
        control step, sensor axes, as the step mean (an F/T sensor's anti-alias filter): from
        the change of the arm's momentum, Newton-Euler on the links beyond the sensor,
            F = dP/dt - M g,   N = dH_p/dt + p_dot x P - sum (c_i - p) x m_i g.
        Differencing the momentum over the step is exact for the engine's semi-implicit
        sub-steps (the sum of m dv telescopes). PyBullet's own joint reaction (getJointState
        of a force/torque-enabled joint) is not used: it disagrees with the arm's motion by
        1-2 % of the torque in the excitation band (Bullet's multibody adds a second reaction
        computed in its constraint pass, velocity-product terms included), while the base
        moves exactly as the arm's momentum says; the inertia term is only 1-6 % of a moment
        row, and that reaction alone put I_x at 0.05 instead of 0.15 and I_xy at -0.06."""
        implicit = self.integrator is Integrator.IMPLICIT
        new, old = self._arm_momentum(r, probe=implicit), r.arm_prev
        assert old is not None                      # _build took the first
        r.arm_prev = new
        dt = self.dt
        force = (new.momentum - old.momentum) / dt - r.arm_masses.sum() * GRAVITY_VEC
        if implicit and self.substeps == 1:
            gravity = new.gravity_moment              # the one kick's
        elif implicit:
            # the kicks' gravity moments, from the period's first (at its start) to its last
            start = r.gravity_start if r.gravity_start is not None else new.gravity_moment
            r.gravity_start = self._arm_momentum(r).gravity_moment
            gravity = 0.5 * (new.gravity_moment + start)
        else:
            gravity = 0.5 * (new.gravity_moment + old.gravity_moment)
        torque = ((new.ang_momentum - old.ang_momentum) / dt
                  + 0.5 * (new.transport + old.transport) - gravity)
        if r.card_index is not None:
            # what the site and ground push on the card is not the base's: the sensor reads
            # the momentum change less the mean contact wrench, about the sensor's origin
            f_c, m_c = self._close_contact_step(r)
            force = force - f_c
            p = self._sensor_origin(r)
            torque = torque - (m_c - cross3(p, f_c))
        held = [k for k, q in enumerate(self.rovers[:2]) if q is r]
        if self.segment is not None and held:
            # the same for the segment's pull on the gripper (rover_sim.segment)
            f_s, m_s = self.segment.wrench_on_arm(held[0])
            force = force - f_s
            p = self._sensor_origin(r)
            torque = torque - (m_s - cross3(p, f_s))
        rot = 0.5 * (new.sensor_rotation + old.sensor_rotation)
        return np.concatenate([rot.T @ force, rot.T @ torque])

    def _accumulate_contact(self, r: _Rover) -> None:
        """Add one sub-step's contact forces on the card (force on the card: the normal force
        along the normal on the other body, less the two friction components; checked against
        a box at rest and sliding) to the step's sums."""
        acc = r.contact
        pts = pb.getContactPoints(bodyA=r.body, linkIndexA=r.card_index,
                                  physicsClientId=self.client)
        acc.points = len(pts)
        for p in pts:
            n, d1, d2 = p[7], p[11], p[13]
            fx = p[9] * n[0] - p[10] * d1[0] - p[12] * d2[0]
            fy = p[9] * n[1] - p[10] * d1[1] - p[12] * d2[1]
            fz = p[9] * n[2] - p[10] * d1[2] - p[12] * d2[2]
            x, y, z = p[5]
            acc.force += (fx, fy, fz)
            acc.moment += (y * fz - z * fy, z * fx - x * fz, x * fy - y * fx)
            acc.penetration = max(acc.penetration, -p[8])
            acc.bodies.add(self._body_kind.get(p[2], 'rover'))

    def _close_contact_step(self, r: _Rover) -> tuple[np.ndarray, np.ndarray]:
        """The step's mean contact force on the card and its mean moment about the world origin;
        keeps the step's ContactState (moment about the card's centre) and resets the sums."""
        acc = r.contact
        n = self.substeps
        f, m = acc.force / n, acc.moment / n
        centre = np.array(pb.getLinkState(r.body, r.card_index, computeForwardKinematics=1,
                                          physicsClientId=self.client)[4])
        r.last_contact = ContactState(
            stamp_s=self.time_s, force=f, torque=m - cross3(centre, f), points=acc.points,
            max_penetration_m=acc.penetration, bodies=tuple(sorted(acc.bodies)))
        r.contact = _Contact()
        return f, m

    def _sensor_origin(self, r: _Rover) -> np.ndarray:
        return np.array(pb.getLinkState(r.body, r.ft_index, computeForwardKinematics=1,
                                        physicsClientId=self.client)[4])

    def mass_points(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every link's mass (n,), world c.o.m. (n, 3) and its velocity (n, 3), the base first:
        the rover as the particles of Eq. A-5, for a ground-truth zero-moment point (the
        accelerations by differencing the velocities of successive steps)."""
        r = self.rovers[index]
        c = self.client
        com, _ = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)
        vel, _ = pb.getBaseVelocity(r.body, physicsClientId=c)
        masses, coms, vels = [pb.getDynamicsInfo(r.body, -1, physicsClientId=c)[0]], [com], [vel]
        for j in range(pb.getNumJoints(r.body, physicsClientId=c)):
            st = pb.getLinkState(r.body, j, computeLinkVelocity=1, computeForwardKinematics=1,
                                 physicsClientId=c)
            masses.append(pb.getDynamicsInfo(r.body, j, physicsClientId=c)[0])
            coms.append(st[0])
            vels.append(st[6])
        return np.array(masses), np.array(coms), np.array(vels)

    def set_gripper_load(self, index: int, mass_kg: float) -> None:
        """Make what rover `index` holds (its card link) weigh `mass_kg`: a part, for app. A's
        heavy-load studies. ValueError for a rover with nothing in its gripper."""
        r = self.rovers[index]
        if r.card_index is None or not (math.isfinite(mass_kg) and mass_kg > 0.0):
            raise ValueError(f'{r.name}: no card to load, or mass {mass_kg} not > 0')
        pb.changeDynamics(r.body, r.card_index, mass=float(mass_kg), physicsClientId=self.client)
        r.arm_masses = np.array([pb.getDynamicsInfo(r.body, j, physicsClientId=self.client)[0]
                                 for j in r.arm_links])

    def grasp_point(self, index: int) -> np.ndarray:
        """Where rover `index`'s gripper holds a part (the card's centre's place: CARD_OFFSET_M
        along the last arm link), world frame, now."""
        r = self.rovers[index]
        st = pb.getLinkState(r.body, r.joint_index['arm_joint_4'], computeForwardKinematics=1,
                             physicsClientId=self.client)
        return np.array(st[4]) + quat_to_matrix(st[5]) @ np.array([CARD_OFFSET_M, 0.0, 0.0])

    def grasp_segment(self, spec: SegmentSpec, stage: StageSpec) -> SegmentCarry:
        """App. A.4: rovers 1 and 2 grasp one rigid segment where their grippers are now, and
        the truss stage is built (rover_sim.segment; SegmentError when it cannot be)."""
        if self.segment is not None:
            raise ValueError('a segment is already held')
        if any(r.card_index is not None for r in self.rovers[:2]):
            raise ValueError('a rover that holds the card cannot grasp the segment')
        self.segment = SegmentCarry(self, spec, stage)
        return self.segment

    def link_masses_and_coms(self, index: int, links: Sequence[int]) -> tuple[np.ndarray,
                                                                              np.ndarray]:
        """Masses and world c.o.m. positions of the given links (used by tests)."""
        r = self.rovers[index]
        c = self.client
        m = np.array([pb.getDynamicsInfo(r.body, j, physicsClientId=c)[0] for j in links])
        p = np.array([pb.getLinkState(r.body, j, computeForwardKinematics=1,
                                      physicsClientId=c)[0] for j in links])
        return m, p

    # ----------------------------------------------------------------- commands
    def rover_index(self, name: str) -> int:
        for i, r in enumerate(self.rovers):
            if r.name == name:
                return i
        raise KeyError(name)

    def command_arm(self, index: int, names: Sequence[str], times_s: Sequence[float],
                    positions: Sequence[Sequence[float]], start_s: float | None = None,
                    velocities: Sequence[Sequence[float]] | None = None) -> None:
        """Follow an arm trajectory (TrajectoryError on a bad one, the old one kept); with
        velocities, cubic interpolation (trajectory.JointTrajectoryFollower)."""
        r = self.rovers[index]
        now = self.time_s
        q, qd = r.arm.target(now)
        r.arm.set(names, times_s, positions, now if start_s is None or start_s <= 0 else start_s,
                  q, velocities=velocities, current_velocity=qd)

    def command_arm_feedforward(self, index: int, torques: Sequence[float] | np.ndarray
                                ) -> None:
        """Joint torques (N m, one per arm joint) added to the arm's PD from the next step on,
        held until the next call: a feed-forward the host computes (coop_insertion.feedforward);
        zeros switch it off."""
        tau = np.asarray(torques, dtype=float)
        if tau.shape != (len(ARM_JOINTS),) or not np.all(np.isfinite(tau)):
            raise ValueError(f'arm feed-forward: need {len(ARM_JOINTS)} finite torques')
        self.rovers[index].tau_ff = tau

    def command_mast(self, index: int, names: Sequence[str], times_s: Sequence[float],
                     positions: Sequence[Sequence[float]], start_s: float | None = None) -> None:
        r = self.rovers[index]
        if self.braid is not None and MAST_JOINTS[1] in names:
            raise TrajectoryError(f'{MAST_JOINTS[1]}: a BRAID mast has no tilt joint (its '
                                  'chain pitches the camera: command_braid)')
        now = self.time_s
        r.mast.set(names, times_s, positions, now if start_s is None or start_s <= 0 else start_s,
                   r.mast.target(now)[0])

    def command_braid(self, index: int, states: Sequence[int] | np.ndarray) -> float:
        """Command rover `index`'s BRAID mast to a chain state (n stage states 0..7, base
        first): the legs switch (coop_braid.carrier's commands, one per leg that differs) and
        the camera moves to the state's pose `config.braid_settle_s` later (until then it stays
        where it was). Returns the sim time it takes effect. ValueError for a pan/tilt mast or
        a state that is not n integers in 0..7."""
        if self.braid is None:
            raise ValueError(f'rover {index + 1} has a {self.config.mast.value} mast, not braid')
        arr = np.asarray(states)
        if arr.shape != (self.braid.n,) or not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f'BRAID state: {self.braid.n} integers (one per stage), not '
                             f'{arr.dtype} {arr.shape}')
        s = self.braid.chain.check_states(arr)      # BraidError (a ValueError): not in 0..7
        at = self.time_s + self.config.braid_settle_s
        self.rovers[index].braid_pending = (at, s.copy())
        if self.config.braid_settle_s == 0.0:
            self._settle_braid(self.rovers[index])
        return at

    def braid_state(self, index: int) -> np.ndarray | None:
        """The BRAID state in effect on rover `index` (None: a pan/tilt mast)."""
        st = self.rovers[index].braid_states
        return None if st is None else st.copy()

    def _settle_braid(self, r: _Rover) -> None:
        if r.braid_pending is not None and self.time_s >= r.braid_pending[0] - 1e-9:
            r.braid_states = r.braid_pending[1]
            r.braid_pending = None

    def place_rover(self, index: int, x: float, y: float, yaw: float = 0.0) -> None:
        """Put rover `index` at rest at (x, y, yaw) (its chassis anchor and odometry too), arm
        and mast as they are: a scenario's start, e.g. the slave near the insertion site."""
        if not all(math.isfinite(v) for v in (x, y, yaw)):
            raise ValueError('place_rover: x, y and yaw must be finite')
        r = self.rovers[index]
        c = self.client
        r.anchor_xy = np.array([x, y], dtype=float)
        r.anchor_yaw = float(yaw)
        r.odom_xy, r.odom_yaw = r.anchor_xy.copy(), float(yaw)
        r.cmd = (0.0, 0.0)
        self._set_base_pose(r, np.array([x, y, NOMINAL_HEIGHT_M]), rpy_to_matrix(0.0, 0.0, yaw))
        for j in r.actuated + r.mast_joints:
            pb.resetJointState(r.body, j, pb.getJointState(r.body, j, physicsClientId=c)[0],
                               targetVelocity=0.0, physicsClientId=c)
        r.prev_velocity = np.zeros(3)
        r.arm_prev = self._arm_momentum(r)
        r.gravity_start = None
        q = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)[1]
        r.prev_quat = r.last_sub_quat = r.prev_sub_quat = q
        r.contact = _Contact()
        assert r.fast is not None                   # _build gives every rover one
        r.fast.reset()

    def command_velocity(self, index: int, v: float, w: float) -> None:
        """Skid-steer body speed (m/s) and yaw rate (rad/s), clipped to the rover's limits."""
        if not (math.isfinite(v) and math.isfinite(w)):
            raise ValueError('velocity command must be finite')
        cfg = self.config
        self.rovers[index].cmd = (float(np.clip(v, -cfg.max_linear_speed_m_s,
                                                cfg.max_linear_speed_m_s)),
                                  float(np.clip(w, -cfg.max_yaw_rate_rad_s,
                                                cfg.max_yaw_rate_rad_s)))

    # ----------------------------------------------------------------- stepping
    def step(self) -> None:
        """Advance one control period (1 / physics_rate_hz): the compliance and the arm's PD
        solved implicitly with each engine step (Integrator.IMPLICIT) or applied as forces at
        every physics sub-step (EXPLICIT)."""
        c = self.client
        h = self.dt / self.substeps
        implicit = self.integrator is Integrator.IMPLICIT
        targets = []
        for r in self.rovers:
            mp, mv = r.mast.target(self.time_s)
            q_arm = [st[0] for st in pb.getJointStates(r.body, r.actuated, physicsClientId=c)]
            inertia = arm_joint_inertias(np.array(q_arm))
            # the arm reference at the PD's own instants: held over a whole control step, its
            # speed would step at 200 Hz and kick the base at the sensors' own rate
            hold = 1 if implicit else PD_HOLD
            q_ref, qd_ref = r.arm.targets([self.time_s + h * sub
                                           for sub in range(0, self.substeps, hold)])
            targets.append((q_ref, qd_ref,
                            (inertia * PD_OMEGA ** 2).tolist(),
                            (2.0 * inertia * PD_OMEGA).tolist()))
            # the mast does not load the arm's F/T sensor: the engine's motors hold it
            for client, body in ((c, r.body), (self.probe_client, r.probe_body)):
                if body is not None:
                    pb.setJointMotorControlArray(
                        body, r.mast_joints, pb.POSITION_CONTROL, targetPositions=mp.tolist(),
                        targetVelocities=mv.tolist(), positionGains=[MAST_BANDWIDTH * h] * 2,
                        velocityGains=[1.0] * 2, forces=[5.0, 5.0], physicsClientId=client)
        if implicit:
            self._implicit_steps(targets, h)
        else:
            self._explicit_substeps(targets, h)
        self._finish_step()

    def _implicit_steps(self, targets: list, h: float) -> None:
        """The engine steps of one control period, each with the compliance wrench and the arm
        torques of the linearly implicit solve (rover_sim.implicit)."""
        c, pc = self.client, self.probe_client
        effort = np.array(ARM_EFFORT_NM)
        for sub in range(self.substeps):
            # the probe: each rover's step alone, free of the stiff forces
            starts = []
            for r in self.rovers:
                states = pb.getJointStates(r.body, r.movable, physicsClientId=c)
                com, quat = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)
                vel, ang = pb.getBaseVelocity(r.body, physicsClientId=c)
                pb.resetBasePositionAndOrientation(r.probe_body, com, quat, physicsClientId=pc)
                pb.resetBaseVelocity(r.probe_body, vel, ang, physicsClientId=pc)
                pb.resetJointStatesMultiDof(r.probe_body, r.movable,
                                            [[st[0]] for st in states],
                                            targetVelocities=[[st[1]] for st in states],
                                            physicsClientId=pc)
                starts.append((states, com, quat, vel, ang))
            pb.stepSimulation(physicsClientId=pc)
            for r, (q_refs, qd_refs, kp, kd), (states, com, quat, vel, ang) in zip(
                    self.rovers, targets, starts, strict=False):
                q_all = [st[0] for st in states]
                mass = np.array(pb.calculateMassMatrix(r.body, q_all, physicsClientId=c))
                mass = mass[np.ix_(r.mass_index, r.mass_index)]
                arm = r.mass_index[6:] - 6
                q = np.array([q_all[i] for i in arm])
                qd = np.array([states[i][1] for i in arm])
                rot = quat_to_matrix(quat)
                v, w = r.cmd
                cy, sy = math.cos(r.anchor_yaw), math.sin(r.anchor_yaw)
                assert r.fast is not None               # the implicit integrator has one
                origin, off, dr, dth, dv, dw = r.fast.state(
                    com, quat, vel, ang, (r.anchor_xy[0], r.anchor_xy[1], NOMINAL_HEIGHT_M),
                    r.anchor_yaw, (v * cy, v * sy, 0.0), w)
                ra = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
                kin = BaseKinematics(rot=rot, rot_anchor=ra, offset=-np.array(off),
                                     deflection=np.array(dr + dth), rate=np.array(dv + dw))
                u = np.concatenate([rot.T @ ang, rot.T @ vel, qd])
                pv, pw = pb.getBaseVelocity(r.probe_body, physicsClientId=pc)
                pqd = [st[1] for st in pb.getJointStates(r.probe_body, r.actuated,
                                                         physicsClientId=pc)]
                free = np.concatenate([rot.T @ np.array(pw), rot.T @ np.array(pv), pqd]) - u
                assert r.implicit is not None
                wrench, tau = r.implicit.solve(
                    h, mass, kin, free, np.asarray(q_refs[sub]) - q,
                    np.asarray(qd_refs[sub]) - qd, np.asarray(kp), np.asarray(kd), effort,
                    r.tau_ff)
                pb.setJointMotorControlArray(r.body, r.actuated, pb.TORQUE_CONTROL,
                                             forces=tau.tolist(), physicsClientId=c)
                pb.applyExternalForce(r.body, -1, (ra @ wrench[:3]).tolist(), origin,
                                      pb.WORLD_FRAME, physicsClientId=c)
                pb.applyExternalTorque(r.body, -1, (ra @ wrench[3:]).tolist(), pb.WORLD_FRAME,
                                       physicsClientId=c)
                if sub == self.substeps - 1:
                    r.last_sub_quat = quat
            pb.stepSimulation(physicsClientId=c)
            if sub == self.substeps - 1:
                for r, start in zip(self.rovers, starts, strict=False):
                    self._probe_kick_state(r, start)
            for r in self.rovers:
                if r.card_index is not None:
                    self._accumulate_contact(r)
                self._move_anchor(r, h)

    def _probe_kick_state(self, r: _Rover, start: tuple) -> None:
        """Pose the rover's probe copy at the positions of the last kick with the velocities it
        gave: the arm's momentum there telescopes over the kicks to exactly their impulses
        (momentum at the end positions would mix two configurations, an O(h) error at one
        engine step per period)."""
        c, pc = self.client, self.probe_client
        states, com, quat, _, _ = start
        vel, ang = pb.getBaseVelocity(r.body, physicsClientId=c)
        qd = [[st[1]] for st in pb.getJointStates(r.body, r.movable, physicsClientId=c)]
        pb.resetBasePositionAndOrientation(r.probe_body, com, quat, physicsClientId=pc)
        pb.resetBaseVelocity(r.probe_body, vel, ang, physicsClientId=pc)
        pb.resetJointStatesMultiDof(r.probe_body, r.movable, [[st[0]] for st in states],
                                    targetVelocities=qd, physicsClientId=pc)

    def _move_anchor(self, r: _Rover, h: float) -> None:
        v, w = r.cmd
        if v != 0.0 or w != 0.0:
            r.anchor_yaw += w * h
            r.anchor_xy[0] += h * v * math.cos(r.anchor_yaw)
            r.anchor_xy[1] += h * v * math.sin(r.anchor_yaw)

    def _explicit_substeps(self, targets: list, h: float) -> None:
        """The physics sub-steps of one control period, the compliance and the arm's PD
        applied as explicit forces at each."""
        c = self.client
        last = self.substeps - 1
        for sub in range(self.substeps):
            for r, (q_refs, qd_refs, kp, kd) in zip(self.rovers, targets, strict=False):
                if sub % PD_HOLD == 0:
                    # PD torques held for PD_HOLD sub-steps (zero-order hold, 2 w h << 1)
                    q_ref, qd_ref = q_refs[sub // PD_HOLD], qd_refs[sub // PD_HOLD]
                    states = pb.getJointStates(r.body, r.actuated, physicsClientId=c)
                    tau = r.tau
                    for j, st in enumerate(states):
                        t_j = (kp[j] * (q_ref[j] - st[0]) + kd[j] * (qd_ref[j] - st[1])
                               + r.tau_ff[j])
                        tau[j] = max(-ARM_EFFORT_NM[j], min(ARM_EFFORT_NM[j], t_j))
                pb.setJointMotorControlArray(r.body, r.actuated, pb.TORQUE_CONTROL, forces=r.tau,
                                             physicsClientId=c)
                pos, quat = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)
                vel, ang = pb.getBaseVelocity(r.body, physicsClientId=c)
                if sub == last:
                    r.last_sub_quat = quat
                v, w = r.cmd
                cy, sy = math.cos(r.anchor_yaw), math.sin(r.anchor_yaw)
                assert r.fast is not None
                f, t, at = r.fast.wrench(pos, quat, vel, ang,
                                         (r.anchor_xy[0], r.anchor_xy[1], NOMINAL_HEIGHT_M),
                                         r.anchor_yaw, (v * cy, v * sy, 0.0), w)
                pb.applyExternalForce(r.body, -1, f, at, pb.WORLD_FRAME, physicsClientId=c)
                pb.applyExternalTorque(r.body, -1, t, pb.WORLD_FRAME, physicsClientId=c)
            pb.stepSimulation(physicsClientId=c)
            if self.segment is not None:
                self.segment.accumulate()
            for r in self.rovers:
                if r.card_index is not None:
                    self._accumulate_contact(r)
                self._move_anchor(r, h)

    def _finish_step(self) -> None:
        """The control period's sensor means, odometry and clock."""
        c = self.client
        self.time_s = (self.steps + 1) * self.dt
        self.steps += 1
        if self.segment is not None:
            self.segment.close_step(self.time_s)
        for r in self.rovers:
            self._settle_braid(r)
            # Every inertial sensor reads its mean over the control period (anti-alias
            # filter), all over the same span. The engine's velocities are those of a sub-step
            # (t_n, t_n+1), its positions those of the instants: the F/T (arm momentum) and
            # the accelerometer, differenced velocities, average over the instants t_n of the
            # period, i.e. over (t_k-1 - h/2, t_k - h/2).
            r.ft_mean = self._arm_wrench(r)
            _, _, vel, _ = self._base_state(r)
            r.accel = (vel - r.prev_velocity) / self.dt
            r.prev_velocity = vel
            # The gyro, the mean body rate at the same instants: the mean of the rotation over
            # the period and over the period one sub-step earlier. (The rotation over the
            # period alone runs h/2 ahead of the F/T; with the damping torque ~70 times the
            # inertial one at 30 rad/s, that skew alone moves the identified inertias by -B h/2.
            # A point sample of the rate misreads it: with b/I ~ 2000 1/s it ripples within 5 ms.)
            quat = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)[1]
            r.gyro_mean = 0.5 * (self._link_rate(r, r.prev_quat, quat)
                                 + self._link_rate(r, r.prev_sub_quat, r.last_sub_quat))
            r.prev_quat, r.prev_sub_quat = quat, r.last_sub_quat
            v, w = r.cmd
            r.wheel_rates = wheel_speeds(v, w, track_m=TRACK_M, radius_m=WHEEL_RADIUS_M)
            odom_xy, odom_yaw = odometry_step(
                r.odom_xy, r.odom_yaw, v, w, self.dt, drift=self.config.noise.odom_drift,
                track_m=TRACK_M, noise=self.rng.standard_normal(3))
            r.odom_xy, r.odom_yaw = odom_xy, float(odom_yaw)

    # ----------------------------------------------------------------- sensing
    def camera_pose(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """True left optical frame (origin, rotation) in the map frame: the tilt link's, or
        with a BRAID mast the pan link's (the base deflected on its compliance) times the
        chain's forward kinematics for the state in effect."""
        r = self.rovers[index]
        if self.braid is not None:
            assert r.braid_states is not None
            st = pb.getLinkState(r.body, r.pan_index, computeForwardKinematics=1,
                                 physicsClientId=self.client)
            t = self.braid.optical_in_pan(r.braid_states)
            rot_p = quat_to_matrix(st[5])
            return np.array(st[4]) + rot_p @ t[:3, 3], rot_p @ t[:3, :3]
        st = pb.getLinkState(r.body, r.tilt_index, computeForwardKinematics=1,
                             physicsClientId=self.client)
        rot_t = quat_to_matrix(st[5])
        return np.array(st[4]) + rot_t @ np.array(CAMERA_OFFSET), rot_t @ OPTICAL_IN_TILT

    def truth(self, index: int) -> Truth:
        r = self.rovers[index]
        p, rot, v, w = self._base_state(r)
        pa, ra, va, wa = self._anchor(r)
        d = deflection(p, rot, v, w, pa, ra, va, wa)
        cp, cr = self.camera_pose(index)
        return Truth(self.time_s, p, rot, d.dr, d.dtheta, cp, cr, pa, r.anchor_yaw)

    def card_pose(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """True pose of the card carried by rover `index` (centre, rotation: x along its width,
        y its face normal, z its height; worldgen.Card), map frame. KeyError: no card."""
        r = self.rovers[index]
        if r.card_index is None:
            raise KeyError(f'{r.name} carries no card')
        st = pb.getLinkState(r.body, r.card_index, computeForwardKinematics=1,
                             physicsClientId=self.client)
        return np.array(st[4]), quat_to_matrix(st[5])

    def contact(self, index: int) -> ContactState | None:
        """The card's contacts over the last control step (None before the first step)."""
        return self.rovers[index].last_contact

    def insertion_depth(self, index: int, *, overlap_m: float = 5e-4) -> float:
        """How far the card's lower edge is into the slot below its mouth (m; negative: above
        it), counted only while both lower corners are between the jaws (else -inf), a corner
        against a jaw's wall counting as between them up to the contact solver's overlap
        (`overlap_m`, the penetration an insertion is allowed: a card pressed against a wall
        sits a few hundredths of a millimetre into it)."""
        site = self.layout.site
        pos, rot = self.card_pose(index)
        card = self.layout.card
        corners = [pos + rot @ np.array([u * card.width_m / 2, 0.0, v * card.height_m / 2])
                   for u in (-1, 1) for v in (-1, 1)]
        lower = sorted(corners, key=lambda q: q[2])[:2]
        x0 = site.slot_centre[0] - site.gap_m / 2
        x1 = site.slot_centre[0] + site.gap_m / 2
        y0 = site.slot_centre[1] - site.jaws[2].half_extents[1]
        y1 = site.slot_centre[1] + site.jaws[2].half_extents[1]
        if not all(x0 - overlap_m <= q[0] <= x1 + overlap_m and y0 <= q[1] <= y1
                   for q in lower):
            return -math.inf
        return float(site.slot_centre[2] - max(q[2] for q in lower))

    def seated(self, index: int, *, tolerance_m: float = 0.002) -> bool:
        """The card is between the jaws with its lower edge within `tolerance_m` of the slot's
        floor (the depth it is inserted to; penetration is judged apart, `contact`)."""
        return self.insertion_depth(index) >= self.layout.site.seat_depth_m - tolerance_m

    def joint_positions(self, index: int, names: Sequence[str]) -> np.ndarray:
        r = self.rovers[index]
        return np.array([pb.getJointState(r.body, r.joint_index[n], physicsClientId=self.client)[0]
                         for n in names])

    def sense(self, index: int) -> Readings:
        """Noisy readings of every sensor of rover `index` (§2.6.1 noise, app. D sensors)."""
        r = self.rovers[index]
        c = self.client
        rng = self.rng
        _, orn = pb.getBasePositionAndOrientation(r.body, physicsClientId=c)
        rot = quat_to_matrix(orn) @ r.inertial_rot.T
        # one draw for every channel (uniform on [-1, 1], scaled per channel): numpy's per-call
        # cost dominates at 200 Hz x rovers
        noise = rng.uniform(-1.0, 1.0, size=self._noise_bounds.size) * self._noise_bounds
        sf = specific_force(r.accel, rot) + noise[0:3]
        gyro = r.gyro_mean + noise[3:6]
        roll, pitch, _ = matrix_to_rpy(rot)
        angles, volts, sat = self.incl_model.read(roll, pitch, rng)
        ft = r.ft_mean
        force = ft[:3] + noise[6:9]
        torque = ft[3:] + noise[9:12]
        names = ARM_JOINTS + MAST_JOINTS
        states = pb.getJointStates(r.body, [r.joint_index[n] for n in names], physicsClientId=c)
        pos = np.array([s[0] for s in states]) + noise[12:18]
        vel = np.array([s[1] for s in states])
        tach = r.wheel_rates + noise[18:22]
        pot = noise[22:23]    # flat ground: the articulation stays straight
        all_names = names + WHEELS + ('articulation',)
        return Readings(
            stamp_s=self.time_s, specific_force=sf, angular_velocity=gyro, incl_angles=angles,
            incl_volts=volts, incl_saturated=sat, incl_variance=self.incl_model.variance(),
            force=force, torque=torque, joint_names=all_names,
            joint_positions=np.concatenate([pos, np.full(4, np.nan), pot]),
            joint_velocities=np.concatenate([vel, tach, [0.0]]))

    def odometry(self, index: int) -> tuple[np.ndarray, float, float, float]:
        """Dead-reckoned (xy, yaw) from the tachometers, and the commanded (v, w)."""
        r = self.rovers[index]
        return r.odom_xy.copy(), r.odom_yaw, r.cmd[0], r.cmd[1]

    def estimated_camera_pose(self, index: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rover's own estimate of its left optical pose: odometry + encoders + nominal mast
        kinematics, blind to the compliance deflection. Returns (position, rotation, 6x6 cov)."""
        r = self.rovers[index]
        pan, tilt = self.joint_positions(index, MAST_JOINTS)
        rot_base = rpy_to_matrix(0.0, 0.0, r.odom_yaw)
        base = np.array([r.odom_xy[0], r.odom_xy[1], NOMINAL_HEIGHT_M])
        rot_pan = rot_base @ rpy_to_matrix(0.0, 0.0, pan)
        p_pan = base + rot_base @ np.array(MAST_POSITION)
        travelled = np.linalg.norm(r.odom_xy - r.anchor_xy) + 0.01
        cov = np.diag([travelled ** 2 * 0.25] * 2 + [1e-4] + [(2 * DEG) ** 2] * 3)
        if self.braid is not None:
            # the binary mast has no sensor of its own: the state it was commanded to (in
            # effect once settled) and the chain's nominal forward kinematics
            assert r.braid_states is not None
            t = self.braid.optical_in_pan(r.braid_states)
            return p_pan + rot_pan @ t[:3, 3], rot_pan @ t[:3, :3], cov
        rot_tilt = rot_pan @ rpy_to_matrix(0.0, tilt, 0.0)
        p_tilt = p_pan + rot_pan @ np.array([0.0, 0.0, TILT_ABOVE_PAN_M])
        pos = p_tilt + rot_tilt @ np.array(CAMERA_OFFSET)
        return pos, rot_tilt @ OPTICAL_IN_TILT, cov

    # ----------------------------------------------------------------- rendering
    def intrinsics(self) -> np.ndarray:
        """3x3 K of both (rectified, identical) cameras: principal point at the image centre;
        render_stereo_at draws the images of this K (coop_common.rendering)."""
        w, h = self.config.image_width, self.config.image_height
        f = (w / 2.0) / math.tan(math.radians(self.config.hfov_deg) / 2.0)
        return np.array([[f, 0.0, (w - 1) / 2.0], [0.0, f, (h - 1) / 2.0], [0.0, 0.0, 1.0]])

    def render_stereo(self, index: int) -> tuple[np.ndarray, np.ndarray]:
        """Left and right mono8 images of rover `index`'s stereo pair (TinyRenderer)."""
        return self.render_stereo_at(*self.camera_pose(index))

    def render_stereo_at(self, pos: np.ndarray, rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Left and right mono8 images of a stereo pair whose left optical frame is at `pos`
        with orientation `rot` (columns: optical x right, y down, z forward) in the world;
        config.supersample n > 1 renders n x n samples per pixel and averages them (pixel
        integration, coop_common.rendering; n^2 times the rendering cost). With
        config.render_workers the right eye is drawn by a second process meanwhile
        (render_worker), the same images; should it fail, both are drawn here from then on
        and `render_note` says why."""
        pos, rot = np.asarray(pos, dtype=float), np.asarray(rot, dtype=float)
        worker = self._worker()
        if worker is not None:
            try:
                worker.request(self.poses(), pos, rot, STEREO_BASELINE_M)
                left = self.render_eye(pos, rot, 0.0)
                return left, worker.result()
            except RenderWorkerError as exc:
                self._stop_worker(f'{exc}: both eyes rendered in the simulator from now on')
        return self.render_eye(pos, rot, 0.0), self.render_eye(pos, rot, STEREO_BASELINE_M)

    def render_eye(self, pos: np.ndarray, rot: np.ndarray, offset: float) -> np.ndarray:
        """One mono8 image of the camera `offset` m along optical x from the left optical frame
        at `pos`, `rot` (render_stereo_at)."""
        n = self.config.supersample
        w, h = n * self.config.image_width, n * self.config.image_height
        proj = projection_matrix(fine_intrinsics(self.intrinsics(), n), w, h, 0.05, 60.0)
        pos, rot = np.asarray(pos, dtype=float), np.asarray(rot, dtype=float)
        eye = pos + rot[:, 0] * offset
        view = pb.computeViewMatrix(eye.tolist(), (eye + rot[:, 2]).tolist(),
                                    (-rot[:, 1]).tolist())
        renderer = (pb.ER_BULLET_HARDWARE_OPENGL if self.renderer is Renderer.EGL
                    else pb.ER_TINY_RENDERER)
        _, _, rgba, _, _ = pb.getCameraImage(w, h, view, proj, renderer=renderer,
                                             flags=pb.ER_NO_SEGMENTATION_MASK,
                                             physicsClientId=self.client)
        rgb = np.reshape(np.asarray(rgba, dtype=np.uint8), (h, w, 4))[:, :, :3]
        return pixel_average(cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2GRAY), n)

    def poses(self) -> list[tuple]:
        """Every rover's pose as the renderer sees it: base (position, orientation) and the
        positions of its moving joints (set_poses puts a copy of the world there)."""
        c = self.client
        return [(*pb.getBasePositionAndOrientation(r.body, physicsClientId=c),
                 [st[0] for st in pb.getJointStates(r.body, r.movable, physicsClientId=c)])
                for r in self.rovers]

    def set_poses(self, poses: Sequence[tuple]) -> None:
        """Pose this world's rovers as `poses` (another World's `poses()`), for a picture."""
        c = self.client
        for r, (pos, orn, joints) in zip(self.rovers, poses, strict=False):
            pb.resetBasePositionAndOrientation(r.body, pos, orn, physicsClientId=c)
            pb.resetJointStatesMultiDof(r.body, r.movable, [[q] for q in joints],
                                        physicsClientId=c)

    def _worker(self) -> RenderWorker | None:
        if self.config.render_workers < 1 or self.render_note is not None:
            return None
        if self._render_worker is None:
            try:
                self._render_worker = RenderWorker(self.config, self._truths)
            except (OSError, RenderWorkerError) as exc:
                self.render_note = (f'render worker did not start ({exc}): both eyes rendered '
                                    'in the simulator')
                return None
        return self._render_worker

    def hand_over_renderer(self, config: SimConfig, truths: Sequence[BaseParameters]
                           ) -> RenderWorker | None:
        """This world's render worker for a new world of `config` and `truths`, when that is the
        same scene (the worker holds a copy of the scene and is told the rovers' poses with
        each picture, so where they stand does not matter); None otherwise. Handed over, it is
        no longer this world's (close leaves it running)."""
        same = config == self.config and len(truths) == len(self._truths) and all(
            np.array_equal(a.to_vector(), b.to_vector())
            for a, b in zip(truths, self._truths, strict=False))
        if not same:
            return None
        worker, self._render_worker = self._render_worker, None
        return worker

    def _stop_worker(self, note: str | None) -> None:
        if self._render_worker is not None:
            self._render_worker.close()
            self._render_worker = None
        self.render_note = note

    # ----------------------------------------------------------------- life cycle
    def close(self) -> None:
        self._stop_worker(self.render_note)
        if self.probe_client is not None:
            with contextlib.suppress(pb.error):
                pb.disconnect(physicsClientId=self.probe_client)
            self.probe_client = None
        if self.client is not None and self.client >= 0:
            try:
                if self._egl_plugin >= 0:
                    pb.unloadPlugin(self._egl_plugin, physicsClientId=self.client)
                pb.disconnect(physicsClientId=self.client)
            except pb.error:
                pass
            self.client = -1
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> World:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


__all__ = [
    'ArmMomentum',
    'ContactState',
    'Readings',
    'Truth',
    'World',
    'rotation_vector',
    'substeps_for',
]
