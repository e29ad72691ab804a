"""Vectorised visibility of camera frustums on an occupancy grid (thesis Fig. 3-8).

A frustum is sampled by a fixed template of rays (azimuth x elevation) and range steps in the
camera frame; every candidate pose rotates and translates the same template, so one numpy gather
casts all rays of all candidates at once. Each sample carries a quadrature weight (the number of
cells it stands for: r dtheta dr / res^2 in 2-D, r^2 cos(el) dtheta dphi dr / res^3 in 3-D), so
sums of weights over visible samples estimate voxel counts without deduplication.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .grid import OccupancyGrid


@dataclass(frozen=True)
class RayTemplate:
    """Ray directions (R, ndim) in the camera frame (forward = +x), sample ranges (S,), and
    per-sample quadrature weights (R, S) in cells."""

    directions: np.ndarray
    ranges: np.ndarray
    weights: np.ndarray
    depth_m: float
    fov_rad: float

    @property
    def ndim(self) -> int:
        return self.directions.shape[1]

    @property
    def frustum_cells(self) -> float:
        """N of Eq. 3-13: the number of cells visible with nothing in the way."""
        return float(self.weights.sum())


def make_template(*, ndim: int, fov_deg: float, depth_m: float, resolution: float,
                  n_az: int | None = None, n_el: int | None = None,
                  vfov_deg: float | None = None, step_cells: float = 0.5,
                  min_range_m: float = 0.0) -> RayTemplate:
    """A frustum template. By default rays are spaced so neighbouring rays are one cell apart at
    the depth of field (every cell is sampled); pass n_az / n_el to thin them (the NI estimate
    then remains a quadrature of the same sum)."""
    if ndim not in (2, 3):
        raise ValueError('ndim must be 2 or 3')
    if not 0 < fov_deg < 180:
        raise ValueError(f'fov_deg must be in (0, 180), got {fov_deg}')
    if not (depth_m > 0 and resolution > 0 and step_cells > 0):
        raise ValueError('depth_m, resolution and step_cells must be > 0')
    fov = np.radians(fov_deg)
    if n_az is None:
        n_az = max(2, int(np.ceil(fov * depth_m / resolution)) + 1)
    step = step_cells * resolution
    n_steps = max(1, int(np.ceil((depth_m - min_range_m) / step)))
    ranges = min_range_m + (np.arange(n_steps) + 0.5) * step
    ranges = ranges[ranges <= depth_m]
    if len(ranges) == 0:
        raise ValueError(f'depth_m {depth_m} holds no sample at {step} m steps (depth below '
                         'half a sample step of the grid)')
    dr = step
    az = (np.arange(n_az) + 0.5) / n_az * fov - fov / 2
    daz = fov / n_az
    if ndim == 2:
        dirs = np.stack([np.cos(az), np.sin(az)], axis=1)
        w = np.outer(np.full(n_az, daz), ranges * dr) / resolution ** 2
    else:
        vfov = np.radians(vfov_deg if vfov_deg is not None else fov_deg * 0.75)
        if n_el is None:
            n_el = max(2, int(np.ceil(vfov * depth_m / resolution)) + 1)
        el = (np.arange(n_el) + 0.5) / n_el * vfov - vfov / 2
        delv = vfov / n_el
        a, e = np.meshgrid(az, el, indexing='ij')
        a, e = a.ravel(), e.ravel()
        dirs = np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)
        w = np.outer(np.cos(e) * daz * delv, ranges ** 2 * dr) / resolution ** 3
    return RayTemplate(dirs, ranges, w.astype(np.float32), float(depth_m), float(fov))


def rotations(yaw: np.ndarray, pitch: np.ndarray | None = None) -> np.ndarray:
    """Camera-to-map rotations (M, ndim, ndim): yaw about z, then pitch (positive = nose down,
    REP 103 about the camera's y axis). 2-D when pitch is None."""
    yaw = np.asarray(yaw, dtype=float).reshape(-1)
    cy, sy = np.cos(yaw), np.sin(yaw)
    if pitch is None:
        return np.stack([np.stack([cy, -sy], -1), np.stack([sy, cy], -1)], axis=1)
    pitch = np.broadcast_to(np.asarray(pitch, dtype=float).reshape(-1), yaw.shape)
    cp, sp = np.cos(pitch), np.sin(pitch)
    z, o = np.zeros_like(yaw), np.ones_like(yaw)
    rz = np.stack([np.stack([cy, -sy, z], -1), np.stack([sy, cy, z], -1),
                   np.stack([z, z, o], -1)], axis=1)
    ry = np.stack([np.stack([cp, z, sp], -1), np.stack([z, o, z], -1),
                   np.stack([-sp, z, cp], -1)], axis=1)
    return rz @ ry


@dataclass
class Cast:
    """Result of casting a template from M poses: flat cell index per sample (-1 outside the
    grid), visibility per sample (first blocking cell included), and the template."""

    flat: np.ndarray
    visible: np.ndarray
    template: RayTemplate


def cast(grid: OccupancyGrid, positions: np.ndarray, yaw: np.ndarray,
         pitch: np.ndarray | None, template: RayTemplate, *,
         blocking: np.ndarray | None = None) -> Cast:
    """Cast the template from every pose. A sample is visible when no blocking cell lies before
    it on its ray; the first blocking cell itself is visible (its surface is measured). Cells
    outside the grid block. `blocking` defaults to the known occupied cells (p >= 0.5): the
    expected view accounts for known occlusions only (§3.2.4 (iv))."""
    positions = np.asarray(positions, dtype=float).reshape(-1, grid.ndim)
    if template.ndim != grid.ndim:
        raise ValueError(f'template is {template.ndim}-D, grid {grid.ndim}-D')
    rot = rotations(yaw, pitch if grid.ndim == 3 else None)
    if rot.shape[0] != positions.shape[0]:
        raise ValueError('one yaw (and pitch) per position')
    world_dirs = np.einsum('mij,rj->mri', rot, template.directions).astype(np.float32)
    cells = ((positions - grid.origin) / grid.resolution).astype(np.float32)   # (M, D)
    steps = (template.ranges / grid.resolution).astype(np.float32)            # (S,)
    shape = grid.shape
    itype = np.int32 if grid.prob.size < 2 ** 31 - 1 else np.int64
    flat: np.ndarray | None = None
    inb: np.ndarray | None = None
    # Per axis, so no (M, R, S, D) temporaries: index = floor(cell + dir * range).
    for ax in range(grid.ndim):
        c = np.floor(cells[:, ax, None, None] + world_dirs[:, :, ax, None] * steps[None, None, :])
        i = c.astype(itype)
        ok = (i >= 0) & (i < shape[ax])
        inb = ok if inb is None else inb & ok
        flat = i if flat is None else flat * itype(shape[ax]) + i
    assert flat is not None and inb is not None         # a grid has 2 or 3 axes
    np.copyto(flat, -1, where=~inb)
    block = grid.occupied() if blocking is None else np.asarray(blocking, dtype=bool)
    blk = block.reshape(-1)[np.maximum(flat, 0)]
    blk |= ~inb
    # Visible: nothing blocking strictly before the sample on its ray.
    seen_block = np.logical_or.accumulate(blk, axis=2)
    visible = inb.copy()
    visible[:, :, 1:] &= ~seen_block[:, :, :-1]
    return Cast(flat, visible, template)


def transmission_table(stop_p: np.ndarray, *, p_max: float = 0.999) -> np.ndarray:
    """log(1 - p) per flat cell (float32) for `expected_visibility`, with one trailing 0 that
    the index -1 (outside the grid) picks. Build it once per map: it is as long as the grid. p is
    capped at `p_max` so the logs stay finite."""
    p = np.clip(np.asarray(stop_p, np.float32).reshape(-1), 0.0, p_max)
    out = np.zeros(p.size + 1, np.float32)
    np.log1p(-p, out=out[:-1])
    return out


def expected_visibility(casting: Cast, stop_p: np.ndarray | None = None, *,
                        table: np.ndarray | None = None, p_max: float = 0.999,
                        compact: bool = False) -> np.ndarray:
    """Probability that each sample of `casting` is seen: 0 where it is not visible past the
    known obstacles, else prod over the distinct cells j before the sample's cell on its ray of
    (1 - p_j), with p_j = `stop_p` (per cell, grid shape or flat; or `table`, its
    `transmission_table`) - the occlusion-aware expected view (Isler et al. 2016; beyond the
    thesis, whose expected view accounts for the known obstacles only). A straight ray leaves a
    cell for good, so a cell's factor enters once, at the last sample of its run; the sample's
    own cell does not occlude it (its surface is what is measured).

    Returns (M, R, S) float32, or with `compact` only the visible samples' values, in the order
    of np.nonzero(casting.visible)."""
    if table is None:
        if stop_p is None:
            raise ValueError('stop_p or table is required')
        table = transmission_table(stop_p, p_max=p_max)
    flat = casting.flat
    lg = table[flat]                   # -1 (outside) picks the trailing 0
    # the factor of a cell enters after its last sample: where the next sample is another cell
    lg[:, :, :-1] *= flat[:, :, :-1] != flat[:, :, 1:]
    acc = np.empty_like(lg)
    acc[:, :, 0] = 0.0                 # exclusive: cells strictly before the sample's cell
    np.cumsum(lg[:, :, :-1], axis=2, out=acc[:, :, 1:])
    if compact:
        return np.exp(acc[casting.visible])
    vis = np.exp(acc, out=acc)
    vis *= casting.visible
    return vis


def ray_prefix_visibility(cells: np.ndarray, sample: np.ndarray,
                          table: np.ndarray) -> np.ndarray:
    """`expected_visibility` on the visible samples only (float32): `cells` their flat cell
    indices listed ray by ray (np.nonzero order of Cast.visible), `sample` their index s along
    their ray. The visible samples of a ray are a prefix of it (whatever blocks hides the rest),
    so the sample s of a ray sits s places after the ray's first one in this list, and one
    running sum with the ray's start subtracted gives every ray's exclusive product."""
    cells = np.asarray(cells)
    n = cells.shape[0]
    if n == 0:
        return np.zeros(0, np.float32)
    lg = table[cells]
    lg[:-1] *= cells[:-1] != cells[1:]       # a cell's factor enters at its last sample
    acc = np.cumsum(lg, dtype=np.float64)
    acc -= lg                                # exclusive
    acc -= acc[np.arange(n) - np.asarray(sample)]
    return np.exp(acc.astype(np.float32))
