"""The identifier's covariance: the sandwich with a Bartlett (Newey-West) score covariance."""
import numpy as np
import pytest

from coop_common.dynparams import load_truth
from coop_id.identifier_core import Identifier, IdentifierConfig


def test_windowed_bartlett_sums_equal_the_whole_sequence_estimator():
    """Window by window, each reaching back into the previous one's last scores, the pieces add
    up to the Bartlett estimator of the whole score sequence."""
    ident = Identifier(IdentifierConfig(strategy='constant', hac_lags=5))
    g = np.random.default_rng(0).normal(size=(53, 22))
    whole = ident._hac(g, np.zeros((0, 22)))
    ref = g.T @ g
    for k in range(1, 6):
        gk = g[k:].T @ g[:-k]
        ref += (1 - k / 6) * (gk + gk.T)
    np.testing.assert_allclose(whole, ref, rtol=1e-12)
    parts, tail = np.zeros((22, 22)), np.zeros((0, 22))
    for lo, hi in ((0, 3), (3, 20), (20, 21), (21, 53)):      # windows shorter than the lags too
        parts += ident._hac(g[lo:hi], tail)
        tail = np.concatenate([tail, g[lo:hi]])[-5:]
    np.testing.assert_allclose(parts, ref, rtol=1e-12)


def _coloured_run(seed: int, lags: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """25 windows of 20 instants x 18 rows A x = F with smooth regressors and row noise that is
    the sum of 3 successive white draws (correlation 2/3, 1/3, 0 at lags 1, 2, 3, about that of
    the band-passed rows): (error, sandwich std, KF std)."""
    rng = np.random.default_rng(seed)
    ident = Identifier(IdentifierConfig(strategy='constant', hac_lags=lags))
    x = load_truth().to_vector()
    amp = rng.uniform(0.5, 1.5, size=(3, 6, 22)) / ident.scale
    phase = rng.uniform(0, 2 * np.pi, size=(3, 6, 22))
    sigma = np.array([2.0, 2.0, 2.0, 0.5, 0.5, 0.5])
    white = list(rng.normal(size=(2, 3, 6)) * sigma)
    t = 0
    for _ in range(25):
        a = np.empty((20, 3, 6, 22))
        y = np.empty((20, 3, 6))
        for k in range(20):
            a[k] = amp * np.sin(0.3 * t + phase) + 0.3 * amp * rng.normal(size=amp.shape)
            white = white[-2:] + [sigma * rng.normal(size=(3, 6))]
            y[k] = a[k] @ x + sum(white) / np.sqrt(3.0)
            t += 1
        ident._absorb(a, y, ident._r_now(), (0, 1, 2))
        ident.end_window(optimise_excitation=False)
    est, cov = ident.estimate()
    return est - x, np.sqrt(np.diag(cov)), np.sqrt(np.diag(ident.kf.cov))


def test_sandwich_covers_under_coloured_row_noise():
    err, std, _ = map(np.array, zip(*(_coloured_run(s, 12) for s in range(20)), strict=False))
    z = err / std
    rms = np.sqrt(np.mean(z ** 2))
    assert 0.85 < rms < 1.2, rms
    assert 0.88 <= np.mean(np.abs(z) <= 1.96) <= 0.99


def test_without_the_lags_the_sandwich_is_too_narrow():
    err, std, _ = map(np.array, zip(*(_coloured_run(s, 0) for s in range(10)), strict=False))
    assert np.sqrt(np.mean((err / std) ** 2)) > 1.25


def test_random_walk_follows_informed_drift_and_spares_unseen_directions():
    """drift_per_s walks the drifting parameters only where the data can follow (the guard
    against windup, Identifier._walk): a mass step in the rows is followed, while a drifting
    parameter the rows never inform (column zero) keeps its variance instead of winding up."""
    rng = np.random.default_rng(1)
    cfg = IdentifierConfig(strategy='constant', drift_per_s=0.02,
                           drift_parameters=('mass', 'Ixx', 'k_z'))
    ident = Identifier(cfg)
    x = load_truth().to_vector()
    i_m, i_ixx = 0, 1
    var0 = np.diag(ident.kf.cov).copy()
    masses = []
    for w in range(40):
        xt = x.copy()
        if w >= 20:
            xt[i_m] *= 1.2
        a = rng.normal(size=(20, 3, 6, 22)) / ident.scale
        a[..., i_ixx] = 0.0
        y = a @ xt + 0.05 * rng.normal(size=(20, 3, 6))
        ident._absorb(a, y, ident._r_now(), (0, 1, 2))
        ident.end_window(optimise_excitation=False)
        masses.append(ident.estimate()[0][i_m])
    # within 3 % from 2 windows after the step (without the walk: ~10 % low at the end)
    assert np.all(np.abs(np.array(masses[22:]) / (1.2 * x[i_m]) - 1) < 0.03)
    assert np.all(np.abs(np.array(masses[10:20]) / x[i_m] - 1) < 0.03)
    # never informed: no walk (isotropic, as before, it would be var0 + 40 windows of q)
    assert np.diag(ident.kf.cov)[i_ixx] <= var0[i_ixx] * (1 + 1e-9)
    assert ident.walked.shape[1] == 2             # mass and k_z


def test_covariance_stays_positive_when_the_change_detector_fires():
    """The detector's inflation (P -> f P) re-weights every score by 1/f, the tail reaching into
    the next window included: weighting only the window sums left the meat indefinite and
    published negative variances (std 0) a few windows after a firing (seen on rover_sim)."""
    rng = np.random.default_rng(3)
    ident = Identifier(IdentifierConfig(strategy='constant', hac_lags=12))
    assert ident.detector is not None
    x = load_truth().to_vector()
    amp = rng.uniform(0.5, 1.5, size=(3, 6, 22)) / ident.scale
    phase = rng.uniform(0, 2 * np.pi, size=(3, 6, 22))
    fire = {6}
    real_check = ident.detector.check
    for w in range(14):
        a = np.empty((20, 3, 6, 22))
        for k in range(20):
            a[k] = amp * np.sin(0.3 * (20 * w + k) + phase) + 0.3 * amp * rng.normal(
                size=amp.shape)
        y = a @ x + 0.5 * rng.normal(size=(20, 3, 6))
        ident.detector.check = (lambda nis: True) if w in fire else real_check
        ident._absorb(a, y, ident._r_now(), (0, 1, 2))
        ident.end_window(optimise_excitation=False)
        _, cov = ident.estimate()
        assert np.linalg.eigvalsh(cov).min() > 0, f'window {w}'


def test_config_strategy_and_condition_matrix_are_checked_at_construction():
    from coop_id.excitation import ConditionMatrix, Strategy
    from coop_id.identifier_core import IdentifierConfig, IdentifierError

    cfg = IdentifierConfig(strategy='condition', condition_matrix='window')
    assert cfg.strategy is Strategy.CONDITION and cfg.condition_matrix is ConditionMatrix.WINDOW
    with pytest.raises(IdentifierError, match='strategy must be one of'):
        IdentifierConfig(strategy='magic')
    with pytest.raises(IdentifierError, match='condition_matrix must be one of'):
        IdentifierConfig(condition_matrix='best')


def test_named_configurations_thesis_and_best_measured():
    """thesis(): ch. 2 as printed (Eq. 2-13 literal, constant parameters, no change
    detection); best_measured(): the defaults; both take changes and check them."""
    from coop_id.identifier_core import IdentifierConfig, IdentifierError
    t = IdentifierConfig.thesis(rate_hz=100.0)
    assert (t.literal_eq_2_13, t.drift_per_s, t.detect_changes, t.rate_hz) == (
        True, 0.0, False, 100.0)
    assert t.strategy == 'information'
    assert IdentifierConfig.best_measured() == IdentifierConfig()
    with pytest.raises(IdentifierError, match='strategy must be one of'):
        IdentifierConfig.thesis(strategy='shake')
