"""The thesis scenario end to end on the model-level simulation (§2.6.1; no rclpy)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from coop_common.dynparams import BaseParameters

from .excitation import Excitation, constant_excitation
from .identifier_core import Identifier, IdentifierConfig
from .model import SensorNoise
from .modelsim import ThesisRover, add_noise, noise_scales, stack_frames


@dataclass
class RunResult:
    strategy: str
    seed: int
    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    estimates: list[np.ndarray] = field(default_factory=list)   # consistent values per window
    std: list[np.ndarray] = field(default_factory=list)
    info_bits: list[np.ndarray] = field(default_factory=list)
    excitation: list[np.ndarray] = field(default_factory=list)  # d per window
    final_low: np.ndarray | None = None
    final_high: np.ndarray | None = None
    observable: np.ndarray | None = None
    consistent: list[bool] = field(default_factory=list)


def reference_noise_scales(truth: BaseParameters, duration_s: float) -> dict[str, np.ndarray]:
    """Maximum sensed deviation per channel under the constant excitation (simulator side)."""
    rover = ThesisRover(truth)
    exc = constant_excitation()
    frames = [rover.rest_frame()]
    for k in range(int(round(duration_s / 0.005))):
        frames.append(rover.step(exc((k + 1) * 0.005)))
    return noise_scales(stack_frames(frames))


def run_identification(truth: BaseParameters, *, strategy: str, seed: int, duration_s: float,
                       noise: float, scales: dict[str, np.ndarray],
                       config: IdentifierConfig | None = None,
                       mass_step: tuple[float, float] | None = None,
                       bias_compensation: bool = True) -> RunResult:
    """One identification run: the rover shakes its arm (all three modes, 18 rows per sample),
    the identifier absorbs noisy samples window by window and re-optimises the excitation.
    mass_step=(t, dm): add dm kg to the base at time t (a rock picked up)."""
    cfg = config or IdentifierConfig()
    cfg.strategy = strategy
    noise_model = None
    if bias_compensation and noise > 0:
        # the sensors' datasheet: uniform +-noise x scale has sigma noise x scale / sqrt(3)
        sig = {c: noise * scales[c] / np.sqrt(3.0) for c in scales}
        noise_model = {m: SensorNoise(sig['specific_force'][m], sig['gyro'][m], sig['incl'][m],
                                      sig['force'][m]) for m in range(3)}
    ident = Identifier(cfg, sensor_noise=noise_model)
    rng = np.random.default_rng(seed)
    rover = ThesisRover(truth)
    per_window = int(round(cfg.window_s * cfg.rate_hz))
    n_windows = int(round(duration_s / cfg.window_s))
    exc: Excitation = ident.excitation
    out = RunResult(strategy, seed)
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
