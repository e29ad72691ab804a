"""Marker identification (§5.3): known centres, false markers, the perspective correction, bad
input."""
from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from coop_insertion.errors import InsertionError
from coop_insertion.marker_render import (
    CARD,
    SITE,
    random_pose,
    random_scene,
    render_plate,
    sim_intrinsics,
)
from coop_insertion.markers import (
    EllipseDetector,
    HoughDetector,
    MarkerDetector,
    ThesisDetector,
    circle_candidates,
    ellipse_conic,
    make_detector,
    three_point_circles,
)

K = sim_intrinsics(640, 480)


def _match(found, scene):
    """Per true marker: the error (px) of the nearest detection within half its radius, or
    None; and the number of detections matching no marker."""
    errs, used = [], set()
    for c, r in zip(scene.centres, scene.radius_px, strict=False):
        d = [math.hypot(m.u - c[0], m.v - c[1]) for m in found]
        j = int(np.argmin(d)) if d else -1
        if j >= 0 and d[j] < 0.5 * r and j not in used:
            used.add(j)
            errs.append(d[j])
        else:
            errs.append(None)
    return errs, len(found) - len(used)


@pytest.fixture(scope='module')
def scenes():
    rng = np.random.default_rng(7)
    return [random_scene(rng, K, 640, 480, occlude_probability=0.0) for _ in range(12)]


def test_protocol_and_factory():
    for kind in ('default', 'thesis', 'hough'):
        assert isinstance(make_detector(kind), MarkerDetector)
    with pytest.raises(InsertionError):
        make_detector('sobel')


def test_three_point_circle_eq_5_7_to_5_9():
    rng = np.random.default_rng(1)
    c = rng.uniform(-50, 50, (100, 2))
    r = rng.uniform(3, 40, 100)
    ang = rng.uniform(0, 2 * np.pi, (100, 3))
    p = [c + r[:, None] * np.stack([np.cos(ang[:, k]), np.sin(ang[:, k])], -1) for k in range(3)]
    cc, rr, th = three_point_circles(*p)
    assert np.allclose(cc, c, atol=1e-6) and np.allclose(rr, r, atol=1e-6)
    # a vertical bisector (a horizontal segment) needs no special case
    cc, rr, _ = three_point_circles(np.array([[-1.0, 0.0]]), np.array([[1.0, 0.0]]),
                                    np.array([[0.0, 1.0]]))
    assert np.allclose(cc, [[0.0, 0.0]]) and np.allclose(rr, [1.0])
    # collinear points: parallel bisectors, theta 0, no centre
    cc, _, th = three_point_circles(np.array([[0.0, 0.0]]), np.array([[1.0, 1.0]]),
                                    np.array([[2.0, 2.0]]))
    assert np.isnan(cc).all() and th[0] == pytest.approx(0.0, abs=1e-6)


def test_default_detector_known_centres(scenes):
    det = EllipseDetector(K=K)
    errs, spurious = [], 0
    for s in scenes:
        e, extra = _match(det.detect(s.image), s)
        errs += e
        spurious += extra
    found = [e for e in errs if e is not None]
    assert len(found) >= len(errs) - 1, f'{len(errs) - len(found)} of {len(errs)} missed'
    assert spurious == 0
    # the bound is the issue's 0.05 px target with room for 24 markers' sampling spread
    assert np.mean(found) < 0.08, np.round(found, 3)
    assert max(found) < 0.5


def test_thesis_detector_finds_markers(scenes):
    det = ThesisDetector()
    errs = []
    for s in scenes[:6]:
        errs += _match(det.detect(s.image), s)[0]
    found = [e for e in errs if e is not None]
    assert len(found) >= 0.5 * len(errs)     # its rate on the full set: bench/markers.py
    assert np.median(found) < 1.0          # a pixel-level region centroid


def test_hough_baseline_runs(scenes):
    errs = _match(HoughDetector().detect(scenes[0].image), scenes[0])[0]
    assert any(e is not None and e < 2.0 for e in errs)


def test_no_false_markers_without_markers():
    rng = np.random.default_rng(11)
    det = EllipseDetector(K=K)
    n = 0
    for _ in range(12):
        s = random_scene(rng, K, 640, 480, with_markers=False)
        n += len(det.detect(s.image))
    assert n == 0


def test_partly_occluded_marker_still_found():
    rng = np.random.default_rng(5)
    det = EllipseDetector(K=K)
    errs = []
    for _ in range(6):
        s = random_scene(rng, K, 640, 480, occlude_probability=1.0, occlude=0.25)
        e = _match(det.detect(s.image), s)[0][0]
        errs.append(e)
    found = [e for e in errs if e is not None]
    # median: one of these six is off by 1 px (the trimmed fit keeps part of the bar's edge)
    assert len(found) >= 5 and np.median(found) < 0.2, errs


def test_circle_candidates_recover_the_true_centre():
    """One of the two candidates is the exact image of the circle's centre (the conic of an
    exactly projected circle), and its normal the plate's."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        R, t = random_pose(rng, K, 640, 480, SITE)
        c3 = R @ np.array([*SITE.markers[0], 0.0]) + t
        H = K @ np.column_stack([R[:, 0], R[:, 1], c3])
        Hi = np.linalg.inv(H)
        C = Hi.T @ np.diag([1.0, 1.0, -SITE.marker_radius_m ** 2]) @ Hi
        normals, centres = circle_candidates(C, K)
        true = (K @ c3)[:2] / c3[2]
        err = np.hypot(*(centres - true).T)
        k = int(np.argmin(err))
        assert err[k] < 1e-6
        assert normals[k] @ R[:, 2] > 1 - 1e-9


def test_perspective_correction_where_the_bias_is_large():
    """The site's 20 mm markers 0.3 m away at 45 deg tilt: the ellipse centre is off by
    more than a pixel; the corrected centre is within 0.1 px, the uncorrected one is not."""
    rng = np.random.default_rng(2)
    s = None
    for _ in range(200):
        R, t = random_pose(rng, K, 640, 480, SITE, distance_m=(0.3, 0.3),
                           max_tilt_rad=math.radians(45))
        tilt = math.degrees(math.acos(abs(R[2, 2])))
        if tilt < 40:
            continue
        s = render_plate(K, 640, 480, R, t, SITE, rng=rng, noise_sigma=2.0, blur_sigma=0.8,
                         gradient=0.3)
        if np.hypot(*(s.ellipse_centres - s.centres).T).min() > 1.0:
            break
    bias = np.hypot(*(s.ellipse_centres - s.centres).T)
    assert bias.min() > 1.0
    plain = _match(EllipseDetector().detect(s.image), s)[0]
    corrected = _match(EllipseDetector(K=K).detect(s.image), s)[0]
    hinted = _match(EllipseDetector(K=K, normal_hint=s.normal).detect(s.image), s)[0]
    assert all(e is not None for e in plain + corrected + hinted)
    assert min(plain) > 0.8
    assert max(corrected) < 0.1 and max(hinted) < 0.1


def test_ellipse_conic_points_on_it():
    C = ellipse_conic(10.0, -4.0, 7.0, 3.0, 0.4)
    phi = np.linspace(0, 2 * np.pi, 9)
    x = 7 * np.cos(phi)
    y = 3 * np.sin(phi)
    c, s = math.cos(0.4), math.sin(0.4)
    P = np.stack([10 + c * x - s * y, -4 + s * x + c * y, np.ones_like(x)])
    assert np.allclose(np.einsum('in,ij,jn->n', P, C, P), 0, atol=1e-9)


@pytest.mark.parametrize('bad', [np.zeros((480, 640), np.float32), np.zeros((480, 640, 3),
                                 np.uint8), np.zeros(10, np.uint8), [[0, 1], [2, 3]],
                                 np.zeros((8, 8), np.uint8)])
def test_bad_image_is_a_domain_error(bad):
    for kind in ('default', 'thesis', 'hough'):
        with pytest.raises(InsertionError):
            make_detector(kind).detect(bad)


@pytest.mark.parametrize('kw', [dict(radius_px=(10, 5)), dict(radius_px=(1, 5)),
                                dict(polarity='grey'), dict(K=np.eye(2)),
                                dict(min_coverage=0.0), dict(ambiguity='guess'),
                                dict(normal_hint=[0, 0, 0])])
def test_bad_options_are_domain_errors(kw):
    with pytest.raises(InsertionError):
        EllipseDetector(**kw)


def test_dark_markers_polarity():
    """Holes (dark on a bright plate) with polarity 'dark'."""
    rng = np.random.default_rng(4)
    R, t = random_pose(rng, K, 640, 480, CARD, max_tilt_rad=math.radians(20))
    s = render_plate(K, 640, 480, R, t, CARD, rng=rng, noise_sigma=2.0)
    inv = cv2.bitwise_not(s.image)
    errs = _match(EllipseDetector(K=K, polarity='dark').detect(inv), s)[0]
    assert all(e is not None and e < 0.3 for e in errs), errs
