#!/usr/bin/env python3
"""Simulator fidelity vs the physics step: relative RMS deviation of the sensed 3-vectors from a
fine-step reference (explicit, default 200 sub-steps) after a 20 Hz low-pass (the band the
identification uses), one rover under the Eq. 2-21 excitation plus a 3 Hz component, noise off;
the implicit integrator at 1, 2, ... engine steps per 5 ms and the explicit one at its sub-steps;
CPU real-time factor beside it.

Usage: bench/sim_substeps.py --json OUT [--implicit 1,2] [--substeps 10,20]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np
from scipy.signal import butter, filtfilt

from coop_common.cli import number, output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from rover_sim.config import Integrator, NoiseConfig, SimConfig
from rover_sim.world import World

SIGNALS = ('base dr', 'base dtheta', 'F/T force', 'F/T torque', 'accel', 'gyro')


def _counts(text: str) -> list[int]:
    try:
        n = [int(v) for v in text.split(',')]
    except ValueError:
        raise argparse.ArgumentTypeError(f'{text!r}: comma-separated integers') from None
    if min(n) < 1:
        raise argparse.ArgumentTypeError(f'{text!r}: sub-steps are >= 1')
    return n


def run(substeps: int, integrator: Integrator = Integrator.EXPLICIT) -> tuple[np.ndarray, float]:
    cfg = SimConfig(rovers=1, stereo_rate_hz=0.0, noise=NoiseConfig(fraction=0.0),
                    physics_substeps=substeps, integrator=integrator)
    with World(cfg, [load_truth()]) as w:
        if w.substeps != substeps:
            raise SystemExit(f'{substeps} sub-steps is below the stability minimum {w.substeps}')
        w.command_arm(0, ['arm_joint_1', 'arm_joint_2'], [1.0], [[0.0, np.pi / 4]])
        for _ in range(300):
            w.step()
        ts = np.arange(0.02, 4.0, 0.02)
        ramp = np.minimum(1.0, ts / 0.5)
        f = (np.pi / 4 + 2 * np.pi / 9 * ramp * np.sin(np.pi / 2 * ts)
             + 0.1 * ramp * np.sin(2 * np.pi * 3 * ts))
        w.command_arm(0, ['arm_joint_2'], ts, f[:, None])
        rows = []
        c0 = time.process_time()
        for _ in range(700):
            w.step()
            tr, s = w.truth(0), w.sense(0)
            rows.append(np.concatenate([tr.dr, tr.dtheta, s.force, s.torque, s.specific_force,
                                        s.angular_velocity]))
        return np.array(rows), 3.5 / (time.process_time() - c0)


def relative_rms(x: np.ndarray, ref: np.ndarray) -> float:
    """RMS of the 3-vector deviation over the RMS of the reference vector's variation: an axis
    the excitation leaves at rest (e.g. the F/T's y force, 0.008 N, a tenth of its noise) is
    not divided by its own near-zero spread."""
    dev = np.sqrt(((x - ref) ** 2).sum(axis=1).mean())
    return float(dev / (np.sqrt(((ref - ref.mean(axis=0)) ** 2).sum(axis=1).mean()) + 1e-15))


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    header = ' '.join(f'{n:>12}' for n in SIGNALS)
    lines = [f'{"integrator, steps":<19} {header} {"CPU RTF 1 rover":>16}']
    for n, row in result['rows'].items():
        per = [row['rel_rms_error'][k] for k in SIGNALS]
        lines.append(f'{n:<19} ' + ' '.join(f'{100 * e:>11.1f}%' for e in per)
                     + f' {row["cpu_rtf"]:>15.1f}x')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--substeps', type=_counts, default=[10, 20],
                    help='comma-separated explicit physics sub-steps per control step')
    ap.add_argument('--implicit', type=_counts, default=[1, 2],
                    help='comma-separated implicit engine steps per control step')
    ap.add_argument('--reference', type=number(int, lo=1, hi=10_000), default=200,
                    help='sub-steps of the reference')
    args = ap.parse_args()
    b, a = butter(4, 20.0 / 100.0)
    ref, _ = run(args.reference)
    ref = filtfilt(b, a, ref, axis=0)
    result = {'reference_substeps': args.reference, 'lowpass_hz': 20.0, 'rows': {}}
    cases = ([(Integrator.IMPLICIT, n) for n in args.implicit]
             + [(Integrator.EXPLICIT, n) for n in args.substeps])
    for integrator, n in cases:
        x, rtf = run(n, integrator)
        x = filtfilt(b, a, x, axis=0)
        per = [relative_rms(x[:, 3 * k:3 * k + 3], ref[:, 3 * k:3 * k + 3])
               for k in range(len(SIGNALS))]
        result['rows'][f'{integrator.value} {n}'] = {
            'rel_rms_error': dict(zip(SIGNALS, per, strict=False)), 'cpu_rtf': rtf}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
