"""Circular marker identification (Sujan 2002, §5.3), no rclpy.

Three detectors behind one interface (`MarkerDetector.detect(image) -> list[Marker]`, mono8 in):

- `ThesisDetector`: the thesis's pipeline as published: histogram equalisation, threshold,
  the Eq. 5-6 Laplacian, a 3x3 low pass, a threshold at the histogram peak - 5, the Tracking
  Hough Transform on three-point circles (Eq. 5-7..5-9, distance-D and d-theta = pi/6 rules,
  > 35 % of the circumference) and a region-growing centroid.
- `EllipseDetector` (the default, `make_detector('default')`): candidate blobs from local
  thresholds on a two-level pyramid with an isolation test, sub-pixel edge points where the
  image crosses the level half-way between the marker's and its surround's planar-fitted
  brightness, a direct least-squares ellipse fit
  (Fitzgibbon, cv2.fitEllipseDirect) with outlier trimming (partial occlusion), and, given the
  camera intrinsics, the perspective bias of the ellipse centre removed (`circle_candidates`).
- `HoughDetector`: cv2.HoughCircles, the usual off-the-shelf baseline.

An imaged circle is an ellipse whose centre is not the image of the circle's centre. From the
ellipse's conic C and K, the cone of rays Q = K^T C K fixes the circle's plane normal up to a
two-fold ambiguity, and the image of the circle's centre is the pole of the plane's vanishing
line, x ~ Q^-1 n (`circle_candidates`). The ambiguity is resolved by a normal hint, by
coplanar markers in the same image (the true normals agree, the false ones do not), or in
stereo (`triangulate.py`: the true normal is the same in both rectified images).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import Enum, StrEnum
from typing import Any, Protocol, assert_never, runtime_checkable

import cv2
import numpy as np

from coop_common.params import choice

from .errors import InsertionError

__all__ = [
    'DETECTORS',
    'LAPLACIAN_5_6',
    'Ambiguity',
    'DetectorKind',
    'EllipseDetector',
    'HoughDetector',
    'Marker',
    'MarkerDetector',
    'Polarity',
    'ThesisDetector',
    'check_image',
    'circle_candidates',
    'ellipse_conic',
    'make_detector',
    'resolve_coplanar',
    'three_point_circles',
]


class Polarity(Enum):
    """Markers brighter than their surround (the thesis's white markers) or darker (holes)."""

    BRIGHT = 'bright'
    DARK = 'dark'


class Ambiguity(StrEnum):
    """What EllipseDetector does with a marker's two perspective candidates when no normal hint
    is given: pick by the markers' common plane ('coplanar'), or keep the ellipse centre."""

    COPLANAR = 'coplanar'
    NONE = 'none'


@dataclass(frozen=True)
class Marker:
    """One circular marker in one image.

    (u, v): the centre estimate (px), the image of the circle's centre when the perspective
    correction was applied and resolved, else the ellipse (or circle) centre. `ellipse`:
    (cx, cy, semi-axis a, semi-axis b, angle of a in rad), None for detectors that fit circles.
    `candidates`: the two perspective-corrected centres (2, 2) and `normals`: the two plane
    normals (2, 3, camera frame, towards the camera) when the correction ran; `resolved` says
    whether (u, v) is one of them. `sigma_px`: standard deviation of the centre from the fit."""

    u: float
    v: float
    radius_px: float
    score: float
    ellipse: tuple[float, float, float, float, float] | None = None
    sigma_px: float = float('nan')
    candidates: np.ndarray | None = field(default=None, compare=False)
    normals: np.ndarray | None = field(default=None, compare=False)
    resolved: bool = False

    @property
    def centre(self) -> tuple[float, float]:
        return (self.u, self.v)


@runtime_checkable
class MarkerDetector(Protocol):
    """Anything that finds circular markers in a mono8 image."""

    def detect(self, image: np.ndarray) -> list[Marker]:
        ...


def check_image(image: object) -> np.ndarray:
    """The image as a 2-D uint8 array, else InsertionError."""
    if not isinstance(image, np.ndarray) or image.ndim != 2 or image.dtype != np.uint8:
        what = (f'{image.dtype} array of shape {image.shape}' if isinstance(image, np.ndarray)
                else type(image).__name__)
        raise InsertionError(f'need a mono8 image (2-D uint8 array), got {what}')
    if image.shape[0] < 16 or image.shape[1] < 16:
        raise InsertionError(f'image {image.shape} is smaller than 16 x 16')
    return np.ascontiguousarray(image)


def _radius_range(radius_px: tuple[float, float]) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in radius_px)
    except (TypeError, ValueError):
        raise InsertionError(f'radius_px must be (min, max), got {radius_px!r}') from None
    if not (2.0 <= lo < hi <= 500.0):
        raise InsertionError(f'radius_px must satisfy 2 <= min < max <= 500, got {radius_px}')
    return lo, hi


def _polarity(p: Polarity | str) -> Polarity:
    try:
        return Polarity(p.value if isinstance(p, Polarity) else p)
    except ValueError:
        raise InsertionError(f'polarity must be one of {[x.value for x in Polarity]}, '
                             f'got {p!r}') from None


def _intrinsics(K: np.ndarray | None) -> np.ndarray | None:
    if K is None:
        return None
    k = np.asarray(K, float)
    if k.shape != (3, 3) or not np.all(np.isfinite(k)) or not (k[0, 0] > 0 and k[1, 1] > 0) \
            or not np.allclose(k[2], [0, 0, 1]) or k[1, 0] != 0:
        raise InsertionError(f'K must be a finite 3x3 pinhole matrix, got {K!r}')
    return k


# ------------------------------------------------------------------ geometry of imaged circles

def ellipse_conic(cx: float, cy: float, a: float, b: float, angle: float) -> np.ndarray:
    """3x3 symmetric conic C of the ellipse (x^T C x = 0 for x = (u, v, 1) on it)."""
    c, s = math.cos(angle), math.sin(angle)
    R = np.array([[c, -s], [s, c]])
    M = R @ np.diag([1.0 / (a * a), 1.0 / (b * b)]) @ R.T
    ctr = np.array([cx, cy])
    Mc = M @ ctr
    return np.block([[M, -Mc[:, None]], [-Mc[None, :], np.array([[ctr @ Mc - 1.0]])]])


def circle_candidates(conic: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The two (plane normal, image of the centre) pairs of a circle imaged as `conic`.

    Q = K^T C K is the cone of rays through the circle (normalised camera coordinates). With
    its eigenvalues l1 >= l2 > 0 > l3 (sign fixed so two are positive) and eigenvectors
    e1, e2, e3, the planes cutting it in circles have normals
    n = +-sqrt((l1 - l2) / (l1 - l3)) e1 + sqrt((l2 - l3) / (l1 - l3)) e3, and the circle's centre
    is imaged at the pole of the plane's vanishing line n: x ~ Q^-1 n, then K x in pixels.
    Returns normals (2, 3) facing the camera and centres (2, 2) in pixels."""
    Q = K.T @ conic @ K
    w, V = np.linalg.eigh(Q)
    if (w > 0).sum() < 2:
        Q, w = -Q, -w
    order = np.argsort(w)[::-1]
    w, V = w[order], V[:, order]
    l1, l2, l3 = w
    if not (l2 > 0 > l3):
        raise InsertionError('the conic is not the image of a real circle (not an ellipse)')
    p = math.sqrt(max(l1 - l2, 0.0) / (l1 - l3))
    q = math.sqrt(max(l2 - l3, 0.0) / (l1 - l3))
    normals = np.empty((2, 3))
    centres = np.empty((2, 2))
    for i, s in enumerate((1.0, -1.0)):
        n = V @ np.array([s * p, 0.0, q])
        x = np.linalg.solve(Q, n)
        x = x / x[2]
        if n @ x > 0:                    # the visible side faces the camera
            n = -n
        normals[i] = n
        centres[i] = (K @ x)[:2]
    return normals, centres


def resolve_coplanar(markers: list[Marker], *, max_angle_rad: float = math.radians(8.0),
                     normal_hint: np.ndarray | None = None) -> list[Marker]:
    """Pick each marker's perspective candidate: the one nearest `normal_hint` when given, else
    the one whose normal agrees best (within `max_angle_rad`) with a candidate normal of another
    marker in the image (coplanar markers share the true normal; the false ones point elsewhere),
    else the marker keeps its ellipse centre and `resolved` stays False."""
    out = []
    for i, m in enumerate(markers):
        if m.normals is None or m.candidates is None:       # (set together)
            out.append(m)
            continue
        if normal_hint is not None:
            h = np.asarray(normal_hint, float)
            k = int(np.argmax(np.abs(m.normals @ h)))
            out.append(replace(m, u=float(m.candidates[k, 0]), v=float(m.candidates[k, 1]),
                               resolved=True))
            continue
        best, best_k, second = math.inf, -1, math.inf
        for j, o in enumerate(markers):
            if j == i or o.normals is None:
                continue
            ang = np.arccos(np.clip(m.normals @ o.normals.T, -1.0, 1.0))   # (2, 2)
            per_k = ang.min(axis=1)
            k = int(np.argmin(per_k))
            if per_k[k] < best:
                best, best_k, second = per_k[k], k, per_k[1 - k]
        # the candidates coincide at normal incidence: nothing to resolve, either is right
        same = np.hypot(*(m.candidates[0] - m.candidates[1])) < 1e-3
        if same or (best_k >= 0 and best < max_angle_rad and second > best):
            k = 0 if same else best_k
            out.append(replace(m, u=float(m.candidates[k, 0]), v=float(m.candidates[k, 1]),
                               resolved=True))
        else:
            out.append(m)
    return out


# ------------------------------------------------------------------ the thesis pipeline (§5.3)

#: Eq. 5-6: the 3x3 discrete Laplacian (second central differences, first-order terms)
LAPLACIAN_5_6 = np.array([[0, 1, 0], [1, -4, 1], [0, 1, 0]], np.float32)


def three_point_circles(p1: np.ndarray, p2: np.ndarray, p3: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Eq. 5-7..5-9 for (N, 2) arrays of (u, v) points: the centre (x, y) where the bisectors of
    segments 1-2 and 2-3 intersect, the radius as the mean distance to the three points, and
    theta, the angle between the bisectors. Bisector k has slope m_k = (u_{k+1} - u_k) /
    (-v_{k+1} + v_k) through the midpoint (x_k, y_k) (Eq. 5-8); [x, y] solves
    [-m1 1; -m2 1] [x; y] = [y1 - m1 x1; y2 - m2 x2] (Eq. 5-7). The slopes are used in the
    homogeneous form (a bisector direction a_k = (-v_{k+1} + v_k, u_{k+1} - u_k) of Eq. 5-9)
    so a vertical bisector needs no special case. NaN where the bisectors are parallel."""
    a1 = np.stack([p1[:, 1] - p2[:, 1], p2[:, 0] - p1[:, 0]], -1)   # Eq. 5-9 a1
    a2 = np.stack([p2[:, 1] - p3[:, 1], p3[:, 0] - p2[:, 0]], -1)   # Eq. 5-9 a2
    m1 = 0.5 * (p1 + p2)                                             # (x1, y1) of Eq. 5-8
    m2 = 0.5 * (p2 + p3)                                             # (x2, y2)
    # m1 + s a1 = m2 + t a2  (Eq. 5-7 with m_k = a_k,y / a_k,x)
    det = a1[:, 0] * (-a2[:, 1]) - a1[:, 1] * (-a2[:, 0])
    d = m2 - m1
    with np.errstate(divide='ignore', invalid='ignore'):
        s = (d[:, 0] * (-a2[:, 1]) - d[:, 1] * (-a2[:, 0])) / det
        c = m1 + s[:, None] * a1
        c[det == 0] = np.nan
        r = (np.linalg.norm(c - p1, axis=1) + np.linalg.norm(c - p2, axis=1)
             + np.linalg.norm(c - p3, axis=1)) / 3.0                 # Eq. 5-9
        cos_t = np.sum(a1 * a2, 1) / (np.linalg.norm(a1, axis=1) * np.linalg.norm(a2, axis=1))
        theta = np.arccos(np.clip(cos_t, -1.0, 1.0))                 # Eq. 5-9
    return c, r, theta


class ThesisDetector:
    """The §5.3 pipeline.

    Step 1, reduction to black-and-white edge points: cv2.equalizeHist; threshold at
    `marker_level` (the expected equalised level of marker pixels); the Eq. 5-6 Laplacian of the
    binary image; a 3x3 constant low pass; a threshold at the filtered image's histogram peak
    minus 5 (the filtered image is stored as 128 + value, saturated to 8 bits: the peak is the
    flat level, the points below it by more than 5 are the rim's marker side).
    Step 2, the Tracking Hough Transform: three feature points per circle, the first at random,
    the second within D of it, the third within D of both with the bisector angle theta of
    Eq. 5-9 > d_theta (pi / 6); circle by Eq. 5-7..5-9; used points leave the list; repeated
    until every point has been processed. All points are drawn in parallel rounds (one random
    triple per unused point, conflicting triples resolved in random order), which is the same
    procedure without a Python loop per point. Circles of radius <= D / 2 vote in a centre /
    radius accumulator; a peak is a marker when the feature points on its circumference
    (within 1.5 px) cover > 35 % of it (in 5 degree sectors). Step 3: region growing (flood fill
    of the step-1 threshold image) from the centre; the centre is the grown region's centroid.

    D is the projected marker diameter, here the largest expected (2 * radius_px[1])."""

    def __init__(self, *, radius_px: tuple[float, float] = (4.0, 80.0),
                 polarity: Polarity | str = Polarity.BRIGHT, marker_level: int = 245,
                 d_theta: float = math.pi / 6, min_circumference: float = 0.35,
                 rounds: int = 6, seed: int = 0) -> None:
        self.r_min, self.r_max = _radius_range(radius_px)
        self.polarity = _polarity(polarity)
        if not (1 <= int(marker_level) <= 254):
            raise InsertionError(f'marker_level must be in [1, 254], got {marker_level}')
        if not (0.0 < d_theta < math.pi / 2):
            raise InsertionError(f'd_theta must be in (0, pi/2), got {d_theta}')
        if not (0.0 < min_circumference < 1.0):
            raise InsertionError(f'min_circumference must be in (0, 1), got {min_circumference}')
        if not (1 <= int(rounds) <= 50):
            raise InsertionError(f'rounds must be in [1, 50], got {rounds}')
        self.marker_level = int(marker_level)
        self.d_theta = float(d_theta)
        self.min_circumference = float(min_circumference)
        self.rounds = int(rounds)
        self.seed = int(seed)

    def reduce(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Step 1: (binary marker image of the first threshold, feature-point mask)."""
        eq = cv2.equalizeHist(image)
        if self.polarity is Polarity.DARK:
            eq = 255 - eq
        binary = np.where(eq >= self.marker_level, np.uint8(255), np.uint8(0))
        lap = cv2.filter2D(binary.astype(np.float32), -1, LAPLACIAN_5_6,
                           borderType=cv2.BORDER_REPLICATE)                 # Eq. 5-6
        low = cv2.blur(lap, (3, 3))                                          # 3x3 low pass
        img8 = np.clip(np.rint(128.0 + low), 0, 255).astype(np.uint8)
        hist = np.bincount(img8.ravel(), minlength=256)
        peak = int(np.argmax(hist))
        return binary, img8 < peak - 5

    def detect(self, image: np.ndarray) -> list[Marker]:
        image = check_image(image)
        binary, feat = self.reduce(image)
        vs, us = np.nonzero(feat)
        pts = np.stack([us, vs], -1).astype(np.float64)
        if len(pts) < 3:
            return []
        D = 2.0 * self.r_max
        circles = self._tracking_hough(pts, D)
        return self._grow(binary, pts, circles)

    def _tracking_hough(self, pts: np.ndarray, D: float) -> list[tuple[float, float, float]]:
        rng = np.random.default_rng(self.seed)
        n = len(pts)
        unused = np.ones(n, bool)
        found_c, found_r = [], []
        tries = 32
        for _ in range(self.rounds):
            first = np.flatnonzero(unused)
            if len(first) < 3:
                break
            first = rng.permutation(first)
            m = len(first)
            p1 = pts[first]
            # second: uniform among the points within D of the first (drawn from all points,
            # the first that falls within D); third: within D of both
            cand2 = rng.integers(0, n, (m, tries))
            ok2 = ((np.linalg.norm(pts[cand2] - p1[:, None], axis=2) < D)
                   & (cand2 != first[:, None]))
            has2 = ok2.any(1)
            second = cand2[np.arange(m), np.argmax(ok2, 1)]
            p2 = pts[second]
            cand3 = rng.integers(0, n, (m, tries))
            p3 = pts[cand3]
            ok3 = ((np.linalg.norm(p3 - p1[:, None], axis=2) < D)
                   & (np.linalg.norm(p3 - p2[:, None], axis=2) < D)
                   & (cand3 != first[:, None]) & (cand3 != second[:, None]) & has2[:, None])
            c, r, th = three_point_circles(np.repeat(p1, tries, 0), np.repeat(p2, tries, 0),
                                           p3.reshape(-1, 2))
            ok3 &= th.reshape(-1, tries) > self.d_theta                    # d-theta rule
            has = ok3.any(1)
            pick = np.argmax(ok3, 1)
            rows = np.flatnonzero(has)
            t3 = cand3[rows, pick[rows]]
            cc = c.reshape(-1, tries, 2)[rows, pick[rows]]
            rr = r.reshape(-1, tries)[rows, pick[rows]]
            tri = np.stack([first[rows], second[rows], t3], 1)
            # used points leave the list: in random order, a triple keeps its points only when
            # no earlier triple took one of them
            k = np.arange(len(tri))
            first_use = np.full(n, len(tri))
            np.minimum.at(first_use, tri.ravel(), np.repeat(k, 3))
            keep = np.all(first_use[tri] == k[:, None], 1)
            unused[tri[keep].ravel()] = False
            unused[first[~has]] = False       # no valid partners: processed, no circle
            good = keep & (rr >= self.r_min) & (rr <= D / 2)
            found_c.append(cc[good])
            found_r.append(rr[good])
        if not found_c:
            return []
        C = np.concatenate(found_c)
        R = np.concatenate(found_r)
        if len(C) == 0:
            return []
        # tracking: the accumulator of (centre, radius) votes, 2 px centre cells
        cell = 2.0
        iu = np.floor(C[:, 0] / cell).astype(np.int64)
        iv = np.floor(C[:, 1] / cell).astype(np.int64)
        ok = (iu >= 0) & (iv >= 0) & (iu < 100000) & (iv < 100000)
        iu, iv, C, R = iu[ok], iv[ok], C[ok], R[ok]
        key = iu * 100000 + iv
        uk, inv, cnt = np.unique(key, return_inverse=True, return_counts=True)
        out: list[tuple[float, float, float]] = []
        taken = np.zeros(len(uk), bool)
        for idx in np.argsort(-cnt):
            if cnt[idx] < 3 or taken[idx]:
                continue
            centre_guess = np.array([(uk[idx] // 100000 + 0.5) * cell,
                                     (uk[idx] % 100000 + 0.5) * cell])
            near = np.linalg.norm(C - centre_guess, axis=1) < 2 * cell
            members = near
            cu, cv_ = np.median(C[members], 0)
            rad = float(np.median(R[members]))
            if any(math.hypot(cu - x, cv_ - y) < max(r, rad) / 2 for x, y, r in out):
                continue
            taken[np.unique(inv[near])] = True
            # > 35 % of the circumference in feature points (5 degree sectors)
            d = pts - (cu, cv_)
            dist = np.hypot(d[:, 0], d[:, 1])
            on = np.abs(dist - rad) < 1.5
            sectors = np.unique((np.degrees(np.arctan2(d[on, 1], d[on, 0])) // 5).astype(int))
            if len(sectors) / 72.0 > self.min_circumference:
                out.append((float(cu), float(cv_), rad))
        return out

    def _grow(self, binary: np.ndarray, pts: np.ndarray,
              circles: list[tuple[float, float, float]]) -> list[Marker]:
        h, w = binary.shape
        out: list[Marker] = []
        for cu, cv_, rad in circles:
            seed = (round(cu), round(cv_))
            if not (0 <= seed[0] < w and 0 <= seed[1] < h):
                continue
            if binary[seed[1], seed[0]] == 0:
                continue
            mask = np.zeros((h + 2, w + 2), np.uint8)
            area, _, _, rect = cv2.floodFill(binary, mask, seed, 128,
                                             flags=4 | cv2.FLOODFILL_MASK_ONLY | (1 << 8))
            if not (0.5 * math.pi * rad * rad <= area <= 1.6 * math.pi * rad * rad):
                continue                        # leaked into the background, or a speck
            x0, y0, rw, rh = rect
            sub = mask[y0 + 1:y0 + 1 + rh, x0 + 1:x0 + 1 + rw]
            m = cv2.moments(sub, binaryImage=True)
            u = x0 + m['m10'] / m['m00']
            v = y0 + m['m01'] / m['m00']
            if any(abs(u - o.u) < 0.5 and abs(v - o.v) < 0.5 for o in out):
                continue                        # the same region grown from another circle
            out.append(Marker(u=float(u), v=float(v), radius_px=math.sqrt(area / math.pi),
                              score=1.0))
        return out


# ------------------------------------------------------------------ the default: sub-pixel ellipse

#: the default detector's settings, the ones its benchmark and its limit study on the
#: simulator's renders (detector_limits) measured
DEFAULT_RADIUS_PX = (2.5, 80.0)
DEFAULT_MIN_CONTRAST = 40.0
DEFAULT_MIN_COVERAGE = 0.6
DEFAULT_MAX_RESIDUAL_PX = 0.5


class EllipseDetector:
    """Sub-pixel ellipse fit with the perspective correction (the default detector).

    1. Candidates (`candidates`): on the image halved (radii up to 12 px) and quartered, the
       level minus its local mean thresholded at `min_contrast` / 2 and 2 `min_contrast`,
       connected components of a marker's size, an isolation test for all at once (brighter
       by `min_contrast` than all but one of 16 samples on a ring round it), then a
       full-resolution threshold half-way between the blob and its ring, whose region must be
       a filled ellipse (its second moments give the coarse ellipse).
    2. Edge points: in a window round each candidate at full resolution, the level
       L(u, v) = (inner(u, v) + outer(u, v)) / 2 from planes fitted to the pixels well inside and
       well outside the coarse ellipse (uneven lighting), then every crossing of L from bright
       to dark outwards between horizontal and between vertical neighbours (linear
       interpolation) within 2.5 px of the coarse ellipse (0.45 radii for small markers), the
       scan direction within 45 degrees of the ellipse normal. The contrast, less the 90th
       percentile of the surround's residual from its plane (bright texture), must reach
       `min_contrast`.
    3. cv2.fitEllipseDirect, twice trimmed to points within 3 sigma (occluder edges go); the
       marker is kept when at least `min_coverage` of the rim (in sectors about 2 px long,
       12 to 72) carries edge points, the RMS
       residual is below `max_residual_px` and the contrast above `min_contrast`.
    4. With `K`, the perspective candidates of `circle_candidates`, resolved by `normal_hint`
       or coplanar markers (`resolve_coplanar`); unresolved markers keep the ellipse centre.
    """

    def __init__(self, *, radius_px: tuple[float, float] = DEFAULT_RADIUS_PX,
                 polarity: Polarity | str = Polarity.BRIGHT, K: np.ndarray | None = None,
                 normal_hint: np.ndarray | None = None,
                 min_contrast: float = DEFAULT_MIN_CONTRAST,
                 min_coverage: float = DEFAULT_MIN_COVERAGE,
                 max_residual_px: float = DEFAULT_MAX_RESIDUAL_PX,
                 max_axis_ratio: float = 3.0,
                 ambiguity: Ambiguity | str = Ambiguity.COPLANAR) -> None:
        self.r_min, self.r_max = _radius_range(radius_px)
        self.polarity = _polarity(polarity)
        self.K = _intrinsics(K)
        if normal_hint is not None:
            h = np.asarray(normal_hint, float).reshape(-1)
            if h.shape != (3,) or not np.all(np.isfinite(h)) or np.linalg.norm(h) == 0:
                raise InsertionError(f'normal_hint must be a finite non-zero 3-vector, '
                                     f'got {normal_hint!r}')
            normal_hint = h / np.linalg.norm(h)
        self.normal_hint = normal_hint
        if not (0 < min_contrast < 255):
            raise InsertionError(f'min_contrast must be in (0, 255), got {min_contrast}')
        if not (0 < min_coverage <= 1):
            raise InsertionError(f'min_coverage must be in (0, 1], got {min_coverage}')
        if not (max_residual_px > 0):
            raise InsertionError(f'max_residual_px must be > 0, got {max_residual_px}')
        if not (max_axis_ratio >= 1):
            raise InsertionError(f'max_axis_ratio must be >= 1, got {max_axis_ratio}')
        ambiguity = choice(Ambiguity, ambiguity, 'ambiguity', error=InsertionError)
        self.min_contrast = float(min_contrast)
        self.min_coverage = float(min_coverage)
        self.max_residual_px = float(max_residual_px)
        self.max_axis_ratio = float(max_axis_ratio)
        self.ambiguity = ambiguity

    # -- stage 1
    def candidates(self, image: np.ndarray) -> list[tuple[float, float, float, float, float]]:
        """Coarse ellipses (cx, cy, a, b, angle) in full-resolution pixels.

        Per pyramid level (`_LEVELS`: the image halved for radii up to 12 px, quartered
        above), the level minus its local mean over about three of the level's largest
        radii, thresholded at `min_contrast` / 2 and at 2 `min_contrast` (a disc that touches
        bright texture at the low level stands alone at the high one), connected components
        of a disc's area, bounding box and fill. Then, for all at once, the isolation test:
        the median of 7 full-resolution samples inside the blob minus the second brightest of
        16 on a ring at 1.8 radii + 1.5 px must reach `min_contrast` (a speck of texture is not
        brighter than the rest of its surround's texture; a marker is).
        Survivors closer than half a radius to a larger one go; each of the rest is thresholded
        again at full resolution, half-way between its inside and its ring, and its ellipse is
        the second moments of the region at its centre, kept when the region is a filled
        ellipse (area / (4 pi sqrt(det second moments)) in [0.8, 1.2])."""
        img = image if self.polarity is Polarity.BRIGHT else 255 - image
        rows = []
        level, cur = img, 1
        for s, level_lo, level_hi in _LEVELS:
            lo, hi = max(level_lo, self.r_min), min(level_hi, self.r_max)
            if lo > hi:
                continue
            while cur < s:
                level = cv2.resize(level, (level.shape[1] // 2, level.shape[0] // 2),
                                   interpolation=cv2.INTER_AREA)
                cur *= 2
            win = 2 * math.ceil(1.5 * hi / s) + 1
            diff = cv2.subtract(level, cv2.blur(level, (win, win)))
            a_min = math.pi * (lo / s) ** 2 * 0.3
            a_max = math.pi * (hi / s) ** 2 * 1.3
            for off in (0.5, 2.0):
                _, bw = cv2.threshold(diff, off * self.min_contrast, 1, cv2.THRESH_BINARY)
                _, _, st, cen = cv2.connectedComponentsWithStats(bw, connectivity=8,
                                                                 ltype=cv2.CV_32S)
                area, w, h = st[:, 4], st[:, 2], st[:, 3]
                ok = (area >= a_min) & (area <= a_max) & (area > 0.4 * w * h) \
                    & (np.maximum(w, h) <= self.max_axis_ratio * np.minimum(w, h) + 2)
                ok[0] = False
                idx = np.flatnonzero(ok)
                if not len(idx):
                    continue
                r = s * np.sqrt(area[idx] / math.pi)
                rows.append(np.stack([s * (cen[idx, 0] + 0.5) - 0.5,
                                      s * (cen[idx, 1] + 0.5) - 0.5, r], -1))
        if not rows:
            return []
        c = np.concatenate(rows)
        inner, ring = _isolation(img, c)
        keep = np.flatnonzero(inner - ring >= self.min_contrast)
        out: list[tuple[float, float, float, float, float]] = []
        taken: list[tuple[float, float, float]] = []
        for k in keep[np.argsort(-c[keep, 2], kind='stable')]:
            cx, cy, r = c[k, :3]
            if any(math.hypot(cx - u, cy - v) < 0.5 * max(r, q) for u, v, q in taken):
                continue
            ell = _blob_ellipse(img, cx, cy, r, 0.5 * (inner[k] + ring[k]))
            if ell is None:
                continue
            taken.append((cx, cy, r))
            if max(ell[2], ell[3]) <= self.max_axis_ratio * min(ell[2], ell[3]):
                out.append(ell)
        return out

    # -- stages 2-3
    def _refine(self, image: np.ndarray, coarse: Sequence[float]) -> Marker | None:
        # (coarse a, b: full axes of the half-size image = semi-axes at full resolution)
        img = image if self.polarity is Polarity.BRIGHT else 255 - image
        ell = coarse
        for _ in range(2):
            edge = self._edge_points(img, ell)
            if edge is None:
                return None
            pts, contrast = edge
            keep = np.ones(len(pts), bool)
            for _ in range(2):
                if keep.sum() < 10:
                    return None
                (ex, ey), (ew, eh), eang = cv2.fitEllipseDirect(pts[keep].astype(np.float32))
                if not (ew > 0 and eh > 0):
                    return None
                ell = (ex, ey, ew / 2, eh / 2, math.radians(eang))
                res = _ellipse_residual(pts, ell)
                s = max(1.4826 * float(np.mean(np.abs(res[keep]))) * 1.2533 / 1.4826, 0.05)
                keep = np.abs(res) < 3 * s
        res = res[keep]
        rms = float(np.sqrt(np.mean(res ** 2)))
        if rms > self.max_residual_px:
            return None
        mr = math.sqrt(ell[2] * ell[3])
        if not (self.r_min <= mr <= self.r_max) \
                or max(ell[2], ell[3]) > self.max_axis_ratio * min(ell[2], ell[3]):
            return None
        # rim coverage in 5 degree sectors of the ellipse's parametric angle
        d = pts[keep] - ell[:2]
        ca, sa = math.cos(ell[4]), math.sin(ell[4])
        phi = np.arctan2((-sa * d[:, 0] + ca * d[:, 1]) / ell[3],
                         (ca * d[:, 0] + sa * d[:, 1]) / ell[2])
        ns = int(np.clip(round(math.pi * mr), 12, 72))     # sectors about 2 px of rim long
        sectors = np.zeros(ns, bool)
        sectors[((phi + math.pi) * (ns / (2 * math.pi))).astype(np.intp) % ns] = True
        coverage = float(sectors.mean())
        if coverage < self.min_coverage:
            return None
        n = int(keep.sum())
        sigma = rms * math.sqrt(2.0 / n)
        score = float(coverage * min(contrast / 100.0, 1.0) / (1.0 + rms))
        return Marker(u=float(ell[0]), v=float(ell[1]), radius_px=mr, score=score,
                      ellipse=(float(ell[0]), float(ell[1]), float(ell[2]), float(ell[3]),
                               float(ell[4])), sigma_px=sigma)

    def _edge_points(self, img: np.ndarray, ell: Sequence[float]
                     ) -> tuple[np.ndarray, float] | None:
        """Sub-pixel crossings of the local mid level near the ellipse `ell`, and the contrast."""
        cx, cy, a, b, ang = ell
        pad = 6
        rmax = max(a, b)
        x0 = max(int(cx - rmax - pad), 0)
        y0 = max(int(cy - rmax - pad), 0)
        x1 = min(int(cx + rmax + pad) + 1, img.shape[1])
        y1 = min(int(cy + rmax + pad) + 1, img.shape[0])
        if x1 - x0 < 8 or y1 - y0 < 8:
            return None
        roi = img[y0:y1, x0:x1].astype(np.float32)
        qx = (np.arange(x0, x1, dtype=np.float32) - np.float32(cx))[None, :]
        qy = (np.arange(y0, y1, dtype=np.float32) - np.float32(cy))[:, None]
        c, s = math.cos(ang), math.sin(ang)
        ia, ib = 1.0 / (a * a), 1.0 / (b * b)
        A = np.float32(c * c * ia + s * s * ib)
        B = np.float32(c * s * (ia - ib))
        C = np.float32(s * s * ia + c * c * ib)
        nx = A * qx + B * qy                  # half the gradient of the conic
        ny = B * qx + C * qy
        q = qx * nx + qy * ny
        rho = (np.sqrt(q) - 1.0) * np.float32(math.sqrt(a * b))   # ~ signed distance (px)
        e = np.float32(min(2.5, max(1.2, 0.45 * math.sqrt(a * b))))  # small discs: narrower
        inner = rho < -e
        outer = (rho > e) & (rho < e + 3.5)
        n_in, n_out = np.count_nonzero(inner), np.count_nonzero(outer)
        if n_in < 4 or n_out < 12:
            return None
        lvl_in, m_in, _ = _plane_fit(inner, roi, qx, qy)
        lvl_out, m_out, rough = _plane_fit(outer, roi, qx, qy)
        contrast = m_in - m_out
        if contrast - rough < self.min_contrast:
            return None
        g = roi - 0.5 * (lvl_in + lvl_out)
        band = np.abs(rho) < e
        horiz = np.abs(nx) >= np.abs(ny)
        # a crossing from the bright inside to the dark outside along the rim's normal only
        # (texture crossing the level the other way goes)
        sg = g > 0
        out_x = nx[:, :-1] > 0
        out_y = ny[:-1, :] > 0
        hx = band[:, :-1] & band[:, 1:] & horiz[:, :-1] & (sg[:, :-1] != sg[:, 1:]) \
            & (sg[:, :-1] == out_x)
        vy = band[:-1, :] & band[1:, :] & ~horiz[:-1, :] & (sg[:-1, :] != sg[1:, :]) \
            & (sg[:-1, :] == out_y)
        r, cc = np.nonzero(hx)
        g0 = g[r, cc]
        t = g0 / (g0 - g[r, cc + 1])
        ph = np.stack([x0 + cc + t, y0 + r.astype(np.float32)], -1)
        r, cc = np.nonzero(vy)
        g0 = g[r, cc]
        t = g0 / (g0 - g[r + 1, cc])
        pv = np.stack([x0 + cc.astype(np.float32), y0 + r + t], -1)
        pts = np.concatenate([ph, pv]).astype(np.float64)
        if len(pts) < 10:
            return None
        return pts, contrast

    def detect(self, image: np.ndarray) -> list[Marker]:
        image = check_image(image)
        found: list[Marker] = []
        for coarse in self.candidates(image):
            m = self._refine(image, coarse)
            if m is None:
                continue
            if any(math.hypot(m.u - o.u, m.v - o.v) < 0.5 * min(m.radius_px, o.radius_px)
                   for o in found):
                continue
            found.append(m)
        if self.K is None:
            return found
        corrected = []
        for m in found:
            assert m.ellipse is not None                # _refine fits one to every marker
            try:
                normals, centres = circle_candidates(ellipse_conic(*m.ellipse), self.K)
            except (InsertionError, np.linalg.LinAlgError):
                corrected.append(m)
                continue
            corrected.append(replace(m, candidates=centres, normals=normals))
        if self.normal_hint is None and self.ambiguity is Ambiguity.NONE:
            return corrected
        return resolve_coplanar(corrected, normal_hint=self.normal_hint)


#: pyramid levels of the candidate stage: (scale, smallest, largest radius in full-res px)
_LEVELS = ((2, 2.0, 12.0), (4, 10.0, 500.0))
_RING = np.linspace(0.0, 2 * math.pi, 16, endpoint=False)[None, :]
_INNER = np.concatenate([[0.0], np.linspace(0.0, 2 * math.pi, 6, endpoint=False)])[None, :]


def _isolation(img: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per blob (rows of c: cx, cy, r in full-res px): the median of the image at the centre
    and 6 points at 0.35 r, minus the second brightest of 16 points on the circle 1.8 r + 1.5
    (one bright point, a vein or a speck, is let through)."""
    h, w = img.shape

    def sample(rad: np.ndarray, phi: np.ndarray) -> np.ndarray:
        u = np.rint(c[:, :1] + rad * np.cos(phi)).astype(np.intp).clip(0, w - 1)
        v = np.rint(c[:, 1:2] + rad * np.sin(phi)).astype(np.intp).clip(0, h - 1)
        return img[v, u].astype(np.float32)

    r = c[:, 2:3]
    inner = sample(np.where(np.arange(7)[None, :] == 0, 0.0, 0.35 * r), _INNER)
    ring = sample(1.8 * r + 1.5, _RING)
    return np.median(inner, axis=1), np.partition(ring, 14, axis=1)[:, 14]


def _blob_ellipse(img: np.ndarray, cx: float, cy: float, r: float, level: float
                  ) -> tuple[float, float, float, float, float] | None:
    """The ellipse (cx, cy, a, b, angle) of the region above `level` at (cx, cy) in a window
    of 1.8 r + 3 px round it, from its second moments; None when that region is not a filled
    ellipse or touches the window's edge."""
    h, w = img.shape
    m = 1.8 * r + 3
    x0, y0 = max(int(cx - m), 0), max(int(cy - m), 0)
    x1, y1 = min(int(cx + m) + 2, w), min(int(cy + m) + 2, h)
    _, bw = cv2.threshold(img[y0:y1, x0:x1], level, 1, cv2.THRESH_BINARY)
    n, lab, st, cen = cv2.connectedComponentsWithStats(bw, connectivity=8, ltype=cv2.CV_32S)
    if n < 2:
        return None
    d = np.hypot(cen[1:, 0] + x0 - cx, cen[1:, 1] + y0 - cy)
    i = 1 + int(np.argmin(d))
    bx, by, bw_, bh, area = st[i]
    if d[i - 1] > 0.5 * r + 1 or area < 5 or bx == 0 or by == 0 or bx + bw_ == x1 - x0 \
            or by + bh == y1 - y0:
        return None
    mo = cv2.moments((lab[by:by + bh, bx:bx + bw_] == i).view(np.uint8), binaryImage=True)
    mu20 = mo['mu20'] / mo['m00'] + 1 / 12
    mu02 = mo['mu02'] / mo['m00'] + 1 / 12
    mu11 = mo['mu11'] / mo['m00']
    det = mu20 * mu02 - mu11 ** 2
    if det <= 0 or not (0.8 <= mo['m00'] / (4 * math.pi * math.sqrt(det)) <= 1.2):
        return None
    dd = math.sqrt((mu20 - mu02) ** 2 / 4 + mu11 ** 2)
    a = 2 * math.sqrt((mu20 + mu02) / 2 + dd)
    b = 2 * math.sqrt(max((mu20 + mu02) / 2 - dd, 1e-6))
    return (x0 + bx + mo['m10'] / mo['m00'], y0 + by + mo['m01'] / mo['m00'], a, b,
            0.5 * math.atan2(2 * mu11, mu20 - mu02))


def _plane_fit(mask: np.ndarray, z: np.ndarray, qx: np.ndarray, qy: np.ndarray,
               max_samples: int = 256) -> tuple[np.ndarray, float, float]:
    """Least-squares plane z = p0 + p1 qx + p2 qy through (at most `max_samples`, evenly
    strided) pixels of `mask`, evaluated on the whole window (qx a row, qy a column of offsets),
    the samples' mean and the 90th percentile of their residuals from the plane (how far the
    surround's bright texture stands above it)."""
    r, c = np.nonzero(mask)
    step = max(1, len(r) // max_samples)
    r, c = r[::step], c[::step]
    x, y, v = qx[0, c].astype(np.float64), qy[r, 0].astype(np.float64), z[r, c]
    A = np.stack([np.ones_like(x), x, y], -1)
    try:
        p = np.linalg.solve(A.T @ A, A.T @ v)
    except np.linalg.LinAlgError:
        p = np.array([float(v.mean()), 0.0, 0.0])
    rough = float(np.percentile(v - A @ p, 90))
    return (np.float32(p[0]) + np.float32(p[1]) * qx + np.float32(p[2]) * qy, float(v.mean()),
            rough)


def _ellipse_residual(pts: np.ndarray, ell: Sequence[float]) -> np.ndarray:
    """Approximate signed geometric distance (px) of points from the ellipse (Sampson)."""
    cx, cy, a, b, ang = ell
    ca, sa = math.cos(ang), math.sin(ang)
    dx, dy = pts[:, 0] - cx, pts[:, 1] - cy
    x = ca * dx + sa * dy
    y = -sa * dx + ca * dy
    f = x * x / (a * a) + y * y / (b * b) - 1.0
    gx, gy = 2 * x / (a * a), 2 * y / (b * b)
    return f / np.maximum(np.hypot(gx, gy), 1e-12)


# ------------------------------------------------------------------ baseline

class HoughDetector:
    """cv2.HoughCircles (HOUGH_GRADIENT) after a 5x5 Gaussian: OpenCV's stock circle finder."""

    def __init__(self, *, radius_px: tuple[float, float] = (4.0, 80.0),
                 canny_high: float = 100.0, accumulator: float = 20.0) -> None:
        self.r_min, self.r_max = _radius_range(radius_px)
        if not (canny_high > 0 and accumulator > 0):
            raise InsertionError('canny_high and accumulator must be > 0')
        self.canny_high = float(canny_high)
        self.accumulator = float(accumulator)

    def detect(self, image: np.ndarray) -> list[Marker]:
        image = check_image(image)
        blur = cv2.GaussianBlur(image, (5, 5), 1.0)
        c = cv2.HoughCircles(blur, cv2.HOUGH_GRADIENT, dp=1, minDist=self.r_min * 2,
                             param1=self.canny_high, param2=self.accumulator,
                             minRadius=int(self.r_min), maxRadius=math.ceil(self.r_max))
        if c is None:
            return []
        return [Marker(u=float(x), v=float(y), radius_px=float(r), score=1.0)
                for x, y, r in c.reshape(-1, c.shape[-1])[:, :3]]


class DetectorKind(StrEnum):
    """The detectors `make_detector` builds by name (the master node's `detector` parameter)."""

    DEFAULT = 'default'
    THESIS = 'thesis'
    HOUGH = 'hough'


DETECTORS = tuple(DetectorKind)


def make_detector(kind: DetectorKind | str = DetectorKind.DEFAULT, **options: Any
                  ) -> MarkerDetector:
    """The detector by name, with its keyword options; InsertionError naming the detectors for
    an unknown name."""
    kind = choice(DetectorKind, kind, 'detector', error=InsertionError)
    match kind:
        case DetectorKind.DEFAULT:
            return EllipseDetector(**options)
        case DetectorKind.THESIS:
            return ThesisDetector(**options)
        case DetectorKind.HOUGH:
            return HoughDetector(**options)
        case _:
            assert_never(kind)
