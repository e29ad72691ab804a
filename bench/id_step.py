#!/usr/bin/env python3
"""Benchmark: one full 0.4 s identification step of coop_id (thesis §2.6.1: 75 ms on a PIII 750).

One step = build A x = F for 80 samples x 3 arm modes (raw channels + filter bank), the Kalman
filter update (the window's decimated rows), the window end (R, the sandwich covariance, the
Eq. 2-12 information metric, the bias-compensated consistent report), and the excitation
re-optimisation (LM, Eq. 2-16..2-20). Peer in the same run: a batch pseudo-inverse (numpy lstsq)
of the same window, the per-step cost a non-recursive solution would pay.

Every part is timed twice: wall clock (perf_counter) and the process's CPU time (process_time;
single-threaded, so the time on one core, which other jobs on the machine do not inflate).

    python bench/id_step.py --json OUT [--steps 25] [--strategy information]
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np

from coop_common.cli import number, output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from coop_id.excitation import STRATEGIES, Strategy, constant_excitation
from coop_id.experiment import reference_noise_scales
from coop_id.identifier_core import Identifier, IdentifierConfig
from coop_id.model import FilterBank, SensorNoise, filtered_rows, raw_channels
from coop_id.modelsim import ThesisRover, add_noise, stack_frames


def windows(n: int, seed: int = 0) -> tuple[list[dict], dict]:
    truth = load_truth()
    scales = reference_noise_scales(truth, 4.0)
    rover, exc, rng = ThesisRover(truth), constant_excitation(), np.random.default_rng(seed)
    out, frames = [], [rover.rest_frame()]
    for _ in range(n):
        for _ in range(80):
            frames.append(rover.step(exc(rover.t + 0.005)))
        out.append(add_noise(stack_frames(frames), scales, 0.1, rng))
        frames = []
    sig = {c: 0.1 * scales[c] / np.sqrt(3.0) for c in scales}
    noise = {m: SensorNoise(sig['specific_force'][m], sig['gyro'][m], sig['incl'][m],
                            sig['force'][m]) for m in range(3)}
    return out, noise


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    lines = [f'coop_id full 0.4 s step, strategy {result["strategy"]}, {result["steps"]} steps, '
             f'OPENBLAS_NUM_THREADS={result["openblas_num_threads"]}',
             f'{"part":28s}{"median ms":>10s}{"CPU ms":>9s}']
    for k, v in result['median_ms'].items():
        lines.append(f'{k:28s}{v:10.2f}{result["median_cpu_ms"][k]:9.2f}')
    lines.append(f'{"thesis (PIII 750 MHz)":28s}{result["thesis_ms"]:10.2f}')
    lines.append(f'{"target":28s}{result["target_ms"]:10.2f}')
    lines.append(f'ratio full step / peer batch lstsq = {result["ratio_full_over_peer"]:.1f}')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--steps', type=number(int, lo=1, hi=10_000), default=25)
    ap.add_argument('--strategy', default='information', choices=STRATEGIES)
    args = ap.parse_args()
    data, noise = windows(args.steps + 3)
    ident = Identifier(IdentifierConfig(strategy=args.strategy), sensor_noise=noise)
    names = ('build_A_80x3_ms', 'kf_updates_ms', 'information_report_ms',
             'excitation_reoptimise_ms', 'full_step_ms', 'peer_batch_lstsq_ms')
    wall: dict[str, list[float]] = {n: [] for n in names}
    cpu: dict[str, list[float]] = {n: [] for n in names}
    bank = FilterBank()

    def now() -> tuple[float, float]:
        return time.perf_counter(), time.process_time()
    for k, win in enumerate(data):
        # (a) build A for 80 samples x 3 modes, timed separately on a twin filter bank
        ta = now()
        rows = []
        for m in range(3):
            ch = raw_channels(specific_force=win['specific_force'][:, m], gyro=win['gyro'][:, m],
                              incl_roll_pitch=win['incl'][:, m], force=win['force'][:, m],
                              torque=win['torque'][:, m])
            rows.append(filtered_rows(bank, ch, tag=str(m)))
        tb = now()
        # peer: batch pseudo-inverse of the window's 1440 x 22 rows
        a = np.concatenate([r[0] for r in rows]).reshape(-1, 22)
        y = np.concatenate([r[1] for r in rows]).ravel()
        tp = now()
        np.linalg.lstsq(a, y, rcond=None)
        tq = now()
        # (b) the identifier's own step: rows + KF update, then window end (info + optimise)
        t1 = now()
        ident.add_samples_all(specific_force=win['specific_force'], gyro=win['gyro'],
                              incl=win['incl'], force=win['force'], torque=win['torque'])
        t2 = now()
        ident.end_window(optimise_excitation=False)
        t3 = now()
        if np.all(np.isfinite(ident.row_var)) and ident.cfg.strategy is not Strategy.CONSTANT:
            ident.excitation = ident._reoptimise()
        t4 = now()
        if k < 3:      # warm-up: R not yet estimated, caches cold
            continue
        for i, out in ((0, wall), (1, cpu)):
            def d(u, v, i=i):
                return 1e3 * (v[i] - u[i])
            out['build_A_80x3_ms'].append(d(ta, tb))
            out['peer_batch_lstsq_ms'].append(d(tp, tq))
            out['kf_updates_ms'].append(d(t1, t2) - d(ta, tb))
            out['information_report_ms'].append(d(t2, t3))
            out['excitation_reoptimise_ms'].append(d(t3, t4))
            out['full_step_ms'].append(d(t1, t4))
    med = {n: statistics.median(v) for n, v in wall.items()}
    med_cpu = {n: statistics.median(v) for n, v in cpu.items()}
    steps = len(wall['full_step_ms'])
    result = {'strategy': args.strategy, 'steps': steps,
              'openblas_num_threads': os.environ.get('OPENBLAS_NUM_THREADS'),
              'median_ms': med, 'median_cpu_ms': med_cpu, 'thesis_ms': 75.0,
              'target_ms': 20.0,
              'ratio_full_over_peer': med['full_step_ms'] / med['peer_batch_lstsq_ms']}
    print(format_table(result))
    write_json(args.json, result, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
