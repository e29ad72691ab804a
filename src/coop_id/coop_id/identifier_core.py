"""The on-line identifier (no rclpy): sensor samples in, consistent estimates + information out.

Pipeline per arm mode: raw channels (Eq. 2-1 products) -> band-pass filter bank (model.FilterBank)
-> rows of A x = F, decimated -> recursive Kalman filter (estimators.RecursiveEstimator; one
compressed update per call). Every window (0.4 s, §2.6.1) the row noise R is re-estimated from
the window residuals (with an inflation for their serial correlation), a change detector may
forget, the window's scores enter the sandwich covariance (see Identifier.estimate), the
per-parameter information (Eq. 2-12) and a consistent report are computed, and the excitation is
re-optimised. The same class serves the model-level experiment and the ROS node.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from coop_common.params import choice

from .consistency import ChangeDetector, Report, make_report, project_physical
from .errors import CoopIdError
from .estimators import RecursiveEstimator
from .excitation import (
    ConditionMatrix,
    CostContext,
    Excitation,
    ExcitationBounds,
    Strategy,
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


class IdentifierError(CoopIdError):
    """Bad configuration or input."""


@dataclass
class IdentifierConfig:
    """Identifier settings: the excitation strategy, sample rate and window, decimation, the
    information resolution and the optional drift model."""

    strategy: Strategy = Strategy.INFORMATION
    rate_hz: float = 200.0
    window_s: float = 0.4
    decimation: int = 4
    bits: int = 10
    accelerometer: bool = True
    #: random walk of the drifting parameters, fraction of their range per sqrt(s) (0: constant)
    drift_per_s: float = 0.0
    #: the parameters that may drift: by default the carried mass (a rock picked up, issue #3
    #: item 5); the suspension is taken as fixed. Each added name is one more way to explain
    #: the same data: at one excitation frequency w a mass change and stiffness changes look
    #: alike (only k_x,y,z - m w^2 is seen), and a walk on both forgets what told them apart.
    #: All 22 walking (mass-step scenario, 10 seeds) stays sane at 0.005 (mass within 19 %,
    #: median 4 %) but wanders at 0.01 (up to 78 %): a few seconds of memory are too little
    #: for the errors-in-variables correction of the weakly excited directions
    drift_parameters: tuple[str, ...] = ('mass',)
    #: the walk is applied only in directions the data re-learns within this time (the
    #: steady-state memory of the walked filter, see Identifier._walk); the others keep their
    #: information instead of winding up
    drift_horizon_s: float = 4.0
    detect_changes: bool = True
    lm_iterations: int = 2
    extra_starts: int = 1
    literal_eq_2_13: bool = False
    #: see excitation.CostContext.condition_matrix ('condition' strategy only)
    condition_matrix: ConditionMatrix = ConditionMatrix.ACCUMULATED
    prior_path: str | None = None
    #: share of the inclinometer in the roll/pitch angle (rest: integrated gyro); 0 when the
    #: inclinometer cannot resolve the dynamic tilt (10 bits over +-20 deg on the thesis rover)
    incl_weight: float = 0.5
    #: lags (decimated instants) of the Bartlett window of the score covariance (sandwich);
    #: None: those within 0.23 s (12 at 200 Hz / 4), after which the correlation the low-pass
    #: of W(s) (double pole at 40 rad/s: (1 + 40 t) e^(-40 t)) leaves in the rows is < 1e-3
    hac_lags: int | None = None
    #: windows a window's scores wait (re-scored with each newer estimate) before they are
    #: frozen: 2 s, so the large errors of the first windows do not pass for noise
    hac_delay_windows: int = 5

    def __post_init__(self) -> None:
        self.strategy = choice(Strategy, self.strategy, 'strategy', error=IdentifierError)
        self.condition_matrix = choice(ConditionMatrix, self.condition_matrix,
                                       'condition_matrix', error=IdentifierError)

    @classmethod
    def thesis(cls, **changes: Any) -> IdentifierConfig:
        """Ch. 2 as the thesis prints it: the information-based excitation costed by Eq. 2-13
        as printed (literal_eq_2_13), constant parameters (no random walk) and no detection of
        parameter changes. `changes`: the rest (rates, sensors, priors)."""
        return cls(**{'strategy': Strategy.INFORMATION, 'literal_eq_2_13': True,
                      'drift_per_s': 0.0, 'detect_changes': False, **changes})

    @classmethod
    def best_measured(cls, **changes: Any) -> IdentifierConfig:
        """The defaults, with the extensions beyond the thesis that measured best (coop_id
        README): the information-based excitation costed by the information deficit
        1 - In_i / n (Eq. 2-13 as printed rates a fully known parameter like an unknown one)
        and the detection of parameter changes (a rock picked up) on. The errors-in-variables
        bias compensation is `Identifier`'s `sensor_noise` argument, not a setting here."""
        return cls(**changes)


class Identifier:
    """Streaming identification of the 22 base parameters (thesis ch. 2)."""

    def __init__(self, config: IdentifierConfig | None = None, *,
                 arm: ArmModel | None = None,
                 sensor_noise: dict[int, SensorNoise] | None = None) -> None:
        """sensor_noise: per arm mode, the sensors' white-noise sigmas (datasheet / message
        covariances). When given, the published estimate is bias-compensated for the noise in
        the regressors (errors in variables); without it, plain recursive least squares."""
        cfg = config or IdentifierConfig()
        cfg.__post_init__()          # a config whose fields were set after construction
        if cfg.decimation < 1 or cfg.window_s <= 0 or cfg.rate_hz <= 0:
            raise IdentifierError('decimation >= 1, window_s > 0 and rate_hz > 0 required')
        if not 0.0 <= cfg.incl_weight <= 1.0:
            raise IdentifierError('incl_weight must be in [0, 1]')
        if (cfg.hac_lags is not None and cfg.hac_lags < 0) or cfg.hac_delay_windows < 0:
            raise IdentifierError('hac_lags and hac_delay_windows must be >= 0')
        if not (np.isfinite(cfg.drift_per_s) and cfg.drift_per_s >= 0):
            raise IdentifierError('drift_per_s must be finite and >= 0')
        if not cfg.drift_horizon_s >= 2 * cfg.window_s:
            raise IdentifierError('drift_horizon_s must be >= 2 windows')
        unknown = [n for n in cfg.drift_parameters if n not in IDX]
        if unknown:
            raise IdentifierError(f'unknown drift_parameters {unknown}')
        self.hac_lags = (int(np.ceil(0.23 * cfg.rate_hz / cfg.decimation))
                         if cfg.hac_lags is None else int(cfg.hac_lags))
        self.cfg = cfg
        self.arm = arm or ArmModel()
        self.ranges = load_prior_ranges(cfg.prior_path)
        self.scale = self.ranges[:, 1] - self.ranges[:, 0]
        self.prior_std = self.scale / np.sqrt(12.0)  # uniform over the range
        x0 = self.ranges.mean(axis=1)
        self.active = np.ones(N_PARAMS, dtype=bool)
        if not cfg.accelerometer:
            self.active[[IDX[n] for n in TRANSLATIONAL]] = False
        drift = np.zeros(N_PARAMS)
        drift[[IDX[n] for n in cfg.drift_parameters]] = cfg.drift_per_s
        drift[~self.active] = 0.0      # nothing to follow a parameter with
        self.kf = RecursiveEstimator(x0=x0, std0=self.prior_std, scale=self.scale, n_rows=6,
                                     drift_per_s=drift)
        self.banks: dict[int, FilterBank] = {}
        self.tilts: dict[int, TiltTracker] = {}
        self.row_var = np.full(6, np.nan)
        self._win_calls: list[_Call] = []
        self._win_nis: list[tuple[float, int]] = []   # (sum innov^2 / S, rows) per call
        self._counter = 0
        self.samples = 0
        self.detector = ChangeDetector() if cfg.detect_changes else None
        self.excitation: Excitation = constant_excitation()
        # predict at half the update instants (the rows are smooth), each counting twice
        n_pred = max(round(cfg.window_s * cfg.rate_hz / cfg.decimation / 2), 1)
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
        # sandwich covariance (see estimate): M = prior information + the covariance of the
        # summed scores, frozen part + windows still pending (scored with the latest estimate)
        self._m_frozen = np.diag(1.0 / (self.prior_std / self.scale) ** 2)
        # the bread when the current window started (random-walk guard, see _walk)
        self._bread_start = self._m_frozen.copy()
        # directions walked at the last window (columns, drifting parameters, scaled)
        self.walked = np.zeros((0, 0))
        self._pending: list[tuple[list[_Call], float]] = []     # (calls, weight)
        self._score_tail = np.zeros((0, N_PARAMS))
        self._cache: tuple[np.ndarray, np.ndarray] | None = None
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
        a, y = filtered_rows(self._bank(mode), ch, accelerometer=self.cfg.accelerometer,
                             incl_weight=self.cfg.incl_weight)
        n = a.shape[0]
        take = np.flatnonzero((np.arange(n) + self._counter_for(mode)) % self.cfg.decimation
                              == 0)
        self._advance(mode, n)
        self.samples += n
        if take.size:
            self._absorb(a[take][:, None], y[take][:, None], self._r_now(), (mode,))
        return int(take.size)

    def add_samples_all(self, *, specific_force: np.ndarray, gyro: np.ndarray,
                        incl: np.ndarray, force: np.ndarray, torque: np.ndarray) -> int:
        """Absorb (n, 3 modes, .) simultaneous samples of all three arm modes (the thesis's
        18 equations per sample): one 18-row filter update per decimated instant."""
        per_mode = []
        for m in range(3):
            ch = raw_channels(specific_force=specific_force[:, m], gyro=gyro[:, m],
                              incl_roll_pitch=incl[:, m], force=force[:, m], torque=torque[:, m],
                              tilt=self._tilt(m, gyro[:, m], incl[:, m]))
            per_mode.append(filtered_rows(self._bank(m), ch,
                                          accelerometer=self.cfg.accelerometer,
                                          incl_weight=self.cfg.incl_weight))
        a = np.stack([p[0] for p in per_mode], axis=1)        # (n, 3, 6, 22)
        y = np.stack([p[1] for p in per_mode], axis=1)        # (n, 3, 6)
        n = a.shape[0]
        take = np.flatnonzero((np.arange(n) + self._counter_for(0)) % self.cfg.decimation
                              == 0)
        for m in range(3):
            self._advance(m, n)
        self.samples += n
        if take.size:
            self._absorb(a[take], y[take], self._r_now(), (0, 1, 2))
        return int(take.size)

    def _bank(self, mode: int) -> FilterBank:
        bank = self.banks.get(mode)
        if bank is None:      # (not setdefault: building a bank designs 5 filters, ~1 ms)
            bank = self.banks[mode] = FilterBank(rate_hz=self.cfg.rate_hz)
        return bank

    def _absorb(self, a: np.ndarray, y: np.ndarray, r: np.ndarray, modes: tuple[int, ...]
                ) -> None:
        """One Kalman update with every decimated instant of a call: a (k, modes, 6, 22),
        y (k, modes, 6), r (6,) per row type. No prediction happens inside a call and R is fixed
        within it, so this equals the k updates one instant after the other (see
        RecursiveEstimator.update_batch)."""
        k = a.shape[0]
        h = a.reshape(k, -1, N_PARAMS) * self.scale          # scaled rows per instant
        rhs = y.reshape(k, -1)
        r_rows = np.tile(r, len(modes))
        innov, s = self.kf.update_batch(a.reshape(-1, N_PARAMS), rhs.ravel(),
                                        np.tile(r_rows, k))
        # normalised innovation squared against the state before the call (expectation 1)
        self._win_nis.append((float(np.sum(innov ** 2 / s)), innov.size))
        s_inst, c_inst = self._eiv_per_instant(modes, r)
        self._s_acc += k * s_inst
        self._c_acc += k * c_inst
        self._win_calls.append(_Call(h, rhs, 1.0 / r_rows, s_inst, c_inst))
        self._cache = None

    def _tilt(self, mode: int, gyro: np.ndarray, incl: np.ndarray) -> np.ndarray | None:
        """Roll/pitch for the pre-filter products: the inclinometer, or with incl_weight 0 the
        integrated gyro (TiltTracker)."""
        if self.cfg.incl_weight > 0:
            return None
        tracker = self.tilts.setdefault(mode, TiltTracker(rate_hz=self.cfg.rate_hz))
        return tracker.update(gyro, incl)

    def _eiv_per_instant(self, modes: Sequence[int], r: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
        """Per decimated instant, sum over its rows of Sigma_A / R and cov(e_A, e_y) / R
        (scaled): the expected attenuation of the information and the score."""
        s_inst, c_inst = np.zeros((N_PARAMS, N_PARAMS)), np.zeros(N_PARAMS)
        if self._eiv is None:
            return s_inst, c_inst
        sc = self.scale
        for m in modes:
            cov, cxy = self._eiv[m]
            s_inst += np.einsum('rij,r->ij', cov, 1.0 / r) * np.outer(sc, sc)
            c_inst += np.einsum('ri,r->i', cxy, 1.0 / r) * sc
        return s_inst, c_inst

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Current estimate and covariance (SI).

        Estimate: the KF state, bias-compensated when the sensor noise is known (errors in
        variables): x = (J - S)^-1 (J x_kf - c), J = P^-1, S = sum Sigma_A / R,
        c = sum cov(e_A, e_y) / R.

        Covariance: the sandwich B^-1 M B^-1 with B = J - S (J without compensation) and
        M = P0^-1 + Var(sum of the scores g_t = sum_rows h (F - h x) / R - E[.]) estimated from
        the residuals with a Bartlett window over `hac_lags` decimated instants (Newey-West).
        The filter's own P = J^-1 is the covariance only if the rows' noise is white with
        variance R; here it is not: every column and the right-hand side are band-pass filtered
        (the noise is coloured, correlated over tens of ms), the noisy regressors put the
        parameters into the residual (errors in variables), and R is estimated per row type.
        The sandwich holds whatever the weights (R) and the noise colour; with white noise of
        variance R it is J^-1 again (or B^-1 J B^-1 with the compensation, which also widens
        the compensated estimate's covariance by what subtracting S costs)."""
        if self._cache is None:
            self._cache = self._estimate()
        return self._cache[0].copy(), self._cache[1].copy()

    def _estimate(self) -> tuple[np.ndarray, np.ndarray]:
        _, bread, xs = self._solve()
        meat = self._m_frozen.copy()
        tail = self._score_tail
        for calls, weight in self._pending:
            g = np.sqrt(weight) * self._scores(calls, xs)
            meat += self._hac(g, tail)
            tail = g
        # The Bartlett sum over one (weighted) score sequence is positive semi-definite by
        # construction; the drift prediction's transform of the frozen part (not of the
        # score tail) can leave it slightly indefinite: clip, a variance is never negative.
        lam, vec = np.linalg.eigh(0.5 * (meat + meat.T))
        if lam.min() < 0.0:
            meat = (vec * np.maximum(lam, 0.0)) @ vec.T
        b_inv = np.linalg.inv(bread)
        cov_s = b_inv @ meat @ b_inv
        cov_s = 0.5 * (cov_s + cov_s.T)
        return xs * self.scale, cov_s * np.outer(self.scale, self.scale)

    def _solve(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(J, B, x) in scaled coordinates: the filter's information, the bread (J - S, kept
        >= 10 % of J in every direction, or J without compensation) and the estimate."""
        info = np.linalg.inv(self.kf.cov_scaled)
        info = 0.5 * (info + info.T)
        xkf = self.kf.kf.x[:, 0]
        if self._eiv is None or not np.any(self._s_acc):
            return info, info, xkf
        corrected = info - self._s_acc
        # never subtract more information than the data brought: keep >= 10 % of each direction
        ch = np.linalg.cholesky(info)
        lam, vec = np.linalg.eigh(np.linalg.solve(ch, np.linalg.solve(ch, corrected).T).T)
        if lam.min() < 0.1:
            corrected = ch @ (vec * np.maximum(lam, 0.1)) @ vec.T @ ch.T
        bread = 0.5 * (corrected + corrected.T)
        return info, bread, np.linalg.solve(bread, info @ xkf - self._c_acc)

    def _predict(self) -> None:
        """Random-walk prediction over a window (drift_per_s > 0): P -> P + Q in the filter,
        Q the walk of the drifting parameters restricted by `_walk`.
        The compensated estimate and its sandwich covariance C = B^-1 M B^-1 get the same Q,
        their means do not move: B' = (B^-1 + Q)^-1, S' = J' - B', c' = J' x_kf - B' x,
        M' = B' (C + Q) B' (pending windows are frozen first: the map is not linear in M's
        parts)."""
        self._freeze(self.estimate()[0] / self.scale, keep=0)
        _, bread, xs = self._solve()
        b_inv = np.linalg.inv(bread)
        cov = b_inv @ self._m_frozen @ b_inv
        q = self._walk(b_inv)
        self.kf.predict(self.cfg.window_s, q)
        j_new = np.linalg.inv(self.kf.cov_scaled)
        j_new = 0.5 * (j_new + j_new.T)
        b_new = np.linalg.inv(b_inv + q)
        b_new = 0.5 * (b_new + b_new.T)
        if self._eiv is not None and np.any(self._s_acc):
            self._s_acc = j_new - b_new
            self._c_acc = j_new @ self.kf.kf.x[:, 0] - b_new @ xs
        m = b_new @ (cov + q) @ b_new
        self._m_frozen = 0.5 * (m + m.T)
        self._bread_start = b_new
        self._cache = None

    def _walk(self, b_inv: np.ndarray) -> np.ndarray:
        """Q (scaled) of one window's random walk, only in the directions of the drifting
        parameters that the data can follow.

        Why: a walk in a direction the data hardly informs winds its variance up, and with the
        errors-in-variables correction that is not benign: there the filter's information J is
        mostly the regressor noise's, which S subtracts, so the bread B = J - S sits at its
        floor (10 % of J) and the compensated estimate B^-1 (J x_kf - c) amplifies noise
        tenfold, and keeps doing so as the walk feeds it. (With every parameter walking, at one
        excitation frequency the mass and the three stiffnesses moved together along
        k - m w^2 = const, to 28 kg and 10^4 N/m.)
        How: G = the marginal information the window brought on the drifting parameters (the
        inverse of their marginal covariance under the bread, now minus at the window's start),
        eigenvalues w. A direction walked with variance q per window and informed with w per
        window settles at the predicted variance P = q (1 + sqrt(1 + 4 / (q w))) / 2 and the
        gain K = P w / (1 + P w): it forgets its past with a time constant of 1 / K windows.
        Only directions with 1 / K <= n = drift_horizon_s / window_s, i.e.
        w >= 1 / (q n (n - 1)), are walked (q in the drifting parameters' scaled coordinates,
        one drift_per_s for all)."""
        q_all = self.kf.process_noise(self.cfg.window_s)
        d = np.flatnonzero(np.diag(q_all) > 0)
        out = np.zeros_like(q_all)
        self.walked = np.zeros((d.size, 0))
        if d.size == 0:
            return out
        q = float(q_all[d[0], d[0]])                  # one drift_per_s for all of them
        n = self.cfg.drift_horizon_s / self.cfg.window_s
        c0 = np.linalg.inv(self._bread_start)[np.ix_(d, d)]
        c1 = b_inv[np.ix_(d, d)]
        gain = np.linalg.inv(c1) - np.linalg.inv(c0)
        w, v = np.linalg.eigh(0.5 * (gain + gain.T))
        v = v[:, w >= 1.0 / (q * n * (n - 1.0))]
        out[np.ix_(d, d)] = q * (v @ v.T)
        self.walked = v
        return out

    @staticmethod
    def _scores(calls: list[_Call], xs: np.ndarray) -> np.ndarray:
        """(instants, 22) centred scores h^T R^-1 (F - h x) - (c - S x) of a window's calls."""
        out = []
        for c in calls:
            e = (c.y - c.h @ xs) * c.r_inv                                   # (k, rows)
            out.append(np.einsum('kri,kr->ki', c.h, e) - (c.c_inst - c.s_inst @ xs))
        return np.concatenate(out) if out else np.zeros((0, N_PARAMS))

    def _hac(self, g: np.ndarray, before: np.ndarray) -> np.ndarray:
        """Bartlett-weighted sum of g_t g_(t-k)^T + transpose over k <= hac_lags, for the
        instants of g (t - k may reach back into `before`, the previous window's scores)."""
        lags = self.hac_lags
        full = np.concatenate([before[-lags:] if lags else before[:0], g])
        n0 = full.shape[0] - g.shape[0]
        m = g.T @ g
        for k in range(1, lags + 1):
            lo = max(k - n0, 0)                  # first instant of g with a partner k back
            if lo >= g.shape[0]:
                break
            gk = g[lo:].T @ full[n0 + lo - k:full.shape[0] - k]
            m += (1.0 - k / (lags + 1.0)) * (gk + gk.T)
        return m

    def _freeze(self, xs: np.ndarray, keep: int | None = None) -> None:
        """Score the pending windows but the last `keep` (default hac_delay_windows) with
        estimate xs, for good."""
        keep = self.cfg.hac_delay_windows if keep is None else keep
        while len(self._pending) > keep:
            calls, weight = self._pending.pop(0)
            g = np.sqrt(weight) * self._scores(calls, xs)
            self._m_frozen += self._hac(g, self._score_tail)
            self._score_tail = g[-self.hac_lags:] if self.hac_lags else g[:0]

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
        if self._win_calls:
            self._pending.append((list(self._win_calls), 1.0))
            self._cache = None
            self._freeze(self.estimate()[0] / self.scale)
            a = np.concatenate([c.h.reshape(-1, 6, N_PARAMS) for c in self._win_calls])
            y = np.concatenate([c.y.reshape(-1, 6) for c in self._win_calls])
            res = y - a @ self.kf.kf.x[:, 0]                         # (n, 6)
            var = np.mean(res ** 2, axis=0)
            # (the published covariance is the sandwich, whatever R; inflating R for the rows'
            # serial correlation keeps the filter's P, which the excitation design uses, near it)
            infl = np.array([_correlation_inflation(res[:, j]) for j in range(6)])
            new = np.maximum(var * infl, 1e-12)
            if not self.cfg.accelerometer:
                new[:3] = 1.0
            first = not np.all(np.isfinite(self.row_var))
            self.row_var = new if first else 0.5 * self.row_var + 0.5 * new
            nis = sum(v for v, _ in self._win_nis) / max(sum(c for _, c in self._win_nis), 1)
            if self.detector is not None and self.detector.check(nis):
                f = self.detector.inflation
                self.kf.inflate(f)
                self._s_acc /= f
                self._c_acc /= f
                # P -> f P: the sandwich follows (B^-1 M B^-1 -> f B^-1 M B^-1)
                # every score weighted by 1/f, the tail's too: the cross terms between
                # windows before and after stay those of one weighted sequence (weighting
                # only the new windows' sums made the meat indefinite: negative variances)
                self._m_frozen /= f
                self._score_tail = self._score_tail / np.sqrt(f)
                self._bread_start /= f
                self._pending = [(calls, w / f) for calls, w in self._pending]
        self._win_calls.clear()
        self._win_nis.clear()
        self._cache = None
        if self.cfg.drift_per_s > 0:
            self._predict()
        self.report = self._make_report()
        if optimise_excitation and self.cfg.strategy is not Strategy.CONSTANT and \
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
                          active=self.active, literal_eq_2_13=self.cfg.literal_eq_2_13,
                          condition_matrix=self.cfg.condition_matrix)
        self._start_k += 1
        starts = tuple(_start_grid(self._start_k + i) for i in range(self.cfg.extra_starts))
        exc, _ = optimise(self.excitation, self.predictor, ctx, strategy=self.cfg.strategy,
                          bounds=self.bounds, iterations=self.cfg.lm_iterations, starts=starts)
        return exc


@dataclass(frozen=True)
class _Call:
    """The rows one call absorbed, kept for the sandwich covariance: h (k instants, rows, 22)
    scaled, y (k, rows), 1 / R per row, the per-instant errors-in-variables terms."""

    h: np.ndarray
    y: np.ndarray
    r_inv: np.ndarray
    s_inst: np.ndarray
    c_inst: np.ndarray


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
