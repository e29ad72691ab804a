"""Dense occupancy-probability grids for view planning (thesis ch. 3.2, 3.2.4).

A grid holds, per voxel (3-D) or cell (2-D), a probability of occupancy and a `known` flag. The
planner takes only these numpy arrays, so it runs on the experiment worlds and on the live shared
map (`from_sparse` converts the sparse keys of coop_msgs/VoxelMap without importing any ROS code).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import assert_never

import numpy as np
from scipy import ndimage

from coop_common.params import choice

from .errors import OptionError, ViewplanError


class MapError(ViewplanError, ValueError):
    """The map cannot be used for planning (empty, malformed, inconsistent)."""


@dataclass
class OccupancyGrid:
    """Occupancy probabilities `prob` (0..1) with a `known` mask, both of shape (nx, ny[, nz]).

    Cell i spans [origin + i * resolution, origin + (i + 1) * resolution). Unknown cells' `prob`
    values are ignored by the planner (it uses the Markov-chain estimate instead).
    """

    prob: np.ndarray
    known: np.ndarray
    resolution: float
    origin: np.ndarray

    def __post_init__(self) -> None:
        self.prob = np.asarray(self.prob, dtype=np.float32)
        self.known = np.asarray(self.known, dtype=bool)
        self.origin = np.asarray(self.origin, dtype=float).reshape(-1)
        if self.prob.ndim not in (2, 3):
            raise MapError(f'grid must be 2-D or 3-D, got {self.prob.ndim}-D')
        if self.known.shape != self.prob.shape:
            raise MapError(f'known mask {self.known.shape} != prob {self.prob.shape}')
        if self.origin.shape != (self.prob.ndim,):
            raise MapError(f'origin must have {self.prob.ndim} coordinates')
        if not (np.isfinite(self.resolution) and self.resolution > 0):
            raise MapError(f'resolution must be > 0, got {self.resolution}')
        if np.any(~np.isfinite(self.prob[self.known])):
            raise MapError('known cells must have finite probabilities')

    @classmethod
    def empty(cls, shape: tuple[int, ...], *, resolution: float,
              origin: np.ndarray | None = None) -> OccupancyGrid:
        """An all-unknown grid (p = 0.5 everywhere)."""
        org = np.zeros(len(shape)) if origin is None else np.asarray(origin, dtype=float)
        return cls(np.full(shape, 0.5, np.float32), np.zeros(shape, bool), resolution, org)

    @classmethod
    def from_sparse(cls, keys: np.ndarray, occupancy: np.ndarray, *, resolution: float,
                    pad_cells: int = 0, bounds_keys: tuple[np.ndarray, np.ndarray] | None = None
                    ) -> OccupancyGrid:
        """Dense grid from sparse integer voxel keys (N, 3) = floor(p / resolution) and their
        occupancy; absent keys are unknown (the coop_msgs/VoxelSet convention).

        The grid spans the keys' bounding box grown by `pad_cells`, or `bounds_keys` (lo, hi)
        inclusive if given."""
        keys = np.asarray(keys, dtype=np.int64)
        occ = np.asarray(occupancy, dtype=np.float32).reshape(-1)
        if keys.ndim != 2 or keys.shape[1] not in (2, 3):
            raise MapError(f'keys must be (N, 2|3), got {keys.shape}')
        if keys.shape[0] == 0:
            raise MapError('empty map: no known voxels')
        if occ.shape[0] != keys.shape[0]:
            raise MapError(f'{keys.shape[0]} keys but {occ.shape[0]} occupancies')
        if np.any(~np.isfinite(occ)) or np.any((occ < 0) | (occ > 1)):
            raise MapError('occupancy must be finite and within 0..1')
        if bounds_keys is None:
            lo = keys.min(axis=0) - pad_cells
            hi = keys.max(axis=0) + pad_cells
        else:
            lo, hi = (np.asarray(b, dtype=np.int64) for b in bounds_keys)
        shape = tuple(int(s) for s in hi - lo + 1)
        grid = cls.empty(shape, resolution=resolution, origin=lo * resolution)
        inside = np.all((keys >= lo) & (keys <= hi), axis=1)
        idx = tuple((keys[inside] - lo).T)
        grid.prob[idx] = occ[inside]
        grid.known[idx] = True
        return grid

    @property
    def ndim(self) -> int:
        return self.prob.ndim

    @property
    def shape(self) -> tuple[int, ...]:
        return self.prob.shape

    def to_index(self, points: np.ndarray) -> np.ndarray:
        """Integer cell index of world points (..., ndim); may lie outside the grid."""
        return np.floor((np.asarray(points, dtype=float) - self.origin)
                        / self.resolution).astype(np.int64)

    def to_world(self, index: np.ndarray) -> np.ndarray:
        """World coordinates of cell centres."""
        return self.origin + (np.asarray(index, dtype=float) + 0.5) * self.resolution

    def in_bounds(self, index: np.ndarray) -> np.ndarray:
        index = np.asarray(index)
        return np.all((index >= 0) & (index < np.array(self.shape)), axis=-1)

    def occupied(self, *, threshold: float = 0.5) -> np.ndarray:
        """Known cells that block sight (p >= threshold)."""
        return self.known & (self.prob >= threshold)

    def free(self, *, p_empty: float = 0.05) -> np.ndarray:
        """Known cells with P < P_empty (thesis §3.2.4 (i): 0.05, 2 sigma)."""
        return self.known & (self.prob < p_empty)


def planning_bounds(keys: np.ndarray, resolution: float, *, pad_m: float,
                    ceiling_m: float = 0.0, camera_height_m: float = 0.0
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Inclusive key bounds (lo, hi) of the planning grid over a 3-D map's keys (N, 3): the
    keys' box grown by pad_m on every side, except upwards when `ceiling_m` > 0: then the top
    is the highest of the map's own top, the ceiling (z, map frame) and one voxel above the
    cameras (`camera_height_m`, so a camera cell is always inside). Stereo on a mast never
    maps the air above its cameras (no ray ends there, so none crosses it), yet every unknown
    voxel in a frustum counts as new information, so padding upwards made views that look up
    pay for air that can never become known."""
    keys = np.asarray(keys, dtype=np.int64)
    if keys.ndim != 2 or keys.shape[1] != 3 or keys.shape[0] == 0:
        raise MapError(f'keys must be (N, 3) with N > 0, got {keys.shape}')
    if not (resolution > 0 and pad_m >= 0):
        raise ValueError('resolution must be > 0 and pad_m >= 0')
    if not pad_m / resolution < 2 ** 31 or not abs(camera_height_m) / resolution < 2 ** 31 \
            or not ceiling_m / resolution < 2 ** 31:
        raise MapError(f'resolution {resolution} m: the pad, ceiling or camera height is more '
                       'than 2^31 voxels')
    pad = int(np.ceil(pad_m / resolution))
    lo = keys.min(axis=0) - pad
    hi = keys.max(axis=0) + pad
    if ceiling_m > 0:
        top_m = max(ceiling_m, camera_height_m + resolution)
        hi[2] = max(int(keys[:, 2].max()), int(np.floor(top_m / resolution)))
    return lo, hi


class EmptyMapError(MapError):
    """The map holds no voxel: nothing to plan on yet (a state, not a defect)."""


def planning_grid(keys: np.ndarray, occupancy: np.ndarray, resolution: float, *, pad_m: float,
                  ceiling_m: float = 0.0, camera_height_m: float = 0.0,
                  max_cells: int | None = None) -> OccupancyGrid:
    """The dense planning grid of a sparse voxel map (keys (N, 3) or flat, occupancy (N,)), with
    the checks the `view_planner` node and `coop_viewplan.offline` both apply: a positive finite
    resolution, one occupancy per key, at least one voxel (EmptyMapError), at most `max_cells`
    cells (a far outlier voxel or a tiny resolution would make a huge grid), and
    `from_sparse`'s own. MapError with the reason otherwise."""
    keys = np.asarray(keys, dtype=np.int64)
    occ = np.asarray(occupancy, dtype=np.float32).reshape(-1)
    if not (resolution > 0 and math.isfinite(resolution)):
        raise MapError(f'bad resolution: {resolution}')
    if keys.size % 3 or keys.size // 3 != occ.size:
        raise MapError(f'malformed voxel set: {keys.size} keys, {occ.size} occupancies')
    if occ.size == 0:
        raise EmptyMapError('empty map: no voxels')
    k3 = keys.reshape(-1, 3)
    bounds = planning_bounds(k3, resolution, pad_m=pad_m, ceiling_m=ceiling_m,
                             camera_height_m=camera_height_m)
    cells = math.prod(int(h) - int(lo) + 1 for lo, h in zip(*bounds, strict=False))
    if max_cells is not None and cells > max_cells:
        raise MapError(f'the planning grid would have {cells} cells > max_grid_cells '
                       f'{max_cells}')
    return OccupancyGrid.from_sparse(k3, occ, resolution=resolution, bounds_keys=bounds)


def markov_estimate(grid: OccupancyGrid, *, iterations: int = 6,
                    prior: float = 0.5) -> np.ndarray:
    """Occupancy estimate for every cell: known cells keep their probability, unknown ones get the
    Markov-chain estimate of §3.2.4 ("p of a voxel is the average of p of its neighbours"),
    found by Jacobi iteration of the neighbour average with the known cells held fixed.

    Unknown cells far from anything known (beyond `iterations` cells) stay at `prior` (0.5, the
    thesis's "nothing known"); unknown cells next to known free space lean towards free, next to
    obstacles towards occupied."""
    if iterations < 0:
        raise ValueError('iterations must be >= 0')
    if not 0.0 <= prior <= 1.0:
        raise ValueError(f'prior must be within 0..1, got {prior}')
    est = np.where(grid.known, grid.prob, np.float32(prior)).astype(np.float32)
    unknown = ~grid.known
    for _ in range(iterations):
        avg = ndimage.uniform_filter(est, size=3, mode='nearest')
        est[unknown] = avg[unknown]
    return est


class FreeGray(StrEnum):
    """The gray of a known free cell: 'empty' (NI 0, the thesis) or 'occupancy' (its P)."""

    EMPTY = 'empty'
    OCCUPANCY = 'occupancy'


FREE_GRAYS = tuple(FreeGray)


def gray_estimate(grid: OccupancyGrid, *, free_gray: FreeGray | str = FreeGray.EMPTY,
                  iterations: int = 6, prior: float = 0.5) -> np.ndarray:
    """Gray values of NI (§3.2.4): known cells their occupancy, unknown ones the Markov-chain
    average of their neighbours (`markov_estimate`). free_gray 'empty': a known cell the map holds
    free (p < 0.5: crossed by rays, no range point kept it occupied) is empty space, gray 0 - the
    thesis tabulates empty space in the field of view "as known, but with no contribution to the
    uncertainty model" (§3.3.2), and "if every point in the field of view is known and is empty
    then NI = 0" (§3.2.4); 'occupancy': the map's own probability (a log-odds map leaves 0.40
    after one miss, whose -p log2 p = 0.53 outweighs an unknown cell's 0.5). Another
    free_gray is refused (OptionError naming the choices)."""
    free_gray = choice(FreeGray, free_gray, 'free_gray', error=OptionError)
    match free_gray:
        case FreeGray.OCCUPANCY:
            return markov_estimate(grid, iterations=iterations, prior=prior)
        case FreeGray.EMPTY:
            empty = grid.known & (grid.prob < 0.5)
            gray = OccupancyGrid(np.where(empty, np.float32(0.0), grid.prob), grid.known,
                                 resolution=grid.resolution, origin=grid.origin)
            return markov_estimate(gray, iterations=iterations, prior=prior)
        case _:
            assert_never(free_gray)


def obstacle_density(grid: OccupancyGrid, *, threshold: float = 0.5) -> float:
    """Share of the known cells that are occupied (p >= threshold): an occupancy prior for
    unknown space from the map itself (0.5 when nothing is known)."""
    n = int(grid.known.sum())
    return float(grid.occupied(threshold=threshold).sum() / n) if n else 0.5


class OcclusionPrior(StrEnum):
    """The occupancy expected of unknown cells: 'markov' or 'density' (occlusion_estimate)."""

    MARKOV = 'markov'
    DENSITY = 'density'


OCCLUSION_PRIORS = tuple(OcclusionPrior)


def occlusion_estimate(grid: OccupancyGrid, *,
                       prior: OcclusionPrior | str = OcclusionPrior.DENSITY,
                       free_gray: FreeGray | str = FreeGray.EMPTY, iterations: int = 6,
                       gray: np.ndarray | None = None) -> np.ndarray:
    """Per-cell probability that a cell stops a ray, for the occlusion-aware expected view
    (`NbvConfig.unknown_occlusion = 'expected'`, beyond the thesis): known cells their occupancy
    (known free 0 under free_gray 'empty', as in NI's gray values), unknown ones the Markov-chain
    estimate. prior 'markov': the planner's gray estimate as it is (unknown space far from the
    map at 0.5); 'density': the same Markov chain started from the map's obstacle density
    (`obstacle_density`) instead of 0.5, so unknown space far from the map is as cluttered as
    the known map. `gray`: the 'markov' estimate if already computed. Another prior or
    free_gray is refused (OptionError naming the choices)."""
    prior = choice(OcclusionPrior, prior, 'prior', error=OptionError)
    free_gray = choice(FreeGray, free_gray, 'free_gray', error=OptionError)
    match prior:
        case OcclusionPrior.MARKOV:
            est = gray if gray is not None else gray_estimate(grid, free_gray=free_gray,
                                                              iterations=iterations)
        case OcclusionPrior.DENSITY:
            est = gray_estimate(grid, free_gray=free_gray, iterations=iterations,
                                prior=obstacle_density(grid))
        case _:
            assert_never(prior)
    return np.asarray(est, np.float32)
