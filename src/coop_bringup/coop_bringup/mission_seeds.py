"""The mission counted: one scenario run for many seeds (the simulator's site clutter, the
rovers' starts, the sensors' noise and the master's rough site region all drawn from the seed),
each phase judged as the report does, and one table of them.

    python -m coop_bringup.mission --seeds 1-20 --out out --run-id seeds

runs `OUT/<run-id>/seed_<k>/` for each seed in turn (a seed whose report is there already is
read back, not run again: a stopped run resumes; a seed stopped by Ctrl-C or SIGTERM stops the
batch, and is run again on the next, its directory kept as `seed_<k>.interrupted-<n>`), then
prints the table and writes it to `OUT/<run-id>/seeds.json` (`format_result` prints that
file). `judge` and the formatting need no ROS.
"""
from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

from coop_common.files import write_json

from .report import MissionError, PhaseStatus


def parse_seeds(spec: str) -> list[int]:
    """'1-20', '3,5,9' or a mix ('1-3,7') into the seeds, in order (MissionError)."""
    seeds: list[int] = []
    for part in (p.strip() for p in spec.split(',') if p.strip()):
        lo, _, hi = part.partition('-')
        try:
            a, b = int(lo), int(hi or lo)
        except ValueError:
            raise MissionError(f'--seeds: {part!r} is not a seed or a range a-b') from None
        if a < 0 or b < a:
            raise MissionError(f'--seeds: {part!r} must be non-negative and increasing')
        seeds += [s for s in range(a, b + 1) if s not in seeds]
    if not seeds:
        raise MissionError('--seeds: no seed given')
    return seeds


def judge(rep: dict) -> dict:
    """One mission report's phases against their targets, as its summary table judges them:
    identification error within its target, map coverage at its target, the camera placed
    (the insert goal got past PLACE_CAMERA), the card seated within the penetration limit."""
    t = rep.get('targets', {})
    status = {p['name']: p['status'] for p in rep.get('phases', [])}
    e = rep.get('identification', {}).get('mean_abs_rel_error')
    cov = rep.get('mapping', {}).get('coverage')
    ins = rep.get('insertion', {})
    row = {
        'seed': rep.get('config', {}).get('seed'),
        'identify': status.get('identify') == PhaseStatus.OK and e is not None
        and e <= t.get('identification_error', 0.15),
        'identification_error': e,
        'map': (status.get('map') == PhaseStatus.OK and cov is not None
                and cov >= t.get('coverage', 0.9)),
        'coverage': cov,
        'place': status.get('place') == PhaseStatus.OK,
        'insert': bool(ins.get('success')),
        'reason': ins.get('reason', ''),
        'search_views': ins.get('search_views'),
        'site_error_mm': ins.get('site_error_mm'),
        'align_mm': ins.get('align_mm'),
        'peak_force_n': ins.get('peak_force_n'),
        'wall_s': rep.get('wall_s'),
        'error': rep.get('error'),
        'source': rep.get('source'),      # the commit the seed ran on
    }
    asked = [p['name'] for p in rep.get('phases', []) if p.get('reason') != 'not asked for']
    row['all'] = all(row[name] for name in asked)
    return row


def _f(v: object, spec: str) -> str:
    return '-' if v is None or (isinstance(v, float) and not math.isfinite(v)) \
        else format(v, spec)


def format_table(rows: list[dict]) -> str:
    """The seeds' table: each phase on target (yes/no) with its figure, and the totals."""
    yn = {True: 'yes', False: 'NO'}
    lines = [f'{"seed":>4s} {"identify":>13s} {"map":>12s} {"place":>5s} {"seated":>6s} '
             f'{"views":>5s} {"site mm":>7s} {"|dx| mm":>7s} {"peak N":>6s} {"wall s":>6s} '
             f'{"all":>4s}  reason']
    for r in rows:
        ident = f'{yn[r["identify"]]} {_f(_pct(r["identification_error"]), ".1f")}%'
        cov = f'{yn[r["map"]]} {_f(_pct(r["coverage"]), ".0f")}%'
        align = None if r['align_mm'] is None else abs(r['align_mm'])
        lines.append(
            f'{r["seed"]:>4d} {ident:>13s} {cov:>12s} {yn[r["place"]]:>5s} '
            f'{yn[r["insert"]]:>6s} {_f(r["search_views"], "d"):>5s} '
            f'{_f(r["site_error_mm"], ".0f"):>7s} {_f(align, ".1f"):>7s} '
            f'{_f(r["peak_force_n"], ".1f"):>6s} {_f(r["wall_s"], ".0f"):>6s} '
            f'{yn[r["all"]]:>4s}  {"" if r["insert"] else (r["error"] or r["reason"])[:60]}')
    n = len(rows)
    lines.append(f'seated {sum(r["insert"] for r in rows)}/{n}; every phase on target '
                 f'{sum(r["all"] for r in rows)}/{n}')
    return '\n'.join(lines)


def format_result(res: dict) -> str:
    """A run's `seeds.json` as its table, saying how far a stopped run got."""
    text = format_table(res['rows'])
    if not res.get('complete', True):
        text += f'\nincomplete: {len(res["rows"])} of {len(res["seeds"])} seeds run'
    return text


def _pct(v: float | None) -> float | None:
    return None if v is None else 100 * v


def run_seeds(seeds: list[int], run_one: Callable[[int, str], dict], out: Path, *,
              log: Callable[[str], None] = print) -> list[dict]:
    """Each seed's mission (`run_one(seed, run_id)` returns its report) under `out`, or its
    report read back when `out/seed_<k>/report.json` holds one; the judged rows, also written
    to `out/seeds.json` after every seed."""
    rows: list[dict] = []
    for seed in seeds:
        run_id = f'seed_{seed}'
        done = out / run_id / 'report.json'
        rep = None
        if done.exists():
            try:
                rep = json.loads(done.read_text())
            except (OSError, ValueError):
                raise MissionError(f'{done} is unreadable: remove {out / run_id} to run '
                                   f'seed {seed} again') from None
            if rep.get('interrupted'):
                kept = _set_aside(out / run_id)
                log(f'seed {seed} was interrupted: run again ({kept.name} kept)')
                rep = None
            else:
                log(f'seed {seed}: its report is there already ({done})')
        elif (out / run_id).exists():
            raise MissionError(f'{out / run_id} holds an unfinished run (no report): '
                               f'remove it to run seed {seed} again')
        if rep is None:
            rep = run_one(seed, run_id)
            if rep.get('interrupted'):
                write_json(out / 'seeds.json', {'seeds': seeds, 'rows': rows,
                                                'complete': False})
                raise KeyboardInterrupt
        rows.append(judge(rep))
        write_json(out / 'seeds.json', {'seeds': seeds, 'rows': rows,
                                        'complete': len(rows) == len(seeds)})
    return rows


def _set_aside(path: Path) -> Path:
    n = 1
    while path.with_name(f'{path.name}.interrupted-{n}').exists():
        n += 1
    kept = path.with_name(f'{path.name}.interrupted-{n}')
    path.rename(kept)
    return kept
