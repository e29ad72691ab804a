#!/usr/bin/env python3
"""Sub-pixel accuracy of the stereo front end: StereoSGBM's pixel locking and its corrections
(coop_mapping.stereo.compute_disparity's sub-pixel modes) side by side in one run, on the dense
VGA frames of bench/map_vs_octomap.py (same scene, same poses) with the renderer's true depth.

Per mode ('sgbm': SGBM's own sub-pixel disparity; 'equalise': equalize_subpixel of it;
'shift2' / 'shift4': phase_averaged_disparity, the mean over 2 / 4 sub-pixel shifts of the
right image), with the time per frame (one thread; read the ratios) and: the
share of disparities within 1/8 px of an integer (25 % if the sub-pixel part were uniform), the
mean disparity error in 8 bins of the TRUE sub-pixel part and its swing (max - min; a
locking-free matcher has none), the disparity error's mean and RMS, the range error RMS and its
ratio to the Eq. 3-7 model's sigma (0.5 px), over pixels with a valid disparity and
|error| < 2 px (the rest are counted as gross mismatches); and the valid pixels and RMS error in
the left 64 columns (the search range), which SGBM leaves invalid and compute_disparity's
`full_width` recovers by padding and a left-right check (the rows: every mode without it, and
the default, shift4 with it).

Then, for each mode, the error of the points normal to the true surface (the distance the map's
surface error measures), by band of true depth: its RMS, and its systematic part, the RMS of its
mean over 31 x 31 px windows at 640 px width (scaled with the width; what no averaging of
neighbouring points or voxels removes; with the random part of a window's mean, about
RMS / sqrt(38) for SGBM's 5 px blocks, still in it). Pixels at depth edges (a central
difference of the true depth above 3 % of it) are left out.

    bench/stereo_subpixel.py --json out/bench/stereo_subpixel.json
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')
sys.path.insert(0, str(Path(__file__).resolve().parent))

import cv2
import numpy as np
from map_vs_octomap import STEREO_POSES

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_mapping.render import TexturedScene, look_at
from coop_mapping.stereo import SUBPIXEL_DEFAULT, StereoCamera, compute_disparity
from coop_mapping.stereo import SUBPIXEL_MODES as MODES

N_BINS = 8
SEARCH_PX = 64
GROSS_PX = 2.0
SIGMA_D_MODEL_PX = 0.5


def frames(width: int, height: int, seed: int, supersample: int = 1):
    """(camera, [(left, right, true disparity)]) for every bench pose."""
    cam = StereoCamera.from_fov(width, height, np.radians(41.2), 0.038)
    out = []
    with TexturedScene(cam, seed=seed, supersample=supersample) as scene:
        for _, eye_xyz, target in STEREO_POSES:
            eye = np.asarray(eye_xyz, float)
            R = look_at(eye, np.asarray(target, float))
            left, right, depth = scene.render(R, eye)
            with np.errstate(divide='ignore', invalid='ignore'):
                d_true = cam.fx * cam.baseline / depth
            out.append((left, right, d_true))
    return cam, out


def disparities(images, mode: str, full_width: bool) -> tuple[list, float]:
    """[(measured, true disparity)] in `mode` and the mean time per frame (s)."""
    t0 = time.perf_counter()
    pairs = [(compute_disparity(left, right, num_disparities=SEARCH_PX, subpixel=mode,
                                full_width=full_width), d_true)
             for left, right, d_true in images]
    return pairs, (time.perf_counter() - t0) / len(images)


def stats(cam: StereoCamera, pairs) -> dict:
    meas = np.concatenate([m[np.isfinite(m) & np.isfinite(t)] for m, t in pairs])
    true = np.concatenate([t[np.isfinite(m) & np.isfinite(t)] for m, t in pairs])
    err = meas - true
    ok = np.abs(err) < GROSS_PX
    meas, true, err = meas[ok], true[ok], err[ok]
    frac_true = true - np.round(true) + 0.5                # in [0, 1)
    b = np.minimum((frac_true * N_BINS).astype(int), N_BINS - 1)
    per_bin = [float(np.mean(err[b == k])) for k in range(N_BINS)]
    z_true = cam.fx * cam.baseline / true
    z_meas = cam.fx * cam.baseline / meas
    sigma_model = z_true ** 2 * SIGMA_D_MODEL_PX / (cam.fx * cam.baseline)
    return {
        'pixels': int(ok.size), 'gross_share': float(1.0 - ok.mean()),
        'near_integer_share': float(np.mean(np.abs(meas - np.round(meas)) < 1.0 / 8)),
        'mean_error_by_true_subpixel_px': per_bin,
        'bias_swing_px': float(max(per_bin) - min(per_bin)),
        'mean_error_px': float(err.mean()),
        'rms_error_px': float(np.sqrt(np.mean(err ** 2))),
        'range_rms_error_m': float(np.sqrt(np.mean((z_meas - z_true) ** 2))),
        'range_rms_over_model': float(np.sqrt(np.mean(((z_meas - z_true) / sigma_model) ** 2))),
    }


DEPTH_BANDS_M = ((0.0, 3.0), (3.0, 5.0), (5.0, 7.0), (7.0, np.inf))
LOCAL_PX_AT_640 = 31


def local_px(width: int) -> int:
    """The systematic part's window: 31 px at 640 px width, the same share of other widths."""
    return 2 * max(2, round((LOCAL_PX_AT_640 - 1) / 2 * width / 640)) + 1


def normal_errors(cam: StereoCamera, pairs) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true depth, error normal to the true surface, its local mean over `local_px` windows)
    of every pixel with a valid disparity off depth edges and |disparity error| < GROSS_PX."""
    h, w = pairs[0][0].shape
    k = local_px(w)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    ray = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u)], -1)
    fxb = cam.fx * cam.baseline
    out = ([], [], [])
    for meas, true in pairs:
        with np.errstate(divide='ignore', invalid='ignore'):
            z_true, z_meas = fxb / true, fxb / meas
            p = z_true[..., None] * ray
            du, dv = np.zeros_like(p), np.zeros_like(p)
            du[:, 1:-1], dv[1:-1] = p[:, 2:] - p[:, :-2], p[2:] - p[:-2]
            n = np.cross(du, dv)
            n /= np.linalg.norm(n, axis=-1, keepdims=True)
            e_n = (z_meas - z_true) * np.sum(ray * n, -1)
            smooth = ((np.abs(np.gradient(z_true, axis=0)) < 0.03 * z_true)
                      & (np.abs(np.gradient(z_true, axis=1)) < 0.03 * z_true))
            ok = np.isfinite(e_n) & smooth & (np.abs(meas - true) < GROSS_PX)
        e0 = np.where(ok, e_n, 0.0).astype(np.float32)
        cnt = cv2.boxFilter(ok.astype(np.float32), -1, (k, k), normalize=False)
        tot = cv2.boxFilter(e0, -1, (k, k), normalize=False)
        full = ok & (cnt >= 0.5 * k ** 2)
        for acc, x in zip(out, (z_true[full], e_n[full], (tot / np.maximum(cnt, 1))[full]),
                          strict=False):
            acc.append(x)
    return tuple(np.concatenate(a) for a in out)


def normal_error_bands(cam: StereoCamera, pairs) -> list[dict]:
    """Per depth band (DEPTH_BANDS_M, then all): share of the scored pixels, RMS of the normal
    error and of its local mean (mm); NaN for a band with no pixel."""
    z, e, local = normal_errors(cam, pairs)

    def rms_mm(x: np.ndarray) -> float:
        return float(1e3 * np.sqrt(np.mean(x ** 2))) if x.size else float('nan')

    rows = []
    for lo, hi in (*DEPTH_BANDS_M, (0.0, np.inf)):
        m = (z >= lo) & (z < hi)
        rows.append({'depth_m': [lo, hi], 'pixels': int(m.sum()),
                     'share': float(m.mean()) if z.size else 0.0,
                     'rms_mm': rms_mm(e[m]), 'systematic_rms_mm': rms_mm(local[m])})
    return rows


def format_table(result: dict) -> str:
    """The tables main prints, from its JSON result (docs/results pages are made with it)."""
    cfg = result['config']
    res = {m: r for m, r in result.items() if m not in ('config', 'frames')}
    lines = [f'stereo sub-pixel accuracy: {result["frames"]} frames {cfg["width"]}x{cfg["height"]}'
             + (f' (rendered {cfg["supersample"]}x{cfg["supersample"]} per pixel)'
                if cfg['supersample'] > 1 else '') + ', '
             f'|error| < {GROSS_PX:g} px (gross mismatches: '
             + ', '.join(f'{m} {100 * res[m]["gross_share"]:.2f} %' for m in res) + ')']
    lines.append(f'{"mode":>10} {"valid px":>9} {"<1/8 px of int":>14} {"bias swing px":>13} '
                 f'{"mean px":>8} {"rms px":>7} {"range rms m":>11} {"/ Eq.3-7":>8} '
                 f'{"ms/frame":>8} {"left 64 px":>10} {"rms px":>6} {"gross":>6}')
    for m, r in res.items():
        lines.append(
            f'{m:>10} {r["pixels"]:9d} {100 * r["near_integer_share"]:13.1f}% '
            f'{r["bias_swing_px"]:13.3f} {r["mean_error_px"]:+8.3f} {r["rms_error_px"]:7.3f} '
            f'{r["range_rms_error_m"]:11.3f} {r["range_rms_over_model"]:8.2f} '
            f'{r["ms_per_frame"]:8.1f} {r["left_columns_valid_px"]:10d} '
            f'{r["left_columns_rms_error_px"]:6.3f} '
            f'{100 * r["left_columns_gross_share"]:5.2f}%')
    lines.append('mean error (px) by true sub-pixel part, bins of 1/8 from -0.5:')
    for m in res:
        bins = res[m]['mean_error_by_true_subpixel_px']
        lines.append(f'{m:>10} ' + ' '.join(f'{v:+.3f}' for v in bins))
    k = local_px(cfg['width'])
    lines.append(f'error normal to the true surface (mm): RMS / systematic (mean over {k} x {k} '
                 'px), share of the scored pixels, by band of true depth:')
    first = res[next(iter(res))]['normal_error_by_depth']
    bands = [tuple(b['depth_m']) for b in first]

    def band(lo: float, hi: float) -> str:
        return 'all' if (lo, hi) == (0.0, np.inf) else f'{lo:g}-{hi:g} m'

    lines.append(f'{"mode":>10} ' + ' '.join(f'{band(*b):>17}' for b in bands))
    lines.append(f'{"share":>10} ' + ' '.join(f'{100 * b["share"]:16.0f}%' for b in first))
    for m in res:
        lines.append(f'{m:>10} ' + ' '.join(
            f'{b["rms_mm"]:8.1f} / {b["systematic_rms_mm"]:5.1f}'
            for b in res[m]['normal_error_by_depth']))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('--width', type=number(int, lo=SEARCH_PX + 1, hi=4096), default=640)
    ap.add_argument('--height', type=number(int, lo=32, hi=4096), default=480)
    ap.add_argument('--seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    ap.add_argument('--supersample', type=int, choices=(1, 3, 5, 7), default=1,
                    help='render at k x k (odd k) samples per pixel, area averaged '
                    '(render.TexturedScene: pixel integration, no texture aliasing)')
    ap.add_argument('--json', type=output_path, default=None)
    args = ap.parse_args(argv)
    cv2.setNumThreads(1)                 # the times are per frame on one thread
    cam, images = frames(args.width, args.height, args.seed, args.supersample)
    res = {}
    rows = [(m, m, False) for m in MODES] + [(f'{SUBPIXEL_DEFAULT}+fw', SUBPIXEL_DEFAULT, True)]
    for label, m, fw in rows:
        pairs, dt = disparities(images, m, fw)
        edge = (stats(cam, [(d[:, :SEARCH_PX], t[:, :SEARCH_PX]) for d, t in pairs]) if fw
                else {'pixels': 0, 'rms_error_px': float('nan'), 'gross_share': float('nan')})
        res[label] = stats(cam, pairs) | {'ms_per_frame': 1e3 * dt, 'full_width': fw,
                                          'normal_error_by_depth': normal_error_bands(cam, pairs),
                                          'left_columns_valid_px': edge['pixels'],
                                          'left_columns_rms_error_px': edge['rms_error_px'],
                                          'left_columns_gross_share': edge['gross_share']}
    result = {'config': vars(args) | {'json': str(args.json)}, 'frames': len(pairs), **res}
    print(format_table(result))
    if args.json:
        write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
