#!/usr/bin/env python3
"""The simulator's reset between two insertion attempts: wall time from the reset of a world
(two rovers, the insertion site, 640x480 stereo with the right eye in a render worker) to its
first stereo pair, the way `rover_sim`'s sim/reset service does it: the world rebuilt with the
render worker handed over (the same scene: the rovers placed anew), and, its peer in the same
run, rebuilt with a new render worker (what a reset to another scene does).

Usage: bench/sim_reset.py --json OUT [--resets N]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np

from coop_common.cli import number, output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from rover_sim.config import SimConfig
from rover_sim.world import World


def reset_times(resets: int, *, keep_worker: bool) -> list[float]:
    """Wall seconds from each reset to the first stereo pair of the new world."""
    config = SimConfig(rovers=2, slot_gap_m=4.5 * 0.0254, image_width=640, image_height=480,
                       render_workers=1)
    truths = [load_truth()] * 2
    world = World(config, truths)
    world.render_stereo(0)
    times = []
    try:
        for k in range(resets):
            t0 = time.perf_counter()
            worker = world.hand_over_renderer(config, truths) if keep_worker else None
            world.close()
            world = World(config, truths, render_worker=worker)
            world.place_rover(1, 2.0 + 0.01 * k, 0.0, 0.0)
            world.render_stereo(0)
            times.append(time.perf_counter() - t0)
    finally:
        world.close()
    return times


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    lines = [f'{"reset to the first 640x480 stereo pair":<44}{"median (s)":>12}{"max (s)":>10}']
    for key, name in (('kept_worker', 'the render worker handed over (same scene)'),
                      ('new_worker', 'peer: a new render worker')):
        r = result[key]
        lines.append(f'{name:<44}{r["median"]:>12.3f}{r["max"]:>10.3f}')
    lines.append(f'handed over / new, median: {result["ratio"]:.2f} '
                 f'({result["resets"]} resets each)')
    return '\n'.join(lines)


def _stats(values: list[float]) -> dict:
    v = np.asarray(values, float)
    return {'median': float(np.median(v)), 'max': float(v.max()),
            'values': [float(x) for x in v]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--resets', type=number(int, lo=1, hi=100), default=5)
    args = ap.parse_args()
    kept = reset_times(args.resets, keep_worker=True)
    new = reset_times(args.resets, keep_worker=False)
    result = {'kept_worker': _stats(kept), 'new_worker': _stats(new), 'resets': args.resets,
              'ratio': float(np.median(kept) / np.median(new)),
              'clock': 'time.perf_counter, from the reset to the first stereo pair'}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
