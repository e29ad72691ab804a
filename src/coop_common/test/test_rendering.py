"""coop_common.rendering: the projection matrix makes TinyRenderer draw the image of K."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coop_common.rendering import fine_intrinsics, pixel_average, projection_matrix

pb = pytest.importorskip('pybullet')

Z = 3.0          # distance of the test plane's front face from the camera


def _k(w: int, h: int, cx: float, cy: float, hfov_deg: float = 50.0) -> np.ndarray:
    f = (w / 2.0) / math.tan(math.radians(hfov_deg) / 2.0)
    return np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])


@pytest.fixture(scope='module')
def plane():
    """A black plane (the background is white) facing a camera at the origin that looks along
    world +x (optical x = world -y, optical y = world -z); the plane is moved to put its edge
    where a test wants."""
    cid = pb.connect(pb.DIRECT)
    half = [0.01, 20.0, 20.0]
    vis = pb.createVisualShape(pb.GEOM_BOX, halfExtents=half, rgbaColor=[0, 0, 0, 1],
                               physicsClientId=cid)
    body = pb.createMultiBody(0, -1, vis, basePosition=[Z + 0.01, 0, 0], physicsClientId=cid)
    view = pb.computeViewMatrix([0, 0, 0], [1, 0, 0], [0, 0, 1], physicsClientId=cid)
    yield cid, body, view
    pb.disconnect(cid)


def _first_covered(plane, k, w, h, proj, axis: str, edge_px: float) -> int:
    """Index of the first column (axis 'u') or row ('v') the plane covers when its edge is at
    pixel coordinate edge_px of the camera `k` (the plane covers the larger coordinates)."""
    cid, body, view = plane
    if axis == 'u':
        x_opt = (edge_px - k[0, 2]) / k[0, 0] * Z      # optical x of the edge
        pos = [Z + 0.01, -x_opt - 20.0, 0.0]
    else:
        y_opt = (edge_px - k[1, 2]) / k[1, 1] * Z
        pos = [Z + 0.01, 0.0, -y_opt - 20.0]
    pb.resetBasePositionAndOrientation(body, pos, [0, 0, 0, 1], physicsClientId=cid)
    _, _, rgba, _, _ = pb.getCameraImage(w, h, view, proj, renderer=pb.ER_TINY_RENDERER,
                                         flags=pb.ER_NO_SEGMENTATION_MASK, physicsClientId=cid)
    lit = np.reshape(np.asarray(rgba, np.uint8), (h, w, 4))[:, :, 0] < 128
    line = lit[h // 3] if axis == 'u' else lit[:, w // 3]
    return int(np.flatnonzero(line)[0])


@pytest.mark.parametrize('w,h', [(64, 48), (65, 49)])
def test_tinyrenderer_draws_the_image_of_k(plane, w, h):
    """Pixel (u, v) shows the ray of K through (u, v): an edge at pixel coordinate e covers
    from index ceil(e) on, for an edge anywhere within a pixel, with K's principal point at the
    image centre and off it. The symmetric matrix of computeProjectionMatrixFOV does not (its
    principal point is (w / 2, h / 2 - 1))."""
    fractions = (0.1, 0.3, 0.45, 0.55, 0.7, 0.9)
    for cx, cy in (((w - 1) / 2.0, (h - 1) / 2.0), (w / 2.0 - 3.25, h / 2.0 + 2.6)):
        k = _k(w, h, cx, cy)
        proj = projection_matrix(k, w, h, 0.05, 60.0)
        for axis, base in (('u', w // 2 + 3), ('v', h // 2 - 4)):
            for frac in fractions:
                e = base + frac
                assert _first_covered(plane, k, w, h, proj, axis, e) == math.ceil(e), (
                    axis, cx, cy, e)
    # the symmetric matrix: column u samples u - w/2 from the axis, row v samples v - (h/2 - 1)
    k = _k(w, h, (w - 1) / 2.0, (h - 1) / 2.0)
    vfov = math.degrees(2.0 * math.atan((h / 2.0) / k[1, 1]))
    sym = pb.computeProjectionMatrixFOV(vfov, w / h, 0.05, 60.0)
    assert np.allclose(sym, projection_matrix(_k(w, h, w / 2.0, h / 2.0 - 1.0), w, h, 0.05,
                                              60.0), rtol=1e-5, atol=1e-6)
    got = [_first_covered(plane, k, w, h, sym, 'u', w // 2 + 3 + f) for f in fractions]
    assert got != [math.ceil(w // 2 + 3 + f) for f in fractions]


def test_bad_intrinsics_are_refused():
    k = _k(64, 48, 31.5, 23.5)
    for bad in (k[:2], np.diag([0.0, 1.0, 1.0]), k + np.array([[0, 0.1, 0], [0] * 3, [0] * 3])):
        with pytest.raises(ValueError):
            projection_matrix(bad, 64, 48, 0.05, 60.0)
    with pytest.raises(ValueError):
        projection_matrix(k, 64, 48, 1.0, 0.5)


def test_fine_intrinsics_and_pixel_average_by_hand():
    k = np.array([[100.0, 0.0, 31.5], [0.0, 90.0, 23.5], [0.0, 0.0, 1.0]])
    f = fine_intrinsics(k, 3)
    # pixel 0 covers fine columns 0..2, centred on 1 = 3 * 0 + 1; pixel 31.5 -> 95.5
    np.testing.assert_allclose(f, [[300.0, 0.0, 95.5], [0.0, 270.0, 71.5], [0.0, 0.0, 1.0]])
    assert np.array_equal(fine_intrinsics(k, 1), k)
    fine = np.zeros((3, 6), np.uint8)
    fine[:, 3:] = 255
    fine[0, 0], fine[1, 1] = 9, 200                   # block means 209/9 = 23.2, 255
    assert np.array_equal(pixel_average(fine, 3), [[23, 255]])
    for bad in (2, 0, 1.0, True):
        with pytest.raises(ValueError, match='odd'):
            fine_intrinsics(k, bad)
        with pytest.raises(ValueError, match='odd'):
            pixel_average(fine, bad)
    with pytest.raises(ValueError, match='integer size'):
        pixel_average(np.zeros((4, 6), np.uint8), 3)
    for bad in (np.zeros((6, 6, 3), np.uint8), np.zeros((6, 6))):
        with pytest.raises(ValueError, match='mono8'):
            pixel_average(bad, 3)
    with pytest.raises(ValueError, match='pinhole'):
        fine_intrinsics(k[:2], 3)
    same = pixel_average(fine, 1)
    assert np.array_equal(same, fine) and same is not fine


@pytest.mark.parametrize('n', [3, 5])
def test_supersampled_pixel_is_the_covered_fraction_of_its_area(plane, n):
    """An edge inside a pixel: rendered with fine_intrinsics(k, n) and pixel_average'd, the
    pixel's level is the fraction of its n samples on the white side (the edge's sub-pixel
    position, quantised to 1 / n), the pixels either side fully black or white."""
    w, h = 64, 48
    k = _k(w, h, (w - 1) / 2.0, (h - 1) / 2.0)
    cid, body, view = plane
    proj = projection_matrix(fine_intrinsics(k, n), n * w, n * h, 0.05, 60.0)
    u = w // 2 + 3
    for frac in (-0.4, -0.2, 0.05, 0.3):              # the edge at u + frac: pixel u split
        x_opt = (u + frac - k[0, 2]) / k[0, 0] * Z
        pb.resetBasePositionAndOrientation(body, [Z + 0.01, -x_opt - 20.0, 0.0], [0, 0, 0, 1],
                                           physicsClientId=cid)
        _, _, rgba, _, _ = pb.getCameraImage(n * w, n * h, view, proj,
                                             renderer=pb.ER_TINY_RENDERER,
                                             flags=pb.ER_NO_SEGMENTATION_MASK,
                                             physicsClientId=cid)
        fine = np.reshape(np.asarray(rgba, np.uint8), (n * h, n * w, 4))[:, :, 0]
        line = pixel_average(fine, n)[h // 3].astype(float)
        samples = u + (np.arange(n) - (n - 1) / 2) / n           # pixel u's sample columns
        white = np.mean(samples < u + frac)                       # left of the edge: background
        bg = line[0]
        assert line[u - 1] == pytest.approx(bg, abs=1) and line[u + 1] == pytest.approx(0, abs=1)
        assert line[u] == pytest.approx(white * bg, abs=1.5), (frac, line[u - 1:u + 2])
