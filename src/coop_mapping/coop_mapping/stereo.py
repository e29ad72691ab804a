"""Stereo ranging with the thesis's error model (Sujan 2002, §3.2.3, Eq. 3-1..3-9).

Rectified mono8 pair -> OpenCV StereoSGBM disparity -> 3-D points in the left optical frame
(z forward, x right, y down) -> per-point covariance from Eq. 3-7 -> common (map) frame with
Eq. 3-9. No rclpy here.
"""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from enum import StrEnum
from typing import assert_never

import cv2
import numpy as np

from coop_common.params import choice

from .errors import MappingError
from .gauss import rotate_sym6

__all__ = [
    'FULL_WIDTH_DEFAULT',
    'SUBPIXEL_DEFAULT',
    'SUBPIXEL_MODES',
    'ErrorModel',
    'StereoCamera',
    'StereoError',
    'StereoRanger',
    'StereoScan',
    'Subpixel',
    'compute_disparity',
    'disparity_to_points',
    'disparity_to_range',
    'equalize_subpixel',
    'phase_averaged_disparity',
    'range_sigma',
    'shift_columns',
]


class Subpixel(StrEnum):
    """The sub-pixel disparity estimate (compute_disparity): SGBM's own, after equalising, or
    the mean over 2 or 4 sub-pixel shifts of the right image."""

    SGBM = 'sgbm'
    EQUALISE = 'equalise'
    SHIFT2 = 'shift2'
    SHIFT4 = 'shift4'


SUBPIXEL_MODES = tuple(Subpixel)
SUBPIXEL_DEFAULT = Subpixel.SHIFT4
FULL_WIDTH_DEFAULT = True
#: the sub-pixel shifts each phase-averaged mode runs SGBM at
_PHASES = {Subpixel.SHIFT2: 2, Subpixel.SHIFT4: 4}


class StereoError(MappingError, ValueError):
    """Bad stereo input (shape, dtype, mismatched pair, bad calibration)."""


@dataclass(frozen=True)
class StereoCamera:
    """Rectified pinhole pair: identical intrinsics, right camera at +baseline along x."""

    fx: float
    fy: float
    cx: float
    cy: float
    baseline: float
    width: int
    height: int

    def __post_init__(self) -> None:
        if not (self.fx > 0 and self.fy > 0 and self.baseline > 0):
            raise StereoError('fx, fy and baseline must be > 0')
        if not (np.isfinite([self.fx, self.fy, self.cx, self.cy, self.baseline]).all()):
            raise StereoError('fx, fy, cx, cy and baseline must be finite')
        if not (self.width > 0 and self.height > 0):
            raise StereoError('image size must be > 0')

    @classmethod
    def from_fov(cls, width: int, height: int, hfov_rad: float, baseline: float) -> StereoCamera:
        f = width / 2.0 / np.tan(hfov_rad / 2.0)
        return cls(f, f, (width - 1) / 2.0, (height - 1) / 2.0, baseline, width, height)

    @classmethod
    def from_projection(cls, P_left: np.ndarray, P_right: np.ndarray, width: int, height: int
                        ) -> StereoCamera:
        """From the 3x4 projection matrices of a rectified pair (CameraInfo.p, ROS
        convention: P_right[0, 3] = -fx * baseline)."""
        Pl = np.asarray(P_left, float).reshape(3, 4)
        Pr = np.asarray(P_right, float).reshape(3, 4)
        fx = Pl[0, 0]
        if not fx > 0:
            raise StereoError('projection matrix with fx <= 0')
        return cls(fx, Pl[1, 1], Pl[0, 2], Pl[1, 2], -Pr[0, 3] / fx, width, height)


def disparity_to_range(d_px: np.ndarray, f_px: float, baseline: float) -> np.ndarray:
    """Eq. 3-1..3-3: Y = b / delta with delta = d / f, i.e. Y = f b / d."""
    d = np.asarray(d_px, float)
    with np.errstate(divide='ignore'):
        return np.where(d > 0, f_px * baseline / np.where(d > 0, d, 1.0), np.nan)


def range_sigma(range_m: np.ndarray, f_px: float, baseline: float, sigma_d_px: float
                ) -> np.ndarray:
    """Eq. 3-4..3-6: s_yy = J s_dd J^T with J = -b / delta^2, so sigma_Y = Y^2 sigma_delta / b
    with sigma_delta = sigma_d / f: the range sigma grows with range squared."""
    Y = np.asarray(range_m, float)
    return Y * Y * (sigma_d_px / f_px) / baseline


@dataclass(frozen=True)
class ErrorModel:
    """Eq. 3-7: sigma_{x,y,z} = S * T_{x,y,z} * L^n in the camera frame, uncorrelated (Eq. 3-8
    with rho = 0). The camera frame here is the optical frame, so z is the range axis."""

    S: float
    T: tuple[float, float, float] = (0.1, 0.1, 1.0)
    n: float = 2.0
    floor_m: float = 1e-4

    def __post_init__(self) -> None:
        if not (self.S > 0 and all(t > 0 for t in self.T) and self.n >= 0 and self.floor_m > 0):
            raise StereoError('S, T must be > 0, n >= 0, floor_m > 0')

    @classmethod
    def from_stereo(cls, camera: StereoCamera, *, sigma_d_px: float = 0.5,
                    lateral: float = 0.1, n: float = 2.0) -> ErrorModel:
        """S from Eq. 3-6 (sigma_Y = Y^2 sigma_d / (f b)); T = (lateral, lateral, 1)."""
        return cls(S=sigma_d_px / (camera.fx * camera.baseline), T=(lateral, lateral, 1.0), n=n)

    def sigmas(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) sigma_x, sigma_y, sigma_z of points given in the camera frame."""
        L = np.linalg.norm(np.asarray(points_cam, float), axis=1)
        return np.maximum(self.S * np.asarray(self.T)[None, :] * (L ** self.n)[:, None],
                          self.floor_m)

    def covariances(self, points_cam: np.ndarray, R_wc: np.ndarray | None = None) -> np.ndarray:
        """(N, 6) covariances xx, xy, xz, yy, yz, zz; in the common frame when R_wc (the
        camera's orientation in it) is given (Eq. 3-9)."""
        sg = self.sigmas(points_cam)
        c = np.zeros((len(sg), 6))
        c[:, [0, 3, 5]] = sg * sg
        return c if R_wc is None else rotate_sym6(c, R_wc)


def _check_pair(left: np.ndarray, right: np.ndarray) -> None:
    for img in (left, right):
        if not isinstance(img, np.ndarray) or img.ndim != 2 or img.dtype != np.uint8:
            raise StereoError('images must be 2-D uint8 (mono8) arrays')
    if left.shape != right.shape:
        raise StereoError(f'image sizes differ: {left.shape} vs {right.shape}')


def compute_disparity(left: np.ndarray, right: np.ndarray, *, num_disparities: int = 64,
                      block_size: int = 5, uniqueness: int = 10, speckle_window: int = 50,
                      speckle_range: int = 2, subpixel: Subpixel | str = SUBPIXEL_DEFAULT,
                      full_width: bool = FULL_WIDTH_DEFAULT) -> np.ndarray:
    """StereoSGBM (3-way) disparity in pixels (float32), NaN where invalid.

    `subpixel` (SUBPIXEL_MODES, default SUBPIXEL_DEFAULT) chooses the sub-pixel estimate:
    'sgbm', SGBM's own parabola interpolation, which pulls disparities towards whole pixels
    (pixel locking, measured by bench/stereo_subpixel.py); 'equalise', `equalize_subpixel` of
    it; 'shift2' / 'shift4', `phase_averaged_disparity` over 2 / 4 sub-pixel shifts of the
    right image (2 / 4 SGBM runs), which cancels the locking error instead of remapping it.

    SGBM leaves the left `num_disparities` columns invalid (no full search range there), a fifth
    of a 320-wide image at 64. `full_width` (default): both images are padded on the left by that
    many replicated columns, so those pixels are searched too, and a disparity is kept only where
    its match lies inside the right image (u - d >= 0) and agrees within 1 px with that right
    pixel's own disparity (SGBM on the mirrored pair: one more SGBM run). Without that check a
    pixel whose true match lies left of the right image takes a wrong match inside it (the
    unweighted Eq. 3-18 fit of fig_3_24 broke down on them at 0.35 m); bench/stereo_subpixel.py
    measures the recovered columns.

    A pixel whose whole block_size x block_size block is clipped white (255: rover_sim's empty
    background above the horizon, an over-exposed sky) gets no disparity: nothing in it can be
    matched, and SGBM's smoothness term fills such a region with the disparity of the textured
    edge it borders (a band of sky at a nearby rock's range: ghost surfaces near camera height
    that no later ray crosses)."""
    _check_pair(left, right)
    if num_disparities <= 0 or num_disparities % 16:
        raise StereoError('num_disparities must be a positive multiple of 16')
    if left.shape[1] <= num_disparities:
        # OpenCV's SGBM fails on such a pair with a misleading "Insufficient memory"
        raise StereoError(f'images {left.shape[1]} px wide: need more than num_disparities '
                          f'({num_disparities})')
    if block_size < 1 or block_size % 2 == 0:
        raise StereoError('block_size must be odd and >= 1')
    subpixel = choice(Subpixel, subpixel, 'subpixel', error=StereoError)
    sgbm = cv2.StereoSGBM.create(
        minDisparity=0, numDisparities=num_disparities, blockSize=block_size,
        P1=8 * block_size ** 2, P2=32 * block_size ** 2, disp12MaxDiff=1,
        uniquenessRatio=uniqueness, speckleWindowSize=speckle_window,
        speckleRange=speckle_range, mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)

    pad = num_disparities if full_width else 0
    left_p = cv2.copyMakeBorder(left, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    right_p = cv2.copyMakeBorder(right, 0, 0, pad, 0, cv2.BORDER_REPLICATE)
    u = np.arange(left.shape[1], dtype=np.float32)

    def run(r: np.ndarray) -> np.ndarray:
        d = sgbm.compute(left_p, r)[:, pad:].astype(np.float32) / 16.0
        with np.errstate(invalid='ignore'):
            d[(d <= 0) | (u - d < 0)] = np.nan    # no match, or a match in the padding
        return d

    match subpixel:
        case Subpixel.SHIFT2 | Subpixel.SHIFT4:
            # (a phase average of disparities each <= u is <= u too)
            d = phase_averaged_disparity(run, right_p, _PHASES[subpixel])
        case Subpixel.SGBM | Subpixel.EQUALISE:
            d = run(right_p)
        case _:
            assert_never(subpixel)
    if not full_width:          # the left num_disparities columns have no full search range
        d[:, :num_disparities] = np.nan
    else:
        # left-right check of the recovered columns against the right image's own disparity
        # (SGBM on the mirrored pair): a pixel whose true match lies left of the right image
        # takes a wrong one inside it, whose own match points elsewhere
        d_right = sgbm.compute(np.ascontiguousarray(right[:, ::-1]),
                               np.ascontiguousarray(left[:, ::-1]))[:, ::-1] / 16.0
        band = d[:, :num_disparities]
        rows, cols = np.nonzero(np.isfinite(band))
        x_r = np.clip(np.rint(cols - band[rows, cols]).astype(np.intp), 0, d.shape[1] - 1)
        back = d_right[rows, x_r]
        bad = ~((back > 0) & (np.abs(back - band[rows, cols]) <= 1.0))
        band[rows[bad], cols[bad]] = np.nan
    d[_clipped_blocks(left, block_size)] = np.nan
    return equalize_subpixel(d) if subpixel is Subpixel.EQUALISE else d


def _clipped_blocks(img: np.ndarray, block_size: int) -> np.ndarray:
    """(H, W) bool: the pixels whose block_size x block_size block is all 255 (clipped)."""
    clipped = (img == 255).astype(np.uint8)
    return cv2.erode(clipped, np.ones((block_size, block_size), np.uint8)).astype(bool)


def shift_columns(img: np.ndarray, s: float) -> np.ndarray:
    """The image resampled at column x + s (bilinear; edges replicated)."""
    h, w = img.shape
    mx = np.broadcast_to(np.arange(w, dtype=np.float32) + np.float32(s), (h, w))
    my = np.broadcast_to(np.arange(h, dtype=np.float32)[:, None], (h, w))
    return cv2.remap(img, np.ascontiguousarray(mx), np.ascontiguousarray(my),
                     cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def phase_averaged_disparity(match: Callable[[np.ndarray], np.ndarray],
                             right: np.ndarray, n_phases: int, max_spread_px: float = 1.0
                             ) -> np.ndarray:
    """Pixel-locking cancellation by sub-pixel shifts (Shimizu and Okutomi's half-pixel shift
    of the image, ICCV 2001, generalised to n phases).

    `match(right_image)` is the matcher's disparity (px, NaN invalid) against the left image.
    The right image resampled at x + k/n (k = 0..n-1) moves every true disparity by +k/n px and
    so the phase of the matcher's periodic sub-pixel error by k/n of its period: the mean of the
    n disparities, each less its shift, cancels the error's first n-1 harmonics (2 phases: the
    dominant one; bench/stereo_subpixel.py measures the rest). A pixel is kept only where all n
    are valid and agree within `max_spread_px` (a disagreement is a mismatch in one of them);
    the result is NaN or > 0."""
    if n_phases < 1:
        raise StereoError('n_phases must be >= 1')
    shifts = np.arange(n_phases) / n_phases
    D = np.stack([match(right if s == 0 else shift_columns(right, s)) - np.float32(s)
                  for s in shifts])
    with np.errstate(invalid='ignore'):
        ok = np.all(np.isfinite(D), 0) & (np.ptp(D, axis=0) < max_spread_px)
        mean = D.mean(0)
        ok &= mean > 0
    out = np.full(D.shape[1:], np.nan, np.float32)
    out[ok] = mean[ok]
    return out


def equalize_subpixel(disp: np.ndarray) -> np.ndarray:
    """Pixel-locking correction by histogram equalisation of the sub-pixel part.

    SGBM interpolates its matching cost with a parabola, which pulls every disparity towards
    the nearest integer ("pixel locking"; measured on the sim's frames by
    bench/stereo_subpixel.py: the mean error swings with the true fractional part by about
    +-0.2 px, the same sign over a whole surface, so no averaging of neighbours removes it).
    Over a frame the true offsets from the nearest integer are close to uniform on
    [-0.5, 0.5), so each valid disparity's offset is replaced by its rank among the frame's
    offsets (mid-rank, scaled into (-0.5, 0.5)): a monotone map, no model of the scene needed
    (the histogram-equalisation correction of particle image velocimetry). NaN stays NaN, and a
    disparity the map would make <= 0 (input below 0.5 px) becomes NaN, as compute_disparity's
    invalid ones: the result is NaN or > 0."""
    d = np.asarray(disp, np.float32)
    ok = np.isfinite(d)
    v = d[ok].astype(np.float64)
    if v.size < 2:
        return d.copy()
    i = np.round(v)
    f = v - i
    fs = np.sort(f)
    rank = 0.5 * (np.searchsorted(fs, f, side='left') + np.searchsorted(fs, f, side='right'))
    eq = i + rank / v.size - 0.5
    out = np.full(d.shape, np.nan, np.float32)
    out[ok] = np.where(eq > 0, eq, np.nan)
    return out


def disparity_to_points(disp: np.ndarray, camera: StereoCamera, *, stride: int = 1,
                        min_range: float = 0.0, max_range: float = np.inf
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Valid pixels -> (N, 3) points in the left optical frame and their (N, 2) u, v."""
    if disp.shape != (camera.height, camera.width):
        raise StereoError(f'disparity {disp.shape} does not match the camera '
                          f'{(camera.height, camera.width)}')
    d = disp[::stride, ::stride]
    v, u = np.mgrid[0:disp.shape[0]:stride, 0:disp.shape[1]:stride]
    z = camera.fx * camera.baseline / d
    ok = np.isfinite(z) & (z >= min_range) & (z <= max_range)
    z, u, v = z[ok], u[ok].astype(float), v[ok].astype(float)
    x = (u - camera.cx) * z / camera.fx
    y = (v - camera.cy) * z / camera.fy
    return np.stack([x, y, z], -1), np.stack([u, v], -1)


@dataclass
class StereoScan:
    """One processed stereo pair: points and covariances in the common frame."""

    points: np.ndarray       # (N, 3) map frame
    covariances: np.ndarray  # (N, 6) map frame
    origin: np.ndarray       # (3,) camera centre in the map frame
    points_cam: np.ndarray   # (N, 3) optical frame
    uv: np.ndarray           # (N, 2) pixels


class StereoRanger:
    """Rectified pair + camera pose -> StereoScan (Eq. 3-1..3-9)."""

    def __init__(self, camera: StereoCamera, *, error_model: ErrorModel | None = None,
                 num_disparities: int = 64, block_size: int = 5, stride: int = 1,
                 min_range: float = 0.2, max_range: float = 20.0,
                 subpixel: Subpixel | str = SUBPIXEL_DEFAULT,
                 full_width: bool = FULL_WIDTH_DEFAULT) -> None:
        """`subpixel`: the sub-pixel disparity estimate, a Subpixel or its string (StereoError
        naming them otherwise); `full_width`: also range the left num_disparities columns
        (both: see compute_disparity)."""
        self.subpixel = choice(Subpixel, subpixel, 'subpixel', error=StereoError)
        self.full_width = bool(full_width)
        self.camera = camera
        self.error_model = error_model or ErrorModel.from_stereo(camera)
        self.num_disparities = num_disparities
        self.block_size = block_size
        self.stride = stride
        self.min_range = min_range
        self.max_range = max_range

    def disparity(self, left: np.ndarray, right: np.ndarray) -> np.ndarray:
        """The pair's disparity (px, NaN invalid) with this ranger's settings."""
        return compute_disparity(left, right, num_disparities=self.num_disparities,
                                 block_size=self.block_size, subpixel=self.subpixel,
                                 full_width=self.full_width)

    def check_images(self, left: np.ndarray, right: np.ndarray) -> None:
        """StereoError unless both images have the camera's size."""
        size = (self.camera.height, self.camera.width)
        if left.shape != size or right.shape != size:
            raise StereoError(f'images {left.shape} / {right.shape} do not match camera_info '
                              f'{size}')

    def process(self, left: np.ndarray, right: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
                *, disparity: np.ndarray | None = None) -> StereoScan:
        """`disparity`: reuse one already computed for this pair (by `disparity`)."""
        R = np.asarray(R_wc, float)
        t = np.asarray(t_wc, float).reshape(3)
        if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6):
            raise StereoError('R_wc must be a rotation matrix')
        self.check_images(left, right)
        disp = disparity if disparity is not None else self.disparity(left, right)
        pc, uv = disparity_to_points(disp, self.camera, stride=self.stride,
                                     min_range=self.min_range, max_range=self.max_range)
        return StereoScan(points=pc @ R.T + t, covariances=self.error_model.covariances(pc, R),
                          origin=t.copy(), points_cam=pc, uv=uv)
