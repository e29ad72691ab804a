"""braid_ik: the Monte Carlo of thesis §E.3.2 and the carrier check of §E.4.

For each chain length n (default 5, 10, 20 stages): N random targets (default 1000) in the
binary workspace cloud (the end position of a uniformly random state) with a random orientation
(the end orientation of another, independent random state: an orientation the mast has, not
paired with that position); every IK method solves each target; per method the median and 95th
percentile solve time (CPU time of the process, one core, BLAS on one thread) and the median
position (mm) and orientation (deg) errors. Exhaustive search (the reference) runs for n <= 5
only. For n = 5, the fraction of targets on which the best heuristic's weighted pose error is
within 10 % of the exhaustive optimum's. Then `--carrier` random commands to a 20-stage mast's
60 actuators, each pulse train with noise uniformly within the documented bound (every other one
at the bound's extremes), counting wrongly addressed actuators and missed commands.

    python -m coop_braid.braid_ik [--targets N] [--stages 5,10,20] [--json PATH] [--plots DIR]
                                  [--seed S] [--carrier M]
"""
from __future__ import annotations

import argparse
import os
import time
from pathlib import Path
from typing import Any

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np
from numpy.typing import NDArray

from coop_braid.carrier import NOISE_BOUND, Bus, Command, add_noise, encode
from coop_braid.chain import Chain
from coop_braid.errors import BraidError
from coop_braid.ik import Method, Weights, solve
from coop_braid.stage import LegState, StageGeometry
from coop_common.cli import number, output_dir, output_path
from coop_common.files import save_figure, write_json

#: the chain lengths of the thesis (E.5)
DEFAULT_STAGES = (5, 10, 20)
#: exhaustive search runs up to this many stages (8^5 = 32768 states)
EXHAUSTIVE_MAX = 5
#: the heuristics, the best of which is compared with exhaustive search
HEURISTICS = (Method.BEAM, Method.COMBINATORIAL, Method.GENETIC)
#: the issue's targets
TARGET_WITHIN_10PCT = 0.95
TARGET_N10_POS_PCT = 0.25
TARGET_N10_MS = 20.0
TARGET_N20_MS = 50.0
#: one colour per method in the plots
METHOD_COLOURS = {'exhaustive': 'k', 'beam': 'C0', 'combinatorial': 'C1', 'genetic': 'C2'}
#: carrier check: stages of the mast the commands go to
CARRIER_STAGES = 20


def make_targets(chain: Chain, count: int, rng: np.random.Generator) -> NDArray[np.float64]:
    """`count` target poses (count, 4, 4): the position of one random state's end, the
    orientation of another's."""
    pos = chain.poses(rng.integers(0, 8, size=(count, chain.n)))
    out = chain.poses(rng.integers(0, 8, size=(count, chain.n)))
    out[:, :3, 3] = pos[:, :3, 3]
    return out


def run_chain(n: int, *, targets: int, seed: int, weights: Weights,
              geometry: StageGeometry) -> dict[str, Any]:
    """One chain length's Monte Carlo: per method the raw times and errors, and the reach."""
    chain = Chain.uniform(geometry, n)
    rng = np.random.default_rng([seed, n])
    goals = make_targets(chain, targets, rng)
    methods = ([Method.EXHAUSTIVE] if n <= EXHAUSTIVE_MAX else []) + list(HEURISTICS)
    raw: dict[str, dict[str, list[float]]] = {}
    for method in methods:
        solve(chain, goals[0], method=method, weights=weights, rng=0)     # tables, warm
        rec: dict[str, list[float]] = {'cpu_ms': [], 'wall_ms': [], 'pos_m': [], 'ang_rad': [],
                                       'cost': [], 'evaluations': []}
        for i, goal in enumerate(goals):
            w0, c0 = time.perf_counter(), time.process_time()
            res = solve(chain, goal, method=method, weights=weights, rng=[seed, n, i])
            rec['cpu_ms'].append((time.process_time() - c0) * 1e3)
            rec['wall_ms'].append((time.perf_counter() - w0) * 1e3)
            rec['pos_m'].append(res.pos_err_m)
            rec['ang_rad'].append(res.ang_err_rad)
            rec['cost'].append(res.cost)
            rec['evaluations'].append(res.evaluations)
        raw[method.value] = rec
    return {'chain': chain, 'raw': raw, 'reach_m': chain.straight_reach()}


def summarise(n: int, run: dict[str, Any]) -> dict[str, Any]:
    """The JSON entry of one chain length."""
    reach = run['reach_m']
    methods = {}
    for name, rec in run['raw'].items():
        pos = np.array(rec['pos_m'])
        methods[name] = {
            'median_ms': float(np.median(rec['cpu_ms'])),
            'p95_ms': float(np.percentile(rec['cpu_ms'], 95)),
            'median_wall_ms': float(np.median(rec['wall_ms'])),
            'pos_err_mm': float(np.median(pos) * 1e3),
            'pos_err_pct_reach': float(np.median(pos) / reach * 100.0),
            'ang_err_deg': float(np.degrees(np.median(rec['ang_rad']))),
            'cost_mm': float(np.median(rec['cost']) * 1e3),
            'p95_pos_err_mm': float(np.percentile(pos, 95) * 1e3),
            'evaluations': float(np.median(rec['evaluations'])),
        }
    heur = [m.value for m in HEURISTICS if m.value in methods]
    best = min(heur, key=lambda m: methods[m]['cost_mm'])
    out: dict[str, Any] = {'stages': n, 'states': f'2^{3 * n}', 'targets': len(
        run['raw'][best]['cost']), 'reach_m': reach, 'best_method': best, 'methods': methods}
    if Method.EXHAUSTIVE.value in run['raw']:
        ref = np.array(run['raw'][Method.EXHAUSTIVE.value]['cost'])
        out['within_10pct_by_method'] = {
            m: float(np.mean(np.array(run['raw'][m]['cost']) <= 1.1 * ref + 1e-12))
            for m in heur}
    return out


def carrier_check(commands: int, *, seed: int) -> dict[str, Any]:
    """`commands` random commands to a CARRIER_STAGES-stage mast's bus, each train with noise
    within NOISE_BOUND (every other one at its extremes): wrong actuators addressed and missed
    commands."""
    bus = Bus(CARRIER_STAGES)
    rng = np.random.default_rng([seed, 37])
    wrong = missed = 0
    t0 = time.perf_counter()
    for k in range(commands):
        cmd = Command(address=int(rng.integers(0, bus.n_actuators)),
                      state=LegState(int(rng.integers(0, 2))))
        train = add_noise(encode(cmd, n_actuators=bus.n_actuators), rng, extreme=bool(k % 2))
        latched = bus.transmit(train)
        hit = [a for row in latched for a in row]
        wrong += sum(1 for a in hit if a != cmd.address)
        if cmd.address not in hit or bus.decoders[cmd.address].state != cmd.state:
            missed += 1
    return {'commands': commands, 'actuators': bus.n_actuators,
            'edge_jitter_periods': NOISE_BOUND.edge_jitter,
            'amplitude_noise_v': NOISE_BOUND.amplitude_v, 'wrong_actuators': wrong,
            'missed_commands': missed, 'seconds': time.perf_counter() - t0}


def format_json(result: dict[str, Any]) -> str:
    """The printed tables of a result JSON."""
    w = result['weights']
    lines = [f'BRAID IK Monte Carlo (thesis E.3.2): {result["targets"]} targets per chain, '
             f'seed {result["seed"]}',
             f'  stage: legs {result["geometry"]["leg_short"] * 1e3:.1f}/'
             f'{result["geometry"]["leg_long"] * 1e3:.1f} mm, disks r_b '
             f'{result["geometry"]["base_radius"] * 1e3:.1f} mm, r_p '
             f'{result["geometry"]["platform_radius"] * 1e3:.1f} mm; cost = '
             f'{w["position"]:g} |dp| + {w["orientation"] * 1e3:g} mm/rad x angle',
             '  times: CPU ms of one solve on one core; errors: medians']
    for key in sorted((k for k in result if k.startswith('n') and k[1:].isdigit()),
                      key=lambda k: int(k[1:])):
        r = result[key]
        lines.append(f'n = {r["stages"]} ({r["states"]} states), reach {r["reach_m"] * 1e3:.1f} '
                     f'mm (straight, every leg long); best heuristic: {r["best_method"]}')
        lines.append(f'  {"method":14s}{"median_ms":>10s}{"p95_ms":>9s}{"pos_err_mm":>11s}'
                     f'{"% reach":>9s}{"ang_err_deg":>12s}{"cost_mm":>9s}')
        for name, m in r['methods'].items():
            lines.append(f'  {name:14s}{m["median_ms"]:10.2f}{m["p95_ms"]:9.2f}'
                         f'{m["pos_err_mm"]:11.3f}{m["pos_err_pct_reach"]:9.3f}'
                         f'{m["ang_err_deg"]:12.2f}{m["cost_mm"]:9.3f}')
        if 'within_10pct_by_method' in r:
            within = ', '.join(f'{m} {v * 100:.1f} %'
                               for m, v in r['within_10pct_by_method'].items())
            lines.append(f'  within 10 % of exhaustive: {within}')
    lines.append('targets (issue #37):')
    for t in result['checks']:
        lines.append(f'  {"met " if t["met"] else "MISS"} {t["what"]}: {t["measured"]} '
                     f'(target {t["target"]})')
    c = result.get('carrier')
    if c:
        lines.append(f'carrier (E.4): {c["commands"]} noisy commands to {c["actuators"]} '
                     f'actuators, edges +-{c["edge_jitter_periods"]} T, peaks '
                     f'+-{c["amplitude_noise_v"]} V: {c["wrong_actuators"]} wrong actuators, '
                     f'{c["missed_commands"]} missed')
    return '\n'.join(lines)


def checks(result: dict[str, Any]) -> list[dict[str, Any]]:
    """The issue's targets against the result (those its chain lengths allow)."""
    out = []
    if 'within_10pct_of_exhaustive' in result:
        v = result['within_10pct_of_exhaustive']
        out.append({'what': 'n=5 best heuristic within 10 % of exhaustive',
                    'measured': f'{v * 100:.1f} %', 'target': '>= 95 %',
                    'met': v >= TARGET_WITHIN_10PCT})
    if 'n10' in result:
        r = result['n10']
        m = r['methods'][r['best_method']]
        out.append({'what': f'n=10 {r["best_method"]} median position error',
                    'measured': f'{m["pos_err_pct_reach"]:.3f} % of reach',
                    'target': f'<= {TARGET_N10_POS_PCT} %',
                    'met': m['pos_err_pct_reach'] <= TARGET_N10_POS_PCT})
        out.append({'what': f'n=10 {r["best_method"]} median solve',
                    'measured': f'{m["median_ms"]:.2f} ms', 'target': f'<= {TARGET_N10_MS} ms',
                    'met': m['median_ms'] <= TARGET_N10_MS})
    if result.get('best_median_ms_n20') is not None:
        v = result['best_median_ms_n20']
        out.append({'what': f'n=20 {result["n20"]["best_method"]} median solve',
                    'measured': f'{v:.2f} ms', 'target': f'<= {TARGET_N20_MS} ms',
                    'met': v <= TARGET_N20_MS})
    if result.get('carrier'):
        c = result['carrier']
        out.append({'what': f'carrier: wrong actuators in {c["commands"]} noisy commands',
                    'measured': str(c['wrong_actuators']), 'target': '0',
                    'met': c['wrong_actuators'] == 0})
    return out


def plot(runs: dict[int, dict[str, Any]], out: Path) -> list[Path]:
    """Fig. E-5 (the workspace cloud of 5 stages, when run) and the error distributions."""
    import matplotlib  # noqa: PLC0415 - only --plots needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    if 5 in runs:
        ws = runs[5]['chain'].workspace()[:, :3, 3] * 1e3
        fig = plt.figure(figsize=(6.5, 6))
        ax = fig.add_subplot(projection='3d')
        ax.scatter(ws[:, 0], ws[:, 1], ws[:, 2], s=0.3, c=ws[:, 2], cmap='viridis', alpha=0.5)
        ax.set_xlabel('x, mm')
        ax.set_ylabel('y, mm')
        ax.set_zlabel('z, mm')
        ax.set_title('Fig. E-5: workspace of a 5-stage BRAID (2^15 states, base at origin)')
        paths.append(save_figure(fig, out / 'braid_workspace_n5.png'))
    fig, axes = plt.subplots(2, len(runs), figsize=(4.2 * len(runs), 6.5), squeeze=False)
    for col, (n, run) in enumerate(sorted(runs.items())):
        pos = {k: np.array(r['pos_m']) * 1e3 for k, r in run['raw'].items()}
        ang = {k: np.degrees(r['ang_rad']) for k, r in run['raw'].items()}
        pos_hi = max(float(np.percentile(v, 99)) for v in pos.values()) * 1.1 + 1e-9
        ang_hi = max(float(np.percentile(v, 99)) for v in ang.values()) * 1.1 + 1e-9
        for name in run['raw']:
            style = {'color': METHOD_COLOURS[name], 'histtype': 'step', 'label': name,
                     'linestyle': '--' if name == Method.EXHAUSTIVE.value else '-'}
            axes[0, col].hist(pos[name], bins=40, range=(0, pos_hi), **style)
            axes[1, col].hist(ang[name], bins=40, range=(0, ang_hi), **style)
        axes[0, col].set_title(f'n = {n}, {len(pos[name])} targets')
        axes[0, col].set_xlabel('position error, mm')
        axes[1, col].set_xlabel('orientation error, deg')
        axes[0, col].legend(fontsize=7)
    axes[0, 0].set_ylabel('targets')
    axes[1, 0].set_ylabel('targets')
    paths.append(save_figure(fig, out / 'braid_ik_errors.png'))
    return paths


def stage_list(text: str) -> tuple[int, ...]:
    """argparse type of `--stages`: comma-separated chain lengths, 1..40 each."""
    try:
        out = tuple(int(v) for v in text.split(','))
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r}: comma-separated integers') from None
    if not out or any(not 1 <= v <= 40 for v in out) or len(set(out)) != len(out):
        raise argparse.ArgumentTypeError(f'{text!r}: distinct chain lengths of 1..40 stages')
    return tuple(sorted(out))


def main(argv: list[str] | None = None) -> int:
    """Run the Monte Carlo, print the tables, write the JSON and the plots."""
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--targets', type=number(int, lo=1, hi=1_000_000), default=1000,
                   help='random targets per chain length (default 1000)')
    p.add_argument('--stages', type=stage_list, default=DEFAULT_STAGES,
                   help='chain lengths, comma-separated (default 5,10,20)')
    p.add_argument('--json', type=output_path, help='write the results here')
    p.add_argument('--plots', type=output_dir, help='write the figures into this directory')
    p.add_argument('--seed', type=number(int, lo=0), default=1)
    p.add_argument('--carrier', type=number(int, lo=0, hi=10_000_000), default=100_000,
                   help='noisy carrier commands to check (default 100000; 0: none)')
    p.add_argument('--w-ang', type=number(float, lo=0.0), default=Weights().orientation,
                   help='orientation weight of the pose error, m/rad (default 0.01)')
    args = p.parse_args(argv)
    try:
        weights = Weights(orientation=args.w_ang)
    except BraidError as exc:
        p.error(str(exc))
    geometry = StageGeometry()
    runs = {n: run_chain(n, targets=args.targets, seed=args.seed, weights=weights,
                         geometry=geometry) for n in args.stages}
    result: dict[str, Any] = {
        'targets': args.targets, 'seed': args.seed,
        'weights': {'position': weights.position, 'orientation': weights.orientation},
        'geometry': {'leg_short': geometry.leg_short, 'leg_long': geometry.leg_long,
                     'base_radius': geometry.base_radius,
                     'platform_radius': geometry.platform_radius},
        'timing': 'CPU time of the process per solve (one core, OPENBLAS_NUM_THREADS='
                  f'{os.environ.get("OPENBLAS_NUM_THREADS")})'}
    for n, run in runs.items():
        result[f'n{n}'] = summarise(n, run)
    if 5 in runs:
        r5 = result['n5']
        result['within_10pct_of_exhaustive'] = r5['within_10pct_by_method'][r5['best_method']]
    result['best_median_ms_n20'] = (result['n20']['methods'][result['n20']['best_method']]
                                    ['median_ms'] if 20 in runs else None)
    if args.carrier:
        result['carrier'] = carrier_check(args.carrier, seed=args.seed)
    result['checks'] = checks(result)
    print(format_json(result))
    if args.json:
        write_json(args.json, result, indent=1)
    if args.plots:
        for path in plot(runs, args.plots):
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
