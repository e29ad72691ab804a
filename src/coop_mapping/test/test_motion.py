"""Camera motion correction core (Eq. 3-16..3-22) and a reduced Fig. 3-24 run."""
import cv2
import numpy as np
import pytest

from coop_mapping.motion import (
    FiducialWeights,
    MotionError,
    RecursivePoseStats,
    certainty_term,
    ekf_point_update,
    project_to_so3,
    robust_g01,
    select_fiducials,
    solve_g01,
    solve_g01_so3,
    solve_rigid,
    track,
    visual_contrast,
)


def _pose(seed=0):
    rng = np.random.default_rng(seed)
    R, _ = cv2.Rodrigues(rng.normal(0, 0.3, (3, 1)))
    return R, rng.normal(0, 0.5, 3)


def test_g01_recovers_transform_eq_3_18():
    R, t = _pose(1)
    r = np.random.default_rng(2).uniform(-1, 1, (12, 3)) + [0, 0, 3]
    p = r @ R.T + t
    for g in (solve_g01(r, p), solve_rigid(r, p)):
        assert np.allclose(g[:3, :3], R, atol=1e-9) and np.allclose(g[:3, 3], t, atol=1e-9)
    with pytest.raises(MotionError):
        solve_g01(r[:3], p[:3])
    flat = r.copy()
    flat[:, 2] = 3.0                      # coplanar: the 12-unknown system is singular
    with pytest.raises(MotionError):
        solve_g01(flat, flat @ R.T + t)


def test_g01_so3_camera_position_does_not_depend_on_the_common_origin():
    """Noisy camera-frame points (5 cm along z): the camera position from Eq. 3-18's X as it
    stands moves when the common frame's origin is moved 10 m away from the scene; with R
    projected onto SO(3) and X re-solved it moves by exactly the origin shift."""
    R, t = _pose(5)
    rng = np.random.default_rng(6)
    r = rng.uniform(-0.5, 0.5, (40, 3)) + [0, 0, 1.1]
    p = r @ R.T + t + rng.normal(0, 1.0, (40, 3)) * [0.005, 0.005, 0.05]
    shift = np.array([10.0, -4.0, 3.0])

    def cam(g):  # as the odometry uses it: R projected (Eq. 3-19 mean), X as solved
        return -project_to_so3(g[:3, :3]).T @ g[:3, 3]

    for solve, moves in ((solve_g01, True), (solve_g01_so3, False)):
        d = np.linalg.norm(cam(solve(r + shift, p)) - cam(solve(r, p)) - shift)
        assert (d > 0.05) if moves else (d < 1e-9), d


def test_robust_g01_rejects_outliers():
    R, t = _pose(3)
    rng = np.random.default_rng(4)
    r = rng.uniform(-1, 1, (40, 3)) + [0, 0, 3]
    p = r @ R.T + t + rng.normal(0, 1e-3, (40, 3))
    p[:4] += 0.5                           # four mistracked fiducials
    g, keep = robust_g01(r, p, method='rigid')
    assert not keep[:4].any() and keep[4:].mean() > 0.9
    assert np.linalg.norm(g[:3, 3] - t) < 2e-3


def test_recursive_stats_equal_batch_eq_3_19():
    rng = np.random.default_rng(5)
    gs = []
    st = RecursivePoseStats()
    for _ in range(10):
        g = np.eye(4)
        g[:3, :3] = np.eye(3) + rng.normal(0, 0.01, (3, 3))
        g[:3, 3] = rng.normal(0, 0.1, 3)
        gs.append(g)
        st.update(g)
    X = np.array([g[:3, 3] for g in gs])
    assert np.allclose(st.X, X.mean(0))
    assert np.allclose(st.R, np.mean([g[:3, :3] for g in gs], 0))
    # Eq. 3-19 as printed uses the deviation from the *new* mean at each step: it is a running
    # estimate, not the batch covariance; check it against a direct evaluation of the recursion
    C = np.zeros((3, 3))
    m = np.zeros(3)
    for i, x in enumerate(X):
        m = (i * m + x) / (i + 1)
        C = (i * C + np.outer(x - m, x - m)) / (i + 1)
    assert np.allclose(st.C_X, C)
    assert np.all(np.diag(st.C_X) > 0) and np.all(np.diag(st.C_X) < X.var(0) * 1.01)


def test_ekf_point_update_linear_equals_kalman():
    x = np.array([[1.0, 2.0, 3.0]])
    P = np.diag([4.0, 1.0, 1.0])[None]
    z = np.array([[3.0, 2.0, 3.0]])
    Rz = np.diag([4.0, 1.0, 1.0])[None]
    xn, Pn = ekf_point_update(x, P, z, Rz, lambda v: v, lambda v: np.eye(3)[None])
    assert np.allclose(xn, [[2.0, 2.0, 3.0]])        # equal weights: the average
    assert np.allclose(Pn[0], np.diag([2.0, 0.5, 0.5]))


def test_visual_contrast_and_spacing():
    img = np.full((50, 50), 100, np.uint8)
    img[25, 25] = 200
    c, w = visual_contrast(img, np.array([[25.0, 25.0], [5.0, 5.0]]))
    assert c[1] == 0.0
    # 3x3 window: mean = (8*100 + 200)/9 = 111.1 -> C = (200-111.1)/111.1 = 0.8
    assert c[0] > 0.79 and w[0] >= 3
    uv = np.array([[10.0, 10.0], [12.0, 10.0], [40.0, 40.0]])
    idx = select_fiducials(uv, np.array([1.0, 0.99, 0.5]), 2,
                           weights=FiducialWeights(spacing_px=10, spacing_penalty=10))
    assert idx.tolist() == [0, 2]        # the close second candidate is penalised


def test_certainty_term_prefers_well_known_neighbourhood():
    def prob(p):
        # certain (P = 0.97) near the origin, uncertain elsewhere
        return np.where(np.linalg.norm(p, axis=1) < 0.35, 0.97, 0.5)
    f = certainty_term(np.array([[0.0, 0, 0], [3.0, 0, 0]]), prob, 0.1)
    assert f[0] > f[1] and f[1] == 0.0


def test_track_recovers_shift():
    rng = np.random.default_rng(6)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (140, 160)).astype(np.uint8), (0, 0), 1.5)
    a, b = tex[10:130, 10:150], tex[13:133, 5:145]   # content moves by (+5, -3) px
    uv = np.array([[40.0, 40.0], [70.0, 60.0], [100.0, 80.0]])
    new, ok = track(a, b, uv)
    assert ok.all() and np.allclose(new - uv, [5.0, -3.0], atol=0.1)


def test_fig_3_24_reduced_run():
    pytest.importorskip('pybullet')
    from coop_mapping.fig_3_24 import run
    out = run([0.35], trials=1, steps=3, methods=('pnp',))
    r = out['results']['pnp']['0.35']
    assert len(r['rms_error_corrected_m']) == 4
    assert r['fallback_steps'] == 0
    # the corrected chain ends better than dead reckoning on this seeded trajectory
    assert r['rms_error_corrected_m'][-1] < r['rms_error_dead_reckoned_m'][-1]


def test_unknown_modes_are_refused_naming_the_allowed_values():
    """g01's solver, the odometry's pose method, the sub-pixel mode and Fig. 3-24's options are
    taken as their StrEnum members where they enter; anything else is refused with the
    choices named (OptionError, StereoError, ConfigError: MappingErrors and ValueErrors)."""
    from coop_mapping.errors import MappingError, OptionError
    from coop_mapping.fiducial_odometry import OdometryConfig
    from coop_mapping.fig_3_24 import ConfigError, TrialConfig, run
    from coop_mapping.motion import G01Method, fit_g01
    from coop_mapping.stereo import StereoCamera, StereoError, StereoRanger

    R, t = _pose(1)
    r = np.random.default_rng(2).uniform(-1, 1, (12, 3)) + [0, 0, 3]
    p = r @ R.T + t
    g01 = r"method must be one of \['linear', 'linear_so3', 'rigid'\], got 'pnp'"
    with pytest.raises(OptionError, match=g01):       # pnp needs pixels, not 3-D points
        fit_g01(r, p, method='pnp')
    with pytest.raises(OptionError, match=g01):
        robust_g01(r, p, method='pnp')
    for m in G01Method:
        g = fit_g01(r, p, method=m.value)
        assert np.allclose(g[:3, :3], R, atol=1e-9) and np.allclose(g[:3, 3], t, atol=1e-9)
    pose = r"method must be one of \['linear', 'linear_so3', 'rigid', 'pnp'\], got 'icp'"
    with pytest.raises(OptionError, match=pose):
        OdometryConfig(method='icp')
    with pytest.raises(ConfigError, match=pose):
        TrialConfig(method='icp')
    with pytest.raises(ConfigError, match=pose):
        run([1.1], 1, 1, methods=('linear', 'icp'))     # before the first trial
    cam = StereoCamera(fx=200.0, fy=200.0, cx=160.0, cy=120.0, baseline=0.1, width=320,
                       height=240)
    with pytest.raises(StereoError, match=r"subpixel must be one of \['sgbm', 'equalise', "
                       r"'shift2', 'shift4'\], got 'shift8'"):
        StereoRanger(cam, subpixel='shift8')
    assert all(issubclass(e, MappingError) and issubclass(e, ValueError)
               for e in (OptionError, StereoError, ConfigError))
