"""App. A in the simulator: what feeding the base's motion forward into the arm's control buys,
with no feed-forward and with the base model on nominal, identified and true parameters.

    ros2 run coop_bringup appendix_a --json out/appendix_a.json --plots out

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
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np

from coop_common.cli import number, output_dir, output_path
from coop_common.dynparams import PARAM_NAMES, BaseParameters, load_truth
from coop_common.files import save_figure, write_json
from coop_common.rover_geometry import ARM_JOINTS, card_in_base
from coop_id.model import load_prior_ranges
from coop_insertion.feedforward import FeedForward, ParameterSource, accept_estimate
from rover_sim.config import SimConfig
from rover_sim.world import World

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


def run(variant: Variant, scenario: Scenario, params: BaseParameters, *, seed: int
        ) -> dict[str, Any]:
    """One run: the card's error (m, 3 axes, base frame) per control period and its times."""
    truth = load_truth()
    world = World(SimConfig(rovers=2, seed=seed, stereo_rate_hz=0.0), [truth, truth])
    try:
        dt = world.dt
        duration = DRIVE_S if scenario == 'driving' else EXCITATION_S
        steps = round(duration / dt)
        # the reference as one dense trajectory (cubic through positions and speeds)
        times = np.arange(1, steps + 1) * dt
        refs = [reference(scenario, t) for t in times]
        world.command_arm(SLAVE, ARM_JOINTS, [0.5] + times[times > 0.5].tolist(),
                          [refs[0].q.tolist()] + [r.q.tolist() for r, t in zip(
                              refs, times, strict=True) if t > 0.5],
                          velocities=[[0.0] * 4] + [r.qd.tolist() for r, t in zip(
                              refs, times, strict=True) if t > 0.5])
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


def plot(series: dict, out: Path) -> list[Path]:
    """One figure per scenario: the card's error over time for each variant."""
    import matplotlib  # noqa: PLC0415 - only --plots needs it
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415
    paths = []
    for scenario in SCENARIOS:
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
    return paths


def format_json(res: dict) -> str:
    """The printed table of a result JSON (docs/results makes its table the same way)."""
    ff = res['feedforward']
    lines = ['App. A, feed-forward of the base motion (Eq. A-4): card position error, mm',
             f'  identified from {ff["identified_from"]}'
             + (f' ({", ".join(ff["identified_unobservable"])} not observed: its estimate)'
                if ff['identified_unobservable'] else ''),
             f'  {"scenario":<11}' + ''.join(f'{v:>20}' for v in VARIANTS)]
    for scenario, row in ff['by_scenario'].items():
        lines.append(f'  {scenario:<11}' + ''.join(
            f'{1e3 * row[v]["rms"]:>9.3f} rms {1e3 * row[v]["peak"]:>6.2f} pk' for v in VARIANTS))
    red = ff['ee_error_reduction_vs_none']
    lines.append('  driving, lower than none: ' + ', '.join(
        f'{v} {100 * red[v]:.1f} %' for v in VARIANTS if v != 'none'))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """`appendix_a` (module docstring)."""
    p = argparse.ArgumentParser(prog='appendix_a', description=__doc__.split('\n\n')[0])
    p.add_argument('--json', type=output_path, help='write the results here')
    p.add_argument('--plots', type=output_dir, help='write the figures into this directory')
    p.add_argument('--seed', type=number(int, lo=0), default=1)
    p.add_argument('--identified', type=Path, default=DEFAULT_IDENTIFIED,
                   help='a `table_2_1 --sim --json` result whose estimates are the identified '
                        f'model (default: {DEFAULT_IDENTIFIED})')
    args = p.parse_args(argv)
    try:
        ff, series = run_feedforward(seed=args.seed, identified=args.identified)
    except ValueError as exc:
        print(f'appendix_a: {exc}', file=sys.stderr)
        return 2
    res = {'feedforward': ff}
    print(format_json(res))
    if args.json:
        write_json(args.json, res)
    if args.plots:
        for path in plot(series, args.plots):
            print(f'wrote {path}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
