#!/usr/bin/env python3
"""Wall time of Table 5-1 attempts end to end: the insertion graph over DDS (coop_bringup.rig:
rover_sim, mapper with the scenario's site map, view_planner, master, slave), the medium slot
(4.5 in) by default, the master's camera placed by `task_view` (optimal) or at random; each
attempt as `coop_bringup table_5_1` runs it (the simulator reset to the slot with the slave's
start perturbed by the attempt's seed, one `insert` goal, the truth's verdict). The graph's
set-up (start, the master's survey) is timed apart. The simulator runs in lockstep with the
master, the slave and the rig (--no-lockstep: paced by the clock); --busy-too runs the same
seeds again on a fresh graph beside a process that keeps one core busy and compares the
outcomes (lockstep's claim: the same successes, the same peak forces). --composed runs the
master, the slave, the mapper and the view planner in one process (`coop_bringup compose`);
--composed-too runs the same seeds again so composed, on a fresh graph, and compares.

Usage: bench/attempt_rate.py --json OUT --site-map MAP [--attempts 10] [--slot 4.5]
       [--placement optimal] [--busy-too] [--no-lockstep]
       [--composed | --composed-too]

MAP: the scenario's site map (`coop_bringup.table_5_1.build_site_map`, seed 1, occlusion
0.05; without it the command builds one first, a few minutes).
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np

from coop_common.cli import number, output_path
from coop_common.files import write_json

SEED = 1
OCCLUSION = 0.05


def format_compose_table(result: dict) -> str:
    """The one-process-per-node / composed comparison --composed-too prints."""
    runs = (('one process per node', result), ('composed', result['composed_run']))
    lines = [f'{"layout":24}{"attempt wall (s)":>18}{"goal sim s/wall s":>19}{"set-up (s)":>12}'
             f'{"successes":>11}']
    for name, r in runs:
        n = len(r['attempt_wall_s']['values'])
        lines.append(f'{name:24}{r["attempt_wall_s"]["median"]:>18.1f}'
                     f'{r["sim_per_wall"]["median"]:>19.2f}{r["setup_wall_s"]:>12.0f}'
                     f'{r["successes"]:>8}/{n}')
    same = [(o['success'], o['peak_force_n']) for o in result['outcomes']] == \
        [(o['success'], o['peak_force_n']) for o in result['composed_run']['outcomes']]
    lines.append(f'composed / one per node, median attempt wall: '
                 f'{result["composed_wall_ratio"]:.2f}; the same outcomes and peak forces: '
                 f'{same}')
    return '\n'.join(lines)


def format_load_table(result: dict) -> str:
    """The idle/busy comparison --busy-too prints."""
    idle, busy = result['outcomes'], result['busy']['outcomes']
    lines = [f'{"seed":>6} {"idle":>8} {"busy":>8} {"peak F idle (N)":>16} '
             f'{"peak F busy (N)":>16} {"rel. diff":>10}']
    for a, b in zip(idle, busy, strict=False):
        rel = abs(a['peak_force_n'] - b['peak_force_n']) / max(abs(a['peak_force_n']), 1e-9)
        lines.append(f'{a["seed"]:>6} {("seated" if a["success"] else "failed"):>8} '
                     f'{("seated" if b["success"] else "failed"):>8} '
                     f'{a["peak_force_n"]:>16.6f} {b["peak_force_n"]:>16.6f} {rel:>10.2e}')
    lines.append(f'identical success lists: {result["identical_successes"]}; largest peak-force '
                 f'difference {result["peak_force_max_rel_diff"]:.2e} (target: identical, '
                 f'within 5 %)')
    return '\n'.join(lines)


def run_attempts(args, site_map: Path, work: Path, *, busy: bool, composed: bool) -> dict:
    """One graph, `args.attempts` attempts; wall times and each attempt's outcome."""
    from coop_bringup.table_5_1 import open_rig
    logs = 'logs' + ('_busy' if busy else '') + ('_composed' if composed else '')
    from coop_common.testing import busy_core
    with busy_core(busy):
        t0 = time.monotonic()
        rig = open_rig(seed=SEED, occlusion_density=OCCLUSION, slot_in=args.slot,
                       log_dir=work / logs, site_map=site_map,
                       render_workers=args.render_workers, lockstep=args.lockstep,
                       composed=composed)
        walls, goals, sims, outcomes = [], [], [], []
        try:
            setup = time.monotonic() - t0
            for k in range(args.attempts):
                w0 = time.monotonic()
                a = rig.attempt(slot_in=args.slot, placement=args.placement,
                                seed=SEED * 1000 + k, timeout_s=args.timeout)
                walls.append(time.monotonic() - w0)
                goals.append(a.duration_s)
                sims.append(a.sim_s)
                outcomes.append({'seed': a.seed, 'success': bool(a.success),
                                 'reason': a.reason, 'peak_force_n': float(a.peak_force_n)})
                print(f'attempt {k + 1}{" (busy)" if busy else ""}'
                      f'{" (composed)" if composed else ""}: '
                      f'{"success" if a.success else "failure"} ({a.reason}); goal '
                      f'{a.sim_s:.1f} sim s in {a.duration_s:.1f} s, attempt {walls[-1]:.1f} s',
                      flush=True)
        finally:
            rig.__exit__(None, None, None)
    return {'attempt_wall_s': _stats(walls), 'attempt_sim_s': _stats(sims),
            'goal_wall_s': _stats(goals),
            'sim_per_wall': _stats([s / w for s, w in zip(sims, goals, strict=False)]),
            'successes': sum(o['success'] for o in outcomes), 'outcomes': outcomes,
            'setup_wall_s': setup}


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    rows = (('attempt wall (s)', result['attempt_wall_s'], '<= 40', '.1f'),
            ('goal wall (s)', result['goal_wall_s'], '-', '.1f'),
            ('goal sim (s)', result['attempt_sim_s'], '-', '.1f'),
            ('goal sim s per wall s', result['sim_per_wall'], '-', '.2f'))
    n = len(result['attempt_wall_s']['values'])
    lines = [f'{result["placement"]} placement, {result["slot_in"]} in slot, {n} attempts '
             f'(seeds from {result["first_seed"]}), render workers '
             f'{result.get("render_workers", 0)}, '
             + ('lockstep' if result.get('lockstep') else 'paced by the clock')
             + (', composed' if result.get('composed') else ''),
             f'{"":24}{"median":>9}{"min":>9}{"max":>9}{"target":>9}']
    for name, st, target, fmt in rows:
        lines.append(f'{name:24}' + ''.join(f'{st[k]:>9{fmt}}' for k in ('median', 'min', 'max'))
                     + f'{target:>9}')
    lines.append(f'successes {result["successes"]}/{n}; graph set-up and the master\'s survey '
                 f'{result["setup_wall_s"]:.0f} s')
    return '\n'.join(lines)


def _stats(values: list[float]) -> dict:
    v = np.asarray(values, float)
    return {'median': float(np.median(v)), 'min': float(v.min()), 'max': float(v.max()),
            'values': [float(x) for x in v]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--site-map', type=Path, default=None,
                    help='the scenario site map (.cmap); default: build one first')
    ap.add_argument('--attempts', type=number(int, lo=1, hi=100), default=10)
    ap.add_argument('--slot', type=number(float, lo=4.26, hi=9.0), default=4.5,
                    help='slot width (in); Table 5-1: 5.0, 4.5, 4.375')
    ap.add_argument('--placement', choices=('optimal', 'random'), default='optimal')
    ap.add_argument('--timeout', type=number(float, lo=5.0, hi=600.0), default=45.0,
                    help='sim seconds an insert goal may take')
    ap.add_argument('--render-workers', type=number(int, lo=0, hi=1), default=1,
                    help="the simulator's render_workers (0: both eyes in the simulator)")
    ap.add_argument('--busy-too', action='store_true',
                    help='run the attempts again beside a busy core and compare the outcomes')
    ap.add_argument('--no-lockstep', dest='lockstep', action='store_false',
                    help='pace the simulator by the clock instead of lockstep')
    layout = ap.add_mutually_exclusive_group()
    layout.add_argument('--composed', action='store_true',
                        help='the master, the slave, the mapper and the view planner in one '
                             'process')
    layout.add_argument('--composed-too', action='store_true',
                        help='run the attempts again composed and compare')
    args = ap.parse_args()
    from coop_bringup.table_5_1 import build_site_map

    work = Path(tempfile.mkdtemp(prefix='attempt_rate_'))
    site_map = args.site_map
    if site_map is None:
        print('building the site map (seed 1, occlusion 0.05)', flush=True)
        site_map = build_site_map(work / 'site.cmap', seed=SEED, occlusion_density=OCCLUSION)
    elif not site_map.is_file():
        ap.error(f'--site-map {site_map}: no such file')
    result = {'slot_in': args.slot, 'placement': args.placement, 'first_seed': SEED * 1000,
              'render_workers': args.render_workers, 'lockstep': args.lockstep,
              'composed': args.composed,
              **run_attempts(args, site_map, work, busy=False, composed=args.composed),
              'logs': str(work),
              'clock': 'attempt_wall_s: the reset and the goal; goal_wall_s, attempt_sim_s: the '
                       'insert goal alone (time.monotonic, the simulator clock)'}
    if args.busy_too:
        busy = run_attempts(args, site_map, work, busy=True, composed=args.composed)
        result['busy'] = busy
        result['identical_successes'] = [o['success'] for o in result['outcomes']] == \
            [o['success'] for o in busy['outcomes']]
        result['peak_force_max_rel_diff'] = max(
            abs(a['peak_force_n'] - b['peak_force_n']) / max(abs(a['peak_force_n']), 1e-9)
            for a, b in zip(result['outcomes'], busy['outcomes'], strict=False))
    if args.composed_too:
        together = run_attempts(args, site_map, work, busy=False, composed=True)
        result['composed_run'] = together
        result['composed_wall_ratio'] = (together['attempt_wall_s']['median']
                                         / result['attempt_wall_s']['median'])
    print(format_table(result))
    if args.busy_too:
        print(format_load_table(result))
    if args.composed_too:
        print(format_compose_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
