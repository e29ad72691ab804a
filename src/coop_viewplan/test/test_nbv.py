"""Unit tests of the next-best-view core (Eq. 3-11..3-15, §3.3.1 strategies)."""
from __future__ import annotations

import itertools

import numpy as np
import pytest

from coop_common.rover_geometry import CAMERA_FROM_BASE_M
from coop_viewplan.grid import MapError, OccupancyGrid, markov_estimate
from coop_viewplan.nbv import (
    STRATEGIES,
    CameraState,
    NbvConfig,
    NextBestViewPlanner,
    PlanningError,
    Traversal,
    binary_entropy,
    configuration_distance,
    keep_out_cells,
    make_strategy,
    max_information,
    occupancy_weight,
    plan_cameras,
    rating_function,
    score_views,
    team_route,
)
from coop_viewplan.raycast import cast, make_template


def _known_free_grid(n: int = 40) -> OccupancyGrid:
    g = OccupancyGrid.empty((n, n), resolution=1.0)
    g.known[:] = True
    g.prob[:] = 0.0
    return g


def test_configuration_distance_eq_3_11():
    d = configuration_distance(np.array([0, 0, 0, 0, 0.0]), np.array([[3, 4, 0, 0, 0.0]]),
                               (1, 1, 1, 0, 0))
    assert d[0] == pytest.approx(5.0)
    # angles wrap: yaw 350 deg vs 10 deg is 20 deg apart, weight 1
    d = configuration_distance(np.array([0, 0, 0, np.radians(10), 0]),
                               np.array([[0, 0, 0, np.radians(350), 0]]),
                               (0, 0, 0, 1, 0))
    assert d[0] == pytest.approx(np.radians(20))


def test_rating_function_eq_3_15():
    rf = rating_function(np.array([10.0]), np.array([2.0]), np.array([0.5]), k=1.5, n=2)
    assert rf[0] == pytest.approx((10 - 1.5 * 4) * 0.5)


def test_eq_3_11_weights_are_one_by_default():
    """§3.2.4 (iii): "alpha_i = 1 for this thesis" - the camera's angles count too (m, rad)."""
    assert NbvConfig().alpha == (1.0, 1.0, 1.0, 1.0, 1.0)
    d = configuration_distance(np.array([0, 0, 0, 0, 0.0]),
                               np.array([[3, 4, 0, np.pi / 2, 0.0]]), NbvConfig().alpha)
    assert d[0] == pytest.approx(np.sqrt(25 + (np.pi / 2) ** 2))


def test_ni_premultiplier_is_minus_p_log_p_as_written():
    """§3.2.4: q_k log2 q_k "is premultiplied by -p_k log2 p_k"; 'binary' stays an option."""
    assert NbvConfig().entropy_weight == 'plogp'
    w = occupancy_weight(np.array([0.0, 1.0, 0.5, 0.25]))
    assert w.tolist() == pytest.approx([0, 0, 0.5, 0.5])
    assert occupancy_weight(np.array([0.5]), weight='binary')[0] == pytest.approx(1.0)
    with pytest.raises(ValueError):
        occupancy_weight(np.array([0.5]), weight='shannon')


@pytest.mark.parametrize('weight', ['plogp', 'binary'])
def test_k_scale_is_the_ni_of_a_fully_unknown_view(weight):
    """K's reference (k_rel x NI of an unknown view per depth) uses the same premultiplier."""
    g = OccupancyGrid.empty((60, 60), resolution=1.0)
    g.known[0, 0] = True           # an all-unknown map cannot be planned on; far from the view
    g.prob[0, 0] = 0.0
    t = make_template(ndim=2, fov_deg=90, depth_m=10, resolution=1.0)
    s = score_views(g, np.full(g.shape, 0.5), np.array([[30.5, 30.5]]), np.array([0.0]), None,
                    t, weight=weight)
    assert s.ni[0] == pytest.approx(max_information(t, weight=weight), rel=1e-3)
    assert max_information(t, weight='plogp') == pytest.approx(
        0.5 * max_information(t, weight='binary'))


def test_binary_entropy_limits():
    assert binary_entropy(np.array([0.0, 1.0, 0.5])).tolist() == pytest.approx([0, 0, 1])


def test_template_counts_frustum_cells():
    # 90 deg, 10 m quarter disc: pi r^2 / 4 = 78.5 cells of 1 m^2
    t = make_template(ndim=2, fov_deg=90, depth_m=10, resolution=1.0)
    assert t.frustum_cells == pytest.approx(np.pi * 100 / 4, rel=0.02)
    t3 = make_template(ndim=3, fov_deg=60, depth_m=5, resolution=0.5, n_az=20, n_el=15,
                       vfov_deg=45)
    a, e = np.radians(60), np.radians(45)
    solid = a * 2 * np.sin(e / 2)
    assert t3.frustum_cells == pytest.approx(solid * 5 ** 3 / 3 / 0.125, rel=0.03)


def test_known_obstacle_occludes_and_first_hit_visible():
    g = _known_free_grid()
    g.prob[20, :] = 1.0            # a wall across x = 20
    t = make_template(ndim=2, fov_deg=10, depth_m=15, resolution=1.0)
    c = cast(g, np.array([[10.5, 20.5]]), np.array([0.0]), None, t)
    seen = np.zeros(g.prob.size, bool)
    seen[c.flat[c.visible]] = True
    seen = seen.reshape(g.shape)
    assert seen[20, 20] and seen[15, 20]
    assert not seen[21:, :].any()


def test_ni_zero_when_all_known_and_grows_with_unknown():
    g = _known_free_grid()
    est = markov_estimate(g)
    t = make_template(ndim=2, fov_deg=90, depth_m=10, resolution=1.0)
    pos = np.array([[20.5, 20.5]])
    s0 = score_views(g, est, pos, np.array([0.0]), None, t)
    assert s0.ni[0] == pytest.approx(0.0, abs=1e-12)
    nis = []
    for edge in (28, 25, 22):   # more and more unknown ahead of the camera
        h = _known_free_grid()
        h.known[edge:, :] = False
        s = score_views(h, markov_estimate(h), pos, np.array([0.0]), None, t)
        nis.append(s.ni[0])
    assert 0 < nis[0] < nis[1] < nis[2]
    # occluding the unknown region with a known wall lowers NI (§3.2.4)
    h = _known_free_grid()
    h.known[22:, :] = False
    h.known[21, :] = True
    h.prob[21, 15:26] = 1.0
    s = score_views(h, markov_estimate(h), pos, np.array([0.0]), None, t)
    assert s.ni[0] < nis[2]


def test_markov_estimate_leans_towards_neighbours():
    g = OccupancyGrid.empty((30, 30), resolution=1.0)
    g.known[:10] = True
    g.prob[:10] = 0.0
    g.known[20:] = True
    g.prob[20:] = 1.0
    est = markov_estimate(g, iterations=20)
    assert est[10, 5] < 0.5 < est[19, 5]
    assert est[0, 0] == 0.0 and est[29, 0] == 1.0


def test_from_sparse_and_empty_map():
    keys = np.array([[0, 0, 0], [2, 1, 0], [-1, 0, 1]])
    g = OccupancyGrid.from_sparse(keys, np.array([0.1, 0.9, 0.0]), resolution=0.5)
    assert g.shape == (4, 2, 2)
    assert g.known.sum() == 3 and g.prob[3, 1, 0] == pytest.approx(0.9)
    assert np.allclose(g.origin, [-0.5, 0.0, 0.0])
    with pytest.raises(MapError):
        OccupancyGrid.from_sparse(np.zeros((0, 3)), np.zeros(0), resolution=0.1)
    planner = NextBestViewPlanner()
    with pytest.raises(MapError):
        planner.plan(OccupancyGrid.empty((10, 10), resolution=1.0),
                     CameraState(np.array([5.0, 5.0])), strategy='random',
                     rng=np.random.default_rng(0))


def test_unknown_strategy_rejected():
    with pytest.raises(ValueError, match='unknown strategy'):
        make_strategy('teleport')


def _half_known_world():
    g = OccupancyGrid.empty((60, 60), resolution=1.0)
    g.known[:, :30] = True
    g.prob[:, :30] = 0.0
    g.prob[25:35, 10:12] = 1.0          # a known obstacle
    return g


@pytest.mark.parametrize('name', STRATEGIES)
def test_every_strategy_returns_free_reachable_view(name):
    g = _half_known_world()
    planner = NextBestViewPlanner(NbvConfig(fov_deg=90, depth_m=15, n_positions=40))
    d = planner.plan(g, CameraState(np.array([5.5, 5.5])), strategy=name,
                     rng=np.random.default_rng(1))
    cell = g.to_index(d.position)
    assert g.known[tuple(cell)] and g.prob[tuple(cell)] < 0.05
    assert np.isfinite(d.path_length)
    assert d.candidates.collision_p[d.index] < 0.05


def test_max_information_looks_at_the_unknown():
    g = _half_known_world()
    planner = NextBestViewPlanner(NbvConfig(fov_deg=90, depth_m=15, n_positions=60))
    d = planner.plan(g, CameraState(np.array([30.5, 20.5])), strategy='max_information',
                     rng=np.random.default_rng(2))
    # unknown is at +y: the chosen heading points there (within the 90 deg FOV)
    assert abs(((d.yaw - np.pi / 2) + np.pi) % (2 * np.pi) - np.pi) <= np.radians(45) + 1e-9
    assert d.rating[d.index] == pytest.approx(d.rating.max())


def test_no_view_is_offered_beside_a_teammate():
    """The planner's best view, with a teammate standing there (or sent there), moves out of the
    teammate's keep-out (as team_route would refuse the goal); a team all round the rover
    leaves no view."""
    g = _half_known_world()
    planner = NextBestViewPlanner(NbvConfig(fov_deg=90, depth_m=15, n_positions=60))
    cam = CameraState(np.array([30.5, 20.5]))
    best = planner.plan(g, cam, strategy='max_information', rng=np.random.default_rng(2))
    keep = keep_out_cells(planner.config.clearance_m, g.resolution) + \
        int(np.ceil(CAMERA_FROM_BASE_M / g.resolution))
    mate = best.position[:2]
    d = planner.plan(g, cam, strategy='max_information', rng=np.random.default_rng(2),
                     teammates=[mate])
    assert np.hypot(*(d.position[:2] - mate)) > keep * g.resolution
    # none of the candidates scored lies in the keep-out
    assert np.hypot(*(d.candidates.positions[:, :2] - mate).T).min() > keep * g.resolution
    team = [(x + 0.5, y + 0.5) for x in range(0, 60, keep) for y in range(0, 60, keep)]
    with pytest.raises(PlanningError, match='no free reachable candidate'):
        planner.plan(g, cam, strategy='max_information', rng=np.random.default_rng(2),
                     teammates=team)


def test_no_free_candidate_raises():
    g = OccupancyGrid.empty((20, 20), resolution=1.0)
    g.known[:] = True
    g.prob[:] = 1.0
    with pytest.raises(PlanningError):
        NextBestViewPlanner().plan(g, CameraState(np.array([10.5, 10.5])),
                                   strategy='max_information', rng=np.random.default_rng(0))


def test_two_cameras_on_one_map_look_at_different_regions():
    g = OccupancyGrid.empty((80, 40), resolution=1.0)
    g.known[30:50, :] = True
    g.prob[30:50, :] = 0.0
    planner = NextBestViewPlanner(NbvConfig(fov_deg=75, depth_m=10, n_positions=80))
    cams = [CameraState(np.array([40.5, 20.5])), CameraState(np.array([40.5, 22.5]))]
    d1, d2 = plan_cameras(planner, g, cams, strategy='max_information',
                          rng=np.random.default_rng(3))
    e1, e2 = planner.expected_cells(g, d1), planner.expected_cells(g, d2)
    overlap = (e1 & e2 & ~g.known).sum() / max(1, (e1 & ~g.known).sum())
    assert overlap < 0.2


def test_3d_scoring_sees_unknown_above_known_floor():
    g = OccupancyGrid.empty((40, 40, 20), resolution=0.25)
    g.known[:, :, :4] = True
    g.prob[:, :, :4] = 0.0
    g.prob[:, :, 0] = 1.0               # the ground
    est = markov_estimate(g)
    t = make_template(ndim=3, fov_deg=75, depth_m=4, resolution=0.25, n_az=16, n_el=12)
    pos = np.array([[5.0, 5.0, 0.6], [5.0, 5.0, 0.6]])
    s = score_views(g, est, pos, np.array([0.0, 0.0]), np.array([0.6, -0.6]), t)
    # looking down (positive pitch) sees the known floor, looking up sees the unknown
    assert s.ni[1] > s.ni[0]
    assert s.unknown_cells[0] < 0.5 * s.unknown_cells[1]


def test_path_distance_exceeds_straight_line_around_a_wall():
    g = _known_free_grid(40)
    g.known[:, 36:] = False
    g.prob[20, 0:33] = 1.0               # a wall with a gap at the top
    cam = CameraState(np.array([15.5, 5.5]))
    res = {}
    for metric in ('configuration', 'path'):
        planner = NextBestViewPlanner(NbvConfig(n_positions=400, distance_metric=metric))
        d = planner.plan(g, cam, strategy='max_unmapped', rng=np.random.default_rng(5))
        res[metric] = d.candidates
    c, p = res['configuration'], res['path']
    assert np.array_equal(c.positions, p.positions)      # same seeded candidate set
    straight = np.hypot(*(c.positions - cam.position).T)
    turn = (c.yaw - cam.yaw + np.pi) % (2 * np.pi) - np.pi     # alpha_i = 1 for yaw too
    assert c.distance == pytest.approx(np.hypot(straight, turn))
    assert p.distance == pytest.approx(np.hypot(p.path_length, turn))
    behind = c.positions[:, 0] > 21
    assert behind.sum() > 10
    assert np.all(p.distance[behind] > c.distance[behind] + 1.0)


def test_free_footprint_lets_a_rover_leave_its_unseen_footprint():
    """A rover whose cameras never saw the ground it stands on: without free_footprint no
    candidate is reachable; with it, the known free space ahead is."""
    res = 0.1
    prob = np.full((60, 60), 0.5)
    known = np.zeros((60, 60), bool)
    prob[:, 20:] = 0.01          # seen free ahead (+y), from 0.5 m beyond the rover
    known[:, 20:] = True
    grid = OccupancyGrid(prob, known, resolution=res, origin=np.zeros(2))
    planner = NextBestViewPlanner(NbvConfig(fov_deg=75.0, depth_m=3.0, clearance_m=0.5))
    cam = CameraState(position=np.array([3.0, 1.5]), yaw=np.pi / 2)
    with pytest.raises(PlanningError):
        planner.plan(grid, cam, strategy='max_information', rng=np.random.default_rng(0))
    d = planner.plan(grid, cam, strategy='max_information', rng=np.random.default_rng(0),
                     free_footprint=True)
    assert np.isfinite(d.candidates.path_length[d.index])
    assert d.candidates.collision_p[d.index] < planner.config.p_empty


def test_raster_sweeps_headings_then_moves_on():
    g = _known_free_grid(40)
    planner = NextBestViewPlanner(NbvConfig(fov_deg=90, depth_m=10, raster_headings=4))
    cam = CameraState(np.array([2.5, 2.5]))
    rng = np.random.default_rng(0)
    cells, yaws = [], []
    for _ in range(6):
        d = planner.plan(g, cam, strategy='raster', rng=rng)
        cam.position, cam.yaw = d.position.copy(), d.yaw
        cam.visited.append(g.to_index(cam.position))
        cells.append(tuple(g.to_index(d.position)))
        yaws.append(d.yaw)
    # a move, three more headings 90 deg apart at the same place, then the next location
    assert cells[0] == cells[1] == cells[2] == cells[3] != cells[4]
    steps = np.diff(np.unwrap(yaws[:4]))
    assert steps == pytest.approx([np.pi / 2] * 3)
    assert cells[4] == cells[5]


def test_near_fraction_takes_the_closest_candidates_first():
    g = _known_free_grid(40)
    cam = CameraState(np.array([20.5, 20.5]))
    far = NextBestViewPlanner(NbvConfig(n_positions=20)).plan(
        g, cam, strategy='max_unmapped', rng=np.random.default_rng(4))
    near = NextBestViewPlanner(NbvConfig(n_positions=20, near_fraction=0.5)).plan(
        g, cam, strategy='max_unmapped', rng=np.random.default_rng(4))
    pl = near.candidates.path_length.reshape(20, -1)[:, 0]     # one row per position
    assert np.all(pl[:10] <= 2.9)                 # the 10 nearest cells: within 2 cells
    assert np.median(far.candidates.path_length) > 5.0


def test_ni_floor_stops_the_zero_information_stay():
    """With a large K every informative view rates below standing still (NI 0, d 0, RF 0):
    the plain argmax of Eq. 3-15 stays; with ni_floor only views with at least that share of
    the decision's best NI compete."""
    g = OccupancyGrid.empty((80, 80), resolution=1.0)
    g.known[10:70, 10:70] = True
    g.prob[10:70, 10:70] = 0.0                  # a known empty square, unknown around it
    cam = CameraState(g.to_world(np.array([40, 40])))   # 20 cells from unknown, depth 10
    picks = {}
    for floor in (0.0, 0.25):
        cfg = NbvConfig(n_positions=40, depth_m=10, k_rel=5.0, near_fraction=0.5,
                        ni_floor=floor)
        d = NextBestViewPlanner(cfg).plan(g, cam, strategy='max_information',
                                          rng=np.random.default_rng(0))
        picks[floor] = (d.scores.ni[d.index], d.scores.ni.max(), d.candidates.distance[d.index])
    ni, best, dist = picks[0.0]
    assert ni == 0.0 and dist == 0.0 and best > 0    # the thesis's argmax: stay, learn nothing
    ni, best, dist = picks[0.25]
    assert ni >= 0.25 * best and dist > 0
    with pytest.raises(ValueError, match='ni_floor'):
        NbvConfig(ni_floor=1.0)


def test_config_options_are_enums_checked_at_construction():
    from coop_viewplan.nbv import DistanceMetric, NbvConfig, UnknownOcclusion

    cfg = NbvConfig(unknown_occlusion='expected', distance_metric='path')
    assert cfg.unknown_occlusion is UnknownOcclusion.EXPECTED
    assert cfg.distance_metric is DistanceMetric.PATH
    with pytest.raises(ValueError, match=r"reach_model must be one of \['known', 'evidence'\]"):
        NbvConfig(reach_model='nearby')
    assert NbvConfig.thesis() == NbvConfig()
    best = NbvConfig.best_measured()
    assert (best.unknown_occlusion, best.distance_metric, best.k_rel, best.ni_floor,
            best.near_fraction) == ('expected', 'path', 0.8, 0.25, 0.5)
    assert NbvConfig.best_measured(k_rel=0.1).k_rel == 0.1


def test_unknown_modes_are_refused_naming_the_allowed_values(tmp_path):
    """Every mode of the cores is taken as its StrEnum member where it enters; any other value
    is an OptionError (a ViewplanError and a ValueError) naming the choices, never a default
    branch."""
    from coop_viewplan.errors import OptionError, ViewplanError
    from coop_viewplan.explore import make_world
    from coop_viewplan.grid import gray_estimate, occlusion_estimate
    from coop_viewplan.nbv import STRATEGY_CLASSES, StrategyName, expected_information

    assert issubclass(OptionError, ViewplanError) and issubclass(OptionError, ValueError)
    g = _known_free_grid(10)
    t = make_template(ndim=2, fov_deg=60, depth_m=4.0, resolution=1.0, n_az=8)
    cases = [
        (lambda: occupancy_weight(np.array([0.5]), weight='shannon'),
         r"entropy_weight must be one of \['plogp', 'binary'\], got 'shannon'"),
        (lambda: gray_estimate(g, free_gray='zero'),
         r"free_gray must be one of \['empty', 'occupancy'\], got 'zero'"),
        (lambda: occlusion_estimate(g, prior='flat'),
         r"prior must be one of \['markov', 'density'\], got 'flat'"),
        (lambda: expected_information(g, g.prob, cast(g, np.array([[5.5, 5.5]]), np.zeros(1),
                                                      None, t), measure='jpeg'),
         r"measure must be one of \['histogram', 'predictor5'\], got 'jpeg'"),
        (lambda: make_strategy('teleport'),
         r"unknown strategy 'teleport': strategy must be one of \['random', 'raster', "
         r"'max_unmapped', 'min_mapped', 'max_information', 'frontier'\]"),
        (lambda: NbvConfig(distance_metric='manhattan'),
         r"distance_metric must be one of \['configuration', 'path'\], got 'manhattan'"),
        (lambda: make_world('mars', seed=0),
         r"unknown world 'mars': one of \['unstructured', 'rooms'\] or an existing .png"),
        (lambda: make_world(tmp_path / 'mars.png', seed=0), r"unknown world '.*mars.png'"),
    ]
    for call, message in cases:
        with pytest.raises(OptionError, match=message):
            call()
    # every strategy name has its class, each named by its member
    assert set(STRATEGY_CLASSES) == set(StrategyName)
    assert all(make_strategy(s.value).name is s for s in StrategyName)


def _open_field(n: int = 60, res: float = 0.1) -> tuple[OccupancyGrid, Traversal]:
    """An n x n field of known free ground (0.1 m cells), every cell navigable."""
    g = OccupancyGrid.empty((n, n), resolution=res)
    g.known[:] = True
    g.prob[:] = 0.0
    nav = np.ones((n, n), bool)
    return g, Traversal(nav, np.zeros((n, n)), nav.copy())


def test_team_route_leaves_a_teammate_standing_beside_the_rover():
    """Two rovers side by side (0.1 m apart: the mission's map scans once put them there): the
    teammate's keep-out (0.7 m) would wall the rover's own footprint in; it shrinks to leave it
    a way out, and the route keeps clear of the teammate beyond its start."""
    g, trav = _open_field()
    route = team_route(trav, g, (1.0, 1.0), (5.0, 5.0), others=[(1.1, 1.0)], clearance_m=0.5)
    assert np.allclose(route[-1], (5.0, 5.0))
    # a teammate 2 m off, or 0.6 m off ahead: the route goes round its keep-out (past the
    # rover's own footprint, 0.5 m)
    for start in ((1.0, 3.0), (2.4, 3.0)):
        route = team_route(trav, g, start, (5.0, 3.0), others=[(3.0, 3.0)], clearance_m=0.5)
        pts = np.vstack([start, *route])
        dense = np.vstack([np.linspace(a, b, 20) for a, b in itertools.pairwise(pts)])
        far = np.hypot(*(dense - start).T) > 0.5
        assert np.hypot(*(dense[far] - (3.0, 3.0)).T).min() >= 0.5, start


def test_team_route_drives_past_where_a_leaving_teammate_stands_not_to_it():
    """`moving`: a teammate that leaves as the rover drives keeps the path off it, not the
    goal; `others` keeps both."""
    g, trav = _open_field()
    route = team_route(trav, g, (1.0, 3.0), (4.0, 3.0), moving=[(2.5, 3.0), (4.3, 3.0)],
                       clearance_m=0.5)
    assert np.allclose(route[-1], (4.0, 3.0))
    pts = np.vstack([(1.0, 3.0), *route])
    assert np.abs(pts[:, 1] - 3.0).max() > 0.5             # round the one on the way
    with pytest.raises(PlanningError):
        team_route(trav, g, (1.0, 3.0), (4.0, 3.0), others=[(4.3, 3.0)], clearance_m=0.5)


def test_team_route_on_the_mission_s_3d_grid_and_off_it():
    """The mission plans on a 3-D grid (its ground plane the traversal's); a start or goal
    off the grid is a PlanningError, not an index error."""
    g = OccupancyGrid.empty((60, 60, 4), resolution=0.1)
    g.known[:] = True
    g.prob[:] = 0.0
    nav = np.ones((60, 60), bool)
    trav = Traversal(nav, np.zeros((60, 60)), nav.copy())
    route = team_route(trav, g, (1.02, 1.03), (4.0, 2.0), clearance_m=0.5)
    assert np.allclose(route[0], (1.05, 1.05)) and np.allclose(route[-1], (4.0, 2.0))
    for start, goal in (((1.0, 1.0), (6.5, 1.0)), ((-0.5, 1.0), (2.0, 2.0))):
        with pytest.raises(PlanningError, match='off the map'):
            team_route(trav, g, start, goal, clearance_m=0.5)


def test_team_route_refuses_a_goal_beside_a_teammate():
    g, trav = _open_field()
    with pytest.raises(PlanningError, match=r'within 0\.7 m of another rover'):
        team_route(trav, g, (1.0, 1.0), (4.0, 4.0), others=[(4.3, 4.2)], clearance_m=0.5)


def test_team_route_snaps_to_a_reachable_cell_not_a_speck():
    """A goal inside an obstacle's clearance: the route ends on the nearest navigable cell
    the rover can reach, never on a free speck walled off from it, and the last leg goes on
    straight (or not, without last_leg)."""
    g, trav = _open_field()
    nav = trav.navigable.copy()
    nav[35:52, 35:52] = False            # an obstacle's clearance round the goal (4.35, 4.35)
    nav[42, 42] = True                    # a speck inside it, next to the goal
    trav = Traversal(nav, trav.collision_p, trav.candidate)
    end = team_route(trav, g, (1.0, 1.0), (4.35, 4.35), clearance_m=0.2, last_leg=False)[-1]
    assert np.hypot(*(end - (4.25, 4.25))) > 0.5          # not the speck's cell centre
    assert nav[tuple(g.to_index(end))]
    assert np.allclose(team_route(trav, g, (1.0, 1.0), (4.35, 4.35), clearance_m=0.2)[-1],
                       (4.35, 4.35))


def test_team_route_keeps_off_blocked_cells_even_in_its_own_footprint():
    """`blocked`: the cells whoever drives the route refuses (the drivers' map/grid); the
    rover's own footprint is freed on the planning grid, not of these."""
    g, trav = _open_field()
    blocked = np.zeros(g.shape, bool)
    blocked[12:40, 13] = True               # a wall at y 1.3-1.4 m, x 1.2-4.0 m
    route = team_route(trav, g, (2.0, 1.0), (2.0, 2.0), clearance_m=0.5, blocked=blocked)
    pts = np.vstack([(2.0, 1.0), *route])
    dense = np.vstack([np.linspace(a, b, 40) for a, b in itertools.pairwise(pts)])
    assert not blocked[tuple(g.to_index(dense).T)].any()
    assert pts[:, 0].min() < 1.2                   # round the wall's end, not through it
