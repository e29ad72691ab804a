"""`make demo`'s map figure (tools/demo.py save_map_figure) from a hand-made OccupancyGrid."""
import importlib.util
from pathlib import Path

import cv2
import numpy as np
from nav_msgs.msg import OccupancyGrid

ROOT = Path(__file__).resolve().parents[1]


def _demo():
    spec = importlib.util.spec_from_file_location('demo', ROOT / 'tools' / 'demo.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_map_figure_draws_the_slice_cameras_and_views(tmp_path):
    demo = _demo()
    g = OccupancyGrid()
    g.header.frame_id = 'map'
    g.info.resolution, g.info.width, g.info.height = 0.1, 40, 30
    g.info.origin.position.x, g.info.origin.position.y = -1.0, -1.5
    data = np.full((30, 40), -1, np.int8)
    data[10:20, 5:35] = 0
    data[14:16, 30:33] = 100
    g.data = data.ravel().tolist()
    # rover1's camera lies outside the slice (it was clipped at the edge), rover2 has no view
    cams = {'rover1': (-1.6, 0.0, 0.3), 'rover2': (1.0, 0.2, np.pi)}
    views = {'rover1': (0.5, -0.5, -1.0)}
    path = demo.save_map_figure(g, cams, views, tmp_path / 'map_grid.png')
    img = cv2.imread(str(path))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 300
    colours = {tuple(c) for c in img.reshape(-1, 3)[::7]}
    assert (0, 0, 0) in colours and (255, 255, 255) in colours      # occupied and free cells
