"""Stereo triangulation of marker centres (Eq. 3-1..3-7 via coop_mapping.stereo)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coop_insertion.errors import InsertionError
from coop_insertion.marker_render import CARD, SITE, random_pose, render_plate
from coop_insertion.markers import EllipseDetector, Marker
from coop_insertion.triangulate import match_markers, triangulate_markers
from coop_mapping.stereo import StereoCamera, range_sigma

CAM = StereoCamera.from_fov(640, 480, math.radians(41.2), 0.038)
K = np.array([[CAM.fx, 0, CAM.cx], [0, CAM.fy, CAM.cy], [0, 0, 1.0]])


def _pair(rng, plate, **kw):
    """A stereo pair with every marker inside both images."""
    while True:
        R, t = random_pose(rng, K, 640, 480, plate, distance_m=(0.25, 0.45), **kw)
        pts = np.array([R @ np.array([*m, 0.0]) + t for m in plate.markers])
        u_right = CAM.fx * (pts[:, 0] - CAM.baseline) / pts[:, 2] + CAM.cx
        r_px = CAM.fx * plate.marker_radius_m / pts[:, 2]
        if np.all(u_right > 1.5 * r_px + 10):
            break
    left = render_plate(K, 640, 480, R, t, plate, rng=rng, noise_sigma=2.0)
    right = render_plate(K, 640, 480, R, t - np.array([CAM.baseline, 0, 0]), plate, rng=rng,
                         noise_sigma=2.0)
    truth = np.array([R @ np.array([*m, 0.0]) + t for m in plate.markers])
    return left, right, truth


@pytest.mark.parametrize('plate', [CARD, SITE])
def test_triangulated_centres_against_known_points(plate):
    rng = np.random.default_rng(21)
    det = EllipseDetector(K=K)
    z_err = []
    for _ in range(4):
        left, right, truth = _pair(rng, plate)
        ml, mr = det.detect(left.image), det.detect(right.image)
        tri = triangulate_markers(ml, mr, CAM, marker_radius_m=plate.marker_radius_m)
        assert len(tri) == len(truth)
        for s in tri:
            k = int(np.argmin(np.linalg.norm(truth - s.position, axis=1)))
            err = s.position - truth[k]
            # within 1 mm, and consistent with the stated covariance
            assert np.linalg.norm(err) < 1e-3, err
            assert err @ np.linalg.solve(s.covariance, err) < 31.0   # chi2(3), p 1e-6
            z_err.append(err[2])
    assert len(z_err) == 8


def test_one_image_only_is_not_triangulated():
    rng = np.random.default_rng(22)
    left, right, _ = _pair(rng, SITE)
    det = EllipseDetector(K=K)
    ml, mr = det.detect(left.image), det.detect(right.image)
    assert len(ml) == 2 and len(mr) == 2
    assert len(triangulate_markers(ml, mr[:1], CAM)) == 1
    assert triangulate_markers(ml, [], CAM) == []


def test_matching_by_epipolar_row_and_size():
    a = Marker(u=300.0, v=200.0, radius_px=10.0, score=1.0)
    b = Marker(u=400.0, v=200.0, radius_px=10.0, score=1.0)
    # right: b's match 20 px left of it, a's match 10 px left; one off-row and one too big
    ra = Marker(u=290.0, v=200.5, radius_px=10.2, score=1.0)
    rb = Marker(u=380.0, v=199.7, radius_px=9.9, score=1.0)
    off_row = Marker(u=295.0, v=210.0, radius_px=10.0, score=1.0)
    too_big = Marker(u=392.0, v=200.0, radius_px=20.0, score=1.0)
    pairs = match_markers([a, b], [too_big, rb, off_row, ra], CAM)
    assert sorted(pairs) == [(0, 3), (1, 1)]
    # with the marker's true size the disparity must fit the apparent radius: d = b r_px / r
    r_m = CAM.baseline * 10.0 / 10.0       # a 10 px marker 10 px of disparity away
    assert match_markers([a, b], [rb, ra], CAM, marker_radius_m=r_m) == [(0, 1)]


def test_propagated_range_sigma_is_eq_3_6():
    a = Marker(u=330.0, v=250.0, radius_px=10.0, score=1.0, sigma_px=0.04)
    ra = Marker(u=300.0, v=250.0, radius_px=10.0, score=1.0, sigma_px=0.04)
    s = triangulate_markers([a], [ra], CAM, sigma_px=0.04)[0]
    z = CAM.fx * CAM.baseline / 30.0
    assert s.position[2] == pytest.approx(z)
    assert math.sqrt(s.covariance[2, 2]) == pytest.approx(
        range_sigma(z, CAM.fx, CAM.baseline, math.sqrt(2) * 0.04))
    e = triangulate_markers([a], [ra], CAM, sigma_px=0.04, covariance='eq3_7')[0]
    assert math.sqrt(e.covariance[2, 2]) == pytest.approx(
        range_sigma(np.linalg.norm(e.position), CAM.fx, CAM.baseline, math.sqrt(2) * 0.04))
    with pytest.raises(InsertionError):
        triangulate_markers([a], [ra], CAM, covariance='guess')
