"""Planar exploration worlds and the mapping loop behind Figs. 3-13, 3-16, 3-20 (§3.3.1).

The worlds are ground truth for the simulated range sensor only; the planner sees nothing but the
map it builds from the scans.
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import assert_never

import numpy as np
from scipy import ndimage

from .errors import OptionError
from .grid import OccupancyGrid
from .nbv import (
    CameraState,
    NbvConfig,
    NextBestViewPlanner,
    PlanningError,
    StrategyName,
    _disk,
    plan_cameras,
)
from .raycast import cast


@dataclass
class World:
    """A planar world: occupied cells (nx, ny), resolution (m), start cell, name; for the rooms
    world the start room, (x0, x1, y0, y1) cell bounds inclusive of its walls."""

    occupied: np.ndarray
    resolution: float
    start: tuple[int, int]
    name: str
    start_room: tuple[int, int, int, int] | None = None

    def in_start_room(self, cells: np.ndarray) -> np.ndarray:
        """(N, 2) cells -> (N,) bool: inside the start room's walls (all True without a room)."""
        c = np.asarray(cells).reshape(-1, 2)
        if self.start_room is None:
            return np.ones(len(c), bool)
        x0, x1, y0, y1 = self.start_room
        return (c[:, 0] >= x0) & (c[:, 0] <= x1) & (c[:, 1] >= y0) & (c[:, 1] <= y1)

    def start_room_cells(self) -> np.ndarray | None:
        """The mappable cells of the start room (its free interior and walls), or None."""
        if self.start_room is None:
            return None
        x0, x1, y0, y1 = self.start_room
        m = np.zeros_like(self.occupied)
        m[x0:x1 + 1, y0:y1 + 1] = True
        return m & self.mappable()

    def mappable(self) -> np.ndarray:
        """Cells a perfect explorer could map: the free space connected to the start and the
        obstacle cells bordering it (the denominator of "fraction of environment modelled")."""
        free = ~self.occupied
        lab, _ = ndimage.label(free, structure=np.ones((3, 3), bool))
        comp = lab == lab[self.start]
        border = ndimage.binary_dilation(comp, structure=np.ones((3, 3), bool)) & self.occupied
        return comp | border


def _free_start(occ: np.ndarray, rng: np.random.Generator, clearance: int,
                region: tuple[slice, slice] | None = None) -> tuple[int, int]:
    clear = ~ndimage.binary_dilation(occ, structure=_disk(clearance + 1, 2))
    if region is not None:
        mask = np.zeros_like(clear)
        mask[region] = True
        clear &= mask
    cells = np.argwhere(clear)
    if len(cells) == 0:
        raise ValueError('no free start cell')
    c = cells[rng.integers(len(cells))]
    return int(c[0]), int(c[1])


def unstructured_world(*, seed: int, size_m: float = 100.0, resolution: float = 1.0,
                       coverage: float = 0.15, clearance_cells: int = 1) -> World:
    """Fig. 3-12: a 100 m x 100 m field scattered with irregular obstacles (random discs,
    rectangles and rotated blocks of 1..8 m) until `coverage` of the area is occupied."""
    rng = np.random.default_rng(seed)
    n = round(size_m / resolution)
    occ = np.zeros((n, n), bool)
    xx, yy = np.meshgrid((np.arange(n) + 0.5) * resolution, (np.arange(n) + 0.5) * resolution,
                         indexing='ij')
    while occ.mean() < coverage:
        cx, cy = rng.uniform(0, size_m, 2)
        kind = rng.integers(3)
        if kind == 0:
            r = rng.uniform(1.0, 5.0)
            occ |= (xx - cx) ** 2 + (yy - cy) ** 2 <= r * r
        else:
            a, b = rng.uniform(1.0, 8.0, 2)
            if kind == 2:
                b = rng.uniform(0.8, 2.0)    # wall-like slab
            th = rng.uniform(0, np.pi)
            u = (xx - cx) * np.cos(th) + (yy - cy) * np.sin(th)
            v = -(xx - cx) * np.sin(th) + (yy - cy) * np.cos(th)
            occ |= (np.abs(u) <= a / 2) & (np.abs(v) <= b / 2)
    start = _free_start(occ, rng, clearance_cells)
    return World(occ, resolution, start, 'unstructured')


def rooms_world(*, seed: int, size_m: float = 100.0, resolution: float = 1.0,
                clearance_cells: int = 1) -> World:
    """Fig. 3-19: an indoor-type 100 m x 100 m plan - a cross of 6 m corridors and 2 x 2 rooms
    per quadrant, each with a 4 m door onto a corridor and some furniture; the camera starts in
    a room."""
    rng = np.random.default_rng(seed)
    n = round(size_m / resolution)
    occ = np.zeros((n, n), bool)
    c = lambda m: round(m / resolution)  # noqa: E731
    occ[0, :] = occ[-1, :] = occ[:, 0] = occ[:, -1] = True
    lo, hi = c(size_m / 2 - 3), c(size_m / 2 + 3)
    occ[lo, :] = occ[hi, :] = occ[:, lo] = occ[:, hi] = True
    occ[lo + 1:hi, :] = False
    occ[:, lo + 1:hi] = False
    # Dividing walls inside each quadrant: rooms of about 23 m.
    rooms = []
    for qx in ((0, lo), (hi, n - 1)):
        for qy in ((0, lo), (hi, n - 1)):
            mx, my = (qx[0] + qx[1]) // 2, (qy[0] + qy[1]) // 2
            occ[mx, qy[0]:qy[1] + 1] = True
            occ[qx[0]:qx[1] + 1, my] = True
            for rx in ((qx[0], mx), (mx, qx[1])):
                for ry in ((qy[0], my), (my, qy[1])):
                    rooms.append((rx, ry))
    door = c(4.0)
    corr = (lo + hi) / 2
    for rx, ry in rooms:
        # door on the room wall nearest a corridor
        dx = min(abs(rx[0] - corr), abs(rx[1] - corr))
        dy = min(abs(ry[0] - corr), abs(ry[1] - corr))
        if dx <= dy:
            wx = rx[0] if abs(rx[0] - corr) < abs(rx[1] - corr) else rx[1]
            s = int(rng.integers(ry[0] + 2, max(ry[0] + 3, ry[1] - door - 1)))
            occ[wx, s:s + door] = False
        else:
            wy = ry[0] if abs(ry[0] - corr) < abs(ry[1] - corr) else ry[1]
            s = int(rng.integers(rx[0] + 2, max(rx[0] + 3, rx[1] - door - 1)))
            occ[s:s + door, wy] = False
        for _ in range(2):   # furniture
            w, h = rng.integers(c(1.0), c(4.0) + 1, 2)
            x0 = int(rng.integers(rx[0] + 4, max(rx[0] + 5, rx[1] - w - 3)))
            y0 = int(rng.integers(ry[0] + 4, max(ry[0] + 5, ry[1] - h - 3)))
            occ[x0:x0 + w, y0:y0 + h] = True
    rx, ry = rooms[int(rng.integers(len(rooms)))]
    start = _free_start(occ, rng, clearance_cells,
                        (slice(rx[0] + 1, rx[1]), slice(ry[0] + 1, ry[1])))
    return World(occ, resolution, start, 'rooms',
                 start_room=(int(rx[0]), int(rx[1]), int(ry[0]), int(ry[1])))


def png_world(path: str | Path, *, resolution: float = 1.0, seed: int = 0,
              clearance_cells: int = 1) -> World:
    """A world from an image: dark pixels (< 0.5 gray) are obstacles; row 0 is the top (+y)."""
    import matplotlib.image as mpimg  # noqa: PLC0415 - heavy, only to read a PNG world
    img = np.asarray(mpimg.imread(str(path)), dtype=float)
    if img.ndim == 3:
        img = img[..., :3].mean(axis=2)
    if img.max() > 1.0:
        img = img / 255.0
    occ = (img < 0.5)[::-1].T.copy()
    start = _free_start(occ, np.random.default_rng(seed), clearance_cells)
    return World(occ, resolution, start, Path(path).stem)


class WorldName(StrEnum):
    """The generated worlds: Fig. 3-12's unstructured field, Fig. 3-19's rooms."""

    UNSTRUCTURED = 'unstructured'
    ROOMS = 'rooms'


def make_world(name: WorldName | str | Path, *, seed: int, resolution: float = 1.0) -> World:
    """A generated world by its WorldName, or a PNG world from an existing .png file;
    OptionError naming both otherwise."""
    if name in tuple(WorldName):
        world = WorldName(name)
        match world:
            case WorldName.UNSTRUCTURED:
                return unstructured_world(seed=seed, resolution=resolution)
            case WorldName.ROOMS:
                return rooms_world(seed=seed, resolution=resolution)
            case _:
                assert_never(world)
    if Path(name).suffix.lower() == '.png' and Path(name).is_file():
        return png_world(name, resolution=resolution, seed=seed)
    raise OptionError(f'unknown world {str(name)!r}: one of {[w.value for w in WorldName]} or '
                      'an existing .png file')


def scan(world: World, grid: OccupancyGrid, planner: NextBestViewPlanner,
         position: np.ndarray, yaw: float) -> None:
    """Simulated range scan: every cell in the field of view up to and including the first
    obstacle on each ray becomes known (free 0, occupied 1)."""
    c = cast(grid, np.asarray(position)[None], np.array([yaw]), None, planner.template(grid),
             blocking=world.occupied)
    cells = c.flat[c.visible]
    grid.known.reshape(-1)[cells] = True
    grid.prob.reshape(-1)[cells] = world.occupied.reshape(-1)[cells].astype(np.float32)


@dataclass
class Trace:
    """One run: fraction mapped and cumulative distance after scan k = 0..scans, paths (every
    camera's position at each scan until the world is mapped), and the fraction of the start
    room mapped (rooms world)."""

    fraction: np.ndarray
    distance: np.ndarray
    paths: list
    room_fraction: np.ndarray | None = None

    def scans_to_leave_start_room(self, world: World) -> int | None:
        """The first scan taken by a camera outside the start room, or None."""
        if world.start_room is None:
            return None
        n = min(len(p) for p in self.paths)
        for k in range(n):
            # explore's grid has its origin at cell (0, 0)'s corner
            cells = np.array([np.floor(p[k] / world.resolution).astype(int)
                              for p in self.paths])
            if not world.in_start_room(cells).all():
                return k
        return None


def explore(world: World, *, strategy: StrategyName | str, n_cameras: int, config: NbvConfig,
            scans: int, seed: int) -> Trace:
    """Map `world` with `n_cameras` cameras for `scans` scan steps (every camera scans once per
    step; distance is summed over cameras)."""
    rng = np.random.default_rng(seed)
    planner = NextBestViewPlanner(config)
    grid = OccupancyGrid.empty(world.occupied.shape, resolution=world.resolution)
    mappable = world.mappable()
    total = mappable.sum()
    room = world.start_room_cells()
    cams = []
    clear = int(np.ceil(config.clearance_m / world.resolution))
    for k in range(n_cameras):
        cell = np.array(world.start) + np.array([0, 2 * k])
        if np.any(cell >= world.occupied.shape) or world.occupied[tuple(cell)]:
            cell = np.array(world.start)
        pos = grid.to_world(cell)
        cams.append(CameraState(pos, yaw=float(rng.uniform(0, 2 * np.pi))))
        # The rover knows the ground it stands on.
        ii, jj = np.indices(world.occupied.shape)
        foot = ((ii - cell[0]) ** 2 + (jj - cell[1]) ** 2 <= (clear + 1) ** 2) & ~world.occupied
        grid.known[foot] = True
        grid.prob[foot] = 0.0
    for cam in cams:
        scan(world, grid, planner, cam.position, cam.yaw)
        cam.visited.append(grid.to_index(cam.position))
    frac = [float((grid.known & mappable).sum() / total)]
    room_frac = [] if room is None else [float((grid.known & room).sum() / room.sum())]
    dist = [0.0]
    paths = [[c.position.copy()] for c in cams]
    for _ in range(scans):
        moved = 0.0
        if frac[-1] < 0.999:
            try:
                decisions = plan_cameras(planner, grid, cams, strategy=strategy, rng=rng)
            except PlanningError:
                decisions = []
            for cam, d, path in zip(cams, decisions, paths, strict=False):
                moved += d.path_length if np.isfinite(d.path_length) else 0.0
                cam.position = d.position.copy()
                cam.yaw = d.yaw
                cam.visited.append(grid.to_index(cam.position))
                path.append(cam.position.copy())
            for cam, path in zip(cams[len(decisions):], paths[len(decisions):], strict=False):
                path.append(cam.position.copy())   # no admissible view: it scans from here again
            for cam in cams:
                scan(world, grid, planner, cam.position, cam.yaw)
        frac.append(float((grid.known & mappable).sum() / total))
        if room is not None:
            room_frac.append(float((grid.known & room).sum() / room.sum()))
        dist.append(dist[-1] + moved)
    return Trace(np.array(frac), np.array(dist), [np.array(p) for p in paths],
                 None if room is None else np.array(room_frac))
