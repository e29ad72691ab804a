#!/usr/bin/env python3
"""coop_mapping VoxelMap vs OctoMap (octomap-python, one thread), side by side on the same scans.

Same hit/miss/clamp model (OctoMap's defaults), same end points, same origins. Two data sets:
  synthetic: rays from three origins to a ground plane (300k points per scan),
  stereo:    dense VGA stereo frames of a textured PyBullet scene from two "rovers" (StereoSGBM,
             points with the Eq. 3-7 covariances; noise sigma ~ L^2).
Per resolution (0.1 m, 0.05 m): points/s of both (best of --repeats, interleaved), speedup,
state agreement (fraction of the union of known voxels with the same free/occupied/unknown
state), bytes per known voxel (ours: every per-voxel array; OctoMap's memoryUsage() per leaf for
reference), frame latency (VGA stereo frame insert), RMS surface error (distance to the true
surface of each map's surface estimate, ours the voxel's merged Gaussian mean, OctoMap's the leaf
centre, over the same voxels for both: every voxel occupied in both maps, the ones of those the
true surface passes through, and those of the latter where the predicted stereo sigma is below
the voxel size; see surface_errors; pooled over several placements of the scene in the grid,
see grid_offsets; the stereo surface voxels also by range from the nearest camera), and two
rovers' maps fused vs every scan in one map. The printed tables are `format_table` of the JSON
`--json` writes.

    bench/map_vs_octomap.py --json out/bench/map_vs_octomap.json
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
os.environ.setdefault('OMP_NUM_THREADS', '1')

import numpy as np

try:
    import coop_mapping  # noqa: F401
except ImportError:  # run from a source checkout before the package is built
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'src' / 'coop_mapping'))

import octomap
from scipy.spatial import cKDTree

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_mapping.octomap_peer import leaf_states
from coop_mapping.render import TexturedScene, look_at
from coop_mapping.stereo import (
    FULL_WIDTH_DEFAULT,
    SUBPIXEL_DEFAULT,
    SUBPIXEL_MODES,
    StereoCamera,
    StereoRanger,
)
from coop_mapping.voxelmap import (
    OCCUPIED,
    SURFACE_BANDWIDTH,
    SURFACE_RADIUS,
    VoxelMap,
    kernel_centroids,
    pack_keys,
    state_agreement,
    unpack_keys,
)

PLANE_Z = 0.013
#: the kernel surface query's settings (VoxelMap.surface_points' defaults)
KERNEL_BANDWIDTH, KERNEL_RADIUS = SURFACE_BANDWIDTH, SURFACE_RADIUS
#: Eq. 3-6/3-7 range-noise constant of the VGA camera (0.5 px, f = 851 px, b = 38 mm)
S_VGA = 0.5 / (851.3 * 0.038)


#: the stereo frames' camera poses: (rover, eye, look-at target) in the scene's frame
STEREO_POSES = (
    ('rover1', (0.0, -0.6, 1.1), (3.5, -0.4, 0.2)),
    ('rover2', (0.2, 0.8, 1.2), (3.8, 0.5, 0.3)),
    ('rover1', (0.5, -0.2, 1.0), (4.0, 0.3, 0.4)),
    ('rover2', (0.4, 0.4, 1.3), (4.5, -0.5, 0.5)),
)


def synthetic_scans(n_points: int, seed: int = 0):
    """Rays from three origins to the plane z = PLANE_Z, the end points moved along the ray by
    range noise sigma = S L^2 (Eq. 3-7, lateral sigma a tenth of it) with their covariances."""
    rng = np.random.default_rng(seed)
    scans = []
    for i in range(3):
        origin = np.array([0.03 + 0.3 * i, 0.02, 1.0])
        d = rng.normal(size=(n_points, 3))
        d[:, 2] = -np.abs(d[:, 2]) * 0.5 - 0.05
        d /= np.linalg.norm(d, axis=1)[:, None]
        L = (PLANE_Z - origin[2]) / d[:, 2]
        keep = L < 8.0
        d, L = d[keep], L[keep]
        sr = S_VGA * L * L
        sl = 0.1 * sr
        pts = origin + d * (L + rng.normal(size=L.shape) * sr)[:, None]
        lat = rng.normal(size=d.shape) * sl[:, None]
        pts += lat - d * np.sum(lat * d, 1)[:, None]
        dd = np.einsum('ni,nj->nij', d, d)
        cov = (sr ** 2 - sl ** 2)[:, None, None] * dd + (sl ** 2)[:, None, None] * np.eye(3)
        cov6 = cov.reshape(-1, 9)[:, [0, 1, 2, 4, 5, 8]]
        scans.append((pts, origin, f'rover{1 + i % 2}', cov6))
    return scans


def stereo_scans(width: int, height: int, seed: int = 0, subpixel: str = SUBPIXEL_DEFAULT,
                 full_width: bool = FULL_WIDTH_DEFAULT, supersample: int = 1):
    cam = StereoCamera.from_fov(width, height, np.radians(41.2), 0.038)
    ranger = StereoRanger(cam, num_disparities=64, max_range=10.0, subpixel=subpixel,
                          full_width=full_width)
    scans, truth = [], []
    with TexturedScene(cam, seed=seed, supersample=supersample) as scene:
        for rover, eye_xyz, target in STEREO_POSES:
            eye = np.asarray(eye_xyz, float)
            R = look_at(eye, np.asarray(target, float))
            left, right, depth = scene.render(R, eye)
            s = ranger.process(left, right, R, eye)
            scans.append((s.points, s.origin, rover, s.covariances))
            truth.append(scene.true_points(depth, R, eye, stride=1))
    return scans, np.concatenate(truth)


def agreement(vm: VoxelMap, tree, res: float) -> float:
    return state_agreement(vm.keys, vm.states(), *leaf_states(tree, res))


def run_ours(scans, res, with_cov, ray_subdivision=4):
    vm = VoxelMap(res, ray_subdivision=ray_subdivision)
    lat = []
    t0 = time.perf_counter()
    for sc in scans:
        t1 = time.perf_counter()
        vm.insert_scan(sc[0], sc[1], source=sc[2],
                       covariances=sc[3] if with_cov and len(sc) > 3 else None)
        lat.append(time.perf_counter() - t1)
    return vm, time.perf_counter() - t0, lat


def run_octomap(scans, res):
    tree = octomap.OcTree(res)
    t0 = time.perf_counter()
    for sc in scans:
        tree.insertPointCloud(sc[0], sc[1])
    return tree, time.perf_counter() - t0


def compare(scans, res, repeats, with_cov):
    n = sum(len(s[0]) for s in scans)
    best_ours, best_oct, lat = np.inf, np.inf, None
    vm = tree = None
    for _ in range(repeats):  # interleaved so a busy machine hurts both alike
        vm, t, la = run_ours(scans, res, with_cov)
        if t < best_ours:
            best_ours, lat = t, la
        tree, t = run_octomap(scans, res)
        best_oct = min(best_oct, t)
    return {
        'points': n,
        'ours_points_per_s': n / best_ours,
        'octomap_points_per_s': n / best_oct,
        'speedup': best_oct / best_ours,
        'state_agreement': agreement(vm, tree, res),
        'bytes_per_known_voxel': vm.bytes_per_known_voxel(),
        'octomap_bytes_per_leaf': tree.memoryUsage() / max(tree.getNumLeafNodes(), 1),
        'known_voxels': len(vm),
        'frame_latency_ms': 1e3 * float(np.median(lat)),
    }, vm, tree


def surface_errors(vm: VoxelMap, tree, res: float, dist, surface_keys, origins,
                   literal: VoxelMap) -> dict:
    """Distance to the true surface of each map's surface estimate: ours the voxel's merged
    Gaussian mean, OctoMap's the leaf centre (all it stores), over the same voxels for both:
      all:     every voxel occupied in both maps (noise voxels off the surface included);
      surface: the occupied-in-both voxels that the true surface passes through
               (`surface_keys`), where an estimate inside the voxel can be right or wrong;
      near:    those surface voxels whose predicted stereo sigma (Eq. 3-7, S L^2 with L the
               distance to the nearest scan origin) is below the voxel size.
    `literal`: the same scans merged with Eq. 3-10 on the raw point covariances only
    (voxel_prior=False), for the effect of the voxel-extent model.
    Returns, per class, the per-voxel errors (m) of ours, OctoMap's, the literal map's, ours
    by the kernel surface query (VoxelMap.surface_points) and the same kernel over OctoMap's
    occupied leaf centres (each weighing 1: what smoothing alone does for a map without
    means); and `surface_range_m`, each surface voxel's distance to the nearest scan origin."""
    keys, mean, _, _ = vm.gaussians()
    ok, ostate = leaf_states(tree, res)
    both = (vm.state_of_keys(keys) == OCCUPIED) & np.isin(keys, ok[ostate == OCCUPIED])
    keys, mean = keys[both], mean[both]
    _, mean_lit, _, _ = literal.gaussians(keys)
    _, kern = vm.surface_points(keys, bandwidth=KERNEL_BANDWIDTH, radius=KERNEL_RADIUS)
    occ = np.sort(ok[ostate == OCCUPIED])
    octo_kern = kernel_centroids(occ, (unpack_keys(occ) + 0.5) * res, np.ones(len(occ)), keys,
                                 bandwidth=KERNEL_BANDWIDTH, radius=KERNEL_RADIUS)
    centre = (unpack_keys(keys) + 0.5) * res
    e = np.stack([dist(mean), dist(centre), dist(mean_lit), dist(kern), dist(octo_kern)])
    surf = np.isin(keys, surface_keys)
    L = np.min(np.linalg.norm(centre[:, None, :] - np.asarray(origins)[None], axis=2), axis=1)
    near = surf & (res > S_VGA * L * L)
    return {'all': e, 'surface': e[:, surf], 'near': e[:, near], 'off_surface': e[:, ~surf],
            'surface_range_m': L[surf]}


#: range bands (m from the nearest scan origin) of the surface-error breakdown
SURFACE_RANGE_BANDS_M = ((0.0, 3.0), (3.0, 5.0), (5.0, 7.0), (7.0, 100.0))


def grid_offsets(res: float, n: int, seed: int = 0) -> np.ndarray:
    """N seeded offsets uniform in [0, res)^3. A map's error depends on where the surfaces fall
    in their voxels: a plane on voxel faces puts every leaf centre res/2 from it (OctoMap's
    worst case), one through the centres puts them on it (its best). The stereo scene as built
    has its box faces and ground on voxel faces, so it is not one of the placements (before
    session 7 it was, as one of 4, which favoured the Gaussian means): the surface error is
    pooled over n random placements of the same scene in the grid."""
    return np.random.default_rng(seed).uniform(0.0, res, (max(n, 1), 3))


def surface_error_study(scans, res: float, offsets: np.ndarray, truth=None) -> dict:
    """surface_errors with the scene (points, origins and truth) shifted by each offset, pooled:
    RMS over the voxels of every placement, and each placement's ratio. truth None: the
    synthetic plane z = PLANE_Z; else the true surface points (nearest-point distance)."""
    per: dict[str, list[np.ndarray]] = {}
    ratios: dict[str, list[float]] = {}
    ratios_k: dict[str, list[float]] = {}
    ranges: list[np.ndarray] = []
    for off in offsets:
        sh = [(sc[0] + off, sc[1] + off, sc[2], sc[3]) for sc in scans]
        vm = VoxelMap(res)
        tree = octomap.OcTree(res)
        for sc in sh:
            vm.insert_scan(sc[0], sc[1], source=sc[2], covariances=sc[3])
            tree.insertPointCloud(sc[0], sc[1])
        if truth is None:
            z = PLANE_Z + off[2]
            ks = unpack_keys(vm.keys)
            skeys = vm.keys[ks[:, 2] == int(np.floor(z / res))]
            def dist(p, z=z):
                return np.abs(p[:, 2] - z)
        else:
            tt = cKDTree(truth + off)
            skeys = np.unique(pack_keys(np.floor((truth + off) / res).astype(np.int64)))
            def dist(p, tt=tt):
                return tt.query(p)[0]
        errs = surface_errors(vm, tree, res, dist, skeys, [sc[1] for sc in sh],
                              literal_map(sh, res))
        ranges.append(errs.pop('surface_range_m'))
        for name, e in errs.items():
            per.setdefault(name, []).append(e)
            if e.shape[1]:
                r = np.sqrt(np.mean(e ** 2, axis=1))
                ratios.setdefault(name, []).append(float(r[0] / r[1]))
                ratios_k.setdefault(name, []).append(float(r[3] / r[1]))
    out = {'grid_offsets_m': offsets.tolist()}
    for name in ('all', 'surface', 'near'):
        e = np.concatenate(per[name], axis=1)
        n = e.shape[1]
        rms = np.sqrt(np.mean(e ** 2, axis=1)) if n else np.full(5, np.nan)
        out[name] = {'voxels': int(n), 'rms_ours_m': float(rms[0]),
                     'rms_octomap_m': float(rms[1]), 'rms_ours_literal_eq_3_10_m': float(rms[2]),
                     'ratio': float(rms[0] / rms[1]),
                     'ratio_per_offset': ratios.get(name, []),
                     'rms_ours_kernel_m': float(rms[3]), 'rms_octomap_kernel_m': float(rms[4]),
                     'kernel_ratio': float(rms[3] / rms[1]),
                     'kernel_ratio_per_offset': ratios_k.get(name, [])}
    # the surface voxels by range from the nearest camera: where the estimate can beat the centre
    e, rng = np.concatenate(per['surface'], axis=1), np.concatenate(ranges)
    out['surface']['by_range'] = []
    for lo, hi in SURFACE_RANGE_BANDS_M:
        m = (rng >= lo) & (rng < hi)
        rms = np.sqrt(np.mean(e[:, m] ** 2, axis=1)) if m.any() else np.full(5, np.nan)
        out['surface']['by_range'].append({
            'range_m': [lo, hi], 'voxels': int(m.sum()), 'rms_ours_m': float(rms[0]),
            'rms_octomap_m': float(rms[1]), 'rms_ours_kernel_m': float(rms[3]),
            'ratio': float(rms[0] / rms[1]), 'kernel_ratio': float(rms[3] / rms[1])})
    # how much of the all-voxel squared error the voxels off the surface carry (same for both)
    off_sq = sum(float(np.sum(e[1] ** 2)) for e in per['off_surface'])
    all_sq = sum(float(np.sum(e[1] ** 2)) for e in per['all'])
    out['all']['off_surface_share_of_octomap_mse'] = off_sq / max(all_sq, 1e-300)
    return out


def literal_map(scans, res) -> VoxelMap:
    vm = VoxelMap(res, voxel_prior=False)
    for sc in scans:
        vm.insert_scan(sc[0], sc[1], source=sc[2], covariances=sc[3])
    return vm


def fused_vs_single(scans, res) -> float:
    maps = {}
    single = VoxelMap(res)
    for sc in scans:
        maps.setdefault(sc[2], VoxelMap(res)).insert_scan(sc[0], sc[1], source=sc[2],
                                                          covariances=sc[3])
        single.insert_scan(sc[0], sc[1], source=sc[2], covariances=sc[3])
    names = sorted(maps)
    fused = maps[names[0]]
    for name in names[1:]:
        fused.merge_map(maps[name])
    keys = np.union1d(fused.keys, single.keys)
    return float(np.mean(fused.state_of_keys(keys) != single.state_of_keys(keys)))


def format_table(res: dict) -> str:
    """The tables main prints, from its JSON result."""
    w, h = res['image']
    ss = res.get('supersample', 1)
    lines = [f"stereo: {res['stereo_frames']} frames {w}x{h} (sub-pixel: {res['subpixel']}"
             f"{', full width' if res['full_width'] else ', without the left 64 columns'}"
             f"{f', rendered {ss}x{ss} per pixel' if ss != 1 else ''}), "
             f"{res['stereo_points']} points; synthetic: {res['synthetic_scans']} scans, "
             f"{res['synthetic_points']} points; best of {res['repeats']}",
             f'{"res m":>6} {"data":>9} {"ours Mpt/s":>10} {"octo Mpt/s":>10} {"speedup":>7} '
             f'{"agree":>7} {"B/voxel":>7} {"frame ms":>8}']
    for k, rec in res['resolutions'].items():
        for name, r in (('synthetic', rec['synthetic']), ('stereo', rec['stereo']),
                        ('all', rec)):
            lines.append(f'{k:>6} {name:>9} {r["ours_points_per_s"] / 1e6:10.3f} '
                         f'{r["octomap_points_per_s"] / 1e6:10.3f} {r["speedup"]:7.2f} '
                         f'{r["state_agreement"]:7.4f} {r["bytes_per_known_voxel"]:7.1f} '
                         f'{r["frame_latency_ms"]:8.1f}')
    kern = res['kernel']
    lines.append('surface error: RMS distance to the true surface of the estimate of each map '
                 '(ours: merged Gaussian mean; octo: voxel centre; lit: ours with Eq. 3-10 on '
                 'raw point covariances), same voxels for both, pooled over '
                 f"{res['grid_offsets']} placements of the scene in the grid (seeded random "
                 'offsets); ratio range: per placement; kern: the kernel surface query '
                 f"(VoxelMap.surface_points, bandwidth {kern['bandwidth_voxels']:g} voxel, "
                 f"radius {kern['radius_voxels']}), its ratio to octo; octo kern: the same "
                 "kernel over OctoMap's occupied leaf centres")
    lines.append(f'{"res m":>6} {"data":>9} {"voxels":>8} {"n":>7} {"ours mm":>8} '
                 f'{"octo mm":>8} {"ratio":>6} {"ratio range":>11} {"lit mm":>7} '
                 f'{"lit ratio":>9} {"kern mm":>7} {"kern ratio":>10} {"kern range":>10} '
                 f'{"octo kern mm":>12}')
    for k, r in res['resolutions'].items():
        for name in ('synthetic', 'stereo'):
            for vs in ('all', 'surface', 'near'):
                q = r[name]['surface_error'][vs]
                rr = q['ratio_per_offset']
                rng_s = f'{min(rr):.2f}-{max(rr):.2f}' if rr else '-'
                rk = q['kernel_ratio_per_offset']
                rng_k = f'{min(rk):.2f}-{max(rk):.2f}' if rk else '-'
                lines.append(
                    f'{k:>6} {name:>9} {vs:>8} {q["voxels"]:7d} '
                    f'{1e3 * q["rms_ours_m"]:8.1f} {1e3 * q["rms_octomap_m"]:8.1f} '
                    f'{q["ratio"]:6.2f} {rng_s:>11} {1e3 * q["rms_ours_literal_eq_3_10_m"]:7.1f} '
                    f'{q["rms_ours_literal_eq_3_10_m"] / q["rms_octomap_m"]:9.2f} '
                    f'{1e3 * q["rms_ours_kernel_m"]:7.1f} {q["kernel_ratio"]:10.2f} '
                    f'{rng_k:>10} {1e3 * q["rms_octomap_kernel_m"]:12.1f}')
    lines.append('stereo surface voxels by range from the nearest camera (the same voxels as '
                 "the 'surface' rows): voxels, ours / octo / kern mm, ratio, kern ratio")
    bands = [b['range_m'] for b in next(iter(res['resolutions'].values()))[
        'stereo']['surface_error']['surface']['by_range']]
    lines.append(f'{"res m":>6} ' + ' '.join(f'{f"{lo:g}-{hi:g} m":>34}' for lo, hi in bands))
    for k, r in res['resolutions'].items():
        cells = []
        for b in r['stereo']['surface_error']['surface']['by_range']:
            cells.append(f'{b["voxels"]:6d} {1e3 * b["rms_ours_m"]:5.1f}/'
                         f'{1e3 * b["rms_octomap_m"]:4.1f}/{1e3 * b["rms_ours_kernel_m"]:4.1f} '
                         f'{b["ratio"]:4.2f} {b["kernel_ratio"]:4.2f}')
        lines.append(f'{k:>6} ' + ' '.join(f'{c:>34}' for c in cells))
    lines.append(f'{"res m":>6} {"data":>9} {"off-surface share of all-voxel MSE":>36} '
                 f'{"fused!=single":>13} {"octo B/leaf":>11}')
    for k, r in res['resolutions'].items():
        for name in ('synthetic', 'stereo'):
            q = r[name]
            share = q['surface_error']['all']['off_surface_share_of_octomap_mse']
            lines.append(f'{k:>6} {name:>9} {100 * share:35.1f}% '
                         f'{100 * r["fused_vs_single_differ"]:12.3f}% '
                         f'{q["octomap_bytes_per_leaf"]:11.1f}')
    lines.append(f'{"res m":>6} {"ray_subdivision":>15} {"ours Mpt/s":>10} {"agree":>7}')
    for key, r in res['ray_subdivision'].items():
        k, sub = key.split('/')
        lines.append(f'{k:>6} {int(sub):>15d} {r["ours_points_per_s"] / 1e6:10.3f} '
                     f'{r["state_agreement"]:7.4f}')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, help='write the results here')
    ap.add_argument('--repeats', type=number(int, lo=1, hi=100), default=2)
    ap.add_argument('--points', type=number(int, lo=1, hi=10 ** 8), default=300_000,
                    help='synthetic points per scan')
    ap.add_argument('--width', type=number(int, lo=65, hi=4096), default=640,
                    help='stereo frame width (px, more than the 64 px disparity range)')
    ap.add_argument('--height', type=number(int, lo=32, hi=4096), default=480)
    ap.add_argument('--resolutions', type=number(float, lo=0.01, hi=10.0), nargs='+',
                    default=[0.1, 0.05], help='voxel sizes (m)')
    ap.add_argument('--grid-offsets', type=number(int, lo=1, hi=1000), default=8,
                    help='placements of the scene in the grid the surface error is pooled '
                    'over: N seeded random offsets')
    ap.add_argument('--subpixel', choices=SUBPIXEL_MODES, default=SUBPIXEL_DEFAULT,
                    help="stereo sub-pixel disparity (stereo.compute_disparity): SGBM's own, "
                    'equalised, or the mean over 2 / 4 sub-pixel shifts of the right image; '
                    'bench/stereo_subpixel.py measures them')
    ap.add_argument('--full-width', action=argparse.BooleanOptionalAction,
                    default=FULL_WIDTH_DEFAULT,
                    help='range the left 64 columns of each frame too (stereo.compute_disparity)')
    ap.add_argument('--supersample', type=int, choices=(1, 3, 5, 7), default=1,
                    help='render the stereo frames at k x k (odd k) samples per pixel, area '
                    'averaged (render.TexturedScene: pixel integration, no texture aliasing)')
    args = ap.parse_args(argv)

    syn = synthetic_scans(args.points)
    st, truth = stereo_scans(args.width, args.height, subpixel=args.subpixel,
                             full_width=args.full_width, supersample=args.supersample)
    out = {'octomap_model': {'prob_hit': 0.7, 'prob_miss': 0.4, 'clamp_min': 0.1192,
                             'clamp_max': 0.971},
           'stereo_frames': len(st), 'image': [args.width, args.height], 'subpixel': args.subpixel,
           'full_width': args.full_width, 'supersample': args.supersample,
           'resolutions': {}}
    out |= {'repeats': args.repeats, 'grid_offsets': args.grid_offsets,
            'stereo_points': sum(len(sc[0]) for sc in st), 'synthetic_scans': len(syn),
            'synthetic_points': sum(len(sc[0]) for sc in syn),
            'kernel': {'bandwidth_voxels': KERNEL_BANDWIDTH, 'radius_voxels': KERNEL_RADIUS}}
    for res in args.resolutions:
        r_syn, _, _ = compare(syn, res, args.repeats, with_cov=True)
        offsets = grid_offsets(res, args.grid_offsets)
        r_syn['surface_error'] = surface_error_study(syn, res, offsets)
        r_st, vm, tree = compare(st, res, args.repeats, with_cov=True)
        r_st['surface_error'] = surface_error_study(st, res, offsets, truth)
        for r in (r_syn, r_st):
            r['rms_surface_error_m'] = r['surface_error']['surface']['rms_ours_m']
            r['octomap_rms_surface_error_m'] = r['surface_error']['surface']['rms_octomap_m']
        rms_ours, rms_oct = r_st['rms_surface_error_m'], r_st['octomap_rms_surface_error_m']
        n = r_syn['points'] + r_st['points']
        t_ours = r_syn['points'] / r_syn['ours_points_per_s'] + \
            r_st['points'] / r_st['ours_points_per_s']
        t_oct = r_syn['points'] / r_syn['octomap_points_per_s'] + \
            r_st['points'] / r_st['octomap_points_per_s']
        rec = {
            'ours_points_per_s': n / t_ours, 'octomap_points_per_s': n / t_oct,
            'speedup': t_oct / t_ours,
            'state_agreement': min(r_syn['state_agreement'], r_st['state_agreement']),
            'bytes_per_known_voxel': max(r_syn['bytes_per_known_voxel'],
                                         r_st['bytes_per_known_voxel']),
            'frame_latency_ms': r_st['frame_latency_ms'],
            'rms_surface_error_m': rms_ours, 'octomap_rms_surface_error_m': rms_oct,
            'rms_surface_error_ratio': rms_ours / rms_oct,
            'rms_surface_error_kernel_m': r_st['surface_error']['surface']['rms_ours_kernel_m'],
            'rms_surface_error_kernel_ratio':
                r_st['surface_error']['surface']['kernel_ratio'],
            'fused_vs_single_differ': fused_vs_single(st, res),
            'synthetic': r_syn, 'stereo': r_st,
        }
        out['resolutions'][f'{res:g}'] = rec
    # the ray_subdivision trade-off on the stereo frames (one run each)
    out['ray_subdivision'] = {}
    for res in args.resolutions:
        tree, _ = run_octomap(st, res)
        for sub in (1, 2, 4, 0):
            vm = VoxelMap(res, ray_subdivision=sub)
            t0 = time.perf_counter()
            for sc in st:
                vm.insert_scan(sc[0], sc[1], covariances=sc[3])
            rate = sum(len(sc[0]) for sc in st) / (time.perf_counter() - t0)
            out['ray_subdivision'][f'{res:g}/{sub}'] = {'ours_points_per_s': rate,
                                                       'state_agreement':
                                                           agreement(vm, tree, res)}
    print(format_table(out))
    if args.json:
        write_json(args.json, out, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
