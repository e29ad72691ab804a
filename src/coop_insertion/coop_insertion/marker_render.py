"""Test images of circular markers with known centres (§5.2 card and site markers), no rclpy.

A flat plate (the card, the insertion site's face, or the slot's jaws with their 0.25 in
markers) with white circular markers, posed in front of a pinhole camera K, over a textured
background; rendered by ray casting each pixel centre onto
the plate, with the pixels near any edge (marker rims, plate border) integrated over their area
by `samples` x `samples` sub-samples (the area mean of coop_common.rendering.pixel_average, done
only where an edge crosses the pixel). Then uneven lighting (a linear gradient and vignetting),
a Gaussian blur (optics), an optional occluding bar in front of a marker, Gaussian noise and
8-bit quantisation. The true centre of a marker is the projection of its circle's centre
K (R c + t), not the centre of its imaged ellipse.

`background_scene` puts white discs (3-70 px radius) straight onto a tilted plane textured as
ground, rock, brushed metal, or the plate scenes' background under uneven light (a shadow edge
and a spot), for a detector tuned on the card's dark plate; with no discs it is a marker-free
image of the same background.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import assert_never

import cv2
import numpy as np

from coop_common.params import choice

from .errors import InsertionError

__all__ = [
    'BACKGROUNDS',
    'CARD',
    'SITE',
    'SLOT',
    'Background',
    'Plate',
    'Rendered',
    'background_scene',
    'background_texture',
    'random_pose',
    'random_scene',
    'render_discs',
    'render_plate',
    'sim_intrinsics',
]

INCH = 0.0254


@dataclass(frozen=True)
class Plate:
    """A rectangular plate (half sizes in m) with circular markers at `markers` (plate x, y in
    m, plate normal +z towards the camera side), all of radius `marker_radius_m`."""

    half_size_m: tuple[float, float]
    markers: tuple[tuple[float, float], ...]
    marker_radius_m: float
    plate_reflectance: float = 0.3
    marker_reflectance: float = 0.9


#: the 4.25 in card of rover_sim's worldgen.Card: markers of 0.25 in radius, 1.25 in off centre
CARD = Plate((2.125 * INCH, 1.375 * INCH), ((-1.25 * INCH, 0.0), (1.25 * INCH, 0.0)),
             0.25 * INCH)
#: the insertion site's face (rover_sim: 0.02 m markers either side of the slot, 0.06 m off)
SITE = Plate((0.1, 0.06), ((-0.062, 0.0), (0.062, 0.0)), 0.02)
#: the slot's jaws (rover_sim worldgen: 0.25 in markers 0.03 m either side of the 4.5 in slot,
#: on faces of grey 0.25-0.3): the markers the master watches during the insertion (ch. 5.3)
SLOT = Plate((0.16, 0.1), ((-0.0872, 0.0), (0.0872, 0.0)), 0.125 * INCH,
             plate_reflectance=0.27)

class Background(StrEnum):
    """The textures `background_texture` makes (`background_scene`'s backgrounds)."""

    GROUND = 'ground'
    ROCK = 'rock'
    METAL = 'metal'
    LIGHT = 'light'


BACKGROUNDS = tuple(Background)


def sim_intrinsics(width: int = 640, height: int = 480, hfov_deg: float = 41.2) -> np.ndarray:
    """K of rover_sim's cameras (principal point at the image centre) at this size."""
    f = (width / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0, 0, 1.0]])


@dataclass(frozen=True)
class Rendered:
    """A rendered image with the true marker centres, radii and plate normal."""

    image: np.ndarray          # mono8
    centres: np.ndarray        # (M, 2) true centre images (px), M = 0 for a marker-free image
    radius_px: np.ndarray      # (M,) approximate imaged radius (f r / depth)
    normal: np.ndarray         # (3,) plate normal in the camera frame (towards the camera)
    occluded: np.ndarray       # (M,) fraction of the rim hidden by the occluder (approx.)
    ellipse_centres: np.ndarray  # (M, 2) centres of the imaged ellipses (the biased point)


def _rot(axis: np.ndarray, ang: float) -> np.ndarray:
    a = np.asarray(axis, float)
    a = a / np.linalg.norm(a)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(ang) * k + (1 - math.cos(ang)) * k @ k


def _plate_coords(K_inv: np.ndarray, R: np.ndarray, t: np.ndarray, u: np.ndarray,
                  v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Plate (x, y) hit by the rays through image points (u, v)."""
    d = K_inv @ np.stack([u.ravel(), v.ravel(), np.ones(u.size)])
    n = R[:, 2]
    s = (n @ t) / (n @ d)
    X = d * s - t[:, None]
    p = R.T @ X
    return p[0].reshape(u.shape), p[1].reshape(u.shape)


def _reflectance(plate: Plate, x: np.ndarray, y: np.ndarray, bg: np.ndarray,
                 with_markers: bool) -> np.ndarray:
    on = (np.abs(x) <= plate.half_size_m[0]) & (np.abs(y) <= plate.half_size_m[1])
    out = np.where(on, plate.plate_reflectance, bg)
    if with_markers:
        for mx, my in plate.markers:
            inside = (x - mx) ** 2 + (y - my) ** 2 <= plate.marker_radius_m ** 2
            out = np.where(inside & on, plate.marker_reflectance, out)
    return out


def render_plate(K: np.ndarray, width: int, height: int, R: np.ndarray, t: np.ndarray,
                 plate: Plate, *, rng: np.random.Generator, with_markers: bool = True,
                 noise_sigma: float = 3.0, blur_sigma: float = 0.8, gradient: float = 0.4,
                 vignetting: float = 0.2, occlude: float = 0.0, samples: int = 9) -> Rendered:
    """One image of `plate` at pose (R, t) (plate frame -> camera optical frame).

    `gradient`: the lighting changes by this fraction across the image (random direction);
    `vignetting`: darkening at the corners; `occlude`: when > 0, a dark bar hides up to this
    fraction of the rim of one marker (the first); `samples`: sub-samples per axis on edge
    pixels (odd)."""
    K = np.asarray(K, float)
    R = np.asarray(R, float)
    t = np.asarray(t, float)
    if R.shape != (3, 3) or t.shape != (3,) or K.shape != (3, 3):
        raise InsertionError('K and R must be 3x3, t a 3-vector')
    if samples < 1 or samples % 2 == 0:
        raise InsertionError(f'samples must be odd and >= 1, got {samples}')
    if not (0.0 <= occlude < 0.5):
        raise InsertionError(f'occlude must be in [0, 0.5), got {occlude}')
    K_inv = np.linalg.inv(K)
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    # background: smooth random texture (blobs of several sizes)
    bg = np.zeros((height, width))
    for cells, amp in ((8, 0.25), (32, 0.12), (96, 0.05)):
        small = rng.random((max(2, cells * height // width), cells))
        bg += amp * cv2.resize(small, (width, height), interpolation=cv2.INTER_CUBIC)
    bg = np.clip(0.1 + bg, 0.02, 0.95)
    x, y = _plate_coords(K_inv, R, t, uu, vv)
    refl = _reflectance(plate, x, y, bg, with_markers)
    # pixels near an edge: a marker rim or the plate border, within 2 pixel footprints
    depth = (R[:, 2] @ t) / (R[:, 2] @ (K_inv @ np.stack([uu.ravel(), vv.ravel(),
                                                          np.ones(uu.size)]))).reshape(uu.shape)
    foot = 2.5 * np.abs(depth) / K[0, 0] / max(abs(R[2, 2]), 0.2)
    near = (np.abs(np.abs(x) - plate.half_size_m[0]) < foot) \
        | (np.abs(np.abs(y) - plate.half_size_m[1]) < foot)
    if with_markers:
        for mx, my in plate.markers:
            near |= np.abs(np.hypot(x - mx, y - my) - plate.marker_radius_m) < foot
    rr, cc = np.nonzero(near)
    if len(rr):
        off = (np.arange(samples) - (samples - 1) / 2) / samples
        du, dv = np.meshgrid(off, off)
        su = (cc[:, None] + du.ravel()[None, :])
        sv = (rr[:, None] + dv.ravel()[None, :])
        sx, sy = _plate_coords(K_inv, R, t, su, sv)
        sub = _reflectance(plate, sx, sy, bg[rr, cc][:, None], with_markers)
        refl[rr, cc] = sub.mean(1)
    # lighting
    phi = rng.uniform(0, 2 * math.pi)
    lin = ((uu - width / 2) * math.cos(phi) + (vv - height / 2) * math.sin(phi)) / width
    r2 = ((uu - width / 2) ** 2 + (vv - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    light = (1.0 + gradient * lin) * (1.0 - vignetting * r2)
    img = 240.0 * refl * light
    centres = np.zeros((0, 2))
    ell_c = np.zeros((0, 2))
    radius = np.zeros(0)
    occluded = np.zeros(0)
    if with_markers:
        pts = np.array([R @ np.array([mx, my, 0.0]) + t for mx, my in plate.markers])
        proj = (K @ pts.T).T
        centres = proj[:, :2] / proj[:, 2:]
        radius = K[0, 0] * plate.marker_radius_m / pts[:, 2]
        ell_c = np.array([_ellipse_centre(K, R, t, (mx, my), plate.marker_radius_m)
                          for mx, my in plate.markers])
        occluded = np.zeros(len(centres))
    if occlude > 0 and with_markers:
        # a dark bar whose edge cuts the first marker's rim: hidden arc fraction
        # f = arccos(d / r) / pi for an edge at distance d from the centre
        f = rng.uniform(0.05, occlude)
        d = radius[0] * math.cos(math.pi * f)
        psi = rng.uniform(0, 2 * math.pi)
        nrm = np.array([math.cos(psi), math.sin(psi)])
        sd = (uu - centres[0, 0]) * nrm[0] + (vv - centres[0, 1]) * nrm[1] - d
        cover = np.clip(0.5 + sd, 0.0, 1.0) * np.clip(0.5 + (d + 40.0 - sd), 0.0, 1.0)
        img = img * (1 - cover) + 40.0 * cover
        occluded[0] = f
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur_sigma) if blur_sigma > 0 else img
    img = img + rng.normal(0.0, noise_sigma, img.shape)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    return Rendered(image, centres, radius, R[:, 2].copy(), occluded, ell_c)


def _ellipse_centre(K: np.ndarray, R: np.ndarray, t: np.ndarray, m: Sequence[float], r: float
                    ) -> np.ndarray:
    """Centre of the exact imaged ellipse of the circle (radius r at plate point m)."""
    H = K @ np.column_stack([R[:, 0], R[:, 1], R @ np.array([m[0], m[1], 0.0]) + t])
    Hi = np.linalg.inv(H)
    C = Hi.T @ np.diag([1.0, 1.0, -r * r]) @ Hi
    return -np.linalg.solve(C[:2, :2], C[:2, 2])


def random_pose(rng: np.random.Generator, K: np.ndarray, width: int, height: int,
                plate: Plate, *, distance_m: tuple[float, float] = (0.25, 0.6),
                max_tilt_rad: float = math.radians(45.0), margin_px: float = 10.0
                ) -> tuple[np.ndarray, np.ndarray]:
    """A plate pose with every marker inside the image (margin plus its radius): tilt uniform in
    [0, max_tilt] about a random in-plane axis, random roll, random position."""
    flip = _rot(np.array([1.0, 0.0, 0.0]), math.pi)        # plate +z towards the camera
    for _ in range(1000):
        roll = _rot(np.array([0.0, 0.0, 1.0]), rng.uniform(0, 2 * math.pi))
        ax = rng.uniform(0, 2 * math.pi)
        tilt = _rot(np.array([math.cos(ax), math.sin(ax), 0.0]), rng.uniform(0, max_tilt_rad))
        R = tilt @ flip @ roll
        z = rng.uniform(*distance_m)
        u = rng.uniform(0.1, 0.9) * width
        v = rng.uniform(0.1, 0.9) * height
        t = z * np.linalg.solve(K, np.array([u, v, 1.0]))
        pts = np.array([R @ np.array([mx, my, 0.0]) + t for mx, my in plate.markers])
        if np.any(pts[:, 2] <= 0.05):
            continue
        proj = (K @ pts.T).T
        c = proj[:, :2] / proj[:, 2:]
        r = K[0, 0] * plate.marker_radius_m / pts[:, 2] * 1.5 + margin_px
        if np.all((c[:, 0] > r) & (c[:, 0] < width - r) & (c[:, 1] > r) & (c[:, 1] < height - r)):
            return R, t
    raise InsertionError('no pose found with every marker in the image')


def random_scene(rng: np.random.Generator, K: np.ndarray, width: int, height: int, *,
                 with_markers: bool = True, plate: Plate | None = None,
                 max_tilt_rad: float = math.radians(45.0),
                 distance_m: tuple[float, float] = (0.25, 0.6),
                 noise_sigma: tuple[float, float] = (1.0, 5.0),
                 blur_sigma: tuple[float, float] = (0.5, 1.5),
                 gradient: tuple[float, float] = (0.0, 0.6),
                 occlude_probability: float = 0.25, occlude: float = 0.25) -> Rendered:
    """A random image for the tests and the benchmark: the card or the site (at random unless
    `plate`), a random pose, random noise / blur / lighting, and with `occlude_probability`
    a bar hiding up to `occlude` of one marker's rim."""
    if plate is None:
        plate = CARD if rng.random() < 0.5 else SITE
    R, t = random_pose(rng, K, width, height, plate, distance_m=distance_m,
                       max_tilt_rad=max_tilt_rad)
    occ = occlude if (rng.random() < occlude_probability) else 0.0
    return render_plate(K, width, height, R, t, plate, rng=rng, with_markers=with_markers,
                        noise_sigma=rng.uniform(*noise_sigma), blur_sigma=rng.uniform(*blur_sigma),
                        gradient=rng.uniform(*gradient), vignetting=rng.uniform(0.0, 0.3),
                        occlude=occ)


# ------------------------------------------------------------------ discs on other backgrounds

def _octave(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Smooth random field in [0, 1] with about `cells` blobs across."""
    small = rng.random((cells, cells))
    return cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC).clip(0.0, 1.0)


def background_texture(rng: np.random.Generator, kind: Background | str, size: int = 1024
                       ) -> np.ndarray:
    """A (size, size) reflectance texture in [0.02, 0.8], about one texel a pixel where it is
    imaged (`render_discs`).

    - 'ground': gravel, pixel-scale noise blurred 3x3 (rover_sim's ground texture) over
      blotches of a few sizes.
    - 'rock': ridged multi-octave noise (bright veins where a field crosses its middle, dark
      cracks) over shading blotches.
    - 'metal': brushed streaks (noise smeared along one direction) over a slow sheen.
    - 'light': the plate scenes' smooth background texture; the uneven light is added by
      `background_scene`."""
    kind = choice(Background, kind, 'background', error=InsertionError)
    match kind:
        case Background.GROUND:
            fine = cv2.GaussianBlur(rng.random((size, size)), (3, 3), 0)
            fine = (fine - fine.mean()) / fine.std()
            base = 0.35 + 0.2 * _octave(rng, size, 6) + 0.1 * _octave(rng, size, 40)
            tex = base + 0.08 * fine
        case Background.ROCK:
            base = 0.3 + 0.2 * _octave(rng, size, 5) + 0.1 * _octave(rng, size, 24)
            veins = np.zeros((size, size))
            for cells, amp in ((10, 0.25), (30, 0.15)):
                f = _octave(rng, size, cells)
                veins += amp * np.exp(-((f - 0.5) / 0.02) ** 2)
            cracks = np.exp(-((_octave(rng, size, 16) - 0.5) / 0.015) ** 2)
            fine = cv2.GaussianBlur(rng.random((size, size)), (3, 3), 0) - 0.5
            tex = (base + veins) * (1.0 - 0.6 * cracks) + 0.1 * fine
        case Background.METAL:
            streak: np.ndarray = rng.normal(0.0, 1.0, (size, size))
            streak = cv2.GaussianBlur(streak, (61, 1), 20.0)
            streak = cv2.GaussianBlur(streak, (1, 3), 0.7)
            streak = (streak - streak.mean()) / streak.std()
            tex = 0.45 + 0.15 * _octave(rng, size, 3) + 0.05 * streak
            ang = rng.uniform(0.0, 180.0)
            M = cv2.getRotationMatrix2D((size / 2, size / 2), ang, 1.0)
            tex = cv2.warpAffine(tex, M, (size, size), borderMode=cv2.BORDER_REFLECT101)
        case Background.LIGHT:
            tex = np.zeros((size, size))
            for cells, amp in ((8, 0.25), (32, 0.12), (96, 0.05)):
                tex += amp * _octave(rng, size, cells)
            tex = 0.1 + tex
        case _:
            assert_never(kind)
    return np.clip(tex, 0.02, 0.8)


def render_discs(K: np.ndarray, width: int, height: int, R: np.ndarray, t: np.ndarray,
                 discs: np.ndarray, texture: np.ndarray, texel_m: float, *,
                 rng: np.random.Generator, light: np.ndarray | None = None,
                 disc_reflectance: float = 0.9, noise_sigma: float = 3.0,
                 blur_sigma: float = 0.8, samples: int = 9) -> Rendered:
    """One image of an unbounded plane at pose (R, t) (plane frame -> camera optical frame)
    textured with `texture` (reflectance, `texel_m` m a texel, centred on the plane's origin,
    mirrored beyond its edge) and carrying white discs `discs` (N, 3: plane x, y, radius in m).
    The rim pixels are area-integrated as in `render_plate`; `light` (height, width) multiplies
    the reflectance (None: even light); then blur, noise and 8-bit quantisation."""
    K, R, t = (np.asarray(a, float) for a in (K, R, t))
    discs = np.asarray(discs, float).reshape(-1, 3)
    if R.shape != (3, 3) or t.shape != (3,) or K.shape != (3, 3):
        raise InsertionError('K and R must be 3x3, t a 3-vector')
    if samples < 1 or samples % 2 == 0:
        raise InsertionError(f'samples must be odd and >= 1, got {samples}')
    if not (texel_m > 0) or texture.ndim != 2:
        raise InsertionError('texture must be 2-D and texel_m > 0')
    K_inv = np.linalg.inv(K)
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    x, y = _plate_coords(K_inv, R, t, uu, vv)
    th, tw = texture.shape
    mx = (x / texel_m + tw / 2).astype(np.float32)
    my = (y / texel_m + th / 2).astype(np.float32)
    refl = cv2.remap(texture.astype(np.float32), mx, my, cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REFLECT101).astype(np.float64)
    bg = refl.copy()
    n = R[:, 2]
    depth = (n @ t) / (n @ (K_inv @ np.stack([uu.ravel(), vv.ravel(),
                                              np.ones(uu.size)]))).reshape(uu.shape)
    foot = 2.5 * np.abs(depth) / K[0, 0] / max(abs(R[2, 2]), 0.2)
    near = np.zeros(uu.shape, bool)
    for dx, dy, r in discs:
        dist = np.hypot(x - dx, y - dy)
        refl = np.where(dist <= r, disc_reflectance, refl)
        near |= np.abs(dist - r) < foot
    rr, cc = np.nonzero(near)
    if len(rr):
        off = (np.arange(samples) - (samples - 1) / 2) / samples
        du, dv = np.meshgrid(off, off)
        sx, sy = _plate_coords(K_inv, R, t, cc[:, None] + du.ravel()[None, :],
                               rr[:, None] + dv.ravel()[None, :])
        sub = np.broadcast_to(bg[rr, cc][:, None], sx.shape).copy()
        for dx, dy, r in discs:
            sub[(sx - dx) ** 2 + (sy - dy) ** 2 <= r * r] = disc_reflectance
        refl[rr, cc] = sub.mean(1)
    img = 240.0 * refl * (1.0 if light is None else light)
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), blur_sigma) if blur_sigma > 0 else img
    img = img + rng.normal(0.0, noise_sigma, img.shape)
    image = np.clip(np.rint(img), 0, 255).astype(np.uint8)
    pts = np.array([R @ np.array([dx, dy, 0.0]) + t for dx, dy, _ in discs]).reshape(-1, 3)
    if len(pts):
        proj = (K @ pts.T).T
        centres = proj[:, :2] / proj[:, 2:]
        ell_c = np.array([_ellipse_centre(K, R, t, (dx, dy), r) for dx, dy, r in discs])
    else:
        centres, ell_c = np.zeros((0, 2)), np.zeros((0, 2))
    radius = K[0, 0] * discs[:, 2] / np.maximum(pts[:, 2], 1e-9) if len(pts) else np.zeros(0)
    return Rendered(image, centres, radius, R[:, 2].copy(), np.zeros(len(discs)), ell_c)


def _lighting(rng: np.random.Generator, width: int, height: int, *, gradient: float,
              vignetting: float, shadow: float = 0.0, spot: float = 0.0) -> np.ndarray:
    """Light factor (height, width): a linear gradient across the image, vignetting, a soft
    shadow edge (half the image darkened by `shadow`) and a Gaussian spot (`spot` brighter)."""
    vv, uu = np.mgrid[0:height, 0:width].astype(np.float64)
    phi = rng.uniform(0, 2 * math.pi)
    lin = ((uu - width / 2) * math.cos(phi) + (vv - height / 2) * math.sin(phi)) / width
    r2 = ((uu - width / 2) ** 2 + (vv - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
    light = (1.0 + gradient * lin) * (1.0 - vignetting * r2)
    if shadow > 0:
        psi = rng.uniform(0, 2 * math.pi)
        d = ((uu - rng.uniform(0.3, 0.7) * width) * math.cos(psi)
             + (vv - rng.uniform(0.3, 0.7) * height) * math.sin(psi))
        soft = rng.uniform(2.0, 15.0)
        light = light * (1.0 - shadow / (1.0 + np.exp(-np.clip(d / soft, -50, 50))))
    if spot > 0:
        cu, cv_ = rng.uniform(0, width), rng.uniform(0, height)
        s = rng.uniform(0.15, 0.35) * width
        light = light * (1.0 + spot * np.exp(-((uu - cu) ** 2 + (vv - cv_) ** 2) / (2 * s * s)))
    return light


def background_scene(rng: np.random.Generator, K: np.ndarray, width: int, height: int,
                     background: Background | str, *, with_markers: bool = True,
                     markers: tuple[int, int] = (2, 5),
                     radius_px: tuple[float, float] = (3.0, 70.0),
                     max_tilt_rad: float = math.radians(45.0),
                     distance_m: tuple[float, float] = (0.4, 1.2),
                     noise_sigma: tuple[float, float] = (1.0, 5.0),
                     blur_sigma: tuple[float, float] = (0.5, 1.5),
                     gradient: tuple[float, float] = (0.0, 0.6),
                     margin_px: float = 10.0) -> Rendered:
    """White discs (count uniform in `markers`, imaged radius log-uniform in `radius_px`, apart
    by at least their radii) painted on a plane `distance_m` away along the optical axis,
    tilted uniformly up to `max_tilt_rad` about a random in-plane axis, textured as
    `background` (`background_texture`), about one texel a pixel; random noise, blur and a
    lighting gradient, for 'light' also a shadow edge darkening 40-65 % and a spot up to 60 %
    brighter. `with_markers=False`: the same kind of image with no disc."""
    background = choice(Background, background, 'background', error=InsertionError)
    lo, hi = markers
    if not (0 < lo <= hi <= 20):
        raise InsertionError(f'markers must be (min, max) with 0 < min <= max <= 20, got '
                             f'{markers}')
    flip = _rot(np.array([1.0, 0.0, 0.0]), math.pi)
    roll = _rot(np.array([0.0, 0.0, 1.0]), rng.uniform(0, 2 * math.pi))
    ax = rng.uniform(0, 2 * math.pi)
    tilt = _rot(np.array([math.cos(ax), math.sin(ax), 0.0]), rng.uniform(0, max_tilt_rad))
    R = tilt @ flip @ roll
    z0 = rng.uniform(*distance_m)
    t = np.array([0.0, 0.0, z0])
    K = np.asarray(K, float)
    K_inv = np.linalg.inv(K)
    discs: list[tuple[float, float, float]] = []
    placed: list[tuple[float, float, float]] = []
    want = int(rng.integers(lo, hi + 1)) if with_markers else 0
    for _ in range(400 * max(want, 1)):
        if len(discs) >= want:
            break
        r_px = math.exp(rng.uniform(math.log(radius_px[0]), math.log(radius_px[1])))
        m = 1.6 * r_px + margin_px
        if 2 * m >= min(width, height):
            continue
        u, v = rng.uniform(m, width - m), rng.uniform(m, height - m)
        if any(math.hypot(u - pu, v - pv) < 1.3 * (r_px + pr) + 6.0 for pu, pv, pr in placed):
            continue
        px, py = _plate_coords(K_inv, R, t, np.array([u]), np.array([v]))
        c3 = R @ np.array([px[0], py[0], 0.0]) + t
        discs.append((float(px[0]), float(py[0]), r_px * c3[2] / K[0, 0]))
        placed.append((u, v, r_px))
    if len(discs) < want:
        raise InsertionError(f'placed {len(discs)} of {want} discs in the image')
    strong = background is Background.LIGHT
    light = _lighting(rng, width, height, gradient=rng.uniform(*gradient) * (1.5 if strong else 1),
                      vignetting=rng.uniform(0.0, 0.4 if strong else 0.3),
                      shadow=rng.uniform(0.4, 0.65) if strong else 0.0,
                      spot=rng.uniform(0.2, 0.6) if strong else 0.0)
    texture = background_texture(rng, background)
    return render_discs(K, width, height, R, t, np.array(discs).reshape(-1, 3), texture,
                        z0 / K[0, 0], rng=rng, light=light,
                        noise_sigma=rng.uniform(*noise_sigma),
                        blur_sigma=rng.uniform(*blur_sigma))
