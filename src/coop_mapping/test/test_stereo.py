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
    range_sigma,
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
    d = compute_disparity(left, right, num_disparities=32, block_size=5)
    assert np.nanmedian(d) == pytest.approx(shift, abs=0.1)
    assert np.mean(np.isfinite(d[:, 40:-10])) > 0.9
    with pytest.raises(StereoError):
        compute_disparity(left, right[:, :-1])
    with pytest.raises(StereoError):
        compute_disparity(left.astype(np.float32), right)


def test_disparity_to_points_pinhole():
    cam = StereoCamera(100.0, 100.0, 1.0, 1.0, 0.2, 3, 3)
    d = np.full((3, 3), 10.0)            # Z = 100 * 0.2 / 10 = 2 m
    pts, uv = disparity_to_points(d, cam)
    assert np.allclose(pts[:, 2], 2.0)
    assert np.allclose(pts[0], [-0.02, -0.02, 2.0])   # pixel (0, 0): (0 - 1) * 2 / 100
    assert uv.shape == (9, 2)


def test_rendered_scene_ranges_against_truth():
    pytest.importorskip('pybullet')
    from coop_mapping.render import TexturedScene, look_at
    cam = StereoCamera.from_fov(320, 240, np.radians(41.2), 0.038)
    with TexturedScene(cam, seed=1) as scene:
        eye = np.array([0.0, 0.0, 1.0])
        R = look_at(eye, np.array([2.5, 0.0, 0.2]))
        left, right, depth = scene.render(R, eye)
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
