"""The insertion task's model and what the master's camera makes of it (Sujan 2002, §5.1-5.3).

Task model: the card (a 4.25 in card, two markers on its face) and the insertion site (two jaws
forming the slot, a marker on each jaw's face beside the mouth), with the marker positions in
their own frames:

- card frame: the card's centre, x along its width, y its face normal (the markers' side), z its
  height (rover_sim's card link; coop_common.rover_geometry.card_in_base);
- site frame: the centre of the slot's mouth, x across the slot (from the near jaw to the far
  one), y the jaws' marked faces' normal, z up. contact.py's planar frame is this frame's x and z
  (its y is the site's z, its z the site's -y).

Each pair of markers gives a frame by Eq. 5-2 (P1 the first marker, P2 the second on the x axis,
P3 on the z axis from the vertical the master's mast encoders give: frames.third_point), so the
master's stereo fixes A_VT (card markers) and A_VO (slot markers); the slave's arm encoders give
A_TS, and Eq. 5-4 with the task model's goal offset gives the card's required motion in the
slave's base frame (frames.required_motion_from_points). The camera's own pose is never needed.

`label_markers` turns a stereo frame's triangulated markers into the four labelled points: the
card's two by their size (0.5 in across against the slot's 0.25 in, §5.3), each pair ordered
along the site's x as the camera sees it (the vertical crossed with the viewing direction).
The site does not move: a camera that stands still may label the card against the slot pair
it saw before (`slot_memory`, from `find_slot` or an earlier labelling), when the card in
front of the mouth hides a slot marker or shades it out of a marker's size.

No rclpy here.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from .contact import INCH, SlotGeometry
from .errors import InsertionError
from .frames import RequiredMotion, homogeneous, invert, required_motion_from_points, third_point
from .triangulate import StereoMarker

__all__ = [
    'LABELS',
    'LabelledMarkers',
    'SlotPair',
    'TaskModel',
    'card_required_motion',
    'find_slot',
    'label_markers',
    'site_from_slot',
    'slot_from_site',
]

LABELS = ('card_a', 'card_b', 'slot_a', 'slot_b')


@dataclass(frozen=True)
class TaskModel:
    """The card, the slot and their markers (defaults: rover_sim's Table 5-1 site and card).

    slot_width_m: the gap between the jaws (Table 5-1: 5.0, 4.5, 4.375 in); standoff_m: how far
    above the mouth the card's lower edge is brought by vision before it descends."""

    slot_width_m: float = 4.5 * INCH
    card_width_m: float = 4.25 * INCH
    card_height_m: float = 2.75 * INCH
    card_thickness_m: float = 0.003
    card_marker_radius_m: float = 0.25 * INCH
    card_marker_x_m: float = 1.25 * INCH        # the card's markers at x = -+ this on its face
    slot_depth_m: float = 0.03
    jaw_width_m: float = 0.10
    jaw_half_length_m: float = 0.10             # the jaws' marked faces at site y = + this
    slot_marker_radius_m: float = 0.125 * INCH
    slot_marker_inset_m: float = 0.03           # beyond the slot's edges, along x
    slot_marker_depth_m: float = 0.03           # below the mouth
    standoff_m: float = 0.015

    def __post_init__(self) -> None:
        for name, v in self.__dict__.items():
            if not (np.isfinite(v) and v > 0):
                raise InsertionError(f'{name} must be finite and > 0, got {v}')
        _ = self.geometry    # the slot must be wider than the card (SlotGeometry checks)

    @property
    def geometry(self) -> SlotGeometry:
        return SlotGeometry(card_width_m=self.card_width_m, slot_width_m=self.slot_width_m,
                            slot_depth_m=self.slot_depth_m, jaw_width_m=self.jaw_width_m,
                            card_height_m=self.card_height_m)

    @property
    def card_markers(self) -> np.ndarray:
        """(2, 3) marker centres in the card frame (on its +y face)."""
        y = self.card_thickness_m / 2
        return np.array([[-self.card_marker_x_m, y, 0.0], [self.card_marker_x_m, y, 0.0]])

    @property
    def slot_markers(self) -> np.ndarray:
        """(2, 3) marker centres in the site frame (on the jaws' +y faces)."""
        x = self.slot_width_m / 2 + self.slot_marker_inset_m
        return np.array([[-x, self.jaw_half_length_m, -self.slot_marker_depth_m],
                         [x, self.jaw_half_length_m, -self.slot_marker_depth_m]])

    @property
    def card_marker_frame(self) -> np.ndarray:
        """The Eq. 5-2 frame of the card's markers in the card frame (level: no rotation)."""
        return homogeneous(np.eye(3), self.card_markers[0])

    @property
    def slot_marker_frame(self) -> np.ndarray:
        """The Eq. 5-2 frame of the slot's markers in the site frame, its origin midway between
        them (the slot's centre line for any slot width)."""
        return homogeneous(np.eye(3), self.slot_markers.mean(axis=0))

    def card_goal(self, above_m: float) -> np.ndarray:
        """The card frame's pose in the site frame with its lower edge `above_m` over the mouth
        (negative: inside the slot), centred over the slot, level."""
        return homogeneous(np.eye(3), [0.0, 0.0, self.card_height_m / 2 + above_m])

    def goal_offset(self, above_m: float) -> np.ndarray:
        """The card-marker frame's goal in the slot-marker frame (Eq. 5-4's goal_offset)."""
        return invert(self.slot_marker_frame) @ self.card_goal(above_m) @ self.card_marker_frame


@dataclass(frozen=True)
class LabelledMarkers:
    """The four markers in the camera frame: rows card_a, card_b, slot_a, slot_b (m), their
    3x3 covariances, and the vertical (unit, camera frame) the frames take their z from."""

    points: np.ndarray          # (4, 3)
    covariances: np.ndarray     # (4, 3, 3)
    up: np.ndarray              # (3,)
    slot_remembered: bool = False   # the slot rows are the slot_memory's, not this frame's

    @property
    def slot(self) -> SlotPair:
        return SlotPair(self.points[2:], self.covariances[2:])


@dataclass(frozen=True)
class SlotPair:
    """The slot's two markers in the camera frame (slot_a, slot_b) and their covariances."""

    points: np.ndarray          # (2, 3)
    covariances: np.ndarray     # (2, 3, 3)


def _size_m(m: StereoMarker, radius_px: float, fx: float) -> float:
    return float(radius_px * m.position[2] / fx)


def _site_axes(up: ArrayLike, markers: list, radii_px: list[float]
               ) -> tuple[np.ndarray, np.ndarray]:
    """The unit vertical and the site's x as the camera sees it (the vertical crossed with the
    viewing direction), after checking the inputs (InsertionError)."""
    u = np.asarray(up, float)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
        raise InsertionError('up must be a finite non-zero 3-vector')
    u = u / np.linalg.norm(u)
    if len(radii_px) != len(markers):
        raise InsertionError('one radius per marker')
    across = np.cross(u, [0.0, 0.0, 1.0])
    if np.linalg.norm(across) < 1e-6:
        raise InsertionError('the camera looks straight down or up: the site x is undefined')
    return u, across / np.linalg.norm(across)


def label_markers(markers: list[StereoMarker], radii_px: list[float], fx: float, up: ArrayLike,
                  model: TaskModel, *, size_tolerance: float = 0.6,
                  slot_memory: SlotPair | None = None,
                  memory_gate_m: float = 0.02) -> LabelledMarkers:
    """The card's and the slot's markers among the triangulated ones. radii_px: each marker's
    radius in the left image; fx: the focal length (px); up: the vertical in the camera frame.
    Markers whose size (radius_px * Z / fx) is within a factor 1 + size_tolerance of either
    kind's are candidates (a fiducial or a glint is not; small markers look larger than they
    are: blur, shading). The labelling is the pair of disjoint candidate pairs whose distances
    apart match the card's and the slot's within 20 %, the card's pair the larger, with the
    least squared spacing error. With no such pair of pairs and a `slot_memory` (the camera has
    not moved since), the card's pair alone among the markers farther than `memory_gate_m`
    from the remembered slot markers, labelled with the remembered slot rows. None of these:
    InsertionError (the caller holds and waits for the next frame)."""
    u, across = _site_axes(up, markers, radii_px)
    kinds = {'card': (model.card_marker_radius_m, 2 * model.card_marker_x_m),
             'slot': (model.slot_marker_radius_m,
                      model.slot_markers[1, 0] - model.slot_markers[0, 0])}
    # candidates: sizes within the tolerance of either kind (fiducials and glints drop out)
    sizes = [_size_m(m, r, fx) for m, r in zip(markers, radii_px, strict=False)]
    lo = kinds['slot'][0] / (1 + size_tolerance)
    hi = kinds['card'][0] * (1 + size_tolerance)
    cand = [k for k, sz in enumerate(sizes) if lo <= sz <= hi]
    # the pairing: two disjoint pairs whose spacings match the card's and the slot's within
    # 20 %, the card's pair the larger; least squared spacing error (size breaks ties)
    best, found = None, {'card': False, 'slot': False}
    pos = [m.position for m in markers]

    def spacing_error(a: int, b: int, kind: str) -> float:
        return float(np.linalg.norm(pos[a] - pos[b])) / kinds[kind][1] - 1.0

    for ca, cb in itertools.combinations(cand, 2):
        ec = spacing_error(ca, cb, 'card')
        if abs(ec) > 0.2:
            continue
        found['card'] = True
        for sa, sb in itertools.combinations([k for k in cand if k not in (ca, cb)], 2):
            es = spacing_error(sa, sb, 'slot')
            if abs(es) > 0.2:
                continue
            found['slot'] = True
            if sizes[ca] + sizes[cb] <= sizes[sa] + sizes[sb]:
                continue
            size_cost = sum(np.log(sizes[k] / kinds[kind][0]) ** 2 for kind, ks in
                            (('card', (ca, cb)), ('slot', (sa, sb))) for k in ks)
            cost = ec * ec + es * es + 0.01 * size_cost
            if best is None or cost < best[0]:
                best = (cost, (ca, cb), (sa, sb))
    if best is None and slot_memory is not None:
        near = [k for k in cand
                if min(np.linalg.norm(pos[k] - q) for q in slot_memory.points) < memory_gate_m]
        card = _best_pair([k for k in cand if k not in near], pos, sizes, *kinds['card'])
        if card is not None:
            found_c = sorted(card, key=lambda k: float(pos[k] @ across))
            return LabelledMarkers(
                np.vstack([np.array([pos[k] for k in found_c]), slot_memory.points]),
                np.concatenate([np.array([markers[k].covariance for k in found_c]),
                                slot_memory.covariances]), u, slot_remembered=True)
    if best is None:
        why = (f'no card pair {2 * model.card_marker_x_m:.3f} m apart' if not found['card'] else
               f'no slot pair {kinds["slot"][1]:.3f} m apart' if not found['slot'] else
               'the card pair is not the larger')
        raise InsertionError(f'markers not labelled: {why} ({len(cand)} of {len(markers)} '
                             "of a marker's size)")
    points, covs = [], []
    for pair in best[1:]:
        ordered = sorted(pair, key=lambda k: float(pos[k] @ across))
        points += [pos[k] for k in ordered]
        covs += [markers[k].covariance for k in ordered]
    return LabelledMarkers(np.array(points), np.array(covs), u)


def _best_pair(cand: list[int], pos: list[np.ndarray], sizes: list[float], radius_m: float,
               spacing_m: float) -> tuple[int, int] | None:
    """The candidate pair whose distance apart matches spacing_m within 20 %, least squared
    spacing error (size breaks ties); None when no pair does."""
    best = None
    for a, b in itertools.combinations(cand, 2):
        e = float(np.linalg.norm(pos[a] - pos[b])) / spacing_m - 1.0
        if abs(e) > 0.2:
            continue
        cost = e * e + 0.01 * sum(np.log(sizes[k] / radius_m) ** 2 for k in (a, b))
        if best is None or cost < best[0]:
            best = (cost, (a, b))
    return None if best is None else best[1]


def find_slot(markers: list[StereoMarker], radii_px: list[float], fx: float, up: ArrayLike,
              model: TaskModel, *, size_tolerance: float = 0.6) -> SlotPair | None:
    """The slot's pair alone (the card not in view): markers of a slot marker's size within
    `size_tolerance`, their distance apart the slot's within 20 %, ordered along the site's x
    as in label_markers; None when no pair qualifies."""
    _, across = _site_axes(up, markers, radii_px)
    r = model.slot_marker_radius_m
    sizes = [_size_m(m, rad, fx) for m, rad in zip(markers, radii_px, strict=False)]
    cand = [k for k, sz in enumerate(sizes) if r / (1 + size_tolerance) <= sz
            <= r * (1 + size_tolerance)]
    pos = [m.position for m in markers]
    pair = _best_pair(cand, pos, sizes, r, model.slot_markers[1, 0] - model.slot_markers[0, 0])
    if pair is None:
        return None
    order = sorted(pair, key=lambda k: float(pos[k] @ across))
    return SlotPair(np.array([pos[k] for k in order]),
                    np.array([markers[k].covariance for k in order]))


def slot_from_site(site_in_camera: ArrayLike, model: TaskModel, *, sigma_m: float) -> SlotPair:
    """The slot's markers in the camera frame where the site frame's pose in that frame (4x4: a
    located site through the camera's odometry) puts them, ordered as find_slot orders them,
    each with an isotropic covariance of `sigma_m` (how well that pose is known): the inverse
    of site_from_slot."""
    t = np.asarray(site_in_camera, float)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise InsertionError('the site pose must be a finite 4x4 matrix')
    if not (math.isfinite(sigma_m) and sigma_m > 0):
        raise InsertionError(f'sigma_m must be finite and > 0, got {sigma_m}')
    points = model.slot_markers @ t[:3, :3].T + t[:3, 3]
    return SlotPair(points, np.repeat(np.eye(3)[None] * sigma_m ** 2, 2, axis=0))


def site_from_slot(pair: SlotPair, up: ArrayLike, model: TaskModel) -> np.ndarray:
    """The site frame (4x4: the slot mouth's centre, x across the slot, z up) in the frame of
    the slot's markers `pair` (the camera's), from the task model's marker positions in the
    site frame and the vertical `up` in that frame (InsertionError when the markers stand one
    above the other)."""
    u = np.asarray(up, float)
    if u.shape != (3,) or not np.all(np.isfinite(u)) or np.linalg.norm(u) < 1e-9:
        raise InsertionError('up must be a finite non-zero 3-vector')
    u = u / np.linalg.norm(u)
    a, b = np.asarray(pair.points, float)
    x = (b - a) - ((b - a) @ u) * u
    if np.linalg.norm(x) < 0.5 * np.linalg.norm(b - a) or np.linalg.norm(x) < 1e-6:
        raise InsertionError('the slot markers are not side by side: no site heading')
    x /= np.linalg.norm(x)
    rot = np.column_stack([x, np.cross(u, x), u])
    mid = model.slot_markers.mean(axis=0)
    return homogeneous(rot, 0.5 * (a + b) - rot @ mid)


def card_required_motion(obs: LabelledMarkers, t_base_card: ArrayLike, model: TaskModel, *,
                         above_m: float) -> RequiredMotion:
    """Eq. 5-1..5-4: the card's required motion in the slave's base frame, to the pose with its
    lower edge `above_m` over the mouth, from the master's labelled markers and the card's pose in
    the base frame (arm kinematics, A_TS of the card-marker frame). Translation and rotation
    are those of the card-marker frame (about its origin); covariance_s from the points'."""
    pts = obs.points
    obj = np.array([pts[0], pts[1], third_point(pts[0], pts[1], obs.up)])
    mid = 0.5 * (pts[2] + pts[3])      # the slot's centre line, whatever its width
    site = np.array([mid, pts[3], third_point(mid, pts[3], obs.up)])
    # the third point is exact given the first two: its covariance is the first point's
    c_mid = 0.25 * (obs.covariances[2] + obs.covariances[3])
    cov = np.array([obs.covariances[0], obs.covariances[1], obs.covariances[0],
                    c_mid, obs.covariances[3], c_mid])
    a_ts = np.asarray(t_base_card, float) @ model.card_marker_frame
    return required_motion_from_points(obj, site, a_ts, goal_offset=model.goal_offset(above_m),
                                       covariances=cov)
