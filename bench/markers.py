#!/usr/bin/env python3
"""Circular-marker detectors side by side (thesis §5.3): the thesis pipeline, the default
sub-pixel ellipse detector with the perspective correction, and cv2.HoughCircles, on the same
640x480 renders with known centres, in families (coop_insertion.marker_render).

- `plates`: the card's and the site's markers at 0.25-0.6 m (random_scene), tilts up to
  45 deg, noise, uneven lighting, blur, a quarter of the images with a bar hiding up to 25 % of
  one marker's rim;
- `slot`: the slot's 0.25 in markers on the jaws (SLOT) at 0.65-0.95 m, 2.8-4.2 px radius, the
  size the master sees them at, tilts up to 45 deg, not occluded;
- `ground`, `rock`, `metal`, `light`: 2-5 white discs of 3-70 px radius painted on a plane
  tilted up to 45 deg, textured as gravel, veined rock, brushed metal, or the plates'
  background under a shadow edge and a spot (background_scene);

each with marker-free images (the same plates and backgrounds without markers).

Per family and detector: time per frame on one thread (CPU time of this process, which a
loaded machine does not inflate, and wall time), the centre error (px) against the projection
of the true circle centre for every detected marker (a detection within half the marker's
radius), the detection rate and the false markers: detections on the marker-free images, and
detections matching no marker on the marker images.

Usage: bench/markers.py --json OUT [--images N] [--empty N] [--family-images N]
                        [--family-empty N] [--families F ...] [--detectors D ...] [--seed S]
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_insertion.marker_render import (
    BACKGROUNDS,
    SLOT,
    background_scene,
    random_scene,
    sim_intrinsics,
)
from coop_insertion.markers import make_detector

WIDTH, HEIGHT = 640, 480
NAMES = ('thesis', 'default', 'hough')
FAMILIES = ('plates', 'slot', *BACKGROUNDS)


def scene(family: str, rng: np.random.Generator, K: np.ndarray, *, with_markers: bool = True):
    """One render of `family` (FAMILIES)."""
    if family == 'plates':
        return random_scene(rng, K, WIDTH, HEIGHT, with_markers=with_markers)
    if family == 'slot':
        return random_scene(rng, K, WIDTH, HEIGHT, with_markers=with_markers, plate=SLOT,
                            distance_m=(0.65, 0.95), occlude_probability=0.0)
    return background_scene(rng, K, WIDTH, HEIGHT, family, with_markers=with_markers)


def images(family: str, n: int, n_empty: int, seed: int):
    """K, the marker images and the marker-free images of one family (its own seed stream)."""
    rng = np.random.default_rng([seed, FAMILIES.index(family)])
    K = sim_intrinsics(WIDTH, HEIGHT)
    with_m = [scene(family, rng, K) for _ in range(n)]
    empty = [scene(family, rng, K, with_markers=False) for _ in range(n_empty)]
    return K, with_m, empty


def run(det, scenes, empty) -> dict:
    cpu, wall = 0.0, 0.0
    errs, resolved, missed, spurious, false_m = [], [], 0, 0, 0
    err_occluded = []
    for s in scenes:
        c0, w0 = time.process_time(), time.perf_counter()
        found = det.detect(s.image)
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        used = set()
        for k, (c, r) in enumerate(zip(s.centres, s.radius_px, strict=False)):
            d = [math.hypot(m.u - c[0], m.v - c[1]) for m in found]
            j = int(np.argmin(d)) if d else -1
            if j >= 0 and d[j] < 0.5 * r and j not in used:
                used.add(j)
                errs.append(d[j])
                resolved.append(found[j].resolved)
                if s.occluded[k] > 0:
                    err_occluded.append(d[j])
            else:
                missed += 1
        spurious += len(found) - len(used)
    for s in empty:
        c0, w0 = time.process_time(), time.perf_counter()
        found = det.detect(s.image)
        cpu += time.process_time() - c0
        wall += time.perf_counter() - w0
        false_m += len(found)
    n_frames = len(scenes) + len(empty)
    n_markers = sum(len(s.centres) for s in scenes)
    e = np.asarray(errs)
    ms = 1e3 * cpu / n_frames
    return {'hz': 1e3 / ms, 'ms_per_frame_cpu': ms, 'ms_per_frame_wall': 1e3 * wall / n_frames,
            'centre_error_px_mean': float(e.mean()) if e.size else float('nan'),
            'centre_error_px_median': float(np.median(e)) if e.size else float('nan'),
            'centre_error_px_p95': float(np.percentile(e, 95)) if e.size else float('nan'),
            'centre_error_px_mean_occluded': (float(np.mean(err_occluded)) if err_occluded
                                              else float('nan')),
            'resolved_share': float(np.mean(resolved)) if resolved else 0.0,
            'detection_rate': (n_markers - missed) / n_markers, 'markers': n_markers,
            'missed': missed, 'spurious_on_marker_images': spurious,
            'false_markers': false_m, 'marker_free_images': len(empty)}


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result."""
    s = result['settings']
    lines = [f'{WIDTH}x{HEIGHT} renders, one thread; per family: marker images (markers), '
             f'marker-free images; ellipse-centre bias of the truth (mean / max px)',
             f'{"family":>6} {"detector":>8} {"Hz (cpu)":>8} {"ms cpu":>7} {"ms wall":>7} '
             f'{"err mean":>8} {"median":>7} {"p95":>6} {"occl.":>6} {"detected":>8} '
             f'{"false":>5} {"spurious":>8} {"resolved":>8}']
    for fam in s['families']:
        f = result['families'][fam]
        lines.append(f'{fam}: {f["images"]} images ({f["markers"]} markers, radius '
                     f'{f["radius_px_min"]:.1f}-{f["radius_px_max"]:.1f} px), '
                     f'{f["empty"]} marker-free; bias {f["ellipse_bias_px_mean"]:.3f} / '
                     f'{f["ellipse_bias_px_max"]:.3f} px')
        for name in s.get('detectors', NAMES):
            r = f['detectors'][name]
            lines.append(f'{fam:>6} {name:>8} {r["hz"]:8.0f} {r["ms_per_frame_cpu"]:7.2f} '
                         f'{r["ms_per_frame_wall"]:7.2f} {r["centre_error_px_mean"]:8.3f} '
                         f'{r["centre_error_px_median"]:7.3f} {r["centre_error_px_p95"]:6.3f} '
                         f'{r["centre_error_px_mean_occluded"]:6.3f} '
                         f'{100 * r["detection_rate"]:7.1f}% {r["false_markers"]:5d} '
                         f'{r["spurious_on_marker_images"]:8d} {100 * r["resolved_share"]:7.0f}%')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--images', type=number(int, lo=1, hi=10000), default=100,
                    help='marker images of the plates family')
    ap.add_argument('--empty', type=number(int, lo=0, hi=10000), default=50,
                    help='marker-free images of the plates family')
    ap.add_argument('--family-images', type=number(int, lo=1, hi=10000), default=50,
                    help='marker images of each other family')
    ap.add_argument('--family-empty', type=number(int, lo=0, hi=10000), default=25,
                    help='marker-free images of each other family')
    ap.add_argument('--families', nargs='+', choices=FAMILIES, default=list(FAMILIES))
    ap.add_argument('--detectors', nargs='+', choices=NAMES, default=list(NAMES))
    ap.add_argument('--seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    K = sim_intrinsics(WIDTH, HEIGHT)
    dets = {'thesis': make_detector('thesis'), 'default': make_detector('default', K=K),
            'hough': make_detector('hough')}
    families = {}
    for fam in args.families:
        n, n_empty = ((args.images, args.empty) if fam == 'plates'
                      else (args.family_images, args.family_empty))
        _, scenes, empty = images(fam, n, n_empty, args.seed)
        bias = np.concatenate([np.hypot(*(s.ellipse_centres - s.centres).T) for s in scenes])
        radii = np.concatenate([s.radius_px for s in scenes])
        families[fam] = {'images': n, 'empty': n_empty,
                         'markers': int(sum(len(s.centres) for s in scenes)),
                         'radius_px_min': float(radii.min()),
                         'radius_px_max': float(radii.max()),
                         'ellipse_bias_px_mean': float(bias.mean()),
                         'ellipse_bias_px_max': float(bias.max()),
                         'detectors': {name: run(dets[name], scenes, empty)
                                       for name in args.detectors}}
    result = {'settings': {'images': args.images, 'empty': args.empty,
                           'family_images': args.family_images,
                           'family_empty': args.family_empty, 'families': args.families,
                           'detectors': args.detectors,
                           'seed': args.seed, 'width': WIDTH, 'height': HEIGHT,
                           'K': K.tolist(), 'threads': 1, 'opencv': cv2.__version__},
              'families': families}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
