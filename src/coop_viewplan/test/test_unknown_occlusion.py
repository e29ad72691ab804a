"""The occlusion-aware expected view (NbvConfig.unknown_occlusion = 'expected', beyond the
thesis): every sample counts with P(seen) = prod (1 - p_j) over the cells before it."""
from __future__ import annotations

import numpy as np
import pytest

from coop_viewplan import fig_3_13
from coop_viewplan.grid import (
    OccupancyGrid,
    gray_estimate,
    markov_estimate,
    obstacle_density,
    occlusion_estimate,
)
from coop_viewplan.nbv import (
    CameraState,
    NbvConfig,
    NextBestViewPlanner,
    plan_cameras,
    score_views,
)
from coop_viewplan.raycast import cast, expected_visibility, make_template


def _one_ray(n: int = 8) -> tuple[OccupancyGrid, object]:
    g = OccupancyGrid.empty((n, 3), resolution=1.0)
    g.known[:2] = True
    g.prob[:2] = 0.0
    t = make_template(ndim=2, fov_deg=1.0, depth_m=5.0, resolution=1.0, n_az=1, step_cells=0.5)
    return g, t


def test_two_unknown_cells_at_one_half_give_1_half_quarter():
    """A ray from a known free cell through unknown cells of p = 0.5: the first unknown cell is
    seen for sure, the second with 0.5, the third with 0.25 (half-cell samples: every cell is
    sampled twice and its factor enters once)."""
    g, t = _one_ray()
    c = cast(g, np.array([[0.5, 1.5]]), np.array([0.0]), None, t)
    row = c.flat[0, 0] // 3
    p = np.where(g.known, g.prob, 0.5)
    vis = expected_visibility(c, p)[0, 0]
    per_cell = {int(i): float(v) for i, v in zip(row, vis, strict=False)}
    assert per_cell[0] == per_cell[1] == 1.0                # known free
    assert per_cell[2] == pytest.approx(1.0)                 # first unknown cell
    assert per_cell[3] == pytest.approx(0.5)
    assert per_cell[4] == pytest.approx(0.25)
    # both samples of one cell carry the same probability
    for i in (2, 3, 4):
        assert np.ptp(vis[row == i]) == 0


def test_known_obstacle_still_blocks_and_stays_visible():
    g, t = _one_ray()
    g.known[3] = True
    g.prob[3] = 1.0
    c = cast(g, np.array([[0.5, 1.5]]), np.array([0.0]), None, t)
    row = c.flat[0, 0] // 3
    vis = expected_visibility(c, np.where(g.known, g.prob, 0.5))[0, 0]
    # its surface is measured if the unknown cell 2 before it is empty: P = 0.5 on its first
    # sample (cast keeps only the first blocking sample visible)
    assert vis[row == 3][0] == pytest.approx(0.5)
    assert np.all(vis[row == 3][1:] == 0) and np.all(vis[row > 3] == 0)


def test_zero_occlusion_reproduces_the_thesis_scores():
    rng = np.random.default_rng(0)
    g = OccupancyGrid.empty((50, 50), resolution=1.0)
    g.known[:, :20] = True
    g.prob[:, :20] = (rng.random((50, 20)) < 0.1).astype(np.float32)
    est = markov_estimate(g)
    t = make_template(ndim=2, fov_deg=90, depth_m=15, resolution=1.0)
    # the last two poses are outside the grid: no samples (they must not eat the others')
    pos = np.array([[10.5, 10.5], [25.5, 15.5], [40.5, 5.5], [-30.0, 5.5], [80.0, 80.0]])
    yaw = np.array([np.pi / 2, np.pi / 3, np.pi / 2, 0.0, 0.0])
    a = score_views(g, est, pos, yaw, None, t)
    assert np.all(a.known_cells[3:] == 0) and np.all(a.known_cells[:3] > 0)
    b = score_views(g, est, pos, yaw, None, t, occlusion=np.zeros(g.shape, np.float32))
    assert a.unknown_expected is None
    assert b.ni == pytest.approx(a.ni, rel=1e-5)
    assert b.unknown_cells == pytest.approx(a.unknown_cells, rel=1e-5)
    assert b.known_cells == pytest.approx(a.known_cells, rel=1e-5)
    assert b.unknown_expected == pytest.approx(a.unknown_cells, rel=1e-5)


def test_expected_occlusion_prefers_open_unknown_to_cluttered_unknown():
    """Camera in a known free strip between two unknown areas of equal size: east looks
    cluttered (estimate 0.6), west open (0.1). The plain count ties, the thesis's NI even
    prefers the cluttered side (-p log2 p is 0.44 at 0.6, 0.33 at 0.1); with the expected
    occlusion the open side wins by far."""
    n = 61
    g = OccupancyGrid.empty((n, 40), resolution=1.0)
    g.known[28:33] = True
    g.prob[28:33] = 0.0
    est = np.where(g.known, 0.0, 0.5).astype(np.float32)
    est[33:] = 0.6        # east (+x) unknown: cluttered
    est[:28] = 0.1        # west (-x) unknown: open
    t = make_template(ndim=2, fov_deg=90, depth_m=15, resolution=1.0)
    pos = np.array([[30.5, 20.5], [30.5, 20.5]])
    yaw = np.array([0.0, np.pi])              # east, west
    plain = score_views(g, est, pos, yaw, None, t)
    occl = score_views(g, est, pos, yaw, None, t, occlusion=est)
    assert plain.unknown_cells[0] == pytest.approx(plain.unknown_cells[1], rel=0.02)
    assert plain.ni[0] > plain.ni[1]                         # thesis: clutter rated higher
    assert occl.ni[1] > 2 * occl.ni[0]                       # expected: open side
    assert occl.unknown_expected[1] > 2 * occl.unknown_expected[0]
    # the thesis's cell counts are unchanged by the option
    assert occl.unknown_cells == pytest.approx(plain.unknown_cells, rel=1e-5)


def test_density_prior_far_from_the_map():
    g = OccupancyGrid.empty((60, 60), resolution=1.0)
    g.known[:10, :10] = True
    g.prob[:10, :10] = 0.0
    g.prob[:10, 0] = 1.0                                     # 10 of 100 known cells occupied
    assert obstacle_density(g) == pytest.approx(0.1)
    assert obstacle_density(OccupancyGrid.empty((3, 3), resolution=1.0)) == 0.5
    mk = occlusion_estimate(g, prior='markov')
    dn = occlusion_estimate(g, prior='density')
    assert mk[50, 50] == pytest.approx(0.5)
    assert dn[50, 50] == pytest.approx(0.1)
    assert np.array_equal(mk, gray_estimate(g))
    # known cells keep their gray value either way
    assert dn[5, 5] == 0.0 and dn[5, 0] == 1.0
    with pytest.raises(ValueError):
        occlusion_estimate(g, prior='flat')


def test_config_rejects_unknown_options():
    with pytest.raises(ValueError):
        NbvConfig(unknown_occlusion='all')
    with pytest.raises(ValueError):
        NbvConfig(occlusion_prior='uniform')
    assert NbvConfig().unknown_occlusion == 'none'


@pytest.mark.parametrize('prior', ['markov', 'density'])
def test_planner_with_expected_occlusion(prior):
    g = OccupancyGrid.empty((60, 60), resolution=1.0)
    g.known[20:40, 20:40] = True
    g.prob[20:40, 20:40] = 0.0
    g.prob[20:40, 20] = 1.0
    cfg = NbvConfig(unknown_occlusion='expected', occlusion_prior=prior, n_positions=20,
                    depth_m=10)
    planner = NextBestViewPlanner(cfg)
    cams = [CameraState(g.to_world(np.array([30, 30]))),
            CameraState(g.to_world(np.array([32, 30])))]
    ds = plan_cameras(planner, g, cams, strategy='max_information',
                      rng=np.random.default_rng(0))
    for d in ds:
        assert d.scores.unknown_expected is not None
        assert np.all(d.scores.unknown_expected <= d.scores.unknown_cells + 1e-6)
        assert np.isfinite(d.rating).all()
    # claimed cells: those the first view sees with P >= 0.5, a subset of its unoccluded view
    occ = planner.occlusion_map(g)
    strict = planner.expected_cells(g, ds[0], occlusion=occ)
    loose = NextBestViewPlanner(NbvConfig(n_positions=20, depth_m=10)).expected_cells(g, ds[0])
    assert strict.any() and not np.any(strict & ~loose)


def test_fig_3_13_cli_takes_the_option(tmp_path, capsys):
    rc = fig_3_13.main(['--seeds', '1', '--scans', '8', '--resolution-m', '2.0',
                        '--candidates', '20', '--strategies', 'max_information',
                        '--unknown-occlusion', 'expected', '--occlusion-prior', 'density'])
    assert rc == 0
    assert 'unknown_occlusion=expected/density' in capsys.readouterr().out


@pytest.mark.parametrize('ndim', [2, 3])
def test_compact_visibility_equals_the_dense_one(ndim):
    """score_views' per-ray prefix form (visible samples only) is expected_visibility."""
    from coop_viewplan.raycast import ray_prefix_visibility, transmission_table
    rng = np.random.default_rng(1)
    shape = (40, 40) if ndim == 2 else (30, 30, 8)
    g = OccupancyGrid.empty(shape, resolution=1.0)
    g.known[:] = rng.random(shape) < 0.6
    g.prob[:] = (rng.random(shape) < 0.1).astype(np.float32)
    stop = np.where(g.known, g.prob, rng.random(shape)).astype(np.float32)
    t = make_template(ndim=ndim, fov_deg=80, depth_m=12, resolution=1.0)
    m = 6
    pos = rng.uniform(5, 25, (m, ndim))
    if ndim == 3:
        pos[:, 2] = rng.uniform(2, 6, m)
    c = cast(g, pos, rng.uniform(0, 2 * np.pi, m),
             rng.uniform(-0.3, 0.3, m) if ndim == 3 else None, t)
    dense = expected_visibility(c, stop)
    mi, ri, si = np.nonzero(c.visible)
    comp = ray_prefix_visibility(c.flat[mi, ri, si], si, transmission_table(stop))
    assert comp == pytest.approx(dense[mi, ri, si], rel=1e-4, abs=1e-6)
    assert np.all(dense[~c.visible] == 0)
    # through score_views: the same NI as with the dense visibility
    from coop_viewplan.nbv import expected_information
    est = markov_estimate(g)
    a = expected_information(g, est, c, visibility=dense)
    b = expected_information(g, est, c, transmission=transmission_table(stop))
    assert b.ni == pytest.approx(a.ni, rel=1e-4)
    assert b.unknown_expected == pytest.approx(a.unknown_expected, rel=1e-4)
