"""Constraints (i)/(ii) of §3.2.4 on a live-style stereo map ('evidence' reach model): hand-built
3-D maps, and the map fused from the sample bag with the node's settings."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from coop_viewplan.grid import OccupancyGrid
from coop_viewplan.nbv import (
    CameraState,
    NbvConfig,
    NextBestViewPlanner,
    PlanningError,
    geodesic_distance,
)

RES = 0.1
FREE, WEAK, HIT, CLAMP = 0.12, 0.4, 0.7, 0.971     # coop_mapping's OctoMap-model levels
CARVED = 0.7 * 0.4 / (0.7 * 0.4 + 0.3 * 0.6)       # one hit, then one ray through: 0.61


def _room(nx: int = 60, ny: int = 40, nz: int = 12) -> OccupancyGrid:
    """6 m x 4 m x 1.2 m at 0.1 m: the ground layer occupied, everything above seen free."""
    prob = np.full((nx, ny, nz), FREE, np.float32)
    prob[:, :, 0] = CLAMP
    return OccupancyGrid(prob, np.ones(prob.shape, bool), resolution=RES, origin=np.zeros(3))


def _planner(**kw) -> NextBestViewPlanner:
    cfg = dict(fov_deg=75.0, depth_m=4.0, n_az=12, n_el=9, step_cells=1.0, n_positions=200,
               camera_height_m=0.8, clearance_m=0.5, p_empty=0.2, reach_model='evidence')
    cfg.update(kw)
    return NextBestViewPlanner(NbvConfig(**cfg))


def _reach(planner: NextBestViewPlanner, grid: OccupancyGrid, start=(5, 20)) -> np.ndarray:
    return geodesic_distance(planner.traversability(grid).navigable, start, resolution=RES)


def test_speckle_does_not_block_a_real_wall_does():
    planner = _planner()
    g = _room()
    g.prob[:, :, 9:] = 0.5
    g.known[:, :, 9:] = False                 # above the camera: never seen
    g.prob[30, :, 4] = HIT                     # a line of lone speckle voxels across x = 3 m
    t = planner.traversability(g)
    assert t.navigable.all()
    assert np.isfinite(_reach(planner, g)[50, 20])
    g.prob[30, :, 2:8] = HIT                   # a real wall: the whole slab seen occupied
    t = planner.traversability(g)
    assert not t.navigable[25:36].any()       # the wall and the clearance either side
    assert np.isinf(_reach(planner, g)[50, 20])
    d = planner.plan(g, CameraState(np.array([0.55, 2.05, 0.8])), strategy='max_information',
                     rng=np.random.default_rng(0))
    assert np.all(d.candidates.positions[:, 0] < 2.5)     # nothing behind the wall offered
    # two occupied voxels in a column block it; so does a single one at the occupancy clamp
    for column in ((HIT, HIT), (CLAMP,)):
        h = _room()
        h.prob[30, 20, 3:3 + len(column)] = column
        assert not planner.traversability(h).navigable[30, 20]
        # with 3 votes needed, two hits pass; the clamp still blocks
        assert _planner(occupied_voxels=3).traversability(h).navigable[30, 20] == (
            len(column) == 2)


def test_hits_a_later_ray_crossed_do_not_block():
    """Far stereo points mis-ranged in front of a surface are crossed by nearer rays: a column
    of such voxels (P 0.61) is no obstacle evidence at the default occupied_p 0.7; uncarved
    hits (0.7) and a column seen twice (0.84) are; occupied_p 0.5 restores the old rule."""
    planner = _planner()
    assert planner.config.occupied_p == 0.7
    for level, blocks in ((CARVED, False), (HIT, True), (0.84, True)):
        h = _room()
        h.prob[30, 20, 2:8] = level
        assert planner.traversability(h).navigable[30, 20] == (not blocks), level
    h = _room()
    h.prob[30, 20, 2:8] = CARVED
    assert not _planner(occupied_p=0.5).traversability(h).navigable[30, 20]
    for bad in (0.4, 1.2):
        with pytest.raises(ValueError, match='occupied_p'):
            NbvConfig(occupied_p=bad)


def test_candidate_inside_an_obstacle_is_rejected():
    planner = _planner()
    g = _room()
    g.prob[25:35, 15:25, 1:10] = CLAMP        # a 1 m x 1 m box, 0.9 m tall
    g.prob[45, 30, 8] = CLAMP                 # something hanging at the camera's height
    t = planner.traversability(g)
    assert not t.candidate[22:38, 12:28].any()            # box + clearance (a disk)
    assert t.candidate[18, 20] and not t.candidate[21, 20]
    assert np.all(t.collision_p[25:35, 15:25] == 1.0)
    assert not t.candidate[45, 30] and t.collision_p[45, 30] >= 0.9
    assert t.candidate[10, 5] and t.collision_p[10, 5] == pytest.approx(FREE)
    d = planner.plan(g, CameraState(np.array([0.55, 2.05, 0.8])), strategy='max_unmapped',
                     rng=np.random.default_rng(1))
    cells = g.to_index(d.candidates.positions)[:, :2]
    assert not np.any((cells[:, 0] >= 22) & (cells[:, 0] < 38)
                      & (cells[:, 1] >= 12) & (cells[:, 1] < 28))
    assert np.all(d.candidates.collision_p < planner.config.p_empty)
    # weakly seen (P 0.4 > P_empty) camera voxels are no candidates, but do not block the path
    g.prob[:, :, 8] = WEAK
    g.prob[50:, :, 8] = FREE
    t = planner.traversability(g)
    assert not t.candidate[:50].any() and t.candidate[52:, 5:35].any()
    assert t.navigable[:20].all()


def test_unseen_ground_around_the_rover_is_passable():
    """The mast camera never sees the ground within ~1.2 m of the rover: only what it saw
    further out is known. Unknown is no obstacle for the path; the goal must be seen free."""
    planner = _planner()
    g = _room()
    ii, jj = np.indices(g.shape[:2])
    near = (ii - 5) ** 2 + (jj - 20) ** 2 <= 12 ** 2
    g.known[near] = False
    g.prob[near] = 0.5
    d = planner.plan(g, CameraState(np.array([0.55, 2.05, 0.8])), strategy='max_information',
                     rng=np.random.default_rng(2), free_footprint=True)
    assert np.isfinite(d.path_length) and d.path_length > 1.0
    assert d.scores.ni[d.index] > 0
    assert g.known[tuple(g.to_index(d.position))]
    # the old rule (the whole column known, unknown = 0.5) finds nothing here
    with pytest.raises(PlanningError):
        NextBestViewPlanner(NbvConfig(**{**planner.config.__dict__, 'reach_model': 'known'})
                            ).plan(g, CameraState(np.array([0.55, 2.05, 0.8])),
                                   strategy='max_information', rng=np.random.default_rng(2))


def test_unknown_reach_model_rejected():
    with pytest.raises(ValueError, match='reach_model'):
        _planner(reach_model='teleport').traversability(_room())


BAG = Path(__file__).resolve().parents[3] / 'bags' / 'mapping_two_rovers'


def test_offline_parameters_are_the_nodes_and_validated_as_the_node_does():
    """`coop_viewplan.offline -p` takes the node's defaults and refuses what the node refuses
    (its ranges, choices and rule) as a usage error before any work."""
    from coop_viewplan import offline
    from coop_viewplan.params import PARAMS
    assert offline.node_parameters() == {k: s.default for k, s in PARAMS.items()}
    assert set(offline.PLANNING_PARAMS) <= set(PARAMS)
    got = offline.node_parameters(['candidates=12', 'k_rel=0.5', 'free_gray=occupancy'])
    assert (got['candidates'], got['k_rel'], got['free_gray']) == (12, 0.5, 'occupancy')
    assert type(got['candidates']) is int
    for bad, reason in [('pad_m=-1', 'pad_m must be >= 0.0'),
                        ('fov_deg=200', 'fov_deg must be <='),
                        ('k_rel=nan', 'k_rel must be finite'),
                        ('candidates=2.5', 'not an integer'),
                        ('ni_measure=jpeg', 'ni_measure must be one of'),
                        ('map_topic=/x', 'unknown parameter'), ('fov_deg', 'not NAME=VALUE')]:
        with pytest.raises(ValueError, match=reason):
            offline.node_parameters([bad])


def test_offline_cli_refuses_a_bad_parameter_before_any_work(tmp_path, capsys):
    from coop_common.testing import usage_error
    from coop_viewplan import offline
    # the bag does not exist either: -p is checked first
    err = usage_error(offline.main, [str(tmp_path / 'none'), '-p', 'pad_m=-1'], capsys)
    assert 'pad_m must be >= 0.0, got -1.0' in err


@pytest.mark.skipif(not BAG.is_dir(), reason='sample bag not present')
def test_sample_bag_map_gives_every_rover_a_view():
    """The map the `stereo` + `mapper` nodes make from bags/mapping_two_rovers, planned on with
    the node's default settings from each rover's last camera pose: a view with NI > 0."""
    pytest.importorskip('rover_bag.bagio')
    offline_map = pytest.importorskip('coop_mapping.offline')
    from coop_viewplan import offline

    res = offline_map.map_from_bag(BAG)
    assert set(res.scans) == {'rover1', 'rover2'}
    params = offline.node_parameters()
    grid = offline.grid_from_voxelmap(res.map, params)
    cams = offline.last_camera_poses(BAG)
    assert set(cams) == {'rover1', 'rover2'}
    answers = offline.plan_team(grid, cams, params)
    assert [a.rover for a in answers] == ['rover1', 'rover2']
    for a in answers:
        d = a.decision
        assert d is not None, f'{a.rover}: {a.message}'
        assert d.scores.ni[d.index] > 0, a.rover
        assert np.isfinite(d.path_length) and d.path_length < 10.0, a.rover
        assert d.candidates.collision_p[d.index] < params['p_empty'], a.rover
        cell = tuple(grid.to_index(d.position))
        assert grid.known[cell] and grid.prob[cell] < params['p_empty'], a.rover


def test_node_and_offline_share_the_map_guards():
    """`grid.planning_grid` is the one rule set both the node's map topic and the offline tool
    apply: each defect refused with its reason, an empty map told apart."""
    from coop_viewplan.grid import EmptyMapError, MapError, planning_grid
    keys = np.array([[0, 0, 0], [1, 0, 0], [2, 1, 0]])
    occ = np.array([0.2, 0.9, 0.3], np.float32)
    g = planning_grid(keys, occ, 0.1, pad_m=0.5, max_cells=10_000)
    assert g.known.sum() == 3
    for args, kw, why in (((keys, occ, 0.0), {}, 'bad resolution'),
                          ((keys, occ, float('nan')), {}, 'bad resolution'),
                          ((keys.reshape(-1)[:-1], occ, 0.1), {}, 'malformed voxel set'),
                          ((keys, occ[:2], 0.1), {}, 'malformed voxel set'),
                          ((keys, occ, 0.1), {'max_cells': 50}, 'max_grid_cells 50'),
                          ((keys, np.array([0.2, 1.5, 0.3]), 0.1), {}, 'within 0..1')):
        with pytest.raises(MapError, match=why):
            planning_grid(*args, pad_m=0.5, **kw)
    with pytest.raises(EmptyMapError, match='empty map'):
        planning_grid(np.zeros((0, 3), int), np.zeros(0), 0.1, pad_m=0.5)


def test_offline_listing_of_a_hand_built_result():
    from coop_viewplan import offline
    res = {'source': 'out/x.cmap', 'voxels': 1200, 'resolution_m': 0.1, 'bag': 'bags/b',
           'answers': [{'rover': 'rover1', 'success': True,
                        'message': 'max_information: 320 candidates',
                        'position_m': [-1.35, -0.85, 0.8], 'yaw_deg': 270.0, 'ni_bits': 0.9612,
                        'distance_m': 1.3, 'path_m': 0.0, 'collision_p': 0.119, 'rating': 0.826},
                       {'rover': 'rover2', 'success': False,
                        'message': 'no free reachable candidate'}]}
    assert offline.format_table(res).splitlines() == [
        'out/x.cmap: 1200 voxels at 0.1 m; poses: last stereo/pose in bags/b',
        'rover1: max_information: 320 candidates, camera at (-1.35, -0.85, +0.80) m yaw +270 '
        'deg, NI 0.961 bits, d 1.30 m, path 0.00 m, P 0.119, RF 0.826',
        'rover2: none (no free reachable candidate)']


@pytest.mark.skipif(not BAG.is_dir(), reason='sample bag not present')
def test_offline_cli_prints_the_table_of_its_json(tmp_path, capsys):
    """`coop_viewplan.offline --json` writes what it printed (docs/results/exploration.md makes
    its listing from that JSON with format_table): a small saved map, the bag's poses."""
    import json

    pytest.importorskip('rover_bag.bagio')
    from coop_mapping.voxelmap import VoxelMap
    from coop_viewplan import offline
    vm = VoxelMap(0.1)
    xy = np.mgrid[-4:2:0.05, -3:3:0.05].reshape(2, -1).T
    vm.insert_scan(np.c_[xy, np.zeros(len(xy))], np.array([-1.0, 0.0, 0.8]))
    vm.save(tmp_path / 'm.cmap')
    out = tmp_path / 'answers.json'
    assert offline.main([str(BAG), '--map', str(tmp_path / 'm.cmap'), '-p', 'candidates=8',
                         '--json', str(out)]) == 0
    text = capsys.readouterr().out
    res = json.loads(out.read_text())
    assert text == offline.format_table(res) + '\n'
    assert [a['rover'] for a in res['answers']] == ['rover1', 'rover2']
    assert res['voxels'] == len(vm) and res['overrides'] == ['candidates=8']
