"""What the BRAID mast buys in the Fig. 3-25 run (issue #37, deliverable 5): mapped voxels per
scan with maximum-information view selection, the same worlds and planner, once with the
rover's pan/tilt mast and once with a BRAID mast whose reachable views (BRAID IK,
`coop_viewplan.mast`) the planner proposes.

    python -m coop_viewplan.fig_3_25_braid --scans 10 --seeds 3 --json out/braid_mapping.json

Each run is `fig_3_25.run_strategy('max_information', ...)` on `rover_sim`'s world: the rover
drives to the chosen view, the mast is commanded (pan and tilt; or the turntable and the
chain's state, which takes effect after the mast's settle time), the stereo pair is rendered
from the camera's true pose (with BRAID the pan link times the chain's forward kinematics),
ranged, and fused. Both masts plan in one grid up to `--ceiling-m` (1.0 m, above the BRAID's
highest camera); the counted site is fig_3_25's (ground to 0.8 m). Scan 0 is each mast's own
start view (the pan/tilt head at 12 deg; BRAID its lowest view nearest 12 deg), so the table
also gives the voxels each planned scan added.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from coop_braid.mast import Tolerance
from coop_common.cli import number, output_dir, output_path
from coop_common.files import save_figure, write_json

from .fig_3_25 import Fig325Config, run_strategy
from .mast import PAN_HEIGHT_M, MastKind, braid_views

MASTS = (MastKind.PAN_TILT, MastKind.BRAID)
#: the control: the pan/tilt head offered the pitches of the BRAID's reached views
MATCHED = 'pan_tilt_matched'
#: the tolerance the views are kept within (braid_views' default)
TOL = Tolerance()
STRATEGY = 'max_information'


def run(cfg: Fig325Config, *, seeds: int, log: Callable[[str], None] | None = None
        ) -> dict[str, Any]:
    """Both masts over the seeds (worlds cfg.seed .. + seeds - 1): the JSON result."""
    out: dict[str, Any] = {'config': {k: (list(v) if isinstance(v, tuple) else v)
                                      for k, v in cfg.__dict__.items() if k != 'mast'},
                           'seeds': seeds, 'strategy': STRATEGY, 'masts': {}}
    bv = braid_views(cfg.braid_stages, pitches_deg=tuple(cfg.pitches_deg))
    out['braid_views'] = [
        {'height_m': v.height_m, 'forward_m': v.forward_m, 'lateral_m': v.lateral_m,
         'heading_deg': math.degrees(v.heading_rad), 'pitch_deg': math.degrees(v.pitch_rad),
         'states': s.tolist()} for v, s in zip(bv.views, bv.states, strict=True)]
    out['braid_tried'] = [
        {'height_above_pan_m': t.height_m, 'pitch_deg': math.degrees(t.pitch_rad),
         'pos_err_mm': 1e3 * t.pos_err_m, 'pitch_err_deg': math.degrees(t.pitch_err_rad),
         'roll_deg': math.degrees(t.roll_rad), 'reached': t.reached} for t in bv.tried]
    matched = tuple(sorted({round(math.degrees(v.pitch_rad), 2) for v in bv.views}))
    out['matched_pitches_deg'] = list(matched)
    runs_of = [(MastKind.PAN_TILT.value, MastKind.PAN_TILT, cfg.pitches_deg),
               (MastKind.BRAID.value, MastKind.BRAID, cfg.pitches_deg)]
    if any(min(abs(m - float(p)) for p in cfg.pitches_deg) > 0.1 for m in matched):
        runs_of.append((MATCHED, MastKind.PAN_TILT, matched))   # else pan_tilt's own pitches
    for name, mast, pitches in runs_of:
        c = Fig325Config(**{**cfg.__dict__, 'mast': mast, 'pitches_deg': tuple(pitches)})
        runs = [run_strategy(STRATEGY, c, seed=cfg.seed + s, log=log) for s in range(seeds)]
        col = {k: np.array([[r[k] for r in x['rows']] for x in runs], float)
               for k in ('known', 'occupied', 'known_all', 'distance_m')}
        out['masts'][name] = {
            'known_voxels_per_seed': col['known'].tolist(),
            'known_voxels': col['known'].mean(axis=0).tolist(),
            'known_voxels_all': col['known_all'].mean(axis=0).tolist(),
            'occupied_voxels': col['occupied'].mean(axis=0).tolist(),
            'distance_m': col['distance_m'].mean(axis=0).tolist(),
            'views': [x['views'] for x in runs],
            'poses': [x['poses'] for x in runs],
            'failures': [x['failures'] for x in runs],
            'plan_seconds': float(sum(x['plan_seconds'] for x in runs)),
            'seconds': float(sum(x['seconds'] for x in runs)),
        }
    return out


def format_table(res: dict[str, Any]) -> str:
    """The printed result: mapped voxels per scan for both masts, what each planned scan added,
    the BRAID views reached and chosen."""
    cfg, m = res['config'], res['masts']
    pt, br = m['pan_tilt'], m['braid']
    seeds = res['seeds']
    lines = [f"Fig. 3-25 run, pan/tilt vs BRAID mast ({cfg['braid_stages']} stages): rover_sim "
             f"seed {cfg['seed']}" + (f"..{cfg['seed'] + seeds - 1} (mean)" if seeds > 1 else '')
             + f", {cfg['rovers']} rover(s), {res['strategy']}, {cfg['n_positions']} positions "
             f"x {cfg['n_yaw']} headings per decision, pitches {cfg['pitches_deg']} deg, "
             f"planning grid to {cfg['ceiling_m']} m",
             f'BRAID views (IK, kept within {1e3 * TOL.position_m:.0f} mm / '
             f'{math.degrees(TOL.pitch_rad):.1f} deg pitch / {math.degrees(TOL.roll_rad):.0f} '
             'deg roll of the wanted view):']
    reached = iter(res['braid_views'])
    for t in res['braid_tried']:
        line = (f"  wanted {t['height_above_pan_m'] + PAN_HEIGHT_M:.2f} m, "
                f"{t['pitch_deg']:4.1f} deg: residual {t['pos_err_mm']:5.1f} mm, "
                f"pitch {t['pitch_err_deg']:.2f} deg, roll {t['roll_deg']:5.1f} deg -> ")
        if t['reached']:
            v = next(reached)
            line += (f"reached: {v['height_m']:.3f} m, pitch {v['pitch_deg']:.2f} deg, "
                     f"turntable offset {v['heading_deg']:5.2f} deg, camera "
                     f"{100 * math.hypot(v['forward_m'], v['lateral_m']):.1f} cm off the axis")
        else:
            line += 'NOT reached'
        lines.append(line)
    ctl = m.get(MATCHED)
    lines.append('mapped = known voxels of the site (12 m x 12 m, ground to 0.8 m); new = what '
                 'the scan added' + ('; p/t matched = the pan/tilt head offered the BRAID '
                                     "views' pitches " + str(res['matched_pitches_deg'])
                                     + ' deg' if ctl else ''))
    lines.append(f"{'scan':>4s} {'pan/tilt':>10s} {'BRAID':>10s} {'ratio':>6s}"
                 + (f" {'p/t matched':>12s}" if ctl else '')
                 + f" {'new p/t':>9s} {'new BRAID':>10s}" + (f" {'new matched':>12s}"
                                                             if ctl else ''))
    a, b = np.array(pt['known_voxels']), np.array(br['known_voxels'])
    c = np.array(ctl['known_voxels']) if ctl else None
    for k in range(len(a)):
        def new(x: np.ndarray, k: int = k) -> float:
            return float(x[k] - x[k - 1] if k else x[k])
        lines.append(f'{k:4d} {a[k]:10.0f} {b[k]:10.0f} {b[k] / max(a[k], 1):6.2f}'
                     + (f' {c[k]:12.0f}' if c is not None else '')
                     + f' {new(a):9.0f} {new(b):10.0f}'
                     + (f' {new(c):12.0f}' if c is not None else ''))
    per = {k: np.array(v['known_voxels_per_seed']) for k, v in m.items()}
    gain = {k: v[:, -1] - v[:, 0] for k, v in per.items()}
    names = {'pan_tilt': 'pan/tilt', 'braid': 'BRAID', MATCHED: 'p/t matched'}
    lines.append('added by the planned scans, per seed: ' + '; '.join(
        f'{names[k]} ' + ', '.join(f'{v:.0f}' for v in g) for k, g in gain.items())
        + f" (BRAID / pan-tilt {gain['braid'].sum() / max(gain['pan_tilt'].sum(), 1):.2f}"
        + (f", BRAID / p/t matched {gain['braid'].sum() / max(gain[MATCHED].sum(), 1):.2f}"
           if ctl else '') + ')')
    lines.append('last scan, per seed: ' + '; '.join(
        f'{names[k]} ' + ', '.join(f'{x:.0f}' for x in v[:, -1]) for k, v in per.items()))
    used = Counter(v for seed in br['views'] for rover in seed for v in rover)
    bv = res['braid_views']
    lines.append('BRAID views chosen (height m / pitch deg: scans): ' + ', '.join(
        f"{bv[v]['height_m']:.2f}/{bv[v]['pitch_deg']:.1f}: {n}"
        for v, n in sorted(used.items()) if v >= 0))
    lines.append('distance moved (m): ' + ', '.join(
        f"{names[k]} {v['distance_m'][-1]:.1f}" for k, v in m.items()) + '; planning failures: '
        + ', '.join(f"{names[k]} {sum(map(sum, v['failures']))}" for k, v in m.items())
        + '; planning time (s): ' + ', '.join(f"{names[k]} {v['plan_seconds']:.0f}"
                                              for k, v in m.items()))
    return '\n'.join(lines)


def plot(res: dict[str, Any], out_dir: Path) -> Path:
    """Mapped voxels and voxels added per scan, both masts; the file written."""
    import matplotlib  # noqa: PLC0415 - heavy, only when plots are asked for
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415 - heavy, only when plotting
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.2))
    for key, label in (('pan_tilt', 'pan/tilt mast'), ('braid', 'BRAID mast'),
                       (MATCHED, "pan/tilt mast, the BRAID's pitches")):
        if key not in res['masts']:
            continue
        v = res['masts'][key]
        per = np.array(v['known_voxels_per_seed'])
        ax[0].plot(per.mean(axis=0), marker='o', label=label)
        ax[0].fill_between(range(per.shape[1]), per.min(axis=0), per.max(axis=0), alpha=0.15)
        ax[1].plot(range(1, per.shape[1]), np.diff(per, axis=1).mean(axis=0), marker='o',
                   label=label)
    ax[0].set(xlabel='scan number', ylabel='known voxels in the site',
              title='mapped voxels (mean; band: min-max over seeds)')
    ax[1].set(xlabel='scan number', ylabel='voxels added by the scan (mean)',
              title='what each planned scan added')
    for a in ax:
        a.grid(alpha=0.3)
        a.legend()
    return save_figure(fig, out_dir / 'braid_mapping.png', dpi=110)


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_viewplan.fig_3_25_braid`: pan/tilt vs BRAID in the Fig. 3-25 run."""
    p = argparse.ArgumentParser(description='Fig. 3-25 run with the pan/tilt and the BRAID '
                                            'mast: mapped voxels per scan')
    d = Fig325Config()
    p.add_argument('--rovers', type=int, default=1, choices=(1, 2))
    p.add_argument('--scans', type=number(int, lo=1), default=d.scans)
    p.add_argument('--seed', type=number(int, lo=0), default=d.seed)
    p.add_argument('--seeds', type=number(int, lo=1), default=3)
    p.add_argument('--braid-stages', type=number(int, lo=1, hi=20), default=d.braid_stages)
    p.add_argument('--ceiling-m', type=number(lo=0.8, hi=3.0), default=1.0)
    p.add_argument('--candidates', type=number(int, lo=1), default=d.n_positions)
    p.add_argument('--pitches-deg', default=','.join(f'{v:g}' for v in d.pitches_deg),
                   help="the pan/tilt head's pitches and the BRAID's wanted ones (deg, "
                        'comma-separated)')
    p.add_argument('--json', type=output_path, default=None)
    p.add_argument('--plots', type=output_dir, default=None)
    p.add_argument('--from-json', type=Path, default=None,
                   help='print the table (and --plots) of a saved --json run')
    p.add_argument('--quiet', action='store_true')
    a = p.parse_args(argv)
    if a.from_json is not None:
        try:
            res = json.loads(a.from_json.read_text())
            print(format_table(res))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            p.error(f'--from-json {a.from_json}: {exc!r}')
        if a.plots is not None:
            print(f'plot: {plot(res, a.plots)}')
        return 0
    try:
        pitches = tuple(float(v) for v in a.pitches_deg.split(',') if v.strip())
    except ValueError:
        p.error(f'--pitches-deg {a.pitches_deg!r}: comma-separated numbers')
    if not pitches or not all(-60.0 <= v <= 60.0 for v in pitches):
        p.error(f'--pitches-deg {a.pitches_deg!r}: 1 or more pitches within +-60 deg')
    cfg = Fig325Config(rovers=a.rovers, scans=a.scans, seed=a.seed,
                       braid_stages=a.braid_stages, ceiling_m=a.ceiling_m,
                       n_positions=a.candidates, pitches_deg=pitches)
    log = None if a.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
    t0 = time.perf_counter()
    res = run(cfg, seeds=a.seeds, log=log)
    res['seconds'] = time.perf_counter() - t0
    print(format_table(res))
    print(f"({res['seconds']:.0f} s)")
    if a.plots is not None:
        print(f'plot: {plot(res, a.plots)}')
    if a.json is not None:
        write_json(a.json, res, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
