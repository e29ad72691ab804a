"""The Fig. 3-25 analogue at reduced size (one rover, two planned scans), through its CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from coop_viewplan import fig_3_25
from coop_viewplan.grid import OccupancyGrid, gray_estimate
from coop_viewplan.nbv import NbvConfig, PlanningError, geodesic_path, score_views


def test_geodesic_path_goes_round_a_wall():
    nav = np.ones((20, 20), bool)
    nav[10, :15] = False
    path = geodesic_path(nav, (2, 2), (18, 2), resolution=1.0)
    assert tuple(path[0]) == (2, 2) and tuple(path[-1]) == (18, 2)
    assert nav[tuple(path.T)].all()
    assert np.all(np.abs(np.diff(path, axis=0)).max(axis=1) == 1)    # 8-connected steps
    assert path[:, 1].max() >= 15                                     # through the gap
    nav[10, :] = False
    with pytest.raises(PlanningError):
        geodesic_path(nav, (2, 2), (18, 2), resolution=1.0)


def test_fig_3_25_cli_small(tmp_path, capsys):
    pytest.importorskip('pybullet')
    out = tmp_path / 'fig_3_25.json'
    rc = fig_3_25.main(['--rovers', '1', '--scans', '2', '--candidates', '12', '--quiet',
                        '--json', str(out), '--plots', str(tmp_path)])
    assert rc == 0
    text = capsys.readouterr().out
    assert 'Fig. 3-25 analogue' in text and 'thesis:' in text and 'here (site):' in text
    res = json.loads(out.read_text())
    assert set(res['strategies']) == {'raster', 'max_information'}
    for name, s in res['strategies'].items():
        known, occ = np.array(s['known_voxels']), np.array(s['occupied_voxels'])
        assert known.shape == (3,) and occ.shape == (3,)
        # the same world and first scan for both strategies; the map only grows
        assert known[0] == res['strategies']['raster']['known_voxels'][0] > 1000
        assert np.all(np.diff(known) >= 0) and known[-1] > known[0], name
        assert np.all(occ <= known)
        assert np.all(np.array(s['known_voxels_all']) >= known)
        assert len(s['poses'][0][0]) == 3                        # start + 2 scans
    assert (tmp_path / 'fig_3_25.png').is_file()


def _half_seen_grid():
    """A 6 m x 6 m x 0.9 m site at 0.1 m: x < 3 m seen empty once (the log-odds map's 0.40 after
    one miss), a few range points there (0.70 after one hit), x >= 3 m unknown."""
    g = OccupancyGrid.empty((60, 60, 9), resolution=0.1, origin=np.array([0.0, 0.0, -0.1]))
    g.known[:30] = True
    g.prob[:30] = 0.4
    g.prob[5:8, 10:13, 1:4] = 0.7
    return g


def test_gray_estimate_known_empty_is_certain():
    g = _half_seen_grid()
    est = gray_estimate(g)
    assert np.all(est[:30][g.prob[:30] < 0.5] == 0.0)         # empty space: gray 0
    assert np.allclose(est[5:8, 10:13, 1:4], 0.7)             # measured points keep theirs
    assert np.all(est[45:] == 0.5)                            # far unknown: the Markov 0.5
    assert 0.0 < est[30, 30, 4] < 0.5                         # next to empty: leans to empty
    old = gray_estimate(g, free_gray='occupancy')
    assert np.allclose(old[:30][g.prob[:30] < 0.5], 0.4)
    with pytest.raises(ValueError):
        gray_estimate(g, free_gray='zero')


def test_view_of_known_empty_space_has_no_information():
    """§3.2.4: "If every point in the field of view is known and is empty then NI = 0", and NI
    grows with the unknowns in view. With the map's own probability a voxel seen empty once
    (p = 0.4, -p log2 p = 0.53) outweighed an unknown one and drew the views back to it."""
    g = _half_seen_grid()
    g.prob[5:8, 10:13, 1:4] = 0.4
    cfg = NbvConfig(fov_deg=41.2, vfov_deg=31.5, depth_m=2.5, n_az=12, n_el=9, step_cells=1.0)
    tpl = cfg.template(ndim=3, resolution=0.1)
    pos = np.array([[3.0, 3.0, 0.75], [3.0, 3.0, 0.75]])
    yaw, pitch = np.array([np.pi, 0.0]), np.radians([20.0, 20.0])   # into the seen / unknown half
    new = score_views(g, gray_estimate(g), pos, yaw, pitch, tpl)
    assert new.known_cells[0] > 0 and new.unknown_cells[0] == 0
    assert new.ni[0] == 0.0 and new.ni[1] > 0.0
    old = score_views(g, gray_estimate(g, free_gray='occupancy'), pos, yaw, pitch, tpl)
    assert old.ni[0] >= old.ni[1] > 0.0
