"""The mission's measures and its report (no rclpy): work-site coverage of the shared voxel map,
the identification error against the simulator's truth, and `report.md` / `report.json` with
their plots under the run's directory.

report.json holds at least `identification.mean_abs_rel_error`, `mapping.coverage` and
`insertion.success` (a bool; false when the phase did not run to its end).
"""
from __future__ import annotations

import math
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from coop_common.files import save_figure, write_json, write_text_atomic

__all__ = [
    'MissionError',
    'PhaseStatus',
    'format_summary',
    'identification_errors',
    'site_coverage',
    'top_view',
    'write_report',
]


#: the lowest voxel layer counted as the site's surface: the ground at z = 0 lands in layer
#: -1 or 0, stereo noise a layer lower
GROUND_KEY = -2


class MissionError(RuntimeError):
    """A mission that cannot go on: the phase and the reason are in the message."""


class PhaseStatus(StrEnum):
    """A mission phase's status in the report (its JSON 'phases' rows)."""

    SKIPPED = 'skipped'
    RUNNING = 'running'
    OK = 'ok'
    FAILED = 'failed'


def _site_columns(keys: np.ndarray, resolution: float, centre_xy: ArrayLike, half_m: float
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The work site's ground cells as key ranges: (lo, hi) inclusive (x, y) keys and the
    (N, 3) keys given."""
    k = np.asarray(keys, np.int64).reshape(-1, 3)
    c = np.asarray(centre_xy, float)
    lo = np.floor((c - half_m) / resolution).astype(np.int64)
    hi = np.floor((c + half_m) / resolution - 1e-9).astype(np.int64)
    return lo, hi, k


def site_coverage(keys: np.ndarray, occupancy: np.ndarray, resolution: float, *,
                  centre_xy: ArrayLike, half_m: float, z_max_m: float = 1.0) -> float:
    """Fraction of the work site's ground cells (a square of side 2 half_m about centre_xy)
    whose surface the map has measured: an occupied voxel (the ground, or the top of what stands
    on it) in the column below z_max_m. A column crossed only by rays (free voxels above an
    unseen ground, behind an obstacle) is not covered."""
    if not (resolution > 0 and half_m > 0):
        raise MissionError('coverage needs a positive resolution and site size')
    lo, hi, k = _site_columns(keys, resolution, centre_xy, half_m)
    occ = np.asarray(occupancy, float).reshape(-1)
    if len(occ) != len(k):
        raise MissionError('one occupancy per voxel key')
    kz = math.floor(z_max_m / resolution)
    sel = np.all((k[:, :2] >= lo) & (k[:, :2] <= hi), axis=1) & (k[:, 2] >= GROUND_KEY) & \
        (k[:, 2] < kz) & (occ >= 0.5)
    cols = np.unique(k[sel, :2], axis=0)
    total = int(np.prod(hi - lo + 1))
    return float(len(cols) / total) if total > 0 else 0.0


def top_view(keys: np.ndarray, occupancy: np.ndarray, resolution: float, *, centre_xy: ArrayLike,
             half_m: float, z_max_m: float = 1.0, ground_m: float = 0.1) -> np.ndarray:
    """Per ground cell of the site (x rows, y columns): -1 unknown, 0 seen free, 1 an occupied
    voxel above `ground_m` (an obstacle)."""
    lo, hi, k = _site_columns(keys, resolution, centre_xy, half_m)
    occ = np.asarray(occupancy, float).reshape(-1)
    out = np.full(tuple(hi - lo + 1), -1, np.int8)
    kz0, kz1 = math.floor(ground_m / resolution), math.floor(z_max_m / resolution)
    sel = np.all((k[:, :2] >= lo) & (k[:, :2] <= hi), axis=1) & (k[:, 2] >= GROUND_KEY) & \
        (k[:, 2] < kz1)
    ij = k[sel, :2] - lo
    out[ij[:, 0], ij[:, 1]] = 0
    obst = (occ[sel] >= 0.5) & (k[sel, 2] >= kz0)
    out[ij[obst, 0], ij[obst, 1]] = 1
    return out


def identification_errors(truth: dict[str, float], estimate: dict[str, float],
                          std: dict[str, float] | None = None,
                          bits: dict[str, float] | None = None) -> dict:
    """Per parameter truth, estimate, 1-sigma, information bits and relative error, and the
    mean absolute relative error over the parameters whose truth is non-zero (Table 2-1's
    figure)."""
    rows, errs = [], []
    for name, x in truth.items():
        if name not in estimate:
            raise MissionError(f'no estimate of {name}')
        v = float(estimate[name])
        rel = abs(v - x) / abs(x) if x != 0 else None
        if rel is not None:
            errs.append(rel)
        rows.append({'name': name, 'truth': float(x), 'estimate': v,
                     'std': None if std is None else float(std.get(name, math.nan)),
                     'information_bits': None if bits is None else float(bits.get(name,
                                                                                  math.nan)),
                     'rel_error': rel})
    return {'params': rows, 'mean_abs_rel_error': float(np.mean(errs)) if errs else None}


# ------------------------------------------------------------------------------ the report


def _fmt(v: object, spec: str = '.3g', none: str = '-') -> str:
    return none if v is None or (isinstance(v, float) and not math.isfinite(v)) else \
        format(v, spec)


def _pct(v: float | None) -> float | None:
    return None if v is None else 100 * v


def format_summary(rep: dict) -> str:
    """The report's summary table (markdown): each phase's result against its target, with
    wall and sim time."""
    t = rep.get('targets', {})
    ident = rep.get('identification', {})
    mapping = rep.get('mapping', {})
    place = rep.get('placement', {})
    ins = rep.get('insertion', {})
    e = ident.get('mean_abs_rel_error')
    results = {
        'identify': (f'mean error {_fmt(_pct(e), ".1f")} %',
                     f'<= {100 * t.get("identification_error", 0.15):.0f} %'),
        'map': (f'coverage {_fmt(_pct(mapping.get("coverage")), ".1f")} % in '
                f'{mapping.get("scans_taken", 0)} scans, '
                f'{_fmt(mapping.get("distance_m"), ".1f")} m driven',
                f'>= {100 * t.get("coverage", 0.9):.0f} %'),
        'place': (f'camera {_fmt(place.get("distance_to_target_m"), ".2f")} m from the target, '
                  f'RF {_fmt(place.get("rating"), ".3g")}', 'task_view'),
        'insert': ('success' if ins.get('success') else f'failure: {ins.get("reason", "-")}',
                   f'seated, penetration <= {t.get("penetration_mm", 0.5)} mm'),
    }
    lines = ['| phase | status | result | target | wall (s) | sim (s) |',
             '|---|---|---|---|---|---|']
    for ph in rep.get('phases', []):
        res, tgt = results.get(ph['name'], ('', ''))
        if ph['status'] != PhaseStatus.OK and ph.get('reason') and ph['reason'] not in res:
            res = f'{res}; {ph["reason"]}' if ph['status'] == PhaseStatus.FAILED else ph['reason']
        lines.append(f'| {ph["name"]} | {ph["status"]} | {res} | {tgt} | '
                     f'{_fmt(ph.get("wall_s"), ".0f")} | {_fmt(ph.get("sim_s"), ".1f")} |')
    return '\n'.join(lines)


def _plots(rep: dict, out: Path, extras: dict) -> dict[str, str]:
    import matplotlib  # noqa: PLC0415 - heavy, only when plotting
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415 - heavy, only when plotting
    files = {}
    ident = rep.get('identification', {}).get('rovers', {})
    if ident:
        fig, ax = plt.subplots(figsize=(11, 3.6))
        width = 0.8 / len(ident)
        for j, (rover, r) in enumerate(sorted(ident.items())):
            ps = [p for p in r['params'] if p['rel_error'] is not None]
            x = np.arange(len(ps)) + j * width
            ax.bar(x, [100 * p['rel_error'] for p in ps], width, label=rover)
            ax.set_xticks(np.arange(len(ps)) + 0.4 - width / 2,
                          [p['name'] for p in ps], rotation=60, fontsize=8)
        ax.set(ylabel='|estimate - truth| / truth (%)', yscale='log',
               title='Identified vs true base parameters')
        ax.legend()
        fig.tight_layout()
        files['identification'] = save_figure(fig, out / 'identification.png').name
        plt.close(fig)
    scans = rep.get('mapping', {}).get('scans', [])
    if scans:
        fig, ax = plt.subplots(1, 2, figsize=(10, 3.4))
        cov = [100 * s['coverage'] for s in scans]
        ax[0].plot([s['scan'] for s in scans], cov, 'o-')
        ax[0].set(xlabel='scan', ylabel='work site seen (%)')
        ax[1].plot([s['distance_m'] for s in scans], cov, 'o-')
        ax[1].set(xlabel='distance driven, all rovers (m)', ylabel='work site seen (%)')
        for a in ax:
            a.axhline(100 * rep.get('targets', {}).get('coverage', 0.9), ls='--', c='gray')
        fig.tight_layout()
        files['coverage'] = save_figure(fig, out / 'coverage.png').name
        plt.close(fig)
    top = extras.get('top_view')
    if top is not None:
        m = rep['mapping']
        lo = np.asarray(m['site_centre']) - m['site_half_m']
        hi = np.asarray(m['site_centre']) + m['site_half_m']
        fig, ax = plt.subplots(figsize=(5.5, 5.5))
        ax.imshow(top.T, origin='lower', extent=(lo[0], hi[0], lo[1], hi[1]), cmap='Greys',
                  vmin=-1, vmax=1.5)
        for rover, path in sorted(extras.get('paths', {}).items()):
            p = np.asarray(path)
            if len(p):
                ax.plot(p[:, 0], p[:, 1], '-', lw=1, label=f'{rover} path')
        cam = rep.get('placement', {}).get('position')
        if cam:
            ax.plot(cam[0], cam[1], 'r^', ms=9, label='master camera')
        ax.set(xlabel='x (m)', ylabel='y (m)', xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]),
               title='Work site from above\n(white unseen, grey seen, black obstacle)')
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=7, loc='upper left')
        fig.tight_layout()
        files['map_top'] = save_figure(fig, out / 'map_top.png').name
        plt.close(fig)
    pts = extras.get('occupied_points')
    if pts is not None and len(pts):
        fig = plt.figure(figsize=(6, 5))
        ax = fig.add_subplot(projection='3d')
        p = np.asarray(pts)
        if len(p) > 20000:
            p = p[np.random.default_rng(0).choice(len(p), 20000, replace=False)]
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], c=p[:, 2], s=1, cmap='viridis')
        ax.set(xlabel='x (m)', ylabel='y (m)', zlabel='z (m)', title='Occupied voxels')
        fig.tight_layout()
        files['map_3d'] = save_figure(fig, out / 'map_3d.png').name
        plt.close(fig)
    curves = extras.get('insertion_curves')
    if curves and curves.get('t'):
        from coop_bringup.table_5_1 import plot_curves  # noqa: PLC0415 - rclpy; only with insertion curves
        ok = rep.get('insertion', {}).get('success')
        files['insertion'] = plot_curves(
            curves, f'Insertion, {rep["config"]["slot_in"]} in slot: '
            f'{"success" if ok else "failure"}', out / 'insertion.png').name
    return files


def format_apart(rep: dict) -> str:
    """What the run kept apart: the simulator's truth from the loop nodes, and in a team's
    namespace the team's names from every other team's (one line each, when measured)."""
    lines = []
    apart = rep.get('truth_apart')
    if apart:
        readers = apart['truth_readers']
        lines.append(
            f'Truth apart: of the graph\'s {apart["nodes"]} nodes, the '
            f'{len(apart["loop_nodes"])} that close loops '
            + ("read none of the simulator's truth topics." if not readers else
               'include truth readers: ' + '; '.join(f'{n} ({", ".join(t)})'
                                                     for n, t in readers.items()) + '.'))
    names = rep.get('names_apart')
    if names and names['team']:
        stray = '; '.join(f'{n} ({", ".join(t)})' for n, t in names['stray'].items())
        lines.append(f"Names that cross the team's namespace: {stray}." if stray else
                     f"Names apart: every topic of the team's nodes is under /{names['team']}/ "
                     "(ROS 2's own and the transform tree aside).")
    return '\n'.join(lines)


def _run_files(rep: dict) -> list[str]:
    """The bag of the run and the live view, when the mission had them."""
    lines = []
    bag = rep.get('bag')
    if bag and 'error' in bag:
        lines.append(f'Bag: none usable in `{bag["path"]}/` ({bag["error"]}).')
    elif bag:
        state = 'closed cleanly' if bag['closed'] and not bag['problems'] else \
            'not closed: ' + ('; '.join(bag['problems']) or 'no metadata.yaml')
        lines.append(
            f'Bag: `{bag["path"]}/`, {bag["messages"]} messages on {len(bag["topics"])} topics, '
            f'{_fmt(bag["duration_s"], ".0f")} sim s, {_fmt(bag["size_mb"], ".1f")} MB'
            f'{"" if bag["all"] else " (images, stereo clouds, map snapshots left out)"}, '
            f'{state}; '
            'replay it with `ros2 run rover_bag play` or read it with '
            '`rover_bag.bagio.read_messages`.')
    if rep.get('live_view'):
        lines.append(f'Live view served on {rep["live_view"]["url"]}.')
    lines += format_apart(rep).splitlines()
    return [*lines, ''] if lines else []


def write_report(rep: dict, out: Path, **extras: Any) -> tuple[Path, Path]:
    """report.json and report.md (with PNG plots) under `out`. extras: top_view (from
    `top_view`), paths {rover: (N, 2) odometry xy}, occupied_points (N, 3), insertion_curves
    (an Attempt's curves); they go into the plots only."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rep['plots'] = _plots(rep, out, extras)
    js = write_json(out / 'report.json', rep)
    lines = [f'# Mission report: {rep["run_id"]}', '',
             f'Scenario: seed {rep["config"]["seed"]}, occlusion density '
             f'{rep["config"]["occlusion_density"]}, slot {rep["config"]["slot_in"]} in, '
             f'{rep["config"]["rovers"]} rovers; phases {", ".join(rep["config"]["phases"])}. '
             f"Judged by the simulator's truth.", '',
             format_summary(rep), '']
    lines += _run_files(rep)
    ident = rep.get('identification', {}).get('rovers', {})
    if ident:
        lines += ['## Identification (ch. 2)', '',
                  '| rover | mean abs. rel. error | samples | message |', '|---|---|---|---|']
        for rover, r in sorted(ident.items()):
            e = r.get('mean_abs_rel_error')
            lines.append(f'| {rover} | {_fmt(None if e is None else 100 * e, ".1f")} % | '
                         f'{r.get("samples", "-")} | {r.get("message", "")} |')
        lines += ['', '| parameter | ' + ' | '.join(
            f'{r} truth | {r} estimate | {r} bits' for r in sorted(ident)) + ' |',
            '|---|' + '---|---|---|' * len(ident)]
        names = [p['name'] for p in next(iter(ident.values()))['params']]
        for k, name in enumerate(names):
            cells = []
            for rover in sorted(ident):
                p = ident[rover]['params'][k]
                cells.append(f'{_fmt(p["truth"], ".4g")} | {_fmt(p["estimate"], ".4g")} | '
                             f'{_fmt(p["information_bits"], ".1f")}')
            lines.append(f'| {name} | ' + ' | '.join(cells) + ' |')
        lines.append('')
    for key, title in (('identification', 'Relative errors'),
                       ('coverage', 'Mapping (ch. 3): coverage against scans and distance'),
                       ('map_top', 'The map from above'), ('map_3d', 'The map in 3-D')):
        if key in rep['plots']:
            lines += [f'![{title}]({rep["plots"][key]})', '']
    place = rep.get('placement', {})
    if place:
        lines += ['## Camera placement (ch. 4, Eq. 4-1)', '',
                  '| position (m) | yaw, pitch (deg) | RF | DOF | Res | TFV | TAV | P |',
                  '|---|---|---|---|---|---|---|---|',
                  f'| {", ".join(_fmt(v, ".2f") for v in place.get("position", []))} | '
                  f'{_fmt(place.get("yaw_deg"), ".0f")}, {_fmt(place.get("pitch_deg"), ".0f")} | '
                  + ' | '.join(_fmt(place.get(k), '.3g') for k in
                               ('rating', 'depth_of_field', 'resolution', 'field_visibility',
                                'angular_visibility', 'collision_probability')) + ' |', '']
    ins = rep.get('insertion', {})
    if ins:
        lines += ['## Insertion (ch. 5, app. A.4)', '',
                  f'{"Success" if ins.get("success") else "Failure"}: {ins.get("reason", "")}. '
                  f'Seated: {ins.get("seated")}; deepest penetration '
                  f'{_fmt(ins.get("max_penetration_mm"), ".2f")} mm; peak force '
                  f'{_fmt(ins.get("peak_force_n"), ".1f")} N; {_fmt(ins.get("sim_s"), ".1f")} '
                  'sim s.', '']
        if 'insertion' in rep['plots']:
            lines += [f'![Insertion curves]({rep["plots"]["insertion"]})', '']
    md = write_text_atomic(out / 'report.md', '\n'.join(lines))
    return md, js
