"""The on-line identifier (no rclpy): sensor samples in, consistent estimates + information out.

Pipeline per arm mode: raw channels (Eq. 2-1 products) -> band-pass filter bank (model.FilterBank)
-> rows of A x = F, decimated -> recursive Kalman filter (estimators.RecursiveEstimator).
Every window (0.4 s, §2.6.1) the row noise R is re-estimated from the window residuals (with an
inflation for their serial correlation), a change detector may forget, the per-parameter
information (Eq. 2-12) and a consistent report are computed, and the excitation is re-optimised.
The same class serves the model-level experiment and the ROS node.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .consistency import ChangeDetector, Report, make_report, project_physical
from .estimators import RecursiveEstimator
from .excitation import (
    STRATEGIES,
    CostContext,
    Excitation,
    ExcitationBounds,
    WindowPredictor,
    constant_excitation,
    optimise,
)
from .information import mutual_information_bits
from .model import (
    IDX,
    N_PARAMS,
    TRANSLATIONAL,
    ArmModel,
    FilterBank,
    SensorNoise,
    TiltTracker,
    filtered_rows,
    load_prior_ranges,
    noise_gram,
    raw_channels,
    regressor_noise,
)


class IdentifierError(ValueError):
    """Bad configuration or input."""


@dataclass
class IdentifierConfig:
    strategy: str = 'information'
    rate_hz: float = 200.0
    window_s: float = 0.4
    decimation: int = 4
    bits: int = 10
    accelerometer: bool = True
    drift_per_s: float = 0.0
    detect_changes: bool = True
    lm_iterations: int = 2
    extra_starts: int = 1
    literal_eq_2_13: bool = False
    prior_path: str | None = None
    #: share of the inclinometer in the roll/pitch angle (rest: integrated gyro); 0 when the
    #: inclinometer cannot resolve the dynamic tilt (10 bits over +-20 deg on the thesis rover)
    incl_weight: float = 0.5


class Identifier:
    """Streaming identification of the 22 base parameters (thesis ch. 2)."""

    def __init__(self, config: IdentifierConfig | None = None, *,
                 arm: ArmModel | None = None,
                 sensor_noise: dict[int, SensorNoise] | None = None) -> None:
        """sensor_noise: per arm mode, the sensors' white-noise sigmas (datasheet / message
        covariances). When given, the published estimate is bias-compensated for the noise in
        the regressors (errors in variables); without it, plain recursive least squares."""
        cfg = config or IdentifierConfig()
        if cfg.strategy not in STRATEGIES:
            raise IdentifierError(f'strategy must be one of {STRATEGIES}, got {cfg.strategy!r}')
        if cfg.decimation < 1 or cfg.window_s <= 0 or cfg.rate_hz <= 0:
            raise IdentifierError('decimation >= 1, window_s > 0 and rate_hz > 0 required')
        if not 0.0 <= cfg.incl_weight <= 1.0:
            raise IdentifierError('incl_weight must be in [0, 1]')
        self.cfg = cfg
        self.arm = arm or ArmModel()
        self.ranges = load_prior_ranges(cfg.prior_path)
        self.scale = self.ranges[:, 1] - self.ranges[:, 0]
        self.prior_std = self.scale / np.sqrt(12.0)  # uniform over the range
        x0 = self.ranges.mean(axis=1)
        self.kf = RecursiveEstimator(x0=x0, std0=self.prior_std, scale=self.scale, n_rows=6,
                                     drift_per_s=cfg.drift_per_s)
        self.banks: dict[int, FilterBank] = {}
        self.tilts: dict[int, TiltTracker] = {}
        self.row_var = np.full(6, np.nan)
        self._win_rows: list[np.ndarray] = []
        self._win_y: list[np.ndarray] = []

        self._win_nis: list[float] = []
        self._counter = 0
        self.samples = 0
        self.detector = ChangeDetector() if cfg.detect_changes else None
        self.excitation: Excitation = constant_excitation()
        self.active = np.ones(N_PARAMS, dtype=bool)
        if not cfg.accelerometer:
            self.active[[IDX[n] for n in TRANSLATIONAL]] = False
        # predict at half the update instants (the rows are smooth), each counting twice
        n_pred = max(int(round(cfg.window_s * cfg.rate_hz / cfg.decimation / 2)), 1)
        self.predictor = WindowPredictor(
            arm=self.arm, times=np.arange(n_pred) * 2 * cfg.decimation / cfg.rate_hz,
            accelerometer=cfg.accelerometer, weight=2.0)
        self.bounds = ExcitationBounds()
        self._start_k = 0
        self._eiv = None
        if sensor_noise:
            gram = noise_gram(FilterBank(rate_hz=cfg.rate_hz), rate_hz=cfg.rate_hz)
            self._eiv = {m: regressor_noise(sn, gram, accelerometer=cfg.accelerometer,
                                            incl_weight=cfg.incl_weight)
                         for m, sn in sensor_noise.items()}
        self._s_acc = np.zeros((N_PARAMS, N_PARAMS))   # sum Sigma_row / R (scaled)
        self._c_acc = np.zeros(N_PARAMS)
        self.report: Report = self._make_report()

    # -- data in -----------------------------------------------------------------------------
    def add_samples(self, mode: int, *, specific_force: np.ndarray, gyro: np.ndarray,
                    incl: np.ndarray, force: np.ndarray, torque: np.ndarray) -> int:
        """Absorb (n, .) consecutive samples of one arm mode (0 = x, 1 = y, 2 = z) at rate_hz.

        The first call for a mode must start at rest (it primes that mode's filters).
        Returns the number of filter updates made.
        """
        if mode not in (0, 1, 2):
            raise IdentifierError('mode must be 0, 1 or 2')
        ch = raw_channels(specific_force=specific_force, gyro=gyro, incl_roll_pitch=incl,
                          force=force, torque=torque, tilt=self._tilt(mode, gyro, incl))
        bank = self.banks.setdefault(mode, FilterBank(rate_hz=self.cfg.rate_hz))
        a, y = filtered_rows(bank, ch, accelerometer=self.cfg.accelerometer,
                             incl_weight=self.cfg.incl_weight)
        n = a.shape[0]
        take = (np.arange(n) + self._counter_for(mode)) % self.cfg.decimation == 0
        self._advance(mode, n)
        updates = 0
        r = self._r_now()
        self._accumulate_eiv((mode,), int(take.sum()), r)
        for k in np.flatnonzero(take):
            innov = self.kf.update(a[k], y[k], r)
            s = np.diag(self.kf.kf.S)
            self._win_nis.append(float(np.mean(innov ** 2 / s)))
            self._win_rows.append(a[k])
            self._win_y.append(y[k])
            updates += 1
        self.samples += n
        return updates

    def add_samples_all(self, *, specific_force: np.ndarray, gyro: np.ndarray,
                        incl: np.ndarray, force: np.ndarray, torque: np.ndarray) -> int:
        """Absorb (n, 3 modes, .) simultaneous samples of all three arm modes (the thesis's
        18 equations per sample): one 18-row filter update per decimated instant."""
        per_mode = []
        for m in range(3):
            ch = raw_channels(specific_force=specific_force[:, m], gyro=gyro[:, m],
                              incl_roll_pitch=incl[:, m], force=force[:, m], torque=torque[:, m],
                              tilt=self._tilt(m, gyro[:, m], incl[:, m]))
            bank = self.banks.setdefault(m, FilterBank(rate_hz=self.cfg.rate_hz))
            per_mode.append(filtered_rows(bank, ch, accelerometer=self.cfg.accelerometer,
                                          incl_weight=self.cfg.incl_weight))
        a = np.stack([p[0] for p in per_mode], axis=1)        # (n, 3, 6, 22)
        y = np.stack([p[1] for p in per_mode], axis=1)        # (n, 3, 6)
        n = a.shape[0]
        take = (np.arange(n) + self._counter_for(0)) % self.cfg.decimation == 0
        for m in range(3):
            self._advance(m, n)
        r = np.tile(self._r_now(), 3)
        updates = 0
        take_idx = np.flatnonzero(take)
        self._accumulate_eiv(range(3), len(take_idx), self._r_now())
        for k in take_idx:
            innov = self.kf.update(a[k].reshape(18, -1), y[k].ravel(), r)
            s = np.diag(self.kf.kf.S)
            self._win_nis.append(float(np.mean(innov ** 2 / s)))
            self._win_rows.extend(a[k])
            self._win_y.extend(y[k])
            updates += 1
        self.samples += n
        return updates

    def _tilt(self, mode: int, gyro: np.ndarray, incl: np.ndarray) -> np.ndarray | None:
        """Roll/pitch for the pre-filter products: the inclinometer, or with incl_weight 0 the
        integrated gyro (TiltTracker)."""
        if self.cfg.incl_weight > 0:
            return None
        tracker = self.tilts.setdefault(mode, TiltTracker(rate_hz=self.cfg.rate_hz))
        return tracker.update(gyro, incl)

    def _accumulate_eiv(self, modes, n_updates: int, r: np.ndarray) -> None:
        if self._eiv is None or n_updates == 0:
            return
        sc = self.scale
        for m in modes:
            cov, cxy = self._eiv[m]
            self._s_acc += n_updates * np.einsum('rij,r->ij', cov, 1.0 / r) * np.outer(sc, sc)
            self._c_acc += n_updates * np.einsum('ri,r->i', cxy, 1.0 / r) * sc

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Current estimate and covariance (SI); bias-compensated when noise is known:
        x = (P^-1 - S)^-1 (P^-1 x_kf - c), S = sum Sigma_A / R, c = sum cov(e_A, e_y) / R."""
        if self._eiv is None or not np.any(self._s_acc):
            return self.kf.x, self.kf.cov
        info = np.linalg.inv(self.kf.cov_scaled)
        info = 0.5 * (info + info.T)
        corrected = info - self._s_acc
        # never subtract more information than the data brought: keep >= 10 % of each direction
        lam, vec = np.linalg.eigh(np.linalg.solve(np.linalg.cholesky(info), np.linalg.solve(
            np.linalg.cholesky(info), corrected).T).T)
        if lam.min() < 0.1:
            lam_c = np.maximum(lam, 0.1)
            ch = np.linalg.cholesky(info)
            corrected = ch @ (vec * lam_c) @ vec.T @ ch.T
        xs = np.linalg.solve(corrected, info @ self.kf.kf.x[:, 0] - self._c_acc)
        cov_s = np.linalg.inv(corrected)
        cov_s = 0.5 * (cov_s + cov_s.T)
        return xs * self.scale, cov_s * np.outer(self.scale, self.scale)

    def _counter_for(self, mode: int) -> int:
        return getattr(self, f'_count_{mode}', 0)

    def _advance(self, mode: int, n: int) -> None:
        setattr(self, f'_count_{mode}', self._counter_for(mode) + n)

    def _r_now(self) -> np.ndarray:
        if np.all(np.isfinite(self.row_var)):
            return self.row_var
        # before the first window: the model explains nothing yet -> rows' own scale (cautious)
        return np.full(6, 1e3)

    # -- once per window ---------------------------------------------------------------------
    def end_window(self, *, optimise_excitation: bool = True) -> Report:
        """Re-estimate R, detect changes, drift-predict, report, re-optimise the excitation."""
        if self._win_rows:
            a = np.stack(self._win_rows)
            y = np.stack(self._win_y)
            res = y - a @ self.kf.x                                  # (n, 6)
            var = np.mean(res ** 2, axis=0)
            infl = np.array([_correlation_inflation(res[:, j]) for j in range(6)])
            new = np.maximum(var * infl, 1e-12)
            if not self.cfg.accelerometer:
                new[:3] = 1.0
            first = not np.all(np.isfinite(self.row_var))
            self.row_var = new if first else 0.5 * self.row_var + 0.5 * new
            if self.detector is not None and self.detector.check(float(np.mean(self._win_nis))):
                self.kf.inflate(self.detector.inflation)
                self._s_acc /= self.detector.inflation
                self._c_acc /= self.detector.inflation
        self._win_rows.clear()
        self._win_y.clear()
        self._win_nis.clear()
        self.kf.predict(self.cfg.window_s)
        self.report = self._make_report()
        if optimise_excitation and self.cfg.strategy != 'constant' and \
                np.all(np.isfinite(self.row_var)):
            self.excitation = self._reoptimise()
        return self.report

    def _make_report(self) -> Report:
        x, cov = self.estimate()
        std = np.sqrt(np.clip(np.diag(cov), 0, None))
        info = mutual_information_bits(np.clip(x, self.ranges[:, 0], self.ranges[:, 1]), std,
                                       self.ranges[:, 0], self.ranges[:, 1], bits=self.cfg.bits)
        rep = make_report(x, cov, info, prior_std=self.prior_std)
        obs = rep.observable & self.active
        return Report(rep.values, rep.std, rep.ci_low, rep.ci_high, rep.information_bits, obs,
                      rep.consistent)

    def _reoptimise(self) -> Excitation:
        x = project_physical(self.estimate()[0])
        ctx = CostContext(x=x, info_scaled=np.linalg.inv(self.kf.cov_scaled), scale=self.scale,
                          ranges=self.ranges, row_var=self.row_var, bits=self.cfg.bits,
                          active=self.active, literal_eq_2_13=self.cfg.literal_eq_2_13)
        self._start_k += 1
        starts = tuple(_start_grid(self._start_k + i) for i in range(self.cfg.extra_starts))
        exc, _ = optimise(self.cfg.strategy, self.excitation, self.predictor, ctx,
                          bounds=self.bounds, iterations=self.cfg.lm_iterations, starts=starts)
        return exc


def _start_grid(k: int) -> np.ndarray:
    """Deterministic extra LM starts cycling through the frequency band (local minima in w)."""
    freqs = (2.0, 8.0, 16.0, 4.0, 24.0, 12.0)
    w = freqs[k % len(freqs)]
    return np.array([0.6, w, 0.5 * ((k % 3) - 1)])


def _correlation_inflation(r: np.ndarray, max_lag: int = 8) -> float:
    """1 + 2 sum rho_k: variance inflation of a sum of serially correlated residuals."""
    r = r - r.mean()
    v = float(r @ r)
    if v <= 0 or r.size < 4 * max_lag:
        return 1.0
    rho = [float(r[:-k] @ r[k:]) / v for k in range(1, max_lag + 1)]
    return float(np.clip(1.0 + 2.0 * sum(rho), 1.0, 50.0))
