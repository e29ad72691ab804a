"""Table C-1: compression ratios of the nine predictors and Huffman coding on rendered scenes
(PyBullet TinyRenderer: random blocks, spheres and cylinders on a ground plane, random camera)
and on pure-noise images, next to the thesis's numbers.

    ros2 run coop_viewplan table_c_1 --images 40 --json out/table_c_1.json
"""
from __future__ import annotations

import argparse
import sys

import numpy as np

from coop_common.cli import number, output_path
from coop_common.files import write_json

from .imageinfo import compression_ratio

SIZES = (16, 32, 64, 128, 256)
THESIS = {1: [1.000] * 5, 2: [1.009, 1.142, 1.253, 1.375, 1.531],
          3: [1.013, 1.142, 1.247, 1.358, 1.488], 4: [0.980, 1.060, 1.149, 1.250, 1.348],
          5: [0.983, 1.143, 1.277, 1.416, 1.723], 6: [0.996, 1.156, 1.289, 1.427, 1.646],
          7: [0.997, 1.157, 1.288, 1.422, 1.619], 8: [1.018, 1.159, 1.282, 1.414, 1.564],
          9: [1.008, 1.126, 1.236, 1.358, 1.480], 10: [0.997, 0.996, 0.996, 0.996, 0.996]}


def render_scene(seed: int, size: int = 256, *, sensor_sigma: float = 2.0) -> np.ndarray:
    """A mono8 image of a random scene rendered by PyBullet's TinyRenderer, with Gaussian
    sensor noise of `sensor_sigma` gray levels (a rendered image has none; a camera does)."""
    import pybullet as pb  # noqa: PLC0415 - heavy, only to render the scenes
    rng = np.random.default_rng(seed)
    cid = pb.connect(pb.DIRECT)
    try:
        ground = pb.createVisualShape(pb.GEOM_BOX, halfExtents=[20, 20, 0.01],
                                      rgbaColor=[*rng.uniform(0.3, 0.6, 3), 1],
                                      physicsClientId=cid)
        pb.createMultiBody(baseVisualShapeIndex=ground, basePosition=[0, 0, -0.01],
                           physicsClientId=cid)
        for _ in range(int(rng.integers(5, 25))):
            kind = rng.integers(3)
            rgba = [*rng.uniform(0, 1, 3), 1]
            if kind == 0:
                vs = pb.createVisualShape(pb.GEOM_BOX, halfExtents=rng.uniform(0.1, 0.8, 3),
                                          rgbaColor=rgba, physicsClientId=cid)
            elif kind == 1:
                vs = pb.createVisualShape(pb.GEOM_SPHERE, radius=rng.uniform(0.1, 0.7),
                                          rgbaColor=rgba, physicsClientId=cid)
            else:
                vs = pb.createVisualShape(pb.GEOM_CYLINDER, radius=rng.uniform(0.1, 0.5),
                                          length=rng.uniform(0.2, 1.5), rgbaColor=rgba,
                                          physicsClientId=cid)
            pos = [*rng.uniform(-4, 4, 2), rng.uniform(0, 0.8)]
            orn = pb.getQuaternionFromEuler(rng.uniform(-np.pi, np.pi, 3).tolist())
            pb.createMultiBody(baseVisualShapeIndex=vs, basePosition=pos,
                               baseOrientation=orn, physicsClientId=cid)
        eye = [*rng.uniform(-7, 7, 2), rng.uniform(1.0, 4.0)]
        view = pb.computeViewMatrix(eye, [*rng.uniform(-1, 1, 2), 0.3], [0, 0, 1])
        proj = pb.computeProjectionMatrixFOV(41.2, 1.0, 0.1, 50.0)
        light = [*rng.uniform(-5, 5, 2), 8.0]
        _, _, rgb, _, _ = pb.getCameraImage(size, size, view, proj, lightDirection=light,
                                            renderer=pb.ER_TINY_RENDERER,
                                            physicsClientId=cid)
    finally:
        pb.disconnect(cid)
    rgb = np.asarray(rgb, np.float64).reshape(size, size, 4)[..., :3]
    gray = rgb @ [0.299, 0.587, 0.114] + rng.normal(0.0, sensor_sigma, (size, size))
    return np.clip(np.rint(gray), 0, 255).astype(np.uint8)


def study(images: list[np.ndarray], sizes: tuple[int, ...] = SIZES) -> dict:
    """CR mean and std per method and crop size (centre crops of each image)."""
    out = {}
    for m in range(1, 11):
        row = []
        for s in sizes:
            ratios: list[float] = []
            for img in images:
                h, w = img.shape
                c = img[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]
                ratios.append(compression_ratio(c, m))
            crs = np.array(ratios)
            crs = crs[np.isfinite(crs)]
            row.append([float(crs.mean()), float(crs.std())] if len(crs) else [None, None])
        out[m] = row
    return out


def format_json(result: dict) -> str:
    """The printed tables of a result (as `--json` writes it: method keys may be strings)."""
    thesis = {int(m): v for m, v in result['thesis'].items()}
    count = {'scenes': result['images'], 'noise': result['noise_images']}
    lines = []
    for name, table in result['results'].items():
        lines.append(f'Table C-1 ({name}, {count[name]} images): CR mean +- std  [thesis]')
        lines.append('method ' + ''.join(f'{f"{s}^2":>22s}' for s in SIZES))
        for m, row in sorted((int(m), row) for m, row in table.items()):
            cells = ''.join(f'{f"{v[0]:.3f}+-{v[1]:.3f} [{t:.3f}]":>22s}'
                            for v, t in zip(row, thesis[m], strict=False))
            lines.append(f'{m:>6d} {cells}')
    lines.append(f"best predictor at 256^2 on scenes: method {result['best_predictor_256']} "
                 '(thesis: method 5)')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """`ros2 run coop_viewplan table_c_1`: the compression ratios on rendered and noise images."""
    p = argparse.ArgumentParser(prog='table_c_1', description=__doc__.split('\n\n')[0])
    p.add_argument('--images', type=number(int, lo=1), default=40)
    p.add_argument('--noise', type=number(int, lo=0), default=20, help='pure-noise images')
    p.add_argument('--sensor-sigma', type=number(lo=0), default=2.0,
                   help='camera noise added to the rendered scenes (gray levels)')
    p.add_argument('--json', type=output_path, default=None)
    args = p.parse_args(argv)
    scenes = [render_scene(s, sensor_sigma=args.sensor_sigma) for s in range(args.images)]
    rng = np.random.default_rng(12345)
    noise = [rng.integers(0, 256, (256, 256)).astype(np.uint8) for _ in range(args.noise)]
    res = {'scenes': study(scenes)}
    if noise:
        res['noise'] = study(noise)
    best = max(range(2, 10), key=lambda m: res['scenes'][m][-1][0])
    result = {'images': len(scenes), 'noise_images': len(noise),
              'sensor_sigma': args.sensor_sigma, 'results': res,
              'thesis': THESIS, 'best_predictor_256': best}
    print(format_json(result))
    if args.json is not None:
        write_json(args.json, result, indent=1)
        print(f'json: {args.json}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
