"""The slave's insertion loop on rover_sim's world core, no DDS and no master: the force-feedback
finish (app. A.4) measured apart from vision and camera placement.

    python -m coop_insertion.force_trials --slots 5.0,4.5,4.375 --seeds 1-5 --json out/ft.json
    python -m coop_insertion.force_trials --friction 0.2 ...   # the card's mu on the site

Each trial places the slave with the card 0.55 m short of the slot (perturbed by the seed, as
`table_5_1` does) and runs `slave.SlaveController` at the physics rate on the world's own
sensors (encoders, odometry, F/T). Its vision is ideal but honest in rate and noise: the true
marker positions seen from a fixed camera 0.6 m from the site, with a 0.1 px-disparity depth
noise, at 4 Hz, only while the card is in that camera's field. The simulator's truth judges each
trial as `table_5_1` does: seated, penetration at most 0.5 mm. --friction sets the simulator's
contact_friction (SimConfig's default otherwise); the slave is not told it. Each trial records
whether the slave's verdict (seated or not) agreed with the truth's seated.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from coop_common.cli import output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from coop_common.rover_geometry import ARM_JOINTS, joint2_in_base

from .slave import Phase, SeatVerdict, SlaveController, SlaveStatus
from .task import LabelledMarkers, TaskModel

#: the fixes' depth noise: a 0.1 px disparity at 0.6 m with f = 850 px, b = 38 mm
SIGMA_DEPTH_M = 5e-4
PENETRATION_LIMIT_M = 5e-4


@dataclass
class Trial:
    """One force-only trial: the truth's verdict, the slave's own, and what was measured."""

    slot_in: float
    seed: int
    success: bool               # the truth: seated, penetration within the limit
    action_success: bool        # the slave's own verdict
    seated: bool
    max_penetration_mm: float
    peak_force_n: float
    sim_s: float
    reason: str
    friction: float = float('nan')      # the simulator's contact_friction
    verdict_agrees: bool = True         # the slave's seated verdict == the truth's seated
    end_contact_n: float = 0.0          # the truth's contact force on the card at the end (N)


def run_trial(slot_in: float, seed: int, *, vision: bool = True, sim_s: float = 45.0,
              slave_options: dict | None = None, site_bias_m: tuple[float, float] = (0.0, 0.0),
              friction: float | None = None, fail_in_contact_s: float | None = None,
              map_error_m: tuple[float, float] = (0.0, 0.0), start_yaw_rad: float = 0.0
              ) -> tuple[Trial, SlaveStatus, list[Phase], SlaveController]:
    """One insertion from the perturbed start until the slave is done or `sim_s` passed.
    site_bias_m: (near, far) slot markers seen this much higher than they are (m), a constant
    error of the site frame as the master's stereo makes it (equal: depth; opposite: tilt).
    friction: the simulator's contact_friction (None: SimConfig's default). fail_in_contact_s:
    the slave is failed (as by a timeout) once it has been this long in contact, and the
    world runs on 2 s with its commands (what a failure leaves on the card). map_error_m:
    (x, y) the site the slave approaches is off by (its odometry frame and the master's
    disagree), the fixes still the true markers'. start_yaw_rad: added to the slave's heading
    at the start."""
    from rover_sim.config import NoiseConfig, SimConfig  # noqa: PLC0415 - only to run trials
    from rover_sim.world import World  # noqa: PLC0415 - PyBullet, only to run trials
    from rover_sim.worldgen import INCH  # noqa: PLC0415 - only to run trials
    gap = slot_in * INCH
    extra: dict[str, Any] = {} if friction is None else {'contact_friction': float(friction)}
    cfg = SimConfig(rovers=2, occlusion_density=0.0, stereo_rate_hz=0.0, slot_gap_m=gap,
                    seed=seed, noise=NoiseConfig(encoder_rad=0.0077), **extra)
    rng = np.random.default_rng(seed)
    with World(cfg, [load_truth()] * 2) as w:
        model = TaskModel(slot_width_m=gap)
        r2 = w.rovers[1].params.cg_to_arm
        sx, sy, top = w.layout.site.slot_centre
        j2 = joint2_in_base(r2)
        w.place_rover(1, sx - 0.30 - j2[0] - 0.55 + rng.uniform(-0.03, 0.03),
                      sy - j2[1] + rng.uniform(-0.02, 0.02),
                      rng.uniform(-0.05, 0.05) + start_yaw_rad)
        site = np.eye(4)
        site[:3, 3] = (sx + map_error_m[0], sy + map_error_m[1], top)
        ctl = SlaveController(model, r2, site_in_odom=site, **(slave_options or {}))
        cam_p = np.array([sx, sy + 0.6, top + 0.35])
        look = np.array([sx, sy, top]) - cam_p
        look /= np.linalg.norm(look)
        xc = np.cross(look, [0.0, 0.0, 1.0])
        xc /= np.linalg.norm(xc)
        r_wc = np.column_stack([xc, np.cross(look, xc), look])
        var = np.array([SIGMA_DEPTH_M ** 2 / 9, SIGMA_DEPTH_M ** 2 / 9, SIGMA_DEPTH_M ** 2])
        k, pen = 0, 0.0
        phases: list[Phase] = []
        contact_t, end_t = None, math.inf
        fix_every = max(1, round(0.25 / w.dt))
        while w.time_s < min(sim_s, end_t):
            w.step()
            k += 1
            rd = w.sense(1)
            xy, yaw, _, _ = w.odometry(1)
            ctl.add_state(w.time_s, rd.joint_positions[:4], [xy[0], xy[1], yaw],
                          np.concatenate([rd.force, rd.torque]))
            c, r = w.card_pose(1)
            seen = abs(c[0] - sx) < 0.15      # the camera's field at the site
            if vision and seen and k % fix_every == 0:
                pts = [c + r @ m for m in model.card_markers] + \
                    [np.array(m) + [0.0, 0.0, b]
                     for m, b in zip(w.layout.site.slot_markers, site_bias_m, strict=False)]
                pc = np.array([r_wc.T @ (p - cam_p) for p in pts])
                pc += rng.normal(size=(4, 3)) * np.sqrt(var)
                ctl.add_observation(w.time_s, LabelledMarkers(
                    pc, np.array([np.diag(var)] * 4), r_wc.T @ np.array([0.0, 0.0, 1.0])))
            if fail_in_contact_s is not None and ctl.phase is Phase.FORCE_INSERT:
                contact_t = w.time_s if contact_t is None else contact_t
                if w.time_s - contact_t >= fail_in_contact_s:
                    ctl.fail('timed out')
                    end_t = w.time_s + 2.0
            cmd = ctl.step(w.time_s)
            if cmd.arm_joints is not None and k % 2 == 0:
                w.command_arm(1, ARM_JOINTS, [0.02], [list(cmd.arm_joints)])
            w.command_velocity(1, cmd.base_linear_x, cmd.base_angular_z)
            cs = w.contact(1)
            pen = max(pen, cs.max_penetration_m if cs else 0.0)
            if not phases or phases[-1] != cmd.status.phase:
                phases.append(cmd.status.phase)
            if cmd.status.done and end_t == math.inf:
                break
        st = cmd.status
        seated = w.seated(1)
        ok = bool(st.done and st.success and seated and pen <= PENETRATION_LIMIT_M)
        said = bool(st.done and st.success)
        trial = Trial(slot_in, seed, ok, said, bool(seated), pen * 1e3,
                      float(ctl.peak_force_n), float(w.time_s),
                      st.reason or f'not done after {sim_s:.0f} sim s ({st.phase.name})',
                      float(cfg.contact_friction), said == bool(seated),
                      float(np.linalg.norm(cs.force)) if cs else 0.0)
        return trial, st, phases, ctl


def _seeds(text: str) -> list[int]:
    if '-' in text:
        a, b = (int(v) for v in text.split('-'))
        return list(range(a, b + 1))
    return [int(v) for v in text.split(',')]


def format_table(trials: list[Trial]) -> str:
    """Per slot: trials, truth-judged successes, the slave's seated verdicts, the truth's seated,
    the verdicts the truth contradicts (false seat: said seated, not seated; missed: seated,
    not said), median and largest peak force, median sim s."""
    lines = [f'{"slot (in)":>9s} {"trials":>6s} {"success":>8s} {"slave said":>10s} '
             f'{"seated":>6s} {"false seat":>10s} {"missed":>6s} {"peak F median (N)":>17s} '
             f'{"max (N)":>7s} {"sim s median":>12s}']
    for slot in sorted({t.slot_in for t in trials}, reverse=True):
        ts = [t for t in trials if t.slot_in == slot]
        lines.append(f'{slot:9.4g} {len(ts):6d} {sum(t.success for t in ts):8d} '
                     f'{sum(t.action_success for t in ts):10d} '
                     f'{sum(t.seated for t in ts):6d} '
                     f'{sum(t.action_success and not t.seated for t in ts):10d} '
                     f'{sum(t.seated and not t.action_success for t in ts):6d} '
                     f'{np.median([t.peak_force_n for t in ts]):17.1f} '
                     f'{max(t.peak_force_n for t in ts):7.1f} '
                     f'{np.median([t.sim_s for t in ts]):12.1f}')
    return '\n'.join(lines)


def format_result(res: dict) -> str:
    """format_table of a --json result."""
    head = (f'contact friction {res["friction"]:g}\n' if res.get('friction') is not None
            else '')
    return head + format_table([Trial(**t) for t in res['trials']]) + \
        f'\n{res["seconds"] / 60:.1f} min'


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_insertion.force_trials`: the trials over slots and seeds."""
    p = argparse.ArgumentParser(prog='force_trials', description=__doc__.split('\n\n')[0])
    p.add_argument('--slots', default='5.0,4.5,4.375', help='slot widths in inches')
    p.add_argument('--seeds', default='1-5', help='e.g. 1-5 or 1,4,7')
    p.add_argument('--sim-s', type=float, default=45.0, help='sim seconds per trial')
    p.add_argument('--site-bias-mm', default='0,0',
                   help='near,far slot markers seen this much higher (a biased site frame)')
    p.add_argument('--friction', type=float, default=None,
                   help="the simulator's contact_friction (the card's mu on the site; default "
                        "SimConfig's); the slave is not told it")
    p.add_argument('--seat-verdict', choices=[v.value for v in SeatVerdict],
                   default=SeatVerdict.FLOOR_FORCE.value,
                   help="what ends the slave's press with seated (slave.SeatVerdict)")
    p.add_argument('--json', type=output_path, default=None)
    args = p.parse_args(argv)
    try:
        slots = [float(v) for v in args.slots.split(',')]
        seeds = _seeds(args.seeds)
        bias = tuple(1e-3 * float(v) for v in args.site_bias_mm.split(','))
        if len(bias) != 2:
            raise ValueError
    except ValueError:
        p.error('--slots: comma-separated inches; --seeds: a-b or comma-separated integers; '
                '--site-bias-mm: near,far')
    if args.friction is not None and not 0.0 <= args.friction <= 2.0:
        p.error('--friction: in [0, 2]')
    if not all(4.25 < s <= 9.8 for s in slots):
        p.error('--slots: each slot must be wider than the 4.25 in card (and at most 9.8 in)')
    t0 = time.perf_counter()
    trials = []
    for slot in slots:
        for seed in seeds:
            trial = run_trial(slot, seed, sim_s=args.sim_s, site_bias_m=bias,
                              friction=args.friction,
                              slave_options={'seat_verdict': args.seat_verdict})[0]
            trials.append(trial)
            print(f'{slot} in seed {seed}: {"success" if trial.success else "failure"} '
                  f'({trial.reason}); seated {trial.seated}'
                  f'{"" if trial.verdict_agrees else " (the verdict disagrees)"}, penetration '
                  f'{trial.max_penetration_mm:.2f} mm, peak {trial.peak_force_n:.1f} N',
                  file=sys.stderr, flush=True)
    res = {'slots': slots, 'seeds': seeds, 'sim_s': args.sim_s, 'site_bias_m': list(bias),
           'friction': trials[0].friction if trials else args.friction,
           'seat_verdict': args.seat_verdict,
           'trials': [asdict(t) for t in trials], 'seconds': time.perf_counter() - t0}
    print(format_result(res))
    if args.json:
        write_json(args.json, res)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
