"""Task-directed placement terms (Eq. 4-1..4-4) against hand-computed geometry."""
from __future__ import annotations

import numpy as np
import pytest

from coop_viewplan.grid import OccupancyGrid
from coop_viewplan.placement import (
    CameraModel,
    PlacementError,
    Target,
    TaskPlacer,
    VisibilityField,
    angular_visibility,
    depth_of_field,
    mast_stations,
    move_known_object,
    occluder_hulls,
    occlusion_distance,
    rate,
    resolution_term,
)

SQUARE = np.array([[2.0, -0.5], [3.0, -0.5], [3.0, 0.5], [2.0, 0.5]])


def test_occluder_hull_point_target():
    # A point target: the hull is the square itself; the ray along +x enters at x = 2.
    hull = occluder_hulls([SQUARE], 0.0)[0]
    assert len(hull) == 4
    d = occlusion_distance(np.zeros(2), [hull], np.array([[1.0, 0.0], [0.0, 1.0], [-1, 0.0]]))
    assert d[0] == pytest.approx(2.0)
    assert np.isinf(d[1]) and np.isinf(d[2])
    # Edge of the shadow: the near corners (2, +-0.5) at atan(0.25) = 14.04 deg.
    a_in, a_out = np.radians(13.9), np.radians(14.2)
    d = occlusion_distance(np.zeros(2), [hull], np.array([[np.cos(a_in), np.sin(a_in)],
                                                           [np.cos(a_out), np.sin(a_out)]]))
    assert np.isfinite(d[0]) and np.isinf(d[1])


def test_minkowski_expansion_grows_the_shadow():
    r = 0.5
    hull = occluder_hulls([SQUARE], r, n_vertices=4)[0]
    # A square target circumscribing the disc (n_vertices = 4, rotated 0): half-width r/cos45
    # along the diagonals -> vertices at (+-0.707, 0), (0, +-0.707) added to the square.
    h = r / np.cos(np.pi / 4)
    assert hull[:, 0].min() == pytest.approx(2.0 - h)
    assert hull[:, 1].max() == pytest.approx(0.5 + h)
    d = occlusion_distance(np.zeros(2), [hull], np.array([[1.0, 0.0]]))
    assert d[0] == pytest.approx(2.0 - h)


def test_tfv_arc_around_known_occluder():
    f = VisibilityField(np.zeros(2), occluder_hulls([SQUARE], 0.0), n_dirs=3600)
    # Inside the occluder's distance: the whole circle of radius 1 is free.
    assert f.tfv(np.array([[1.0, 0.0]]))[0] == pytest.approx(1.0)
    # Behind it: occluded.
    assert f.tfv(np.array([[5.0, 0.0]]))[0] == 0.0
    # Far away elsewhere: the circle minus the 2 x 14.04 deg shadow.
    expect = 1 - 2 * np.degrees(np.arctan(0.25)) / 360
    assert f.tfv(np.array([[0.0, 5.0]]))[0] == pytest.approx(expect, abs=2e-3)
    assert f.visible(np.array([[0.0, 5.0], [5.0, 0.0]])).tolist() == [True, False]


def test_tfv_3d_cap():
    cube = np.array([[x, y, z] for x in (2.0, 3.0) for y in (-0.5, 0.5) for z in (-0.5, 0.5)])
    f = VisibilityField(np.zeros(3), occluder_hulls([cube], 0.0), n_dirs=4000)
    assert f.tfv(np.array([[5.0, 0, 0]]))[0] == 0.0
    # Looking from -x: nearest occluded direction is ~180 - 14 deg away -> (2 * 166) / 360.
    assert f.tfv(np.array([[-5.0, 0, 0]]))[0] == pytest.approx(2 * (180 - 14.04) / 360,
                                                               abs=0.03)


def test_angular_visibility_edge_on_and_behind():
    t = Target(np.zeros(2), np.array([0.0, 1.0]))
    cams = np.array([[5.0, 0.0], [0.0, 5.0], [3.0, 3.0], [0.0, -5.0]])
    tav = angular_visibility(cams, t)
    assert tav == pytest.approx([0.0, 1.0, np.cos(np.pi / 4), 0.0])


def test_resolution_and_depth_of_field():
    cam = CameraModel(fov_deg=60, pixels=640, near_m=1, far_m=20)
    r = 2 * 10 * np.tan(np.radians(30)) / 640
    assert resolution_term(np.array([10.0]), cam)[0] == pytest.approx(1 / r)
    assert resolution_term(np.array([10.0]), cam, 0.01)[0] == pytest.approx(1 / (r + 0.01))
    assert depth_of_field(np.array([0.5, 1.0, 20.0, 20.5]), cam).tolist() == [0, 1, 1, 0]


def _room(n=60):
    g = OccupancyGrid.empty((n, n), resolution=1.0)
    g.known[:] = True
    g.prob[:] = 0.0
    return g


def test_placement_faces_the_target_and_avoids_the_occluder():
    g = _room()
    g.prob[28:33, 36:38] = 1.0      # a wall right in front of the target's face
    t = Target(np.array([30.5, 30.5]), np.array([0.0, 1.0]), radius=0.25)
    placer = TaskPlacer(CameraModel(near_m=2, far_m=20), max_candidates=5000, n_dirs=720)
    pl = placer.place(g, t, rng=np.random.default_rng(0))
    rel = pl.position - t.position
    assert rel[1] > 0                                # on the visible side
    assert pl.terms['tav'] > 0.5 and pl.terms['tfv'] > 0 and pl.terms['dof'] == 1
    # the line of sight does not cross the wall
    s = np.linspace(0, 1, 200)[:, None] * rel + t.position
    assert not g.prob[tuple(np.floor(s).astype(int).T)].any()


def test_secondary_target_wins_when_primary_is_boxed_in():
    g = _room()
    g.prob[27:35, 32:34] = 1.0      # the primary's face is walled off at 2 m
    prim = Target(np.array([30.5, 30.5]), np.array([0.0, 1.0]), radius=0.25)
    sec = Target(np.array([45.5, 30.5]), np.array([0.0, 1.0]), radius=0.25, sigma=0.001)
    placer = TaskPlacer(CameraModel(near_m=2, far_m=20), max_candidates=5000)
    pl = placer.place(g, prim, [sec], rng=np.random.default_rng(0))
    assert pl.target_index == 1


def test_bad_input():
    g = _room()
    g.prob[10, 10] = 1.0
    placer = TaskPlacer()
    with pytest.raises(PlacementError, match='inside an obstacle'):
        placer.place(g, Target(np.array([10.5, 10.5]), np.array([1.0, 0])),
                     rng=np.random.default_rng(0))
    with pytest.raises(PlacementError):
        Target(np.zeros(2), np.zeros(2))
    full = _room()
    full.prob[:] = 1.0
    full.prob[30, 30] = 0.0
    with pytest.raises(PlacementError):
        placer.place(full, Target(np.array([30.5, 30.5]), np.array([1.0, 0])),
                     rng=np.random.default_rng(0))


def test_moving_object_updates_map():
    g = _room(20)
    model = np.array([[0, 0], [0, 1], [1, 0], [1, 1]])
    cells = move_known_object(g, np.zeros((0, 2)), model, np.array([5, 5]))
    assert g.prob[5, 5] == 1.0
    cells = move_known_object(g, cells, model, np.array([8, 5]))
    assert g.prob[5, 5] == 0.0 and g.known[5, 5] and g.prob[9, 6] == 1.0
    assert len(cells) == 4


def test_secondary_inside_an_obstacle_is_skipped_not_fatal():
    # A moving object covering a secondary target hides that target only: the primary is still
    # in plain view and must be placed for (the placement used to raise 'inside an obstacle').
    g = _room()
    prim = Target(np.array([30.5, 30.5]), np.array([0.0, 1.0]), radius=0.25)
    sec = Target(np.array([45.5, 30.5]), np.array([0.0, 1.0]), radius=0.25, sigma=0.001)
    g.prob[44:47, 29:32] = 1.0      # the object sits on the secondary
    for search in ('bounded', 'random'):
        placer = TaskPlacer(CameraModel(near_m=2, far_m=20), max_candidates=5000, search=search)
        pl = placer.place(g, prim, [sec], rng=np.random.default_rng(0))
        assert pl.target_index == 0 and pl.terms['tfv'] > 0
    # the primary inside an obstacle is still a bad request
    g.prob[30, 30] = 1.0
    with pytest.raises(PlacementError, match='inside an obstacle'):
        TaskPlacer().place(g, prim, [sec], rng=np.random.default_rng(0))


def test_secondary_against_an_occluder_or_in_unknown_space_is_unrated():
    """A secondary whose own cell is free but which sits inside an occluder grown by its
    radius (next to a wall), or in unobserved space (unknown occludes), cannot be seen: it is
    not rated whatever its weight, and the primary is watched; the same primary is refused."""
    g = _room()
    g.prob[44:47, 29:32] = 1.0                                   # a box
    g.known[:, 50:] = False                                      # unobserved to the north
    prim = Target(np.array([30.5, 30.5]), np.array([0.0, 1.0]), radius=0.25)
    beside = Target(np.array([47.2, 30.5]), np.array([1.0, 0.0]), radius=0.5, weight=50.0)
    unseen = Target(np.array([30.5, 55.5]), np.array([0.0, -1.0]), radius=0.25, weight=50.0)
    for search in ('bounded', 'random'):
        placer = TaskPlacer(CameraModel(near_m=2, far_m=20), max_candidates=5000, search=search)
        pl = placer.place(g, prim, [beside, unseen], rng=np.random.default_rng(0))
        assert pl.target_index == 0 and pl.extras['unrated'] == [1, 2]
    with pytest.raises(PlacementError, match='primary target is inside an'):
        TaskPlacer(CameraModel(near_m=2, far_m=20)).place(g, beside, [prim],
                                                          rng=np.random.default_rng(0))


def test_mast_stations_and_non_finite_targets():
    """mast_stations puts the camera at the mast height over each ground cell a rover may
    stand on, with that cell's P; the placer takes only those positions."""
    g3 = OccupancyGrid(np.zeros((4, 3, 5), np.float32), np.ones((4, 3, 5), bool),
                       resolution=0.5, origin=np.array([-1.0, 2.0, -0.5]))
    cand = np.zeros((4, 3), bool)
    cand[1, 2] = cand[3, 0] = True
    pcol = np.full((4, 3), 0.3)
    pcol[3, 0] = 0.1
    st = mast_stations(g3, cand, pcol, 0.8)
    np.testing.assert_allclose(st.positions, [[-0.25, 3.25, 0.8], [0.75, 2.25, 0.8]])
    np.testing.assert_allclose(st.collision_p, [0.3, 0.1])
    t = Target(np.array([0.75, 3.25, 0.8]), np.array([0.0, -1.0, 0.0]), radius=0.0)
    pl = TaskPlacer(CameraModel(near_m=0.5, far_m=5), p_empty=0.2).place(
        g3, t, rng=np.random.default_rng(0), stations=st)
    np.testing.assert_allclose(pl.position, [0.75, 2.25, 0.8])   # the one with P < 0.2
    for bad in ({'radius': np.inf}, {'weight': np.inf}, {'sigma': np.nan}):
        with pytest.raises(PlacementError, match='finite'):
            Target(np.zeros(2), np.array([1.0, 0.0]), **bad)


def _study_views(seeds, density):
    """(grid, targets, fields) of Table 4-1 scenarios with the object at its last step."""
    from coop_viewplan import task_study as ts
    cfg = ts.StudyConfig()
    out = []
    for s in seeds:
        sc = ts.make_scenario(np.random.default_rng(s), density, cfg)
        g = OccupancyGrid(sc.grid.prob.copy(), sc.grid.known.copy(), sc.grid.resolution,
                          sc.grid.origin)
        obj = move_known_object(g, np.zeros((0, 2), np.int64), sc.object_cells,
                                g.to_index(sc.path[-1]))
        hull = ts._object_hull(g, obj, 0.0)
        targets = [sc.primary, sc.secondary]
        fields = [ts._with_object(ts._static_field(sc.grid, t, cfg), hull, t) for t in targets]
        out.append((g, targets, fields, cfg))
    return out


def test_bounded_search_finds_the_exhaustive_maximum():
    # §4.3.1 (ii), bounding by distance: the bounded search must return the maximum of Eq. 4-1
    # over every candidate, rating only a fraction of them. (A random subset of 1500 of the
    # ~4,500-6,500 candidates missed the maximum in 2/3 of the placements.)
    for g, targets, fields, cfg in _study_views(range(6), 0.05):
        kw = dict(clearance_m=cfg.clearance_m, n_dirs=cfg.n_dirs)
        for sec in (targets[1:], []):
            full = TaskPlacer(cfg.camera, max_candidates=10 ** 9, search='random', **kw).place(
                g, targets[0], sec, rng=np.random.default_rng(0), fields=fields)
            pl = TaskPlacer(cfg.camera, max_candidates=cfg.max_candidates, **kw).place(
                g, targets[0], sec, rng=np.random.default_rng(1), fields=fields)
            assert pl.terms['rating'] == pytest.approx(full.terms['rating'], rel=1e-12)
            np.testing.assert_allclose(pl.position, full.position)
            assert pl.target_index == full.target_index
            assert pl.extras['exact']
            assert pl.extras['evaluated'] < 0.2 * len(full.candidates)


def test_rating_bound_is_an_upper_bound():
    for g, targets, fields, cfg in _study_views([3], 0.20):
        placer = TaskPlacer(cfg.camera, clearance_m=cfg.clearance_m, n_dirs=cfg.n_dirs)
        cams, p = placer.all_candidates(g, targets)
        for t, f in zip(targets, fields, strict=False):
            r = rate(cams, t, f, cfg.camera, p).rating
            ub = placer.rating_bound(cams, t, p)
            assert np.all(r <= ub * (1 + 1e-12))
            assert np.any(r > 0.5 * ub)             # and not a loose one


def test_bounded_search_cap_reports_inexact():
    g, targets, fields, cfg = _study_views([0], 0.05)[0]
    placer = TaskPlacer(cfg.camera, clearance_m=cfg.clearance_m, n_dirs=cfg.n_dirs,
                        max_candidates=3)
    pl = placer.place(g, targets[0], targets[1:], rng=np.random.default_rng(0), fields=fields)
    assert pl.extras['evaluated'] == 3 and not pl.extras['exact']
    with pytest.raises(PlacementError):
        TaskPlacer(search='dense')


def test_cached_fields_serve_a_repeated_request_on_the_same_grid(monkeypatch):
    """cache_fields: the second request for the same target on the same grid object builds no
    occluders and places the same; a new grid object (a new map) builds them again; a target
    inside an occluder is refused from the cache too."""
    from coop_viewplan import placement
    calls = []
    real = placement.grid_occluders
    monkeypatch.setattr(placement, 'grid_occluders',
                        lambda *a, **k: calls.append(1) or real(*a, **k))
    g = _room()
    g.prob[28:33, 36:38] = 1.0
    t = Target(np.array([30.5, 30.5]), np.array([0.0, 1.0]), radius=0.25)
    placer = TaskPlacer(CameraModel(near_m=2, far_m=20), max_candidates=5000, cache_fields=2)
    a = placer.place(g, t, rng=np.random.default_rng(0))
    b = placer.place(g, t, rng=np.random.default_rng(0))
    assert len(calls) == 1 and np.array_equal(a.position, b.position)
    assert a.terms == b.terms
    placer.place(_room(), t, rng=np.random.default_rng(0))
    assert len(calls) == 2
    inside = Target(np.array([30.5, 35.9]), np.array([0.0, -1.0]), radius=0.5)
    for _ in range(2):
        with pytest.raises(PlacementError, match='inside'):
            placer.place(g, inside, rng=np.random.default_rng(0))
    assert len(calls) == 3          # built once for g again (the cache follows the grid)


def test_filled_tiles_are_boxes_with_the_hulls_of_their_cells():
    """grid_occluders gives a run of filled tiles as one box (its 8 corners), and the box path
    of occluder_hulls / occlusion_distance (slab test, no Qhull) answers as the hull path does
    on the same shapes."""
    from coop_viewplan.placement import grid_occluders, sphere_directions
    g = OccupancyGrid.empty((16, 8, 8), resolution=0.1)
    g.known[:], g.prob[:] = True, 0.0
    g.known[4:12, 0:4, 0:4] = False                  # unknown: two filled 4-cell tiles
    g.prob[0:2, 6:8, 4:6], g.prob[0, 6, 6] = 1.0, 1.0  # an occupied piece, not a box
    sets = grid_occluders(g, tile_cells=4)
    boxes = [s for s in sets if len(s) == 8]
    assert len(boxes) == 1 and len(sets) == 2
    np.testing.assert_allclose(boxes[0].min(0), [0.4, 0.0, 0.0])
    np.testing.assert_allclose(boxes[0].max(0), [1.2, 0.4, 0.4])
    target = np.array([1.5, 0.25, 0.15])
    dirs = sphere_directions(400)
    for r in (0.0, 0.05):
        hulls = occluder_hulls(sets, r)
        fast = occlusion_distance(target, hulls, dirs)
        # the same shapes through Qhull: a face centre added makes a box set a general one
        slow_sets = [np.vstack([h, h.mean(0) * [1, 1, 0] + [0, 0, h[:, 2].min()]])
                     if len(h) == 8 else h for h in hulls]
        slow = occlusion_distance(target, slow_sets, dirs)
        np.testing.assert_allclose(fast, slow, rtol=0, atol=1e-12)
        d = occlusion_distance(target, hulls, np.array([[-1.0, 0.0, 0.0]]))
        assert d[0] == pytest.approx(1.5 - 1.2 - r)          # the box's +x face, grown by r
    with pytest.raises(PlacementError, match='inside'):
        occlusion_distance(np.array([0.8, 0.2, 0.2]), occluder_hulls(sets, 0.0), dirs)


def _occlusion_reference(target, hulls, dirs):
    """occlusion_distance the straightforward way: Qhull on each hull, one hull at a time."""
    from scipy.spatial import ConvexHull

    from coop_viewplan.placement import _hull_entry_each
    return _hull_entry_each(target, [ConvexHull(h).equations for h in hulls], dirs,
                            np.full(len(dirs), np.inf))


def test_vectorised_hull_occlusion_matches_a_per_hull_reference():
    """occlusion_distance rates all 3-D hulls at once (only the rays that pass near a hull's
    bounding sphere): the same distances as one hull at a time, the same refusal when the
    target is inside one; in 2-D it is still the per-hull loop, bit for bit."""
    from coop_viewplan.placement import _expanded_hulls, sphere_directions
    rng = np.random.default_rng(5)
    dirs = np.vstack([sphere_directions(720), np.eye(3), -np.eye(3)])
    for _trial in range(6):
        hulls = []
        for _ in range(60):
            centre = rng.uniform(-4, 4, 3)
            if np.linalg.norm(centre) < 0.8:
                continue
            pts = centre + rng.normal(scale=rng.uniform(0.05, 0.6), size=(rng.integers(4, 30), 3))
            hulls.append(occluder_hulls([pts], rng.choice([0.0, 0.05]))[0])
        target = rng.normal(scale=0.05, size=3)
        try:
            ref = _occlusion_reference(target, hulls, dirs)
        except PlacementError:
            continue                    # the random cloud covered the target: skip
        got = occlusion_distance(target, hulls, dirs)
        assert np.array_equal(np.isfinite(got), np.isfinite(ref))
        assert np.isfinite(ref).sum() > 20
        np.testing.assert_allclose(got[np.isfinite(got)], ref[np.isfinite(ref)], rtol=0,
                                   atol=1e-12)
        # the same with the halfspaces handed over (as TaskPlacer does)
        pts_sets = [h + 0.0 for h in hulls]
        grown, eqs = _expanded_hulls(pts_sets, 0.0)
        again = occlusion_distance(target, grown, dirs, equations=eqs)
        np.testing.assert_allclose(again[np.isfinite(again)], ref[np.isfinite(ref)], rtol=0,
                                   atol=1e-12)
        # the target inside one of them (the hull's centroid): refused like the reference
        inside = hulls[len(hulls) // 2].mean(axis=0)
        with pytest.raises(PlacementError, match='inside'):
            _occlusion_reference(inside, hulls, dirs)
        with pytest.raises(PlacementError, match='inside'):
            occlusion_distance(inside, hulls, dirs)
        with pytest.raises(PlacementError, match='inside'):
            occlusion_distance(inside, grown, dirs, equations=eqs)
    # 2-D: the loop as before
    a = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    d2 = np.stack([np.cos(a), np.sin(a)], 1)
    polys = [occluder_hulls([rng.uniform(-0.3, 0.3, (6, 2)) + c], 0.1)[0]
             for c in ([2.0, 0.0], [0.0, -3.0], [-1.5, 1.5])]
    assert np.array_equal(occlusion_distance(np.zeros(2), polys, d2),
                          _occlusion_reference(np.zeros(2), polys, d2))


def test_expanded_hulls_are_the_direct_convex_hulls():
    """occluder_hulls on 3-D tile pieces (Qhull on the few Minkowski points that can be
    vertices) gives exactly the vertex arrays of Qhull on every point, and the halfspaces it
    hands on bound those hulls."""
    from scipy.spatial import ConvexHull

    from coop_viewplan.placement import _expanded_hulls, grid_occluders
    rng = np.random.default_rng(11)
    g = OccupancyGrid.empty((24, 20, 12), resolution=0.1, origin=np.array([-1.03, 0.4, 0.0]))
    g.known[:] = rng.random(g.shape) < 0.8
    g.prob[:] = (rng.random(g.shape) < 0.3).astype(np.float32)
    sets = grid_occluders(g, tile_cells=4)
    sets += [rng.normal(size=(12, 3)), np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]])]
    assert len(sets) > 100
    cube = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    for r in (0.0, 0.05):
        got, eqs = _expanded_hulls(sets, r)
        public = occluder_hulls(sets, r)
        assert len(public) == len(got) and all(map(np.array_equal, got, public))
        boxes = 0
        for pts, h, eq in zip(sets, got, eqs, strict=False):
            grown = pts if r == 0 else (pts[:, None, :] + cube[None] * r).reshape(-1, 3)
            lo, hi = pts.min(0), pts.max(0)
            corners = np.array([[a, b, c] for a in (lo[0], hi[0]) for b in (lo[1], hi[1])
                                for c in (lo[2], hi[2])])
            if len(h) == 8 and all((pts == c).all(1).any() for c in corners):
                boxes += 1              # a filled box: its corners grown, no Qhull
                np.testing.assert_array_equal(h.min(0), lo - r)
                continue
            try:
                hull = ConvexHull(grown)
            except Exception:  # noqa: BLE001 - a degenerate set, whatever Qhull raises
                np.testing.assert_array_equal(h, grown)       # degenerate: kept as is
                assert eq is None
                continue
            np.testing.assert_array_equal(h, grown[hull.vertices])
            dist = h @ eq[:, :3].T + eq[:, 3]
            assert dist.max() < 1e-12                         # every vertex inside every face
            assert ((np.abs(dist) < 1e-12).sum(axis=0) >= 3).all()   # each face is a facet
        assert boxes > 0


def test_a_target_touching_an_occluder_is_outside_it():
    """A target whose grown shape only touches an occluder (a part on the ground; a free voxel's
    centre next to an occupied one, radius half a voxel) is outside it: the rays into the
    occluder are blocked at 0, those away from it are clear; a target 1e-6 m deeper is refused.
    The same for the box (slab) path, the 3-D hull path and the 2-D hull path; and the placer
    puts a camera above a target resting on a floor."""
    from coop_viewplan.placement import sphere_directions
    r = 0.05
    box = np.array([[x, y, z] for x in (0.0, 1.0) for y in (0.0, 1.0) for z in (0.0, 1.0)])
    wedge = np.vstack([box, [[0.5, 0.5, 1.5]]])          # a roof on it: a general hull
    dirs = sphere_directions(400)
    for shape in (box, wedge):
        grown = occluder_hulls([shape], r)
        assert (len(grown[0]) == 8) == (shape is box)    # box: slab path; wedge: 3-D hulls
        target = np.array([1.0 + r, 0.5, 0.5])            # on the +x face, grown by r
        d = occlusion_distance(target, grown, dirs)
        assert np.all(d[dirs[:, 0] < -1e-6] == 0.0)      # into the occluder: blocked at once
        assert np.all(np.isinf(d[dirs[:, 0] > 1e-6]))     # away from it: clear
        with pytest.raises(PlacementError, match='inside'):
            occlusion_distance(target - [1e-6, 0, 0], grown, dirs)
    # 2-D (the per-hull path; a square would take the slab path): a point target on the x = 2
    # face of a triangle
    tri = np.array([[2.0, -1.0], [4.0, 0.0], [2.0, 1.0]])
    dirs2 = np.stack([np.cos(np.linspace(0, 2 * np.pi, 361)),
                      np.sin(np.linspace(0, 2 * np.pi, 361))], axis=1)
    target = np.array([2.0, 0.3])
    d = occlusion_distance(target, occluder_hulls([tri], 0.0), dirs2)
    assert np.all(d[dirs2[:, 0] > 1e-6] == 0.0) and np.all(np.isinf(d[dirs2[:, 0] < -1e-6]))
    with pytest.raises(PlacementError, match='inside'):
        occlusion_distance(target + [1e-6, 0], occluder_hulls([tri], 0.0), dirs2)
    # a target resting on an occupied floor (a free voxel's centre one layer above it)
    g = OccupancyGrid.empty((40, 40, 20), resolution=0.1)
    g.known[:], g.prob[:] = True, 0.0
    g.prob[:, :, 0] = 1.0
    t = Target(g.to_world(np.array([20, 20, 1])), np.array([0.0, 0.0, 1.0]), radius=0.05)
    pl = TaskPlacer(CameraModel(near_m=0.3, far_m=1.5)).place(g, t, rng=np.random.default_rng(0))
    assert pl.position[2] > t.position[2] + 0.3 and pl.terms['tfv'] > 0


def test_a_target_in_the_notch_of_a_tile_piece_is_outside_it():
    """A tile piece that is not convex (an L; a U, whose hull is its tile's box) has a hull
    that holds free cells. A target in such a notch, touching the piece, is placed, with the
    occlusion distances of the piece given cell by cell (exact); one whose grown shape
    overlaps a cell is still refused. 3-D and 2-D (there the target's shape is a polygon
    circumscribing its disc, which reaches r / cos(pi / 8) along the axes: radius 0.04)."""
    for nd, r in ((3, 0.05), (2, 0.04)):
        g = OccupancyGrid.empty((16,) * nd, resolution=0.1)
        corners = np.array(np.meshgrid(*([[0, 1]] * nd), indexing='ij')).reshape(nd, -1).T
        for notch in ((slice(6, 8), slice(6, 8)),            # L: the tile's +x+y corner free
                      (slice(5, 7), slice(6, 8))):           # U: a slot open to +y
            g.known[:], g.prob[:] = True, 0.0
            g.prob[(slice(4, 8),) * nd] = 1.0                # one 4-cell tile of grid_occluders
            g.prob[notch + (slice(4, 8),) * (nd - 2)] = 0.0
            cell = np.array([6, 6, 5][:nd])
            normal = np.array([0.0, 1.0, 0.0][:nd])
            target = Target(g.to_world(cell), normal, radius=r)
            placer = TaskPlacer(CameraModel(near_m=0.3, far_m=1.5), clearance_m=0.2,
                                n_dirs=400)
            boxes = [g.origin + (c + corners) * g.resolution for c in np.argwhere(g.prob >= 0.5)]
            exact = VisibilityField(target.position, occluder_hulls(boxes, r), n_dirs=400)
            f = placer._grid_field(g, target)
            assert np.array_equal(f.occ, exact.occ)
            assert np.isfinite(f.occ).any() and np.isinf(f.occ).any()
            pl = placer.place(g, target, rng=np.random.default_rng(0))
            assert pl.terms['tfv'] > 0 and pl.terms['tav'] > 0
            with pytest.raises(PlacementError, match='inside an \\(expanded\\) obstacle'):
                TaskPlacer(CameraModel(near_m=0.3, far_m=1.5), clearance_m=0.2,
                           n_dirs=400).place(g, Target(target.position, normal, radius=r + 0.01),
                                             rng=np.random.default_rng(0))


def test_search_and_experiment_modes_are_checked_at_construction():
    from coop_viewplan.fig_3_25 import Fig325Config, PoseSource
    from coop_viewplan.placement import PlacementError, Search, TaskPlacer
    from coop_viewplan.task_study import StudyConfig
    assert TaskPlacer(search='random').search is Search.RANDOM
    with pytest.raises(PlacementError, match=r"search must be one of \['bounded', 'random'\]"):
        TaskPlacer(search='exhaustive')
    with pytest.raises(ValueError, match='search must be one of'):
        StudyConfig(search='all')
    assert Fig325Config(pose_source='odometry').pose_source is PoseSource.ODOMETRY
    with pytest.raises(ValueError, match='pose_source must be one of'):
        Fig325Config(pose_source='gps')


def test_a_primary_taken_in_free_space_sees_past_the_cells_that_hold_it():
    """PrimarySpace.FREE: the occluder cells that hold the primary (grown by its radius: range
    noise at a target the task defines in free space) are not occluders of it; the rest are."""
    g = _room()
    g.prob[44:47, 29:32] = 1.0                                   # a box
    beside = Target(np.array([47.2, 30.5]), np.array([1.0, 0.0]), radius=0.5)
    cam = CameraModel(near_m=2, far_m=20)
    with pytest.raises(PlacementError, match='primary target is inside an'):
        TaskPlacer(cam).place(g, beside, rng=np.random.default_rng(0))
    pl = TaskPlacer(cam, primary_space='free').place(g, beside, rng=np.random.default_rng(0))
    assert pl.target_index == 0 and pl.terms['tfv'] > 0
    assert pl.extras['freed_cells'] == 1                         # the box's cell (46, 30)
    assert pl.position[0] > 47.2                                 # seen from its free side
    # walled in: the cells about it still hide it from every candidate
    g.prob[45:50, 28:34] = 1.0
    g.prob[46:49, 29:33] = 0.0
    inside = Target(np.array([47.5, 30.5]), np.array([1.0, 0.0]), radius=0.5)
    with pytest.raises(PlacementError, match='no candidate sees'):
        TaskPlacer(cam, primary_space='free').place(g, inside, rng=np.random.default_rng(0))
    with pytest.raises(PlacementError, match='primary_space'):
        TaskPlacer(primary_space='ignore')


def test_incidence_limit_and_the_fair_random_draw_share_the_feasible_set():
    from coop_viewplan.placement import Choose
    g = _room()
    g.prob[28:33, 36:38] = 1.0      # a wall in front of the target's face
    t = Target(np.array([30.5, 30.5]), np.array([0.0, 1.0]), radius=0.25)
    placer = TaskPlacer(CameraModel(near_m=2, far_m=12), max_candidates=20000)
    narrow = placer.narrowed(max_incidence_deg=30.0)
    assert narrow.camera.max_incidence_deg == 30.0 and narrow.camera.far_m == 12
    assert placer.narrowed(max_incidence_deg=0.0) is placer        # 0: the camera's own
    best = narrow.place(g, t, rng=np.random.default_rng(0))
    feasible = None
    draws = []
    for seed in range(40):
        pl = narrow.place(g, t, rng=np.random.default_rng(seed), choose='random')
        feasible = pl.extras['feasible'] if feasible is None else feasible
        assert pl.extras['feasible'] == feasible
        draws.append(pl.position)
        rel = pl.position - t.position
        # every draw within the depth of field and the incidence, and rated (seen)
        assert 2 <= np.hypot(*rel) <= 12
        assert np.degrees(np.arccos(rel[1] / np.hypot(*rel))) <= 30.0 + 1e-6
        s = np.linspace(0, 1, 200)[:, None] * rel + t.position
        assert not g.prob[tuple(np.floor(s).astype(int).T)].any()
    # a draw is the seed's; the draws spread over the feasible set, the best is the maximum
    again = narrow.place(g, t, rng=np.random.default_rng(3), choose=Choose.RANDOM)
    np.testing.assert_array_equal(again.position, draws[3])
    assert feasible >= 10 and len({tuple(d) for d in draws}) >= 0.6 * feasible
    assert best.terms['rating'] >= max(
        narrow.place(g, t, rng=np.random.default_rng(s), choose='random').terms['rating']
        for s in range(5))
    # wider incidence, more feasible poses; a bad choice is refused
    wide = placer.place(g, t, rng=np.random.default_rng(0), choose='random')
    assert wide.extras['feasible'] > feasible
    with pytest.raises(PlacementError, match='choose'):
        placer.place(g, t, rng=np.random.default_rng(0), choose='worst')
