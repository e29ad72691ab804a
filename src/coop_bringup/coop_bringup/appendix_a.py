"""App. A in the simulator: what feeding the base's motion forward into the arm's control buys,
with no feed-forward and with the base model on nominal, identified and true parameters.

    ros2 run coop_bringup appendix_a --json out/appendix_a.json --plots out
    ros2 run coop_bringup appendix_a --parts segment --json out/appendix_a_segment.json

Part `feedforward` (A.1-A.2, Eq. A-4): the slave rover's arm (the card in its gripper) holds
a pose while the rover drives (velocity steps forward, back and a turn in place: each a jolt of
the compliant base), and follows the thesis's excitation (Eq. 2-21's amplitude and frequency on
arm joint 1, started from rest). Every control period (200 Hz) the arm gets PD + the torques of
coop_insertion.feedforward, computed from that period's sensor readings only (encoders, F/T,
gyro, accelerometer, inclinometer at rest) and the rover's own drive command:

- none: gravity compensation and the arm's own reference dynamics (H q_r'' + h q_r'), no base
  term: the baseline a controller without a base model has;
- nominal: plus F d'' + f d' from the base model on the prior ranges' centres (what is known of
  a small field rover before it identifies itself: coop_id's starting estimate);
- identified: the same on the estimates `table_2_1 --sim` printed (the identifier run through
  the simulator; a parameter it reports unobservable keeps its estimate, as the node does);
- true: the same on the simulator's own parameters (Table 2-1), the bound on what a model
  can buy. Only this experiment reads them, to compare; no node is offered them.

The simulator's truth judges: the card's centre in the base frame from the true joint angles
against where the reference puts it. While driving the reference is still, and the error is
measured from its mean over the half second before the first step (what the base's motion
adds); under the excitation it is the whole tracking error.

Part `tipover` (A.3, Eq. A-5): random aggressive swings and drives with a heavy part in the
gripper, without and with coop_insertion.tipover's limiter, judged by the true zero-moment point.

Part `segment` (A.4, Figs. A-9..A-12): the two rovers carry one segment into a truss stage
(coop_insertion.segment_trials) over `--segment-seeds`, each seed a stage placed anew and a
master that believes it up to 1.5 cm off; then one run whose master falls silent mid-carriage,
to see the slave hold and the internal force settle. The truth judges: seated, the peak internal
force against `--internal-limit-n`, the slave's estimate of the master's force against the
master's true grasp force.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from coop_common.cli import number, output_dir, output_path
from coop_common.dynparams import PARAM_NAMES, BaseParameters, load_truth
from coop_common.files import save_figure, write_json
from coop_common.rover_geometry import (
    ARM_JOINTS,
    WHEEL_CONTACTS,
    card_in_base,
)
from coop_id.model import load_prior_ranges
from coop_insertion.feedforward import FeedForward, ParameterSource, accept_estimate
from coop_insertion.segment_trials import SegmentTrial, Trace
from coop_insertion.segment_trials import format_table as format_segment
from coop_insertion.segment_trials import run_trial as run_segment_trial
from coop_insertion.tipover import (
    Footprint,
    Limit,
    Loads,
    RoverMasses,
    TipOverError,
    limit_path,
    zmp,
)
from rover_sim.config import SimConfig
from rover_sim.world import World

from .mission_seeds import parse_seeds

Variant = Literal['none', 'nominal', 'identified', 'true']
VARIANTS: tuple[Variant, ...] = get_args(Variant)
Scenario = Literal['driving', 'excitation']
SCENARIOS: tuple[Scenario, ...] = get_args(Scenario)
#: the slave (the rover with the card: rover_sim's second)
SLAVE = 1
CARD_KG = 0.01
#: the pose the arm holds while driving: reaching forward, the card level
HOLD = (0.0, -0.6, 1.2, -0.6)
#: the drive: (from t s, forward speed m/s, yaw rate rad/s)
DRIVE = ((0.0, 0.0, 0.0), (2.0, 0.25, 0.0), (4.0, 0.0, 0.0), (5.5, -0.25, 0.0),
         (7.5, 0.0, 0.0), (9.0, 0.0, 0.8), (10.5, 0.0, 0.0))
DRIVE_S = 12.0
SETTLE = (1.5, 2.0)
#: Eq. 2-21 on joint 1: pi/4 + 2 pi/9 sin(pi/2 t), here started from rest at pi/4
EXC_AMPLITUDE, EXC_FREQUENCY, EXC_OFFSET = 2 * math.pi / 9, math.pi / 2, math.pi / 4
EXC_START_S, EXCITATION_S = 2.0, 14.0
DEFAULT_IDENTIFIED = Path('docs/results/data/table_2_1_sim.json')


def nominal_parameters() -> BaseParameters:
    """The prior ranges' centres (coop_id's starting estimate: design knowledge only)."""
    return BaseParameters.from_vector(load_prior_ranges().mean(axis=1))


def identified_parameters(path: Path, *, strategy: str = 'information'
                          ) -> tuple[BaseParameters, list[str]]:
    """The estimates of a `table_2_1 --sim --json` run and the parameters it reported
    unobservable (kept at their estimates, as the feed-forward node keeps them:
    coop_insertion.feedforward.accept_estimate); ValueError when the file lacks them or the
    set would not be accepted."""
    try:
        rows = json.loads(path.read_text())['strategies'][strategy]['per_parameter']
        x = np.array([float(rows[name]['estimate']) for name in PARAM_NAMES])
        observable = [bool(rows[name]['observable']) for name in PARAM_NAMES]
    except (OSError, KeyError, TypeError, ValueError) as exc:
        raise ValueError(f'{path}: no {strategy!r} estimates of a table_2_1 --sim run '
                         f'({exc})') from exc
    verdict = accept_estimate(x, observable=observable, physically_consistent=True, age_s=0.0,
                              max_age_s=1.0)
    if not verdict.ok:
        raise ValueError(f'{path}: the estimates would not be used: {verdict.reason}')
    return BaseParameters.from_vector(x), [n for n, o in zip(PARAM_NAMES, observable,
                                                             strict=True) if not o]


@dataclass(frozen=True)
class Reference:
    """The arm's reference and the rover's drive command at time t."""

    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    speed: float
    yaw_rate: float


def reference(scenario: Scenario, t: float) -> Reference:
    """The scenario's arm reference and drive command at t (s)."""
    z = np.zeros(4)
    match scenario:
        case 'driving':
            speed, yaw_rate = next((v, w) for t0, v, w in reversed(DRIVE) if t >= t0)
            return Reference(np.array(HOLD), z, z, speed, yaw_rate)
        case 'excitation':
            q, qd, qdd = np.array(HOLD), z.copy(), z.copy()
            q[0] = EXC_OFFSET
            if t > EXC_START_S:
                ph = EXC_FREQUENCY * (t - EXC_START_S)
                a, w = EXC_AMPLITUDE, EXC_FREQUENCY
                q[0] += a * (1.0 - math.cos(ph))
                qd[0], qdd[0] = a * w * math.sin(ph), a * w * w * math.cos(ph)
            return Reference(q, qd, qdd, 0.0, 0.0)


def run(variant: Variant, scenario: Scenario, params: BaseParameters, *, seed: int,
        duration_s: float | None = None) -> dict[str, Any]:
    """One run (the scenario's whole length, or `duration_s` of it): the card's error (m, 3
    axes, base frame) per control period and its times."""
    truth = load_truth()
    world = World(SimConfig(rovers=2, seed=seed, stereo_rate_hz=0.0), [truth, truth])
    try:
        dt = world.dt
        duration = duration_s or (DRIVE_S if scenario == 'driving' else EXCITATION_S)
        steps = round(duration / dt)
        # the reference as one dense trajectory (cubic through positions and speeds)
        times = np.arange(1, steps + 1) * dt
        refs = [reference(scenario, t) for t in times]
        world.command_arm(SLAVE, ARM_JOINTS, [0.5] + times[times > 0.5].tolist(),
                          [refs[0].q.tolist()] + [r.q.tolist() for r, t in zip(
                              refs, times, strict=True) if t > 0.5],
                          velocities=[[0.0] * 4] + [r.qd.tolist() for r, t in zip(
                              refs, times, strict=True) if t > 0.5])
        # the core feeds forward the set it is given (NOMINAL and IDENTIFIED differ only in
        # where a node takes it from): here the nominal, identified or true one
        source = ParameterSource.NONE if variant == 'none' else ParameterSource.IDENTIFIED
        ff = FeedForward(params, dt=dt, source=source, load_kg=CARD_KG)
        rest_tilt: np.ndarray | None = None
        names = list(world.sense(SLAVE).joint_names)
        cols = [names.index(j) for j in ARM_JOINTS]
        cg = truth.cg_to_arm
        errors, ts = [], []
        for k in range(steps):
            t = k * dt
            ref = reference(scenario, t)
            world.command_velocity(SLAVE, ref.speed, ref.yaw_rate)
            s = world.sense(SLAVE)
            if rest_tilt is None:
                rest_tilt = s.incl_angles.copy()
            tau = ff.torque(q=s.joint_positions[cols], qd=s.joint_velocities[cols],
                            force=s.force, torque=s.torque, gyro=s.angular_velocity,
                            specific_force=s.specific_force, roll=float(rest_tilt[0]),
                            pitch=float(rest_tilt[1]), anchor_speed=ref.speed,
                            anchor_yaw_rate=ref.yaw_rate, qd_ref=ref.qd, qdd_ref=ref.qdd)
            world.command_arm_feedforward(SLAVE, tau)
            world.step()
            # judged on the truth, against the reference at the instant stepped to
            after = reference(scenario, world.time_s)
            q_true = world.joint_positions(SLAVE, ARM_JOINTS)
            errors.append(card_in_base(q_true, cg)[:3, 3] - card_in_base(after.q, cg)[:3, 3])
            ts.append(world.time_s)
    finally:
        world.close()
    return {'t': np.array(ts), 'error': np.array(errors)}


def score(scenario: Scenario, t: np.ndarray, error: np.ndarray) -> dict[str, float]:
    """RMS and peak of the card's error (m): while driving, from the first drive step on and
    less its mean over the settle window; under the excitation, from its start on."""
    if scenario == 'driving':
        still = (t >= SETTLE[0]) & (t < SETTLE[1])
        e = error[t >= SETTLE[1]] - error[still].mean(axis=0)
    else:
        e = error[t >= EXC_START_S]
    norm = np.linalg.norm(e, axis=1)
    return {'rms': float(np.sqrt(np.mean(norm ** 2))), 'peak': float(norm.max())}


def run_feedforward(*, seed: int, identified: Path) -> tuple[dict[str, Any], dict]:
    """The part's JSON and the runs' series (for plots)."""
    ident, fallback = identified_parameters(identified)
    params: dict[Variant, BaseParameters] = {
        'none': nominal_parameters(), 'nominal': nominal_parameters(),
        'identified': ident, 'true': load_truth()}
    series: dict = {}
    by: dict[str, dict[str, dict[str, float]]] = {}
    for scenario in SCENARIOS:
        by[scenario] = {}
        for variant in VARIANTS:
            r = run(variant, scenario, params[variant], seed=seed)
            series[(scenario, variant)] = r
            by[scenario][variant] = score(scenario, r['t'], r['error'])
    none = by['driving']['none']['rms']
    return {
        'seed': seed,
        'identified_from': str(identified),
        'identified_unobservable': fallback,
        'ee_error_m': {v: by['driving'][v]['rms'] for v in VARIANTS},
        'ee_error_reduction_vs_none': {v: 1.0 - by['driving'][v]['rms'] / none
                                       for v in VARIANTS},
        'by_scenario': by,
    }, series


#: the tip-over study: a part this heavy in the gripper (kg: half the arm, 50 cards), random
#: aggressive arm swings with a drive ramp, the limiter's required margin (fraction of the
#: footprint's depth) and how finely it checks the plan (s)
LOAD_KG = 0.5
TIP_MOTIONS = 100
MIN_FRACTION = 0.2
PLAN_STEP_S = 0.01
TIP_SETTLE_S, TIP_AFTER_S = 0.5, 0.4
START = (0.0, -0.6, 1.2, 0.0)


@dataclass(frozen=True)
class Motion:
    """A swing of the arm from START to `target` in `duration_s` (quintic), with the rover
    ramping its speed to `speed` at `accel` (m/s^2) from the same instant."""

    target: tuple[float, float, float, float]
    duration_s: float
    speed: float
    accel: float

    def scaled(self, scale: float) -> Motion:
        """The same path slower: accelerations times `scale` (time by 1 / sqrt(scale))."""
        return Motion(self.target, self.duration_s / math.sqrt(scale), self.speed,
                      self.accel * scale)

    def arm(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q, q', q'' at t (s from the swing's start)."""
        u = min(max(t / self.duration_s, 0.0), 1.0)
        h = 10 * u ** 3 - 15 * u ** 4 + 6 * u ** 5
        hd = (30 * u ** 2 - 60 * u ** 3 + 30 * u ** 4) / self.duration_s
        hdd = (60 * u - 180 * u ** 2 + 120 * u ** 3) / self.duration_s ** 2
        d = np.array(self.target) - np.array(START)
        return np.array(START) + h * d, hd * d, hdd * d

    def drive(self, t: float) -> tuple[float, float]:
        """The rover's commanded speed and its acceleration at t."""
        ramp = abs(self.speed) / self.accel if self.accel > 0 else 0.0
        if t <= 0.0:
            return 0.0, 0.0
        if t >= ramp:
            return self.speed, 0.0
        return math.copysign(self.accel * t, self.speed), math.copysign(self.accel, self.speed)


def random_motions(n: int, seed: int) -> list[Motion]:
    """n aggressive swings: anywhere in joint 1, reaching out and up, in a quarter to 0.6 s,
    with a drive ramp of 1-4 m/s^2 to up to the rover's top speed either way."""
    rng = np.random.default_rng(seed)
    return [Motion((float(rng.uniform(-math.pi, math.pi)), float(rng.uniform(-1.0, 0.2)),
                    float(rng.uniform(0.2, 2.2)), float(rng.uniform(-1.2, 1.2))),
                   float(rng.uniform(0.25, 0.6)), float(rng.uniform(-0.25, 0.25)),
                   float(rng.uniform(1.0, 4.0))) for _ in range(n)]


def motion_path(masses: RoverMasses, motion: Motion) -> list[tuple[Loads, Loads]]:
    """The limiter's view of a motion (the rover's model, no truth): its instants every
    PLAN_STEP_S from the swing's start to its end."""
    ts = np.arange(-PLAN_STEP_S, motion.duration_s + 1.5 * PLAN_STEP_S, PLAN_STEP_S)
    return masses.path([motion.arm(t)[0] for t in ts], PLAN_STEP_S,
                       [(motion.drive(t)[1], 0.0, 0.0) for t in ts])


def true_margin(world: World, index: int, prev: np.ndarray | None, dt: float,
                footprint: Footprint) -> tuple[float, np.ndarray]:
    """The zero-moment point of the simulator's true state (every link's mass, c.o.m. and its
    acceleration across the last step) as a fraction of the footprint's depth inside it
    (the wheels where the chassis anchor stands; -inf when the ground carries no weight), and
    the velocities for the next call."""
    masses, coms, vels = world.mass_points(index)
    if prev is None:
        return math.inf, vels
    truth = world.truth(index)
    c, s_ = math.cos(truth.anchor_yaw), math.sin(truth.anchor_yaw)
    rot = np.array([[c, -s_], [s_, c]])
    try:
        p = zmp(Loads.of(masses, coms, (vels - prev) / dt))
    except TipOverError:                  # the ground carries no weight: the rover is airborne
        return -math.inf, vels
    local = rot.T @ (p - truth.anchor_position[:2])
    return footprint.margin_fraction(local), vels


def run_tipover_motion(motion: Motion | None, *, seed: int, params: BaseParameters,
                       servo_feedforward: bool = True) -> dict[str, float]:
    """One motion on a fresh simulator (None: the arm holds, the rover stands): the true
    zero-moment point's smallest margin fraction from the swing's start to TIP_AFTER_S after
    it ends. With `servo_feedforward` the arm's PD gets the load's weight and the plan's own
    dynamics (coop_insertion.feedforward, no base term): a servo whose gains were set for the
    card, not the part, lags and overshoots a fast swing by enough to move the true point
    off the plan's."""
    truth = load_truth()
    world = World(SimConfig(rovers=2, seed=seed, stereo_rate_hz=0.0), [truth, truth])
    footprint = Footprint.of(WHEEL_CONTACTS)
    try:
        world.set_gripper_load(SLAVE, LOAD_KG)
        dt = world.dt
        ff = (FeedForward(params, dt=dt, source=ParameterSource.NONE, load_kg=LOAD_KG)
              if servo_feedforward else None)
        names = list(world.sense(SLAVE).joint_names)
        cols = [names.index(j) for j in ARM_JOINTS]

        def servo(t: float) -> None:
            if ff is None:
                return
            s = world.sense(SLAVE)
            _, qd_r, qdd_r = motion.arm(t) if motion is not None else (None, None, None)
            world.command_arm_feedforward(SLAVE, ff.torque(
                q=s.joint_positions[cols], qd=s.joint_velocities[cols], force=s.force,
                torque=s.torque, gyro=s.angular_velocity, specific_force=s.specific_force,
                qd_ref=qd_r, qdd_ref=qdd_r))
        world.command_arm(SLAVE, ARM_JOINTS, [0.3], [list(START)])
        for _ in range(round(TIP_SETTLE_S / dt)):
            servo(-1.0)
            world.step()
        t0 = world.time_s
        length = motion.duration_s if motion else 0.0
        if motion is not None:
            ts = np.arange(dt, length + dt / 2, dt)
            refs = [motion.arm(t) for t in ts]
            world.command_arm(SLAVE, ARM_JOINTS, ts.tolist(), [r[0].tolist() for r in refs],
                              velocities=[r[1].tolist() for r in refs])
        worst, prev = math.inf, None
        for _ in range(round((length + TIP_AFTER_S) / dt)):
            t = world.time_s - t0
            if motion is not None:
                world.command_velocity(SLAVE, motion.drive(t)[0], 0.0)
            servo(t)
            world.step()
            margin, prev = true_margin(world, SLAVE, prev, dt, footprint)
            worst = min(worst, margin)
    finally:
        world.close()
    return {'min_margin': float(worst)}


def run_tipover(*, seed: int, identified: Path, motions: int) -> dict[str, Any]:
    """The tip-over study: each random motion run as planned and through the limiter
    (limit_path on the identified model, MIN_FRACTION of the depth required)."""
    ident, _ = identified_parameters(identified)
    model = RoverMasses.of(ident, load_kg=LOAD_KG)
    rest = model.loads(START)
    rows: list[dict[str, Any]] = []
    for k, motion in enumerate(random_motions(motions, seed)):
        without = run_tipover_motion(motion, seed=seed + k, params=ident)['min_margin']
        try:
            lim: Limit | None = limit_path(motion_path(model, motion), model.footprint,
                                           min_fraction=MIN_FRACTION)
        except TipOverError:
            lim = None
        if lim is None or lim.stop:
            limited, scale, planned = None, None, None
        else:
            limited = motion.scaled(lim.scale) if lim.scale < 1.0 else motion
            scale, planned = lim.scale, lim.margin_fraction
        with_ = run_tipover_motion(limited, seed=seed + k, params=ident)['min_margin']
        rows.append({'motion': k, 'without': without, 'with': with_,
                     'refused': limited is None, 'scale': scale, 'planned_margin': planned})
    worst_without = min(float(r['without']) for r in rows)
    worst_with = min(float(r['with']) for r in rows)
    left_without = sum(r['without'] < 0.0 for r in rows)
    left_with = sum(r['with'] < 0.0 for r in rows)
    return {
        'seed': seed, 'load_kg': LOAD_KG, 'min_fraction': MIN_FRACTION,
        'rest_margin_model': model.footprint.margin_fraction(zmp(rest)),
        'motions': len(rows), 'left_without': left_without, 'left_with': left_with,
        'refused': sum(r['refused'] for r in rows),
        'slowed': sum(r['scale'] is not None and float(r['scale']) < 1.0 for r in rows),
        'min_margin_without': worst_without,
        'min_margin_with': worst_with,
        'below_required_with': sum(r['with'] < MIN_FRACTION for r in rows),
        'rows': rows,
    }


SEGMENT_INTERNAL_LIMIT_N = 20.0
#: the silent-partner run: the master stops sending this long after the grasp (mid-lift)
SILENT_AT_S = 2.0


def run_segment(*, seeds: list[int], internal_limit_n: float = SEGMENT_INTERNAL_LIMIT_N,
                log: bool = True) -> tuple[dict[str, Any], Trace]:
    """Part (c): the two-rover insertion per seed, and the silent-partner run (seed
    seeds[0]); the first seed's trace for the figures."""
    trials: list[SegmentTrial] = []
    trace = Trace()
    for k, seed in enumerate(seeds):
        tr = run_segment_trial(seed, internal_limit_n=internal_limit_n,
                               trace=trace if k == 0 else None)
        trials.append(tr)
        if log:
            print(f'segment seed {seed}: {"seated" if tr.success else "failure"} '
                  f'({tr.reason}), {tr.tries} tries, peak internal '
                  f'{tr.peak_internal_force_n:.2f} N', file=sys.stderr, flush=True)
    silent = run_segment_trial(seeds[0], internal_limit_n=internal_limit_n,
                               silent_at_s=SILENT_AT_S)
    errs = [t.partner_error_n for t in trials if math.isfinite(t.partner_error_n)]
    res = {
        'seeds': len(trials),
        'seated': sum(t.success for t in trials),
        'peak_internal_force_n': max(t.peak_internal_force_n for t in trials),
        'internal_limit_n': internal_limit_n,
        'partner_error_rms_n': float(np.median(errs)) if errs else math.nan,
        'partner_force_rms_n': float(np.median([t.partner_force_n for t in trials
                                                if math.isfinite(t.partner_force_n)])),
        'trials': [asdict(t) for t in trials],
        'silent': asdict(silent),
    }
    return res, trace


def plot_segment(trace: Trace, out: Path) -> list[Path]:
    """The Fig. A-10..A-12 analogue of one run: the grasp points (endpoints) and their forces
    on the part, both rovers' arm joints and base deflections, the internal force and the
    slave's estimate of the master's force against the truth."""
    import matplotlib  # noqa: PLC0415 - only --plots needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415
    t = np.asarray(trace.t)
    grasp, force = np.asarray(trace.grasp), np.asarray(trace.force)
    joints, base = np.asarray(trace.joints), np.asarray(trace.base)
    est = np.asarray(trace.estimate)
    paths = []
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for k, who in enumerate(('master (rover1)', 'slave (rover2)')):
        ax = axes[0, k]
        ax.plot(t, 1e3 * (grasp[:, k, 0] - grasp[0, k, 0]), label='x')
        ax.plot(t, 1e3 * (grasp[:, k, 2] - grasp[0, k, 2]), label='z')
        ax.set_title(f'{who}: endpoint (mm from the grasp)')
        ax.legend(fontsize=8)
        ax = axes[1, k]
        ax.plot(t, force[:, k, 0], label='f_x')
        ax.plot(t, force[:, k, 2], label='f_z')
        ax.set_title(f'{who}: force on the part (N)')
        ax.set_xlabel('time (s)')
        ax.legend(fontsize=8)
    paths.append(save_figure(fig, out / 'appendix_a_segment_endpoints.png'))
    fig, axes = plt.subplots(2, 2, figsize=(10, 6), sharex=True)
    for k, who in enumerate(('master', 'slave')):
        ax = axes[0, k]
        for j in range(4):
            ax.plot(t, joints[:, k, j], lw=0.8, label=ARM_JOINTS[j])
        ax.set_title(f'{who}: arm joints (rad)')
        ax.legend(fontsize=7)
        ax = axes[1, k]
        ax.plot(t, 1e3 * base[:, k, 0], label='dr_x')
        ax.plot(t, 1e3 * base[:, k, 2], label='dr_z')
        ax.set_title(f'{who}: base deflection (mm)')
        ax.set_xlabel('time (s)')
        ax.legend(fontsize=8)
    paths.append(save_figure(fig, out / 'appendix_a_segment_joints_base.png'))
    fig, ax = plt.subplots(figsize=(10, 3.6))
    ax.plot(t, np.asarray(trace.internal), label='internal force, truth |1/2 (f_1 - f_2)|')
    ax.plot(t, force[:, 0, 2], lw=0.8, label="master's f_z, truth")
    ax.plot(t, est[:, 2], lw=0.8, ls='--', label="master's f_z, the slave's estimate")
    ax.set_xlabel('time (s)')
    ax.set_ylabel('N')
    ax.set_title('Surrogate sensing: the partner force the slave estimates, and the truth')
    ax.legend(fontsize=8)
    paths.append(save_figure(fig, out / 'appendix_a_segment_forces.png'))
    return paths


def plot(series: dict, res: dict, out: Path) -> list[Path]:
    """The feed-forward runs' card error over time per scenario; the tip-over study's true
    margins without and with the limiter."""
    import matplotlib  # noqa: PLC0415 - only --plots needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415
    paths = []
    for scenario in SCENARIOS if series else ():
        fig, ax = plt.subplots(figsize=(8, 3.6))
        for variant in VARIANTS:
            r = series[(scenario, variant)]
            e = r['error']
            if scenario == 'driving':
                still = (r['t'] >= SETTLE[0]) & (r['t'] < SETTLE[1])
                e = e - e[still].mean(axis=0)
            ax.plot(r['t'], 1e3 * np.linalg.norm(e, axis=1), lw=0.8, label=variant)
        ax.set_xlabel('time (s)')
        ax.set_ylabel('card position error (mm)')
        ax.set_title(f'Feed-forward of the base motion (Eq. A-4): {scenario}')
        ax.legend(ncol=4, fontsize=8)
        paths.append(save_figure(fig, out / f'appendix_a_feedforward_{scenario}.png'))
    if 'tipover' in res:
        rows = res['tipover']['rows']
        fig, ax = plt.subplots(figsize=(8, 3.6))
        k = [r['motion'] for r in rows]
        ax.scatter(k, [max(r['without'], -1.0) for r in rows], s=10, label='without limiter')
        ax.scatter(k, [r['with'] for r in rows], s=10, label='with limiter')
        ax.axhline(0.0, color='k', lw=0.8)
        ax.axhline(res['tipover']['min_fraction'], color='k', lw=0.8, ls='--')
        ax.set_xlabel('motion')
        ax.set_ylabel('true ZMP margin (fraction of depth, clipped at -1)')
        ax.set_title("Tip-over: the true zero-moment point's smallest margin per motion")
        ax.legend(fontsize=8)
        paths.append(save_figure(fig, out / 'appendix_a_tipover.png'))
    return paths


def format_json(res: dict) -> str:
    """The printed table of a result JSON (docs/results makes its table the same way)."""
    lines: list[str] = []
    if 'feedforward' in res:
        ff = res['feedforward']
        lines += ['App. A, feed-forward of the base motion (Eq. A-4): card position error, mm',
                  f'  identified from {ff["identified_from"]}'
                  + (f' ({", ".join(ff["identified_unobservable"])} not observed: its estimate)'
                     if ff['identified_unobservable'] else ''),
                  f'  {"scenario":<11}' + ''.join(f'{v:>20}' for v in VARIANTS)]
        for scenario, row in ff['by_scenario'].items():
            lines.append(f'  {scenario:<11}' + ''.join(
                f'{1e3 * row[v]["rms"]:>9.3f} rms {1e3 * row[v]["peak"]:>6.2f} pk'
                for v in VARIANTS))
        red = ff['ee_error_reduction_vs_none']
        lines.append('  driving, lower than none: ' + ', '.join(
            f'{v} {100 * red[v]:.1f} %' for v in VARIANTS if v != 'none'))
    if 'tipover' in res:
        t = res['tipover']
        lines += [f'App. A.3, tip-over (Eq. A-5): {t["motions"]} random swings with '
                  f'{t["load_kg"]} kg in the gripper, limiter margin {t["min_fraction"]:.2f}',
                  f'  {"":<16}{"left the footprint":>20}{"true min margin":>17}',
                  f'  {"without limiter":<16}{t["left_without"]:>20d}'
                  f'{t["min_margin_without"]:>17.3f}',
                  f'  {"with limiter":<16}{t["left_with"]:>20d}{t["min_margin_with"]:>17.3f}',
                  f'  with: {t["slowed"]} slowed, {t["refused"]} refused (below the margin '
                  f'standing still), {t["below_required_with"]} under {t["min_fraction"]:.2f} '
                  f'at some instant; model margin at rest {t["rest_margin_model"]:.3f}']
    if 'segment' in res:
        g = res['segment']
        lines += [f'App. A.4, two rovers carry one segment into a truss stage: {g["seeds"]} '
                  'seeds',
                  format_segment([SegmentTrial(**t) for t in g['trials']],
                                 internal_limit_n=g['internal_limit_n']),
                  f'  partner force estimate: rms error {g["partner_error_rms_n"]:.3f} N of a '
                  f'{g["partner_force_rms_n"]:.3f} N rms force (medians over seeds, in free '
                  'carriage)']
        q = g['silent']
        lines.append(f'  master silent {q["silent_at_s"]:g} s after the grasp: the slave '
                     f'{"released" if q["released"] else "did not release"} the internal '
                     f'force (peak {q["peak_internal_force_n"]:.2f} N over the run)')
    return '\n'.join(lines)


PARTS = ('feedforward', 'tipover', 'segment')


def main(argv: list[str] | None = None) -> int:
    """`appendix_a` (module docstring)."""
    p = argparse.ArgumentParser(prog='appendix_a', description=__doc__.split('\n\n')[0])
    p.add_argument('--json', type=output_path, help='write the results here')
    p.add_argument('--plots', type=output_dir, help='write the figures into this directory')
    p.add_argument('--seed', type=number(int, lo=0), default=1)
    p.add_argument('--parts', default=','.join(PARTS),
                   help=f'comma-separated, of {", ".join(PARTS)} (default: all)')
    p.add_argument('--motions', type=number(int, lo=1, hi=10_000), default=TIP_MOTIONS,
                   help=f'random motions of the tip-over study (default {TIP_MOTIONS})')
    p.add_argument('--segment-seeds', default='1-20', metavar='A-B[,C]',
                   help='seeds of the two-rover segment insertion (default 1-20)')
    p.add_argument('--internal-limit-n', type=number(float, lo=0.1), default=20.0,
                   help='the internal force between the rovers a seated run must stay under')
    p.add_argument('--identified', type=Path, default=DEFAULT_IDENTIFIED,
                   help='a `table_2_1 --sim --json` result whose estimates are the identified '
                        f'model (default: {DEFAULT_IDENTIFIED})')
    args = p.parse_args(argv)
    parts = [x for x in args.parts.split(',') if x]
    if not parts or any(x not in PARTS for x in parts):
        p.error(f'--parts: comma-separated, of {", ".join(PARTS)}; got {args.parts!r}')
    try:
        seeds = parse_seeds(args.segment_seeds)
    except ValueError as exc:
        p.error(f'--segment-seeds: {exc}')
    res: dict[str, Any] = {}
    series: dict = {}
    trace: Trace | None = None
    try:
        if 'feedforward' in parts:
            res['feedforward'], series = run_feedforward(seed=args.seed,
                                                         identified=args.identified)
        if 'tipover' in parts:
            res['tipover'] = run_tipover(seed=args.seed, identified=args.identified,
                                         motions=args.motions)
        if 'segment' in parts:
            res['segment'], trace = run_segment(seeds=seeds,
                                                internal_limit_n=args.internal_limit_n)
    except ValueError as exc:
        print(f'appendix_a: {exc}', file=sys.stderr)
        return 2
    print(format_json(res))
    if args.json:
        write_json(args.json, res)
    if args.plots:
        for path in plot(series, res, args.plots) + (
                plot_segment(trace, args.plots) if trace is not None else []):
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
