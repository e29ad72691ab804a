"""Camera motion correction (§3.2.5) fixes behind the Fig. 3-24 analogue: the disparity gate on
slanted planes, the SGBM search range, the covariance-weighted rigid fit, the first-order pose
covariance, the pose Kalman update, and which fiducials the running estimator keeps."""
import cv2
import numpy as np
import pytest

import coop_mapping.fiducial_odometry as fo_mod
from coop_mapping.fiducial_odometry import (
    FiducialOdometry,
    OdometryConfig,
    fuse_pose,
    pnp_covariance,
    pose_jacobian_cam,
    pose_jacobian_placed,
    sample_points,
    stereo_point_cov,
)
from coop_mapping.motion import (
    camera_pose_covariance,
    project_to_so3,
    solve_g01_so3,
    solve_rigid,
    solve_rigid_cov,
)
from coop_mapping.stereo import StereoCamera

CAM = StereoCamera.from_fov(320, 240, np.radians(41.2), 0.038)


def _rot(w):
    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def _stereo_points(rng, n):
    """n camera-frame points spread over the image at 0.9-2 m, like the 1100 mm scene."""
    u = rng.uniform(20, CAM.width - 20, n)
    v = rng.uniform(20, CAM.height - 20, n)
    z = rng.uniform(0.9, 2.0, n)
    return np.stack([(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z], -1)


def _triangulate_noisy(rng, pc, sigma_px, sigma_d):
    """The stereo measurement of pc with pixel and disparity noise (what SGBM + LK return)."""
    u = CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx + rng.normal(0, sigma_px, len(pc))
    v = CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy + rng.normal(0, sigma_px, len(pc))
    d = CAM.fx * CAM.baseline / pc[:, 2] + rng.normal(0, sigma_d, len(pc))
    z = CAM.fx * CAM.baseline / d
    return np.stack([(u - CAM.cx) * z / CAM.fx, (v - CAM.cy) * z / CAM.fy, z], -1)


# ------------------------------------------------------------------ disparity consistency gate
def test_sample_points_gate_accepts_slanted_plane_rejects_occlusion_edge():
    """A slanted plane has a linear disparity ramp (the ground at 350 mm: ~0.3 px per row); the
    5x5 gate must remove that plane before judging consistency. An occlusion edge (a disparity
    step) must still be rejected, a fronto-parallel plane accepted."""
    h, w = 60, 80
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    ramp = 30.0 + 0.3 * v                              # 1.2 px over the 5 rows of the window
    step = np.where(u < 40, 30.0, 40.0).astype(np.float32)
    flat = np.full((h, w), 30.0, np.float32)
    uv = np.array([[20.0, 30.0], [40.0, 30.0]])
    p, ok = sample_points(ramp, uv, CAM)
    assert ok.all()
    assert np.allclose(p[:, 2], CAM.fx * CAM.baseline / (30.0 + 0.3 * 30.0))
    _, ok = sample_points(step, uv, CAM)
    assert ok[0] and not ok[1]                         # on the step: foreground/background mix
    _, ok = sample_points(flat, uv, CAM)
    assert ok.all()
    noisy = ramp + np.random.default_rng(0).normal(0, 0.1, ramp.shape).astype(np.float32)
    noisy[29:32, 39:42] += 3.0                         # a speckle of wrong matches
    _, ok = sample_points(noisy, uv, CAM)
    assert ok[0] and not ok[1]


# ------------------------------------------------------------------ SGBM search range
def test_search_range_follows_camera_and_nearest_depth():
    from coop_mapping.fig_3_24 import search_range
    for width in (320, 640):
        cam = StereoCamera.from_fov(width, width * 3 // 4, np.radians(41.2), 0.038)
        for z_near in (0.28, 0.87):
            d = cam.fx * cam.baseline / z_near
            assert search_range(cam, z_near, margin=0.0) % 16 == 0
            assert d <= search_range(cam, z_near, margin=0.0) < d + 16
            assert 1.2 * d <= search_range(cam, z_near) < 1.2 * d + 16
    cam640 = StereoCamera.from_fov(640, 480, np.radians(41.2), 0.038)
    assert search_range(cam640, 0.28) > 64              # 640 px at 350 mm needs > 64 px


def test_fig_3_24_trial_sets_search_range_from_the_scene():
    pytest.importorskip('pybullet')
    from coop_mapping.fig_3_24 import TrialConfig, run_trial
    r = run_trial(TrialConfig(distance=0.35, steps=1, width=640, height=480, method='pnp'), 0)
    assert r['num_disparities'] == 144                  # nearest depth ~0.28 m: 117 px + 10 %
    assert 64 < r['max_true_disparity_px'] <= r['num_disparities']
    assert len(r['kept']) == 1 and r['kept'][0] >= 30


@pytest.mark.parametrize('args, reason', [
    (['--trials', '0'], '--trials: 0 must be >= 1'),           # was an IndexError traceback
    (['--steps', '0'], '--steps: 0 must be >= 1'),             # was a silent 'nan%' run
    (['--seed', '-1'], '--seed: -1 must be >= 0'),
    (['--distances', 'nan'], "--distances: 'nan' is not finite"),
    (['--distances', '1.1', '0.05'],                          # 1.1 used to run first
     'scene at 0.05 m: a disparity range of 496 px, not less than the image width 320'),
    (['--width', '16'], '--width: 16 must be >= 32'),
    (['--height', '100000'], '--height: 100000 must be <= 4096'),
    (['--json', '{tmp}'], 'is a directory'),                  # these failed after the run
    (['--plots', '{tmp}/f/x.png'], 'is not a directory'),
    (['--plots', '{tmp}/x.xyz'], 'a figure file ends in one of .png, .pdf, .svg'),
])
def test_fig_3_24_cli_refuses_before_any_trial(tmp_path, capsys, args, reason):
    pytest.importorskip('pybullet')
    from coop_common.testing import usage_error
    from coop_mapping.fig_3_24 import main
    (tmp_path / 'f').write_text('a file')
    assert reason in usage_error(main, [a.format(tmp=tmp_path) for a in args], capsys)


def test_fig_3_24_far_scene_is_rendered_not_clipped():
    """The renderer's far plane scales with the scene: at 100 m the first view has depth (it
    was all beyond the 30 m plane, and the range NaN)."""
    pytest.importorskip('pybullet')
    from coop_mapping.fig_3_24 import TrialConfig, check_config
    assert check_config(TrialConfig(distance=100.0)) == 16
    assert check_config(TrialConfig(distance=0.35, width=640, height=480)) == 144


# ------------------------------------------------------------------ rigid fit and covariances
def test_stereo_point_cov_matches_triangulation():
    rng = np.random.default_rng(1)
    pc = np.array([[0.5, 0.2, 1.5]])                    # off-axis: range error along the ray
    C = stereo_point_cov(pc, CAM, 0.5, 0.5)[0]
    mc = np.array([_triangulate_noisy(rng, pc, 0.5, 0.5)[0] for _ in range(20000)])
    Cm = np.cov(mc.T)
    assert np.allclose(np.sqrt(np.diag(C)), np.sqrt(np.diag(Cm)), rtol=0.1)
    corr = C[0, 2] / np.sqrt(C[0, 0] * C[2, 2])
    assert corr > 0.8 and abs(corr - Cm[0, 2] / np.sqrt(Cm[0, 0] * Cm[2, 2])) < 0.05


def test_rigid_cov_recovers_transform_and_beats_scalar_weights():
    rng = np.random.default_rng(2)
    R, t = _rot([0.05, -0.1, 0.03]), np.array([0.1, -0.05, 0.2])
    pc = _stereo_points(rng, 35)
    r = (pc - t) @ R                                    # common-frame points: pc = R r + t
    S = stereo_point_cov(pc, CAM, 0.5, 0.5)
    g = solve_rigid_cov(r, pc, S)
    assert np.allclose(g[:3, :3], R, atol=1e-9) and np.allclose(g[:3, 3], t, atol=1e-9)
    err_cov, err_scalar = [], []
    for _ in range(100):
        p = _triangulate_noisy(rng, pc, 0.5, 0.5)
        gc = solve_rigid_cov(r, p, stereo_point_cov(p, CAM, 0.5, 0.5))
        gs = solve_rigid(r, p, 1.0 / stereo_point_cov(p, CAM, 0.5, 0.5)[:, 2, 2])
        for gg, out in ((gc, err_cov), (gs, err_scalar)):
            out.append(np.linalg.norm(gg[:3, :3].T @ gg[:3, 3] - R.T @ t))  # camera position
    assert np.sqrt(np.mean(np.square(err_cov))) < 0.5 * np.sqrt(np.mean(np.square(err_scalar)))


@pytest.mark.parametrize('solver', ['so3', 'rigid_cov'])
def test_camera_pose_covariance_matches_monte_carlo(solver):
    rng = np.random.default_rng(3)
    R, t = _rot([0.02, 0.1, -0.05]), np.array([0.05, 0.02, -0.1])
    pc = _stereo_points(rng, 30)
    r = (pc - t) @ R
    Cp = stereo_point_cov(pc, CAM, 0.5, 0.5)
    Cr = np.broadcast_to(np.diag([2e-3, 2e-3, 5e-3]) ** 2, (len(r), 3, 3)).copy()
    S = Cp + R[None] @ Cr @ R.T[None]
    fit = solve_g01_so3 if solver == 'so3' else (lambda a, b: solve_rigid_cov(a, b, S))
    C = camera_pose_covariance(fit, r, pc, Cr, Cp)

    def pose(g):
        Rg = project_to_so3(g[:3, :3])
        return Rg.T, -Rg.T @ g[:3, 3]
    R0, c0 = pose(fit(r, pc))
    samples = []
    for _ in range(400):
        p = pc + np.einsum('nij,nj->ni', np.linalg.cholesky(Cp), rng.normal(size=pc.shape))
        rr = r + rng.normal(size=r.shape) * [2e-3, 2e-3, 5e-3]
        Rs, cs = pose(fit(rr, p))
        samples.append(np.concatenate([cv2.Rodrigues(Rs @ R0.T)[0].ravel(), cs - c0]))
    sd_mc = np.std(samples, 0)
    assert np.allclose(np.sqrt(np.diag(C)), sd_mc, rtol=0.2), (np.sqrt(np.diag(C)), sd_mc)


def test_pnp_covariance_matches_monte_carlo():
    rng = np.random.default_rng(4)
    R, c = _rot([0.01, -0.02, 0.03]), np.array([0.02, -0.01, 0.0])     # camera -> common
    x = _stereo_points(rng, 30) @ R.T + c
    P = np.broadcast_to(np.eye(3) * 1e-6, (30, 3, 3)).copy()
    g = np.eye(4)
    g[:3, :3], g[:3, 3] = R.T, -R.T @ c
    C = pnp_covariance(x, P, g, CAM, 0.5)
    K = np.array([[CAM.fx, 0, CAM.cx], [0, CAM.fy, CAM.cy], [0, 0, 1]])
    pc = (x - c) @ R
    uv0 = np.stack([CAM.fx * pc[:, 0] / pc[:, 2] + CAM.cx, CAM.fy * pc[:, 1] / pc[:, 2] + CAM.cy],
                   -1)
    samples = []
    for _ in range(300):
        xs = x + rng.normal(0, 1e-3, x.shape)
        uv = uv0 + rng.normal(0, 0.5, uv0.shape)
        rv, tv = cv2.Rodrigues(g[:3, :3])[0], g[:3, 3].reshape(3, 1).copy()
        _, rv, tv = cv2.solvePnP(xs, uv, K, None, rv, tv, useExtrinsicGuess=True,
                                 flags=cv2.SOLVEPNP_ITERATIVE)
        Rg = cv2.Rodrigues(rv)[0]
        samples.append(np.concatenate([cv2.Rodrigues(Rg.T @ R.T)[0].ravel(),
                                       -Rg.T @ tv.ravel() - c]))
    assert np.allclose(np.sqrt(np.diag(C)), np.std(samples, 0), rtol=0.2)


def test_pose_jacobians_match_finite_differences():
    rng = np.random.default_rng(5)
    R, c = _rot([0.3, -0.2, 0.1]), np.array([0.4, -0.3, 0.2])
    x = rng.uniform(-1, 1, (4, 3)) + [0, 0, 2]
    p = (x - c) @ R
    Jc, Jp = pose_jacobian_cam(x, R, c), pose_jacobian_placed(x, c)
    for k in range(6):
        d = np.zeros(6)
        d[k] = 1e-7
        R2, c2 = _rot(d[:3]) @ R, c + d[3:]
        assert np.allclose(((x - c2) @ R2 - p) / 1e-7, Jc[:, :, k], atol=1e-5)
        assert np.allclose((c2 + p @ R2.T - x) / 1e-7, Jp[:, :, k], atol=1e-5)


def test_fuse_pose_weights_by_covariance():
    Tp = np.eye(4)
    Tm = np.eye(4)
    Tm[:3, :3] = _rot([0.0, 0.0, 0.02])
    Tm[:3, 3] = [0.01, 0.0, 0.0]
    S = np.eye(6) * 1e-4
    T, Sf = fuse_pose(Tp, S, Tm, S)                     # equal: half way
    assert np.allclose(T[:3, 3], [0.005, 0, 0]) and np.allclose(Sf, S / 2)
    assert np.isclose(cv2.Rodrigues(T[:3, :3])[0][2, 0], 0.01)
    T, _ = fuse_pose(Tp, S, Tm, S * 1e8)                # a useless measurement changes nothing
    assert np.allclose(T, Tp, atol=1e-9)
    T, _ = fuse_pose(Tp, S * 1e8, Tm, S)                # a useless prediction: the measurement
    assert np.allclose(T, Tm, atol=1e-9)


# ------------------------------------------------------------------ the running estimator
def _odometry_with_stubs(monkeypatch, method, sigmas=None):
    """A FiducialOdometry on synthetic, exact data; the tracker and the stereo sampling are
    stubs so the test decides which fiducial is lost where:
    #0 lost by the tracker, #1 no valid disparity in the first frame, #2 lost by the tracker in
    the second frame of the step only, #3 a gross outlier (range 0.5 m off) in both frames."""
    rng = np.random.default_rng(6)
    n = 12
    pc0 = _stereo_points(rng, n)
    T0 = np.eye(4)
    delta = np.eye(4)
    delta[:3, 3] = [-0.02, 0.0, 0.0]
    cfg = OdometryConfig(n_fiducials=n, method=method, **(sigmas or {}))
    od = FiducialOdometry(CAM, cfg, T0)
    od.x = pc0.copy()                                  # common frame = first camera frame
    od.P = stereo_point_cov(pc0, CAM, 0.5, 0.5)
    T1 = T0 @ delta                                    # the true pose = the commanded one
    pc1 = (od.x - T1[:3, 3]) @ T1[:3, :3]
    uv1 = np.stack([CAM.fx * pc1[:, 0] / pc1[:, 2] + CAM.cx,
                    CAM.fy * pc1[:, 1] / pc1[:, 2] + CAM.cy], -1)
    od.uv = uv1 + [3.0, 0.0]
    left0, left1 = np.zeros((240, 320), np.uint8), np.ones((240, 320), np.uint8)
    disp0, disp1 = np.zeros((240, 320), np.float32), np.ones((240, 320), np.float32)
    od.prev_left = np.full((240, 320), 2, np.uint8)

    def track(prev, curr, uv, **kw):
        ok = np.ones(len(uv), bool)
        if curr is left0:
            ok[0] = False
            return uv1.copy(), ok
        ok[2] = False
        return uv.copy(), ok

    def sample(disp, uv, cam):
        p = pc1.copy()
        p[3, 2] += 0.5
        ok = np.ones(len(uv), bool)
        if disp is disp0:
            ok[1] = False
        return p, ok

    fits = []
    real_robust = fo_mod.robust_g01

    def robust(r, p, **kw):
        fits.append(r.copy())
        return real_robust(r, p, **kw)
    monkeypatch.setattr(fo_mod, 'track', track)
    monkeypatch.setattr(fo_mod, 'sample_points', sample)
    monkeypatch.setattr(fo_mod, 'robust_g01', robust)
    monkeypatch.setattr(FiducialOdometry, '_add_fiducials', lambda self, left, disp: None)
    return od, [(left0, disp0), (left1, disp1)], delta, T1, fits


@pytest.mark.parametrize('method', ['rigid', 'linear_so3'])
def test_step_uses_and_keeps_the_right_fiducials(monkeypatch, method):
    od, frames, delta, T1, fits = _odometry_with_stubs(monkeypatch, method)
    x0 = od.x.copy()
    T = od.step(frames, delta)
    assert np.allclose(T, T1, atol=1e-9)
    assert len(fits) == 2

    def rows(r):
        return {int(np.flatnonzero(np.all(np.isclose(x0, q), 1))[0]) for q in r}
    assert rows(fits[0]) == set(range(12)) - {0, 1}    # lost, and no range in frame 0
    assert rows(fits[1]) == set(range(12)) - {0, 2}    # lost in frame 1: not used there
    # kept: all but the tracker's loss and the fit's outlier; #1 (no range at this step) and
    # #2 (an inlier of the first frame's fit) stay
    assert od.kept == [10]
    assert rows(od.x) == set(range(12)) - {0, 3}


def test_step_fuses_prediction_and_measurement(monkeypatch):
    od, frames, delta, T1, _ = _odometry_with_stubs(
        monkeypatch, 'rigid', {'sigma_t_m': 0.002, 'sigma_rot_rad': np.radians(0.2)})
    od.T = od.T.copy()
    od.T[:3, 3] += [0.004, 0.0, 0.0]                   # a prediction 4 mm off
    T = od.step(frames, delta)
    err = np.linalg.norm(T[:3, 3] - T1[:3, 3])
    assert 0.0 < err < 0.004                           # pulled towards the exact measurement
    assert np.all(np.linalg.eigvalsh(od.S) > 0)
    assert np.sqrt(od.S[3, 3]) < 0.002                 # smaller than the prediction's


def test_fig_3_24_named_configurations():
    from coop_mapping.fig_3_24 import TrialConfig
    assert TrialConfig.thesis().method == 'linear' == TrialConfig().method
    b = TrialConfig.best_measured(distance=0.35)
    assert (b.method, b.fuse_prediction, b.distance) == ('rigid', True, 0.35)
