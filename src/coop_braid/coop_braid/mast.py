"""BRAID as a rover's camera mast (issue #37, deliverable 5): where the stereo pair's left
optical frame is for a chain state, and which camera views the mast can take (by IK).

The mast is a BRAID chain (thesis app. E: "camera/sensor placement tasks") standing on the
rover's pan turntable in place of the pan/tilt head: the chain's base frame is the pan link's
frame raised by `base_above_pan_m`, and the camera sits on the chain's end platform looking
along the platform's x axis (towards leg 1), `camera_above_end_m` above it:

    T_pan,optical(s) = B A_0n(s) C,    B = Trans(0, 0, base_above_pan_m),
                                       C = Trans(0, 0, camera_above_end_m) R_optical

with R_optical the optical frame (z forward, x right, y down) in the platform frame, the same
as the pan/tilt mast's optical frame in its tilt link. A 3-RPS stage has no torsion of its own,
so the turntable keeps the heading free; the chain gives the camera its height, its pitch and
a horizontal offset (what the pan/tilt head cannot).

`view_table` turns a lattice of wanted views (height and pitch of the camera in the pan frame)
into the views the mast reaches: each wanted view is solved by BRAID IK (`coop_braid.ik`), and
kept only when the pose the IK's state gives is within a tolerance of it; what is kept is that
pose (the state's forward kinematics), not the wanted one, so a planner rates the view the
camera will really have.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from coop_braid.chain import Chain
from coop_braid.errors import BraidError
from coop_braid.ik import IKResult, Method, Weights, solve
from coop_braid.stage import StageGeometry

Array = NDArray[np.float64]

#: the optical frame's axes (columns: x right, y down, z forward) in a frame whose x points
#: forward and z up (the pan/tilt mast's tilt link, the BRAID's end platform)
OPTICAL_IN_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
#: stages of the rover's BRAID mast by default: 0.45 m retracted, 0.60 m extended (n = 10 is
#: where the beam IK meets the issue's targets, docs/results/braid.md)
DEFAULT_STAGES = 10
#: the rover's BRAID mast: the chain's base this far below the pan joint (on the chassis deck,
#: 0.07 m above the base c.g., the pan joint 0.40 m above it), so the straight, retracted chain
#: holds the camera 0.15 m above the pan joint and the extended one 0.30 m
ROVER_BASE_ABOVE_PAN_M = -0.33
#: how a pitch residual ranks against a position residual in `view_table` (m/rad)
PITCH_WEIGHT_M = 0.3


class MastKind(StrEnum):
    """The camera mast a rover carries: the pan/tilt head (the default rover) or BRAID."""

    PAN_TILT = 'pan_tilt'
    BRAID = 'braid'


def _trans(x: float, y: float, z: float) -> Array:
    out = np.eye(4)
    out[:3, 3] = (x, y, z)
    return out


@dataclass(frozen=True)
class Tolerance:
    """The largest residual at which a wanted view counts as reached: the camera's position
    (m), the pitch of its optical axis (rad; its heading is the turntable's to correct) and its
    roll about the optical axis (rad; a rolled stereo pair still ranges, a planner rating views
    by heading and pitch alone ignores it, so it is bounded rather than zero: a 3-RPS stage
    tilts in steps of about 14 deg, and the chain's orientations form a lattice that coarse,
    with roll and pitch coupled)."""

    position_m: float = 0.03
    pitch_rad: float = math.radians(2.5)
    roll_rad: float = math.radians(15.0)

    def __post_init__(self) -> None:
        for name in ('position_m', 'pitch_rad', 'roll_rad'):
            v = getattr(self, name)
            if not math.isfinite(v) or v <= 0.0:
                raise BraidError(f'Tolerance.{name} = {v!r}: finite and > 0')


@dataclass(frozen=True)
class BraidMast:
    """A BRAID chain carrying the left optical frame on the rover's pan link (module
    docstring): the chain, the height of its base above the pan joint and of the camera above
    its end platform (m)."""

    chain: Chain
    base_above_pan_m: float = 0.0
    camera_above_end_m: float = 0.03
    _base: Array = field(init=False, repr=False, compare=False)
    _camera: Array = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ('base_above_pan_m', 'camera_above_end_m'):
            v = getattr(self, name)
            if not math.isfinite(v) or not -1.0 <= v <= 1.0:
                raise BraidError(f'BraidMast.{name} = {v!r}: finite, within +-1 m')
        cam = _trans(0.0, 0.0, self.camera_above_end_m)
        cam[:3, :3] = OPTICAL_IN_BODY
        object.__setattr__(self, '_base', _trans(0.0, 0.0, self.base_above_pan_m))
        object.__setattr__(self, '_camera', cam)

    @classmethod
    def uniform(cls, n: int = DEFAULT_STAGES, geometry: StageGeometry | None = None, *,
                base_above_pan_m: float = 0.0, camera_above_end_m: float = 0.03) -> BraidMast:
        """A mast of n identical stages (`StageGeometry()` by default)."""
        return cls(Chain.uniform(geometry or StageGeometry(), n),
                   base_above_pan_m=base_above_pan_m, camera_above_end_m=camera_above_end_m)

    @classmethod
    def rover(cls, n: int = DEFAULT_STAGES) -> BraidMast:
        """The rover's BRAID mast of n default stages (ROVER_BASE_ABOVE_PAN_M)."""
        return cls.uniform(n, base_above_pan_m=ROVER_BASE_ABOVE_PAN_M)

    @property
    def n(self) -> int:
        """Stages of the chain."""
        return self.chain.n

    def optical_in_pan(self, states: NDArray[np.integer] | Sequence[int]) -> Array:
        """T_pan,optical = B A_0n(states) C (4x4): the left optical frame in the pan link."""
        return self._base @ self.chain.pose(states) @ self._camera

    def end_target(self, optical_in_pan: NDArray[np.floating]) -> Array:
        """The chain-end pose A_0n* that puts the optical frame at `optical_in_pan`."""
        t = np.asarray(optical_in_pan, dtype=float)
        return np.linalg.inv(self._base) @ t @ np.linalg.inv(self._camera)

    def reach(self, optical_in_pan: NDArray[np.floating], *, method: Method = Method.BEAM,
              weights: Weights | None = None, seed: int = 0) -> tuple[IKResult, Array]:
        """BRAID IK for a wanted optical pose in the pan frame: the IK's answer (its errors are
        the chain end's, which are the camera's: C is rigid and the position error of a pose
        product differs only by the rotation error acting on C's offset, below 1 mm at
        3 deg) and the optical pose the answer's state really gives."""
        res = solve(self.chain, self.end_target(optical_in_pan), method=method,
                    weights=weights, rng=seed)
        return res, self.optical_in_pan(res.states)


def view_rotation(pitch: float, yaw: float = 0.0, roll: float = 0.0) -> Array:
    """The optical frame's rotation in a z-up frame for a camera heading `yaw` (about z),
    pitched `pitch` nose down and rolled `roll` about its optical axis (rad)."""
    cy, sy, cp, sp = math.cos(yaw), math.sin(yaw), math.cos(pitch), math.sin(pitch)
    cr, sr = math.cos(roll), math.sin(roll)
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx @ OPTICAL_IN_BODY


def roll_of(optical: NDArray[np.floating]) -> float:
    """Roll (rad) of an optical frame about its axis: the angle of its x axis (image right) out
    of the horizontal plane, positive when the right side of the image is lower."""
    x = np.asarray(optical, dtype=float)[:3, 0]
    return float(-math.asin(float(np.clip(x[2], -1.0, 1.0))))


def heading_pitch(optical: NDArray[np.floating]) -> tuple[float, float]:
    """Heading (rad, about z) and nose-down pitch (rad) of an optical frame's z axis."""
    z = np.asarray(optical, dtype=float)[:3, 2]
    return float(math.atan2(z[1], z[0])), float(-math.asin(float(np.clip(z[2], -1.0, 1.0))))


@dataclass(frozen=True)
class MastView:
    """A view the mast reaches: the chain state, the optical pose it gives in the pan frame
    (`pose`, the forward kinematics of `states`), the wanted height (m, above the pan joint) and
    pitch (rad) it was solved for, and its residuals from the wanted view: position (m), pitch
    (rad) and roll (rad). Its `offset` (camera position in the pan frame: x forward, y left,
    z up), `heading` and `pitch` are what a planner places and rates."""

    states: NDArray[np.int64]
    pose: Array
    wanted_height_m: float
    wanted_pitch_rad: float
    pos_err_m: float
    pitch_err_rad: float
    roll_rad: float

    @property
    def offset(self) -> Array:
        """Camera position in the pan frame (m)."""
        return self.pose[:3, 3].copy()

    @property
    def heading(self) -> float:
        """Heading of the optical axis in the pan frame (rad): the turntable turns it away."""
        return heading_pitch(self.pose)[0]

    @property
    def pitch(self) -> float:
        """Nose-down pitch of the optical axis (rad)."""
        return heading_pitch(self.pose)[1]


@dataclass(frozen=True)
class Tried:
    """One wanted view of `view_table`: height (m, pan frame), pitch (rad), the best residuals
    found (position m, pitch rad, roll rad) and whether they were within the tolerance."""

    height_m: float
    pitch_rad: float
    pos_err_m: float
    pitch_err_rad: float
    roll_rad: float
    reached: bool


@dataclass(frozen=True)
class ViewTable:
    """What `view_table` tried (`tried`) and the views it kept (`views`)."""

    views: tuple[MastView, ...]
    tried: tuple[Tried, ...]


def view_table(mast: BraidMast, *, heights_m: Sequence[float], pitches_rad: Sequence[float],
               forwards_m: Sequence[float] = (0.0,), headings_rad: Sequence[float] = (0.0,),
               rolls_rad: Sequence[float] = (0.0,), tolerance: Tolerance | None = None,
               method: Method = Method.BEAM, weights: Weights | None = None,
               seed: int = 0) -> ViewTable:
    """The views the mast reaches from a lattice of wanted ones. For each height (of the camera
    above the pan joint) and nose-down pitch, BRAID IK (`method`, `weights`) is asked for the
    camera at (f, 0, height) in the pan frame with heading h and roll r, for every forward offset
    f in `forwards_m`, heading h in `headings_rad` and roll r in `rolls_rad`: where the camera
    stands over the turntable matters little to a view, the turntable turns a heading away and
    a roll within the tolerance does no harm, and the chain's orientations are a coarse lattice
    (`Tolerance`), so the IK is given several poses that serve the view. Each answer's pose is
    the forward kinematics of its state; its residuals are measured from it: the position from
    the wanted one, the pitch from the wanted pitch, the roll. The answer with the least
    position + pitch residual (pitch in m at `pitch_weight_m` = 0.3 m/rad) that is within the
    tolerance is the view; a wanted view with none is left out (and reported in `tried`)."""
    tol = tolerance or Tolerance()
    lists = (heights_m, pitches_rad, forwards_m, headings_rad, rolls_rad)
    if min(len(v) for v in lists) == 0:
        raise BraidError('view_table: at least one height, pitch, forward offset, heading and '
                         'roll')
    for v in itertools.chain.from_iterable(lists):
        if not math.isfinite(v):
            raise BraidError(f'view_table: {v!r} is not finite')
    views: list[MastView] = []
    tried: list[Tried] = []
    for h, p in itertools.product(heights_m, pitches_rad):
        best: MastView | None = None
        closest: tuple[float, float, float, float] | None = None
        for f, yaw, roll in itertools.product(forwards_m, headings_rad, rolls_rad):
            want = np.eye(4)
            want[:3, :3] = view_rotation(float(p), float(yaw), float(roll))
            want[:3, 3] = (f, 0.0, h)
            res, pose = mast.reach(want, method=method, weights=weights, seed=seed)
            pos_err = float(np.linalg.norm(pose[:3, 3] - want[:3, 3]))
            pitch_err = abs(heading_pitch(pose)[1] - float(p))
            roll_got = roll_of(pose)
            score = pos_err + PITCH_WEIGHT_M * pitch_err
            if closest is None or score < closest[0]:
                closest = (score, pos_err, pitch_err, roll_got)
            ok = (pos_err <= tol.position_m and pitch_err <= tol.pitch_rad
                  and abs(roll_got) <= tol.roll_rad)
            if ok and (best is None or score < best.pos_err_m
                       + PITCH_WEIGHT_M * best.pitch_err_rad):
                best = MastView(res.states, pose, float(h), float(p), pos_err, pitch_err,
                                roll_got)
        assert closest is not None
        if best is not None:
            views.append(best)
            tried.append(Tried(float(h), float(p), best.pos_err_m, best.pitch_err_rad,
                               best.roll_rad, True))
        else:
            tried.append(Tried(float(h), float(p), *closest[1:], False))
    return ViewTable(tuple(views), tuple(tried))
