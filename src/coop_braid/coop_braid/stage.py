"""One parallel stage of BRAID (thesis app. E.3.1, Fig. E-2): the stage geometry and the forward
kinematics A_{i-1,i} of its 8 binary leg states.

The stage is modelled as the mechanism Fig. E-1(b)/E-2 describes: three legs 120 deg apart
between a base disk (frame i-1) and a platform disk (frame i). Leg j is attached at radius
`base_radius` in the base and `platform_radius` in the platform, at azimuth a_j = (j - 1) 120 deg
(leg 1 on the +x axis of both disks). The base flexure of a leg is a hinge whose axis is tangent
to the base circle (the three parallel axes of E.2), so leg j stays in the vertical plane through
the z axis and its base point; the platform end is a 3-DOF (spherical) joint. This is the 3-RPS
parallel stage: 3 DOF (z, pitch, yaw about x and y, Eq. E-5's R_xy), the x-y translation and the
torsion coupled to them, as the thesis notes.

Leg j has the effective length l_j (its vertical projection b_j and the leg angles of Figs. E-3
and E-4 follow from it). With the elevation angle theta_j of leg j in its plane (pi/2 is
vertical), its platform point is

    p_j = (r_b + l_j cos theta_j) u_j + l_j sin theta_j e_z,   u_j = (cos a_j, sin a_j, 0),

and the loop closure of the stage (the two transcendental equations E-24 and E-30 and the
height E-31, written for all three legs at once) is that the three platform points form the
platform's equilateral triangle:

    |p_j - p_k|^2 = 3 r_p^2   for (j, k) = (1, 2), (2, 3), (3, 1).

These three equations in (theta_1, theta_2, theta_3) are solved by Newton-Raphson as in E.3.1;
the frame of the platform is then the triangle's (origin at its centroid, x towards leg 1, z its
normal), which gives A_{i-1,i} (Eq. E-4). When one leg differs from the other two the solution
is closed-form (`symmetric_tilt`), which the tests use as the hand computation.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

from coop_braid.errors import BraidError

#: the azimuths a_j of the three legs, 120 deg apart (Fig. E-2)
LEG_AZIMUTHS = np.array([0.0, 2.0 * math.pi / 3.0, 4.0 * math.pi / 3.0])
#: number of binary states of one stage: 2^3
STATES_PER_STAGE = 8


class LegState(IntEnum):
    """The two states of a binary leg (E.2): retracted (SMA off) or extended."""

    SHORT = 0
    LONG = 1


def leg_states(state: int) -> tuple[LegState, LegState, LegState]:
    """The three legs' states of stage state `state` in 0..7: bit j - 1 is leg j."""
    if not 0 <= state < STATES_PER_STAGE:
        raise BraidError(f'stage state {state} is not in 0..7')
    return (LegState(state & 1), LegState((state >> 1) & 1), LegState((state >> 2) & 1))


class StageSolveError(BraidError):
    """The loop-closure equations of a stage have no solution for these leg lengths (the legs
    cannot be assembled) or Newton-Raphson did not converge to the upright branch."""


def _points(theta: NDArray[np.float64], lengths: NDArray[np.float64],
            base_radius: float) -> NDArray[np.float64]:
    """The platform points p_j (3, 3), one per row, for leg angles theta and lengths l."""
    rho = base_radius + lengths * np.cos(theta)
    return np.stack([rho * np.cos(LEG_AZIMUTHS), rho * np.sin(LEG_AZIMUTHS),
                     lengths * np.sin(theta)], axis=1)


def solve_leg_angles(lengths: NDArray[np.float64], *, base_radius: float,
                     platform_radius: float, tol: float = 1e-15,
                     max_iter: int = 50) -> NDArray[np.float64]:
    """The leg elevation angles (theta_1, theta_2, theta_3) that close the stage's loop for leg
    lengths `lengths`, by Newton-Raphson (E.3.1) from the upright pose of equal legs.

    With rho_j = r_b + l_j cos theta_j and z_j = l_j sin theta_j and u_j . u_k = -1/2, the
    residual of pair (j, k) is rho_j^2 + rho_k^2 + rho_j rho_k + (z_j - z_k)^2 - 3 r_p^2.
    Raises StageSolveError when it does not converge to a solution with every leg above the
    base (0 < theta_j < pi)."""
    legs = np.asarray(lengths, dtype=float)
    pairs = ((0, 1), (1, 2), (2, 0))
    target = 3.0 * platform_radius ** 2
    c0 = np.clip((platform_radius - base_radius) / legs, -1.0, 1.0)
    theta = np.arccos(c0)                       # equal legs: platform parallel to the base
    for _ in range(max_iter):
        c, s = np.cos(theta), np.sin(theta)
        rho, z = base_radius + legs * c, legs * s
        drho, dz = -legs * s, legs * c
        f = np.empty(3)
        jac = np.zeros((3, 3))
        for row, (j, k) in enumerate(pairs):
            f[row] = rho[j] ** 2 + rho[k] ** 2 + rho[j] * rho[k] + (z[j] - z[k]) ** 2 - target
            jac[row, j] = (2 * rho[j] + rho[k]) * drho[j] + 2 * (z[j] - z[k]) * dz[j]
            jac[row, k] = (2 * rho[k] + rho[j]) * drho[k] - 2 * (z[j] - z[k]) * dz[k]
        try:
            step = np.linalg.solve(jac, f)
        except np.linalg.LinAlgError:
            raise StageSolveError(f'legs {legs.tolist()}: singular loop-closure '
                                  'Jacobian') from None
        theta = theta - step
        if float(np.max(np.abs(step))) <= tol * max(1.0, float(np.max(np.abs(theta)))) \
                or float(np.max(np.abs(f))) <= tol * target:
            break
    else:
        raise StageSolveError(f'legs {legs.tolist()}: Newton-Raphson did not converge')
    p = _points(theta, legs, base_radius)
    resid = max(abs(float(np.sum((p[j] - p[k]) ** 2)) - target) for j, k in pairs)
    if not np.all(np.isfinite(theta)) or resid > 1e-12 * max(target, 1e-12):
        raise StageSolveError(f'legs {legs.tolist()}: the loop does not close '
                              f'(residual {resid:.3g} m^2)')
    if not np.all((theta > 0.0) & (theta < math.pi)):
        raise StageSolveError(f'legs {legs.tolist()}: a leg folds below the base '
                              f'(angles {np.degrees(theta).round(2).tolist()} deg)')
    return theta


def platform_frame(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The 4x4 transform of the platform frame from its three attachment points (rows): origin
    at their centroid, x towards point 1, z the normal of the triangle (p2 - p1) x (p3 - p1)."""
    c = points.mean(axis=0)
    ex = points[0] - c
    ex = ex / np.linalg.norm(ex)
    ez = np.cross(points[1] - points[0], points[2] - points[0])
    ez = ez / np.linalg.norm(ez)
    ey = np.cross(ez, ex)
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2], out[:3, 3] = ex, ey, ez, c
    return out


@dataclass(frozen=True)
class StageGeometry:
    """One BRAID stage's geometry (Fig. E-2), metres: the two lengths of a binary leg and the
    attachment radii of the legs in the base and the platform disk; the legs are 120 deg apart.

    Refused at construction (BraidError with the reason) when a value is not finite and
    positive, the short leg is not shorter than the long one, or a leg state cannot be
    assembled (the loop closure has no upright solution: legs too different for the disks).
    The 8 transforms A_{i-1,i} are solved once here (`transforms`)."""

    leg_short: float = 0.045
    leg_long: float = 0.060
    base_radius: float = 0.040
    platform_radius: float = 0.040
    _transforms: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        for name in ('leg_short', 'leg_long', 'base_radius', 'platform_radius'):
            v = getattr(self, name)
            if not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0.0:
                raise BraidError(f'StageGeometry.{name} = {v!r}: must be finite and > 0 m')
        if self.leg_short >= self.leg_long:
            raise BraidError(f'StageGeometry: leg_short {self.leg_short} m must be shorter than '
                             f'leg_long {self.leg_long} m (two distinct binary lengths)')
        out = np.empty((STATES_PER_STAGE, 4, 4))
        for s in range(STATES_PER_STAGE):
            try:
                out[s] = stage_transform(self.leg_lengths(s), base_radius=self.base_radius,
                                         platform_radius=self.platform_radius)
            except StageSolveError as exc:
                raise BraidError(f'StageGeometry: state {s} cannot be assembled: {exc}') from None
        out.setflags(write=False)
        object.__setattr__(self, '_transforms', out)

    def leg_lengths(self, state: int) -> NDArray[np.float64]:
        """(l_1, l_2, l_3) of stage state `state` (bit j - 1 set: leg j long)."""
        return np.array([self.leg_long if leg else self.leg_short for leg in leg_states(state)])

    @property
    def transforms(self) -> NDArray[np.float64]:
        """A_{i-1,i} of the 8 stage states, (8, 4, 4), read-only (index: the stage state)."""
        return self._transforms

    def transform(self, state: int) -> NDArray[np.float64]:
        """A_{i-1,i} (Eq. E-4) of one stage state."""
        leg_states(state)
        return self._transforms[state]


def stage_transform(lengths: NDArray[np.float64], *, base_radius: float,
                    platform_radius: float) -> NDArray[np.float64]:
    """A_{i-1,i} (Eq. E-4) of a stage with leg lengths (l_1, l_2, l_3) (any, not only the binary
    pair): Newton-Raphson on the loop closure, then the platform triangle's frame."""
    legs = np.asarray(lengths, dtype=float)
    if legs.shape != (3,) or not np.all(np.isfinite(legs)) or np.any(legs <= 0.0):
        raise BraidError(f'leg lengths {legs.tolist()}: three finite lengths > 0 m')
    theta = solve_leg_angles(legs, base_radius=base_radius, platform_radius=platform_radius)
    return platform_frame(_points(theta, legs, base_radius))


def symmetric_tilt(odd: float, pair: float, *, radius: float) -> tuple[float, float, float]:
    """Closed form of the stage with equal disks (r_b = r_p = r) when legs 2 and 3 have length
    `pair` and leg 1 length `odd` (Fig. E-3's section through leg 1): legs 2 and 3 stand vertical
    (rho_2 = rho_3 = r), and leg 1's angle solves
    3 r l_1 cos theta_1 - 2 l_1 l_2 sin theta_1 = -(l_1^2 + l_2^2).
    Returns (theta_1, the platform's tilt about -y in rad (positive: leg 1 higher), and the
    height of the centroid)."""
    a, b, r = odd, pair, radius
    amp, delta = math.hypot(3 * r * a, 2 * a * b), math.atan2(2 * a * b, 3 * r * a)
    theta1 = math.acos(-(a * a + b * b) / amp) - delta
    rho1, z1 = r + a * math.cos(theta1), a * math.sin(theta1)
    tilt = math.atan2(z1 - b, rho1 + r / 2)
    return theta1, tilt, (z1 + 2 * b) / 3
