#!/usr/bin/env python3
"""Contact in rover_sim: scripted insertions of the card into the Table 5-1 slots.

For each slot gap and each lateral offset of the card from the slot's centre line, rover 2 is
placed with its card level 2 cm above the mouth and lowers it at 1 cm/s (kept level against the
base's sag from its true pitch, as a vision loop would), then holds. Printed per case: seated,
deepest penetration, peak contact force, the bodies touched; and the world's CPU real-time
factor with the card in contact against the same motion far from anything, in the same run.

Usage: bench/sim_contact.py --json OUT [--hold-s S]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from coop_common.cli import number, output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from rover_sim.config import Integrator, NoiseConfig, SimConfig
from rover_sim.scenarios import card_over_slot, lower_card
from rover_sim.world import World
from rover_sim.worldgen import INCH, TABLE_5_1_GAPS_M

OFFSETS_MM = (0.0, 1.0, 2.0, 4.0)


def insertion(gap: float, offset_m: float, hold_s: float, *, away_m: float = 0.0,
              integrator: Integrator = Integrator.EXPLICIT) -> dict:
    """One scripted insertion (away_m: the same arm motion that far from the site)."""
    cfg = SimConfig(rovers=2, occlusion_density=0.0, stereo_rate_hz=0.0, slot_gap_m=gap,
                    noise=NoiseConfig(fraction=0.0), integrator=integrator)
    with World(cfg, [load_truth()] * 2) as w:
        start = card_over_slot(w, 1, offset_m=offset_m, away_m=away_m)
        depth = start.clearance_m + w.layout.site.seat_depth_m + 0.005
        worst, peak, bodies, steps = 0.0, 0.0, set(), 0
        c0 = time.process_time()
        for cs in lower_card(w, start, depth_m=depth, hold_s=hold_s):
            worst = max(worst, cs.max_penetration_m)
            peak = max(peak, math.hypot(*cs.force))
            bodies.update(cs.bodies)
            steps += 1
        cpu = time.process_time() - c0
        return {'gap_in': gap / INCH, 'offset_mm': offset_m * 1e3, 'seated': w.seated(1),
                'depth_mm': w.insertion_depth(1) * 1e3, 'max_penetration_mm': worst * 1e3,
                'peak_force_n': peak, 'bodies': sorted(bodies), 'rtf_cpu': steps * w.dt / cpu}


def format_table(result: dict) -> str:
    """The table main prints, from its JSON result (docs/results pages are made with it)."""
    lines = [f'integrator: {result.get("integrator", "explicit")}',
             f'{"slot (in)":>9} {"offset (mm)":>11} {"seated":>7} {"depth (mm)":>10} '
             f'{"max pen. (mm)":>13} {"peak F (N)":>10}  touched']
    for r in result['cases']:
        depth = f'{r["depth_mm"]:10.1f}' if math.isfinite(r['depth_mm']) else f'{"-":>10}'
        lines.append(f'{r["gap_in"]:>9.3f} {r["offset_mm"]:>11.1f} {r["seated"]!s:>7} {depth} '
                     f'{r["max_penetration_mm"]:>13.4f} {r["peak_force_n"]:>10.2f}  '
                     f'{", ".join(r["bodies"]) or "-"}')
    rate = result['rate']
    lines.append(f'world CPU real-time factor, 2 rovers: {rate["contact"]:.2f}x with the card in '
                 f'contact, {rate["free"]:.2f}x with the same motion in free space '
                 f'(ratio {rate["contact"] / rate["free"]:.2f})')
    return '\n'.join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--json', type=output_path, required=True)
    ap.add_argument('--hold-s', type=number(float, lo=0.0, hi=60.0), default=2.0,
                    help='sim seconds held after the lowering')
    ap.add_argument('--integrator', type=Integrator, default=Integrator.EXPLICIT,
                    choices=list(Integrator), help="the simulator's (rover_sim.config)")
    args = ap.parse_args()
    cases = [insertion(gap, mm * 1e-3, args.hold_s, integrator=args.integrator)
             for gap in TABLE_5_1_GAPS_M for mm in OFFSETS_MM]
    free = insertion(TABLE_5_1_GAPS_M[2], 0.004, args.hold_s, away_m=2.0,
                     integrator=args.integrator)
    contact = next(c for c in cases if c['offset_mm'] == 4.0 and c['gap_in'] == 4.375)
    result = {'hold_s': args.hold_s, 'integrator': args.integrator.value, 'cases': cases,
              'rate': {'contact': contact['rtf_cpu'], 'free': free['rtf_cpu']},
              'clock': 'rtf: sim seconds per CPU second of this process, world core only'}
    print(format_table(result))
    write_json(args.json, result, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
