"""A small textured scene rendered with PyBullet (DIRECT, TinyRenderer) as a stereo data source
for tests, the benchmark and the experiments when the simulator is not in the loop.

Returns rectified mono8 pairs and the true depth (z in the left optical frame) of every pixel,
so surface errors can be measured against the truth. No rclpy here.
"""
from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass

import cv2
import numpy as np

from coop_common.rendering import fine_intrinsics, pixel_average, projection_matrix

from .stereo import StereoCamera

__all__ = ['Box', 'TexturedScene', 'default_boxes', 'look_at']


@dataclass(frozen=True)
class Box:
    """An axis-aligned box: centre and half extents (m)."""

    centre: tuple[float, float, float]
    half_extents: tuple[float, float, float]


def default_boxes() -> list[Box]:
    """Ground slab (top at z = 0) and a few rocks / walls in front of +x."""
    return [Box((4.0, 0.0, -0.05), (6.0, 6.0, 0.05)),
            Box((3.0, -0.8, 0.3), (0.3, 0.3, 0.3)),
            Box((4.2, 0.9, 0.5), (0.4, 0.5, 0.5)),
            Box((6.5, 0.0, 0.75), (0.2, 3.0, 0.75)),
            Box((2.2, 0.6, 0.15), (0.15, 0.2, 0.15))]


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """R_wc of an optical frame (z forward, x right, y down) at `eye` looking at `target`
    (`up`: the world's up, +z by default)."""
    if up is None:
        up = np.array([0.0, 0.0, 1.0])
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)


def _tiles(boxes: list[Box], tile: float) -> list[Box]:
    out = []
    for b in boxes:
        c = np.asarray(b.centre, float)
        h = np.asarray(b.half_extents, float)
        n = np.maximum(1, np.ceil(2 * h / tile)).astype(int)
        sub = h / n
        for ix in range(n[0]):
            for iy in range(n[1]):
                for iz in range(n[2]):
                    cc = c - h + sub * (2 * np.array([ix, iy, iz]) + 1)
                    out.append(Box(tuple(cc), tuple(sub)))
    return out


class TexturedScene:
    """PyBullet DIRECT world of textured boxes; render(R_wc, t_wc) -> left, right, depth.

    `supersample` k (odd, >= 1): TinyRenderer samples the scene at pixel centres only (one
    texel per pixel, no area integration), so texture finer than a pixel aliases, differently
    in the two images of a pair; a camera's pixel integrates the light over its area. With
    k > 1 the images are rendered at k times the resolution (the same field of view and
    principal point) and averaged over k x k blocks (coop_common.rendering.fine_intrinsics,
    pixel_average); odd k puts a fine sample on each pixel centre, where the true depth is
    read."""

    def __init__(self, camera: StereoCamera, *, boxes: list[Box] | None = None, seed: int = 0,
                 near: float = 0.1, far: float = 30.0, tile_m: float = 0.8,
                 supersample: int = 1) -> None:
        import pybullet as p  # noqa: PLC0415 - heavy, only for this data source

        # the camera sampled n x n per pixel (ValueError unless n is an odd integer >= 1),
        # checked before anything is opened
        k = fine_intrinsics(np.array([[camera.fx, 0.0, camera.cx], [0.0, camera.fy, camera.cy],
                                      [0.0, 0.0, 1.0]]), supersample)
        self._p = p
        self.camera = camera
        self.supersample = int(supersample)
        self.near, self.far = near, far
        self.boxes = boxes if boxes is not None else default_boxes()
        self._cid = p.connect(p.DIRECT)
        rng = np.random.default_rng(seed)
        self._tmp = tempfile.TemporaryDirectory(prefix='coop_mapping_tex_')
        # blurred noise: texture with contrast at several scales so SGBM has something to match;
        # TinyRenderer maps one texture per face, so big boxes are cut into tiles of <= tile_m
        for i, b in enumerate(_tiles(self.boxes, tile_m)):
            tex: np.ndarray = rng.integers(0, 256, (256, 256)).astype(np.uint8)
            tex = cv2.GaussianBlur(tex, (0, 0), 1.2)
            # (OpenCV's stubs want an array for dst; None returns a new one)
            tex = cv2.normalize(tex, None, 0, 255, cv2.NORM_MINMAX)  # type: ignore[call-overload]
            path = os.path.join(self._tmp.name, f'tex{i}.png')
            cv2.imwrite(path, cv2.cvtColor(tex, cv2.COLOR_GRAY2BGR))
            vis = p.createVisualShape(p.GEOM_BOX, halfExtents=b.half_extents,
                                      physicsClientId=self._cid)
            body = p.createMultiBody(baseMass=0, baseVisualShapeIndex=vis,
                                     basePosition=b.centre, physicsClientId=self._cid)
            tid = p.loadTexture(path, physicsClientId=self._cid)
            p.changeVisualShape(body, -1, textureUniqueId=tid, rgbaColor=[1, 1, 1, 1],
                                physicsClientId=self._cid)
        n = self.supersample
        self._size = (n * camera.width, n * camera.height)
        self._proj = projection_matrix(k, *self._size, near, far)

    def close(self) -> None:
        if self._cid is not None:
            self._p.disconnect(self._cid)
            self._cid = None
            self._tmp.cleanup()

    def __enter__(self) -> TexturedScene:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _view(self, R_wc: np.ndarray, t_wc: np.ndarray) -> list[float]:
        R_gl = np.asarray(R_wc, float) @ np.diag([1.0, -1.0, -1.0])
        V = np.eye(4)
        V[:3, :3] = R_gl.T
        V[:3, 3] = -R_gl.T @ np.asarray(t_wc, float)
        return V.T.reshape(-1).tolist()  # column-major, as OpenGL

    def _render_one(self, R_wc: np.ndarray, t_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        p = self._p
        w, h = self._size
        _, _, rgb, zbuf, _ = p.getCameraImage(
            w, h, viewMatrix=self._view(R_wc, t_wc),
            projectionMatrix=self._proj, renderer=p.ER_TINY_RENDERER, shadow=0,
            lightDirection=[0.3, 0.2, 1.0], physicsClientId=self._cid)
        rgb = np.asarray(rgb, np.uint8).reshape(h, w, 4)
        gray = cv2.cvtColor(rgb[:, :, :3], cv2.COLOR_RGB2GRAY)
        zb = np.asarray(zbuf, np.float64).reshape(h, w)
        n = self.supersample
        if n > 1:
            gray = pixel_average(gray, n)
            zb = zb[n // 2::n, n // 2::n]
        depth = self.far * self.near / (self.far - (self.far - self.near) * zb)
        depth[zb >= 1.0] = np.nan
        return gray, depth

    def render(self, R_wc: np.ndarray, t_wc: np.ndarray, *, noise_sigma: float = 0.0,
               rng: np.random.Generator | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Left, right mono8 (right camera at +baseline along the left optical x) and the
        true depth of the left image (m, NaN for sky)."""
        R = np.asarray(R_wc, float)
        t = np.asarray(t_wc, float)
        left, depth = self._render_one(R, t)
        right, _ = self._render_one(R, t + R @ np.array([self.camera.baseline, 0.0, 0.0]))
        if noise_sigma > 0:
            rng = rng or np.random.default_rng(0)
            left = np.clip(left + rng.normal(0, noise_sigma, left.shape), 0, 255).astype(np.uint8)
            right = np.clip(right + rng.normal(0, noise_sigma, right.shape), 0,
                            255).astype(np.uint8)
        return left, right, depth

    def true_points(self, depth: np.ndarray, R_wc: np.ndarray, t_wc: np.ndarray,
                    stride: int = 1) -> np.ndarray:
        """Map-frame surface points of the true depth image."""
        cam = self.camera
        v, u = np.mgrid[0:cam.height:stride, 0:cam.width:stride]
        z = depth[::stride, ::stride]
        ok = np.isfinite(z)
        z, u, v = z[ok], u[ok], v[ok]
        pc = np.stack([(u - cam.cx) * z / cam.fx, (v - cam.cy) * z / cam.fy, z], -1)
        return pc @ np.asarray(R_wc, float).T + np.asarray(t_wc, float)
