#!/usr/bin/env python3
"""Benchmark: BRAID inverse kinematics (coop_braid.ik, thesis §E.3.2) per method and chain
length, against the issue's budgets (n = 10: 20 ms, n = 20: 50 ms per solve on one core).

For each n (default 5, 10, 20) a fixed set of targets (a random state's end position with
another random state's orientation, as braid_ik draws them) is solved by every method
(exhaustive only for n = 5, where it is the peer: each method's time is also given as a ratio
to it). Around them, the cores the searches stand on: one chain FK (Eq. E-3) of n stages, the
whole workspace of 5 stages (2^15 poses, Fig. E-5) and decoding one carrier pulse train (§E.4,
60 actuators).

Each solve is timed by wall clock and by the process's CPU time (single-threaded: the time on
one core, which other jobs on the machine do not inflate).

    python bench/braid_ik.py --json OUT [--targets 100] [--stages 5,10,20]
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np

from coop_braid.braid_ik import make_targets, stage_list
from coop_braid.carrier import Command, decode, encode
from coop_braid.chain import Chain
from coop_braid.ik import Method, solve
from coop_braid.stage import LegState, StageGeometry
from coop_common.cli import number, output_path
from coop_common.files import write_json

BUDGET_MS = {10: 20.0, 20: 50.0}


def timed(fn, n: int) -> tuple[float, float]:
    """Median wall and CPU ms per call over n calls."""
    walls, cpus = [], []
    for _ in range(n):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append((time.perf_counter() - w0) * 1e3)
        cpus.append((time.process_time() - c0) * 1e3)
    return statistics.median(walls), statistics.median(cpus)


def time_solves(chain: Chain, goals: np.ndarray, method: Method) -> tuple[float, float]:
    """Median wall and CPU ms of one solve of each goal (after one warm-up solve that builds
    the method's tables)."""
    solve(chain, goals[0], method=method, rng=0)
    walls, cpus = [], []
    for i, goal in enumerate(goals):
        w0, c0 = time.perf_counter(), time.process_time()
        solve(chain, goal, method=method, rng=i)
        walls.append((time.perf_counter() - w0) * 1e3)
        cpus.append((time.process_time() - c0) * 1e3)
    return statistics.median(walls), statistics.median(cpus)


def format_table(result: dict) -> str:
    """The printed table of a result JSON."""
    lines = [f'BRAID IK, {result["targets"]} targets per chain length, '
             f'OPENBLAS_NUM_THREADS={result["openblas_num_threads"]}',
             f'{"n":>3s} {"method":14s}{"median ms":>10s}{"CPU ms":>9s}{"x exhaustive":>13s}'
             f'{"budget ms":>10s}']
    for n, methods in result['ik'].items():
        ref = methods.get('exhaustive', {}).get('median_cpu_ms')
        for name, m in methods.items():
            ratio = f'{m["median_cpu_ms"] / ref:13.2f}' if ref else f'{"-":>13s}'
            budget = BUDGET_MS.get(int(n))
            lines.append(f'{n:>3s} {name:14s}{m["median_ms"]:10.3f}{m["median_cpu_ms"]:9.3f}'
                         f'{ratio}{budget if budget else "-":>10}')
    lines.append('cores:')
    for k, v in result['cores'].items():
        lines.append(f'    {k:40s}{v["median_ms"]:10.3f}{v["median_cpu_ms"]:9.3f}')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--targets', type=number(int, lo=5, hi=100_000), default=100)
    ap.add_argument('--stages', type=stage_list, default=(5, 10, 20))
    args = ap.parse_args()
    geometry = StageGeometry()
    ik: dict[str, dict[str, dict[str, float]]] = {}
    for n in args.stages:
        chain = Chain.uniform(geometry, n)
        goals = make_targets(chain, args.targets, np.random.default_rng([7, n]))
        methods = ([Method.EXHAUSTIVE] if n <= 5 else []) + [
            Method.BEAM, Method.COMBINATORIAL, Method.GENETIC]
        ik[str(n)] = {}
        for method in methods:
            wall, cpu = time_solves(chain, goals, method)
            ik[str(n)][method.value] = {'median_ms': wall, 'median_cpu_ms': cpu}
    chain20 = Chain.uniform(geometry, 20)
    states = np.random.default_rng(1).integers(0, 8, 20)
    chain5 = Chain.uniform(geometry, 5)
    train = encode(Command(41, LegState.LONG), n_actuators=60)
    cores = {}
    for name, fn, reps in (
            ('chain FK, 20 stages (Chain.pose)', lambda: chain20.pose(states), 2000),
            ('workspace of 5 stages (32768 poses)', chain5.workspace, 50),
            ('decode one pulse train (60 actuators)', lambda: decode(train, n_actuators=60),
             2000)):
        wall, cpu = timed(fn, reps)
        cores[name] = {'median_ms': wall, 'median_cpu_ms': cpu}
    result = {'targets': args.targets,
              'openblas_num_threads': os.environ.get('OPENBLAS_NUM_THREADS'),
              'ik': ik, 'cores': cores, 'budget_ms': {str(k): v for k, v in BUDGET_MS.items()}}
    print(format_table(result))
    write_json(args.json, result, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
