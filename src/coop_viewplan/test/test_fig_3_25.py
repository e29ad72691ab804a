"""The Fig. 3-25 analogue at reduced size (one rover, two planned scans), through its CLI."""
from __future__ import annotations

import json

import numpy as np
import pytest

from coop_viewplan import fig_3_25
from coop_viewplan.nbv import PlanningError, geodesic_path


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
