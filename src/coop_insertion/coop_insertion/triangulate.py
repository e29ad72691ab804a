"""Stereo triangulation of marker centres with their covariance (thesis §5.3 with the stereo
model of §3.2.3, Eq. 3-1..3-7, from coop_mapping.stereo), no rclpy.

Left and right markers of a rectified pair are matched by the epipolar constraint (same row
within `max_row_px`), a positive disparity, similar size, and, when the marker's true radius is
known, a disparity consistent with its apparent size (d = b r_px / r); the assignment minimises
the summed normalised cost (scipy's linear_sum_assignment). A marker seen in one image only is
not triangulated. When both markers carry perspective candidates (markers.circle_candidates),
the pair of candidates whose plane normals agree best is used (a rectified pair has one
orientation, so the true normal is the same in both images; the false ones differ).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import assert_never

import numpy as np
from scipy.optimize import linear_sum_assignment

from coop_common.params import choice
from coop_mapping.stereo import ErrorModel, StereoCamera, disparity_to_range

from .errors import InsertionError
from .markers import Marker

__all__ = [
    'CovarianceModel',
    'StereoMarker',
    'match_markers',
    'stereo_candidates',
    'triangulate_markers',
]


class CovarianceModel(StrEnum):
    """A triangulated marker's covariance (`triangulate_markers`): its centres' errors
    propagated through (u, v, d) -> (X, Y, Z), or coop_mapping's Eq. 3-7 dense-stereo model."""

    PROPAGATED = 'propagated'
    EQ3_7 = 'eq3_7'


@dataclass(frozen=True)
class StereoMarker:
    """A marker triangulated in the left optical frame (x right, y down, z forward, m)."""

    left: int                    # index in the left list
    right: int                   # index in the right list
    position: np.ndarray         # (3,)
    covariance: np.ndarray       # (3, 3)
    uv_left: tuple[float, float]
    uv_right: tuple[float, float]


def stereo_candidates(ml: Marker, mr: Marker) -> tuple[tuple[float, float], tuple[float, float]]:
    """The centres to triangulate: the perspective candidates whose normals agree best across
    the two images when both have them, else the markers' own (u, v)."""
    if ml.normals is None or mr.normals is None or ml.candidates is None or \
            mr.candidates is None:                      # (normals and candidates go together)
        return (ml.u, ml.v), (mr.u, mr.v)
    cos = ml.normals @ mr.normals.T                     # (2, 2)
    i, j = np.unravel_index(int(np.argmax(cos)), cos.shape)
    ci, cj = ml.candidates[i], mr.candidates[j]
    return (float(ci[0]), float(ci[1])), (float(cj[0]), float(cj[1]))


def match_markers(left: list[Marker], right: list[Marker], camera: StereoCamera, *,
                  max_row_px: float = 2.0, max_radius_ratio: float = 1.3,
                  marker_radius_m: float | None = None, max_disparity_error: float = 0.3
                  ) -> list[tuple[int, int]]:
    """(left index, right index) pairs: same row within `max_row_px`, disparity > 0, radii
    within `max_radius_ratio`, and with `marker_radius_m` the disparity within
    `max_disparity_error` (relative) of the one its apparent size implies (size: the ellipse's
    major semi-axis, else radius_px)."""
    if not (max_row_px > 0 and max_radius_ratio >= 1 and max_disparity_error > 0):
        raise InsertionError('max_row_px, max_disparity_error must be > 0, '
                             'max_radius_ratio >= 1')
    if marker_radius_m is not None and not marker_radius_m > 0:
        raise InsertionError(f'marker_radius_m must be > 0, got {marker_radius_m}')
    if not left or not right:
        return []
    big = 1e6

    def size(m: Marker) -> float:
        # the major semi-axis: the circle's diameter across the tilt axis is not foreshortened
        return max(m.ellipse[2], m.ellipse[3]) if m.ellipse is not None else m.radius_px

    cost = np.full((len(left), len(right)), big)
    for i, a in enumerate(left):
        for j, b in enumerate(right):
            dv = abs(a.v - b.v)
            d = a.u - b.u
            ratio = max(size(a), size(b)) / max(min(size(a), size(b)), 1e-9)
            if dv > max_row_px or d <= 0 or ratio > max_radius_ratio:
                continue
            c = (dv / max_row_px) ** 2 + ((ratio - 1) / (max_radius_ratio - 1 + 1e-9)) ** 2
            if marker_radius_m is not None:
                r_px = 0.5 * (size(a) + size(b))
                d_exp = camera.baseline * r_px / marker_radius_m
                rel = abs(d - d_exp) / d_exp
                if rel > max_disparity_error:
                    continue
                c += (rel / max_disparity_error) ** 2
            cost[i, j] = c
    rows, cols = linear_sum_assignment(cost)
    return [(int(i), int(j)) for i, j in zip(rows, cols, strict=False) if cost[i, j] < big]


def triangulate_markers(left: list[Marker], right: list[Marker], camera: StereoCamera, *,
                        sigma_px: float = 0.05, marker_radius_m: float | None = None,
                        covariance: CovarianceModel | str = CovarianceModel.PROPAGATED,
                        max_row_px: float = 2.0) -> list[StereoMarker]:
    """Matched markers -> 3-D centres in the left optical frame with covariances.

    Range by Eq. 3-1..3-3 (Z = f b / d, coop_mapping.stereo.disparity_to_range). Covariance:
    'propagated' (default) is J diag(s_u^2, s_v^2, s_d^2) J^T of (u, v, d) -> (X, Y, Z), whose
    range term is Eq. 3-4..3-6 (sigma_Z = Z^2 sigma_d / (f b), coop_mapping.stereo.range_sigma),
    with s_u = s_v = the centres' sigma (each marker's fit sigma, at least `sigma_px`) and
    s_d = sqrt(2) s_u; 'eq3_7' is coop_mapping's Eq. 3-7 error model (ErrorModel.from_stereo
    with that sigma_d), the dense-stereo model the map uses."""
    covariance = choice(CovarianceModel, covariance, 'covariance', error=InsertionError)
    if not (sigma_px > 0 and math.isfinite(sigma_px)):
        raise InsertionError(f'sigma_px must be finite and > 0, got {sigma_px}')
    out = []
    for i, j in match_markers(left, right, camera, marker_radius_m=marker_radius_m,
                              max_row_px=max_row_px):
        (ul, vl), (ur, vr) = stereo_candidates(left[i], right[j])
        s = max([sigma_px, *(x for x in (left[i].sigma_px, right[j].sigma_px)
                             if math.isfinite(x))])
        d = ul - ur
        if not d > 0:
            continue
        v = 0.5 * (vl + vr)
        Z = float(disparity_to_range(np.array([d]), camera.fx, camera.baseline)[0])
        X = (ul - camera.cx) * Z / camera.fx
        Y = (v - camera.cy) * Z / camera.fy
        p = np.array([X, Y, Z])
        s_d = math.sqrt(2.0) * s
        match covariance:
            case CovarianceModel.PROPAGATED:
                # d(X, Y, Z) / d(u, v, d): Z = f b / d
                dZ = -Z / d
                J = np.array([[Z / camera.fx, 0.0, (ul - camera.cx) / camera.fx * dZ],
                              [0.0, Z / camera.fy, (v - camera.cy) / camera.fy * dZ],
                              [0.0, 0.0, dZ]])
                S = np.diag([s * s, s * s / 2.0, s_d * s_d])     # v is the mean of two rows
                cov = J @ S @ J.T              # cov[2, 2] = range_sigma(Z, f, b, s_d)^2, Eq. 3-6
            case CovarianceModel.EQ3_7:
                c6 = ErrorModel.from_stereo(camera, sigma_d_px=s_d).covariances(p[None])[0]
                cov = np.array([[c6[0], c6[1], c6[2]], [c6[1], c6[3], c6[4]],
                                [c6[2], c6[4], c6[5]]])
            case _:
                assert_never(covariance)
        out.append(StereoMarker(i, j, p, cov, (ul, vl), (ur, vr)))
    return out
