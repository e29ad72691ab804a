"""The default marker detector's detection limit on the simulator's own renders, no rclpy.

    python -m coop_insertion.detector_limits --json docs/results/data/detector_limits.json

rover_sim's World (the Table 5-1 site, its 4.5 in slot, no obstacles) renders the slot's
0.25 in markers through its own renderer (`World.render_eye`, the left camera, 640 x 480,
K = World.intrinsics()) from camera poses on a grid of marker diameter in pixels (the range
r = f * 0.25 in / diameter from the camera to the marker's centre) and incidence (the angle
between the ray to the marker and the marked face's normal). Per render the camera stands at
that range and incidence on a random side of the normal (the incidence's plane within
15 deg of horizontal) and looks at a point near the marker, so the marker falls at a random
place in the middle of the image; the two slot markers are aimed at in turn. A marker is
detected when `make_detector('default', K=K)` returns a marker within max(1, r_px / 2) px of
the projection of its centre; any detection near no marker of the site (the slot markers,
or within its radius of one of the site's two fiducials) is a false one.

From the table: `min_diameter_px_by_incidence`, per incidence the smallest diameter from
which on every larger diameter of the grid is detected in at least `rate` of the renders
(None where not even the largest is); `min_diameter_px`, that diameter straight on
(incidence 0); `max_incidence_deg`, the largest incidence up to which every incidence of the
grid has one. A placement is inside the limit when its incidence is at most
`max_incidence_deg` and its marker diameter at least the entry for the next larger incidence
of the grid.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np

from coop_common.cli import number, output_path
from coop_common.files import write_json

from .errors import InsertionError
from .markers import make_detector

__all__ = [
    'DIAMETERS_PX',
    'INCIDENCES_DEG',
    'CellResult',
    'camera_pose',
    'derive_limits',
    'format_table',
    'main',
    'measure',
]

#: the grid: marker diameter (px, f * 2 r / range) and incidence (deg)
DIAMETERS_PX = (3.0, 4.0, 5.0, 6.0, 7.0, 8.0, 10.0, 12.0, 16.0)
INCIDENCES_DEG = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)


@dataclass(frozen=True)
class CellResult:
    """One (diameter, incidence) cell: renders, detections, false markers and centre errors."""

    diameter_px: float
    incidence_deg: float
    renders: int
    detected: int
    false_markers: int
    centre_error_px_mean: float

    @property
    def rate(self) -> float:
        return self.detected / self.renders if self.renders else float('nan')


def _look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera rotation (columns: optical x right, y down, z forward) at `eye` towards
    `target`, world z up."""
    z = target - eye
    z = z / np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x = x / np.linalg.norm(x)
    return np.column_stack([x, np.cross(z, x), z])


def camera_pose(marker: np.ndarray, normal: np.ndarray, range_m: float, incidence_rad: float,
                *, rng: np.random.Generator, fx: float, width: int, height: int,
                spread: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(eye, R) with the marker `range_m` away at `incidence_rad` from the face's `normal`
    (the incidence's plane at a random side, within 15 deg of horizontal) and imaged at a
    random place within `spread` of the half-image from the centre."""
    n = np.asarray(normal, float) / np.linalg.norm(normal)
    side = np.cross(n, [0.0, 0.0, 1.0])
    side = side / np.linalg.norm(side)
    up = np.cross(side, n)
    beta = math.radians(rng.uniform(-15.0, 15.0)) + (math.pi if rng.random() < 0.5 else 0.0)
    u = math.cos(beta) * side + math.sin(beta) * up
    d = math.cos(incidence_rad) * n + math.sin(incidence_rad) * u
    eye = marker + range_m * d
    R = _look_at(eye, marker)
    # turn the camera so the marker lands at pixel offset (du, dv) from the principal point
    du = rng.uniform(-spread, spread) * width / 2
    dv = rng.uniform(-spread, spread) * height / 2
    ray = R @ np.array([-du / fx, -dv / fx, 1.0])
    return eye, _look_at(eye, eye + ray * range_m)


def measure(*, diameters_px: tuple[float, ...] = DIAMETERS_PX,
            incidences_deg: tuple[float, ...] = INCIDENCES_DEG, per_cell: int = 20,
            seed: int = 0, world_seed: int = 1, width: int = 640, height: int = 480,
            log: Callable[[str], None] | None = None) -> tuple[list[CellResult], dict]:
    """Render and detect every cell `per_cell` times; the cells and the settings used."""
    if per_cell < 1:
        raise InsertionError(f'per_cell must be >= 1, got {per_cell}')
    if not all(0.0 <= a < 90.0 for a in incidences_deg):
        raise InsertionError(f'incidences must be in [0, 90) deg, got {incidences_deg}')
    if not all(d > 0 for d in diameters_px):
        raise InsertionError(f'diameters must be > 0 px, got {diameters_px}')
    from coop_common.dynparams import load_truth  # noqa: PLC0415 - only to render
    from rover_sim.config import SimConfig  # noqa: PLC0415 - only to render
    from rover_sim.world import World  # noqa: PLC0415 - PyBullet, only to render

    cfg = SimConfig(rovers=1, seed=world_seed, occlusion_density=0.0, stereo_rate_hz=0.0,
                    image_width=width, image_height=height)
    rng = np.random.default_rng(seed)
    cells = []
    with World(cfg, [load_truth()]) as world:
        K = world.intrinsics()
        fx = float(K[0, 0])
        detector = make_detector('default', K=K)
        site = world.layout.site
        slot = np.asarray(site.slot_markers, float)
        known = np.vstack([slot, np.asarray(site.markers, float)])
        normal = np.array([0.0, 1.0, 0.0])          # the jaws' +y faces (worldgen.make_site)
        diameter_m = 2.0 * site.slot_marker_radius_m
        t0 = time.perf_counter()
        for d_px in diameters_px:
            rng_m = fx * diameter_m / d_px
            for inc in incidences_deg:
                found, false, errs = 0, 0, []
                for k in range(per_cell):
                    marker = slot[k % len(slot)]
                    eye, R = camera_pose(marker, normal, rng_m, math.radians(inc), rng=rng,
                                         fx=fx, width=width, height=height)
                    image = world.render_eye(eye, R, 0.0)
                    dets = detector.detect(image)
                    pc = (known - eye) @ R                 # camera frame
                    vis = pc[:, 2] > 0.05
                    uv = np.full((len(known), 2), np.nan)
                    uv[vis] = (pc[vis, :2] / pc[vis, 2:]) * fx + K[:2, 2]
                    r_px = np.where(vis, fx * 0.5 * diameter_m / np.maximum(pc[:, 2], 1e-9), 0.0)
                    r_px[len(slot):] = np.where(vis[len(slot):], fx * site.marker_radius_m
                                                / np.maximum(pc[len(slot):, 2], 1e-9), 0.0)
                    aimed = k % len(slot)
                    # the site's fiducials are 1 mm proud discs: seen obliquely, their lit rim
                    # moves the fitted centre, within their radius
                    tol = np.maximum(1.0, 0.5 * r_px)
                    tol[len(slot):] = np.maximum(1.0, r_px[len(slot):])
                    hit = False
                    for m in dets:
                        dist = np.hypot(uv[:, 0] - m.u, uv[:, 1] - m.v)
                        near = np.nan_to_num(dist, nan=np.inf) < tol
                        if near[aimed] and not hit:
                            hit = True
                            errs.append(float(dist[aimed]))
                        elif not near.any():
                            false += 1
                    found += hit
                cells.append(CellResult(d_px, inc, per_cell, found, false,
                                        float(np.mean(errs)) if errs else float('nan')))
                if log is not None:
                    log(f'{d_px:4.0f} px ({rng_m:.2f} m) {inc:4.0f} deg: {found}/{per_cell}, '
                        f'{false} false  [{time.perf_counter() - t0:.0f} s]')
        settings = {'per_cell': per_cell, 'seed': seed, 'world_seed': world_seed,
                    'width': width, 'height': height, 'fx': fx,
                    'slot_marker_diameter_m': diameter_m, 'renderer': world.renderer.value,
                    'detector': "make_detector('default', K=World.intrinsics())",
                    'slot_gap_m': site.gap_m, 'occlusion_density': 0.0}
    return cells, settings


def derive_limits(cells: list[CellResult], *, rate: float = 0.97) -> dict:
    """min_diameter_px, max_incidence_deg and min_diameter_px_by_incidence (module doc)."""
    ds = sorted({c.diameter_px for c in cells})
    incs = sorted({c.incidence_deg for c in cells})
    table = {(c.diameter_px, c.incidence_deg): c.rate for c in cells}

    def smallest(inc: float) -> float | None:
        best = None
        for d in reversed(ds):
            if table.get((d, inc), 0.0) >= rate:
                best = d
            else:
                break
        return best

    by_inc = {f'{inc:g}': smallest(inc) for inc in incs}
    dmin = by_inc[f'{incs[0]:g}'] if incs and incs[0] == 0.0 else None
    max_inc = None
    for inc in incs:
        if by_inc[f'{inc:g}'] is None:
            break
        max_inc = inc
    return {'rate': rate, 'min_diameter_px': dmin, 'max_incidence_deg': max_inc,
            'min_diameter_px_by_incidence': by_inc}


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result."""
    s, lim = result['settings'], result['limits']
    cells = result['cells']
    ds = sorted({c['diameter_px'] for c in cells})
    incs = sorted({c['incidence_deg'] for c in cells})
    rate = {(c['diameter_px'], c['incidence_deg']): c['detected'] / c['renders'] for c in cells}
    false = sum(c['false_markers'] for c in cells)
    lines = [f'default detector on rover_sim renders ({s["width"]}x{s["height"]}, fx '
             f'{s["fx"]:.1f} px) of the 0.25 in slot markers: detection rate (%) in '
             f'{s["per_cell"]} renders per cell; {false} false markers in all',
             f'{"diam px":>7} {"range m":>7} | ' + ' '.join(f'{i:>5.0f}' for i in incs)
             + '  incidence (deg)']
    for d in ds:
        rng_m = s['fx'] * s['slot_marker_diameter_m'] / d
        lines.append(f'{d:7.0f} {rng_m:7.2f} | '
                     + ' '.join(f'{100 * rate[(d, i)]:5.0f}' for i in incs))

    def fmt(x: float | None, unit: str) -> str:
        return 'none in the grid' if x is None else f'{x:g} {unit}'

    lines.append(f'detected in >= {100 * lim["rate"]:g} %: min_diameter_px '
                 f'{fmt(lim["min_diameter_px"], "px")}, max_incidence_deg '
                 f'{fmt(lim["max_incidence_deg"], "deg")}')
    lines.append('min_diameter_px by incidence: ' + ', '.join(
        f'{k} deg: {"-" if v is None else f"{v:g}"}'
        for k, v in lim['min_diameter_px_by_incidence'].items()))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_insertion.detector_limits`: measure the limit and write the JSON."""
    os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
    ap = argparse.ArgumentParser(prog='detector_limits', description=__doc__.split('\n\n')[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--per-cell', type=number(int, lo=1, hi=1000), default=20)
    ap.add_argument('--seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    ap.add_argument('--rate', type=number(float, lo=0.5, hi=1.0), default=0.97)
    ap.add_argument('--quiet', action='store_true')
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    t0 = time.perf_counter()
    cells, settings = measure(per_cell=args.per_cell, seed=args.seed,
                              log=None if args.quiet else
                              (lambda m: print(m, file=sys.stderr, flush=True)))
    settings['wall_s'] = time.perf_counter() - t0
    result = {'settings': settings, 'cells': [
        {'diameter_px': c.diameter_px, 'incidence_deg': c.incidence_deg, 'renders': c.renders,
         'detected': c.detected, 'false_markers': c.false_markers,
         'centre_error_px_mean': c.centre_error_px_mean} for c in cells],
        'limits': derive_limits(cells, rate=args.rate)}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
