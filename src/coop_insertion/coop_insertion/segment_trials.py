"""Two rovers carrying one segment into a truss stage (app. A.4) on rover_sim's world core, no
DDS: `segment.SegmentMaster` on rover 1, `segment.SegmentSlave` on rover 2, each on its own
sensors (arm encoders, odometry, its arm-base F/T), at 100 Hz; the simulator's truth scores.

    python -m coop_insertion.segment_trials --seeds 1-20 --json out/segment.json

Each seed draws the stage's true place (its centre 5 +- 1 cm behind the grasp line, its mouth
at 28 +- 1 cm), the master's belief of it (the centre within +- `prior_error_m`, the mouth
within +- 3 mm: a map's error, never the truth), and the noise. Both rovers use the nominal arm
mount (coop_common NOMINAL_CG_TO_ARM, 1 cm from the simulator's truth) and the arm encoders of
a real arm (force_trials' noise). A trial succeeds when the master says seated, the truth has
the segment seated, it never went more than 1 mm into the stage, and the internal force
between the rovers (the truth's 1/2 |f_1 - f_2|) never exceeded `internal_limit_n`.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from coop_common.cli import output_path
from coop_common.dynparams import load_truth
from coop_common.files import write_json
from coop_common.rover_geometry import (
    ARM_JOINTS,
    NOMINAL_CG_TO_ARM,
    card_in_base,
)

from .errors import InsertionError
from .segment import (
    MasterSettings,
    PartModel,
    PartReference,
    RoverArm,
    SegmentMaster,
    SegmentPhase,
    SegmentSlave,
    SlaveSettings,
)

PENETRATION_LIMIT_M = 1e-3
CONTROL_EVERY = 2              # the controllers at 100 Hz on the 200 Hz physics


@dataclass
class SegmentTrial:
    """One two-rover insertion: the truth's verdicts and what was measured."""

    seed: int
    success: bool
    said_seated: bool
    seated: bool
    tries: int
    peak_internal_force_n: float
    max_penetration_mm: float
    sim_s: float
    reason: str
    partner_error_n: float = math.nan     # rms |slave's estimate - truth| of the master's force
    partner_force_n: float = math.nan     # rms |truth| of the master's force, same span
    silent_at_s: float | None = None
    released: bool = False                # silent master: the slave's internal force fell


@dataclass
class Trace:
    """Per control step, for the Fig. A-10..A-12 analogue (`appendix_a --plots`)."""

    t: list[float] = field(default_factory=list)
    ref: list[list[float]] = field(default_factory=list)          # master's reference (x, z)
    grasp: list[list[list[float]]] = field(default_factory=list)  # true grasp points (2, 3)
    force: list[list[list[float]]] = field(default_factory=list)  # true grasp forces (2, 3)
    estimate: list[list[float]] = field(default_factory=list)     # slave's master estimate
    joints: list[list[list[float]]] = field(default_factory=list)  # (2, 4) arm joints
    base: list[list[list[float]]] = field(default_factory=list)   # (2, 3) base deflection
    internal: list[float] = field(default_factory=list)           # truth |f_int|
    phase: list[str] = field(default_factory=list)


def run_trial(seed: int, *, mass_kg: float = 0.5, clearance_m: float = 0.004,
              prior_error_m: float = 0.015, friction: float | None = None,
              internal_limit_n: float = 20.0, sim_s: float = 160.0,
              silent_at_s: float | None = None, trace: Trace | None = None,
              stage: tuple[float, float] | None = None,
              belief: tuple[float, float] | None = None
              ) -> SegmentTrial:
    """One insertion from the grasp until the master is done or `sim_s` passed.
    silent_at_s: the master stops sending (and moving) this long after the grasp; the trial
    then runs 3 s more and records whether the slave released the internal force.
    stage: the stage's (centre behind the grasp line, mouth height) instead of the seed's
    draw; belief: the master's (centre x, mouth height) instead of the seed's draw."""
    from rover_sim.config import NoiseConfig, SimConfig  # noqa: PLC0415 - only to run trials
    from rover_sim.segment import SegmentSpec, StageSpec  # noqa: PLC0415
    from rover_sim.world import World  # noqa: PLC0415 - PyBullet, only to run trials
    if not (math.isfinite(mass_kg) and mass_kg > 0 and clearance_m > 0 and prior_error_m >= 0):
        raise InsertionError('segment trial: mass, clearance > 0, prior error >= 0')
    extra: dict[str, Any] = {} if friction is None else {'contact_friction': float(friction)}
    cfg = SimConfig(rovers=2, occlusion_density=0.0, stereo_rate_hz=0.0, seed=seed,
                    noise=NoiseConfig(encoder_rad=0.0077), **extra)
    rng = np.random.default_rng(seed)
    model = PartModel(mass_kg=mass_kg)
    with World(cfg, [load_truth()] * 2, card=False) as w:
        for _ in range(100):                          # the arms settle at home
            w.step()
        q_true0 = w.joint_positions(0, ARM_JOINTS)
        g0 = np.array(w.rovers[0].params.cg_to_arm)
        tr0 = w.truth(0)
        # the stage is placed from the truth (the world's layout); no controller reads it
        grip_x = float((tr0.base_position
                        + tr0.base_rotation @ card_in_base(q_true0, g0)[:3, 3])[0])
        behind, top = (0.05 + rng.uniform(-0.01, 0.01), 0.28 + rng.uniform(-0.01, 0.01)) \
            if stage is None else stage
        spec = StageSpec(centre_x=grip_x - behind, top_z=top, clearance_m=clearance_m)
        seg = w.grasp_segment(SegmentSpec(mass_kg=mass_kg, width_m=model.width_m,
                                          height_m=model.height_m), spec)
        belief_x = spec.centre_x + rng.uniform(-prior_error_m, prior_error_m)
        belief_top = spec.top_z + rng.uniform(-0.003, 0.003)
        if belief is not None:
            belief_x, belief_top = belief
        arms, grasps = [], []
        for k in (0, 1):
            rd = w.sense(k)
            xy, yaw, _, _ = w.odometry(k)
            arm = RoverArm(np.array(NOMINAL_CG_TO_ARM), rd.joint_positions[:4],
                           share_kg=0.5 * mass_kg)
            arms.append(arm)
            grasps.append(arm.grasp(rd.joint_positions[:4], xy, yaw))
        t0 = w.time_s
        master = SegmentMaster(model, grasp=grasps[0], stage_x=belief_x,
                               stage_top_z=belief_top, stage_depth_m=spec.depth_m, t0=t0,
                               settings=MasterSettings())
        slave = SegmentSlave(model, grasp=grasps[1], master_grasp=grasps[0], t0=t0,
                             settings=SlaveSettings())
        peak, pen, k = 0.0, 0.0, 0
        err2, tru2, n_free = 0.0, 0.0, 0
        ref: PartReference | None = None
        end_s = t0 + sim_s
        silent_int: list[float] = []
        while w.time_s < end_s:
            w.step()
            k += 1
            truth = seg.last
            assert truth is not None
            peak = max(peak, float(np.linalg.norm(truth.internal_force)))
            pen = max(pen, truth.max_penetration_m)
            if k % CONTROL_EVERY:
                continue
            t = w.time_s
            silent = silent_at_s is not None and t - t0 >= silent_at_s
            rds = [w.sense(i) for i in (0, 1)]
            odo = [w.odometry(i) for i in (0, 1)]
            qs = [rd.joint_positions[:4] for rd in rds]
            fm, mm = arms[0].force(rds[0].force, rds[0].torque, qs[0], odo[0][1])
            fs, _ = arms[1].force(rds[1].force, rds[1].torque, qs[1], odo[1][1])
            # a silent master's process sends nothing: its arm keeps the last set-point and
            # loses the gravity torques (the simulator node drops stale ones)
            for i in ((1,) if silent else (0, 1)):
                w.command_arm_feedforward(i, arms[i].gravity(qs[i]))
            if silent:
                w.command_arm_feedforward(0, np.zeros(len(ARM_JOINTS)))
            if not silent:
                ref = master.step(t, arms[0].grasp(qs[0], odo[0][0], odo[0][1]), fm, mm,
                                  arms[0].pitch(qs[0]))
                w.command_arm(0, ARM_JOINTS, [0.02],
                              [list(arms[0].joints(master.command, master.command_pitch,
                                                   odo[0][0],
                                                   odo[0][1]))])
            target, pitch = slave.step(t, None if silent else ref, fs, arms[1].pitch(qs[1]))
            w.command_arm(1, ARM_JOINTS, [0.02],
                          [list(arms[1].joints(target, pitch, odo[1][0], odo[1][1]))])
            if master.phase in (SegmentPhase.LIFT, SegmentPhase.DESCEND) and not silent and \
                    float(np.linalg.norm(truth.contact_force)) < 0.05:
                e = slave.partner_estimate - truth.grasp_force[0]
                err2 += float(e @ e)
                tru2 += float(truth.grasp_force[0] @ truth.grasp_force[0])
                n_free += 1
            if silent:
                silent_int.append(float(np.linalg.norm(truth.internal_force)))
            if trace is not None:
                trace.t.append(t - t0)
                trace.ref.append([float(ref.position[0]), float(ref.position[2])]
                                 if ref is not None else [math.nan, math.nan])
                trace.grasp.append([(truth.position + truth.rotation @ gi).tolist()
                                    for gi in seg.grasp_in_segment])
                trace.force.append(truth.grasp_force.tolist())
                trace.estimate.append(slave.partner_estimate.tolist())
                trace.joints.append([q.tolist() for q in qs])
                trace.base.append([w.truth(i).dr.tolist() for i in (0, 1)])
                trace.internal.append(float(np.linalg.norm(truth.internal_force)))
                trace.phase.append(master.phase.value)
            if master.phase in (SegmentPhase.DONE, SegmentPhase.FAILED) and silent_at_s is None:
                break
            if silent_at_s is not None and t - t0 >= silent_at_s + 3.0:
                break
        st = master.status
        truth = seg.last
        assert truth is not None
        said = st.phase is SegmentPhase.DONE
        ok = bool(said and truth.seated and pen <= PENETRATION_LIMIT_M
                  and peak <= internal_limit_n)
        reason = st.reason or (
            f'master silent from {silent_at_s:g} s ({st.phase.value})' if silent_at_s is not None
            else f'not done after {sim_s:.0f} s ({st.phase.value})')
        if said and not ok:
            reason += (' (the truth: not seated)' if not truth.seated else
                       f' (internal force {peak:.1f} N over {internal_limit_n:g} N)'
                       if peak > internal_limit_n else f' (penetration {pen * 1e3:.2f} mm)')
        released = bool(silent_int and silent_int[-1] <= max(1.0, 0.5 * silent_int[0]))
        return SegmentTrial(
            seed, ok, said, bool(truth.seated), st.tries, peak, pen * 1e3, w.time_s - t0,
            reason, math.sqrt(err2 / n_free) if n_free else math.nan,
            math.sqrt(tru2 / n_free) if n_free else math.nan, silent_at_s, released)


def format_table(trials: list[SegmentTrial], *, internal_limit_n: float) -> str:
    """Seeds, seated (truth-judged success), the master's verdicts, tries, the peak internal
    force (median, largest) against the limit, the partner-force estimate's rms error."""
    n = len(trials)
    ok = sum(t.success for t in trials)
    peaks = [t.peak_internal_force_n for t in trials]
    errs = [t.partner_error_n for t in trials if math.isfinite(t.partner_error_n)]
    lines = [f'{"seeds":>5s} {"seated":>6s} {"master said":>11s} {"truth seated":>12s} '
             f'{"tries med":>9s} {"peak F_int med (N)":>18s} {"max (N)":>7s} '
             f'{"limit (N)":>9s} {"partner est rms (N)":>19s} {"sim s med":>9s}',
             f'{n:5d} {ok:6d} {sum(t.said_seated for t in trials):11d} '
             f'{sum(t.seated for t in trials):12d} '
             f'{np.median([t.tries for t in trials]) if trials else math.nan:9.1f} '
             f'{np.median(peaks) if peaks else math.nan:18.2f} '
             f'{max(peaks) if peaks else math.nan:7.2f} {internal_limit_n:9.1f} '
             f'{np.median(errs) if errs else math.nan:19.3f} '
             f'{np.median([t.sim_s for t in trials]) if trials else math.nan:9.1f}']
    for t in trials:
        if not t.success:
            lines.append(f'  seed {t.seed}: {t.reason}')
    return '\n'.join(lines)


def _seeds(text: str) -> list[int]:
    if '-' in text:
        a, b = (int(v) for v in text.split('-'))
        return list(range(a, b + 1))
    return [int(v) for v in text.split(',')]


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_insertion.segment_trials`: the two-rover insertion over seeds."""
    p = argparse.ArgumentParser(prog='segment_trials', description=__doc__.split('\n\n')[0])
    p.add_argument('--seeds', default='1-20', help='e.g. 1-20 or 1,4,7')
    p.add_argument('--mass-kg', type=float, default=0.5)
    p.add_argument('--prior-error-m', type=float, default=0.015)
    p.add_argument('--internal-limit-n', type=float, default=20.0)
    p.add_argument('--json', type=output_path, default=None)
    a = p.parse_args(argv)
    try:
        seeds = _seeds(a.seeds)
    except ValueError:
        p.error('--seeds: a-b or comma-separated integers')
    t0 = time.perf_counter()
    trials = []
    for seed in seeds:
        tr = run_trial(seed, mass_kg=a.mass_kg, prior_error_m=a.prior_error_m,
                       internal_limit_n=a.internal_limit_n)
        trials.append(tr)
        print(f'seed {seed}: {"seated" if tr.success else "failure"} ({tr.reason}), '
              f'{tr.tries} tries, peak internal {tr.peak_internal_force_n:.2f} N, '
              f'{tr.sim_s:.1f} s', file=sys.stderr, flush=True)
    print(format_table(trials, internal_limit_n=a.internal_limit_n))
    if a.json:
        write_json(a.json, {'seeds': seeds, 'mass_kg': a.mass_kg,
                            'prior_error_m': a.prior_error_m,
                            'internal_limit_n': a.internal_limit_n,
                            'trials': [asdict(t) for t in trials],
                            'seconds': time.perf_counter() - t0})
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
