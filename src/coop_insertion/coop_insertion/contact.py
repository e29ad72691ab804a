"""Force-feedback finish of the insertion (Sujan 2002, app. A.4, Figs. A-5/A-6): identify the
contact state from the force/torque readings of all cooperating rovers, then move in the
direction of least resistance, never pushing the contact force above a limit.

The planar model (§5.2 assumes the insertion planar). Task (site) frame: origin at the centre of
the slot's mouth, x across the slot (from the left jaw to the right jaw), y out of the slot
(the card comes in along -y), z = x cross y, moments about z. The slot is `slot_width_m` wide
(walls x = +-W/2 for -D <= y <= 0), `slot_depth_m` deep (bottom y = -D); each jaw's mouth face
is y = 0 for W/2 <= |x| <= W/2 + jaw_width_m, its mouth edge the corner (+-W/2, 0). The card
(width w) is a rectangle; its pose is that of its leading-edge centre p = (x, y) and its tilt
theta (counter-clockwise): card axis u = (-sin theta, cos theta) (pointing back at the gripper),
lateral axis v = (cos theta, sin theta), leading corners c_L,R = p -+ (w/2) v.

A contact is either a site edge on a card face (its normal is set by the card's angle theta) or a
card corner on a site face (normal set by the site's angle alpha, zero in the site frame): the
two kinds Fig. A-6 writes as the ratios tan(theta) and tan(alpha). Each state's equilibrium is
Fig. A-6's: sum F = 0 = F_x + F_y + sum (f_n + f_fr), sum M = 0 = M + sum r x (f_n + f_fr), with
|f_fr| <= mu f_n. The states (single contacts have a side, left or right):

- FREE: no contact.
- EDGE_ON_FACE: a jaw's mouth edge on the card's leading face; -f_x/f_y = tan theta (A-6 a).
- EDGE_ON_SIDE: a jaw's mouth edge on a card side face; f_y/f_x = tan theta (A-6 b).
- CORNER_ON_MOUTH: a card corner on a jaw's mouth face (a lateral miss);
  -f_x/f_y = tan alpha (A-6 c).
- CORNER_ON_WALL: a card corner on a jaw's inner wall; f_y/f_x = tan alpha.
- CORNER_ON_BOTTOM: a card corner on the slot bottom (card tilted); -f_x/f_y = tan alpha.
- TWO_POINT: a corner on one wall (or the bottom) and the other jaw's edge on the card's side
  face, wedged / jammed; one alpha and one theta contact (A-6 d/e).
- CORNER_AND_SIDE: a corner on the slot bottom and the card held up off it by a jaw: its other
  corner on the other jaw's wall, or its own side face on its own jaw's mouth edge (the card
  leaning that way). The card on one corner that a floor reading alone can take for SEATED:
  the wall's or edge's friction carries the load the missing corner would.
- SEATED: the leading face flat on the slot bottom; -f_x/f_y = tan alpha at both corners.

The figure panels themselves are not in the thesis text this project has, only their equations;
the list is this module's reading of them (which face or corner touches is named by the normal's
axis and whether theta or alpha sets it), with the states a rectangle in a slot can reach.

Identification fits every hypothesis to the measured planar wrench (F_x, F_y, M_z) by
non-negative least squares over the friction-cone edges of its contacts (noise-weighted by
force_noise_n and moment_noise_nm), adds the squared distance, in pose_sigma_m, between each
fitted contact point and where the estimated card pose puts that feature, and a penalty per
contact; the least score wins. FREE is the hypothesis with no contact, so a wrench inside the
noise is FREE.

Friction is not known: the card's mu on the site is somewhere in friction_range (default 0.2 to
0.6), and every cone is fitted at the range's top, so a contact is never denied for friction a
mu in the range allows (fitted at a fixed 0.3, a corner sliding at 0.6 is not a single
contact). What the fit needed is reported (Identification.friction_needed: the largest
friction-to-normal ratio of a loaded contact), a lower bound on the site's mu.

SEATED is the one state whose call ends the insertion, and a single wrench cannot always tell
it from a card on one corner held up by a jaw (CORNER_AND_SIDE). seat_check decides it by the
wrench, the pose estimate only placing the features (it called such a card flat and deep):
the seated fit (both corners on the floor, the pair shifted within 3 pose sigmas) must give
each corner at least seat_corner_force_n, and every one-corner rival must fit the wrench worse
by seat_margin (chi^2), its cones at the widest friction. The rivals: a corner alone on the
bottom (within 3 pose sigmas of the estimate's corner); a corner in the floor-wall corner; and
the two CORNER_AND_SIDE pairs as the geometry allows them, the other corner h up (from
seat_depth_m, below which the card counts as seated, to 3 pose sigmas above the estimate's
height of it) either on the other wall, the card spanning the slot from it, or with side face
s on jaw s's edge, the card leaning by asin(h / w), each where its corner on the floor is
within 3 pose sigmas of the estimate's (the estimate's depth and tilt are what it gets wrong,
not where across the slot the card is). At mu 0.6 a jaw's friction can carry
about a third of the other corner's share, so a seated card passes only with its corners
loaded alike; the planner's probe (LeastResistance) evens them.

As the thesis notes, the contact points of a two-point state are not unique; the motion plan
does not need them to be.

No rclpy here.
"""
from __future__ import annotations

import enum
import itertools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import nnls

from .errors import InsertionError

__all__ = [
    'INCH',
    'CardPose',
    'Contact',
    'ContactIdentifier',
    'ContactKind',
    'ContactState',
    'Identification',
    'LeastResistance',
    'SeatCheck',
    'SlotGeometry',
    'Step',
    'planar_step_in_frame',
    'planar_wrench',
    'task_wrench',
]

INCH = 0.0254
#: weight per newton of the contact forces in the fit (chi^2 units: 0.01 costs 0.0625 at 25 N)
SQUEEZE_RIDGE = 0.01


class ContactState(enum.Enum):
    """The contact states of app. A.4 (Fig. A-6) between the card and the slot."""

    FREE = 'free'
    EDGE_ON_FACE = 'edge_on_face'
    EDGE_ON_SIDE = 'edge_on_side'
    CORNER_ON_MOUTH = 'corner_on_mouth'
    CORNER_ON_WALL = 'corner_on_wall'
    CORNER_ON_BOTTOM = 'corner_on_bottom'
    TWO_POINT = 'two_point'
    CORNER_AND_SIDE = 'corner_and_side'
    SEATED = 'seated'


class ContactKind(enum.StrEnum):
    """What touches what in one fitted contact (Contact.kind): the single-contact states of
    ContactState, of which the two-point ones are made, and a seated card's corner on the
    floor."""

    EDGE_ON_FACE = 'edge_on_face'
    EDGE_ON_SIDE = 'edge_on_side'
    CORNER_ON_MOUTH = 'corner_on_mouth'
    CORNER_ON_WALL = 'corner_on_wall'
    CORNER_ON_BOTTOM = 'corner_on_bottom'
    SEATED = 'seated'


def _pos(name: str, v: float, *, zero_ok: bool = False) -> float:
    x = float(v)
    if not np.isfinite(x) or x < 0 or (x == 0 and not zero_ok):
        raise InsertionError(f'{name} must be finite and {">=" if zero_ok else ">"} 0, got {v}')
    return x


@dataclass(frozen=True)
class SlotGeometry:
    """The card and the slot (Table 5-1: a 4.25 in card into 5.0 / 4.5 / 4.375 in sites)."""

    card_width_m: float = 4.25 * INCH
    slot_width_m: float = 4.5 * INCH
    slot_depth_m: float = 0.05
    jaw_width_m: float = 0.1
    card_height_m: float = 2.75 * INCH

    def __post_init__(self) -> None:
        for name in ('card_width_m', 'slot_width_m', 'slot_depth_m', 'jaw_width_m',
                     'card_height_m'):
            _pos(name, getattr(self, name))
        if self.slot_width_m <= self.card_width_m:
            raise InsertionError(f'the slot ({self.slot_width_m} m) must be wider than the card '
                                 f'({self.card_width_m} m)')

    @property
    def clearance_m(self) -> float:
        """Total lateral play of the centred card (slot width - card width)."""
        return self.slot_width_m - self.card_width_m


@dataclass(frozen=True)
class CardPose:
    """The card's leading-edge centre (x, y) and tilt theta in the site frame (m, m, rad)."""

    x: float
    y: float
    theta: float

    def __post_init__(self) -> None:
        if not np.all(np.isfinite([self.x, self.y, self.theta])):
            raise InsertionError(f'card pose must be finite, got {self}')

    @property
    def p(self) -> np.ndarray:
        return np.array([self.x, self.y])

    @property
    def u(self) -> np.ndarray:
        return np.array([-np.sin(self.theta), np.cos(self.theta)])

    @property
    def v(self) -> np.ndarray:
        return np.array([np.cos(self.theta), np.sin(self.theta)])

    def corner(self, side: int, width: float) -> np.ndarray:
        """Leading corner on side -1 (left) or +1 (right)."""
        return self.p + side * 0.5 * width * self.v


@dataclass(frozen=True)
class Contact:
    """One fitted contact: where (site frame), its unit normal (the direction the site pushes the
    card), the normal and friction force magnitudes, and the side (-1 left jaw, +1 right)."""

    point: np.ndarray
    normal: np.ndarray
    normal_force_n: float
    friction_force_n: float
    side: int
    kind: ContactKind


@dataclass(frozen=True)
class SeatCheck:
    """seat_check's verdict on one wrench: the seated fit's normal force at the left and right
    corner (N) and its chi^2; the best one-corner rival (its name) and its chi^2; margin = rival
    chi^2 - seated chi^2; passed: each corner carries at least the identifier's
    seat_corner_force_n and the margin is at least its seat_margin."""

    corner_forces_n: tuple[float, float]
    seated_chi2: float
    rival: str
    rival_chi2: float
    passed: bool

    @property
    def margin(self) -> float:
        return self.rival_chi2 - self.seated_chi2

    @property
    def lighter_side(self) -> int:
        """-1 if the left corner carries less, else +1."""
        return -1 if self.corner_forces_n[0] < self.corner_forces_n[1] else 1


@dataclass(frozen=True)
class Identification:
    """The winning hypothesis: state, side (-1 / +1; 0 for FREE, SEATED and two-point states
    name the side of the corner), fitted contacts, the noise-weighted wrench residual (chi^2),
    the total score, every hypothesis's score (for diagnostics), and for SEATED the seat check
    (ContactIdentifier.seat_check) of the same wrench, else None."""

    state: ContactState
    side: int
    contacts: tuple[Contact, ...]
    wrench_chi2: float
    score: float
    scores: dict[str, float] = field(default_factory=dict)
    seat: SeatCheck | None = None

    @property
    def friction_needed(self) -> float:
        """The largest friction-to-normal ratio among the contacts loaded beyond 0.5 N: the
        least mu that explains the wrench with them (0 without)."""
        return max((abs(c.friction_force_n) / c.normal_force_n for c in self.contacts
                    if c.normal_force_n > 0.5), default=0.0)

    @property
    def in_contact(self) -> bool:
        return self.state is not ContactState.FREE

    @property
    def floor_force_n(self) -> float:
        """The slot floor's normal force on the card (N): its corners on the bottom, alone or
        wedged, or the card seated; 0 without."""
        return float(sum(c.normal_force_n for c in self.contacts
                         if c.kind in (ContactKind.CORNER_ON_BOTTOM, ContactKind.SEATED)))


def _check_wrench(w: Sequence[float] | np.ndarray) -> np.ndarray:
    a = np.asarray(w, float)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise InsertionError(f'planar wrench must be a finite (F_x, F_y, M_z), got {w}')
    return a


@dataclass(frozen=True)
class _Spec:
    """One contact of a hypothesis: the normal, and the point either fixed or on a segment
    a + s (b - a), s in [0, 1]; `feature` is where the card pose puts the touching feature."""

    normal: np.ndarray
    a: np.ndarray
    b: np.ndarray | None
    feature: np.ndarray
    side: int
    kind: ContactKind


class ContactIdentifier:
    """Contact-state identification (app. A.4, Fig. A-6) from the summed wrench of all rovers.

    Options (keyword-only): force_noise_n and moment_noise_nm (1-sigma noise of the summed
    planar wrench: a wrench within a few of these is FREE), friction_range (the interval the
    card's Coulomb mu on the site lies in, not known closer: cones are fitted at its top),
    friction (a mu known exactly: the range (friction, friction)), pose_sigma_m (1-sigma of
    the card pose estimate, weighting how far a fitted contact may lie from the feature the
    pose puts there), contact_penalty (score per contact,
    in chi^2 units), seat_angle_rad and seat_depth_m (how flat and how deep a card on the bottom
    must be to count as SEATED rather than CORNER_ON_BOTTOM), samples (points tried along a
    segment locus, within 3 pose sigmas of the pose's feature, in the two-point fits),
    seat_corner_force_n and seat_margin (seat_check: the least normal force on each corner of a
    seated card, and how much worse (chi^2) every one-corner rival must fit the wrench)."""

    def __init__(self, geometry: SlotGeometry, *, force_noise_n: float = 0.5,
                 moment_noise_nm: float = 0.02,
                 friction_range: tuple[float, float] = (0.2, 0.6),
                 friction: float | None = None,
                 pose_sigma_m: float = 0.003, contact_penalty: float = 9.0,
                 seat_angle_rad: float = 0.02, seat_depth_m: float = 0.002,
                 samples: int = 9, seat_corner_force_n: float = 1.0,
                 seat_margin: float = 9.0) -> None:
        if not isinstance(geometry, SlotGeometry):
            raise InsertionError('geometry must be a SlotGeometry')
        self.geometry = geometry
        self.force_noise_n = _pos('force_noise_n', force_noise_n)
        self.moment_noise_nm = _pos('moment_noise_nm', moment_noise_nm)
        if friction is not None:
            friction_range = (friction, friction)
        fr = np.asarray(friction_range, float).ravel()
        if fr.size != 2 or not fr[0] <= fr[1]:
            raise InsertionError(f'friction_range must be (low, high), got {friction_range}')
        lo, hi = (_pos('friction', v, zero_ok=True) for v in fr)
        self.friction_range = (lo, hi)
        #: the cone every contact is fitted with: the widest the range allows
        self.friction = hi
        self.seat_corner_force_n = _pos('seat_corner_force_n', seat_corner_force_n)
        self.seat_margin = _pos('seat_margin', seat_margin, zero_ok=True)
        self.pose_sigma_m = _pos('pose_sigma_m', pose_sigma_m)
        self.contact_penalty = _pos('contact_penalty', contact_penalty, zero_ok=True)
        self.seat_angle_rad = _pos('seat_angle_rad', seat_angle_rad)
        self.seat_depth_m = _pos('seat_depth_m', seat_depth_m)
        if int(samples) != samples or samples < 2:
            raise InsertionError(f'samples must be an integer >= 2, got {samples}')
        self.samples = int(samples)
        self._scale = np.array([1 / self.force_noise_n, 1 / self.force_noise_n,
                                1 / self.moment_noise_nm])

    # -- hypotheses ---------------------------------------------------------------------------
    def _edge(self, s: int) -> np.ndarray:
        return np.array([s * self.geometry.slot_width_m / 2, 0.0])

    def _hypotheses(self, pose: CardPose) -> dict[tuple[ContactState, int], list[_Spec]]:
        g = self.geometry
        half, d, jaw = g.slot_width_m / 2, g.slot_depth_m, g.jaw_width_m
        u, v, p = pose.u, pose.v, pose.p
        up, lat = np.array([0.0, 1.0]), np.array([1.0, 0.0])
        hyps: dict[tuple[ContactState, int], list[_Spec]] = {(ContactState.FREE, 0): []}
        for s in (-1, 1):
            e = self._edge(s)
            corner = pose.corner(s, g.card_width_m)
            # the point of the leading face (clamped to it) nearest the edge
            xi = float(np.clip(np.dot(e - p, v), -g.card_width_m / 2, g.card_width_m / 2))
            on_face = p + xi * v
            # the point of side face s (from corner s back along u) nearest the edge
            eta = float(np.clip(np.dot(e - corner, u), 0.0, g.card_height_m))
            on_side = corner + eta * u
            edge_on_side = _Spec(-s * v, e, None, on_side, s, ContactKind.EDGE_ON_SIDE)
            wall = _Spec(-s * lat, np.array([s * half, 0.0]), np.array([s * half, -d]), corner,
                         s, ContactKind.CORNER_ON_WALL)
            bottom = _Spec(up, np.array([-half, -d]), np.array([half, -d]), corner, s,
                           ContactKind.CORNER_ON_BOTTOM)
            hyps[(ContactState.EDGE_ON_FACE, s)] = [_Spec(u, e, None, on_face, s,
                                                          ContactKind.EDGE_ON_FACE)]
            hyps[(ContactState.EDGE_ON_SIDE, s)] = [edge_on_side]
            hyps[(ContactState.CORNER_ON_MOUTH, s)] = [
                _Spec(up, np.array([s * half, 0.0]), np.array([s * (half + jaw), 0.0]), corner,
                      s, ContactKind.CORNER_ON_MOUTH)]
            hyps[(ContactState.CORNER_ON_WALL, s)] = [wall]
            hyps[(ContactState.CORNER_ON_BOTTOM, s)] = [bottom]
            # wedged: corner s on wall s (or on the bottom) and the other jaw's edge on the
            # card's side face -s
            other = -s
            e_o = self._edge(other)
            c_o = pose.corner(other, g.card_width_m)
            eta_o = float(np.clip(np.dot(e_o - c_o, u), 0.0, g.card_height_m))
            side_o = _Spec(-other * v, e_o, None, c_o + eta_o * u, other,
                           ContactKind.EDGE_ON_SIDE)
            hyps[(ContactState.TWO_POINT, s)] = [wall, side_o]
            hyps[(ContactState.TWO_POINT, 2 * s)] = [bottom, side_o]
            # on corner s, held up by a jaw: the other corner on the other jaw's wall, or side
            # face s on jaw s's mouth edge (the card leaning towards s)
            wall_o = _Spec(-other * lat, np.array([other * half, 0.0]),
                           np.array([other * half, -d]), c_o, other,
                           ContactKind.CORNER_ON_WALL)
            hyps[(ContactState.CORNER_AND_SIDE, s)] = [bottom, wall_o]
            hyps[(ContactState.CORNER_AND_SIDE, 2 * s)] = [bottom, edge_on_side]
        c_l, c_r = pose.corner(-1, g.card_width_m), pose.corner(1, g.card_width_m)
        hyps[(ContactState.SEATED, 0)] = [
            _Spec(up, np.array([np.clip(c[0], -half, half), -d]), None, c, k,
                  ContactKind.SEATED)
            for k, c in ((-1, c_l), (1, c_r))]
        return hyps

    # -- fitting ------------------------------------------------------------------------------
    def _generators(self, point: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """Columns: the unit wrenches of the friction cone's edges n +- mu t at the point."""
        mu = self.friction
        t0, t1 = -normal[1], normal[0]
        g = [(normal[0] + mu * t0, normal[1] + mu * t1)]
        if mu > 0:
            g.append((normal[0] - mu * t0, normal[1] - mu * t1))
        return np.array([[gx, gy, point[0] * gy - point[1] * gx] for gx, gy in g]).T

    def _fit_points(self, w: np.ndarray, specs: list[_Spec], points: list[np.ndarray]
                    ) -> tuple[float, np.ndarray, list[np.ndarray]]:
        a = np.hstack([self._generators(pt, sp.normal)
                       for pt, sp in zip(points, specs, strict=False)])
        # the least contact forces that fit: two opposed contacts can squeeze the card with any
        # force and leave the wrench unchanged, and a bare NNLS put 54 N of such squeeze on
        # each contact from a 0.76 N reading (then a 23 mm 'retreat' from it); the tiny ridge
        # costs nothing where the fit is unique
        ridge = SQUEEZE_RIDGE * np.eye(a.shape[1])
        lam, _ = nnls(np.vstack([a * self._scale[:, None], ridge]),
                      np.concatenate([w * self._scale, np.zeros(a.shape[1])]))
        r = (w - a @ lam) * self._scale
        ncol = a.shape[1] // len(specs)
        return float(r @ r), lam, [lam[k * ncol:(k + 1) * ncol] for k in range(len(specs))]

    def _fit(self, w: np.ndarray, specs: list[_Spec]
             ) -> tuple[float, float, list[tuple[np.ndarray, np.ndarray]]]:
        """Best (chi2 + geometric term) over the hypothesis's contact points."""
        if not specs:
            r = w * self._scale
            return float(r @ r), 0.0, []
        choices = []
        for sp in specs:
            if sp.b is None:
                choices.append([sp.a])
            elif len(specs) == 1:
                choices.append([self._single_point(w, sp)])
            else:
                # points within +-3 pose sigmas of the feature's projection (further ones cost
                # more than a contact in the geometric term)
                choices.append(self._locus(sp))
        combos: Iterable[tuple[np.ndarray, ...]] = itertools.product(*choices)
        if [sp.kind for sp in specs] == [ContactKind.CORNER_ON_BOTTOM,
                                         ContactKind.CORNER_ON_WALL] and \
                specs[0].side == -specs[1].side:
            # the card spans the slot from the other corner, h up the other wall, to its corner
            # on the floor sqrt(w^2 - h^2) across: one point fixes the other
            combos = [(self._spanned(wall_pt, specs[1].side), wall_pt)
                      for wall_pt in choices[1]]
        best = None
        for pts in combos:
            chi2, _, lams = self._fit_points(w, specs, list(pts))
            geo = sum(float(np.sum((pt - sp.feature) ** 2))
                      for pt, sp in zip(pts, specs, strict=False))
            geo /= self.pose_sigma_m ** 2
            if best is None or chi2 + geo < best[0] + best[1]:
                best = (chi2, geo, list(zip(pts, lams, strict=False)))
        assert best is not None                     # every spec has a point to try
        return best

    def _spanned(self, wall_pt: np.ndarray, wall_side: int) -> np.ndarray:
        """The floor point of the card's corner when its other corner is at wall_pt on the
        wall of side wall_side (the card spans the slot between them)."""
        g = self.geometry
        h = float(np.clip(wall_pt[1] + g.slot_depth_m, 0.0, g.card_width_m))
        return np.array([wall_pt[0] - wall_side * np.sqrt(g.card_width_m ** 2 - h ** 2),
                         -g.slot_depth_m])

    def _single_point(self, w: np.ndarray, sp: _Spec) -> np.ndarray:
        """The point of a segment locus on the measured line of action (moment balance
        M = r x F), clamped to the segment; the pose's feature if the force is too small."""
        f = w[:2]
        d = sp.b - sp.a
        den = d[0] * f[1] - d[1] * f[0]
        if np.hypot(*f) < self.force_noise_n or abs(den) < 1e-9 * np.hypot(*f) * np.hypot(*d):
            s = np.dot(sp.feature - sp.a, d) / np.dot(d, d)
        else:
            s = (w[2] - (sp.a[0] * f[1] - sp.a[1] * f[0])) / den
        return sp.a + float(np.clip(s, 0.0, 1.0)) * d

    def seat_check(self, wrench: Sequence[float] | np.ndarray, pose: CardPose) -> SeatCheck:
        """Whether the wrench says both corners carry the card on the floor, by a margin over
        every one-corner rival (see the module notes). Only the wrench's chi^2 compares: the
        pose estimate sets where the features may be (within 3 pose sigmas), not which
        hypothesis wins."""
        w = _check_wrench(wrench)
        if not isinstance(pose, CardPose):
            raise InsertionError('pose must be a CardPose')
        g = self.geometry
        half, d = g.slot_width_m / 2, g.slot_depth_m
        up = np.array([0.0, 1.0])
        span = 3 * self.pose_sigma_m
        shifts = np.linspace(-span, span, self.samples)

        def floor_at(x: float) -> np.ndarray:
            return np.array([float(np.clip(x, -half, half)), -d])

        corners = {s: pose.corner(s, g.card_width_m) for s in (-1, 1)}
        floor = {s: _Spec(up, floor_at(corners[s][0]), None, corners[s], s,
                          ContactKind.SEATED)
                 for s in (-1, 1)}
        best_seat = None
        for dx in shifts:
            # the pair where the wrench and the estimate agree best (many shifts fit a wrench
            # alike; the corner loads are read at the likeliest)
            pts = [floor_at(corners[-1][0] + dx), floor_at(corners[1][0] + dx)]
            chi2, _, lams = self._fit_points(w, [floor[-1], floor[1]], pts)
            cost = chi2 + 2 * (dx / self.pose_sigma_m) ** 2
            if best_seat is None or cost < best_seat[0]:
                best_seat = (cost, chi2, lams)
        assert best_seat is not None                # `shifts` is never empty
        _, seated_chi2, lams = best_seat
        loads = (float(lams[0].sum()), float(lams[1].sum()))

        # (pairs: the specs, and the point sets tried together, one point per spec)
        # a rival's point sets: points for its specs, or (a spec that moves with them, points)
        rivals: dict[str, tuple[list[_Spec],
                                Sequence[list[np.ndarray] | tuple[_Spec, list[np.ndarray]]]]] = {}
        wc = g.card_width_m
        for s in (-1, 1):
            bottom = floor[s]
            rivals[f'corner_on_bottom:{s:+d}'] = (
                [bottom], [[floor_at(corners[s][0] + dx)] for dx in shifts])
            # the corner in the floor-wall corner: the floor and the wall at one point
            wall_pt = np.array([s * half, -d])
            rivals[f'corner_in_corner:{s:+d}'] = (
                [bottom, _Spec(np.array([-s, 0.0]), wall_pt, None, corners[s], s,
                               ContactKind.CORNER_ON_WALL)], [[wall_pt, wall_pt]])
            # the other corner h up the other jaw's wall, h from seat_depth_m (lower, the card
            # is seated) within 3 pose sigmas of where the estimate puts that corner; the card
            # spans the slot from it, so corner s is on the floor sqrt(w^2 - h^2) across
            h_est = max(self.seat_depth_m, corners[-s][1] + d)
            heights = np.linspace(max(self.seat_depth_m, h_est - span), h_est + span,
                                  self.samples)
            wall = _Spec(np.array([s, 0.0]), np.array([-s * half, 0.0]), None, corners[-s], -s,
                         ContactKind.CORNER_ON_WALL)
            # (each only where the estimate's corner is within 3 pose sigmas of where the
            # rival puts it: in a wide slot a centred card spans no jaw to jaw)
            sets = [[self._spanned(np.array([-s * half, -d + h]), -s),
                     np.array([-s * half, -d + h])] for h in heights]
            sets = [p for p in sets if abs(p[0][0] - corners[s][0]) <= span]
            if sets:
                rivals[f'corner_and_side:{s:+d}'] = ([bottom, wall], sets)
            # side face s on jaw s's mouth edge, the card leaning towards s by phi (the other
            # corner h = w sin(phi) up, over the same heights): corner s is D tan(phi) in from
            # the wall, and the edge pushes along -v of the card's tilt -s phi
            leaning: list[tuple[_Spec, list[np.ndarray]]] = []
            for h in heights:
                phi = float(np.arcsin(min(h / wc, 1.0)))
                v = np.array([np.cos(phi), -s * np.sin(phi)])
                edge = _Spec(-s * v, self._edge(s), None, corners[s], s,
                             ContactKind.EDGE_ON_SIDE)
                x_s = s * (half - d * np.tan(phi))
                if abs(x_s - corners[s][0]) <= span:
                    leaning.append((edge, [np.array([x_s, -d]), self._edge(s)]))
            if leaning:
                rivals[f'corner_and_side:{2 * s:+d}'] = ([bottom, leaning[0][0]], leaning)
        rival, rival_chi2 = '', np.inf
        for name, (specs, point_sets) in rivals.items():
            for item in point_sets:
                if isinstance(item, tuple):         # a spec that changes with the points
                    sp, pts = [specs[0], item[0]], item[1]
                else:
                    sp, pts = specs, item
                chi2 = self._fit_points(w, sp, list(pts))[0]
                if chi2 < rival_chi2:
                    rival, rival_chi2 = name, chi2
        passed = (min(loads) >= self.seat_corner_force_n and
                  rival_chi2 - seated_chi2 >= self.seat_margin)
        return SeatCheck(loads, float(seated_chi2), rival, float(rival_chi2), bool(passed))

    def _locus(self, sp: _Spec) -> list[np.ndarray]:
        """The points tried for a contact: its fixed point, or samples of its segment within 3
        pose sigmas of the feature's projection."""
        if sp.b is None:
            return [sp.a]
        seg = sp.b - sp.a
        length = float(np.sqrt(seg @ seg))
        proj = float(np.dot(sp.feature - sp.a, seg)) / length
        lo = max(0.0, proj - 3 * self.pose_sigma_m)
        hi = min(length, proj + 3 * self.pose_sigma_m)
        ss = (np.linspace(lo, hi, self.samples) if hi > lo else
              np.array([min(max(proj, 0.0), length)]))
        return [sp.a + s / length * seg for s in ss]

    def identify(self, wrench: Sequence[float] | np.ndarray, pose: CardPose) -> Identification:
        """The contact state from the summed planar wrench (F_x, F_y, M_z about the site origin;
        the force the site exerts on the card, see task_wrench / planar_wrench) and the card's
        estimated pose in the site frame."""
        w = _check_wrench(wrench)
        if not isinstance(pose, CardPose):
            raise InsertionError('pose must be a CardPose')
        scores: dict[str, float] = {}
        best = None
        for (state, side), specs in self._hypotheses(pose).items():
            chi2, geo, fitted = self._fit(w, specs)
            score = chi2 + geo + self.contact_penalty * len(specs)
            if state is ContactState.SEATED:
                # flat and at depth, or it is not seated
                flat = abs(pose.theta) / self.seat_angle_rad
                deep = (pose.y + self.geometry.slot_depth_m) / self.seat_depth_m
                score += flat ** 2 + deep ** 2
            key = state.value if side == 0 else f'{state.value}:{side:+d}'
            scores[key] = score
            if best is None or score < best[0]:
                best = (score, state, side, chi2, specs, fitted)
        assert best is not None                     # there is always a FREE hypothesis
        score, state, side, chi2, specs, fitted = best
        contacts = []
        for sp, (pt, lam) in zip(specs, fitted, strict=False):
            fn = float(lam.sum())
            ft = float(self.friction * (lam[0] - lam[1])) if lam.size == 2 else 0.0
            contacts.append(Contact(np.asarray(pt, float), sp.normal.copy(), fn, ft, sp.side,
                                    sp.kind))
        if state in (ContactState.TWO_POINT, ContactState.CORNER_AND_SIDE):
            side = int(np.sign(side))
        seat = self.seat_check(w, pose) if state is ContactState.SEATED else None
        return Identification(state, side, tuple(contacts), chi2, score, scores, seat)


@dataclass(frozen=True)
class Step:
    """One commanded increment of the card, in the site frame: (dx, dy) of the card's
    leading-edge centre and dtheta about it. predicted_force_n: the largest contact force the
    stiffness model predicts after the step; done when SEATED and pressed to seat_force_n;
    reason says why this step."""

    dx: float
    dy: float
    dtheta: float
    predicted_force_n: float
    done: bool
    retreat: bool
    reason: str

    @property
    def vector(self) -> np.ndarray:
        return np.array([self.dx, self.dy, self.dtheta])


class LeastResistance:
    """Motion in the direction of least resistance (app. A.4) with a force limit.

    For the identified state a desired increment is formed (slide off a jaw's mouth past its
    edge, rotate towards alignment, slide along a wall or side face, back off a two-point jam,
    rotate a corner flat on the bottom, keep inserting when free), then projected onto the
    motions that the stiffness model says keep every contact force (and the measured resultant)
    at or below force_limit_n: for a contact with normal n at r carrying f_n, the card point
    there moves v(r) = (dx, dy) + dtheta z x (r - p) and the force becomes
    f_n + stiffness * max(0, -n . v(r)); a force above the limit forces a retreat of the excess
    over the stiffness. The projection is the least-squares nearest feasible increment (rotation
    weighted by half the card width), then bounded by max_step_m / max_rotation_rad and so that
    no point of the card moves further than (force_limit_n - |F|) / stiffness: a contact the
    identification missed cannot go over the limit in one step either. A retreat far beyond
    what the excess force asks (conflicting constraints of a wedge) backs off along the card's
    axis instead.

    Options (keyword-only): insert_step_m (nominal advance per step), max_step_m,
    max_rotation_rad, force_limit_n (default 25 N), stiffness_n_per_m (contact stiffness seen
    through the arm and base), contact_force_n (the light contact force kept while sliding;
    above it the step also lifts off), align_gain (fraction of the estimated lateral/tilt
    misalignment removed per step), entry_margin_m (how far inside the jaw edge a corner is
    aimed when sliding off a mouth face; default a quarter of the clearance), level_rad (the
    turn a step about a corner on the bottom when the estimate does not say which way),
    seat_force_n (a SEATED card is pressed until the floor pushes back this hard),
    probe_stiffness_n_per_m (the stiffness the seat probe moves by: the arm's compliance that a
    card pressed on the floor answers with, well below the contacts' own).

    A SEATED card pressed to seat_force_n is done when its seat check passed
    (ContactIdentifier.seat_check); else the step is the probe: see _probe."""

    def __init__(self, geometry: SlotGeometry, *, insert_step_m: float = 0.0005,
                 max_step_m: float = 0.002, max_rotation_rad: float = 0.01,
                 force_limit_n: float = 25.0, stiffness_n_per_m: float = 2.0e4,
                 contact_force_n: float = 3.0, align_gain: float = 0.3,
                 entry_margin_m: float | None = None, level_rad: float = 0.004,
                 seat_force_n: float = 3.0, probe_stiffness_n_per_m: float = 2.0e3) -> None:
        if not isinstance(geometry, SlotGeometry):
            raise InsertionError('geometry must be a SlotGeometry')
        self.geometry = geometry
        self.insert_step_m = _pos('insert_step_m', insert_step_m)
        self.max_step_m = _pos('max_step_m', max_step_m)
        self.max_rotation_rad = _pos('max_rotation_rad', max_rotation_rad)
        self.force_limit_n = _pos('force_limit_n', force_limit_n)
        self.stiffness = _pos('stiffness_n_per_m', stiffness_n_per_m)
        self.contact_force_n = _pos('contact_force_n', contact_force_n, zero_ok=True)
        if self.contact_force_n >= self.force_limit_n:
            raise InsertionError('contact_force_n must be below force_limit_n')
        self.align_gain = _pos('align_gain', align_gain, zero_ok=True)
        if self.align_gain > 1:
            raise InsertionError('align_gain must be in [0, 1]')
        self.entry_margin_m = (geometry.clearance_m / 4 if entry_margin_m is None
                               else _pos('entry_margin_m', entry_margin_m))
        if self.entry_margin_m >= geometry.clearance_m / 2:
            raise InsertionError('entry_margin_m must be below half the clearance')
        self.level_rad = _pos('level_rad', level_rad)
        self.seat_force_n = _pos('seat_force_n', seat_force_n, zero_ok=True)
        self.probe_stiffness = _pos('probe_stiffness_n_per_m', probe_stiffness_n_per_m)
        self._weight = np.array([1.0, 1.0, geometry.card_width_m / 2])
        self._reach = float(np.hypot(geometry.card_width_m / 2, geometry.card_height_m))
        self._budget = np.inf

    def _desired(self, ident: Identification, pose: CardPose, w: np.ndarray
                 ) -> tuple[np.ndarray, str]:
        g = self.geometry
        st, s = ident.state, ident.side
        step = self.insert_step_m
        align = -self.align_gain * np.array([pose.x, 0.0, pose.theta])
        lift = 0.0
        if ident.contacts and max(c.normal_force_n for c in ident.contacts) > \
                self.contact_force_n:
            lift = step
        if st is ContactState.FREE:
            return align + np.array([0.0, -step, 0.0]), 'free: advance along -y, align'
        if st is ContactState.SEATED:
            # flat on the floor by the wrench: press until the floor pushes back by
            # seat_force_n, where one corner's moment would stand clear of the noise
            pressed = ident.floor_force_n
            if pressed < self.seat_force_n:
                # (a card on the floor answers through the arm's compliance, probe_stiffness)
                dy = min(step, (self.seat_force_n - pressed) / self.probe_stiffness)
                return np.array([0.0, -dy, 0.0]), 'seated: press to the seating force'
            if ident.seat is None or ident.seat.passed:
                return np.zeros(3), 'seated'
            return self._probe(ident, pose, w)
        if st is ContactState.CORNER_ON_MOUTH:
            # move the corner from where the wrench puts it to entry_margin inside the edge
            xc = ident.contacts[0].point[0]
            dx = s * (g.slot_width_m / 2 - self.entry_margin_m) - xc
            return np.array([dx, lift, align[2]]), 'corner on a mouth face: slide off past edge'
        if st is ContactState.EDGE_ON_FACE:
            # the edge under the leading face: shift the card until corner s clears the edge
            e = np.array([s * g.slot_width_m / 2, 0.0])
            xi = float(np.dot(e - pose.p, pose.v))
            overlap = g.card_width_m / 2 - s * xi
            dx = -s * (max(overlap, 0.0) + self.entry_margin_m)
            return np.array([dx, lift, align[2]]), 'edge on the leading face: shift clear, align'
        if st is ContactState.EDGE_ON_SIDE:
            # slide along the side face (along -u, tangent to the contact), away from the edge,
            # rotating towards alignment
            d = -step * pose.u - s * 0.5 * step * pose.v
            return np.array([d[0], d[1], align[2]]), 'edge on a side face: slide in, align'
        if st is ContactState.CORNER_ON_WALL:
            # -y is tangent to the wall: keep inserting, ease off the wall, align
            return (np.array([-s * 0.5 * step, -step, align[2]]),
                    'corner on a wall: slide along it, align')
        if st is ContactState.CORNER_AND_SIDE:
            # on one corner, held up by a jaw: pivot flat about the corner as below, and ease
            # away from the jaw that holds the card up (its friction is what holds it)
            d, _ = self._pivot(ident.contacts[0], s, pose)
            d[0] -= ident.contacts[1].side * 0.5 * step
            return d, 'corner and side: rotate flat about the corner, ease off the jaw'
        if st is ContactState.CORNER_ON_BOTTOM:
            return self._pivot(ident.contacts[0], s, pose)
        if st is ContactState.TWO_POINT:
            # jammed: back off along the card axis and rotate out of the wedge. The tilt to
            # remove is the estimated one; if the estimate says aligned, the wedge's moment
            # about the card centre says which way
            dth = -pose.theta
            if abs(pose.theta) < 1e-3:
                m = sum(np.cross(c.point - pose.p, (c.normal_force_n * c.normal +
                                                     c.friction_force_n *
                                                     np.array([-c.normal[1], c.normal[0]])))
                        for c in ident.contacts)
                dth = float(np.sign(m)) * self.max_rotation_rad
            d = step * pose.u
            return np.array([d[0], d[1], dth]), 'two-point (wedged): back off, rotate out'
        raise InsertionError(f'unknown state {st}')  # pragma: no cover

    def _pivot(self, bottom: Contact, s: int, pose: CardPose) -> tuple[np.ndarray, str]:
        """Pivot about the corner on the bottom until the other comes down too: by the
        estimate's tilt when it agrees with the wrench (corner s lowest turns the card towards
        sign s), else by level_rad a step the wrench's way (through the graph the estimate
        called a card flat that stood on one corner, tilted past its tolerance)."""
        dth = -pose.theta
        if not (np.sign(dth) == s and abs(dth) > self.level_rad):
            dth = s * self.level_rad
        r = pose.p - bottom.point
        dp = dth * np.array([-r[1], r[0]])
        return np.array([dp[0], dp[1], dth]), 'corner on the bottom: rotate flat about it'

    def _probe(self, ident: Identification, pose: CardPose, w: np.ndarray
               ) -> tuple[np.ndarray, str]:
        """SEATED by the fit and pressed, but the seat check fails (a corner light, or a
        one-corner rival within the margin): an active probe whose wrench response tells them
        apart. The card turns about its heavier corner to bring the lighter one down, by a
        fraction of what would even a seated card's loads (a card on one corner keeps its
        imbalance, and keeps turning until the other corner lands; a seated one evens its
        loads, which the check needs at mu 0.6); the press is held at 2 x seat_force_n (more
        load, more chi^2 between the hypotheses)."""
        seat, step, k = ident.seat, self.insert_step_m, self.probe_stiffness
        assert seat is not None                     # a probe follows a failed seat check
        g = self.geometry
        light = seat.lighter_side
        f_light, f_heavy = sorted(seat.corner_forces_n)
        # a sixteenth of the turn that would even the corners' loads, at most a quarter of
        # level_rad a step (the arm answers late: larger turns swung the load from corner to
        # corner); none within a quarter of the total
        dth = 0.0
        if f_heavy - f_light > 0.25 * (f_heavy + f_light):
            dth = -light * min(0.25 * self.level_rad,
                               (f_heavy - f_light) / (16 * k * g.card_width_m))
        r = pose.p - pose.corner(-light, g.card_width_m)
        d = dth * np.array([-r[1], r[0]])
        dx = 0.0
        dy = float(np.clip((ident.floor_force_n - 2 * self.seat_force_n) / k, -step, step))
        return (np.array([d[0] + dx, d[1] + dy, dth]),
                f'seated by the fit, not by the check ({seat.rival} within '
                f'{seat.margin:.1f} chi^2, corners {seat.corner_forces_n[0]:.1f} / '
                f'{seat.corner_forces_n[1]:.1f} N): probe')

    def _constraints(self, ident: Identification, wrench: np.ndarray, pose: CardPose
                     ) -> list[tuple[np.ndarray, float, float]]:
        """(a, b, f) rows meaning a . d >= b (n . v(r) >= (f - limit) / k), f the force now."""
        rows = []
        for c in ident.contacts:
            rows.append((c.normal, c.point, c.normal_force_n))
        f = wrench[:2]
        fn = float(np.hypot(*f))
        if fn > 1e-9:
            n = f / fn
            # the point of the line of action nearest the card's reference point
            # (r x F = M: r0 = (M / |F|^2) (F_y, -F_x) is on it)
            r0 = wrench[2] / fn ** 2 * np.array([f[1], -f[0]])
            r = r0 + np.dot(pose.p - r0, n) * n
            rows.append((n, r, fn))
        out = []
        for n, r, force in rows:
            rel = r - pose.p
            a = np.array([n[0], n[1], -n[0] * rel[1] + n[1] * rel[0]])
            out.append((a, (force - self.force_limit_n) / self.stiffness, force))
        return out

    def step(self, ident: Identification, wrench: Sequence[float] | np.ndarray, pose: CardPose
             ) -> Step:
        """The bounded increment for this control step (site frame, about the card's
        leading-edge centre)."""
        if not isinstance(ident, Identification) or not isinstance(pose, CardPose):
            raise InsertionError('step needs an Identification and a CardPose')
        w = _check_wrench(wrench)
        desired, reason = self._desired(ident, pose, w)
        cons = self._constraints(ident, w, pose)
        self._budget = max(0.0, self.force_limit_n - float(np.hypot(w[0], w[1]))) / \
            self.stiffness
        d = self._bound(self._project(desired, cons), self._project(np.zeros(3), cons))
        retreat = any(b > 0 for _, b, _ in cons)
        if retreat:
            reason = 'force above the limit: retreat; ' + reason
            d = self._sane_retreat(d, pose, max(b for _, b, _ in cons))
        return Step(float(d[0]), float(d[1]), float(d[2]), self._predict(ident, w, pose, d),
                    ident.state is ContactState.SEATED and not retreat and not np.any(desired),
                    retreat, reason)

    def _sane_retreat(self, d: np.ndarray, pose: CardPose, need_m: float) -> np.ndarray:
        """A retreat moves a contact point about as far as its excess force asks (need_m, the
        largest (f - limit) / stiffness). Two nearly opposed contacts that both want relief (a
        wedge) make the linear constraints conflict, and their least-squares answer can be
        anything: a 122 mm, 44 deg 'retreat' into the slot in a 4.5 in trial. Such a retreat
        (a card point moving more than twice the need and a step further) becomes a back-off
        out of the slot along the card's axis u, by the need within the step bound."""
        travel = float(np.hypot(d[0], d[1])) + abs(float(d[2])) * self._reach
        if travel <= 2 * need_m + self.max_step_m:
            return d
        back = float(np.clip(need_m, self.insert_step_m, self.max_step_m))
        return np.array([*(back * pose.u), 0.0])

    def _predict(self, ident: Identification, w: np.ndarray, pose: CardPose,
                 d: np.ndarray) -> float:
        """Largest contact force after d by the linear contact spring (0 once separated)."""
        worst = 0.0
        for a, _, force in self._constraints(ident, w, pose):
            worst = max(worst, force - self.stiffness * float(a @ d))
        return worst

    def _project(self, desired: np.ndarray, cons: Sequence[tuple[np.ndarray, float, Any]]
                 ) -> np.ndarray:
        """Nearest (weighted) d to desired with a_k . d >= b_k: enumerate active sets."""
        wgt = self._weight
        # work in scaled coordinates z = W d, so the metric is Euclidean
        z0 = desired * wgt
        rows = [(a / wgt, b) for a, b, _ in cons]
        best = None
        for k in range(len(rows) + 1):
            for active in itertools.combinations(range(len(rows)), k):
                z = z0.copy()
                if active:
                    am = np.array([rows[i][0] for i in active])
                    bm = np.array([rows[i][1] for i in active])
                    gram = am @ am.T
                    if np.linalg.matrix_rank(gram) < len(active):
                        continue
                    lam = np.linalg.solve(gram, bm - am @ z0)
                    if np.any(lam < -1e-12):
                        continue
                    z = z0 + am.T @ lam
                if all(a @ z >= b - 1e-12 for a, b in rows):
                    cost = float(np.sum((z - z0) ** 2))
                    if best is None or cost < best[0]:
                        best = (cost, z)
        if best is None:
            # conflicting retreats (cannot happen for b <= 0, where d = 0 is feasible): retreat
            # along the summed constraint normals
            a = np.asarray(sum(a for a, _, _ in cons))
            need = max(b for _, b, _ in cons)
            return a * need / max(float(a @ a), 1e-12)
        return best[1] / wgt

    def _bound(self, d: np.ndarray, d_min: np.ndarray) -> np.ndarray:
        """Into the step bounds along the segment from d_min (the smallest feasible increment:
        0, or the retreat a force above the limit needs) to d; the feasible set is convex, so
        the whole segment is feasible. A retreat larger than the bounds is kept whole here
        (getting under the force limit comes first), then checked by _sane_retreat."""
        def within(x: np.ndarray) -> bool:
            # and no card point moves further than an unforeseen contact could take before its
            # force reaches the limit (what the identification may have missed)
            travel = np.hypot(x[0], x[1]) + abs(x[2]) * self._reach
            return (np.hypot(x[0], x[1]) <= self.max_step_m * (1 + 1e-9) and
                    abs(x[2]) <= self.max_rotation_rad * (1 + 1e-9) and
                    travel <= self._budget * (1 + 1e-9))

        if within(d):
            return d
        if not within(d_min):
            return d_min
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if within(d_min + mid * (d - d_min)) else (lo, mid)
        return d_min + lo * (d - d_min)


def task_wrench(sensor_wrench: Sequence[float] | np.ndarray, t_task_sensor: ArrayLike, *,
                tare: ArrayLike | None = None, reaction: bool = True) -> np.ndarray:
    """A rover's 6-axis F/T reading (F, M in its sensor frame) as the wrench the environment
    exerts on the carried card, in the task (site) frame, moments about the task origin.

    tare: the reading in free space with the same arm pose (gravity and offsets), subtracted
    first. reaction: the sensor reports the base's wrench on the arm (rover_sim's F_12, N_12
    of Eq. B-1), so in quasi-static contact the site's wrench on the card is its negative.
    t_task_sensor: 4x4 pose of the sensor frame in the task frame (vision + arm kinematics)."""
    w = np.asarray(sensor_wrench, float)
    if w.shape != (6,) or not np.all(np.isfinite(w)):
        raise InsertionError(f'sensor wrench must be a finite 6-vector, got {w}')
    if tare is not None:
        t0 = np.asarray(tare, float)
        if t0.shape != (6,) or not np.all(np.isfinite(t0)):
            raise InsertionError('tare must be a finite 6-vector')
        w = w - t0
    t = np.asarray(t_task_sensor, float)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise InsertionError('t_task_sensor must be a finite 4x4 transform')
    r, p = t[:3, :3], t[:3, 3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6):
        raise InsertionError('t_task_sensor: rotation block is not orthonormal')
    f = r @ w[:3]
    m = r @ w[3:] + np.cross(p, f)
    out = np.concatenate([f, m])
    return -out if reaction else out


def planar_wrench(task_wrenches: ArrayLike) -> np.ndarray:
    """Sum of the rovers' task-frame wrenches (N, 6) reduced to the plane of the insertion:
    (F_x, F_y, M_z). "The measured forces/torques are evaluated from force/torque sensor
    readings of all cooperating robots" (app. A.4)."""
    w = np.atleast_2d(np.asarray(task_wrenches, float))
    if w.ndim != 2 or w.shape[1] != 6 or w.shape[0] < 1 or not np.all(np.isfinite(w)):
        raise InsertionError(f'task wrenches must be a finite (N >= 1, 6) array, got {w.shape}')
    total = w.sum(axis=0)
    return np.array([total[0], total[1], total[5]])


def planar_step_in_frame(step: Step, pose: CardPose, t_frame_task: ArrayLike) -> tuple[np.ndarray,
                                                                              np.ndarray]:
    """A Step as a 3-D translation of the card's leading-edge centre and a rotation vector
    (about that point), both in the frame t_frame_task maps into (e.g. the slave's base frame
    R_S: t_frame_task = its pose of the site frame)."""
    if not isinstance(step, Step) or not isinstance(pose, CardPose):
        raise InsertionError('need a Step and a CardPose')
    t = np.asarray(t_frame_task, float)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise InsertionError('t_frame_task must be a finite 4x4 transform')
    r = t[:3, :3]
    return r @ np.array([step.dx, step.dy, 0.0]), r @ np.array([0.0, 0.0, step.dtheta])
