"""`make demo`'s map figure (tools/demo.py draw_map / save_map_figure) from a hand-made grid."""
import importlib.util
from pathlib import Path

import matplotlib
import numpy as np
from nav_msgs.msg import OccupancyGrid

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def _demo():
    spec = importlib.util.spec_from_file_location('demo', ROOT / 'tools' / 'demo.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _grid() -> OccupancyGrid:
    g = OccupancyGrid()
    g.header.frame_id = 'map'
    g.info.resolution, g.info.width, g.info.height = 0.1, 40, 30
    g.info.origin.position.x, g.info.origin.position.y = -1.0, -1.5
    data = np.full((30, 40), -1, np.int8)      # rows are y, columns x
    data[10:20, 5:35] = 0                      # free: x -0.5..2.5, y -0.5..0.5
    data[14:16, 30:33] = 100                   # occupied: x 2.0..2.3, y -0.1..0.1
    g.data = data.ravel().tolist()
    return g


def test_map_figure_puts_each_cell_where_it_is_in_metres(tmp_path):
    demo = _demo()
    # rover1's camera lies outside the slice (it was clipped at the edge), rover2 has no view
    cams = {'rover1': (-1.6, 0.0, 0.3), 'rover2': (1.0, 0.2, np.pi)}
    views = {'rover1': (0.5, -0.8, -1.0)}
    fig, ax = plt.subplots(figsize=(7, 7))
    demo.draw_map(ax, _grid(), cams, views)
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[:, :, :3].astype(int)

    def colour(x, y):
        u, v = ax.transData.transform((x, y))
        return img[int(round(img.shape[0] - v)), int(round(u))]

    assert list(colour(2.15, 0.0)) == [0, 0, 0]              # occupied
    assert list(colour(0.0, 0.3)) == [255, 255, 255]         # free
    assert list(colour(2.5, -1.2)) == [153, 153, 153]        # unknown (grey 0.6)
    assert ax.get_xlim()[0] <= -1.6 - 0.5 + 1e-9            # the camera outside is in view
    plt.close(fig)
    path = demo.save_map_figure(_grid(), cams, views, tmp_path / 'map_grid.png')
    assert path.stat().st_size > 10_000
