"""Dynamic tip-over stability (Sujan 2002, app. A.3, Eq. A-5): the zero-moment point of a rover
with its arm and load, its margin inside the wheels' footprint, and a limiter that scales a
commanded motion so the margin stays (no rclpy).

Frame: any frame with z up and the ground (the support plane) at z = 0, e.g. the rover's
base_footprint (REP 120) or `map` on flat ground. Each mass m_i at r_i with acceleration a_i
loads the ground with m_i (a_i - g) (d'Alembert: inertia and weight), g the gravitational
acceleration ((0, 0, -9.81) on level ground, tilted in a frame that tilts). External forces F_k
act on the rover at S_k (the F/T sensor's reading of what the arm's environment pushes), external
moments M_j on it. The zero-moment point p = (x, y, 0) is where the horizontal moment of all
of them vanishes:

    x = (sum A_z x_i - sum A_x z_i + sum M_y + sum (z_S F_x - x_S F_z)) / (sum A_z - sum F_z)
    y = (sum A_z y_i - sum A_y z_i - sum M_x + sum (z_S F_y - y_S F_z)) / (sum A_z - sum F_z)

with A_i = m_i (a_i - g). The x row is Eq. A-5's; the y row as printed has the signs of its
moment and external-force terms the other way round, which does not follow from its own first
line (T = 0) and is not the x row turned by 90 deg: the row above is derived from that first
line (tested against the moment balance). The denominator is the ground's vertical reaction; at
or below zero the rover leaves the ground and there is no ZMP (TipOverError).

The rover stays upright while p lies inside the support polygon, the convex hull of its wheels'
ground contacts. `margin` is p's signed distance to the polygon's boundary (negative outside);
`margin_fraction` divides it by the polygon's centroid's distance to its nearest edge, so 1 is
p at the centroid, 0 on the boundary. `limit_motion` takes a motion as accelerations (and
forces) that grow linearly with a scale s of the command (s = 1 the command as given, s = 0 no
motion): p(s) is a ratio of two linear functions of s, so each edge's condition is linear in s
and the largest s that keeps a required margin is exact, without search.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from coop_common.dynparams import BaseParameters
from coop_common.rover_geometry import BASE_HEIGHT_M, WHEEL_CONTACTS

from .errors import InsertionError
from .feedforward import ArmModel

__all__ = ['Footprint', 'Limit', 'Loads', 'RoverMasses', 'TipOverError', 'limit_motion',
           'limit_path', 'zmp']

GRAVITY = np.array([0.0, 0.0, -9.81])


class TipOverError(InsertionError):
    """Bad input to the tip-over core, or a state with no zero-moment point (the ground carries
    no weight)."""


def _arr(name: str, v: ArrayLike, shape: tuple[int | None, ...]) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    if a.ndim != len(shape) or any(s is not None and s != d for s, d in zip(shape, a.shape,
                                                                          strict=True)):
        raise TipOverError(f'{name}: shape {a.shape}, expected {shape}')
    if not np.all(np.isfinite(a)):
        raise TipOverError(f'{name}: not finite')
    return a


@dataclass(frozen=True)
class Loads:
    """What loads the ground: masses (n,) kg at positions (n, 3) m with accelerations (n, 3)
    m/s^2; external forces (k, 3) N on the rover at points (k, 3) m; external moments (j, 3) N m;
    gravity (3,) m/s^2."""

    masses: np.ndarray
    positions: np.ndarray
    accelerations: np.ndarray
    forces: np.ndarray
    force_points: np.ndarray
    moments: np.ndarray
    gravity: np.ndarray

    @classmethod
    def of(cls, masses: ArrayLike, positions: ArrayLike, accelerations: ArrayLike | None = None,
           *, forces: ArrayLike | None = None, force_points: ArrayLike | None = None,
           moments: ArrayLike | None = None, gravity: ArrayLike = GRAVITY) -> Loads:
        """Checked loads (TipOverError for shapes that do not agree, non-finite numbers,
        negative masses); missing accelerations, forces and moments are zero."""
        m = _arr('masses', masses, (None,))
        n = len(m)
        if n == 0 or np.any(m < 0):
            raise TipOverError('masses: need at least one, none negative')
        r = _arr('positions', positions, (n, 3))
        a = _arr('accelerations', np.zeros((n, 3)) if accelerations is None else accelerations,
                 (n, 3))
        f = _arr('forces', np.zeros((0, 3)) if forces is None else forces, (None, 3))
        s = _arr('force_points', np.zeros((0, 3)) if force_points is None else force_points,
                 (len(f), 3))
        mo = _arr('moments', np.zeros((0, 3)) if moments is None else moments, (None, 3))
        g = _arr('gravity', gravity, (3,))
        return cls(m, r, a, f, s, mo, g)

    def terms(self) -> tuple[np.ndarray, float]:
        """(numerator (2,), denominator) of the zero-moment point: p = numerator / denominator."""
        A = self.masses[:, None] * (self.accelerations - self.gravity)
        r, F, S = self.positions, self.forces, self.force_points
        M = self.moments.sum(axis=0) if len(self.moments) else np.zeros(3)
        nx = (A[:, 2] @ r[:, 0] - A[:, 0] @ r[:, 2] + M[1]
              + np.sum(S[:, 2] * F[:, 0] - S[:, 0] * F[:, 2]))
        ny = (A[:, 2] @ r[:, 1] - A[:, 1] @ r[:, 2] - M[0]
              + np.sum(S[:, 2] * F[:, 1] - S[:, 1] * F[:, 2]))
        den = float(A[:, 2].sum() - F[:, 2].sum())
        return np.array([nx, ny]), den


def zmp(loads: Loads) -> np.ndarray:
    """The zero-moment point (x, y) on the ground (module docstring); TipOverError when the
    ground carries no weight."""
    num, den = loads.terms()
    if not den > 1e-9:
        raise TipOverError(f'the ground carries {den:.3g} N: the rover is off the ground')
    return num / den


@dataclass(frozen=True)
class Footprint:
    """The support polygon: the convex hull of the wheels' ground contacts (x, y), counter-
    clockwise, as edges n . p >= c with inward unit normals."""

    vertices: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray

    @classmethod
    def of(cls, contacts: ArrayLike) -> Footprint:
        """From the wheel contacts (m, 2 or 3; z ignored); TipOverError for fewer than three
        not on one line."""
        p = _arr('contacts', contacts, (None, None))
        if p.shape[1] not in (2, 3) or len(p) < 3:
            raise TipOverError(f'contacts: {p.shape}, need >= 3 points of 2 or 3 coordinates')
        hull = _hull(p[:, :2])
        if len(hull) < 3:
            raise TipOverError('contacts: all on one line, no support polygon')
        edges = np.roll(hull, -1, axis=0) - hull
        inward = np.stack([-edges[:, 1], edges[:, 0]], axis=1)     # left of a ccw edge
        inward /= np.linalg.norm(inward, axis=1, keepdims=True)
        return cls(hull, inward, np.einsum('ij,ij->i', inward, hull))

    @property
    def centroid(self) -> np.ndarray:
        v, w = self.vertices, np.roll(self.vertices, -1, axis=0)
        cross = v[:, 0] * w[:, 1] - w[:, 0] * v[:, 1]
        area = cross.sum() / 2.0
        return ((v + w) * cross[:, None]).sum(axis=0) / (6.0 * area)

    @property
    def depth(self) -> float:
        """The centroid's distance to the nearest edge (margin_fraction's unit)."""
        return float(np.min(self.normals @ self.centroid - self.offsets))

    def margin(self, p: np.ndarray) -> float:
        """p's signed distance to the boundary (m; negative outside)."""
        return float(np.min(self.normals @ np.asarray(p, float) - self.offsets))

    def margin_fraction(self, p: np.ndarray) -> float:
        return self.margin(p) / self.depth


def _turn(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """z of (a - o) x (b - o): > 0 for a left turn."""
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _hull(p: np.ndarray) -> np.ndarray:
    """Convex hull, counter-clockwise (Andrew's monotone chain), collinear points dropped."""
    pts = np.unique(p, axis=0)
    if len(pts) < 3:
        return pts

    def half(points: np.ndarray) -> list[np.ndarray]:
        out: list[np.ndarray] = []
        for q in points:
            while len(out) >= 2 and _turn(out[-2], out[-1], q) <= 1e-12:
                out.pop()
            out.append(q)
        return out
    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


@dataclass(frozen=True)
class Limit:
    """What `limit_motion` allows: the scale of the command (0..1), the margin fraction at
    that scale, and `stop` when even no motion (s = 0) is below the required margin (then the
    rover must not be commanded through it: s is 0)."""

    scale: float
    margin_fraction: float
    stop: bool


def limit_motion(at_rest: Loads, commanded: Loads, footprint: Footprint, *,
                 min_fraction: float = 0.2) -> Limit:
    """The largest s in [0, 1] such that the loads at_rest + s (commanded - at_rest) keep the
    zero-moment point at least `min_fraction` of the footprint's depth inside (module
    docstring). `at_rest` and `commanded` are the same masses in the same places, with the
    accelerations and external forces of no motion and of the command."""
    if not 0.0 <= min_fraction < 1.0:
        raise TipOverError(f'min_fraction {min_fraction} outside [0, 1)')
    n0, d0 = at_rest.terms()
    n1, d1 = commanded.terms()
    need = footprint.offsets + min_fraction * footprint.depth
    # edge e: normal . n(s) >= need_e d(s), n(s) = n0 + s dn, d(s) = d0 + s dd, d(s) > 0
    dn, dd = n1 - n0, d1 - d0
    lhs0 = footprint.normals @ n0 - need * d0           # >= 0 at s = 0 to start
    slope = footprint.normals @ dn - need * dd
    if not d0 > 1e-9 or np.any(lhs0 < -1e-9):
        return Limit(0.0, footprint.margin_fraction(n0 / d0) if d0 > 1e-9 else -np.inf, True)
    s = 1.0
    falling = slope < 0
    if np.any(falling):
        s = min(s, float(np.min(-lhs0[falling] / slope[falling])))
    if dd < 0:                                          # the ground must keep some weight
        s = min(s, 0.999 * d0 / -dd)
    s = max(s, 0.0)
    p = (n0 + s * dn) / (d0 + s * dd)
    return Limit(s, footprint.margin_fraction(p), False)


def limit_path(path: list[tuple[Loads, Loads]], footprint: Footprint, *,
               min_fraction: float = 0.2) -> Limit:
    """`limit_motion` along a planned motion: at each of its instants, the loads with the
    masses where the plan puts them standing still and with the plan's accelerations (and
    forces). The scale is the smallest over the instants: the accelerations a time-scaling of
    the plan by 1 / sqrt(scale) keeps inside the margin. `stop` when some instant is below the
    margin even standing still: no slowing-down makes that plan safe, and it must not be
    commanded."""
    if not path:
        raise TipOverError('an empty path')
    worst = Limit(1.0, np.inf, False)
    for still, moving in path:
        lim = limit_motion(still, moving, footprint, min_fraction=min_fraction)
        if lim.stop:
            return lim
        if lim.scale < worst.scale or (lim.scale == worst.scale
                                       and lim.margin_fraction < worst.margin_fraction):
            worst = lim
    return worst


@dataclass(frozen=True)
class RoverMasses:
    """One rover as Eq. A-5's particles, from its model only (no truth): the base's mass at its
    c.g. (the identified mass, which is the rover without its arm), the arm's links and load
    where its joints put them (feedforward.ArmModel, mounted at the identified r_2), over the
    wheels' support polygon. Frame: under the base at rest (x forward, z up, the ground at
    z = 0, the c.g. `height` above it)."""

    base_mass: float
    arm: ArmModel
    height: float
    footprint: Footprint
    tilt_stiffness: tuple[float, float] = (math.inf, math.inf)    # k_roll, k_pitch (N m/rad)

    @classmethod
    def of(cls, params: BaseParameters, *, load_kg: float = 0.0,
           wheel_contacts: ArrayLike = WHEEL_CONTACTS, height: float = BASE_HEIGHT_M
           ) -> RoverMasses:
        if not (np.isfinite(params.mass) and params.mass > 0.0):
            raise TipOverError(f'base mass {params.mass}: must be > 0')
        k_roll, k_pitch = (float(k) if k > 0 else math.inf for k in params.stiffness[3:5])
        return cls(float(params.mass), ArmModel.rover(params.cg_to_arm, load_kg=load_kg),
                   float(height), Footprint.of(wheel_contacts), (k_roll, k_pitch))

    @property
    def masses(self) -> np.ndarray:
        return np.concatenate([[self.base_mass], self.arm.masses])

    def positions(self, q: ArrayLike) -> np.ndarray:
        """The particles' positions at arm joints q ((1 + n, 3): the base's first), the sprung
        body leaning on its suspension under the arm's weight: rolled and pitched about its
        c.g. by the weight's moment over the identified stiffness (Eq. B-4 at rest), which
        moves everything above the ground toward the side the arm loads."""
        arm = self.arm.com_positions(q)
        moment = np.sum(self.arm.masses[:, None] * np.cross(arm, GRAVITY), axis=0)
        roll = moment[0] / self.tilt_stiffness[0]
        pitch = moment[1] / self.tilt_stiffness[1]
        cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        rot = np.array([[cp, sp * sr, sp * cr], [0.0, cr, -sr], [-sp, cp * sr, cp * cr]])
        lift = np.array([0.0, 0.0, self.height])
        return np.vstack([lift, arm @ rot.T + lift])

    def loads(self, q: ArrayLike, *, base_acceleration: ArrayLike = (0.0, 0.0, 0.0),
              arm_accelerations: ArrayLike | None = None) -> Loads:
        """The loads at q with the base accelerating (base axes) and the links accelerating
        on top of it ((n, 3); none: the arm still on the base)."""
        a0 = _arr('base_acceleration', base_acceleration, (3,))
        n = self.arm.n
        acc = np.zeros((n + 1, 3)) + a0
        if arm_accelerations is not None:
            acc[1:] += _arr('arm_accelerations', arm_accelerations, (n, 3))
        return Loads.of(self.masses, self.positions(q), acc)

    def path(self, qs: ArrayLike, dt: float, base_accelerations: ArrayLike | None = None
             ) -> list[tuple[Loads, Loads]]:
        """A planned motion sampled every dt ((m, n) joint positions, m >= 3; the base's
        accelerations (m, 3) along it, none: standing): per inner sample, the loads standing
        still and moving, the links' accelerations by the plan's second differences."""
        q = _arr('qs', qs, (None, self.arm.n))
        if len(q) < 3 or not dt > 0.0:
            raise TipOverError(f'a path needs >= 3 samples and dt > 0 (got {len(q)}, {dt})')
        base = (np.zeros((len(q), 3)) if base_accelerations is None else
                _arr('base_accelerations', base_accelerations, (len(q), 3)))
        pos = np.array([self.arm.com_positions(qk) for qk in q])
        acc = (pos[:-2] - 2 * pos[1:-1] + pos[2:]) / dt ** 2
        return [(self.loads(q[k]), self.loads(q[k], base_acceleration=base[k],
                                              arm_accelerations=acc[k - 1]))
                for k in range(1, len(q) - 1)]

    def drive_acceleration(self, q: ArrayLike, *, top: float, min_fraction: float) -> float:
        """The largest forward or backward base acceleration (up to `top`, m/s^2) that keeps
        the point `min_fraction` inside at q, either way; 0 when standing still is already
        below it."""
        still = self.loads(q)
        allowed = top
        for sign in (1.0, -1.0):
            lim = limit_motion(still, self.loads(q, base_acceleration=(sign * top, 0.0, 0.0)),
                               self.footprint, min_fraction=min_fraction)
            allowed = min(allowed, 0.0 if lim.stop else top * lim.scale)
        return allowed
