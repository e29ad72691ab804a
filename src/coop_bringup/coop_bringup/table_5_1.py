"""Table 5-1 in the simulator: task success of the cooperative insertion for slot widths of 5.0,
4.5 and 4.375 in (the thesis's easy, medium and hard rows) and 4.2925 in (1 % of the card's
width in clearance, beyond the thesis), with the master's camera placed optimally (the view
planner's `task_view`) or at random (§5.4): drawn uniformly from the poses `task_view` finds
feasible for the same request (free, the markers within the detector's range and incidence,
the target unoccluded), drawn again where the optimal placement is re-placed ('random'), or
drawn once ('random_fixed', Table 4-1's fixed camera).

    ros2 run coop_bringup table_5_1 --json out/table_5_1.json --resume --plots out

runs the thesis's scale: 10 attempts a cell for the three thesis rows with each placement, and
30 for the 1 % row with the optimal placement (`--rows`: `width[:attempts[:placement+...]]`).

Every attempt runs through the whole graph over DDS (coop_bringup.rig: rover_sim, the mapper
with the site's map, view_planner, master and slave): the simulator is reset to the row's slot
width with the slave's start perturbed (attempt seed), one `insert` goal runs, and the
simulator's truth decides success: the card seated to depth with its penetration into anything
at most 0.5 mm at every step. The site map the view planner places the camera in is built once
per scenario by the mapping pipeline (coop_viewplan.fig_3_25's maximum-information exploration
with stereo ranging and the shared voxel map, saved with `save_map`; each cloud placed with
the rover's own estimated camera pose), plus the master's own survey of the site through the
live stereo and mapper nodes. The master is told only a region 0.3 m either side of a centre
drawn per attempt (rig.rough_site) and finds the slot in it by its markers.
"""
from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from coop_common.cli import number, output_dir, output_path
from coop_common.files import save_figure, write_json
from coop_common.provenance import source_revision

from .rig import InsertionRig, SimStalled, as_row

ROWS_IN = (5.0, 4.5, 4.375, 4.2925)
#: the thesis's scale: 10 attempts a cell, 30 for the 1 % row (optimal placement only)
DEFAULT_ROWS = '5.0,4.5,4.375,4.2925:30:optimal'
DEFAULT_ATTEMPTS = 10
#: what an attempt saved by a run of these settings stands for: raised when the system under
#: test changes so that older attempts would not be the same experiment (3: the master told a
#: rough region, the slave's floor-force verdict; 4: the master's search after a sim reset);
#: --resume reuses only the same
TABLE_FORMAT = 4
#: the placements a table compares (the rig's 'given' pins a pose: for tests)
TABLE_PLACEMENTS = ('optimal', 'random', 'random_fixed')
THESIS = {5.0: (10, 7), 4.5: (10, 4), 4.375: (9, 2)}       # of 10: optimal, random
LABELS = {5.0: 'Easy', 4.5: 'Medium', 4.375: 'Hard', 4.2925: '1 % clearance'}


def build_site_map(path: Path, *, seed: int, occlusion_density: float, scans: int = 14,
                   log: Callable[[str], None] | None = None) -> Path:
    """The scenario's map by the mapping pipeline (coop_viewplan.fig_3_25's exploration)."""
    from coop_viewplan.fig_3_25 import Fig325Config, PoseSource, run_strategy  # noqa: PLC0415 - only to build a site map
    cfg = Fig325Config(rovers=2, scans=scans, seed=seed, occlusion_density=occlusion_density,
                       pose_source=PoseSource.ODOMETRY)
    run_strategy('max_information', cfg, seed=seed, log=log, save_map=path)
    return path


#: a run gives up after this many simulator restarts (stalls)
MAX_RESTARTS = 6


def open_rig(*, seed: int, occlusion_density: float, slot_in: float, log_dir: Path,
             site_map: Path, log: Callable[[str], None] = print, render_workers: int = 1,
             lockstep: bool = True, composed: bool = False) -> InsertionRig:
    """The attempts' graph, ready: the rovers placed for the row, the master's survey of the
    site fused into the map, the stereo ranging stopped (the map is the scenario's); in
    lockstep with the simulator unless told otherwise; composed: the nodes that are not the
    simulator's or the stereo's in one process (InsertionRig)."""
    r = InsertionRig(seed=seed, occlusion_density=occlusion_density, slot_in=slot_in,
                     log_dir=log_dir, site_map=site_map, render_workers=render_workers,
                     lockstep=lockstep, composed=composed).__enter__()
    try:
        r.place(slot_in, np.random.default_rng(seed))
        log(f'site surveyed: {r.survey()} scans in the map')
        r.stop_mapping()
        r.set_slot(slot_in)
    except BaseException:
        r.__exit__(None, None, None)
        raise
    return r


def _cell_key(slot_in: float, placement: str, seed: int) -> tuple[float, str, int]:
    return (round(float(slot_in), 6), placement, int(seed))


def _done_attempts(checkpoint: Path | None, settings: dict | None = None,
                   log: Callable[[str], None] = print) -> dict:
    """The attempts a previous run of the same `settings` saved in `checkpoint` (its --json):
    (slot_in, placement, seed) -> (row, curves); none when its settings differ."""
    if checkpoint is None or not checkpoint.exists():
        return {}
    try:
        old = json.loads(checkpoint.read_text())
    except (OSError, ValueError):
        return {}
    if settings is not None and old.get('settings') != settings:
        log(f'{checkpoint} was run with other settings ({old.get("settings")}, not '
            f'{settings}): nothing resumed')
        return {}
    done = {}
    for row in old.get('rows', []):
        for placement in old.get('placements', []):
            rows = row.get(f'{placement}_attempts') or []
            curves = row.get(f'{placement}_curves') or [{}] * len(rows)
            for a, c in zip(rows, curves, strict=False):
                done[_cell_key(a['slot_in'], placement, a['seed'])] = (a, thin_curves(c))
    return done


#: the curves an attempt keeps in the JSON: at most one sample per this much sim time (s),
#: plus every phase change, rounded to what the plots show (a 120-attempt table at the
#: feedback's full rate is 17 MB of JSON)
CURVE_DT_S = 0.25
_CURVE_DIGITS = {'t': 3, 'displacement_m': 5, 'angle_rad': 5, 'force': 3}


def thin_curves(c: dict, dt_s: float = CURVE_DT_S) -> dict:
    """An attempt's curves (rig.Attempt.curves) with one sample per `dt_s` of sim time, every
    sample where the phase changes and the last, values rounded (_CURVE_DIGITS)."""
    t = c.get('t') or []
    if not t:
        return c
    keep, last_t = [], -math.inf
    for i, ti in enumerate(t):
        changed = i > 0 and c['phase'][i] != c['phase'][i - 1]
        if ti - last_t >= dt_s or changed or i == len(t) - 1:
            keep.append(i)
            last_t = ti

    def rounded(key: str, v: Any) -> Any:
        d = _CURVE_DIGITS.get(key)
        if d is None:
            return v
        return [round(float(x), d) for x in v] if isinstance(v, list) else round(float(v), d)
    return {k: [rounded(k, v[i]) for i in keep] if isinstance(v, list) and len(v) == len(t)
            else v for k, v in c.items()}


def parse_rows(spec: str, *, attempts: int,
               placements: tuple[str, ...]) -> list[tuple[float, int, tuple[str, ...]]]:
    """`width[:attempts[:placement+...]]`, comma-separated (e.g. DEFAULT_ROWS), into (slot
    width in, attempts, placements) per row; `attempts` and `placements` where a row gives
    none (ValueError with the reason)."""
    rows: list[tuple[float, int, tuple[str, ...]]] = []
    for item in (x.strip() for x in spec.split(',') if x.strip()):
        parts = item.split(':')
        if len(parts) > 3:
            raise ValueError(f'{item!r}: width[:attempts[:placement+...]]')
        width = float(parts[0])
        if not 4.25 < width <= 9.8:
            raise ValueError(f'{item!r}: the slot must be wider than the 4.25 in card (and at '
                             'most 9.8 in)')
        n = int(parts[1]) if len(parts) > 1 and parts[1] else attempts
        if n < 1:
            raise ValueError(f'{item!r}: at least one attempt')
        pl = tuple(parts[2].split('+')) if len(parts) > 2 else placements
        if not pl or any(x not in TABLE_PLACEMENTS for x in pl):
            raise ValueError(f'{item!r}: placements of {", ".join(TABLE_PLACEMENTS)}')
        if width in [r[0] for r in rows]:
            raise ValueError(f'{item!r}: the {width:g} in row is given twice')
        if len(set(pl)) != len(pl):
            raise ValueError(f'{item!r}: a placement is given twice')
        rows.append((width, n, pl))
    if not rows:
        raise ValueError('no rows')
    return rows


def run(*, attempts: int, rows: tuple[float, ...] | list[tuple[float, int, tuple[str, ...]]],
        placements: tuple[str, ...], seed: int, occlusion_density: float, timeout_s: float,
        max_force_n: float, site_map: Path | None, checkpoint: Path | None = None,
        resume: bool = False, log: Callable[[str], None] = print) -> dict:
    """The table: `rows` slot widths (in), each with `attempts` per placement, or (width,
    attempts, placements) per row (parse_rows). With `checkpoint`, the result so far is
    written there (atomically) after every attempt, `complete` false until the end; `resume`
    reuses the attempts it holds. An attempt the simulator stalled in (rig.SimStalled) is run
    again on a fresh graph, up to MAX_RESTARTS per run; each restart is listed in
    `sim_restarts`. Each attempt run records the source revision it ran on (`source`), so a
    table resumed over several checkouts says which code ran which attempt."""
    t0 = time.perf_counter()
    work = Path(tempfile.mkdtemp(prefix='table_5_1_'))
    if site_map is None:
        log(f'building the site map (seed {seed}, occlusion {occlusion_density})')
        site_map = build_site_map(work / 'site.cmap', seed=seed,
                                  occlusion_density=occlusion_density)
    settings = {'format': TABLE_FORMAT, 'seed': seed, 'occlusion_density': occlusion_density,
                'timeout_s': timeout_s, 'max_force_n': max_force_n}
    done = _done_attempts(checkpoint, settings, log) if resume else {}
    source = source_revision()
    if done:
        log(f'resuming: {len(done)} attempts from {checkpoint}')
    res: dict[str, Any] = {'settings': settings, 'attempts': attempts, 'seed': seed,
                           'occlusion_density': occlusion_density,
                           'placements': list(placements), 'rows': [], 'sim_restarts': [],
                           'complete': False, 'seconds': 0.0, 'logs': str(work / 'logs')}
    rig: InsertionRig | None = None

    specs = [r if isinstance(r, tuple) else (float(r), attempts, placements) for r in rows]
    res['placements'] = list(dict.fromkeys(p for *_, pl in specs for p in pl))
    try:
        for slot_in, n_row, row_placements in specs:
            row = {'slot_in': slot_in, 'label': LABELS.get(slot_in, f'{slot_in} in'),
                   'attempts': n_row, 'thesis': THESIS.get(slot_in)}
            res['rows'].append(row)
            if rig is not None:
                rig.set_slot(slot_in)
            for placement in row_placements:
                got: list[dict] = []
                curves: list[dict] = []
                row[f'{placement}_attempts'] = got
                row[f'{placement}_curves'] = curves
                for k in range(n_row):
                    key = _cell_key(slot_in, placement, seed * 1000 + k)
                    if key in done:
                        a, c = done[key]
                    else:
                        a, c = None, None
                        while a is None:
                            if rig is None:
                                rig = open_rig(
                                    seed=seed, occlusion_density=occlusion_density,
                                    slot_in=slot_in, site_map=site_map, log=log,
                                    log_dir=work / 'logs' / f'graph_{len(res["sim_restarts"])}')
                            try:
                                at = rig.attempt(slot_in=slot_in, placement=placement,
                                                 seed=key[2], timeout_s=timeout_s,
                                                 max_force_n=max_force_n)
                            except SimStalled as exc:
                                res['sim_restarts'].append(
                                    {'slot_in': slot_in, 'placement': placement,
                                     'seed': key[2], 'reason': str(exc),
                                     'stack_file': str(exc.stack_file or '')})
                                log(f'{slot_in} in {placement} #{k + 1}: {exc}; '
                                    'restarting the graph')
                                rig.__exit__(None, None, None)
                                rig = None
                                if len(res['sim_restarts']) > MAX_RESTARTS:
                                    raise
                                continue
                            a, c = as_row(at), thin_curves(at.curves)
                            a['source'] = source
                    got.append(a)
                    curves.append(c)
                    log(f'{slot_in} in {placement} #{k + 1}: '
                        f'{"success" if a["success"] else "failure"} ({a["reason"]}); '
                        f'penetration {a["max_penetration_mm"]:.2f} mm, peak force '
                        f'{_fmt(a["peak_force_n"])} N, fixes {a.get("fixes", 0)}/'
                        f'{a.get("frames", 0)}, aligned {_fmt(a.get("align_mm"))} mm '
                        f'{_fmt(a.get("align_tilt_deg"))} deg, site {_fmt(a.get("site_error_mm"))}'
                        f' mm off after {a.get("search_views", 0)} views, {a["sim_s"]:.0f} sim s, '
                        f'{a["duration_s"]:.0f} s')
                    row[f'{placement}_successes'] = sum(bool(x['success']) for x in got)
                    row[f'{placement}_peak_force_n'] = max(
                        (x['peak_force_n'] for x in got if x['peak_force_n'] is not None),
                        default=None)
                    res['seconds'] = time.perf_counter() - t0
                    if checkpoint is not None:
                        write_json(checkpoint, res)
    finally:
        if rig is not None:
            rig.__exit__(None, None, None)
    res['complete'] = True
    res['seconds'] = time.perf_counter() - t0
    return res


def _fmt(v: float | None, digits: int = 1) -> str:
    return '-' if v is None else f'{v:.{digits}f}'


def _median(xs: list) -> float | None:
    xs = [x for x in xs if x is not None]
    return float(np.median(xs)) if xs else None


def cell_summary(attempts: list[dict]) -> dict:
    """What a cell's attempts show beyond the count: how many got to the descent, the median
    fix rate (fixes per stereo pair the master looked at while the slave ran), the median
    alignment by the truth when the descent began (|offset| across the slot, mm; |tilt|,
    deg), and the slave's verdicts the truth contradicts: a "seated" the truth denies (false),
    a card the truth seated that the slave never called seated (missed)."""
    reached = [a for a in attempts if a.get('align_mm') is not None]
    rates = [a['fixes'] / a['frames'] for a in attempts if a.get('frames')]
    recorded = all('align_mm' in a for a in attempts)   # a run that recorded the alignment
    located = [a['site_error_mm'] for a in attempts if a.get('site_error_mm') is not None]
    return {'n': len(attempts), 'seated': sum(bool(a['success']) for a in attempts),
            'reached_descent': len(reached) if recorded else None,
            'located': len(located) if all('site_error_mm' in a for a in attempts) else None,
            'site_error_mm': _median(located),
            'search_views': _median([a['search_views'] for a in attempts
                                     if 'search_views' in a]),
            'fix_rate': _median(rates) if rates else None,
            'align_mm': _median([abs(a['align_mm']) for a in reached]),
            'align_tilt_deg': _median([abs(a['align_tilt_deg']) for a in reached]),
            'false_seated': sum(bool(a['action_success']) and not bool(a['seated'])
                                for a in attempts),
            'missed_seated': sum(bool(a['seated']) and not bool(a['action_success'])
                                 for a in attempts),
            'peak_force_n': max((a['peak_force_n'] for a in attempts
                                 if a['peak_force_n'] is not None), default=None)}


def format_table(res: dict) -> str:
    """The result as Table 5-1's text: success per row and placement next to the thesis's."""
    counts = sorted({r.get('attempts', res['attempts']) for r in res['rows']})
    placements = res['placements']
    head = (f'Table 5-1 through sim + nodes: {" or ".join(map(str, counts))} attempts per cell '
            '(thesis: 10); success = seated, penetration <= 0.5 mm')
    lines = [head, f'{"row":16s} {"slot (in)":>9s} '
             + ' '.join(f'{p:>12s}' for p in placements)
             + f' {"thesis opt":>10s} {"thesis rnd":>10s}']
    for r in res['rows']:
        th = r.get('thesis')
        cells = []
        for p in placements:
            got = r.get(f'{p}_attempts')
            cells.append('-' if got is None else
                         f'{sum(bool(a["success"]) for a in got)}/{len(got)}')
        lines.append(
            f'{r["label"]:16s} {r["slot_in"]:9.4g} '
            + ' '.join(f'{c:>12s}' for c in cells)
            + f' {"-" if th is None else f"{th[0]}/10":>10s}'
            f' {"-" if th is None else f"{th[1]}/10":>10s}')
    lines += ['', 'per cell: attempts that located the slot, median views it took and '
              "the located site's error (mm), attempts that got to",
              'the descent, median fix rate, median alignment by the truth at the descent, '
              "the slave's verdicts the truth",
              'contradicts (false: said seated, missed: seated and not said), peak contact force',
              f'{"row":16s} {"placement":>12s} {"seated":>7s} {"located":>7s} {"views":>5s} '
              f'{"site mm":>7s} {"descent":>7s} '
              f'{"fix rate":>8s} {"|dx| mm":>8s} {"|tilt| deg":>10s} {"false":>5s} '
              f'{"missed":>6s} {"peak F (N)":>10s}']
    for r in res['rows']:
        for p in placements:
            got = r.get(f'{p}_attempts')
            if not got:
                continue
            c = cell_summary(got)
            lines.append(
                f'{r["label"]:16s} {p:>12s} {c["seated"]:>3d}/{c["n"]:<3d} '
                f'{_fmt(c["located"], 0):>7s} {_fmt(c["search_views"], 0):>5s} '
                f'{_fmt(c["site_error_mm"], 0):>7s} '
                f'{_fmt(c["reached_descent"], 0):>7s} {_fmt(c["fix_rate"], 2):>8s} '
                f'{_fmt(c["align_mm"]):>8s} {_fmt(c["align_tilt_deg"], 2):>10s} '
                f'{c["false_seated"]:>5d} {c["missed_seated"]:>6d} '
                f'{_fmt(c["peak_force_n"]):>10s}')
    restarts = len(res.get('sim_restarts', []))
    if restarts:
        lines.append(f'{restarts} attempt(s) run again on a fresh graph after a simulator stall')
    if not res.get('complete', True):
        lines.append('incomplete: the run stopped before the last attempt')
    # a resumed run's `seconds` is its last sitting's; the attempts carry their own times
    spent = sum(a.get('duration_s') or 0.0 for r in res['rows'] for p in placements
                for a in r.get(f'{p}_attempts') or [])
    lines.append(f'{res["seconds"] / 60:.1f} min' if spent <= res['seconds'] else
                 f'{res["seconds"] / 60:.1f} min this sitting; the attempts took '
                 f'{spent / 60:.1f} min in all')
    return '\n'.join(lines)


def plot_curves(c: dict, title: str, path: Path) -> Path:
    """One attempt's Figs. 5-13 / 5-14 curves (an Attempt's `curves`): displacement and angular
    error against time, and the F/T force after contact."""
    import matplotlib  # noqa: PLC0415 - heavy, only when plotting
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415 - heavy, only when plotting
    fig, ax = plt.subplots(1, 3, figsize=(13, 3.6))
    t = c['t']
    ax[0].plot(t, [1e3 * v for v in c['displacement_m']])
    ax[0].set(xlabel='time (s)', ylabel='displacement error (mm)')
    ax[1].plot(t, c['angle_rad'])
    ax[1].set(xlabel='time (s)', ylabel='angular error (rad)')
    contact = [k for k, ph in enumerate(c['phase']) if ph == 2]
    if contact:
        k0 = contact[0]
        ax[2].plot(t[k0:], [f[1] for f in c['force'][k0:]], label='F_y')
        ax[2].plot(t[k0:], [f[2] for f in c['force'][k0:]], label='F_z')
        ax[2].legend()
    ax[2].set(xlabel='time (s)', ylabel='F/T force after contact (N)')
    fig.suptitle(title)
    fig.tight_layout()
    out = save_figure(fig, path)
    plt.close(fig)
    return out


def plot(res: dict, out: Path) -> list[Path]:
    """Figs. 5-13 / 5-14 for each placement: the first attempt of the last (hardest) row that
    ran it, so a 1 % row of the optimal placement alone does not hide the random one."""
    paths = []
    for placement in res['placements']:
        ran = [r for r in res['rows'] if r.get(f'{placement}_curves')]
        if not ran:
            continue
        row = ran[-1]
        curves = row[f'{placement}_curves']
        ok = row[f'{placement}_attempts'][0]['success']
        paths.append(plot_curves(
            curves[0], f'{row["label"]} ({row["slot_in"]} in), {placement} placement: '
            f'{"success" if ok else "failure"}', out / f'fig_5_13_{placement}.png'))
    return paths


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_insertion.table_5_1`: the attempts per row and placement, resumable."""
    p = argparse.ArgumentParser(prog='table_5_1', description=__doc__.split('\n\n')[0])
    p.add_argument('--attempts', type=number(int, lo=1), default=DEFAULT_ATTEMPTS,
                   help='per cell, where --rows gives none')
    p.add_argument('--rows', default=DEFAULT_ROWS,
                   help='comma-separated width[:attempts[:placement+...]], widths in inches '
                        f'(default {DEFAULT_ROWS})')
    p.add_argument('--placements', default=','.join(TABLE_PLACEMENTS),
                   help=f'comma-separated, of {", ".join(TABLE_PLACEMENTS)}')
    p.add_argument('--seed', type=number(int, lo=0), default=1)
    p.add_argument('--occlusion-density', type=number(float, lo=0.0, hi=0.5), default=0.05)
    p.add_argument('--timeout', type=number(float, lo=1.0), default=90.0,
                   help='sim seconds per attempt')
    p.add_argument('--max-force', type=number(float, lo=1.0), default=25.0)
    p.add_argument('--site-map', type=Path, default=None,
                   help='a map file of the scenario (default: built by the mapping pipeline)')
    p.add_argument('--json', type=output_path, default=None,
                   help='the result; written after every attempt (complete: false until the end)')
    p.add_argument('--resume', action='store_true',
                   help='reuse the attempts an interrupted run saved in --json')
    p.add_argument('--plots', type=output_dir, default=None)
    args = p.parse_args(argv)
    if args.resume and not args.json:
        p.error('--resume reads the attempts saved in --json: give --json')
    placements = tuple(x for x in args.placements.split(',') if x)
    if not placements or any(x not in TABLE_PLACEMENTS for x in placements):
        p.error(f'--placements: of {", ".join(TABLE_PLACEMENTS)}')
    try:
        rows = parse_rows(args.rows, attempts=args.attempts, placements=placements)
    except ValueError as exc:
        p.error(f'--rows: {exc}')
    # SIGTERM (`timeout`, a supervisor) as Ctrl-C: the graph's nodes run in their own
    # sessions and would outlive the run
    signal.signal(signal.SIGTERM, signal.default_int_handler)
    res = run(attempts=args.attempts, rows=rows, placements=placements, seed=args.seed,
              occlusion_density=args.occlusion_density, timeout_s=args.timeout,
              max_force_n=args.max_force, site_map=args.site_map, checkpoint=args.json,
              resume=args.resume, log=lambda s: print(s, file=sys.stderr, flush=True))
    print(format_table(res))
    if args.json:
        write_json(args.json, res)
    if args.plots:
        for path in plot(res, args.plots):
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())

