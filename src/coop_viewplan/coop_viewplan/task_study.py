"""The Table 4-1 study (§4.3.1): a camera guides a moving object to an insertion site; the task
succeeds if the target stays in view for the whole approach and the final measurement of the
object-goal distance is within tolerance.

The thesis gives the outcome table but not the scenario's numbers; the ones below are chosen
once, a priori, and documented (they are not fitted to the table):
* 60 m x 60 m planar world at 0.5 m, random discs and boxes to the occlusion density, a 2 m clear
  zone around each target (`StudyConfig.clear_zone_m`, cells whose centre lies within it are kept
  free) and a clear corridor for the object's path; whatever the clear zone, a target never lies
  inside an (expanded) occluder hull: where one would, that target's clear zone is widened in
  half-cell steps until it does not (never needed at the default 2 m);
* primary target (the insertion site) at the centre, one-sided with a random normal, radius
  0.25 m; a secondary target 8..15 m away with its own normal and a 5 mm (1 sigma) uncertainty of
  its geometric relation to the primary (ST_error, Eq. 4-4);
* the object (1 m radius with its carrier) approaches from 15 m in 8 steps and stops 2 m short;
  its model updates the map at every step (§4.3.1 steps 1-4);
* camera: 60 deg FOV, 640 pixels, depth of field 1..20 m, 0.5 m mount clearance; a target is
  seen when its line of sight is clear (expanded hulls), it faces the camera (TAV > 0) and lies
  inside the depth of field;
* final error ~ N(0, (kappa R / TAV)^2) with R of Eq. 4-2 and kappa = 1 pixel, plus the
  secondary target's relation error when guiding by the secondary; tolerance is a fraction of
  the 0.5 m insertion scale.
Methods: optimal re-placement (Eq. 4-1 maximised at every step over primary and secondary, by
the distance-bounded search of `TaskPlacer`: the maximum over every free cell in the depth of
field, not over a random subset of them);
biased random re-placement (a random free spot in the depth of field with a clear line of sight,
re-drawn when the target is lost); biased random fixed placement (drawn once).
"""
from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import assert_never

import numpy as np

from coop_common.params import choice

from .grid import OccupancyGrid
from .placement import (
    CameraModel,
    PlacementError,
    Search,
    Target,
    TaskPlacer,
    VisibilityField,
    angular_visibility,
    depth_of_field,
    grid_occluders,
    move_known_object,
    occluder_hulls,
    occlusion_distance,
)


class Method(StrEnum):
    """How the camera is placed (Table 4-1's rows): Eq. 4-1 maximised at every step, a
    biased random spot re-drawn when the target is lost, or one drawn once."""

    OPTIMAL_REPLACEMENT = 'optimal_replacement'
    RANDOM_REPLACEMENT = 'random_replacement'
    RANDOM_FIXED = 'random_fixed'


METHODS = tuple(Method)
DENSITIES = (0.05, 0.20, 0.35)
TOLERANCES = (0.20, 0.10, 0.01)

#: Table 4-1 as printed (success %, "<<1" as 0.1); [tolerance][method][density][secondary].
THESIS_TABLE_4_1: dict[float, dict[Method, list[list[float]]]] = {
    0.20: {Method.OPTIMAL_REPLACEMENT: [[100, 100], [76, 95], [13, 25]],
           Method.RANDOM_REPLACEMENT: [[51, 63], [18, 31], [5, 10]],
           Method.RANDOM_FIXED: [[45, 58], [16, 28], [5, 9]]},
    0.10: {Method.OPTIMAL_REPLACEMENT: [[99, 100], [63, 86], [10, 18]],
           Method.RANDOM_REPLACEMENT: [[30, 37], [11, 18], [3, 6]],
           Method.RANDOM_FIXED: [[23, 30], [8, 15], [3, 4]]},
    0.01: {Method.OPTIMAL_REPLACEMENT: [[97, 99], [30, 52], [3, 7]],
           Method.RANDOM_REPLACEMENT: [[3, 4], [1, 2], [0.1, 1]],
           Method.RANDOM_FIXED: [[1, 1], [0.1, 0.1], [0.1, 0.1]]},
}


#: the study's camera (StudyConfig.camera)
STUDY_CAMERA = CameraModel(fov_deg=60.0, pixels=640, near_m=1.0, far_m=20.0)


@dataclass(frozen=True)
class StudyConfig:
    """The placement study's world, object, camera and tolerances (§4 study)."""

    size_m: float = 60.0
    resolution_m: float = 0.5
    target_radius_m: float = 0.25
    secondary_sigma_m: float = 0.005
    object_radius_m: float = 1.0
    approach_m: float = 15.0
    stop_m: float = 2.0
    steps: int = 8
    camera: CameraModel = STUDY_CAMERA
    clearance_m: float = 0.5
    kappa_px: float = 1.0
    task_scale_m: float = 0.5
    max_candidates: int = 1500
    n_dirs: int = 360
    search: Search = Search.BOUNDED
    clear_zone_m: float = 2.0    # obstacle-free radius around each target (cell centres)

    def __post_init__(self) -> None:
        object.__setattr__(self, 'search', choice(Search, self.search, 'search'))


@dataclass
class Scenario:
    """One study scene: the known world, the two targets and the moving object."""

    grid: OccupancyGrid          # static world, exactly known (as in the thesis's study)
    primary: Target
    secondary: Target
    path: np.ndarray             # (steps, 2) object centre per step
    object_cells: np.ndarray     # model cells relative to the centre cell
    clear_radii: tuple[float, float] = (2.0, 2.0)   # effective clear zone (primary, secondary)


def _inside_hull(grid: OccupancyGrid, t: Target, reach_m: float = 4.0) -> bool:
    """Whether the target point lies inside an expanded occluder hull (as `_static_field` builds
    them), i.e. the scenario would be invalid for that target."""
    raw = grid_occluders(grid, unknown_occludes=False)
    near = [h for h in raw if np.min(np.linalg.norm(h - t.position, axis=1)) <= reach_m]
    try:
        occlusion_distance(t.position, occluder_hulls(near, t.radius), np.array([[1.0, 0.0]]))
    except PlacementError:
        return True
    return False


def make_scenario(rng: np.random.Generator, density: float, cfg: StudyConfig) -> Scenario:
    """A random scene of obstacle `density` under `cfg`, drawn from `rng`."""
    if not cfg.clear_zone_m >= 0:
        raise ValueError('clear_zone_m must be >= 0')
    n = round(cfg.size_m / cfg.resolution_m)
    res = cfg.resolution_m
    xx, yy = np.meshgrid((np.arange(n) + 0.5) * res, (np.arange(n) + 0.5) * res, indexing='ij')
    centre = np.array([cfg.size_m / 2, cfg.size_m / 2])
    a = rng.uniform(0, 2 * np.pi)
    primary = Target(centre, np.array([np.cos(a), np.sin(a)]), radius=cfg.target_radius_m)
    b, r = rng.uniform(0, 2 * np.pi), rng.uniform(8.0, 15.0)
    c = rng.uniform(0, 2 * np.pi)
    secondary = Target(centre + r * np.array([np.cos(b), np.sin(b)]),
                       np.array([np.cos(c), np.sin(c)]), radius=cfg.target_radius_m,
                       sigma=cfg.secondary_sigma_m)
    o = rng.uniform(0, 2 * np.pi)
    u = np.array([np.cos(o), np.sin(o)])
    s = np.linspace(cfg.approach_m, cfg.stop_m, cfg.steps)
    path = centre + s[:, None] * u
    keep_clear = np.zeros((n, n), bool)
    for t in (primary, secondary):
        d2 = (xx - t.position[0]) ** 2 + (yy - t.position[1]) ** 2
        keep_clear |= d2 <= cfg.clear_zone_m ** 2
    # corridor of the object's approach
    rel_x, rel_y = xx - centre[0], yy - centre[1]
    along = rel_x * u[0] + rel_y * u[1]
    across = -rel_x * u[1] + rel_y * u[0]
    keep_clear |= (along >= 0) & (along <= cfg.approach_m + 2) & \
        (np.abs(across) <= cfg.object_radius_m + 1.0)
    occ = np.zeros((n, n), bool)
    target_cells = density * n * n
    for _ in range(100000):
        if (occ & ~keep_clear).sum() >= target_cells:
            break
        cx, cy = rng.uniform(0, cfg.size_m, 2)
        if rng.random() < 0.5:
            rad = rng.uniform(0.5, 2.5)
            blob = (xx - cx) ** 2 + (yy - cy) ** 2 <= rad * rad
        else:
            w, h = rng.uniform(0.5, 4.0, 2)
            th = rng.uniform(0, np.pi)
            uu = (xx - cx) * np.cos(th) + (yy - cy) * np.sin(th)
            vv = -(xx - cx) * np.sin(th) + (yy - cy) * np.cos(th)
            blob = (np.abs(uu) <= w / 2) & (np.abs(vv) <= h / 2)
        occ |= blob & ~keep_clear
    grid = OccupancyGrid(occ.astype(np.float32), np.ones((n, n), bool), res, np.zeros(2))
    # Validity: no target inside an obstacle or an expanded occluder hull. Widen that target's
    # clear zone in half-cell steps where needed (a no-op at the default 2 m). Uses no random
    # numbers, so the draws after this point are the same for every clear zone.
    radii = []
    for t in (primary, secondary):
        r = cfg.clear_zone_m
        while _inside_hull(grid, t):
            r += res / 2
            d2 = (xx - t.position[0]) ** 2 + (yy - t.position[1]) ** 2
            grid.prob[d2 <= r * r] = 0.0
        radii.append(float(r))
    rc = int(np.ceil(cfg.object_radius_m / res))
    ax = np.arange(-rc, rc + 1)
    gi, gj = np.meshgrid(ax, ax, indexing='ij')
    disc = (gi ** 2 + gj ** 2) * res * res <= cfg.object_radius_m ** 2
    return Scenario(grid, primary, secondary, path, np.argwhere(disc) - rc,
                    (radii[0], radii[1]))


def _static_field(grid: OccupancyGrid, t: Target, cfg: StudyConfig) -> VisibilityField:
    raw = grid_occluders(grid, unknown_occludes=False)
    far = cfg.camera.far_m + 2.0
    near = [h for h in raw if np.min(np.linalg.norm(h - t.position, axis=1)) <= far]
    return VisibilityField(t.position, occluder_hulls(near, t.radius), n_dirs=cfg.n_dirs)


def _object_hull(grid: OccupancyGrid, cells: np.ndarray, radius: float) -> list[np.ndarray]:
    corners = np.array([[0, 0], [0, 1], [1, 0], [1, 1]])
    pts = grid.origin + (cells[:, None, :] + corners[None]).reshape(-1, 2) * grid.resolution
    return occluder_hulls([pts], radius)


def _with_object(f: VisibilityField, hull: list[np.ndarray], t: Target) -> VisibilityField:
    try:
        return f.with_occluders(occluder_hulls(hull, t.radius))
    except PlacementError:          # the object covers this target: it is hidden everywhere
        out = f.with_occluders([])
        out.occ = np.zeros_like(out.occ)
        return out


def _seen(cam: np.ndarray, t: Target, f: VisibilityField, cfg: StudyConfig) -> bool:
    c = cam[None]
    d = np.linalg.norm(cam - t.position)
    return bool(f.visible(c)[0] and angular_visibility(c, t)[0] > 0
                and depth_of_field(np.array([d]), cfg.camera)[0] > 0)


def _sigma(cam: np.ndarray, t: Target, cfg: StudyConfig) -> float:
    d = np.linalg.norm(cam - t.position)
    r = 2 * d * np.tan(np.radians(cfg.camera.fov_deg) / 2) / cfg.camera.pixels
    tav = angular_visibility(cam[None], t)[0]
    return cfg.kappa_px * r / max(tav, 1e-6)


def run_trial(seed: int, density: float, *, use_secondary: bool,
              cfg: StudyConfig = StudyConfig()) -> dict[Method, dict]:
    """One scenario, all three methods. Returns per method: whether guidance survived the
    approach ('tracked'), the final error (m) and the target used at the end."""
    rng = np.random.default_rng(seed)
    sc = make_scenario(rng, density, cfg)
    targets = [sc.primary] + ([sc.secondary] if use_secondary else [])
    placer = TaskPlacer(cfg.camera, clearance_m=cfg.clearance_m,
                        max_candidates=cfg.max_candidates, n_dirs=cfg.n_dirs, search=cfg.search)
    static_fields = [_static_field(sc.grid, t, cfg) for t in targets]
    # One noise draw per trial, shared by the methods (common random numbers).
    z_meas = rng.standard_normal()
    z_rel = rng.standard_normal()
    out = {}
    for method in METHODS:
        # Both random methods draw the same first placement: they differ only in re-placing.
        mrng = np.random.default_rng([seed, 0 if method is Method.OPTIMAL_REPLACEMENT else 1])
        grid = OccupancyGrid(sc.grid.prob.copy(), sc.grid.known.copy(), sc.grid.resolution,
                             sc.grid.origin)
        obj = np.zeros((0, 2), np.int64)
        cam = None
        watched = 0
        tracked = True
        for k in range(cfg.steps):
            obj = move_known_object(grid, obj, sc.object_cells,
                                    grid.to_index(sc.path[k]))
            hull = _object_hull(grid, obj, 0.0)
            fields = [_with_object(f, hull, t)
                      for f, t in zip(static_fields, targets, strict=False)]
            if cam is not None and grid.prob[tuple(grid.to_index(cam))] >= 0.5:
                # the object hit the camera: a fixed one is lost, the others are placed anew
                if method is Method.RANDOM_FIXED:
                    tracked = False
                    break
                cam = None
            match method:
                case Method.OPTIMAL_REPLACEMENT:
                    try:
                        pl = placer.place(grid, targets[0], targets[1:], rng=mrng,
                                          fields=fields)
                    except PlacementError:
                        tracked = False
                        break
                    cam, watched = pl.position, pl.target_index
                case Method.RANDOM_REPLACEMENT | Method.RANDOM_FIXED:
                    seen = [] if cam is None else [i for i, (t, f) in enumerate(
                        zip(targets, fields, strict=False)) if _seen(cam, t, f, cfg)]
                    if not seen and (cam is None or method is Method.RANDOM_REPLACEMENT):
                        cam = _random_biased(grid, targets, fields, placer, mrng)
                        seen = [] if cam is None else [i for i, (t, f) in enumerate(
                            zip(targets, fields, strict=False)) if _seen(cam, t, f, cfg)]
                    if not seen:
                        tracked = False
                        break
                    watched = seen[0]
                case _:
                    assert_never(method)
            assert cam is not None          # each method placed one, or the run ended
            if not _seen(cam, targets[watched], fields[watched], cfg):
                tracked = False
                break
        err = np.inf
        if tracked:
            assert cam is not None                  # the last step's check held
            t = targets[watched]
            err = abs(_sigma(cam, t, cfg) * z_meas + (t.sigma * z_rel if watched > 0 else 0.0))
        out[method] = {'tracked': tracked, 'error_m': float(err), 'target': watched}
    return out


def _random_biased(grid: OccupancyGrid, targets: list[Target], fields: list[VisibilityField],
                   placer: TaskPlacer, rng: np.random.Generator) -> np.ndarray | None:
    """A random free spot within the depth of field with a clear line of sight to some target
    (the bias); the target's facing is not considered."""
    try:
        cams, _ = placer.candidates(grid, targets, rng)
    except PlacementError:
        return None
    ok = np.zeros(len(cams), bool)
    for t, f in zip(targets, fields, strict=False):
        d = np.linalg.norm(cams - t.position, axis=1)
        ok |= f.visible(cams) & (d >= placer.camera.near_m) & (d <= placer.camera.far_m)
    idx = np.flatnonzero(ok)
    if len(idx) == 0:
        return None
    return cams[rng.choice(idx)]


def run_study(*, trials: int, densities: tuple[float, ...] = DENSITIES,
              tolerances: tuple[float, ...] = TOLERANCES, cfg: StudyConfig = StudyConfig(),
              seed0: int = 0) -> list[dict]:
    """Every cell of Table 4-1: success rate (%) per density x secondary x tolerance x method.
    The same scenarios (seeds) are used with and without the secondary target and for every
    tolerance, so the cells differ only in what they vary."""
    cells = []
    for di, dens in enumerate(densities):
        for sec in (False, True):
            results = [run_trial(seed0 + 100000 * di + s, dens, use_secondary=sec, cfg=cfg)
                       for s in range(trials)]
            for tol in tolerances:
                lim = tol * cfg.task_scale_m
                for m in METHODS:
                    ok = [r[m]['tracked'] and r[m]['error_m'] <= lim for r in results]
                    tracked = [r[m]['tracked'] for r in results]
                    cells.append({'density': dens, 'secondary': sec, 'tolerance': tol,
                                  'method': m, 'trials': trials,
                                  'success_rate': 100.0 * float(np.mean(ok)),
                                  'tracked_rate': 100.0 * float(np.mean(tracked)),
                                  'secondary_used': 100.0 * float(np.mean(
                                      [r[m]['tracked'] and r[m]['target'] > 0
                                       for r in results]))})
    return cells


def rating_maps(seed: int, density: float, *, cfg: StudyConfig = StudyConfig()
                ) -> list[dict]:
    """Fig. 4-8b: RF (Eq. 4-1, best of primary and secondary) over every free cell of one
    scenario, with the moving object far from and close to the primary target."""
    sc = make_scenario(np.random.default_rng(seed), density, cfg)
    targets = [sc.primary, sc.secondary]
    # every candidate rated (an exhaustive search) for the map
    placer = TaskPlacer(cfg.camera, clearance_m=cfg.clearance_m, max_candidates=10 ** 9,
                        n_dirs=720, search=Search.RANDOM)
    static = [_static_field(sc.grid, t, cfg) for t in targets]
    out = []
    for k in (0, cfg.steps - 1):
        grid = OccupancyGrid(sc.grid.prob.copy(), sc.grid.known.copy(), sc.grid.resolution,
                             sc.grid.origin)
        obj = move_known_object(grid, np.zeros((0, 2), np.int64), sc.object_cells,
                                grid.to_index(sc.path[k]))
        hull = _object_hull(grid, obj, 0.0)
        fields = [_with_object(f, hull, t) for f, t in zip(static, targets, strict=False)]
        pl = placer.place(grid, targets[0], targets[1:], rng=np.random.default_rng(seed),
                          fields=fields)
        img = np.full(grid.shape, np.nan)
        idx = grid.to_index(pl.candidates)
        img[idx[:, 0], idx[:, 1]] = pl.ratings
        out.append({'step': k, 'grid': grid, 'rating': img, 'best': pl.position,
                    'target_index': pl.target_index, 'targets': targets,
                    'object': sc.path[k]})
    return out
