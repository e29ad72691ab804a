"""NI with App. C's predictor 5 (nbv.predictor5_codes, expected_information(measure=...))."""
from __future__ import annotations

import numpy as np
import pytest

from coop_viewplan.grid import OccupancyGrid
from coop_viewplan.imageinfo import residual
from coop_viewplan.nbv import InfoLookup, expected_information, predictor5_codes
from coop_viewplan.raycast import Cast, RayTemplate


def test_residuals_by_hand():
    n = 10
    level = np.array([[[1, 2, 3], [2, 3, 4], [3, 4, 6]]])      # a plane but the last sample
    vis = np.ones(level.shape, bool)
    codes, n_res = predictor5_codes(level, vis, n)             # all known (code = level)
    assert n_res == 37
    resid = codes - 2 * (n - 1)
    # first ray and first sample keep their levels; inside, I - (W + N - NW)
    np.testing.assert_array_equal(resid[0], [[1, 2, 3], [2, 0, 0], [3, 0, 1]])
    # the same as App. C's residual of the 2-D image
    np.testing.assert_array_equal(resid[0], residual(level[0], 5))
    # a hidden neighbour: the sample keeps its own level; unknown cells go to the upper half
    vis[0, 0, 1] = False
    unk = level + n * np.array([[[0, 0, 0], [0, 1, 0], [0, 0, 0]]])
    codes, _ = predictor5_codes(unk, vis, n)
    assert codes[0, 1, 1] == n_res + 3 + 2 * (n - 1)          # unknown, raw level 3
    assert codes[0, 1, 2] == 4 + 2 * (n - 1)                   # its NW is hidden: raw level
    assert codes[0, 2, 2] == 1 + 2 * (n - 1)                   # 6 - (4 + 4 - 3), all seen


def _view(levels: np.ndarray) -> tuple[OccupancyGrid, np.ndarray, Cast]:
    """One pose whose R x S samples see one distinct unknown cell each, at gray `levels`."""
    r, s = levels.shape
    p = (levels.reshape(-1) + 0.5) / 10.0
    grid = OccupancyGrid(np.zeros((r * s, 1), np.float32), np.zeros((r * s, 1), bool),
                         resolution=1.0, origin=np.zeros(2))
    tpl = RayTemplate(np.tile([[1.0, 0.0]], (r, 1)), np.arange(s) + 0.5,
                      np.ones((r, s), np.float32), float(s), 1.0)
    cast = Cast(np.arange(r * s).reshape(1, r, s), np.ones((1, r, s), bool), tpl)
    return grid, p.reshape(r * s, 1), cast


def test_predictable_view_carries_less_information():
    """Same gray-level histogram, so the same NI by Eq. 3-13's histogram; predictor 5 rates the
    smooth (predictable) view below the scrambled one, which is App. C's point."""
    rng = np.random.default_rng(0)
    smooth = np.add.outer(np.arange(4), np.arange(5)) % 10          # a ramp: I = r + s
    scrambled = rng.permutation(smooth.reshape(-1)).reshape(smooth.shape)
    ni = {}
    for name, lv in (('smooth', smooth), ('scrambled', scrambled)):
        grid, est, cast = _view(lv)
        lk = InfoLookup.build(grid, est, n_gray=10)
        ni[name] = {m: float(expected_information(grid, est, cast, lookup=lk, n_shells=1,
                                                  measure=m).ni[0])
                    for m in ('histogram', 'predictor5')}
    assert ni['smooth']['histogram'] == pytest.approx(ni['scrambled']['histogram'])
    assert ni['smooth']['predictor5'] < 0.8 * ni['scrambled']['predictor5']


def test_known_empty_view_has_no_information_and_bad_measure_fails():
    grid, est, cast = _view(np.zeros((3, 4), int))
    grid.known[:] = True
    est[:] = 0.0
    lk = InfoLookup.build(grid, est, n_gray=10)
    assert expected_information(grid, est, cast, lookup=lk, measure='predictor5').ni[0] == 0.0
    with pytest.raises(ValueError, match='measure'):
        expected_information(grid, est, cast, lookup=lk, measure='jpeg')
