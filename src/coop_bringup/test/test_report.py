"""The mission's measures and report (coop_bringup.report) on hand-built maps and results."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from coop_bringup.report import (
    MissionError,
    format_summary,
    identification_errors,
    site_coverage,
    top_view,
    write_report,
)

RES = 0.1


def _ground(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    """Keys of the ground voxels (z key -1, the ground at z = 0) over [x0, x1) x [y0, y1)."""
    i = np.arange(round(x0 / RES), round(x1 / RES))
    j = np.arange(round(y0 / RES), round(y1 / RES))
    ii, jj = np.meshgrid(i, j, indexing='ij')
    return np.column_stack([ii.ravel(), jj.ravel(), np.full(ii.size, -1)])


def test_coverage_counts_measured_surfaces_not_rays():
    half = _ground(0.0, 2.0, -1.0, 1.0)                    # the west half of a 4 m site
    # free voxels above the unseen east half: crossed by rays, not covered
    above = _ground(2.0, 4.0, -1.0, 1.0) + [0, 0, 5]
    keys = np.vstack([half, above])
    occ = np.r_[np.full(len(half), 0.97), np.full(len(above), 0.12)]
    cov = site_coverage(keys, occ, RES, centre_xy=(2.0, 0.0), half_m=2.0)
    assert cov == pytest.approx(400 / 1600)                 # 20 x 20 of the 40 x 40 cells
    # every column: a rock top (z key 3) counts like the ground
    rock = _ground(2.0, 4.0, -1.0, 1.0) + [0, 0, 4]
    keys2 = np.vstack([half, rock, _ground(0.0, 4.0, 1.0, 2.0), _ground(0.0, 4.0, -2.0, -1.0)])
    occ2 = np.full(len(keys2), 0.97)
    assert site_coverage(keys2, occ2, RES, centre_xy=(2.0, 0.0), half_m=2.0) == 1.0
    # outside the site and above z_max: not counted
    far = _ground(10.0, 14.0, -2.0, 2.0)
    assert site_coverage(far, np.full(len(far), 0.97), RES, centre_xy=(2.0, 0.0),
                         half_m=2.0) == 0.0
    high = _ground(0.0, 4.0, -2.0, 2.0) + [0, 0, 15]
    assert site_coverage(high, np.full(len(high), 0.97), RES, centre_xy=(2.0, 0.0),
                         half_m=2.0) == 0.0
    with pytest.raises(MissionError):
        site_coverage(half, np.ones(3), RES, centre_xy=(2.0, 0.0), half_m=2.0)
    with pytest.raises(MissionError):
        site_coverage(half, np.ones(len(half)), RES, centre_xy=(2.0, 0.0), half_m=0.0)


def test_top_view_tells_unseen_free_and_obstacle_cells():
    ground = _ground(0.0, 1.0, 0.0, 1.0)
    rock = np.array([[3, 3, 2]])
    free = np.array([[8, 8, 5]])
    keys = np.vstack([ground, rock, free])
    occ = np.r_[np.full(len(ground), 0.97), 0.97, 0.12]
    top = top_view(keys, occ, RES, centre_xy=(1.0, 1.0), half_m=1.0)
    assert top.shape == (20, 20)
    assert top[3, 3] == 1                     # the rock
    assert top[0, 0] == 0 and top[9, 9] == 0  # the ground: seen, no obstacle
    assert top[15, 15] == -1                  # never seen
    assert (top == 1).sum() == 1


def test_identification_errors_against_truth():
    truth = {'mass': 3.0, 'Ixz': 0.0, 'k_x': 200.0}
    est = {'mass': 3.3, 'Ixz': 0.01, 'k_x': 190.0}
    r = identification_errors(truth, est, {'mass': 0.1, 'Ixz': 0.01, 'k_x': 5.0},
                              {'mass': 7.0, 'Ixz': 2.0, 'k_x': 6.0})
    assert r['mean_abs_rel_error'] == pytest.approx((0.1 + 0.05) / 2)
    rows = {p['name']: p for p in r['params']}
    assert rows['Ixz']['rel_error'] is None and rows['mass']['information_bits'] == 7.0
    with pytest.raises(MissionError):
        identification_errors(truth, {'mass': 3.0})


def test_report_files_and_summary(tmp_path):
    rep = {'run_id': 'test', 'config': {'seed': 1, 'occlusion_density': 0.05, 'slot_in': 5.0,
                                        'rovers': 2, 'phases': ['identify', 'map']},
           'targets': {'identification_error': 0.15, 'coverage': 0.9, 'penetration_mm': 0.5},
           'identification': {'mean_abs_rel_error': 0.05, 'rovers': {'rover1': {
               **identification_errors({'mass': 3.0}, {'mass': 3.15}), 'samples': 10,
               'message': 'ok'}}},
           'mapping': {'coverage': 0.5, 'scans': [{'scan': 0, 'coverage': 0.4,
                                                   'distance_m': 0.0},
                                                  {'scan': 1, 'coverage': 0.5,
                                                   'distance_m': 2.0}],
                       'scans_taken': 1, 'distance_m': 2.0, 'site_centre': [1.0, 1.0],
                       'site_half_m': 1.0},
           'insertion': {'success': False, 'reason': 'not run'},
           'phases': [{'name': 'identify', 'status': 'ok', 'reason': '', 'wall_s': 3.0,
                       'sim_s': 5.0},
                      {'name': 'map', 'status': 'failed', 'reason': 'coverage 50.0 % after '
                       '1 scans', 'wall_s': 9.0, 'sim_s': 4.0},
                      {'name': 'place', 'status': 'skipped', 'reason': 'after map failed',
                       'wall_s': None, 'sim_s': None}]}
    top = np.zeros((20, 20), np.int8)
    md, js = write_report(rep, tmp_path, top_view=top, paths={'rover1': [(0.5, 0.5),
                                                                          (1.0, 1.2)]},
                          occupied_points=np.random.default_rng(0).random((50, 3)))
    data = json.loads(js.read_text())
    assert data['insertion']['success'] is False
    assert data['identification']['mean_abs_rel_error'] == 0.05
    assert data['mapping']['coverage'] == 0.5
    for name in ('identification', 'coverage', 'map_top', 'map_3d'):
        assert (tmp_path / data['plots'][name]).stat().st_size > 1000
    text = md.read_text()
    assert '| identify | ok | mean error 5.0 % | <= 15 % | 3 | 5.0 |' in text
    assert 'coverage 50.0 % after 1 scans' in text and 'after map failed' in text
    assert format_summary(data) in text
    assert math.isfinite(data['identification']['rovers']['rover1']['params'][0]['rel_error'])
