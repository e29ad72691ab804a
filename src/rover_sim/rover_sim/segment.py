"""Two rovers carrying one part (app. A.4, Figs. A-9..A-12): a rigid truss segment held in both
grippers and the truss stage it is inserted into.

The segment is a box along the line between the two grasp points (world y when the rovers
stand side by side facing +x), held by a fixed constraint at each gripper's grasp point (where
the card's centre sits in the card scenario: CARD_OFFSET_M along the last arm link). The
stage is a U-channel along the same line: two walls and a floor, the channel a little wider
than the segment. The insertion is planar in x-z, as the thesis's model of A.4 is: the
segment's cross-section goes into the channel's.

`SegmentCarry` owns the PyBullet bodies and constraints; `World` calls it every engine
sub-step (`accumulate`) and at the end of each control step (`close_step`), and subtracts
`wrench_on_arm` from the arm's F/T reading as it does the card's contact: what the segment pulls
on the gripper is not the base's push. The constraint forces and the stage's contact forces are
ground truth (`SegmentTruth`): they score an experiment, no controller reads them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING

import numpy as np
import pybullet as pb

from .compliance import matrix_to_quat
from .errors import SimError

if TYPE_CHECKING:
    from .world import World


class SegmentError(SimError):
    """A segment or stage that cannot be built: bad dimensions, a world that cannot hold it."""


@dataclass(frozen=True)
class SegmentSpec:
    """The truss segment: a box, its length along the grasp line (grasp points `overhang_m`
    in from its ends), `width_m` along x and `height_m` along z, its mass."""

    mass_kg: float = 0.5
    width_m: float = 0.04
    height_m: float = 0.04
    overhang_m: float = 0.05

    def __post_init__(self) -> None:
        for name in ('mass_kg', 'width_m', 'height_m'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise SegmentError(f'segment {name}: must be a positive number, got {v!r}')
        if not (math.isfinite(self.overhang_m) and self.overhang_m >= 0):
            raise SegmentError(f'segment overhang_m: must be >= 0, got {self.overhang_m!r}')


@dataclass(frozen=True)
class StageSpec:
    """The truss stage: a channel along the grasp line, `centre_x` (world x of its middle
    plane), `top_z` (its mouth, world z), `clearance_m` wider than the segment, `depth_m` deep,
    `length_m` long, centred between the grasps; walls `wall_m` thick."""

    centre_x: float
    top_z: float
    clearance_m: float = 0.004
    depth_m: float = 0.05
    length_m: float = 0.8
    wall_m: float = 0.03

    def __post_init__(self) -> None:
        for name in ('clearance_m', 'depth_m', 'length_m', 'wall_m'):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise SegmentError(f'stage {name}: must be a positive number, got {v!r}')
        if not (math.isfinite(self.centre_x) and math.isfinite(self.top_z) and self.top_z > 0
                and self.depth_m < self.top_z):
            raise SegmentError('stage: centre_x and top_z must be finite, the floor above ground')


@dataclass(frozen=True)
class SegmentTruth:
    """The segment over the last control step (ground truth, world frame): its centre and
    rotation at the step's end, the mean force and moment (about each grasp point) each
    rover's gripper exerted on it, the mean contact force of the stage and ground on it, its
    deepest overlap into them, and whether it is seated."""

    stamp_s: float
    position: np.ndarray
    rotation: np.ndarray
    grasp_force: np.ndarray           # (2, 3): rover k's gripper on the segment, N
    grasp_moment: np.ndarray          # (2, 3): about rover k's grasp point, N m
    contact_force: np.ndarray         # (3,): stage and ground on the segment, N
    max_penetration_m: float
    seated: bool

    @property
    def internal_force(self) -> np.ndarray:
        """The part of the grippers' forces that cancels out, 1/2 (f_1 - f_2) (equal shares
        of the resultant): what squeezes or stretches the segment between the rovers."""
        return 0.5 * (self.grasp_force[0] - self.grasp_force[1])


@dataclass
class _Sums:
    force: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    moment: np.ndarray = field(default_factory=lambda: np.zeros((2, 3)))
    contact: np.ndarray = field(default_factory=lambda: np.zeros(3))
    penetration: float = 0.0
    n: int = 0


class SegmentCarry:
    """The segment held by rovers 0 and 1 of a world, and the stage (module docstring)."""

    def __init__(self, world: World, spec: SegmentSpec, stage: StageSpec) -> None:
        """Grasp a new segment between the two first rovers' grippers where they are now (no
        internal force at the grasp), and build the stage. SegmentError: fewer than two
        rovers, an implicit integrator (its probe world has no segment), a grasp line that is
        not horizontal within 5 cm, or a stage that overlaps the segment."""
        from .config import Integrator  # noqa: PLC0415 - config imports nothing of ours here
        if len(world.rovers) < 2:
            raise SegmentError('the segment needs two rovers')
        if world.integrator is not Integrator.EXPLICIT:
            raise SegmentError('the segment needs the explicit integrator (the implicit '
                               "step's probe world has no segment)")
        self.world, self.spec, self.stage = world, spec, stage
        c = world.client
        grips = [self._grasp_point(k) for k in (0, 1)]
        g0, g1 = (g[0] for g in grips)
        axis = g1 - g0
        span = float(np.linalg.norm(axis))
        if span < 0.2 or abs(axis[2]) > 0.05:
            raise SegmentError(f'grasp points {np.round(g0, 3).tolist()} and '
                               f'{np.round(g1, 3).tolist()}: not a horizontal span >= 0.2 m')
        y = axis / span
        x = np.cross(y, [0.0, 0.0, 1.0])
        x /= np.linalg.norm(x)
        self._rot = np.column_stack([x, y, np.cross(x, y)])
        centre = 0.5 * (g0 + g1)
        self.length_m = span + 2 * spec.overhang_m
        half = [spec.width_m / 2, self.length_m / 2, spec.height_m / 2]
        quat = [float(v) for v in matrix_to_quat(self._rot)]
        self.body = pb.createMultiBody(
            baseMass=spec.mass_kg,
            baseCollisionShapeIndex=pb.createCollisionShape(pb.GEOM_BOX, halfExtents=half,
                                                            physicsClientId=c),
            baseVisualShapeIndex=pb.createVisualShape(pb.GEOM_BOX, halfExtents=half,
                                                      rgbaColor=[0.8, 0.6, 0.2, 1],
                                                      physicsClientId=c),
            basePosition=centre.tolist(), baseOrientation=quat, physicsClientId=c)
        pb.changeDynamics(self.body, -1, lateralFriction=world.config.contact_friction,
                          linearDamping=0, angularDamping=0, physicsClientId=c)
        # the rovers' links touch nothing (the world's rule); the grasp is the constraint
        for r in world.rovers:
            for j in range(-1, pb.getNumJoints(r.body, physicsClientId=c)):
                pb.setCollisionFilterPair(self.body, r.body, -1, j, 0, physicsClientId=c)
        self.grasp_in_segment = [self._rot.T @ (g - centre) for g in (g0, g1)]
        self.constraints = []
        for k, (g, link) in enumerate(((g0, grips[0][1]), (g1, grips[1][1]))):
            body = world.rovers[k].body
            com, orn = pb.getLinkState(body, link, computeForwardKinematics=1,
                                       physicsClientId=c)[:2]
            inv_p, inv_o = pb.invertTransform(com, orn)
            # the joint frame: at the grasp point, with the segment's axes
            lp, lo = pb.multiplyTransforms(inv_p, inv_o, g.tolist(), quat)
            cid = pb.createConstraint(body, link, self.body, -1, pb.JOINT_FIXED, [0, 0, 0],
                                      parentFramePosition=lp,
                                      childFramePosition=self.grasp_in_segment[k].tolist(),
                                      parentFrameOrientation=lo,
                                      childFrameOrientation=[0, 0, 0, 1], physicsClientId=c)
            pb.changeConstraint(cid, maxForce=1e4, physicsClientId=c)
            self.constraints.append(cid)
        self._build_stage(centre, y)
        self._sums = _Sums()
        self.last: SegmentTruth | None = None
        self._on_arm = np.zeros((2, 6))

    def _grasp_point(self, k: int) -> tuple[np.ndarray, int]:
        """Rover k's grasp point (world) and its last arm link."""
        return self.world.grasp_point(k), self.world.rovers[k].joint_index['arm_joint_4']

    def _build_stage(self, centre: np.ndarray, axis: np.ndarray) -> None:
        st, sp, c = self.stage, self.spec, self.world.client
        gap = sp.width_m + st.clearance_m
        yc = float(centre[1])
        floor_z = st.top_z - st.depth_m
        boxes = (  # (kind, centre, half extents): near wall, far wall, floor (world axes)
            ('stage_near', (st.centre_x - gap / 2 - st.wall_m / 2, yc, st.top_z / 2),
             (st.wall_m / 2, st.length_m / 2, st.top_z / 2)),
            ('stage_far', (st.centre_x + gap / 2 + st.wall_m / 2, yc, st.top_z / 2),
             (st.wall_m / 2, st.length_m / 2, st.top_z / 2)),
            ('stage_floor', (st.centre_x, yc, floor_z / 2), (gap / 2, st.length_m / 2,
                                                             floor_z / 2)))
        if abs(axis[0]) > 1e-3:
            raise SegmentError('the stage is built along world y: the grasp line must be too')
        self.stage_bodies = []
        for kind, pos, half in boxes:
            body = self.world._static_body(
                pb.createVisualShape(pb.GEOM_BOX, halfExtents=list(half),
                                     rgbaColor=[0.35, 0.35, 0.4, 1], physicsClientId=c),
                pos, collision=pb.createCollisionShape(pb.GEOM_BOX, halfExtents=list(half),
                                                       physicsClientId=c))
            self.world._body_kind[body] = kind
            self.stage_bodies.append(body)
        lo, hi = self.bottom_and_top()
        if lo < st.top_z + 0.005 and abs(float(centre[0]) - st.centre_x) < gap / 2 + 0.05:
            raise SegmentError('the stage overlaps the segment where it is grasped')
        del hi

    def bottom_and_top(self) -> tuple[float, float]:
        """World z of the segment's lowest and highest corner now."""
        pos, orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.world.client)
        rot = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        h = np.array([self.spec.width_m, self.length_m, self.spec.height_m]) / 2
        zs = [pos[2] + rot[2] @ (h * np.array([a, b, d]))
              for a in (-1, 1) for b in (-1, 1) for d in (-1, 1)]
        return float(min(zs)), float(max(zs))

    # ------------------------------------------------------------- stepping (World calls)
    def accumulate(self) -> None:
        """Add one engine sub-step's constraint and contact forces to the step's sums."""
        c = self.world.client
        s = self._sums
        for k, cid in enumerate(self.constraints):
            st = pb.getConstraintState(cid, physicsClientId=c)
            # the constraint's force and moment on its parent, the gripper (world axes)
            s.force[k] -= st[:3]
            s.moment[k] -= st[3:6]
        for p in pb.getContactPoints(bodyA=self.body, physicsClientId=c):
            n, d1, d2 = p[7], p[11], p[13]
            # the force on body A (the segment): along the normal from B to A, less friction
            s.contact += [p[9] * n[i] - p[10] * d1[i] - p[12] * d2[i] for i in range(3)]
            s.penetration = max(s.penetration, -p[8])
        s.n += 1

    def close_step(self, stamp_s: float) -> None:
        """The control step's means: the truth (`last`) and what each arm feels."""
        s = self._sums
        n = max(s.n, 1)
        force, moment = s.force / n, s.moment / n
        pos, orn = pb.getBasePositionAndOrientation(self.body, physicsClientId=self.world.client)
        rot = np.array(pb.getMatrixFromQuaternion(orn)).reshape(3, 3)
        self.last = SegmentTruth(stamp_s, np.array(pos), rot, force, moment, s.contact / n,
                                 s.penetration, self._seated(np.array(pos), rot))
        # on the arm: the opposite wrench, its moment about the world origin
        for k in (0, 1):
            g = np.array(pos) + rot @ self.grasp_in_segment[k]
            f = -force[k]
            self._on_arm[k] = np.concatenate([f, -moment[k] + np.cross(g, f)])
        self._sums = _Sums()

    def wrench_on_arm(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The mean force the segment exerted on rover k's gripper over the last step, and its
        moment about the world origin (world axes)."""
        return self._on_arm[k, :3].copy(), self._on_arm[k, 3:].copy()

    def _seated(self, pos: np.ndarray, rot: np.ndarray, *, tolerance_m: float = 0.002
                ) -> bool:
        """Between the walls over the stage's length with its bottom within `tolerance_m` of
        the floor: every lower corner of the segment's middle part (the stage's length)."""
        st, sp = self.stage, self.spec
        gap = sp.width_m + st.clearance_m
        floor_z = st.top_z - st.depth_m
        h = st.length_m / 2
        corners = [pos + rot @ np.array([a * sp.width_m / 2, b * h, -sp.height_m / 2])
                   for a in (-1, 1) for b in (-1, 1)]
        return all(abs(p[0] - st.centre_x) <= gap / 2 + 5e-4 and p[2] <= floor_z + tolerance_m
                   for p in corners)

    def remove(self) -> None:
        c = self.world.client
        for cid in self.constraints:
            pb.removeConstraint(cid, physicsClientId=c)
        self.constraints = []



class Scenario(StrEnum):
    """What the rovers hold: rover 2 the card (ch. 5), or rovers 1 and 2 one segment (A.4)."""

    CARD = 'card'
    SEGMENT = 'segment'


def carry_segment(world: World, spec: SegmentSpec, *, behind_m: float, top_z: float,
                  clearance_m: float = 0.004, settle_steps: int = 100) -> SegmentCarry:
    """App. A.4's start: the arms settle at home for `settle_steps` steps, rovers 1 and 2 grasp
    the segment where their grippers are, and the stage stands with its channel's centre
    `behind_m` behind the grasp line (-x) and its mouth at `top_z` (world m)."""
    for _ in range(settle_steps):
        world.step()
    if len(world.rovers) < 2:
        raise SegmentError('the segment needs two rovers')
    x = 0.5 * sum(float(world.grasp_point(k)[0]) for k in (0, 1))
    return world.grasp_segment(spec, StageSpec(centre_x=x - behind_m, top_z=top_z,
                                               clearance_m=clearance_m))
