#!/usr/bin/env python3
"""Benchmark: one servo step of the base feed-forward (coop_insertion.feedforward, app. A Eq. A-4)
against the issue's budget of 1 ms per 100 Hz step on one core.

One step = the base observer's Kalman update on one sensor sample and the arm's Newton-Euler
pass that gives F, the base-rate torques, G and the reference's own dynamics. Parts timed apart:
the observer, the Newton-Euler pass, and the whole `FeedForward.torque`; a step while a new
parameter set blends in runs both models. Peer in the same run: one `World.step` of the
simulator with two rovers (the 200 Hz physics period the feed-forward rides on), so the ratio
says what the feed-forward adds to a simulated servo period.

Each part is timed by wall clock and by the process's CPU time (single-threaded: the time on
one core, which other jobs on the machine do not inflate).

    python bench/feedforward.py --json OUT [--steps 2000]
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
from coop_insertion.feedforward import ArmModel, BaseObserver, FeedForward, ParameterSource
from rover_sim.config import SimConfig
from rover_sim.world import World

TARGET_MS = 1.0


def timed(fn, n: int) -> tuple[float, float]:
    """Median wall and CPU ms per call over n calls (timed in blocks of 50)."""
    walls, cpus = [], []
    block = 50
    for _ in range(max(1, n // block)):
        w0, c0 = time.perf_counter(), time.process_time()
        for _ in range(block):
            fn()
        walls.append((time.perf_counter() - w0) * 1e3 / block)
        cpus.append((time.process_time() - c0) * 1e3 / block)
    return statistics.median(walls), statistics.median(cpus)


def format_table(result: dict) -> str:
    """The printed table of a result JSON."""
    lines = [f'feed-forward servo step, {result["steps"]} calls, '
             f'OPENBLAS_NUM_THREADS={result["openblas_num_threads"]}',
             f'{"part":34s}{"median ms":>10s}{"CPU ms":>9s}']
    for k, v in result['median_ms'].items():
        lines.append(f'{k:34s}{v:10.3f}{result["median_cpu_ms"][k]:9.3f}')
    lines.append(f'{"target (one 100 Hz step)":34s}{result["target_ms"]:10.3f}')
    lines.append('ratio feed-forward step / simulator step (CPU) = '
                 f'{result["ratio_step_over_sim"]:.2f}')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--steps', type=number(int, lo=50, hi=1_000_000), default=2000)
    args = ap.parse_args()
    truth = load_truth()
    rng = np.random.default_rng(0)
    q, qd = np.array([0.1, -0.6, 1.2, -0.6]), np.array([0.2, -0.1, 0.3, 0.0])
    sample = dict(force=np.array([0.0, 0.0, 9.9]), torque=np.array([2.9, 0.0, 0.0]),
                  gyro=np.zeros(3), specific_force=np.array([0.0, 0.0, 9.81]))

    def noisy() -> dict:
        return {k: v + rng.normal(0, 1e-3, 3) for k, v in sample.items()}
    arm = ArmModel.rover(truth.cg_to_arm, load_kg=0.01)
    obs = BaseObserver(truth, 0.01)
    ff = FeedForward(truth, dt=0.01, source=ParameterSource.IDENTIFIED, load_kg=0.01)
    blending = FeedForward(truth, dt=0.01, source=ParameterSource.IDENTIFIED, load_kg=0.01,
                           blend_s=1e6)
    blending.set_parameters(truth)            # stays mid-blend: both models every step
    world = World(SimConfig(rovers=2, stereo_rate_hz=0.0), [truth, truth])
    try:
        parts = {
            'observer update': lambda: obs.update(**noisy()),
            "Newton-Euler pass (F, f d', G, own)": lambda: arm.terms(
                q, qd, base_rate=(0.0, 0.0, 0.1), qd_ref=qd, qdd_ref=qd),
            'FeedForward.torque': lambda: ff.torque(q=q, qd=qd, **noisy()),
            'FeedForward.torque, blending': lambda: blending.torque(q=q, qd=qd, **noisy()),
            'peer: World.step (2 rovers)': world.step,
        }
        med, med_cpu = {}, {}
        for name, fn in parts.items():
            for _ in range(50):
                fn()                           # warm
            med[name], med_cpu[name] = timed(fn, args.steps)
    finally:
        world.close()
    result = {'steps': args.steps, 'openblas_num_threads': os.environ.get('OPENBLAS_NUM_THREADS'),
              'median_ms': med, 'median_cpu_ms': med_cpu, 'target_ms': TARGET_MS,
              'ratio_step_over_sim': med_cpu['FeedForward.torque']
              / med_cpu['peer: World.step (2 rovers)']}
    print(format_table(result))
    write_json(args.json, result, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
