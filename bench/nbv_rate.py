#!/usr/bin/env python3
"""Benchmark of coop_viewplan: 3-D NI scoring rate (candidate poses/s), next-best-view decision
time, and task-placement time (2-D study scene; 3-D map as the view planner node serves it);
batched scoring is compared with scoring one pose at a time (the peer) in the same run.
The printed table is `format_table` of the JSON `--json` writes.

Usage: bench/nbv_rate.py --json OUT"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from functools import partial
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'src' / 'coop_viewplan'))

import numpy as np

from coop_common.cli import number, output_path
from coop_common.files import write_json
from coop_viewplan.grid import OccupancyGrid, markov_estimate, occlusion_estimate
from coop_viewplan.nbv import CameraState, InfoLookup, NbvConfig, NextBestViewPlanner, score_views
from coop_viewplan.params import PARAMS as NODE_SPECS
from coop_viewplan.placement import (
    CameraModel,
    PlacementError,
    Target,
    TaskPlacer,
    mast_stations,
)
from coop_viewplan.task_study import StudyConfig, make_scenario


def world_3d(rng: np.random.Generator, *, size_m: float = 24.0, height_m: float = 3.0,
             res: float = 0.1) -> OccupancyGrid:
    """A 0.1 m map: ground, 30 boxes, the west half known (free/occupied), the rest unknown."""
    n, h = int(size_m / res), int(height_m / res)
    occ = np.zeros((n, n, h), bool)
    occ[:, :, 0] = True
    for _ in range(30):
        x, y = rng.integers(0, n - 20, 2)
        w, d = rng.integers(5, 20, 2)
        occ[x:x + w, y:y + d, :rng.integers(5, h)] = True
    g = OccupancyGrid.empty(occ.shape, resolution=res)
    g.known[: n // 2] = True
    g.prob[: n // 2] = occ[: n // 2].astype(np.float32)
    return g


def timed(fn, repeat: int = 3) -> float:
    best = np.inf
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result."""
    nan = float('nan')
    lines = [f"{'benchmark':78s} {'poses/s':>9s} {'peer/s':>8s} {'ratio':>6s} {'seconds':>8s}"]
    for r in result['rows']:
        lines.append(f"{r['what']:78s} {r.get('poses_per_s', nan):9.0f} "
                     f"{r.get('peer_one_at_a_time_poses_per_s', nan):8.0f} "
                     f"{r.get('speedup', nan):6.1f} {r.get('seconds', nan):8.3f}")
    lines.append(f"task placement 3-D outcomes: {result['task_placement_3d_outcomes']}")
    if 'load_average' in result:
        la = result['load_average']
        lines.append(f'load average at the end {la[0]:.1f}, {la[1]:.1f}, {la[2]:.1f} '
                     f'(1, 5, 15 min), {result.get("cpus", "?")} cores')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('.')[0])
    p.add_argument('--json', type=output_path, default=None)
    p.add_argument('--poses', type=number(int, lo=1, hi=10 ** 6), default=400)
    args = p.parse_args(argv)
    rng = np.random.default_rng(0)
    g = world_3d(rng)
    est = markov_estimate(g)
    rows = []
    free = np.argwhere(g.free()[:, :, 10])
    cells = free[rng.choice(len(free), args.poses)]
    pos = np.c_[g.to_world(np.c_[cells, np.full(len(cells), 10)])]
    yaw = rng.uniform(0, 2 * np.pi, args.poses)
    pitch = rng.uniform(-0.3, 0.3, args.poses)
    for label, n_az, n_el, step in (('24x18 rays, 0.1 m steps', 24, 18, 1.0),
                                    ('32x24 rays, 0.05 m steps', 32, 24, 0.5)):
        cfg = NbvConfig(fov_deg=75, depth_m=10, n_az=n_az, n_el=n_el, step_cells=step)
        tpl = cfg.template(ndim=3, resolution=g.resolution)
        lk = InfoLookup.build(g, est)      # once per map, timed separately below
        t_batch = timed(partial(score_views, g, est, pos, yaw, pitch, tpl, lookup=lk))
        k = 40
        t_one = timed(lambda tpl=tpl, lk=lk, k=k: [
            score_views(g, est, pos[i:i + 1], yaw[i:i + 1], pitch[i:i + 1], tpl, lookup=lk)
            for i in range(k)], repeat=1)
        rows.append({'what': f'NI scoring 3-D, {label}', 'samples_per_pose': int(tpl.weights.size),
                     'poses_per_s': args.poses / t_batch, 'peer_one_at_a_time_poses_per_s':
                     k / t_one, 'speedup': (args.poses / t_batch) / (k / t_one)})
        # the opt-in occlusion-aware expected view (NbvConfig.unknown_occlusion='expected')
        occ = occlusion_estimate(g, prior='density')
        t_occ = timed(partial(score_views, g, est, pos, yaw, pitch, tpl, lookup=lk,
                              occlusion=occ))
        rows.append({'what': f'NI scoring 3-D, {label}, unknown space occludes (expected)',
                     'samples_per_pose': int(tpl.weights.size),
                     'poses_per_s': args.poses / t_occ,
                     'ratio_to_histogram_ni': t_batch / t_occ})
        if step == 1.0:   # App. C's predictor-5 NI on the same poses (NbvConfig.ni_measure)
            t_p5 = timed(partial(score_views, g, est, pos, yaw, pitch, tpl, lookup=lk,
                                 measure='predictor5'))
            rows.append({'what': f'NI scoring 3-D, {label}, predictor-5 NI (App. C)',
                         'samples_per_pose': int(tpl.weights.size),
                         'poses_per_s': args.poses / t_p5,
                         'ratio_to_histogram_ni': t_batch / t_p5})
    t_map = timed(lambda: InfoLookup.build(g, markov_estimate(g)))
    rows.append({'what': f'per-map preparation (Markov estimate + tables, {g.prob.size} cells)',
                 'seconds': t_map})
    t_occ_map = timed(lambda: occlusion_estimate(g, prior='density'))
    rows.append({'what': '  + occlusion estimate (density prior) for unknown_occlusion expected',
                 'seconds': t_occ_map})
    cfg = NbvConfig(fov_deg=75, depth_m=10, n_az=24, n_el=18, step_cells=1.0, n_positions=40,
                    pitches_deg=(0.0,), camera_height_m=1.0)
    planner = NextBestViewPlanner(cfg)
    nav = planner.traversability(g).navigable
    start = np.argwhere(nav)[len(np.argwhere(nav)) // 2]
    cam = CameraState(g.to_world(np.r_[start, 10]))
    t_dec = timed(lambda: planner.plan(g, cam, strategy='max_information',
                                       rng=np.random.default_rng(1)), repeat=2)
    rows.append({'what': 'NBV decision 3-D (40 positions x 8 headings, 24x18 rays), all included',
                 'seconds': t_dec})
    # the node's constraint model on the live map (nbv 'evidence': obstacle columns block,
    # unknown does not, the camera voxel must be seen free)
    ev = NextBestViewPlanner(replace(cfg, reach_model='evidence', p_empty=0.2))
    t_ev = timed(lambda: ev.plan(g, cam, strategy='max_information',
                                 rng=np.random.default_rng(1), free_footprint=True), repeat=2)
    rows.append({'what': "NBV decision 3-D as above, node's 'evidence' reach model",
                 'seconds': t_ev})
    sc = make_scenario(np.random.default_rng(2), 0.20, StudyConfig())
    placer = TaskPlacer(CameraModel(fov_deg=60, pixels=640, near_m=1, far_m=20),
                        max_candidates=4000, n_dirs=720)
    sec = [Target(sc.secondary.position, sc.secondary.normal, radius=0.25, sigma=0.005)]
    t_pl = timed(lambda: placer.place(sc.grid, sc.primary, sec, rng=np.random.default_rng(3)),
                 repeat=2)
    rows.append({'what': 'task placement 2-D 60 m at 0.5 m, 20% occl., primary + secondary, '
                         '4000 candidates, 720 directions', 'seconds': t_pl})
    # task_view on a 3-D map as the node serves it: the camera on the mast (camera_height_m)
    # over the ground cells the 'evidence' model admits, the node's TaskPlacer defaults; first
    # requests (no cached field) for 8 seeded targets on seen-free voxels 0.6-1.0 m high
    d = {k: v.default for k, v in NODE_SPECS.items()}
    t0 = time.perf_counter()
    trav = ev.traversability(g)
    stations = mast_stations(g, trav.candidate, trav.collision_p, d['camera_height_m'])
    t_st = time.perf_counter() - t0
    rows.append({'what': 'task placement 3-D: mast stations (once per map)', 'seconds': t_st})
    free3 = np.argwhere(g.free())
    z = g.to_world(free3)[:, 2]
    pick = free3[(z > 0.6) & (z < 1.0)]
    pick = pick[np.random.default_rng(4).choice(len(pick), 8, replace=False)]
    times, outcomes = [], {}
    for k, cell in enumerate(pick):
        placer3 = TaskPlacer(CameraModel(fov_deg=d['task_fov_deg'], pixels=d['task_pixels'],
                                         near_m=d['task_near_m'], far_m=d['task_far_m']),
                             clearance_m=d['clearance_m'], p_empty=d['p_empty'],
                             max_candidates=d['task_candidates'], cache_fields=0)
        normal = np.r_[np.cos(k * np.pi / 2), np.sin(k * np.pi / 2), 0.0]
        tgt = Target(g.to_world(cell), normal, radius=0.05)
        t0 = time.perf_counter()
        try:
            placer3.place(g, tgt, rng=np.random.default_rng(k), stations=stations)
            outcome = 'placed'
        except PlacementError as exc:
            outcome = str(exc).split(' (')[0]
        times.append(time.perf_counter() - t0)
        outcomes[outcome] = outcomes.get(outcome, 0) + 1
    rows.append({'what': "task placement 3-D, node defaults, 8 targets' first requests: median",
                 'seconds': float(np.median(times)), 'max_seconds': float(np.max(times)),
                 'outcomes': outcomes})
    rows.append({'what': '  ... and the slowest', 'seconds': float(np.max(times))})
    result = {'rows': rows, 'task_placement_3d_outcomes': outcomes, 'poses': args.poses,
              'load_average': list(os.getloadavg()), 'cpus': os.cpu_count()}
    print(format_table(result))
    if args.json is not None:
        write_json(args.json, result, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
