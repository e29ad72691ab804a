"""The thesis scenario end to end on the model-level simulation (§2.6.1; no rclpy).

    python -m coop_id.experiment --seeds 20 --json out.json   # the +20 % mass step (drift)

The printed table is `format_json` of the JSON `--json` writes (docs/results makes its table
from that JSON the same way).
"""
from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from coop_common.cli import enum_choices, number, output_path
from coop_common.dynparams import BaseParameters, load_truth
from coop_common.files import write_json
from coop_common.params import choice

from .excitation import Excitation, Strategy, constant_excitation
from .identifier_core import Identifier, IdentifierConfig, IdentifierError
from .model import IDX, SensorNoise
from .modelsim import ThesisRover, add_noise, noise_scales, stack_frames


@dataclass
class RunResult:
    """One identification run: the estimates, their standard deviations and information bits, and
    the excitation, per window."""

    strategy: Strategy
    seed: int
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    estimates: list[np.ndarray] = field(default_factory=list)   # consistent values per window
    std: list[np.ndarray] = field(default_factory=list)
    info_bits: list[np.ndarray] = field(default_factory=list)
    excitation: list[np.ndarray] = field(default_factory=list)  # d per window
    # the last window's 95 % interval and observability (set at the run's end)
    final_low: np.ndarray = field(default_factory=lambda: np.zeros(0))
    final_high: np.ndarray = field(default_factory=lambda: np.zeros(0))
    observable: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    consistent: list[bool] = field(default_factory=list)


def reference_noise_scales(truth: BaseParameters, duration_s: float) -> dict[str, np.ndarray]:
    """Maximum sensed deviation per channel under the constant excitation (simulator side)."""
    rover = ThesisRover(truth)
    exc = constant_excitation()
    frames = [rover.rest_frame()]
    for k in range(round(duration_s / 0.005)):
        frames.append(rover.step(exc((k + 1) * 0.005)))
    return noise_scales(stack_frames(frames))


def run_identification(truth: BaseParameters, *, strategy: Strategy | str, seed: int,
                       duration_s: float, noise: float, scales: dict[str, np.ndarray],
                       config: IdentifierConfig | None = None,
                       mass_step: tuple[float, float] | None = None,
                       bias_compensation: bool = True) -> RunResult:
    """One identification run: the rover shakes its arm (all three modes, 18 rows per sample),
    the identifier absorbs noisy samples window by window and re-optimises the excitation.
    mass_step=(t, dm): add dm kg to the base at time t (a rock picked up). `config` is not
    changed: the run's is a copy with `strategy` (IdentifierError for an unknown one)."""
    cfg = replace(config or IdentifierConfig(),
                  strategy=choice(Strategy, strategy, 'strategy', error=IdentifierError))
    noise_model = None
    if bias_compensation and noise > 0:
        # the sensors' datasheet: uniform +-noise x scale has sigma noise x scale / sqrt(3)
        sig = {c: noise * scales[c] / np.sqrt(3.0) for c in scales}
        noise_model = {m: SensorNoise(sig['specific_force'][m], sig['gyro'][m], sig['incl'][m],
                                      sig['force'][m]) for m in range(3)}
    ident = Identifier(cfg, sensor_noise=noise_model)
    rng = np.random.default_rng(seed)
    rover = ThesisRover(truth)
    per_window = round(cfg.window_s * cfg.rate_hz)
    n_windows = round(duration_s / cfg.window_s)
    if n_windows < 1:
        raise ValueError(f'duration {duration_s} s holds no {cfg.window_s} s identification '
                         'window')
    exc: Excitation = ident.excitation
    out = RunResult(cfg.strategy, seed)
    times = []
    prev = [rover.rest_frame()]
    for w in range(n_windows):
        frames = prev if w == 0 else []
        for _ in range(per_window):
            t_next = rover.t + 1.0 / cfg.rate_hz
            if mass_step is not None and rover.t < mass_step[0] <= t_next:
                rover.mass_offset += mass_step[1]
            frames.append(rover.step(exc(t_next)))
        data = add_noise(stack_frames(frames), scales, noise, rng)
        ident.add_samples_all(specific_force=data['specific_force'], gyro=data['gyro'],
                              incl=data['incl'], force=data['force'], torque=data['torque'])
        rep = ident.end_window()
        new = ident.excitation
        if new is not exc:  # a new segment starts its phase now; the PD absorbs the jump
            new = Excitation(new.amplitude_rad, new.frequency_rad_s, new.offset_rad,
                             t_ref=rover.t)
            ident.excitation = new
        exc = new
        times.append(rover.t)
        out.estimates.append(rep.values.copy())
        out.std.append(rep.std.copy())
        out.info_bits.append(rep.information_bits.copy())
        out.excitation.append(exc.d.copy())
        out.consistent.append(rep.consistent)
    out.times = np.array(times)
    out.final_low, out.final_high = rep.ci_low, rep.ci_high
    out.observable = rep.observable
    return out


@dataclass
class StepTracking:
    """One run of the mass-step scenario: how the mass estimate follows the step."""

    seed: int
    times: np.ndarray            # window ends, s
    mass: np.ndarray             # published mass estimate per window, kg
    mean_error: np.ndarray       # mean abs. rel. error (non-zero truths) vs the truth in force
    mass_before: float           # true mass before / after the step
    mass_after: float
    step_s: float

    def mass_error(self) -> np.ndarray:
        """|m / m_true - 1| per window (the truth in force at the window's end)."""
        true = np.where(self._after(), self.mass_after, self.mass_before)
        return np.abs(self.mass / true - 1.0)

    def _after(self) -> np.ndarray:
        # (a window ending at the step holds at most one sample of the new mass: before)
        return self.times > self.step_s + 1e-6

    def settle_time(self, tol: float) -> float | None:
        """Seconds after the step from which the mass estimate stays within tol of the new
        mass (None: not by the end)."""
        after = self._after()
        bad = np.flatnonzero(after & (self.mass_error() > tol))
        if bad.size == 0:
            return float(self.times[after][0] - self.step_s)
        if bad[-1] == self.times.size - 1:
            return None
        return float(self.times[bad[-1] + 1] - self.step_s)

    def worst_after(self, delay_s: float) -> tuple[float, float]:
        """(max mass error, max mean error) over the windows from delay_s after the step."""
        sel = self.times >= self.step_s + delay_s - 1e-9
        return float(self.mass_error()[sel].max()), float(self.mean_error[sel].max())


def mass_step_tracking(truth: BaseParameters, *, seeds: list[int],
                       config_factory: Callable[[], IdentifierConfig], step_s: float = 8.0,
                       duration_s: float = 14.0, fraction: float = 0.2, noise: float = 0.1,
                       strategy: Strategy | str = Strategy.INFORMATION,
                       scales: dict[str, np.ndarray] | None = None) -> list[StepTracking]:
    """The drift scenario of issue #3 item 5: the rover identifies itself, then at step_s
    (after convergence, so that an estimator that does not track visibly lags) picks up a rock
    of `fraction` x its mass. config_factory() gives a fresh IdentifierConfig per run."""
    scales = scales if scales is not None else reference_noise_scales(truth, 4.0)
    x = truth.to_vector()
    m0 = float(x[IDX['mass']])
    dm = fraction * m0
    x_new = x.copy()
    x_new[IDX['mass']] += dm
    nz = x != 0
    out = []
    for seed in seeds:
        r = run_identification(truth, strategy=strategy, seed=seed, duration_s=duration_s,
                               noise=noise, scales=scales, config=config_factory(),
                               mass_step=(step_s, dm))
        est = np.stack(r.estimates)
        ref = np.where((r.times > step_s + 1e-6)[:, None], x_new, x)
        err = (np.abs(est - ref)[:, nz] / np.abs(ref[:, nz])).mean(axis=1)
        out.append(StepTracking(seed, r.times, est[:, IDX['mass']], err, m0, m0 + dm, step_s))
    return out


def format_tracking(runs: list[StepTracking], *, tol: float = 0.05, delay_s: float = 2.0
                    ) -> str:
    """The mass-step runs as a text table: the mass estimate about the step, settling, errors."""
    step = runs[0].step_s
    lines = [f'mass step {runs[0].mass_before:g} -> {runs[0].mass_after:g} kg at {step:g} s, '
             f'{len(runs)} seed(s)',
             f'{"seed":>4s}{"m@step":>8s}{"+1 s":>7s}{"+2 s":>7s}{"+4 s":>7s}{"end":>7s}'
             f'{"t5% s":>7s}{"m err":>9s}{"all err":>9s}  (max from {delay_s:g} s after)']
    for r in runs:
        def at(t: float, r: StepTracking = r) -> float:
            return float(r.mass[np.argmin(np.abs(r.times - t))])
        settle = r.settle_time(tol)
        wm, we = r.worst_after(delay_s)
        lines.append(f'{r.seed:4d}{at(step):8.3f}{at(step + 1):7.3f}{at(step + 2):7.3f}'
                     f'{at(step + 4):7.3f}{r.mass[-1]:7.3f}'
                     f'{"never" if settle is None else f"{settle:.1f}":>7s}'
                     f'{100 * wm:8.1f}%{100 * we:8.1f}%')
    worst = np.array([r.worst_after(delay_s) for r in runs])
    settles = [r.settle_time(tol) for r in runs]
    n_never = sum(v is None for v in settles)
    med = float(np.median([np.inf if v is None else v for v in settles]))
    lines.append(f'mass within {100 * tol:g} % of the new mass from {delay_s:g} s after the '
                 f'step: {int(np.sum(worst[:, 0] <= tol))}/{len(runs)} seeds; worst '
                 f'{100 * worst[:, 0].max():.1f} %, median {100 * np.median(worst[:, 0]):.1f} %')
    med_s = 'never' if not np.isfinite(med) else f'{med:.1f} s'
    lines.append(f'time to stay within {100 * tol:g} %: median {med_s}, never {n_never}; '
                 f'mean error of all parameters from {delay_s:g} s after: worst '
                 f'{100 * worst[:, 1].max():.1f} %')
    return '\n'.join(lines)


def tracking_json(runs: list[StepTracking], *, drift_per_s: float,
                  drift_parameters: tuple[str, ...], strategy: Strategy | str,
                  fraction: float,
                  duration_s: float) -> dict:
    """The JSON of a mass-step run: the settings and each seed's series (what format_json
    prints from)."""
    return {'scenario': 'mass_step', 'drift_per_s': drift_per_s,
            'drift_parameters': list(drift_parameters), 'strategy': str(strategy),
            'fraction': fraction, 'duration_s': duration_s,
            'step_s': runs[0].step_s, 'mass_before': runs[0].mass_before,
            'mass_after': runs[0].mass_after,
            'runs': [{'seed': r.seed, 'times': [float(t) for t in r.times],
                      'mass': [float(m) for m in r.mass],
                      'mean_error': [float(e) for e in r.mean_error]} for r in runs]}


def format_json(doc: dict) -> str:
    """The printed table of a mass-step run, from the JSON `--json` writes."""
    runs = [StepTracking(r['seed'], np.asarray(r['times'], float), np.asarray(r['mass'], float),
                         np.asarray(r['mean_error'], float), doc['mass_before'],
                         doc['mass_after'], doc['step_s']) for r in doc['runs']]
    return (f'drift_per_s {doc["drift_per_s"]:g} on '
            f'{",".join(doc["drift_parameters"]) or "nothing"}, strategy {doc["strategy"]}\n'
            + format_tracking(runs))


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_id.experiment`: the mass step (drift) scenario over seeds."""
    ap = argparse.ArgumentParser(prog='coop_id.experiment',
                                 description='the +20 % mass step (drift) scenario')
    ap.add_argument('--seeds', type=number(int, lo=1, hi=10_000), default=20)
    ap.add_argument('--first-seed', type=number(int, lo=0, hi=2 ** 32 - 1), default=0)
    ap.add_argument('--drift', type=number(float, lo=0.0, hi=10.0), default=0.01,
                    help='drift_per_s')
    ap.add_argument('--drift-parameters', default='mass',
                    help='comma-separated names of Table 2-1 parameters ("" for none)')
    ap.add_argument('--step', type=number(float, lo=0.0, lo_open=True, hi=600.0), default=8.0,
                    help='step time, s')
    ap.add_argument('--duration', type=number(float, lo=0.0, lo_open=True, hi=600.0),
                    default=14.0)
    ap.add_argument('--fraction', type=number(float, lo=-1.0, lo_open=True, hi=10.0),
                    default=0.2, help='the mass step as a fraction of the mass')
    ap.add_argument('--strategy', default=Strategy.INFORMATION.value,
                    choices=enum_choices(Strategy))
    ap.add_argument('--json', type=output_path, default=None,
                    help='write the result here (the printed table is made from it)')
    args = ap.parse_args(argv)
    names = tuple(n for n in args.drift_parameters.split(',') if n)
    unknown = [n for n in names if n not in IDX]
    if unknown:
        ap.error(f'--drift-parameters: unknown {unknown}; of {",".join(IDX)}')
    if not args.step + 2.0 <= args.duration:     # the table reads from 2 s after the step
        ap.error(f'--step ({args.step:g} s) must come at least 2 s before the end (--duration '
                 f'{args.duration:g} s)')

    def factory() -> IdentifierConfig:
        return IdentifierConfig(drift_per_s=args.drift, drift_parameters=names)
    runs = mass_step_tracking(load_truth(), seeds=list(range(args.first_seed,
                                                             args.first_seed + args.seeds)),
                              config_factory=factory, step_s=args.step,
                              duration_s=args.duration, fraction=args.fraction,
                              strategy=args.strategy)
    doc = tracking_json(runs, drift_per_s=args.drift, drift_parameters=names,
                        strategy=args.strategy, fraction=args.fraction,
                        duration_s=args.duration)
    print(format_json(doc))
    if args.json is not None:
        write_json(args.json, doc, indent=1)
    return 0


if __name__ == '__main__':
    sys.exit(main())
