"""Task-directed camera placement (thesis ch. 4): RF = DOF^a Res^b TFV^g TAV^d (1 - P), Eq. 4-1.

* DOF: binary, 1 inside [near, far] (§4.2.3.1);
* Res = 1 / R with R = 2 d tan(fov / 2) / n (Eq. 4-2), plus ST_error for a secondary target
  (Eq. 4-4);
* TFV (§4.2.3.3): the target is reduced to a point and every occluder grown by the target's shape
  (Minkowski sum), replaced by its convex hull, and projected onto the circle/sphere of radius d
  centred on the target. A camera at distance d in direction u sees the target iff no hull is
  entered before d along u. TFV is the angular excursion the camera can make on that circle
  before the target is occluded: in 2-D the contiguous visible arc through u over 2 pi; in 3-D
  twice the angle from u to the nearest occluded direction, over 2 pi;
* TAV = cos(beta) for |beta| <= pi/2 else 0 (Eq. 4-3, one-sided target), beta between the camera
  axis (pointing at the target) and the target normal;
* P: collision probability of the camera position (max occupancy over the mount's footprint).

Search (§4.3.1: "(i) increasing the environment grid coarseness, (ii) bounding the evaluation of
RF by distance to the target, (iii) employ a finite random selection of goal configurations"):
candidates are the free cells on a coarsened lattice (`stride`) within the depth of field of some
target. `search='bounded'` (default) then bounds the evaluation by distance: TFV, TAV and DOF are
at most 1, so RF <= weight (1 - P) Res(d)^beta, a bound that falls with the distance d to the
target; candidates are rated best bound first and the search stops once no bound is above the best
rating found, which is then the maximum over the whole candidate set (at most `max_candidates`
evaluations). `search='random'` rates a random subset of `max_candidates` candidates instead.
"""
from __future__ import annotations

import copy
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError

from coop_common.params import choice

from .errors import ViewplanError
from .grid import OccupancyGrid

# A target whose grown shape only touches an expanded occluder (a part resting on the ground, a
# target in a free voxel next to an occupied or unknown one: the free cell's centre lies exactly
# on the occluder grown by half a cell) is outside it: a ray into the occluder is blocked at
# once (distance 0), a ray that leaves it at once (exit within TOUCH_M, m) or runs away from it
# sees the target. Only a target deeper than TOUCH_M inside an occluder is refused. A ray exactly
# along the touched face is left undefined (the slab path blocks it at 0, the hull paths follow
# the rounding of the face offset); the directions of sphere_directions and of the 2-D fields
# never run exactly along an axis, and a tolerance there would move the distances of targets
# that are clearly outside.
TOUCH_M = 1e-9


#: the largest target weight: a rating times a weight beyond it may overflow to inf
MAX_WEIGHT = 1e6


class PlacementError(ViewplanError, ValueError):
    """The placement request cannot be served (target inside an obstacle, no free candidate)."""


@dataclass(frozen=True)
class Target:
    """A target: position (ndim,), unit outward normal of the viewed face, radius (m),
    geometric uncertainty sigma (m, ST_error of Eq. 4-4; 0 for the primary), weight."""

    position: np.ndarray
    normal: np.ndarray
    radius: float = 0.1
    sigma: float = 0.0
    weight: float = 1.0

    def __post_init__(self) -> None:
        p = np.asarray(self.position, float).reshape(-1)
        n = np.asarray(self.normal, float).reshape(-1)
        if p.shape != n.shape or p.shape[0] not in (2, 3):
            raise PlacementError('target position and normal must both be 2-D or 3-D')
        if not np.all(np.isfinite(p)) or not np.all(np.isfinite(n)):
            raise PlacementError('target position and normal must be finite')
        big = np.abs(n).max()
        n = n / big if big > 0 else n         # no overflow in the norm of a huge normal
        nn = np.linalg.norm(n)
        if nn < 1e-9:
            raise PlacementError('target normal must be non-zero')
        if not (np.isfinite([self.radius, self.sigma, self.weight]).all() and self.radius >= 0
                and self.sigma >= 0 and 0 < self.weight <= MAX_WEIGHT):
            raise PlacementError('radius, sigma must be finite and >= 0, weight in '
                                 f'(0, {MAX_WEIGHT:g}]')
        object.__setattr__(self, 'position', p)
        object.__setattr__(self, 'normal', n / nn)


@dataclass(frozen=True)
class CameraModel:
    """Field of view (deg), pixels along the detector axis, depth of field [near, far] (m),
    and the largest incidence (deg, between the view ray and the target's face normal) at
    which the task's image processing still finds the target (90: the face's edge)."""

    fov_deg: float = 60.0
    pixels: int = 640
    near_m: float = 1.0
    far_m: float = 30.0
    max_incidence_deg: float = 90.0


@dataclass(frozen=True)
class Exponents:
    """alpha, beta, gamma, delta of Eq. 4-1 (unity in the thesis)."""

    dof: float = 1.0
    res: float = 1.0
    tfv: float = 1.0
    tav: float = 1.0


# ----------------------------------------------------------------------------- occluders


def occluder_hulls(points_sets: list[np.ndarray], target_radius: float, *,
                   n_vertices: int = 8) -> list[np.ndarray]:
    """Steps (i) and (ii) of §4.2.3.3: each occluder (an (k, ndim) vertex set) is grown by the
    target's shape (a disc/ball of `target_radius`, as a circumscribed polygon/polyhedron) by a
    Minkowski sum and replaced by the convex hull. Returns hull vertex arrays."""
    return _expanded_hulls(points_sets, target_radius, n_vertices=n_vertices)[0]


def _expanded_hulls(points_sets: list[np.ndarray], target_radius: float, *,
                    n_vertices: int = 8) -> tuple[list[np.ndarray], list[np.ndarray | None]]:
    """occluder_hulls, and each hull's halfspaces as Qhull gives them (`equations`, rows
    (n, c) with n.x + c <= 0 inside) so that occlusion_distance need not run Qhull a second
    time (TaskPlacer passes them on); None where it computes them itself as before: boxes
    (the slab test needs none), degenerate sets and every 2-D hull (the 2-D path is kept as
    it was, bit for bit).

    3-D sets (a live map's ~1600 tile pieces and boxes near a target) first go through
    `_hull_candidates`, all at once: the box test, and which Minkowski points can be hull
    vertices. Qhull then gets ~1.6 % of the points and returns the same hull (the same vertex
    array: in 3-D the vertices are listed by input index, which the candidates keep in
    order) at a fraction of the cost."""
    sets = [np.asarray(p, float) for p in points_sets]
    all_3d = bool(sets) and all(p.ndim == 2 and p.shape[1] == 3 and len(p) for p in sets)
    boxes, candidates = _hull_candidates(sets) if all_3d else (None, None)
    verts: list[np.ndarray] = []
    eqs: list[np.ndarray | None] = []
    for i, set_pts in enumerate(sets):
        pts = set_pts
        nd = pts.shape[1]
        if boxes is not None:
            box = boxes[i]
        else:
            box = _bounding_box_if_filled(pts) if nd == 3 or target_radius <= 0 else None
        if box is not None:
            # the hull of a set holding its bounding box's corners is that box, and a box grown
            # by the cube (3-D target shape) is a box: no Qhull (thousands of tiles on a map)
            lo, hi = box[0] - target_radius, box[1] + target_radius
            verts.append(_box_corners(lo, hi))
            eqs.append(None)
            continue
        keep = None if candidates is None else candidates[i]     # (k, 8) or None
        if target_radius > 0:
            if nd == 2:
                a = np.arange(n_vertices) * 2 * np.pi / n_vertices
                shape = np.stack([np.cos(a), np.sin(a)], 1) * target_radius / np.cos(
                    np.pi / n_vertices)
            else:
                shape = _CUBE_SIGNS * target_radius
            pts = (pts[:, None, :] + shape[None]).reshape(-1, nd)
            if keep is not None:
                keep = keep.reshape(-1)                 # the sum's (point, corner) order
        elif keep is not None:
            keep = np.asarray(keep.any(axis=1))         # no growth: a point of any corner
        if nd == 3:
            hull = _hull_3d(pts, keep)
            if hull is not None:
                verts.append(hull[0])
                eqs.append(hull[1])
                continue
        else:
            try:
                hull = ConvexHull(pts)
                verts.append(pts[hull.vertices])
                eqs.append(None)
                continue
            except QhullError:
                pass
        verts.append(pts)   # degenerate (collinear) set: keep the points as they are
        eqs.append(None)
    return verts, eqs


def _hull_3d(pts: np.ndarray, keep: np.ndarray | None) -> tuple[np.ndarray, np.ndarray] | None:
    """Vertices (in input order, as ConvexHull.vertices) and equations of the convex hull of
    3-D points, from the candidate points `keep` (a mask that holds every vertex) if given;
    None if degenerate. The vertex indices are read off the triangles with a mask: scipy's
    `vertices` is np.unique of them, which costs as much as Qhull on these small sets."""
    for cand in ([] if keep is None else [np.flatnonzero(keep)]) + [np.arange(len(pts))]:
        try:
            hull = ConvexHull(pts[cand])
        except QhullError:
            continue
        used = np.zeros(len(cand), bool)
        used[hull.simplices.ravel()] = True
        return pts[cand[used]], hull.equations
    return None


#: the 3-D target shape's corners (a cube of half-side 1), in the order of the Minkowski sums
_CUBE_SIGNS = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)],
                       float)


def _hull_candidates(sets: list[np.ndarray], *, max_extent: int = 8
                     ) -> tuple[list[tuple[np.ndarray, np.ndarray] | None],
                                list[np.ndarray | None]]:
    """For 3-D point sets, all at once: each set's `_bounding_box_if_filled`, and for the
    others a (k, 8) mask of the (point p, cube corner s) pairs, s in `_CUBE_SIGNS` order, for
    which p + r s may be a vertex of the convex hull of the set grown by the cube of
    half-side r (None: no mask, any pair may be).

    Why the mask is safe: a vertex of hull(S + cube) is p + r s where p maximises over S some
    direction w of sign pattern s. If another point q of S lies on p's line parallel to axis
    a, beyond p in the direction s_a, then w.q > w.p and p maximises no such w. So (p, s) is
    kept only if p is the last point of S along each of its three axis lines in the
    directions s: on a lattice tile piece, a few points per corner.

    How: coordinates are replaced by their ranks per axis (exact equality and order are all
    the line test needs), each set becomes a dense boolean volume of its ranks, and "a point
    beyond along axis a" is a cumulative OR along that axis. A set spanning more than
    `max_extent` ranks on some axis (not a tile piece) gets no mask."""
    n = np.array([len(s) for s in sets])
    is_box, lo, hi = _filled_boxes(sets)
    boxes = [(lo[i], hi[i]) if b else None for i, b in enumerate(is_box)]
    cand: list = [None] * len(sets)
    rest = np.flatnonzero(~is_box)
    if len(rest) == 0:
        return boxes, cand
    # the other sets' coordinates as ranks per axis, relative to their set's lowest
    nr = n[rest]
    pts = np.concatenate([sets[i] for i in rest])
    first = np.concatenate([[0], np.cumsum(nr)[:-1]])
    rank = np.stack([np.unique(pts[:, a], return_inverse=True)[1].reshape(-1)
                     for a in range(3)], axis=1)
    r_lo = np.minimum.reduceat(rank, first, axis=0)
    extent = np.maximum.reduceat(rank, first, axis=0) - r_lo + 1      # (sets, 3)
    small = (extent <= max_extent).all(axis=1)
    if not small.any():
        return boxes, cand
    local = (rank - np.repeat(r_lo, nr, axis=0))[np.repeat(small, nr)]
    e = int(extent[small].max())
    vol = np.zeros((int(small.sum()), e, e, e), bool)
    at = (np.repeat(np.arange(len(vol)), nr[small]), local[:, 0], local[:, 1], local[:, 2])
    vol[at] = True
    # is p the last point of its line along axis a, going - (side 0) or + (side 1)?
    last = np.empty((len(local), 3, 2), bool)
    for a in range(3):
        below, above = _points_beyond(vol, a + 1)
        last[:, a, 0], last[:, a, 1] = ~below[at], ~above[at]
    side = (_CUBE_SIGNS > 0).astype(np.int64)                        # (8, 3)
    keep = last[:, np.arange(3), side].all(axis=2)                    # (points, 8)
    for i, k in zip(rest[small], np.split(keep, np.cumsum(nr[small])[:-1]), strict=False):
        cand[i] = k
    return boxes, cand


def _points_beyond(vol: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """For a boolean volume: whether some True cell lies strictly below / strictly above each
    cell along `axis` (cumulative ORs shifted by one)."""
    below, above = np.zeros_like(vol), np.zeros_like(vol)
    head, tail = [slice(None)] * vol.ndim, [slice(None)] * vol.ndim
    head[axis], tail[axis] = slice(None, -1), slice(1, None)
    below[tuple(tail)] = np.logical_or.accumulate(vol, axis=axis)[tuple(head)]
    rev = np.flip(np.logical_or.accumulate(np.flip(vol, axis), axis=axis), axis)
    above[tuple(head)] = rev[tuple(tail)]
    return below, above


def _filled_boxes(sets: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_bounding_box_if_filled` of many non-empty sets of one dimension at once: whether
    each is a filled box, and every set's bounding box (lo, hi) (G, ndim)."""
    n = np.array([len(s) for s in sets])
    nd = sets[0].shape[1]
    starts = np.concatenate([[0], np.cumsum(n)[:-1]])
    pts = np.concatenate(sets)
    sid = np.repeat(np.arange(len(sets)), n)
    lo = np.minimum.reduceat(pts, starts, axis=0)
    hi = np.maximum.reduceat(pts, starts, axis=0)
    # a point with every coordinate at lo or hi is a corner: which one, as a binary code
    at_hi = pts == hi[sid]
    corner = (at_hi | (pts == lo[sid])).all(axis=1)
    present = np.zeros((len(sets), 2 ** nd), bool)
    present[sid[corner], at_hi[corner] @ (1 << np.arange(nd))] = True
    return np.asarray(present.all(axis=1) & (hi > lo).all(axis=1)), lo, hi


_CORNER_SELECT = {nd: np.array(np.meshgrid(*([[0, 1]] * nd), indexing='ij')).reshape(nd, -1).T
                  for nd in (2, 3)}


def _box_corners(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return np.where(_CORNER_SELECT[len(lo)] == 0, lo, hi)


def _bounding_box_if_filled(pts: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(lo, hi) of the set's bounding box if every corner of it is one of the points (the
    convex hull is then the box itself), else None: `_filled_boxes` of one set."""
    is_box, lo, hi = _filled_boxes([pts])
    return (lo[0], hi[0]) if is_box[0] else None


def _box_distance(pts: np.ndarray, p: np.ndarray) -> float:
    """Distance from p to the bounding box of pts (0 inside)."""
    return float(np.linalg.norm(np.maximum(np.maximum(pts.min(axis=0) - p, p - pts.max(axis=0)),
                                           0.0)))


def grid_occluders(grid: OccupancyGrid, *, threshold: float = 0.5, unknown_occludes: bool = True,
                   tile_cells: int = 4, box: tuple[np.ndarray, np.ndarray] | None = None
                   ) -> list[np.ndarray]:
    """Occluders of a grid as cell-corner vertex sets: occupied cells (and unknown ones when
    `unknown_occludes`) cut into tiles of `tile_cells` per side, one set per connected piece of
    a tile, so the convex hulls stay close to the occluders' true shape. box: (lo, hi) cell
    index bounds (hi exclusive) to restrict to, e.g. the reach of a target (tiles then start
    at lo). Each set's vertices are unique and in lexicographic order; a run of tiles filled
    entirely along the first axis (most of the unknown space of a live map) is one set, its
    box's 2^ndim corners (the union of the tiles' hulls)."""
    nd = grid.ndim
    lo = np.zeros(nd, np.int64)
    hi = np.asarray(grid.shape, np.int64)
    if box is not None:
        lo = np.clip(np.asarray(box[0], np.int64), 0, grid.shape)
        hi = np.clip(np.asarray(box[1], np.int64), lo, grid.shape)
    occ = _occluder_mask(grid, lo, hi, threshold=threshold, unknown_occludes=unknown_occludes)
    corners = _CORNER_SELECT[nd]
    n_tiles = [int(np.ceil(n / tile_cells)) for n in occ.shape]
    tiles = np.zeros(occ.shape, np.int64)
    mult = 1
    for ax in range(nd):
        idx = np.arange(occ.shape[ax]) // tile_cells
        sh = [1] * nd
        sh[ax] = -1
        tiles = tiles + idx.reshape(sh) * mult
        mult *= n_tiles[ax]
    cells = np.argwhere(occ)
    if len(cells) == 0:
        return []
    lab, _n = ndimage.label(occ)
    tile_of = tiles[occ]
    # filled tiles: their box's corners (one connected piece each)
    full = np.bincount(tile_of, minlength=mult) == np.bincount(tiles.ravel(), minlength=mult)
    full_ids = np.flatnonzero(full)
    t_idx = np.stack(np.unravel_index(full_ids, n_tiles, order='F'), axis=1)
    box_lo = t_idx * tile_cells
    box_hi = np.minimum(box_lo + tile_cells, occ.shape)
    # a run of filled tiles along the first axis is one box: the same union, so the same hulls
    # (a box grown by the target's cube is the union of its tiles grown), far fewer of them
    # (ids are in Fortran order: a run is consecutive ids without a wrap of the first axis)
    starts = np.ones(len(full_ids), bool)
    starts[1:] = (np.diff(full_ids) != 1) | (t_idx[1:, 0] == 0)
    first = np.flatnonzero(starts)
    last = np.append(first[1:], len(full_ids))[:len(first)] - 1
    box_lo, box_hi = box_lo[first], box_hi[last]
    boxes = [grid.origin + (lo + np.where(corners == 0, a, b)) * grid.resolution
             for a, b in zip(box_lo, box_hi, strict=False)]
    rest = ~full[tile_of]
    cells = cells[rest]
    if len(cells) == 0:
        return boxes
    _, gid = np.unique(lab[occ][rest].astype(np.int64) * mult + tile_of[rest],
                       return_inverse=True)
    # every group's cell corners as one sorted set of (group, raveled corner) codes: one sort
    # for all groups (a unique per group cost 20 s on a live 3-D map)
    dims = np.array(occ.shape) + 1
    size = int(np.prod(dims))
    lin = np.ravel_multi_index(tuple((cells[:, None, :] + corners[None]).reshape(-1, nd).T),
                               dims)
    code = np.unique(np.repeat(gid.astype(np.int64), len(corners)) * size + lin)
    g, c = np.divmod(code, size)
    pts = np.stack(np.unravel_index(c, dims), axis=1) + lo
    world = grid.origin + pts * grid.resolution
    return boxes + np.split(world, np.flatnonzero(np.diff(g)) + 1)


def _occluder_mask(grid: OccupancyGrid, lo: np.ndarray, hi: np.ndarray, *,
                   threshold: float = 0.5, unknown_occludes: bool = True) -> np.ndarray:
    """The cells grid_occluders cuts into occluders, of the index box [lo, hi) only."""
    sl = tuple(slice(a, b) for a, b in zip(lo, hi, strict=False))
    known = grid.known[sl]
    occ = known & (grid.prob[sl] >= threshold)
    return occ | ~known if unknown_occludes else occ


def _deep_in_boxes(o: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Per box (lo, hi (B, ndim)): whether point o lies deeper than TOUCH_M inside it."""
    return np.all((lo + TOUCH_M < o) & (o < hi - TOUCH_M), axis=1)


def _deep_in_hulls(c: np.ndarray, face0: np.ndarray) -> np.ndarray:
    """Per hull, from its faces' offsets c (n.x + c <= 0 inside, x relative to the point;
    hulls stacked, hull i's first face at face0[i]): whether the point lies deeper than
    TOUCH_M inside it."""
    return np.logical_and.reduceat(c < -TOUCH_M, face0)


def _hulls_holding(target: np.ndarray, sets: list[np.ndarray], hulls: list[np.ndarray],
                   equations: list[np.ndarray | None]) -> np.ndarray:
    """Indices of the grown hulls (`_expanded_hulls` of `sets`, with its equations) that hold
    `target` deeper than TOUCH_M (the test of occlusion_distance), left out the sets that are
    boxes of cells (their 2^ndim corners only: a filled tile, a run of them, one cell), which
    hold it only if their cells do. A set of more vertices whose hull is a box (a U-shaped
    piece, its corners all present) is tested as that box."""
    nd = len(target)
    cand = [i for i, s in enumerate(sets) if len(s) > 2 ** nd]
    maybe = np.array([i for i in cand if equations[i] is None and len(hulls[i]) == 2 ** nd],
                     np.int64)
    out: list[int] = []
    if len(maybe):
        is_box, lo, hi = _filled_boxes([hulls[i] for i in maybe])
        out = maybe[is_box & _deep_in_boxes(target, lo, hi)].tolist()
        cand = sorted(set(cand) - set(maybe[is_box].tolist()))
    idx, eqs = [], []
    for i in cand:
        eq = equations[i] if equations[i] is not None else _hull_equations(hulls[i])
        if eq is not None:
            idx.append(i)
            eqs.append(eq)
    if eqs:
        eq = np.concatenate(eqs)
        face0 = np.concatenate([[0], np.cumsum([len(e) for e in eqs])[:-1]])
        deep = _deep_in_hulls(eq[:, :-1] @ target + eq[:, -1], face0)
        out.extend(np.asarray(idx, np.int64)[deep].tolist())
    return np.asarray(sorted(out), np.int64)


def _cells_as_boxes(grid: OccupancyGrid, sets: list[np.ndarray], *, unknown_occludes: bool
                    ) -> list[np.ndarray]:
    """The occluder cells (`_occluder_mask`) inside the bounding boxes of cell-corner vertex
    sets (tile pieces of grid_occluders), each cell as its box's corners: the same occluders,
    exactly."""
    per_set = []
    for pts in sets:
        lo = np.rint((pts.min(axis=0) - grid.origin) / grid.resolution).astype(np.int64)
        hi = np.rint((pts.max(axis=0) - grid.origin) / grid.resolution).astype(np.int64)
        per_set.append(np.argwhere(_occluder_mask(grid, lo, hi,
                                                  unknown_occludes=unknown_occludes)) + lo)
    cells = np.unique(np.concatenate(per_set), axis=0)
    corners = _CORNER_SELECT[grid.ndim]
    return list(grid.origin + (cells[:, None, :] + corners[None]) * grid.resolution)


def _halfspaces(hulls: list[np.ndarray]) -> list[np.ndarray]:
    """Qhull's halfspaces of each hull's vertex set; degenerate hulls are left out."""
    return [eq for eq in map(_hull_equations, hulls) if eq is not None]


def _hull_equations(hull: np.ndarray) -> np.ndarray | None:
    """Qhull's `equations` of a vertex set (rows (n, c), n.x + c <= 0 inside), None if
    degenerate."""
    try:
        return ConvexHull(hull).equations
    except QhullError:
        return None


def occlusion_distance(target: np.ndarray, hulls: list[np.ndarray],
                       directions: np.ndarray, *,
                       equations: list[np.ndarray | None] | None = None) -> np.ndarray:
    """Step (iii) of §4.2.3.3: for each unit direction u (K, ndim) from the reduced target, the
    distance at which the ray first enters an expanded hull (inf if none). A camera at
    target + d u sees the whole target iff d < occlusion_distance(u). Raises PlacementError if
    the target point lies deeper than TOUCH_M inside a hull (target inside an obstacle; one on
    a hull's boundary is outside it). equations: per hull, its
    halfspaces if known (`_expanded_hulls`, 3-D: saves a second Qhull per hull), None to have
    them computed here (2-D hulls always are, as before)."""
    u = np.asarray(directions, float)
    best = np.full(u.shape[0], np.inf)
    hs = [np.asarray(h, float) for h in hulls]
    if not hs:
        return best
    # boxes (exactly 2^ndim vertices, the corners of their bounding box): the slab test
    box = np.zeros(len(hs), bool)
    maybe = [i for i, h in enumerate(hs) if len(h) == 2 ** h.shape[1]]
    if maybe:
        is_box, lo, hi = _filled_boxes([hs[i] for i in maybe])
        box[np.asarray(maybe)[is_box]] = True
        best = _box_entry(target, lo[is_box], hi[is_box], u)
    others = np.flatnonzero(~box)
    if len(others) == 0:
        return best
    if u.shape[1] == 3:
        verts, eqs = [], []
        for i in others:
            eq = equations[i] if equations is not None else None
            eq = _hull_equations(hs[i]) if eq is None else eq
            if eq is not None:                  # a degenerate hull bounds nothing: skipped
                verts.append(hs[i])
                eqs.append(eq)
        if not eqs:
            return best
        return np.minimum(best, _hull_entry(np.asarray(target, float), verts, eqs, u))
    # 2-D (the Table 4-1 study): one hull at a time, as it always was
    return _hull_entry_each(target, _halfspaces([hulls[i] for i in others]), u, best)


def _hull_entry_each(target: np.ndarray, eqs: list[np.ndarray], u: np.ndarray,
                     best: np.ndarray) -> np.ndarray:
    """occlusion_distance over hulls given by their halfspaces, one hull at a time (any
    dimension; the 2-D path, and the reference `_hull_entry` is tested against), folded into
    `best`."""
    for eq in eqs:
        n, c = eq[:, :-1], eq[:, -1] + eq[:, :-1] @ target     # n.x + c <= 0 inside, x rel.
        if np.all(c < -TOUCH_M):
            raise PlacementError('target is inside an (expanded) obstacle')
        denom = u @ n.T                                           # (K, F)
        with np.errstate(divide='ignore', invalid='ignore'):
            t = -c[None, :] / denom
        t_enter = np.where(denom < 0, t, -np.inf).max(axis=1)
        t_exit = np.where(denom > 0, t, np.inf).min(axis=1)
        parallel_out = ((np.abs(denom) < 1e-15) & (c[None, :] > 0)).any(axis=1)
        hit = (t_enter <= t_exit) & (t_exit > TOUCH_M) & ~parallel_out
        best = np.where(hit, np.minimum(best, np.maximum(t_enter, 0.0)), best)
    return best


def _ray_pairs(target: np.ndarray, centre: np.ndarray, rad2: np.ndarray, u: np.ndarray, *,
               pairs_per_block: int = 1 << 15) -> Iterator[tuple[int, np.ndarray, np.ndarray]]:
    """The (direction, shape) pairs whose ray from `target` passes within a shape's bounding
    sphere (centre (S, ndim), squared radius (S,)), in blocks of directions: yields
    (first direction of the block, direction index in the block (ascending), shape index).

    Only these pairs can hit: the others miss the shape by at least a margin of 1e-9 relative
    to the sphere's size and distance, far above the rounding of the exact tests, so those
    tests would find them missed too and skipping them changes no result. Around a target on
    a live map (720 directions, ~800 tile pieces and ~900 boxes within 5 m) about 1 % of the
    pairs with tile pieces remain, and a quarter of those with boxes (long runs of tiles)."""
    w = centre - target
    ww = (w ** 2).sum(axis=1)
    reach2 = rad2 + 1e-9 * (rad2 + ww)
    step = max(1, pairs_per_block // len(centre))
    for k0 in range(0, len(u), step):
        proj = u[k0:k0 + step] @ w.T                                # (k, S)
        along = np.maximum(proj, 0.0)                               # the nearest ray point
        k, h = np.nonzero(ww - 2 * along * proj + along ** 2 <= reach2)
        if len(k):
            yield k0, k, h


def _min_per_direction(best: np.ndarray, k0: int, k: np.ndarray, dist: np.ndarray) -> None:
    """best[k0 + k] = min(best, dist) per direction, k ascending (pairs of one block)."""
    ks, first = np.unique(k, return_index=True)
    best[k0 + ks] = np.minimum(best[k0 + ks], np.minimum.reduceat(dist, first))


def _hull_entry(target: np.ndarray, verts: list[np.ndarray], eqs: list[np.ndarray],
                u: np.ndarray) -> np.ndarray:
    """occlusion_distance for convex hulls (vertices, Qhull halfspaces), all at once. Per
    (direction, hull) pair as in the 2-D loop: with faces n.x + c <= 0 (x relative to the
    target) and denom = u.n, the ray enters at the largest -c / denom over the faces with
    denom < 0, leaves at the smallest over those with denom > 0, misses if it runs parallel
    (|denom| < 1e-15) outside a face (c > 0), and hits iff enter <= exit and exit > TOUCH_M.
    Raises PlacementError if the target is inside a hull (c < -TOUCH_M for all its faces).

    Only the pairs of `_ray_pairs` are rated; their faces are stacked flat (no padding):
    a pair's rows are its hull's, and the max / min / any per pair are reduceat over them."""
    n_faces = np.array([len(e) for e in eqs])
    face0 = np.concatenate([[0], np.cumsum(n_faces)[:-1]])
    eq = np.concatenate(eqs)
    normal = eq[:, :-1]
    c = eq[:, -1] + normal @ target
    if _deep_in_hulls(c, face0).any():
        raise PlacementError('target is inside an (expanded) obstacle')
    # bounding spheres: the centre of the vertices' box, the farthest vertex from it
    n_verts = np.array([len(v) for v in verts])
    vert0 = np.concatenate([[0], np.cumsum(n_verts)[:-1]])
    vv = np.concatenate(verts)
    centre = (np.minimum.reduceat(vv, vert0, axis=0) + np.maximum.reduceat(vv, vert0, axis=0)) / 2
    rad2 = np.maximum.reduceat(((vv - np.repeat(centre, n_verts, axis=0)) ** 2).sum(axis=1),
                               vert0)
    best = np.full(len(u), np.inf)
    for k0, k, h in _ray_pairs(target, centre, rad2, u):
        nf = n_faces[h]
        seg = np.concatenate([[0], np.cumsum(nf)[:-1]])             # each pair's first row
        rows = np.repeat(face0[h] - seg, nf) + np.arange(int(nf.sum()))
        denom = np.einsum('ij,ij->i', u[k0 + np.repeat(k, nf)], normal[rows])
        cr = c[rows]
        with np.errstate(divide='ignore', invalid='ignore'):
            t = -cr / denom
        t_enter = np.maximum.reduceat(np.where(denom < 0, t, -np.inf), seg)
        t_exit = np.minimum.reduceat(np.where(denom > 0, t, np.inf), seg)
        parallel_out = np.logical_or.reduceat((np.abs(denom) < 1e-15) & (cr > 0), seg)
        hit = (t_enter <= t_exit) & (t_exit > TOUCH_M) & ~parallel_out
        _min_per_direction(best, k0, k, np.where(hit, np.maximum(t_enter, 0.0), np.inf))
    return best


def _box_entry(target: np.ndarray, lo: np.ndarray, hi: np.ndarray, u: np.ndarray
               ) -> np.ndarray:
    """occlusion_distance for axis-aligned boxes (B, ndim) by the slab method, for the
    (direction, box) pairs of `_ray_pairs` (the same arithmetic per pair as rating them
    all). Raises PlacementError if the target lies in a box deeper than TOUCH_M (a target on
    its boundary is outside, as in the hull test)."""
    o = np.asarray(target, float)
    best = np.full(u.shape[0], np.inf)
    if len(lo) == 0:
        return best
    if _deep_in_boxes(o, lo, hi).any():
        raise PlacementError('target is inside an (expanded) obstacle')
    zero = u == 0.0
    with np.errstate(divide='ignore'):
        inv = np.where(zero, 0.0, 1.0 / np.where(zero, 1.0, u))          # (K, nd)
    lo_o, hi_o = lo - o, hi - o                                         # (B, nd)
    # a direction parallel to an axis: the slab is everything (-inf, inf) or nothing
    # (inf, inf: never entered)
    inside = (lo_o <= 0) & (hi_o >= 0)                                  # (B, nd)
    for k0, k, b in _ray_pairs(o, (lo + hi) / 2, (((hi - lo) / 2) ** 2).sum(axis=1), u):
        ik, par = inv[k0 + k], zero[k0 + k]                             # (P, nd)
        t1 = np.where(par, np.where(inside[b], -np.inf, np.inf), lo_o[b] * ik)
        t2 = np.where(par, np.inf, hi_o[b] * ik)
        t_enter = np.minimum(t1, t2).max(axis=1)
        t_exit = np.maximum(t1, t2).min(axis=1)
        hit = (t_enter <= t_exit) & (t_exit > TOUCH_M)
        _min_per_direction(best, k0, k, np.where(hit, np.maximum(t_enter, 0.0), np.inf))
    return best


def sphere_directions(n: int) -> np.ndarray:
    """n roughly uniform unit vectors (Fibonacci sphere)."""
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = np.pi * (1 + 5 ** 0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


class VisibilityField:
    """The projection of the expanded occluders around one target, sampled in `n_dirs`
    directions, answering TFV and line-of-sight queries for many camera positions at once."""

    def __init__(self, target: np.ndarray, hulls: list[np.ndarray], *, n_dirs: int = 720,
                 equations: list[np.ndarray | None] | None = None) -> None:
        """equations: the hulls' halfspaces where known (see occlusion_distance)."""
        self.target = np.asarray(target, float)
        self.ndim = self.target.shape[0]
        if self.ndim == 2:
            self.angles = (np.arange(n_dirs) + 0.5) * 2 * np.pi / n_dirs
            self.dirs = np.stack([np.cos(self.angles), np.sin(self.angles)], 1)
        else:
            self.dirs = sphere_directions(n_dirs)
        self.occ = occlusion_distance(self.target, hulls, self.dirs, equations=equations)

    def with_occluders(self, hulls: list[np.ndarray]) -> VisibilityField:
        """A copy with more (already expanded) hulls, e.g. a moving object's (§4.3.1)."""
        out = object.__new__(VisibilityField)
        out.__dict__.update(self.__dict__)
        out.occ = np.minimum(self.occ, occlusion_distance(self.target, hulls, self.dirs))
        return out

    def _nearest(self, u: np.ndarray) -> np.ndarray:
        if self.ndim == 2:
            a = np.mod(np.arctan2(u[:, 1], u[:, 0]), 2 * np.pi)
            n = len(self.angles)
            return np.minimum((a / (2 * np.pi) * n).astype(np.int64), n - 1)
        return np.argmax(u @ self.dirs.T, axis=1)

    def tfv(self, cameras: np.ndarray) -> np.ndarray:
        """TFV in [0, 1] for camera positions (M, ndim) (0 where the target is occluded)."""
        rel = np.asarray(cameras, float) - self.target
        d = np.linalg.norm(rel, axis=1)
        u = rel / np.maximum(d, 1e-12)[:, None]
        vis = self.occ[None, :] > d[:, None]                        # (M, K)
        b = self._nearest(u)
        own = vis[np.arange(len(b)), b]
        if self.ndim == 2:
            n = vis.shape[1]
            shift = (np.arange(n)[None, :] + b[:, None]) % n
            fwd = vis[np.arange(len(b))[:, None], shift]            # from b forwards
            bwd = vis[np.arange(len(b))[:, None], (b[:, None] - np.arange(n)[None, :]) % n]
            nf = np.where(fwd.all(axis=1), n, np.argmin(fwd, axis=1))
            nb = np.where(bwd.all(axis=1), n, np.argmin(bwd, axis=1))
            arc = np.minimum(nf + nb - 1, n) / n
            return np.where(own, arc, 0.0)
        cosang = np.clip(u @ self.dirs.T, -1, 1)
        ang = np.where(vis, np.inf, np.arccos(cosang)).min(axis=1)
        return np.where(own, np.minimum(2 * ang, 2 * np.pi) / (2 * np.pi), 0.0)

    def visible(self, cameras: np.ndarray) -> np.ndarray:
        """Line of sight to the whole target (through the expanded-hull test)."""
        rel = np.asarray(cameras, float) - self.target
        d = np.linalg.norm(rel, axis=1)
        b = self._nearest(rel / np.maximum(d, 1e-12)[:, None])
        return self.occ[b] > d


# ----------------------------------------------------------------------------- rating


def resolution_term(d: np.ndarray, camera: CameraModel, st_error: float = 0.0) -> np.ndarray:
    """Eq. 4-2 / 4-4: Res_RF = 1 / (2 d tan(fov / 2) / n + ST_error)."""
    r = 2 * np.asarray(d, float) * np.tan(np.radians(camera.fov_deg) / 2) / camera.pixels
    return 1.0 / np.maximum(r + st_error, 1e-12)


def angular_visibility(cameras: np.ndarray, target: Target, *,
                       max_incidence_deg: float = 90.0) -> np.ndarray:
    """Eq. 4-3: cos(beta) for a one-sided target, 0 behind it and where beta exceeds
    max_incidence_deg (what the image processing handles)."""
    rel = np.asarray(cameras, float) - target.position
    u = rel / np.maximum(np.linalg.norm(rel, axis=1), 1e-12)[:, None]
    c = np.clip(u @ target.normal, 0.0, 1.0)
    if max_incidence_deg < 90.0:
        c = np.where(c >= np.cos(np.radians(max_incidence_deg)) - 1e-12, c, 0.0)
    return c


def depth_of_field(d: np.ndarray, camera: CameraModel) -> np.ndarray:
    """§4.2.3.1: 1 inside [near, far], else 0."""
    d = np.asarray(d, float)
    return ((d >= camera.near_m) & (d <= camera.far_m)).astype(float)


@dataclass
class TaskRating:
    """Per-candidate terms for one target, and their product RF (Eq. 4-1)."""

    rating: np.ndarray
    dof: np.ndarray
    res: np.ndarray
    tfv: np.ndarray
    tav: np.ndarray
    collision_p: np.ndarray


def rate(cameras: np.ndarray, target: Target, field_: VisibilityField, camera: CameraModel,
         collision_p: np.ndarray, *, exponents: Exponents = Exponents()) -> TaskRating:
    """Eq. 4-1 for every camera position, looking at `target` (secondary targets add their
    geometric uncertainty to R, Eq. 4-4, and are weighted by `target.weight`)."""
    cams = np.asarray(cameras, float)
    d = np.linalg.norm(cams - target.position, axis=1)
    dof = depth_of_field(d, camera)
    res = resolution_term(d, camera, target.sigma)
    tfv = field_.tfv(cams)
    tav = angular_visibility(cams, target, max_incidence_deg=camera.max_incidence_deg)
    e = exponents
    p = np.asarray(collision_p, float)
    with np.errstate(invalid='ignore', over='ignore'):
        rf = dof ** e.dof * res ** e.res * tfv ** e.tfv * tav ** e.tav * (1 - p) * target.weight
    rf = np.where((dof > 0) & (tfv > 0) & (tav > 0), rf, 0.0)
    return TaskRating(rf, dof, res, tfv, tav, p)


@dataclass
class Placement:
    """The best camera position, the target it watches (0 = primary), its terms, and the rated
    candidates with their best rating over the targets (for Fig. 4-8b-like maps: every
    candidate with `search='random'` and max_candidates >= their number; the bounded search
    returns only those it had to rate). extras: search, candidates, evaluated (candidate-target
    ratings computed) and exact (the pick is the maximum over every candidate)."""

    position: np.ndarray
    target_index: int
    terms: dict
    candidates: np.ndarray
    ratings: np.ndarray
    extras: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Stations:
    """Camera positions a robot can take (N, ndim) and the collision probability P of each
    (Eq. 4-1's 1 - P), e.g. a rover's mast height over the ground cells it may stand on."""

    positions: np.ndarray
    collision_p: np.ndarray


def mast_stations(grid: OccupancyGrid, candidate: np.ndarray, collision_p: np.ndarray,
                  height_m: float) -> Stations:
    """The camera of a rover's mast, at `height_m` (z in the grid's frame), over every ground
    cell of the 3-D `grid` where the rover may stand (`candidate`, (nx, ny) bool, e.g. the
    next-best-view planner's Traversal.candidate) with that cell's P."""
    idx = np.argwhere(np.asarray(candidate, bool))
    xy = grid.origin[:2] + (idx + 0.5) * grid.resolution
    return Stations(np.column_stack([xy, np.full(len(idx), float(height_m))]),
                    np.asarray(collision_p, float)[tuple(idx.T)])


class Search(StrEnum):
    """TaskPlacer's search: candidates rated best distance bound first, stopping when no bound
    beats the best ('bounded', exact), or a random subset of max_candidates ('random')."""

    BOUNDED = 'bounded'
    RANDOM = 'random'


SEARCHES = tuple(Search)


def _freed(grid: OccupancyGrid, cells: np.ndarray) -> OccupancyGrid:
    """A copy of the grid with `cells` (K, ndim) known and free."""
    if len(cells) == 0:
        return grid
    idx = tuple(np.asarray(cells, np.int64).T)
    prob, known = grid.prob.copy(), grid.known.copy()
    prob[idx], known[idx] = 0.0, True
    return replace(grid, prob=prob, known=known)


class Choose(StrEnum):
    """Which rated candidate TaskPlacer.place returns: the 'best' (Eq. 4-1's maximum), or one
    drawn uniformly from every 'feasible' one, rating > 0 (free, within the depth of field
    and the incidence the image processing handles, the target not occluded): the fair
    random placement of §5.4, from the same set the best is searched in."""

    BEST = 'best'
    RANDOM = 'random'


class PrimarySpace(StrEnum):
    """What TaskPlacer makes of the grid's occluder cells that hold the primary target (its own
    cell, or one grown by the target's radius that reaches it): 'refuse' the request (the
    thesis's rule: a target against an occluder cannot be wholly seen), or take them as 'free'
    (a task whose primary target it defines in free space, e.g. just in front of a known site:
    occupied cells there are range noise off the site's edges, or the task's own objects, and
    do not hide the target from itself; counted in `Placement.extras['freed_cells']`). Every
    other cell occludes as before, so a target walled in is still never seen."""

    REFUSE = 'refuse'
    FREE = 'free'


def cells_holding(grid: OccupancyGrid, position: np.ndarray, radius: float) -> np.ndarray:
    """(K, ndim) indices of the grid cells that, grown by `radius` (as TaskPlacer grows its
    occluders), hold `position` deeper than TOUCH_M, within the grid."""
    rel = (np.asarray(position, float) - grid.origin) / grid.resolution
    reach = (radius - TOUCH_M) / grid.resolution
    # cell i, spanning [i, i + 1) in cells, grown: i - reach < rel < i + 1 + reach
    lo = np.maximum(np.floor(rel - 1 - reach).astype(np.int64) + 1, 0)
    hi = np.minimum(np.ceil(rel + reach).astype(np.int64), np.asarray(grid.shape))
    axes = [np.arange(a, b) for a, b in zip(lo, hi, strict=False)]
    axes = [a[(a - reach < r) & (r < a + 1 + reach)] for a, r in zip(axes, rel, strict=False)]
    if any(len(a) == 0 for a in axes):
        return np.zeros((0, grid.ndim), np.int64)
    return np.stack(np.meshgrid(*axes, indexing='ij'), axis=-1).reshape(-1, grid.ndim)


class TaskPlacer:
    """Optimum camera placement for watching a primary target, with optional secondary targets
    (§4.2.3), on an occupancy grid. The camera axis always points at the watched target."""

    def __init__(self, camera: CameraModel | None = None, *, exponents: Exponents = Exponents(),
                 p_empty: float = 0.05, clearance_m: float = 0.5, stride: int = 1,
                 max_candidates: int = 4000, n_dirs: int = 720,
                 unknown_occludes: bool = True,
                 search: Search | str = Search.BOUNDED,
                 primary_space: PrimarySpace | str = PrimarySpace.REFUSE,
                 cache_fields: int = 0) -> None:
        """cache_fields: keep the visibility fields of this many (target position, radius)
        for the grid last placed on, so a repeated request on the same map skips building
        them (the node's case; a grid changed in place would be served stale fields, so the
        experiments, which move objects in their grids, leave it 0). primary_space: see
        PrimarySpace."""
        self.search = choice(Search, search, 'search', error=PlacementError)
        self.primary_space = choice(PrimarySpace, primary_space, 'primary_space',
                                    error=PlacementError)
        self.camera = camera or CameraModel()
        self.exponents = exponents
        self.p_empty = p_empty
        self.clearance_m = clearance_m
        self.stride = max(1, int(stride))
        self.max_candidates = int(max_candidates)
        self.n_dirs = int(n_dirs)
        self.cache_fields = int(cache_fields)
        self._cache_grid: OccupancyGrid | None = None
        self._cache: dict[tuple, VisibilityField | PlacementError] = {}
        self.unknown_occludes = unknown_occludes

    def narrowed(self, near_m: float = 0.0, far_m: float = 0.0, *,
                 max_incidence_deg: float = 0.0) -> TaskPlacer:
        """This placer for a task whose depth of field (§4.2.3.1: what focus and the image
        processing allow) is [near_m, far_m] within the camera's, and whose image processing
        finds the target up to max_incidence_deg off its face normal; 0 keeps the camera's
        limit. Only narrows (a field is built out to the far limit). A placer narrowed in depth
        keeps no cache: its fields, cut at the nearer limit, must not serve the wider one (the
        incidence limit does not enter the fields: one narrowed in it alone shares them)."""
        near = max(self.camera.near_m, near_m)
        far = min(self.camera.far_m, far_m) if far_m > 0 else self.camera.far_m
        inc = self.camera.max_incidence_deg
        if max_incidence_deg > 0:
            inc = min(inc, max_incidence_deg)
        if not near < far:
            raise PlacementError(f'depth of field [{near:g}, {far:g}] m is empty')
        if (near, far, inc) == (self.camera.near_m, self.camera.far_m,
                                self.camera.max_incidence_deg):
            return self
        other = copy.copy(self)
        other.camera = replace(self.camera, near_m=near, far_m=far, max_incidence_deg=inc)
        if (near, far) != (self.camera.near_m, self.camera.far_m):
            other.cache_fields, other._cache_grid, other._cache = 0, None, {}
        return other

    def collision_probability(self, grid: OccupancyGrid) -> np.ndarray:
        """P per cell: the largest occupancy within the clearance (unknown = 0.5)."""
        r = int(np.ceil(self.clearance_m / grid.resolution))
        p = np.where(grid.known, grid.prob, 0.5)
        ax = np.arange(-r, r + 1)
        g = np.meshgrid(*([ax] * grid.ndim), indexing='ij')
        fp = sum(x ** 2 for x in g) <= r * r
        return ndimage.maximum_filter(p, footprint=fp, mode='constant', cval=1.0)

    def candidates(self, grid: OccupancyGrid, targets: list[Target], rng: np.random.Generator,
                   pcol: np.ndarray | None = None, stations: Stations | None = None
                   ) -> tuple[np.ndarray, np.ndarray]:
        """Free cells (P < P_empty) on a lattice of `stride`, within the depth of field of some
        target (distance bounding), thinned to a random subset of `max_candidates`."""
        pos, p = self.all_candidates(grid, targets, pcol, stations)
        if len(pos) > self.max_candidates:
            keep = rng.choice(len(pos), self.max_candidates, replace=False)
            return pos[keep], p[keep]
        return pos, p

    def all_candidates(self, grid: OccupancyGrid, targets: list[Target],
                       pcol: np.ndarray | None = None, stations: Stations | None = None
                       ) -> tuple[np.ndarray, np.ndarray]:
        """Every free cell (P < P_empty) on a lattice of `stride` within the depth of field of
        some target, and its P; with `stations`, those of the given camera positions."""
        if stations is None:
            pcol = self.collision_probability(grid) if pcol is None else pcol
            sl = tuple(slice(0, None, self.stride) for _ in range(grid.ndim))
            idx = np.argwhere(np.ones(grid.shape, bool)[sl]) * self.stride
            p = pcol[tuple(idx.T)]
            pos = grid.to_world(idx)
        else:
            pos = np.asarray(stations.positions, float).reshape(-1, grid.ndim)
            p = np.asarray(stations.collision_p, float).reshape(-1)
        ok = p < self.p_empty
        near = np.zeros(len(pos), bool)
        for t in targets:
            d = np.linalg.norm(pos - t.position, axis=1)
            near |= (d >= self.camera.near_m) & (d <= self.camera.far_m)
        keep = np.flatnonzero(ok & near)
        if len(keep) == 0:
            raise PlacementError('no free candidate within the depth of field of any target')
        return pos[keep], p[keep]

    def _grid_field(self, grid: OccupancyGrid, t: Target, *, free_own: bool = False
                    ) -> VisibilityField:
        """The visibility field of target t from the grid's occluders (cached, see
        cache_fields). Raises PlacementError if t is inside an expanded occluder; with
        free_own, the cells that hold t (cells_holding) are not occluders of it."""
        key = (t.position.tobytes(), float(t.radius), free_own)
        if self.cache_fields:
            if grid is not self._cache_grid:
                self._cache_grid, self._cache = grid, {}
            if key in self._cache:
                f = self._cache[key]
                if isinstance(f, PlacementError):
                    raise PlacementError(str(f))
                return f
        if free_own:
            grid = _freed(grid, cells_holding(grid, t.position, t.radius))
        # Distance bounding: occluders beyond the depth of field cannot hide the target from
        # any admissible camera (only the grid within reach is cut into them).
        reach = self.camera.far_m + t.radius + grid.resolution * np.sqrt(grid.ndim)
        # clipped to the grid in metres first: a huge radius must not overflow the indices
        top = grid.origin + np.asarray(grid.shape) * grid.resolution
        box = (grid.to_index(np.clip(t.position - reach, grid.origin, top)),
               grid.to_index(np.clip(t.position + reach, grid.origin, top)) + 1)
        near = [h for h in grid_occluders(grid, unknown_occludes=self.unknown_occludes, box=box)
                if _box_distance(h, t.position) <= reach]
        hulls, equations = _expanded_hulls(near, t.radius)
        holding = _hulls_holding(t.position, near, hulls, equations)
        if len(holding):
            # the hull of a tile piece that is not convex (an L, a U) may hold a target that
            # none of its cells does: such pieces go in cell by cell, and only a target inside
            # a grown cell is refused
            cell_hulls, cell_eqs = _expanded_hulls(
                _cells_as_boxes(grid, [near[i] for i in holding],
                                unknown_occludes=self.unknown_occludes), t.radius)
            keep = np.ones(len(hulls), bool)
            keep[holding] = False
            hulls = [h for h, k in zip(hulls, keep, strict=False) if k] + cell_hulls
            equations = [e for e, k in zip(equations, keep, strict=False) if k] + cell_eqs
        try:
            f = VisibilityField(t.position, hulls, n_dirs=self.n_dirs, equations=equations)
        except PlacementError as exc:       # the target inside an occluder: cached too
            f = exc
        if self.cache_fields:
            if len(self._cache) >= self.cache_fields:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = f
        if isinstance(f, PlacementError):
            raise f
        return f

    def rating_bound(self, cameras: np.ndarray, target: Target, collision_p: np.ndarray
                     ) -> np.ndarray:
        """An upper bound of Eq. 4-1 per candidate that needs no visibility test: TFV and TAV
        lie in [0, 1], so with gamma, delta >= 0, RF <= DOF^a Res^b (1 - P) weight (0 outside
        the depth of field). inf inside the depth of field if gamma or delta < 0."""
        d = np.linalg.norm(np.asarray(cameras, float) - target.position, axis=1)
        dof = depth_of_field(d, self.camera)
        e = self.exponents
        if e.tfv < 0 or e.tav < 0:
            return np.where(dof > 0, np.inf, 0.0)
        res = resolution_term(d, self.camera, target.sigma)
        p = np.asarray(collision_p, float)
        with np.errstate(invalid='ignore', over='ignore'):
            ub = dof ** e.dof * res ** e.res * (1 - p) * target.weight
        return np.where(dof > 0, ub, 0.0)

    def place(self, grid: OccupancyGrid, primary: Target, secondary: Sequence[Target] = (), *,
              rng: np.random.Generator, hulls: list[np.ndarray] | None = None,
              fields: list[VisibilityField] | None = None,
              stations: Stations | None = None,
              choose: Choose | str = Choose.BEST) -> Placement:
        """Maximise Eq. 4-1 over the candidates, for the primary and every secondary target
        (choose='random': draw one of the feasible candidates, rating > 0, uniformly with
        `rng`, every candidate rated; `extras['feasible']` counts them);
        raises PlacementError on bad input (primary target inside an obstacle, no free
        candidate). A secondary target inside an obstacle or an expanded occluder (covered by a
        moving object, in unobserved space, closer to a wall than its radius; one that only
        touches an occluder is outside it, see TOUCH_M) is not rated: it cannot be seen,
        and the primary or another secondary may still be (`Placement.extras['unrated']`); one
        inside an obstacle or outside the map is skipped the same way, before any rating.
        stations: the camera positions a robot can take and their P (a rover's mast over the
        ground it may stand on), instead of every free cell of the grid."""
        choose = choice(Choose, choose, 'choose', error=PlacementError)
        targets = [primary, *secondary]
        active = []
        for k, t in enumerate(targets):
            if t.position.shape[0] != grid.ndim:
                raise PlacementError(f'target is {t.position.shape[0]}-D, map {grid.ndim}-D')
            cell = grid.to_index(t.position)
            if not grid.in_bounds(cell):
                if k == 0:
                    raise PlacementError('target outside the map')
                continue                    # a secondary there cannot be rated: skipped
            if grid.known[tuple(cell)] and grid.prob[tuple(cell)] >= 0.5:
                if k == 0 and self.primary_space is PrimarySpace.REFUSE:
                    raise PlacementError('target is inside an obstacle')
                if k > 0:
                    continue
            active.append(k)
        free_primary = self.primary_space is PrimarySpace.FREE
        pcol = self.collision_probability(grid) if stations is None else None
        act = [targets[k] for k in active]
        if self.search is Search.RANDOM:
            cams, p = self.candidates(grid, act, rng, pcol, stations)
        else:
            cams, p = self.all_candidates(grid, act, pcol, stations)
        cache: dict[int, VisibilityField] = {}

        unrated: list[int] = []

        def rating_of(k: int, sel: np.ndarray | slice) -> np.ndarray:
            """Eq. 4-1 of target k at cams[sel]; 0 for a secondary target that is inside an
            expanded occluder (recorded in `unrated`)."""
            try:
                f = field_for(k)
            except PlacementError as exc:
                if k == 0:
                    raise PlacementError(f'primary {exc}') from exc
                if k not in unrated:
                    unrated.append(k)
                return np.zeros(len(cams[sel]))
            return rate(cams[sel], targets[k], f, self.camera, p[sel],
                        exponents=self.exponents).rating

        def field_for(k: int) -> VisibilityField:
            if k in cache:
                return cache[k]
            t = targets[k]
            if fields is not None:
                f = fields[k]
            elif hulls is not None:
                f = VisibilityField(t.position, hulls, n_dirs=self.n_dirs)
            else:
                f = self._grid_field(grid, t, free_own=k == 0 and free_primary)
            cache[k] = f
            return f

        m = len(cams)
        ratings = np.full((len(targets), m), np.nan)       # nan: not evaluated
        extras = {'search': self.search, 'candidates': m}
        if self.search is Search.RANDOM or choose is Choose.RANDOM:
            for k in active:
                ratings[k] = rating_of(k, slice(None))
            extras.update(evaluated=m * len(active), exact=True)
        else:
            ub = np.zeros((len(targets), m))
            for k in active:
                ub[k] = self.rating_bound(cams, targets[k], p)
            flat = ub.ravel()
            order = np.argsort(-flat, kind='stable')
            order = order[flat[order] > 0]
            best, pos, batch = 0.0, 0, 64
            cap = min(len(order), self.max_candidates)
            while pos < cap and flat[order[pos]] > best:
                chunk = order[pos:min(pos + batch, cap)]
                ks, ii = np.divmod(chunk, m)
                for k in np.unique(ks):
                    sel = ii[ks == k]
                    r = rating_of(int(k), sel)
                    ratings[k, sel] = r
                    best = max(best, float(r.max()))
                pos += len(chunk)
                batch *= 2
            extras.update(evaluated=pos, pairs=len(order),
                          exact=bool(pos >= len(order) or flat[order[pos]] <= best))
        extras['unrated'] = sorted(unrated)
        if free_primary:
            held = tuple(cells_holding(grid, primary.position, primary.radius).T)
            known = grid.known[held]
            occ = (known & (grid.prob[held] >= 0.5)) | (~known & self.unknown_occludes)
            extras['freed_cells'] = int(occ.sum())
        seen = ~np.all(np.isnan(ratings), axis=0)
        r_all = np.where(np.isnan(ratings), -np.inf, ratings)
        best_t = np.argmax(r_all, axis=0)                   # ties: the lowest index (primary)
        best_rf = r_all[best_t, np.arange(m)]
        if not np.any(best_rf > 0):
            raise PlacementError('no candidate sees any target (all ratings are 0)')
        if choose is Choose.RANDOM:
            feasible = np.flatnonzero(best_rf > 0)
            extras.update(choose=choose, feasible=len(feasible))
            i = int(rng.choice(feasible))
        else:
            i = int(np.argmax(best_rf))
        k = int(best_t[i])
        tr = rate(cams[i:i + 1], targets[k], field_for(k), self.camera, p[i:i + 1],
                  exponents=self.exponents)
        return Placement(cams[i], k,
                         {'rating': float(best_rf[i]), 'dof': float(tr.dof[0]),
                          'res': float(tr.res[0]), 'tfv': float(tr.tfv[0]),
                          'tav': float(tr.tav[0]), 'collision_p': float(tr.collision_p[0])},
                         cams[seen], best_rf[seen], extras)


def move_known_object(grid: OccupancyGrid, old_cells: np.ndarray, model_cells: np.ndarray,
                      offset_cells: np.ndarray) -> np.ndarray:
    """§4.3.1 steps 1-4 for a moving object with a known model: its old cells become measured
    empty space, the model is inserted at its newly identified pose (integer cell offset).
    Returns the object's new cells."""
    old = np.asarray(old_cells, np.int64).reshape(-1, grid.ndim)
    ok = grid.in_bounds(old)
    grid.prob[tuple(old[ok].T)] = 0.0
    grid.known[tuple(old[ok].T)] = True
    new = np.asarray(model_cells, np.int64).reshape(-1, grid.ndim) + np.asarray(offset_cells)
    new = new[grid.in_bounds(new)]
    grid.prob[tuple(new.T)] = 1.0
    grid.known[tuple(new.T)] = True
    return new
