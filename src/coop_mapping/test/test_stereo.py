"""Stereo core: Eq. 3-1..3-9 against hand-computed numbers, SGBM on known shifts, a rendered
scene against its true depth."""
import cv2
import numpy as np
import pytest

from coop_mapping.gauss import mat_from_sym6
from coop_mapping.stereo import (
    ErrorModel,
    StereoCamera,
    StereoError,
    StereoRanger,
    compute_disparity,
    disparity_to_points,
    disparity_to_range,
    equalize_subpixel,
    phase_averaged_disparity,
    range_sigma,
    shift_columns,
)


def test_disparity_to_range_and_sigma_hand_computed():
    # f = 500 px, b = 0.1 m: d = 10 px -> Y = 5 m; sigma_d = 0.5 px -> 25 * 0.001 / 0.1 = 0.25 m
    assert disparity_to_range(np.array([10.0]), 500.0, 0.1)[0] == pytest.approx(5.0)
    assert np.isnan(disparity_to_range(np.array([0.0]), 500.0, 0.1)[0])
    assert range_sigma(np.array([5.0]), 500.0, 0.1, 0.5)[0] == pytest.approx(0.25)
    # sigma grows with range squared (Eq. 3-6)
    s = range_sigma(np.array([1.0, 2.0, 4.0]), 500.0, 0.1, 0.5)
    assert np.allclose(s[1:] / s[:-1], 4.0)


def test_error_model_eq_3_7_and_rotation_eq_3_9():
    cam = StereoCamera(500.0, 500.0, 100.0, 80.0, 0.1, 200, 160)
    em = ErrorModel.from_stereo(cam, sigma_d_px=0.5, lateral=0.1)
    pts = np.array([[0.0, 0.0, 5.0], [3.0, 0.0, 4.0]])   # L = 5 for both
    sg = em.sigmas(pts)
    assert np.allclose(sg[:, 2], 0.25) and np.allclose(sg[:, 0], 0.025)
    # optical z along map x: the range variance lands on map xx
    R = np.array([[0.0, 0, 1], [-1, 0, 0], [0, -1, 0]])
    C = mat_from_sym6(em.covariances(pts[:1], R))[0]
    assert np.allclose(np.diag(C), [0.0625, 0.025 ** 2, 0.025 ** 2])


def test_sgbm_recovers_known_shift():
    rng = np.random.default_rng(0)
    tex = cv2.GaussianBlur(rng.integers(0, 256, (120, 400)).astype(np.uint8), (0, 0), 1.0)
    shift = 12
    left = tex[:, 0:300].copy()
    right = tex[:, shift:shift + 300].copy()   # texture column c: left u = c, right u = c - 12
    d = compute_disparity(left, right, num_disparities=32, block_size=5, full_width=False)
    assert np.nanmedian(d) == pytest.approx(shift, abs=0.1)
    assert np.mean(np.isfinite(d[:, 40:-10])) > 0.9
    assert not np.isfinite(d[:, :32]).any()            # no full search range there
    # full width: the left 32 columns are searched too; where the match would lie left of the
    # right image (u < 12) there is none
    d = compute_disparity(left, right, num_disparities=32, block_size=5, full_width=True)
    assert np.mean(np.isfinite(d[:, 16:32])) > 0.9
    assert np.nanmedian(d[:, 16:32]) == pytest.approx(shift, abs=0.1)
    assert not np.isfinite(d[:, :shift]).any()
    for mode in ('sgbm', 'equalise', 'shift2'):
        dm = compute_disparity(left, right, num_disparities=32, subpixel=mode, full_width=True)
        u = np.arange(dm.shape[1])
        assert not np.any(np.isfinite(dm) & (u - np.nan_to_num(dm) < 0)), mode
    with pytest.raises(StereoError):
        compute_disparity(left, right[:, :-1])
    with pytest.raises(StereoError):
        compute_disparity(left.astype(np.float32), right)


def test_no_disparity_in_a_clipped_white_region():
    # a textured band under a clipped white "sky": SGBM carries the band's disparity up into
    # the sky; only the band and the block-wide rim of sky next to it keep one
    rng = np.random.default_rng(1)
    tex = cv2.GaussianBlur(rng.integers(0, 230, (120, 400)).astype(np.uint8), (0, 0), 1.0)
    tex[:60] = 255
    left, right = tex[:, 0:300].copy(), tex[:, 12:312].copy()
    d = compute_disparity(left, right, num_disparities=32, block_size=5)
    assert not np.isfinite(d[:58]).any()
    assert np.mean(np.isfinite(d[62:, 40:-10])) > 0.9
    assert np.nanmedian(d[62:]) == pytest.approx(12, abs=0.1)


def test_disparity_to_points_pinhole():
    cam = StereoCamera(100.0, 100.0, 1.0, 1.0, 0.2, 3, 3)
    d = np.full((3, 3), 10.0)            # Z = 100 * 0.2 / 10 = 2 m
    pts, uv = disparity_to_points(d, cam)
    assert np.allclose(pts[:, 2], 2.0)
    assert np.allclose(pts[0], [-0.02, -0.02, 2.0])   # pixel (0, 0): (0 - 1) * 2 / 100
    assert uv.shape == (9, 2)


@pytest.fixture(scope='module')
def rendered():
    """(camera, left, right, true depth, R, eye): one 320x240 view of a textured sim scene."""
    pytest.importorskip('pybullet')
    from coop_mapping.render import TexturedScene, look_at
    cam = StereoCamera.from_fov(320, 240, np.radians(41.2), 0.038)
    with TexturedScene(cam, seed=1) as scene:
        eye = np.array([0.0, 0.0, 1.0])
        R = look_at(eye, np.array([2.5, 0.0, 0.2]))
        left, right, depth = scene.render(R, eye)
    return cam, left, right, depth, R, eye


def test_rendered_scene_ranges_against_truth(rendered):
    cam, left, right, depth, R, eye = rendered
    scan = StereoRanger(cam, num_disparities=32).process(left, right, R, eye)
    u = scan.uv.astype(int)
    zt = depth[u[:, 1], u[:, 0]]
    ok = np.isfinite(zt)
    assert ok.mean() > 0.95 and len(scan.points) > 0.4 * 320 * 240
    err = np.abs(scan.points_cam[ok, 2] - zt[ok])
    sigma = scan.covariances[ok]
    # the error model's range sigma (Eq. 3-6 with 0.5 px) bounds the typical error
    model_sigma = np.sqrt(sigma[:, 0] + sigma[:, 3] + sigma[:, 5])
    assert np.median(err / model_sigma) < 1.0
    assert np.median(err) < 0.1


def _locked(d_true: np.ndarray, strength: float = 0.6) -> np.ndarray:
    """A pixel-locking matcher: the offset from the nearest integer pulled towards 0 by a
    monotone map (derivative 1 - strength cos(2 pi f) > 0)."""
    n = np.round(d_true)
    f = d_true - n
    return n + f - strength / (2 * np.pi) * np.sin(2 * np.pi * f)


def test_equalize_subpixel_undoes_pixel_locking():
    rng = np.random.default_rng(3)
    d_true = rng.uniform(5.0, 40.0, (120, 160))
    meas = _locked(d_true)
    meas[::7, ::5] = np.nan
    eq = equalize_subpixel(meas)
    assert eq.shape == meas.shape and eq.dtype == np.float32
    assert np.array_equal(np.isnan(eq), np.isnan(meas))
    ok = np.isfinite(meas)
    err_raw = (meas - d_true)[ok]
    err_eq = (eq - d_true)[ok]
    # locking error up to 0.6 / (2 pi) ~ 0.095 px; after equalisation only the sample CDF's
    assert np.sqrt(np.mean(err_raw ** 2)) > 0.06
    assert np.sqrt(np.mean(err_eq ** 2)) < 0.01
    # the bias by true sub-pixel part is flat afterwards
    b = np.minimum(((d_true[ok] - np.round(d_true[ok]) + 0.5) * 8).astype(int), 7)
    swing = [np.ptp([e[b == k].mean() for k in range(8)]) for e in (err_raw, err_eq)]
    assert swing[0] > 0.1 and swing[1] < 0.01


def test_equalize_subpixel_is_monotone_and_keeps_ties():
    d = np.array([[3.0, 3.0, 3.1, 2.9, np.nan, 7.4, 7.6, 3.0]], np.float32)
    eq = equalize_subpixel(d)
    ok = np.isfinite(d[0])
    v, w = d[0][ok], eq[0][ok]
    order = np.argsort(v, kind='stable')
    assert np.all(np.diff(w[order]) >= 0)           # order kept
    assert w[0] == w[1] == w[-1]                      # equal inputs, equal outputs
    assert np.all(np.abs(w - np.round(v)) <= 0.5)     # each stays within its integer's cell
    assert np.isnan(eq[0, 4])
    assert np.array_equal(equalize_subpixel(np.full((2, 2), np.nan)), np.full((2, 2), np.nan),
                          equal_nan=True)
    # a valid disparity below 0.5 px could map to <= 0: it becomes invalid, never a negative
    small = np.r_[np.full(900, 10.25), np.full(10, 0.0625)].astype(np.float32)
    eq = equalize_subpixel(small)
    assert np.all(np.isnan(eq) | (eq > 0)) and np.isnan(eq[-10:]).all()


def test_ranger_rejects_unknown_subpixel_mode():
    cam = StereoCamera(500.0, 500.0, 100.0, 80.0, 0.1, 200, 160)
    with pytest.raises(StereoError, match='subpixel'):
        StereoRanger(cam, subpixel='parabola')


def _ramp_matcher(d_true: np.ndarray, locked):
    """A fake matcher for phase_averaged_disparity: its 'right image' is a float ramp whose
    column 1 holds 1 + the shift applied to it, so it returns locked(d_true + shift)."""
    def match(img):
        s = float(img[0, 1]) - 1.0
        return locked(d_true + s).astype(np.float32)
    ramp = np.tile(np.arange(16, dtype=np.float32), (4, 1))
    return match, ramp


def test_shift_columns_resamples_at_x_plus_s():
    ramp = np.tile(np.arange(20, dtype=np.float32), (3, 1))
    out = shift_columns(ramp, 0.25)
    assert np.allclose(out[:, :-1], ramp[:, :-1] + 0.25, atol=1e-3)
    assert np.allclose(out[:, -1], 19.0)                 # edge replicated
    assert np.array_equal(shift_columns(ramp, 0.0), ramp)


@pytest.mark.parametrize('n', [2, 4])
def test_phase_average_cancels_pixel_locking(n):
    """A first-harmonic locking error (the dominant one SGBM shows) cancels exactly over 2
    phases; its second harmonic needs 4."""
    rng = np.random.default_rng(4)
    d_true = rng.uniform(5.0, 40.0, (30, 40))

    def locked(d):
        f = d - np.round(d)
        return (d - 0.1 * np.sin(2 * np.pi * f)
                + (0.03 * np.sin(4 * np.pi * f) if n == 4 else 0.0))
    match, ramp = _ramp_matcher(d_true, locked)
    assert np.sqrt(np.mean((locked(d_true) - d_true) ** 2)) > 0.06
    out = phase_averaged_disparity(match, ramp, n)
    assert out.dtype == np.float32 and out.shape == d_true.shape
    assert np.max(np.abs(out - d_true)) < 1e-4
    if n == 2:          # with a second harmonic too, 2 phases leave it
        def locked2(d):
            f = d - np.round(d)
            return d - 0.1 * np.sin(2 * np.pi * f) + 0.03 * np.sin(4 * np.pi * f)
        m2, _ = _ramp_matcher(d_true, locked2)
        assert np.max(np.abs(phase_averaged_disparity(m2, ramp, 2) - d_true)) > 0.02
        assert np.max(np.abs(phase_averaged_disparity(m2, ramp, 4) - d_true)) < 1e-4


def test_phase_average_drops_pixels_the_phases_disagree_on():
    d_true = np.full((4, 6), 10.0)

    def locked(d):
        out = d.copy()
        if abs(d[0, 0] - 10.5) < 1e-6:     # the half-pixel phase: a mismatch and a hole
            out[1, 2] += 3.0
            out[2, 3] = np.nan
        return out
    match, ramp = _ramp_matcher(d_true, locked)
    out = phase_averaged_disparity(match, ramp, 2)
    assert np.isnan(out[1, 2]) and np.isnan(out[2, 3])
    assert np.isfinite(out).sum() == out.size - 2 and np.allclose(out[np.isfinite(out)], 10.0)
    # a mean <= 0 is invalid, as SGBM's own
    match0, _ = _ramp_matcher(np.full((2, 2), -0.2), lambda d: d.copy())
    assert np.isnan(phase_averaged_disparity(match0, ramp, 2)).all()
    with pytest.raises(StereoError):
        phase_averaged_disparity(match, ramp, 0)


def test_compute_disparity_rejects_unknown_subpixel_mode():
    img = np.zeros((40, 80), np.uint8)
    with pytest.raises(StereoError, match='subpixel'):
        compute_disparity(img, img, num_disparities=16, subpixel='parabola')
    # OpenCV's SGBM fails on an image no wider than the disparity range ("Insufficient
    # memory"): a StereoError with the reason instead
    with pytest.raises(StereoError, match='wide'):
        compute_disparity(img[:, :16], img[:, :16], num_disparities=16)
    assert compute_disparity(img[:, :17], img[:, :17], num_disparities=16).shape == (40, 17)


def test_camera_calibration_must_be_finite():
    """A camera_info with a NaN principal point would range every point to NaN."""
    for bad in ({'cx': np.nan}, {'cy': np.inf}, {'fx': np.inf}):
        with pytest.raises(StereoError, match='finite'):
            StereoCamera(**{'fx': 100.0, 'fy': 100.0, 'cx': 50.0, 'cy': 40.0,
                            'baseline': 0.04, 'width': 100, 'height': 80, **bad})


@pytest.mark.parametrize('mode,ratio', [('equalise', 0.9), ('shift2', 0.7), ('shift4', 0.65)])
def test_subpixel_corrections_range_the_rendered_scene_better(rendered, mode, ratio):
    """SGBM pixel-locks on the sim's frames; each correction is closer to the truth (measured
    here: equalise 0.79x, shift2 0.58x, shift4 0.52x SGBM's RMS disparity error)."""
    cam, left, right, depth, R, eye = rendered
    rms, valid = {}, {}
    for m in ('sgbm', mode):
        scan = StereoRanger(cam, num_disparities=32, subpixel=m).process(left, right, R, eye)
        u = scan.uv.astype(int)
        zt = depth[u[:, 1], u[:, 0]]
        ok = np.isfinite(zt)
        e = cam.fx * cam.baseline * (1.0 / scan.points_cam[ok, 2] - 1.0 / zt[ok])
        e = e[np.abs(e) < 2.0]                      # gross mismatches are not sub-pixel errors
        rms[m] = np.sqrt(np.mean(e ** 2))
        valid[m] = e.size
    assert rms['sgbm'] > 0.15                       # the locking is there to correct
    assert rms[mode] < ratio * rms['sgbm']
    assert valid[mode] > 0.98 * valid['sgbm']       # not by dropping the hard pixels


def test_supersampled_render_is_the_same_camera_with_pixel_integration():
    """TexturedScene(supersample=3) renders 3x3 samples per pixel and averages them: the true
    depth (read at each pixel's centre sample) is the plain render's, the images are the same
    view (close to the plain one, a little smoother), and a supersample that puts no sample on
    the pixel centre is refused."""
    pytest.importorskip('pybullet')
    from coop_mapping.render import TexturedScene, look_at
    cam = StereoCamera.from_fov(160, 120, np.radians(41.2), 0.038)
    eye = np.array([0.0, 0.0, 1.0])
    R = look_at(eye, np.array([2.5, 0.0, 0.2]))
    with TexturedScene(cam, seed=1) as a, TexturedScene(cam, seed=1, supersample=3) as b:
        l1, _, d1 = a.render(R, eye)
        l3, r3, d3 = b.render(R, eye)
    assert l3.shape == r3.shape == d3.shape == (120, 160) and l3.dtype == np.uint8
    ok = np.isfinite(d1)
    assert np.array_equal(ok, np.isfinite(d3)) and ok.mean() > 0.9
    np.testing.assert_allclose(d3[ok], d1[ok], rtol=1e-4)
    diff = np.abs(l1.astype(float) - l3)
    assert np.median(diff) < 0.25 * l1.std()              # the same view, shifted by nothing
    gradient = [np.abs(np.diff(img.astype(float), axis=1)).mean() for img in (l1, l3)]
    assert gradient[1] < gradient[0]                       # the area average smooths
    with pytest.raises(ValueError, match='odd'):
        TexturedScene(cam, supersample=2)
