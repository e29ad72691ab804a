r"""Figs. 3-13, 3-16, 3-20: fraction mapped and distance moved vs scan number for the five pose
selection methods of §3.3.1 and a nearest-frontier baseline, mean and 95 % interval over seeds.

    ros2 run coop_viewplan fig_3_13 --world unstructured --cameras 1 --seeds 5 --scans 150 \
        --json out/fig_3_13.json --plots out/fig_3_13
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from scipy import stats

from coop_common.cli import enum_choices, number, output_dir, output_path
from coop_common.files import save_figure, write_json
from coop_common.params import choice

from .errors import OptionError
from .explore import WorldName, explore, make_world
from .grid import OcclusionPrior
from .nbv import (
    STRATEGIES,
    DistanceMetric,
    EntropyWeight,
    NbvConfig,
    NiMeasure,
    StrategyName,
    UnknownOcclusion,
)

THESIS_FIGURE = {('unstructured', 1): 'Fig. 3-13', ('unstructured', 2): 'Fig. 3-16',
                 ('rooms', 1): 'Fig. 3-20'}


def _ci(a: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean and 95 % t-interval over axis 0."""
    a = np.asarray(a, float)
    m = a.mean(axis=0)
    n = a.shape[0]
    if n < 2:
        return m, m.copy(), m.copy()
    h = stats.t.ppf(0.975, n - 1) * a.std(axis=0, ddof=1) / np.sqrt(n)
    return m, m - h, m + h


def _first_reach(frac: np.ndarray, level: float) -> int | None:
    hit = np.flatnonzero(frac >= level)
    return int(hit[0]) if len(hit) else None


def _summary(values: Sequence[float | None]) -> dict:
    got = [v for v in values if v is not None]
    out = {'per_seed': values, 'reached': len(got), 'mean': None, 'ci95': None}
    if got:
        m, lo, hi = _ci(np.array(got)[:, None])
        out.update(mean=float(m[0]), ci95=[float(lo[0]), float(hi[0])])
    return out


def run(*, world: WorldName | str, cameras: int, fov_deg: float, depth_m: float, seeds: int,
        scans: int, resolution_m: float, strategies: Sequence[StrategyName | str], k_rel: float,
        n_positions: int, distance_metric: DistanceMetric | str = NbvConfig.distance_metric,
        level: float = 0.9, near_fraction: float = 0.0, angle_weight: float = 1.0,
        entropy_weight: EntropyWeight | str = NbvConfig.entropy_weight,
        ni_measure: NiMeasure | str = NbvConfig.ni_measure,
        unknown_occlusion: UnknownOcclusion | str = NbvConfig.unknown_occlusion,
        occlusion_prior: OcclusionPrior | str = NbvConfig.occlusion_prior,
        ni_floor: float = NbvConfig.ni_floor) -> dict:
    """Each strategy over `seeds` worlds; an unknown strategy or mode (NbvConfig's) is an
    OptionError naming the choices, before any run."""
    names = [choice(StrategyName, s, 'strategy', error=OptionError) for s in strategies]
    distance_metric = choice(DistanceMetric, distance_metric, 'distance_metric',
                             error=OptionError)
    entropy_weight = choice(EntropyWeight, entropy_weight, 'entropy_weight', error=OptionError)
    ni_measure = choice(NiMeasure, ni_measure, 'ni_measure', error=OptionError)
    unknown_occlusion = choice(UnknownOcclusion, unknown_occlusion, 'unknown_occlusion',
                               error=OptionError)
    occlusion_prior = choice(OcclusionPrior, occlusion_prior, 'occlusion_prior',
                             error=OptionError)
    cfg = NbvConfig(fov_deg=fov_deg, depth_m=depth_m, k_rel=k_rel, n_positions=n_positions,
                    distance_metric=distance_metric, near_fraction=near_fraction,
                    alpha=(1.0, 1.0, 1.0, angle_weight, angle_weight),
                    entropy_weight=entropy_weight, ni_measure=ni_measure,
                    unknown_occlusion=unknown_occlusion, occlusion_prior=occlusion_prior,
                    ni_floor=ni_floor)
    res: dict = {}
    for name in names:
        fr, di, s90, d90, room90, leave, rooms_final = [], [], [], [], [], [], []
        t0 = time.perf_counter()
        for seed in range(seeds):
            w = make_world(world, seed=seed, resolution=resolution_m)
            tr = explore(w, strategy=name, n_cameras=cameras, config=cfg, scans=scans,
                         seed=1000 + seed)
            fr.append(tr.fraction)
            di.append(tr.distance)
            k = _first_reach(tr.fraction, level)
            s90.append(k)
            d90.append(None if k is None else float(tr.distance[k]))
            if w.start_room is not None and tr.room_fraction is not None:    # set together
                room90.append(_first_reach(tr.room_fraction, level))
                rooms_final.append(float(tr.room_fraction[-1]))
                leave.append(tr.scans_to_leave_start_room(w))
        fm, flo, fhi = _ci(np.array(fr))
        dm, dlo, dhi = _ci(np.array(di))
        s_sum, d_sum = _summary(s90), _summary(d90)
        res[name] = {
            'scans_to_90pct': s_sum['mean'], 'distance_to_90pct_m': d_sum['mean'],
            'scans_to_90pct_detail': s_sum, 'distance_to_90pct_detail': d_sum,
            'final_fraction': float(fm[-1]), 'final_distance_m': float(dm[-1]),
            'seconds': time.perf_counter() - t0,
            'curve': {'scan': list(range(scans + 1)),
                      'fraction_mean': fm.tolist(), 'fraction_lo': flo.tolist(),
                      'fraction_hi': fhi.tolist(), 'distance_mean_m': dm.tolist(),
                      'distance_lo_m': dlo.tolist(), 'distance_hi_m': dhi.tolist()},
        }
        if room90:
            # Fig. 3-20's claim: the first to map its room and find its way out into the corridor
            res[name]['scans_to_map_start_room'] = _summary(room90)
            res[name]['scans_to_leave_start_room'] = _summary(leave)
            res[name]['final_start_room_fraction'] = float(np.mean(rooms_final))
    return res


def _fmt(v: float | None, ci: list | None = None, p: int = 0) -> str:
    if v is None:
        return 'not reached'
    s = f'{v:.{p}f}'
    if ci is not None:
        s += f' [{ci[0]:.{p}f}, {ci[1]:.{p}f}]'
    return s


def _scans_cell(summary: dict, seeds: int) -> str:
    """'mean [95 % CI]' and 'reached/seeds' of a _summary of scan counts, table-aligned."""
    return (f"{_fmt(summary['mean'], summary['ci95'], 1):>24s} "
            f"{summary['reached']:>4d}/{seeds:<3d}")


def verdict(strategies: dict) -> dict:
    """Where maximum information stands: rank among the five thesis methods (censored runs
    count as scans + 1), distance ratio against the frontier baseline."""
    def key(name: str, what: str) -> float:
        d = strategies[name][what + '_detail']
        return d['mean'] if d['mean'] is not None and d['reached'] == len(d['per_seed']) \
            else float('inf')
    five = [s for s in STRATEGIES[:5] if s in strategies]
    out: dict = {}
    if 'max_information' in strategies:
        for what in ('scans_to_90pct', 'distance_to_90pct'):
            # Runs that never reach 90 % rank after those that do, by their final fraction.
            order = sorted(five, key=lambda s: (key(s, what),
                                                -strategies[s]['final_fraction']))
            out[f'{what}_rank_of_max_information'] = order.index(StrategyName.MAX_INFORMATION) + 1
            out[f'{what}_order'] = order
        ranked = sorted(five, key=lambda s: -strategies[s]['final_fraction'])
        out['final_fraction_rank_of_max_information'] = \
            ranked.index(StrategyName.MAX_INFORMATION) + 1
        for what in ('scans_to_map_start_room', 'scans_to_leave_start_room'):
            if what in strategies['max_information']:
                def room_key(name: str, what: str = what) -> tuple[float, float]:
                    # censored runs after the others, by the share of the room they mapped
                    d = strategies[name][what]
                    return (d['mean'] if d['reached'] == len(d['per_seed']) else float('inf'),
                            -strategies[name]['final_start_room_fraction'])
                order = sorted(five, key=room_key)
                out[f'{what}_rank_of_max_information'] = \
                    order.index(StrategyName.MAX_INFORMATION) + 1
                out[f'{what}_order'] = order
        if 'frontier' in strategies:
            a = key('max_information', 'distance_to_90pct')
            b = key('frontier', 'distance_to_90pct')
            out['distance_to_90pct_max_information_over_frontier'] = (
                a / b if np.isfinite(a) and np.isfinite(b) else None)
            a = key('max_information', 'scans_to_90pct')
            b = key('frontier', 'scans_to_90pct')
            out['scans_to_90pct_max_information_over_frontier'] = (
                a / b if np.isfinite(a) and np.isfinite(b) else None)
    return out


def plot(result: dict, out_dir: Path) -> list[Path]:
    """Draw the mapped-fraction and distance curves into `out_dir`; the files written."""
    import matplotlib  # noqa: PLC0415 - heavy, only when plots are asked for
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415 - heavy, only when plotting
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for name, r in result['strategies'].items():
        c = r['curve']
        x = c['scan']
        line, = ax[0].plot(x, c['fraction_mean'], label=name)
        ax[0].fill_between(x, c['fraction_lo'], c['fraction_hi'], color=line.get_color(),
                           alpha=0.2)
        ax[1].plot(x, c['distance_mean_m'], label=name, color=line.get_color())
        ax[1].fill_between(x, c['distance_lo_m'], c['distance_hi_m'], color=line.get_color(),
                           alpha=0.2)
    ax[0].axhline(0.9, color='k', lw=0.5, ls='--')
    ax[0].set(xlabel='scan number', ylabel='fraction of environment mapped', ylim=(0, 1))
    ax[1].set(xlabel='scan number', ylabel='distance moved (m)')
    ax[0].legend(fontsize=8)
    fig.suptitle(f"{result['figure']}: {result['world']}, {result['cameras']} camera(s), "
                 f"{result['fov_deg']:.0f} deg / {result['depth_m']:.0f} m, "
                 f"{result['seeds']} seeds (mean, 95% CI)")
    stem = f"fig_3_13_{Path(result['world']).stem}_{result['cameras']}cam"
    return [save_figure(fig, out_dir / f'{stem}.png', dpi=110)]


def format_json(result: dict) -> str:
    """The printed table of a result, as `--json` writes it."""
    r = result
    seeds, strat = r['seeds'], r['strategies']
    lines = [f"{r['figure']}: world={r['world']} cameras={r['cameras']} "
             f"fov={r['fov_deg']:.0f} deg depth={r['depth_m']:.0f} m seeds={seeds} "
             f"scans={r['scans']} res={r['resolution_m']} m"
             + (f" unknown_occlusion=expected/{r['occlusion_prior']}"
                if r['unknown_occlusion'] == UnknownOcclusion.EXPECTED else '')
             + (f" ni_floor={r['ni_floor']:g}" if r['ni_floor'] > 0 else '')
             + (f" near_fraction={r['near_fraction']:g}" if r['near_fraction'] > 0 else '')
             + (f" distance={r['distance']}"
                if r['distance'] != DistanceMetric.CONFIGURATION else '')
             + (f" k_rel={r['k_rel']:g}" if r['k_rel'] != NbvConfig.k_rel else '')
             + (f" candidates={r['candidates']}" if r['candidates'] != NbvConfig.n_positions
                else '')
             + (f" angle_weight={r['angle_weight']:g}"
                if r.get('angle_weight', NbvConfig.alpha[3]) != NbvConfig.alpha[3] else '')
             + (f" entropy_weight={r['entropy_weight']}"
                if r.get('entropy_weight', NbvConfig.entropy_weight) != NbvConfig.entropy_weight
                else '')
             + (f" ni_measure={r['ni_measure']}"
                if r.get('ni_measure', NbvConfig.ni_measure) != NbvConfig.ni_measure else '')]
    lines.append(f"{'strategy':16s} {'scans to 90% [95% CI]':>24s} {'reached':>8s} "
                 f"{'distance to 90% m [95% CI]':>30s} {'final frac':>10s} {'final dist m':>12s}")
    for name, v in strat.items():
        d = v['distance_to_90pct_detail']
        lines.append(f"{name:16s} {_scans_cell(v['scans_to_90pct_detail'], seeds)} "
                     f"{_fmt(d['mean'], d['ci95']):>30s} "
                     f"{v['final_fraction']:>10.3f} {v['final_distance_m']:>12.0f}")
    if any('scans_to_map_start_room' in v for v in strat.values()):
        lines.append('start room (Fig. 3-20: "the information theoretic vision algorithm is the '
                     'first to map the room and find its way out into the corridor"): scans until '
                     '90 % of the start room is mapped, and until a camera scans from outside its '
                     'walls')
        lines.append(f"{'strategy':16s} {'room 90% [95% CI]':>24s} {'reached':>8s} "
                     f"{'left room [95% CI]':>24s} {'reached':>8s}")
        for name, v in strat.items():
            lines.append(f"{name:16s} {_scans_cell(v['scans_to_map_start_room'], seeds)} "
                         f"{_scans_cell(v['scans_to_leave_start_room'], seeds)}")
    if 'one_camera_max_information' in r:
        o = r['one_camera_max_information']
        lines.append(f"{'max_info 1 cam':16s} {_fmt(o['scans_to_90pct'], None, 1):>24s} "
                     f"{o['scans_to_90pct_detail']['reached']:>4d}/{seeds:<3d}")
    lines.append('verdict: ' + json.dumps(r['verdict']))
    return '\n'.join(lines)


def build_parser() -> argparse.ArgumentParser:
    """fig_3_13's command line."""
    p = argparse.ArgumentParser(prog='fig_3_13', description=__doc__.split('\n\n')[0])
    p.add_argument('--world', default=WorldName.UNSTRUCTURED.value,
                   help=f'{" | ".join(enum_choices(WorldName))} | path to a PNG (dark = '
                        'obstacle)')
    p.add_argument('--cameras', type=int, choices=(1, 2), default=1)
    p.add_argument('--fov-deg', type=number(lo=0, hi=180, lo_open=True, hi_open=True),
                   default=None,
                   help='default: 90 (one camera, unstructured) else 75, as in the thesis')
    p.add_argument('--depth-m', type=number(lo=0, lo_open=True), default=None,
                   help='default: 15 (one camera, unstructured) else 10, as in the thesis')
    p.add_argument('--seeds', type=number(int, lo=1), default=5)
    p.add_argument('--scans', type=number(int, lo=1), default=150)
    p.add_argument('--resolution-m', type=number(lo=0.1, hi=50), default=1.0,
                   help='cell size of the world and the map (m; 0.1-50)')
    p.add_argument('--strategies', default=','.join(STRATEGIES))
    p.add_argument('--k-rel', type=number(lo=0), default=NbvConfig.k_rel,
                   help='K of Eq. 3-15 relative to the NI of a fully unknown view per depth')
    p.add_argument('--distance', choices=enum_choices(DistanceMetric),
                   default=NbvConfig.distance_metric.value,
                   help='d of Eq. 3-15: Eq. 3-11 straight-line configuration distance, or '
                        'with the translation measured along the collision-free path')
    p.add_argument('--candidates', type=number(int, lo=1), default=NbvConfig.n_positions,
                   help='candidate positions per decision (x 8 headings)')
    p.add_argument('--near-fraction', type=number(lo=0, hi=1),
                   default=NbvConfig.near_fraction,
                   help='share of the candidate positions taken nearest to the camera (path '
                        'length), the rest at random (thesis: "random, closest to current '
                        'pose, etc."); default: all random')
    p.add_argument('--angle-weight', type=number(lo=0), default=NbvConfig.alpha[3],
                   help='alpha of yaw and pitch in Eq. 3-11 (m per rad); thesis: "alpha_i = 1 '
                        'for this thesis" (default); 0 = the pre-2026-11-21 runs')
    p.add_argument('--entropy-weight', choices=enum_choices(EntropyWeight),
                   default=NbvConfig.entropy_weight.value,
                   help='premultiplier of q_k log2 q_k in NI: -p_k log2 p_k as the thesis writes '
                        'it (plogp, default) or the binary occupancy entropy (the pre-2026-11-21 '
                        'runs)')
    p.add_argument('--ni-measure', choices=enum_choices(NiMeasure),
                   default=NbvConfig.ni_measure.value,
                   help='NI binning: gray levels of the cells in view (Eq. 3-13, default) or the '
                        "App. C predictor-5 residual of the view's gray image")
    p.add_argument('--unknown-occlusion', choices=enum_choices(UnknownOcclusion),
                   default=NbvConfig.unknown_occlusion.value,
                   help='none: the expected view is occluded by the known obstacles only '
                        '(thesis, default); expected: each cell counts with its probability of '
                        'being seen past the unknown cells before it (beyond the thesis)')
    p.add_argument('--occlusion-prior', choices=enum_choices(OcclusionPrior),
                   default=NbvConfig.occlusion_prior.value,
                   help="with --unknown-occlusion expected: unknown cells' occupancy, the "
                        "Markov chain started from the known map's obstacle density (density, "
                        "default) or the planner's Markov-chain estimate as it is (markov, 0.5 "
                        "far from the map)")
    p.add_argument('--ni-floor', type=number(lo=0, hi=1, hi_open=True),
                   default=NbvConfig.ni_floor,
                   help='max_information: only views with at least this share of the '
                        "decision's best NI compete (beyond the thesis; 0, default: the plain "
                        'argmax of Eq. 3-15)')
    p.add_argument('--compare-one-camera', action='store_true',
                   help='with --cameras 2: also run max_information with one camera, same '
                        'sensor, and report the scans ratio')
    p.add_argument('--json', type=output_path, default=None)
    p.add_argument('--plots', type=output_dir, default=None, help='directory for PNG plots')
    return p


def main(argv: list[str] | None = None) -> int:
    """`ros2 run coop_viewplan fig_3_13`: the exploration runs over seeds, table and plots."""
    parser = build_parser()
    args = parser.parse_args(argv)
    default_wide = args.world == WorldName.UNSTRUCTURED and args.cameras == 1
    fov = args.fov_deg if args.fov_deg is not None else (90.0 if default_wide else 75.0)
    depth = args.depth_m if args.depth_m is not None else (15.0 if default_wide else 10.0)
    names = [s.strip() for s in args.strategies.split(',') if s.strip()]
    bad = [s for s in names if s not in STRATEGIES]
    if bad or not names:
        parser.error(f'--strategies: unknown {bad}; of {enum_choices(StrategyName)}')
    strategies = [StrategyName(s) for s in names]
    if depth < args.resolution_m:         # the view would hold no cell
        parser.error(f'--depth-m {depth} is below --resolution-m {args.resolution_m}')
    try:
        make_world(args.world, seed=0, resolution=args.resolution_m)
    except (ValueError, OSError, SyntaxError) as exc:     # PIL: SyntaxError for "not a PNG"
        parser.error(f'--world {args.world}: {exc}')
    common = dict(world=args.world, fov_deg=fov, depth_m=depth, seeds=args.seeds,
                  scans=args.scans, resolution_m=args.resolution_m, k_rel=args.k_rel,
                  n_positions=args.candidates, distance_metric=args.distance,
                  near_fraction=args.near_fraction, angle_weight=args.angle_weight,
                  entropy_weight=args.entropy_weight, ni_measure=args.ni_measure,
                  unknown_occlusion=args.unknown_occlusion, occlusion_prior=args.occlusion_prior,
                  ni_floor=args.ni_floor)
    strat = run(cameras=args.cameras, strategies=strategies, **common)
    result = {'figure': THESIS_FIGURE.get((args.world, args.cameras), 'Fig. 3-13 analogue'),
              'world': args.world, 'cameras': args.cameras, 'fov_deg': fov, 'depth_m': depth,
              'seeds': args.seeds, 'scans': args.scans, 'resolution_m': args.resolution_m,
              'k_rel': args.k_rel, 'distance': args.distance, 'candidates': args.candidates,
              'near_fraction': args.near_fraction, 'angle_weight': args.angle_weight,
              'entropy_weight': args.entropy_weight, 'ni_measure': args.ni_measure,
              'unknown_occlusion': args.unknown_occlusion,
              'occlusion_prior': args.occlusion_prior, 'ni_floor': args.ni_floor,
              'strategies': strat,
              'verdict': verdict(strat)}
    if args.compare_one_camera and args.cameras == 2:
        one = run(cameras=1, strategies=[StrategyName.MAX_INFORMATION],
                  **common)[StrategyName.MAX_INFORMATION]
        two = strat.get(StrategyName.MAX_INFORMATION)
        ratio = None
        if two and one['scans_to_90pct'] and two['scans_to_90pct']:
            ratio = one['scans_to_90pct'] / two['scans_to_90pct']
        result['one_camera_max_information'] = {k: one[k] for k in (
            'scans_to_90pct', 'distance_to_90pct_m', 'scans_to_90pct_detail', 'final_fraction')}
        result['verdict']['scans_one_over_two_cameras'] = ratio
    print(format_json(result))
    if args.plots is not None:
        for p in plot(result, args.plots):
            print(f'plot: {p}')
    if args.json is not None:
        write_json(args.json, result, indent=1)
        print(f'json: {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
