#!/usr/bin/env python3
"""Circular-marker detectors side by side (thesis §5.3): the thesis pipeline, the default
sub-pixel ellipse detector with the perspective correction, and cv2.HoughCircles, on the same
640x480 renders (coop_insertion.marker_render.random_scene: the card's and the site's markers at
0.25-0.6 m, tilts up to 45 deg, noise, uneven lighting, blur, a quarter of the images with a
bar hiding up to 25 % of one marker's rim) with known centres, and on marker-free images (the
same plates and backgrounds without markers).

Per detector: time per frame on one thread (CPU time of this process, which a loaded machine
does not inflate, and wall time), the centre error (px) against the projection of the true
circle centre for every detected marker (a detection within half the marker's radius), the
detection rate and the false markers: detections on the marker-free images, and detections
matching no marker on the marker images.

Usage: bench/markers.py --json OUT [--images N] [--empty N] [--seed S]
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

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from coop_common.cli import number, output_path  # noqa: E402
from coop_common.files import write_json  # noqa: E402
from coop_insertion.marker_render import random_scene, sim_intrinsics  # noqa: E402
from coop_insertion.markers import make_detector  # noqa: E402

WIDTH, HEIGHT = 640, 480
NAMES = ('thesis', 'default', 'hough')


def images(n: int, n_empty: int, seed: int):
    rng = np.random.default_rng(seed)
    K = sim_intrinsics(WIDTH, HEIGHT)
    with_m = [random_scene(rng, K, WIDTH, HEIGHT) for _ in range(n)]
    empty = [random_scene(rng, K, WIDTH, HEIGHT, with_markers=False) for _ in range(n_empty)]
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
        for k, (c, r) in enumerate(zip(s.centres, s.radius_px)):
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
    lines = [f'{s["images"]} images {WIDTH}x{HEIGHT} with {result["markers"]} markers '
             f'(mean ellipse-centre bias of the truth {result["ellipse_bias_px_mean"]:.3f} px, '
             f'max {result["ellipse_bias_px_max"]:.3f}), {s["empty"]} marker-free images',
             f'{"detector":>8} {"Hz (cpu)":>8} {"ms cpu":>7} {"ms wall":>7} {"err mean":>8} '
             f'{"median":>7} {"p95":>6} {"occl.":>6} {"detected":>8} {"false":>5} '
             f'{"spurious":>8} {"resolved":>8}']
    for name in NAMES:
        r = result['detectors'][name]
        lines.append(f'{name:>8} {r["hz"]:8.0f} {r["ms_per_frame_cpu"]:7.2f} '
                     f'{r["ms_per_frame_wall"]:7.2f} {r["centre_error_px_mean"]:8.3f} '
                     f'{r["centre_error_px_median"]:7.3f} {r["centre_error_px_p95"]:6.3f} '
                     f'{r["centre_error_px_mean_occluded"]:6.3f} '
                     f'{100 * r["detection_rate"]:7.1f}% {r["false_markers"]:5d} '
                     f'{r["spurious_on_marker_images"]:8d} {100 * r["resolved_share"]:7.0f}%')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--images', type=number(int, lo=1, hi=10000), default=100)
    ap.add_argument('--empty', type=number(int, lo=0, hi=10000), default=50)
    ap.add_argument('--seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)
    K, scenes, empty = images(args.images, args.empty, args.seed)
    bias = np.concatenate([np.hypot(*(s.ellipse_centres - s.centres).T) for s in scenes])
    dets = {'thesis': make_detector('thesis'), 'default': make_detector('default', K=K),
            'hough': make_detector('hough')}
    result = {'settings': {'images': args.images, 'empty': args.empty, 'seed': args.seed,
                           'width': WIDTH, 'height': HEIGHT, 'K': K.tolist(),
                           'threads': 1, 'opencv': cv2.__version__},
              'markers': int(sum(len(s.centres) for s in scenes)),
              'ellipse_bias_px_mean': float(bias.mean()),
              'ellipse_bias_px_max': float(bias.max()),
              'detectors': {name: run(dets[name], scenes, empty) for name in NAMES}}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
