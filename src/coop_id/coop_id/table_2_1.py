"""Experiment executable: reproduce thesis Table 2-1, Fig. 2-6 and Fig. 2-7 (§2.6.1).

    ros2 run coop_id table_2_1 --seeds 30 --json out.json --plots figs/

Runs the thesis scenario on the model-level simulation (coop_id.modelsim) for each strategy and
seed, prints the Table 2-1 layout (true value, the thesis's two columns as quoted reference data,
then the mean estimate of each strategy over the seeds), the mean absolute relative error, the
time to 20 % mean error, 95 % interval coverage and physical consistency, and writes JSON.
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from coop_common.cli import enum_choices, number, output_dir, output_path
from coop_common.dynparams import PARAM_LABELS, PARAM_NAMES, TruthFileError, load_truth
from coop_common.files import save_figure, write_json
from rover_sim.config import Integrator

from . import offline
from .excitation import STRATEGIES, Strategy
from .experiment import RunResult, reference_noise_scales, run_identification
from .identifier_core import IdentifierConfig

#: Thesis Table 2-1, quoted as reference data (constant / variable excitation columns).
THESIS_CONSTANT = (4.021, 0.123, 0.054, 0.119, 0.045, 0.071, 0.037, 0.030, 0.512, -1.053,
                   142.554, 139.956, 22.368, 78.665, 105.061, 133.714, 1103.281, 1094.529,
                   390.469, 945.103, 1950.426, 2402.537)
THESIS_VARIABLE = (3.655, 0.144, 0.089, 0.177, 0.011, 0.047, 0.014, 0.012, 0.360, 0.042,
                   78.362, 75.559, 16.757, 195.264, 266.254, 333.860, 979.494, 1244.836,
                   375.479, 1934.569, 2394.257, 2891.637)
THESIS_AVG_ERROR = {'constant': 108.8, 'variable': 18.9}


def rel_errors(est: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """|est - truth| / |truth| over the parameters whose true value is non-zero.

    (A relative error of a zero product of inertia is undefined; those are judged by the 95 %
    interval coverage instead. The thesis's own columns give 110.1 % / 21.8 % by this rule.)"""
    nz = truth != 0
    return np.abs(est[..., nz] - truth[nz]) / np.abs(truth[nz])


def time_to(times: np.ndarray, curve: np.ndarray, level: float) -> float | None:
    """First time after which the curve stays <= level (None if it never settles there)."""
    times, curve = np.asarray(times, dtype=float), np.asarray(curve, dtype=float)
    above = np.flatnonzero(curve > level)
    if above.size == 0:
        return float(times[0])
    if above[-1] == curve.size - 1:
        return None
    return float(times[above[-1] + 1])


def summarise(runs: Mapping[Strategy, list[RunResult]], truth: np.ndarray) -> dict:
    """Per strategy: final and per-parameter errors over the seeds, error curves, coverage and
    consistency (the JSON summary)."""
    out = {}
    for name, rs in runs.items():
        final = np.stack([r.estimates[-1] for r in rs])
        std = np.stack([r.std[-1] for r in rs])
        err_final = rel_errors(final, truth).mean(axis=1)
        curves = np.stack([rel_errors(np.stack(r.estimates), truth).mean(axis=1) for r in rs])
        times = rs[0].times
        mean_curve = curves.mean(axis=0)
        per_seed_t20 = [time_to(times, c, 0.2) for c in curves]
        low = np.stack([r.final_low for r in rs])
        high = np.stack([r.final_high for r in rs])
        cover = (low <= truth) & (truth <= high)
        obs = np.stack([r.observable for r in rs])
        consistent = np.mean([np.mean(r.consistent) for r in rs])
        info = np.stack([r.info_bits[-1] for r in rs]).mean(axis=0)
        out[name] = {
            'mean_abs_rel_error': float(err_final.mean()),
            'mean_abs_rel_error_seed_std': float(err_final.std()),
            'time_to_20pct_s': time_to(times, mean_curve, 0.2),
            'time_to_20pct_s_per_seed_median': _median_or_none(per_seed_t20),
            'coverage_95': float(cover.mean()),
            'coverage_95_observable': float(cover[obs].mean()) if obs.any() else None,
            'physically_consistent_fraction': float(consistent),
            'per_parameter': {
                n: {'estimate': float(final[:, i].mean()), 'std': float(std[:, i].mean()),
                    'seed_spread': float(final[:, i].std()),
                    'information_bits': float(info[i]),
                    'observable_fraction': float(obs[:, i].mean()),
                    'coverage_95': float(cover[:, i].mean())}
                for i, n in enumerate(PARAM_NAMES)},
            'error_curve': {'t': times.tolist(), 'mean_abs_rel_error': mean_curve.tolist()},
        }
    return out


def _median_or_none(v: list[float | None]) -> float | None:
    """Median time over seeds, counting 'never' as +inf (None if most seeds never get there)."""
    arr = np.array([np.inf if x is None else x for x in v])
    med = float(np.median(arr))
    return None if not np.isfinite(med) else med


def format_table(summary: dict, truth: np.ndarray, seeds: int) -> str:
    """The summary as Table 2-1's text: the estimates next to the thesis's, then per strategy."""
    names = list(summary)
    head = f'{"Parameter":16s}{"True":>10s}{"thesis:const":>13s}{"thesis:var":>12s}'
    head += ''.join(f'{n:>13s}' for n in names)
    lines = [f'Table 2-1 reproduction: mean estimate over {seeds} seed(s)', head,
             '-' * len(head)]
    for i, p in enumerate(PARAM_NAMES):
        row = f'{PARAM_LABELS[p]:16s}{truth[i]:10.4g}{THESIS_CONSTANT[i]:13.4g}'
        row += f'{THESIS_VARIABLE[i]:12.4g}'
        row += ''.join(f'{summary[n]["per_parameter"][p]["estimate"]:13.4g}' for n in names)
        lines.append(row)
    lines.append('-' * len(head))
    th_c = 100 * rel_errors(np.array(THESIS_CONSTANT), truth).mean()
    th_v = 100 * rel_errors(np.array(THESIS_VARIABLE), truth).mean()
    row = f'{"% Avg. Error":16s}{"":10s}{th_c:13.1f}{th_v:12.1f}'
    row += ''.join(f'{100 * summary[n]["mean_abs_rel_error"]:13.1f}' for n in names)
    lines.append(row)
    lines.append(f'(thesis prints 108.8 / 18.9 over its own averaging; the same 20 non-zero '
                 f'parameters give {th_c:.1f} / {th_v:.1f})')
    lines.append('')
    lines.append(f'{"strategy":12s}{"err %":>8s}{"+-seed":>8s}{"t20 s":>8s}{"t20 med":>9s}'
                 f'{"cover95":>9s}{"consist":>9s}')
    for n in names:
        s = summary[n]
        t20 = 'never' if s['time_to_20pct_s'] is None else f'{s["time_to_20pct_s"]:.1f}'
        t20m = ('never' if s['time_to_20pct_s_per_seed_median'] is None
                else f'{s["time_to_20pct_s_per_seed_median"]:.1f}')
        lines.append(f'{n:12s}{100 * s["mean_abs_rel_error"]:8.1f}'
                     f'{100 * s["mean_abs_rel_error_seed_std"]:8.1f}{t20:>8s}{t20m:>9s}'
                     f'{100 * s["coverage_95"]:8.1f}%'
                     f'{100 * s["physically_consistent_fraction"]:8.1f}%')
    if Strategy.CONSTANT in summary:
        base = summary[Strategy.CONSTANT]['mean_abs_rel_error']
        for n in names:
            if n != Strategy.CONSTANT:
                lines.append(f'ratio {n}/constant = {summary[n]["mean_abs_rel_error"] / base:.3f}')
    return '\n'.join(lines)


def _truth(doc: dict) -> np.ndarray:
    return np.array([doc['truth'][p] for p in PARAM_NAMES], dtype=float)


def format_json(doc: dict) -> str:
    """The model-level study's printed result, from its JSON (docs/results is made with it).

    Without the accelerometer (§2.6.2) the parameters it cannot see stay at the prior and weigh
    on the mean error; the rotational subset is then summed up on its own: the error of the
    seed-mean estimate over the non-zero parameters some strategy observes (those flagged
    unobservable in every seed of every strategy are left out), and each strategy's 95 %
    coverage of the parameters it flagged observable."""
    summary = doc['strategies']
    truth = _truth(doc)
    out = format_table(summary, truth, doc['seeds'])
    if doc['accelerometer']:
        return out
    seen = [i for i, p in enumerate(PARAM_NAMES) if truth[i] != 0 and any(
        s['per_parameter'][p]['observable_fraction'] > 0 for s in summary.values())]
    lines = [out, '', f'without accelerometer, over the {len(seen)} non-zero parameters some '
             'strategy observes (error of the seed-mean estimate):']
    for n, s in summary.items():
        est = np.array([s['per_parameter'][PARAM_NAMES[i]]['estimate'] for i in seen])
        err = np.mean(np.abs(est - truth[seen]) / np.abs(truth[seen]))
        cov = s['coverage_95_observable']
        cov_s = '-' if cov is None else f'{100 * cov:.1f}%'
        lines.append(f'{n:12s} err {100 * err:6.1f}%  cover95 of its observable {cov_s}')
    return '\n'.join(lines)


def draw_plots(runs: Mapping[Strategy, list[RunResult]], truth: np.ndarray, out_dir: Path
               ) -> list[Path]:
    """Draw the convergence plots into `out_dir`; the files written."""
    import matplotlib  # noqa: PLC0415 - only when plots are asked for
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415

    paths = []
    k = PARAM_NAMES.index('k_pitch')
    fig, ax = plt.subplots(figsize=(6, 4))
    for name, rs in runs.items():
        bits = np.stack([np.stack(r.info_bits)[:, k] for r in rs]).mean(axis=0)
        ax.plot(rs[0].times, bits, label=name)
    ax.set_xlabel('time (s)')
    ax.set_ylabel('mutual information (bits)')
    ax.set_title('Fig. 2-6: information in stiffness theta_p (mean over seeds)')
    ax.set_ylim(0, 10.5)
    ax.legend()
    paths.append(save_figure(fig, out_dir / 'fig_2_6_information_k_pitch.png'))
    params = ('cg_y', 'cg_z', 'mass', 'Ixx', 'b_y', 'k_pitch', 'k_y')
    fig, axes = plt.subplots(2, 4, figsize=(14, 6))
    for ax, p in zip(axes.ravel(), params, strict=False):
        i = PARAM_NAMES.index(p)
        for name, rs in runs.items():
            ax.plot(rs[0].times, np.stack(rs[0].estimates)[:, i], label=name)
        ax.axhline(truth[i], color='k', ls='--', lw=1)
        ax.set_title(PARAM_LABELS[p])
        ax.set_xlabel('time (s)')
    axes.ravel()[-1].axis('off')
    axes.ravel()[0].legend(fontsize=7)
    fig.suptitle('Fig. 2-7: convergence (seed of the first run; dashed: true value)')
    paths.append(save_figure(fig, out_dir / 'fig_2_7_convergence.png'))
    return paths


#: what each mode reads besides --json: an option given to a mode that does not read it (even at
#: its default value) is a usage error, not a silent no-op
_MODE_OPTIONS = {
    'model': ('truth', 'seeds', 'first_seed', 'duration', 'noise', 'strategies',
              'no_accelerometer', 'no_bias_compensation', 'plots'),
    'sim': ('duration', 'noise', 'strategies', 'integrator', 'lockstep', 'busy_too'),
    'bag': ('bag', 'rover', 'no_accelerometer', 'no_bias_compensation'),
}


def _strategies(text: str) -> list[Strategy]:
    names = text.split(',')
    bad = [s for s in names if s not in STRATEGIES]
    if bad:
        raise argparse.ArgumentTypeError(f'unknown strategies {bad}; choose from '
                                         f'{",".join(STRATEGIES)}')
    if len(set(names)) != len(names):
        raise argparse.ArgumentTypeError(f'a strategy is listed twice: {text}')
    return [Strategy(n) for n in names]


def _existing(text: str) -> Path:
    p = Path(text)
    if not p.exists():
        raise argparse.ArgumentTypeError(f'{text} does not exist')
    return p


def _given(ap: argparse.ArgumentParser, argv: list[str]) -> set[str]:
    """The destinations of the options spelled out in `argv` (at their default value too)."""
    out = set()
    for action in ap._actions:
        for opt in action.option_strings:
            if any(a == opt or a.startswith(opt + '=') for a in argv):
                out.add(action.dest)
    return out


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """table_2_1's command line."""
    window_s = IdentifierConfig().window_s
    # no abbreviations: an option is given when one of its spellings is in argv (_given)
    ap = argparse.ArgumentParser(prog='table_2_1', description=__doc__.splitlines()[0],
                                 allow_abbrev=False)
    ap.add_argument('--truth', type=_existing, default=None, help='true parameter YAML '
                    '(default: Table 2-1, coop_common/data/table_2_1_truth.yaml)')
    ap.add_argument('--seeds', type=number(int, lo=1, hi=10_000), default=30)
    ap.add_argument('--duration', type=number(float, lo=window_s, hi=600.0), default=10.0,
                    help=f'seconds of excitation ({window_s:g} s, one identification window, '
                    'to 600 s)')
    ap.add_argument('--noise', type=number(float, lo=0.0, hi=1.0, hi_open=True), default=0.10,
                    help='white sensor noise, fraction of the maximum sensed value')
    ap.add_argument('--strategies', type=_strategies, default=list(STRATEGIES),
                    help=f'comma-separated, of {",".join(STRATEGIES)}')
    ap.add_argument('--first-seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    ap.add_argument('--no-accelerometer', action='store_true',
                    help='the thesis experimental rover (§2.6.2): rotational subset only')
    ap.add_argument('--no-bias-compensation', action='store_true',
                    help='plain recursive least squares (no errors-in-variables correction)')
    ap.add_argument('--json', type=output_path, default=None)
    ap.add_argument('--plots', type=output_dir, default=None)
    ap.add_argument('--sim', action='store_true',
                    help='identification end to end through rover_sim + identifier, one run '
                         'per listed strategy')
    ap.add_argument('--integrator', choices=enum_choices(Integrator),
                    default=Integrator.EXPLICIT.value,
                    help="with --sim: the simulator's integrator (rover_sim parameter)")
    ap.add_argument('--lockstep', action='store_true',
                    help='with --sim: the simulator in lockstep with the identifier')
    ap.add_argument('--busy-too', action='store_true',
                    help='with --sim --lockstep: each run again beside a busy core, compared')
    ap.add_argument('--bag', type=_existing, default=None,
                    help='identify from a recorded bag instead (no DDS; the core as the node)')
    ap.add_argument('--rover', default='rover1', help='rover namespace in --bag')
    args = ap.parse_args(argv)
    given = _given(ap, argv if argv is not None else sys.argv[1:])
    if args.sim and args.bag is not None:
        ap.error('--sim and --bag are two different sources: give one')
    if args.busy_too and not args.lockstep:
        ap.error('--busy-too compares lockstep runs: give --lockstep too')
    mode = 'sim' if args.sim else 'bag' if args.bag is not None else 'model'
    ignored = [f'--{k.replace("_", "-")}' for k in vars(args)
               if k not in ('json', 'sim') and k not in _MODE_OPTIONS[mode] and k in given]
    if ignored:
        ap.error(f'{", ".join(ignored)}: not used with '
                 + {'model': 'the model-level study', 'sim': '--sim', 'bag': '--bag'}[mode])
    return args


def format_sim(doc: dict) -> str:
    """`--sim`'s printed table, from its JSON: each strategy's estimate (std) beside the truth
    the simulator latched, * where the identifier flagged the parameter unobservable."""
    strategies = list(doc['strategies'])
    runs = doc['strategies']
    lines = [f'end to end through rover_sim ({doc.get("integrator", "explicit")} integrator'
             + (', lockstep' if doc.get('lockstep') else '') + ') + '
             f'identifier: {doc["duration_s"]} s, noise {doc["noise"]}; estimate (std), * = '
             'flagged unobservable',
             f'{"Parameter":16s}{"True":>9s}' + ''.join(f'{s:>22s}' for s in strategies),
             '-' * (25 + 22 * len(strategies))]
    for p in PARAM_NAMES:
        cells = ''
        for s in strategies:
            q = runs[s]['per_parameter'][p]
            mark = ' ' if q['observable'] else '*'
            cells += f'{q["estimate"]:>11.4g} ({q["std"]:7.2g}){mark}'
        truth = runs[strategies[0]]['per_parameter'][p]['truth']
        lines.append(f'{PARAM_LABELS[p]:16s}{truth:9.4g}{cells}')
    lines.append('-' * (25 + 22 * len(strategies)))
    lines.append(f'{"% Avg. Error":25s}' + ''.join(
        f'{100 * runs[s]["mean_abs_rel_error"]:>22.1f}' for s in strategies))
    for s in strategies:
        r = runs[s]
        lines.append(f'{s}: {r["message"]}; {r["samples"]} samples; logs {r["logs"]}')
    return '\n'.join(lines)


def _sim_run(r: dict) -> dict:
    """One --sim run as its JSON."""
    return {'success': r['success'], 'message': r['message'],
            'mean_abs_rel_error': r['mean_abs_rel_error'],
            'samples': r['samples'], 'rejected': r['rejected'], 'logs': r['logs'],
            'per_parameter': {p: {'estimate': float(r['estimate'][i]),
                                  'std': float(r['std'][i]),
                                  'observable': bool(r['observable'][i]),
                                  'truth': float(r['truth'][i])}
                              for i, p in enumerate(PARAM_NAMES)}}


def format_sim_load(doc: dict) -> str:
    """`--sim --lockstep --busy-too`'s comparison: each strategy idle and beside a busy core."""
    lines = [f'{"strategy":14s}{"error idle %":>14s}{"error busy %":>14s}{"samples":>16s}'
             f'{"largest estimate difference":>30s}']
    for s, idle in doc['strategies'].items():
        busy = doc['busy'][s]
        diff = max(abs(idle['per_parameter'][p]['estimate'] - busy['per_parameter'][p]['estimate'])
                   / max(abs(idle['per_parameter'][p]['estimate']), 1e-12)
                   for p in PARAM_NAMES)
        lines.append(f'{s:14s}{100 * idle["mean_abs_rel_error"]:>14.2f}'
                     f'{100 * busy["mean_abs_rel_error"]:>14.2f}'
                     f'{idle["samples"]:>8d}/{busy["samples"]:<7d}{diff:>30.2e}')
    return '\n'.join(lines)


def _main_sim(args: argparse.Namespace) -> int:
    """Every listed strategy end to end, each in its own fresh sim + identifier (the same seed,
    so the same noise draws where the commands agree): one table, estimates side by side."""
    from coop_common.testing import busy_core  # noqa: PLC0415 - only --sim

    from .sim_mode import run_sim_identification  # noqa: PLC0415 - rclpy, only --sim

    def run(strategy: Strategy, busy: bool) -> dict:
        with busy_core(busy):
            return run_sim_identification(duration_s=args.duration, strategy=strategy,
                                          noise=args.noise, integrator=args.integrator,
                                          lockstep=args.lockstep)

    results, busy = {}, {}
    for strategy in args.strategies:
        try:
            results[strategy] = run(strategy, busy=False)
            if args.busy_too:
                busy[strategy] = run(strategy, busy=True)
        except (RuntimeError, FileNotFoundError) as exc:
            print(f'table_2_1 --sim ({strategy}): {exc}', file=sys.stderr)
            return 1
    doc = {
        'mode': 'sim', 'duration_s': args.duration, 'noise': args.noise,
        'integrator': args.integrator, 'lockstep': args.lockstep,
        'strategies': {s: _sim_run(r) for s, r in results.items()}}
    if args.busy_too:
        doc['busy'] = {s: _sim_run(r) for s, r in busy.items()}
    print(format_sim(doc))
    if args.busy_too:
        print(format_sim_load(doc))
    if args.json is not None:
        write_json(args.json, doc, indent=1)
    return 0


def format_bag(doc: dict) -> str:
    """`--bag`'s printed table, from its JSON (True and the mean error only where the bag
    carries the simulator's truth)."""
    pp = doc['per_parameter']
    lines = [f'identification from {doc["bag"]} ({doc["rover"]}): {doc["samples"]} samples',
             f'{"Parameter":16s}{"True":>10s}{"estimate":>11s}{"std":>10s}  observable']
    for p in PARAM_NAMES:
        q = pp[p]
        t = f'{"-":>10s}' if q['truth'] is None else f'{q["truth"]:10.4g}'
        lines.append(f'{PARAM_LABELS[p]:16s}{t}{q["estimate"]:11.4g}{q["std"]:10.3g}  '
                     f'{q["observable"]}')
    if doc['mean_abs_rel_error'] is not None:
        nz = sum(pp[p]['truth'] != 0 for p in PARAM_NAMES)
        lines.append(f'% Avg. Error {100 * doc["mean_abs_rel_error"]:.1f} (over the {nz} '
                     'non-zero parameters)')
    return '\n'.join(lines)


def _main_bag(args: argparse.Namespace) -> int:

    try:
        _, rows = offline.bag_samples(args.bag, rover=args.rover)
        noise = (None if args.no_bias_compensation
                 else offline.bag_sensor_noise(args.bag, rover=args.rover))
        report = offline.identify_rows(rows, IdentifierConfig(
            accelerometer=not args.no_accelerometer), noise=noise)
        truth = offline.bag_truth(args.bag, rover=args.rover)
    except (offline.BagError, OSError, ValueError) as exc:
        print(f'table_2_1 --bag: {exc}', file=sys.stderr)
        return 1
    err = None
    if truth is not None:
        nz = truth != 0
        err = float(np.mean(np.abs(report.values[nz] - truth[nz]) / np.abs(truth[nz])))
    doc = {
        'mode': 'bag', 'bag': str(args.bag), 'rover': args.rover, 'samples': len(rows),
        'accelerometer': not args.no_accelerometer,
        'bias_compensation': not args.no_bias_compensation and noise is not None,
        'mean_abs_rel_error': err,
        'per_parameter': {p: {'estimate': float(report.values[i]),
                              'std': float(report.std[i]),
                              'observable': bool(report.observable[i]),
                              'truth': None if truth is None else float(truth[i])}
                          for i, p in enumerate(PARAM_NAMES)}}
    print(format_bag(doc))
    if args.json is not None:
        write_json(args.json, doc, indent=1)
    return 0


def main(argv: list[str] | None = None) -> int:
    """`ros2 run coop_id table_2_1`: Table 2-1 off-line, from a bag, or through the simulator."""
    args = parse_args(argv if argv is not None else sys.argv[1:])
    if args.sim:
        return _main_sim(args)
    if args.bag is not None:
        return _main_bag(args)
    try:
        truth_p = load_truth(args.truth)
    except TruthFileError as exc:
        print(f'table_2_1: {exc}', file=sys.stderr)
        return 2
    truth = truth_p.to_vector()
    scales = reference_noise_scales(truth_p, args.duration)
    strategies = args.strategies
    runs: dict[Strategy, list[RunResult]] = {s: [] for s in strategies}
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    for s in strategies:
        for seed in seeds:
            cfg = IdentifierConfig(accelerometer=not args.no_accelerometer)
            runs[s].append(run_identification(truth_p, strategy=s, seed=seed,
                                              duration_s=args.duration, noise=args.noise,
                                              scales=scales, config=cfg,
                                              bias_compensation=not args.no_bias_compensation))
    doc = {'seeds': args.seeds, 'first_seed': args.first_seed, 'duration_s': args.duration,
           'noise': args.noise, 'accelerometer': not args.no_accelerometer,
           'bias_compensation': not args.no_bias_compensation,
           'truth': dict(zip(PARAM_NAMES, truth.tolist(), strict=False)),
           'thesis': {'constant': dict(zip(PARAM_NAMES, THESIS_CONSTANT, strict=False)),
                      'variable': dict(zip(PARAM_NAMES, THESIS_VARIABLE, strict=False)),
                      'avg_error_pct': THESIS_AVG_ERROR},
           'strategies': summarise(runs, truth)}
    print(format_json(doc))
    if args.plots is not None:
        for p in draw_plots(runs, truth, args.plots):
            print(f'wrote {p}')
    if args.json is not None:
        write_json(args.json, doc, indent=1)
        print(f'wrote {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
