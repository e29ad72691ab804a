"""The OpenGL projection matrix that makes PyBullet's TinyRenderer draw the image of a given
pinhole camera matrix K, so that the K a simulated camera reports is the one its images have.

TinyRenderer (bullet3 examples/TinyRenderer/our_gl.cpp) maps normalised device coordinates to
the window by x_w = (x_ndc + 1) w / 2, y_w = (y_ndc + 1) h / 2, fills pixel P where the
triangle covers the integer point P, and getCameraImage returns the rows top first
(row r = h - 1 - y_w). In the OpenCV convention (pixel (u, v) covers [u - 1/2, u + 1/2] x
[v - 1/2, v + 1/2]), the symmetric matrix of computeProjectionMatrixFOV therefore puts the
principal point at (w / 2, h / 2 - 1), not at the image centre ((w - 1) / 2, (h - 1) / 2):
half a pixel off in each axis, in opposite directions (measured by
test_rendering.py::test_tinyrenderer_draws_the_image_of_k). `projection_matrix` shifts the
matrix's third column so the renderer's principal point is K's.

TinyRenderer also samples the scene once per pixel (at its centre, one texel, no area
integration), so texture finer than a pixel aliases, differently in the two images of a stereo
pair, where a camera's pixel integrates the light over its area. `fine_intrinsics` and
`pixel_average` render n x n samples per pixel and average them. No pybullet here.
"""
from __future__ import annotations

import numpy as np

__all__ = ['fine_intrinsics', 'pixel_average', 'projection_matrix']


def projection_matrix(k: np.ndarray, width: int, height: int, near: float, far: float
                      ) -> list[float]:
    """16 floats, column-major (PyBullet's projectionMatrix): the perspective projection of
    the camera with 3x3 intrinsics `k` (x right, y down, z forward) onto a `width` x `height`
    TinyRenderer image, depth clipped to [near, far]. Skew must be 0."""
    k = np.asarray(k, float)
    if k.shape != (3, 3) or k[0, 1] != 0.0 or not (k[0, 0] > 0 and k[1, 1] > 0):
        raise ValueError(f'need a 3x3 pinhole matrix with fx, fy > 0 and no skew, got {k!r}')
    if not (width > 0 and height > 0 and 0 < near < far):
        raise ValueError(f'need a positive image size and 0 < near < far, got {width}x{height}, '
                         f'near {near}, far {far}')
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    p = np.zeros((4, 4))
    # column u = fx X/Z + cx samples x_ndc = 2u/w - 1; row v = fy Y/Z + cy samples
    # y_ndc = 2(h - 1 - v)/h - 1; with X = x_eye, Y = -y_eye, Z = -z_eye (OpenGL eye frame)
    p[0, 0] = 2.0 * fx / width
    p[0, 2] = 1.0 - 2.0 * cx / width
    p[1, 1] = 2.0 * fy / height
    p[1, 2] = (2.0 * cy + 2.0 - height) / height
    p[2, 2] = -(far + near) / (far - near)
    p[2, 3] = -2.0 * far * near / (far - near)
    p[3, 2] = -1.0
    return p.T.reshape(-1).tolist()


def _factor(n: int) -> int:
    """The supersampling factor: an odd integer >= 1 (odd puts a sample on each pixel centre,
    and no block mean is a tie)."""
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1 or n % 2 == 0:
        raise ValueError(f'the supersampling factor must be an odd integer >= 1, got {n!r}')
    return int(n)


def fine_intrinsics(k: np.ndarray, n: int) -> np.ndarray:
    """3x3 K of the image n times finer in each axis whose n x n blocks are the pixels of K's
    image: pixel u covers fine columns [n u, n u + n), centred on n u + (n - 1) / 2, so
    f' = n f, skew' = n skew and c' = n c + (n - 1) / 2. With n odd a fine sample sits on
    each pixel centre (where a renderer's depth is read)."""
    n = _factor(n)
    k = np.asarray(k, float)
    if k.shape != (3, 3) or not np.array_equal(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0.0:
        raise ValueError(f'need a 3x3 pinhole matrix, got {k!r}')
    return np.array([[n * k[0, 0], n * k[0, 1], n * k[0, 2] + (n - 1) / 2],
                     [0.0, n * k[1, 1], n * k[1, 2] + (n - 1) / 2], [0.0, 0.0, 1.0]])


def pixel_average(fine: np.ndarray, n: int) -> np.ndarray:
    """The mono8 image whose pixels are the means of the n x n blocks of the mono8 image
    `fine` (a rendering of `fine_intrinsics(k, n)`, shape (n h, n w)), rounded to the nearest
    level (n odd: no mean is a tie). A new array, also for n = 1."""
    n = _factor(n)
    fine = np.asarray(fine)
    if fine.ndim != 2 or fine.dtype != np.uint8:
        raise ValueError(f'need a mono8 image, got {fine.dtype} of shape {fine.shape}')
    h, w = fine.shape[0] // n, fine.shape[1] // n
    if fine.shape != (n * h, n * w):
        raise ValueError(f'image {fine.shape} is not n = {n} times an integer size')
    if n == 1:
        return fine.copy()
    mean = fine.reshape(h, n, w, n).mean(axis=(1, 3))
    return np.clip(np.rint(mean), 0, 255).astype(np.uint8)
