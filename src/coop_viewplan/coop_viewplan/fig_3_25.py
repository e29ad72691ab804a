"""Fig. 3-25 analogue in the simulator: mapped voxels per scan for sequential/raster vs maximum
information camera pose selection (thesis §3.3.2), on one shared voxel map, without DDS.

    ros2 run coop_viewplan fig_3_25 --rovers 2 --scans 10 --json out/fig_3_25.json --plots out

The PyBullet world of `rover_sim` (its `World` core: the rovers, their masts and stereo pairs,
the seeded rocks and drums) is stepped directly; each scan renders every rover's stereo pair,
ranges it with the `coop_mapping` stereo core and the `stereo` node's defaults (Eq. 3-1..3-9),
and fuses the cloud into one `coop_mapping` VoxelMap (the `mapper`'s defaults, 0.1 m). Between
scans each rover's next camera pose - rover position on the ground, mast pan and tilt - is chosen
on that map by the next-best-view core with the node's constraint model ('evidence': obstacle
columns block, unknown does not, the camera voxel must be seen free): (a) the raster strategy
(§3.3.1 (ii): the next unvisited free location of a boustrophedon lattice, where the mast then
sweeps `raster_headings` pan angles, one per scan; 0 = one heading along the raster, as in
fig_3_13), (b) maximum information (argmax RF of Eq. 3-15; the NI's gray value of a voxel the
map holds free is 0, empty space as the thesis tabulates it, `grid.gray_estimate`). The rover
drives there along the planned collision-free path (its skid steer at <= 0.25 m/s, the world's
physics stepping), pans and tilts its mast, and scans.
"Mapped" is the number of known voxels (free + occupied) of the shared map inside the site (the
planning volume: the rocks-and-drums square + 1 m, ground to 1 m); all known voxels (out to the
stereo range) and the occupied ones (voxels holding measured points, the thesis's "mapped
environment points") are printed too.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

from coop_common.cli import enum_choices, number, output_dir, output_path
from coop_common.dynparams import load_truth
from coop_common.files import save_figure, write_json
from coop_common.params import choice
from coop_mapping.offline import MapSettings, StereoSettings
from coop_mapping.voxelmap import OCCUPIED, unpack_keys
from rover_sim.config import SimConfig
from rover_sim.rover_model import MAST_JOINTS, STEREO_BASELINE_M
from rover_sim.world import World
from rover_sim.worldgen import ObstacleKind

from .grid import FreeGray, MapError, OccupancyGrid, gray_estimate
from .mast import BraidViews, MastKind, braid_views
from .nbv import (
    STRATEGIES,
    CameraState,
    NbvConfig,
    NextBestViewPlanner,
    PlanningError,
    ReachModel,
    StrategyName,
    geodesic_path,
    waypoints,
)

THESIS_CLAIM = ('Fig. 3-25 (§3.3.2, one stereo camera on the mobile manipulator): number of '
                'mapped environment points vs scan number, sequential/raster vs maximum '
                'information pose selection - "the effectiveness of the information based pose '
                'selection process is seen" (maximum information maps more per scan).')
STRATEGY_NAMES = {'raster': 'sequential/raster', 'max_information': 'maximum information'}


class PoseSource(StrEnum):
    """The camera pose each cloud is placed with: the simulator's 'truth' or the rover's own
    'odometry'."""

    TRUTH = 'truth'
    ODOMETRY = 'odometry'


@dataclass(frozen=True)
class Fig325Config:
    """Experiment settings (CLI flags of the same names)."""

    rovers: int = 2
    scans: int = 10
    seed: int = 1
    occlusion_density: float = 0.08
    resolution_m: float = 0.1
    depth_m: float = 10.0                 # the stereo node's max_range_m
    pitches_deg: tuple[float, ...] = (5.0, 20.0)
    initial_tilt_deg: float = 12.0
    n_positions: int = 40
    n_yaw: int = 8
    raster_spacing_m: float = 2.0
    raster_headings: int = 9              # pan sweep per raster location: 9 x 41.2 deg > 360
    clearance_m: float = 0.5
    p_empty: float = 0.45
    k_rel: float = 0.15
    pose_source: PoseSource = PoseSource.TRUTH   # camera pose of each cloud
    # gray value of a known free voxel in NI: 'empty' 0 (§3.2.3/§3.3.2: empty space in the field
    # of view is tabulated as known with no contribution to the uncertainty model; "if every
    # point in the field of view is known and is empty then NI = 0"); 'occupancy' the map's
    # log-odds probability (0.40 after one miss, -p log2 p = 0.53: more than an unknown voxel's
    # 0.5; the earlier runs)
    free_gray: FreeGray = FreeGray.EMPTY
    max_speed_m_s: float = 0.25
    # the camera mast (issue #37): the pan/tilt head, or a BRAID chain of braid_stages whose
    # reachable views (BRAID IK, coop_viewplan.mast) the planner proposes; the planning grid's
    # top (the site counted stays ground to 0.8 m)
    mast: MastKind = MastKind.PAN_TILT
    braid_stages: int = 10
    ceiling_m: float = 0.8

    def __post_init__(self) -> None:
        for name, kind in (('pose_source', PoseSource), ('free_gray', FreeGray),
                           ('mast', MastKind)):
            object.__setattr__(self, name, choice(kind, getattr(self, name), name))


@dataclass
class RoverRun:
    """One rover's planning state across scans."""

    camera: CameraState
    distance_m: float = 0.0
    poses: list = field(default_factory=list)
    failures: int = 0
    views: list = field(default_factory=list)     # the BRAID view of each planned scan


def _wrap(a: float) -> float:
    return math.atan2(math.sin(a), math.cos(a))


class SimMapper:
    """The world, the stereo ranger and the shared map of one run (no DDS, no rclpy)."""

    ROVER_HALF_WIDTH_M = 0.2      # rover_sim chassis 0.5 m x 0.36 m

    def __init__(self, cfg: Fig325Config, *, seed: int) -> None:

        self.cfg = cfg
        sim = SimConfig(rovers=cfg.rovers, seed=seed, occlusion_density=cfg.occlusion_density,
                        stereo_rate_hz=0.0, max_linear_speed_m_s=cfg.max_speed_m_s,
                        mast=cfg.mast, braid_stages=cfg.braid_stages)
        #: the BRAID mast's reachable views (None: the pan/tilt head), and each rover's view
        self.braid: BraidViews | None = (braid_views(cfg.braid_stages,
                                                     pitches_deg=tuple(cfg.pitches_deg))
                                         if cfg.mast is MastKind.BRAID else None)
        self.world = World(sim, [load_truth()] * cfg.rovers)
        self.mast_joints = list(MAST_JOINTS)
        k = self.world.intrinsics()
        w, h = sim.image_width, sim.image_height
        p_left = np.array([[k[0, 0], 0, k[0, 2], 0], [0, k[1, 1], k[1, 2], 0], [0, 0, 1, 0]])
        p_right = p_left.copy()
        p_right[0, 3] = -k[0, 0] * STEREO_BASELINE_M
        self.stereo = StereoSettings()
        self.ranger = self.stereo.ranger(p_left.ravel(), p_right.ravel(), w, h)
        self.map = MapSettings(resolution_m=cfg.resolution_m).new_map()
        # the true obstacles that stand above the chassis (0.23 m): (x, y, radius), only to
        # count how often a path planned through then-unknown space met one (the sim has no
        # obstacle collisions)
        self.obstacles = np.array([(o.position[0], o.position[1], o.radius)
                                   for o in self.world.layout.obstacles
                                   if o.kind is ObstacleKind.DRUM or 1.7 * o.radius > 0.23]
                                  ).reshape(-1, 3)
        self.contacts = 0
        self.hfov_deg = sim.hfov_deg
        self.vfov_deg = math.degrees(2 * math.atan((h / 2) / k[1, 1]))
        # The environment to map (the planning grid and the "site" count): the rocks-and-drums
        # square plus 1 m, from the ground surface layer up to the cameras (0.80 m: c.g. 0.30 +
        # mast 0.40 + tilt 0.04 + camera 0.06). Stereo measures surfaces only: rays to the
        # ground never cross the air above the cameras or the ground below its surface, so those
        # voxels would stay unknown however often they were looked at, and counted as expected
        # information they would draw the cameras' views to the sky. Rays leaving the grid end.
        half = sim.extent_m / 2 + 1.0
        res = cfg.resolution_m
        self.bounds = (np.floor(np.array([-half, -half, -0.1]) / res + 1e-6).astype(np.int64),
                       np.ceil(np.array([half, half, 0.8]) / res - 1e-6).astype(np.int64) - 1)
        # the planning grid: the site up to cfg.ceiling_m (a camera above 0.8 m plans in it)
        self.plan_bounds = (self.bounds[0], np.r_[self.bounds[1][:2], max(
            self.bounds[1][2], int(np.ceil(cfg.ceiling_m / res - 1e-6)) - 1)])
        size = (self.bounds[1] - self.bounds[0] + 1) * res
        self.site_label = f'{size[0]:.0f} m x {size[1]:.0f} m x {size[2]:.1f} m'
        self.views = [0] * cfg.rovers      # the BRAID view each rover's mast is in

    def close(self) -> None:
        self.world.close()

    def __enter__(self) -> SimMapper:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ world
    def step_for(self, seconds: float) -> None:
        for _ in range(round(seconds / self.world.dt)):
            self.world.step()

    def camera(self, i: int) -> tuple[np.ndarray, float, float]:
        """Camera position, heading and pitch (nose down +) of rover i (true pose)."""
        pos, rot = self.world.camera_pose(i)
        fwd = rot[:, 2]
        return pos, float(math.atan2(fwd[1], fwd[0])), float(-math.asin(np.clip(fwd[2], -1, 1)))

    def aim_mast(self, targets: dict[int, tuple[float, float, int]], *, settle_s: float = 0.8
                 ) -> None:
        """Pan/tilt the masts so each camera heads at yaw (map) with the given pitch; with a
        BRAID mast, command the chain to the state of view index `view` (-1: keep its state)
        and turn the turntable so that the view's optical axis heads at yaw (its pitch is the
        view's). settle_s covers the BRAID's settle time (SimConfig.braid_settle_s 1 s)."""
        for i, (yaw, pitch, view) in targets.items():
            base_yaw = self.world.truth(i).anchor_yaw
            if self.braid is None:
                pan = float(np.clip(_wrap(yaw - base_yaw), -3.0, 3.0))
                tilt = float(np.clip(pitch, -1.1, 1.1))
                self.world.command_mast(i, self.mast_joints, [0.6], [[pan, tilt]])
                continue
            if view >= 0:
                self.world.command_braid(i, self.braid.states[view])
                self.views[i] = view
            head = self.braid.views[self.views[i]].heading_rad
            pan = float(np.clip(_wrap(yaw - head - base_yaw), -3.0, 3.0))
            self.world.command_mast(i, self.mast_joints[:1], [0.6], [[pan]])
        self.step_for(0.6 + settle_s)

    def drive(self, paths: Mapping[int, Sequence[np.ndarray] | np.ndarray], *,
              tol_m: float = 0.08) -> dict[int, float]:
        """Drive rovers along their waypoint lists (map xy) at once: turn on the spot when the
        heading is off by more than 20 deg, else drive with a proportional heading correction.
        Returns the distance each anchor (the chassis) moved."""
        w = self.world
        todo = {i: list(map(np.asarray, p)) for i, p in paths.items() if len(p)}
        moved = {i: 0.0 for i in paths}
        last = {i: w.truth(i).anchor_position[:2].copy() for i in paths}
        limit = sum(float(np.sum(np.linalg.norm(np.diff(np.vstack([last[i], *p]), axis=0),
                                                axis=1))) for i, p in todo.items())
        t_max = w.time_s + limit / (0.5 * self.cfg.max_speed_m_s) + 20.0
        every = max(1, round(0.05 / w.dt))
        touching: set[int] = set()
        while todo and w.time_s < t_max:
            for i in list(todo):
                tr = w.truth(i)
                xy, yaw = tr.anchor_position[:2], tr.anchor_yaw
                moved[i] += float(np.linalg.norm(xy - last[i]))
                last[i] = xy.copy()
                if len(self.obstacles) and np.any(
                        np.hypot(*(self.obstacles[:, :2] - xy).T)
                        < self.obstacles[:, 2] + self.ROVER_HALF_WIDTH_M):
                    touching.add(i)
                while todo[i] and np.linalg.norm(todo[i][0] - xy) < (
                        tol_m if len(todo[i]) == 1 else 0.25):
                    todo[i].pop(0)
                if not todo[i]:
                    w.command_velocity(i, 0.0, 0.0)
                    del todo[i]
                    continue
                d = todo[i][0] - xy
                err = _wrap(math.atan2(d[1], d[0]) - yaw)
                if abs(err) > math.radians(20):
                    w.command_velocity(i, 0.0, float(np.clip(2.5 * err, -1.0, 1.0)))
                else:
                    dist = float(np.linalg.norm(d)) + 0.25 * (len(todo[i]) - 1)
                    w.command_velocity(i, min(self.cfg.max_speed_m_s, 0.8 * dist + 0.05),
                                       float(np.clip(2.0 * err, -1.0, 1.0)))
            for _ in range(every):
                w.step()
        for i in paths:
            w.command_velocity(i, 0.0, 0.0)
            moved[i] += float(np.linalg.norm(w.truth(i).anchor_position[:2] - last[i]))
        self.contacts += len(touching)
        self.step_for(0.3)          # let the base compliance settle before imaging
        return moved

    # ------------------------------------------------------------------ sensing and mapping
    def scan(self, i: int) -> int:
        """Render rover i's stereo pair, range it, fuse it into the shared map; points fused."""
        left, right = self.world.render_stereo(i)
        if self.cfg.pose_source is PoseSource.ODOMETRY:
            t, rot, _ = self.world.estimated_camera_pose(i)
        else:
            t, rot = self.world.camera_pose(i)
        sc = self.ranger.process(left, right, rot, t)
        pts, cov = sc.points, sc.covariances
        # self and teammate filter: the rovers (body, arm, mast, card) are not the site; a rover
        # mapped by a teammate would stay behind as a ghost obstacle where it stood
        body = np.zeros(len(pts), bool)
        for j in range(len(self.world.rovers)):
            base = self.world.truth(j).base_position
            body |= (np.hypot(pts[:, 0] - base[0], pts[:, 1] - base[1]) < 0.45) \
                & (pts[:, 2] < 1.0)
        pts, cov = pts[~body], cov[~body]
        if len(pts) == 0:
            return 0
        self.map.insert_scan(pts, t, covariances=cov, source=f'rover{i + 1}')
        return len(pts)

    def counts(self) -> dict[str, int]:
        """Known and occupied voxels of the shared map: in the site (the planning volume: the
        rocks-and-drums square + 1 m, ground to 1 m) and in all (out to the stereo range)."""
        k = unpack_keys(self.map.keys)
        occ = self.map.states() == OCCUPIED
        lo, hi = self.bounds
        site = np.all((k >= lo) & (k <= hi), axis=1)
        return {'known': int(site.sum()), 'occupied': int(np.count_nonzero(occ & site)),
                'known_all': len(self.map), 'occupied_all': int(np.count_nonzero(occ))}

    def grid(self) -> OccupancyGrid:
        return OccupancyGrid.from_sparse(unpack_keys(self.map.keys), self.map.probability(),
                                         resolution=self.map.resolution,
                                         bounds_keys=self.plan_bounds)


def planner_config(cfg: Fig325Config, mapper: SimMapper, camera_height_m: float) -> NbvConfig:
    """The planner's settings for the experiment's camera and map (with a BRAID mast, the
    views it reaches; camera_height_m then the lowest of them, where the rover's own voxel is
    checked)."""
    views = mapper.braid.views if mapper.braid is not None else ()
    if views:
        camera_height_m = min(v.height_m for v in views)
    return NbvConfig(mast_views=views,
                     fov_deg=mapper.hfov_deg, vfov_deg=mapper.vfov_deg, depth_m=cfg.depth_m,
                     n_az=24, n_el=18, step_cells=1.0, k_rel=cfg.k_rel,
                     n_positions=cfg.n_positions, n_yaw=cfg.n_yaw,
                     pitches_deg=tuple(cfg.pitches_deg), camera_height_m=camera_height_m,
                     clearance_m=cfg.clearance_m, p_empty=cfg.p_empty,
                     reach_model=ReachModel.EVIDENCE,
                     raster_spacing_m=cfg.raster_spacing_m,
                     raster_headings=cfg.raster_headings, free_gray=cfg.free_gray)


def run_strategy(strategy: StrategyName | str, cfg: Fig325Config, *, seed: int,
                 log: Callable[[str], None] | None = None, save_map: Path | None = None) -> dict:
    """One run of one strategy: mapped voxel counts after the initial scan and each of
    `cfg.scans` planned scans (every rover scans once per scan step). save_map: write the
    shared map there at the end (the mapper's file format: `mapper -p map_file:=...` loads
    it), e.g. the site map an insertion experiment's view planner places its camera in."""
    t0 = time.perf_counter()
    rng = np.random.default_rng(1000 + seed)
    with SimMapper(cfg, seed=seed) as sm:
        n = cfg.rovers
        sm.step_for(0.2)
        first = -1
        if sm.braid is not None:      # the lowest view nearest the initial tilt
            bv = sm.braid.views
            first = min(range(len(bv)), key=lambda v: (
                round(bv[v].height_m, 2),
                abs(bv[v].pitch_rad - math.radians(cfg.initial_tilt_deg))))
        sm.aim_mast({i: (sm.camera(i)[1], math.radians(cfg.initial_tilt_deg), first)
                     for i in range(n)})
        runs = []
        for i in range(n):
            pos, yaw, pitch = sm.camera(i)
            runs.append(RoverRun(CameraState(pos, yaw, pitch),
                                 poses=[[float(v) for v in (*pos, yaw, pitch)]]))
            sm.scan(i)
        height = float(np.mean([r.camera.position[2] for r in runs]))
        planner = NextBestViewPlanner(planner_config(cfg, sm, height))
        rows = [{'scan': 0, **sm.counts(), 'distance_m': 0.0}]
        plan_s = 0.0
        for k in range(1, cfg.scans + 1):
            tp = time.perf_counter()
            grid = sm.grid()
            for r in runs:
                r.camera.visited.append(grid.to_index(r.camera.position)[:2])
            est = gray_estimate(grid, free_gray=planner.config.free_gray,
                                iterations=planner.config.markov_iterations)
            base = planner.traversability(grid)
            claimed = np.zeros(grid.shape, bool)
            clear = math.ceil(cfg.clearance_m / grid.resolution) + 2
            goals: dict[int, np.ndarray] = {}
            paths: dict[int, list] = {}
            aims: dict[int, tuple[float, float, int]] = {}
            for i, r in enumerate(runs):
                trav = base
                for j, other in enumerate(runs):       # other rovers: where they are / go
                    if j != i:
                        trav = trav.with_blocked_disk(
                            grid.to_index(other.camera.position)[:2], clear)
                        if j in goals:
                            trav = trav.with_blocked_disk(goals[j], clear)
                start = grid.to_index(r.camera.position)[:2]
                try:
                    d = planner.plan(grid, r.camera, strategy=strategy, rng=rng,
                                     claimed=claimed, estimate=est, traversability=trav,
                                     free_footprint=True)
                except (PlanningError, MapError) as exc:
                    r.failures += 1
                    if log:
                        log(f'  {strategy} scan {k} rover{i + 1}: no view ({exc}); '
                            'turning on the spot')
                    aims[i] = (r.camera.yaw + math.radians(sm.hfov_deg), r.camera.pitch, -1)
                    continue
                claimed |= planner.expected_cells(grid, d)
                goal = grid.to_index(d.position)[:2]
                goals[i] = goal
                nav = trav.with_free_disk(start, clear - 2).navigable.copy()
                nav[start[0], start[1]] = True
                cells = geodesic_path(nav, tuple(start), tuple(goal),
                                      resolution=grid.resolution)
                paths[i] = waypoints(cells, grid) if len(cells) > 1 else []
                aims[i] = (d.yaw, d.pitch, d.view)
                r.views.append(d.view)
            plan_s += time.perf_counter() - tp
            moved = sm.drive(paths)
            sm.aim_mast(aims)
            for i, r in enumerate(runs):
                r.distance_m += moved.get(i, 0.0)
                pos, yaw, pitch = sm.camera(i)
                r.camera.position, r.camera.yaw, r.camera.pitch = pos, yaw, pitch
                r.poses.append([float(v) for v in (*pos, yaw, pitch)])
                sm.scan(i)
            rows.append({'scan': k, **sm.counts(),
                         'distance_m': float(sum(r.distance_m for r in runs))})
            if log:
                c = rows[-1]
                log(f"  {strategy} seed {seed} scan {k}: site known {c['known']}, occupied "
                    f"{c['occupied']}; all known {c['known_all']}; moved {c['distance_m']:.1f} m")
        top = _top_view(sm)
        top['site'] = sm.site_label
        contacts = sm.contacts
        if save_map is not None:
            sm.map.save(save_map)
    return {'rows': rows, 'plan_seconds': plan_s, 'seconds': time.perf_counter() - t0,
            'failures': [r.failures for r in runs], 'poses': [r.poses for r in runs],
            'views': [r.views for r in runs],
            'obstacle_contacts': contacts, 'top_view': top}


def _top_view(sm: SimMapper) -> dict:
    """Per ground cell: -1 unknown, 0 known free, 1 an occupied voxel above the ground."""
    k = unpack_keys(sm.map.keys)
    lo, hi = sm.bounds
    keep = np.all((k >= lo) & (k <= hi), axis=1)
    k, st = k[keep], sm.map.states()[keep]
    img = np.full((hi[0] - lo[0] + 1, hi[1] - lo[1] + 1), -1, np.int8)
    img[k[:, 0] - lo[0], k[:, 1] - lo[1]] = 0
    up = (st == OCCUPIED) & (k[:, 2] * sm.map.resolution >= 0.2)
    img[k[up, 0] - lo[0], k[up, 1] - lo[1]] = 1
    return {'origin_m': (lo[:2] * sm.map.resolution).tolist(),
            'resolution_m': sm.map.resolution, 'grid': img.tolist()}


def run(cfg: Fig325Config, *, strategies: list[StrategyName | str], seeds: int,
        log: Callable[[str], None] | None = None) -> dict:
    """Each strategy over the seeds: the per-scan rows and their means (the JSON result)."""
    out: dict[str, Any] = {'config': {k: (list(v) if isinstance(v, tuple) else v)
                      for k, v in cfg.__dict__.items()},
           'seeds': seeds, 'thesis_claim': THESIS_CLAIM, 'strategies': {}}
    for name in strategies:
        runs = [run_strategy(name, cfg, seed=cfg.seed + s, log=log) for s in range(seeds)]
        col = {c: np.array([[r[c] for r in x['rows']] for x in runs], float)
               for c in ('known', 'occupied', 'known_all', 'occupied_all', 'distance_m')}
        out['strategies'][name] = {
            'known_voxels': col['known'].mean(axis=0).tolist(),
            'occupied_voxels': col['occupied'].mean(axis=0).tolist(),
            'known_voxels_all': col['known_all'].mean(axis=0).tolist(),
            'occupied_voxels_all': col['occupied_all'].mean(axis=0).tolist(),
            'distance_m': col['distance_m'].mean(axis=0).tolist(),
            'known_voxels_per_seed': col['known'].tolist(),
            'known_voxels_all_per_seed': col['known_all'].tolist(),
            'failures': [x['failures'] for x in runs],
            'obstacle_contacts': [x['obstacle_contacts'] for x in runs],
            'plan_seconds': float(sum(x['plan_seconds'] for x in runs)),
            'seconds': float(sum(x['seconds'] for x in runs)),
            'poses': [x['poses'] for x in runs],
            'top_view': runs[0]['top_view'],
        }
    return out


def _scans_to(curve: np.ndarray, level: float) -> int | None:
    hit = np.flatnonzero(curve >= level)
    return int(hit[0]) if len(hit) else None


def verdict(res: dict) -> str:
    """Scans each method needs to reach 90 % of the larger final count (as fig_3_13's "scans
    to 90 %"), and in how many scans maximum information is ahead; for the site and for all
    known voxels."""
    s = res['strategies']
    if not {'raster', 'max_information'} <= set(s):
        return 'verdict: needs both raster and max_information'
    out = []
    for key, label in (('known_voxels', 'site'), ('known_voxels_all', 'all')):
        a, b = np.array(s['raster'][key]), np.array(s['max_information'][key])
        level = 0.9 * max(a[-1], b[-1])
        sa, sb = _scans_to(a, level), _scans_to(b, level)
        ahead = int(np.sum(b[1:] > a[1:]))
        n = len(a) - 1
        faster = sb is not None and (sa is None or sb < sa)
        word = 'reproduced' if faster and ahead > n / 2 else 'not reproduced'
        out.append(f'here ({label}): scans to 90 % of the larger final count ({level:.0f}): '
                   f"max information {sb if sb is not None else 'not reached'}, raster "
                   f"{sa if sa is not None else 'not reached'}; max information ahead after "
                   f'{ahead} of {n} scans; last scan {b[-1]:.0f} vs {a[-1]:.0f} '
                   f'({b[-1] / max(a[-1], 1):.2f}x) - {word}')
    return '\n'.join(out)


def format_table(res: dict) -> str:
    """The result as a text table: mapped voxels per scan and strategy."""
    s = res['strategies']
    names = list(s)
    cfg = res['config']
    short = {'raster': 'raster', 'max_information': 'max info'}
    lines = [f"Fig. 3-25 analogue: rover_sim seed {cfg['seed']}"
             f"{'..' + str(cfg['seed'] + res['seeds'] - 1) if res['seeds'] > 1 else ''}"
             f"{' (mean)' if res['seeds'] > 1 else ''}, {cfg['rovers']} rover(s), occlusion "
             f"{cfg['occlusion_density']:.0%}, stereo 320x240 41.2 deg, map "
             f"{cfg['resolution_m']} m, raster sweeps {cfg['raster_headings']} heading(s), poses "
             f"from {cfg['pose_source']}, NI gray of known free voxels: "
             f"{cfg.get('free_gray', 'occupancy')}"
             + (f", mast {cfg['mast']}" + (f" ({cfg['braid_stages']} stages)"
                                           if cfg['mast'] == 'braid' else '')
                + f", planning grid to {cfg['ceiling_m']} m" if 'mast' in cfg else ''),
             'mapped = known voxels (free + occupied) of the shared map in the site (the '
             f"planning volume, {s[names[0]]['top_view'].get('site', '')}); all = out to the "
             'stereo range; occupied = voxels holding range points, in the site']
    heads = ([f'{short.get(n, n)} site' for n in names] + [f'{short.get(n, n)} all'
                                                           for n in names]
             + [f'{short.get(n, n)} occ.' for n in names])
    lines.append(f"{'scan':>4s} " + ' '.join(f'{h:>16s}' for h in heads))
    for k in range(len(s[names[0]]['known_voxels'])):
        vals = ([s[n]['known_voxels'][k] for n in names]
                + [s[n]['known_voxels_all'][k] for n in names]
                + [s[n]['occupied_voxels'][k] for n in names])
        lines.append(f'{k:4d} ' + ' '.join(f'{v:16.0f}' for v in vals))
    lines.append('distance moved (m, all rovers): ' + ', '.join(
        f"{n} {s[n]['distance_m'][-1]:.1f}" for n in names))
    lines.append('planning failures (stayed and turned): ' + ', '.join(
        f"{n} {sum(map(sum, s[n]['failures']))}" for n in names))
    lines.append('moves that came within 0.2 m of a true obstacle (path planned through '
                 'then-unknown space; the sim has no obstacle collisions): ' + ', '.join(
                     f"{n} {sum(s[n]['obstacle_contacts'])}" for n in names))
    lines.append('thesis: ' + res['thesis_claim'])
    lines.append(verdict(res))
    return '\n'.join(lines)


def plot(res: dict, out_dir: Path) -> Path:
    """Draw the mapped-voxel curves into `out_dir`; the file written."""
    import matplotlib  # noqa: PLC0415 - heavy, only when plots are asked for
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt  # noqa: PLC0415 - heavy, only when plotting
    s = res['strategies']
    fig, ax = plt.subplots(1, 2 + len(s), figsize=(5 * (2 + len(s)), 4.2))
    for name, v in s.items():
        lab = STRATEGY_NAMES.get(name, name)
        ax[0].plot(v['known_voxels'], marker='o', label=lab)
        ax[1].plot(v['occupied_voxels'], marker='o', label=lab)
    ax[0].set(xlabel='scan number', ylabel='known voxels in the site (free + occupied)',
              title='Fig. 3-25 analogue: mapped voxels')
    ax[1].set(xlabel='scan number', ylabel='occupied voxels in the site',
              title='voxels holding range points')
    for a in ax[:2]:
        a.grid(alpha=0.3)
        a.legend()
    for a, (name, v) in zip(ax[2:], s.items(), strict=False):
        tv = v['top_view']
        g = np.array(tv['grid'], float)
        ext = [tv['origin_m'][0], tv['origin_m'][0] + g.shape[0] * tv['resolution_m'],
               tv['origin_m'][1], tv['origin_m'][1] + g.shape[1] * tv['resolution_m']]
        a.imshow(g.T, origin='lower', extent=ext, cmap='gray_r', vmin=-1.5, vmax=1)
        for rover in v['poses'][0]:
            p = np.array(rover)
            if len(p):
                a.plot(p[:, 0], p[:, 1], '.-', lw=0.8)
        a.set(title=f'map after the last scan: {STRATEGY_NAMES.get(name, name)}',
              xlabel='x (m)', ylabel='y (m)')
    return save_figure(fig, out_dir / 'fig_3_25.png', dpi=110)


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_viewplan.fig_3_25`: the Fig. 3-25 analogue in rover_sim."""
    p = argparse.ArgumentParser(description='Fig. 3-25 analogue in rover_sim: mapped voxels per '
                                            'scan, raster vs maximum information pose selection')
    d = Fig325Config()
    p.add_argument('--rovers', type=int, default=d.rovers, choices=(1, 2))
    p.add_argument('--scans', type=number(int, lo=1), default=d.scans)
    p.add_argument('--seed', type=number(int, lo=0), default=d.seed,
                   help='world seed of the first run')
    p.add_argument('--seeds', type=number(int, lo=1), default=1,
                   help='runs (worlds seed..seed+N-1)')
    p.add_argument('--occlusion-density', type=number(lo=0, hi=0.5),
                   default=d.occlusion_density)
    p.add_argument('--depth-m', type=number(lo=0, lo_open=True), default=d.depth_m)
    p.add_argument('--candidates', type=number(int, lo=1), default=d.n_positions,
                   help='candidate positions per decision (x 8 headings x pitches)')
    p.add_argument('--raster-spacing-m', type=number(lo=0, lo_open=True),
                   default=d.raster_spacing_m)
    p.add_argument('--raster-headings', type=number(int, lo=0), default=d.raster_headings,
                   help='headings the raster sweeps at each location (0: one, along the '
                        'raster, as in fig_3_13)')
    p.add_argument('--p-empty', type=number(lo=0, hi=1), default=d.p_empty)
    p.add_argument('--pose', choices=enum_choices(PoseSource), default=d.pose_source.value)
    p.add_argument('--free-gray', choices=enum_choices(FreeGray), default=d.free_gray.value,
                   help="NI gray value of known free voxels: 'empty' 0 (the thesis's known "
                        "empty space); 'occupancy' the map's log-odds probability (earlier)")
    p.add_argument('--mast', choices=enum_choices(MastKind), default=d.mast.value,
                   help="the rovers' camera mast: the pan/tilt head, or BRAID (the planner "
                        'proposes the views its IK reaches)')
    p.add_argument('--braid-stages', type=number(int, lo=1, hi=20), default=d.braid_stages)
    p.add_argument('--ceiling-m', type=number(lo=0.8, hi=3.0), default=d.ceiling_m,
                   help='top of the planning grid (m); the site counted stays ground to 0.8 m')
    p.add_argument('--strategies', default='raster,max_information')
    p.add_argument('--json', type=output_path, default=None)
    p.add_argument('--plots', type=output_dir, default=None)
    p.add_argument('--quiet', action='store_true')
    p.add_argument('--from-json', type=Path, default=None,
                   help='print the table (and --plots) of a saved --json run; no simulation')
    a = p.parse_args(argv)
    if a.from_json is not None:
        try:
            res = json.loads(a.from_json.read_text())
            if not isinstance(res, dict):
                raise ValueError('not a fig_3_25 --json result')
        except (OSError, ValueError) as exc:     # JSONDecodeError is a ValueError
            p.error(f'--from-json {a.from_json}: {exc}')
        try:
            table = format_table(res)
        except (KeyError, TypeError, ValueError, IndexError) as exc:
            p.error(f'--from-json {a.from_json}: not a fig_3_25 --json result ({exc!r})')
        print(table)
        if a.plots is not None:
            print(f'plot: {plot(res, a.plots)}')
        return 0
    names = [s.strip() for s in a.strategies.split(',') if s.strip()]
    bad = [s for s in names if s not in STRATEGIES]
    if bad or not names:
        p.error(f'unknown strategy {bad}; one of {enum_choices(StrategyName)}')
    if a.depth_m < d.resolution_m:          # the view would hold no voxel
        p.error(f'--depth-m {a.depth_m} is below the map resolution {d.resolution_m} m')
    cfg = Fig325Config(rovers=a.rovers, scans=a.scans, seed=a.seed,
                       occlusion_density=a.occlusion_density, depth_m=a.depth_m,
                       n_positions=a.candidates, raster_spacing_m=a.raster_spacing_m,
                       raster_headings=a.raster_headings,
                       p_empty=a.p_empty, pose_source=a.pose, free_gray=a.free_gray,
                       mast=a.mast, braid_stages=a.braid_stages, ceiling_m=a.ceiling_m)
    log = None if a.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    t0 = time.perf_counter()
    res = run(cfg, strategies=names, seeds=a.seeds, log=log)
    res['seconds'] = time.perf_counter() - t0
    print(format_table(res))
    print(f"({res['seconds']:.0f} s)")
    if a.plots is not None:
        print(f'plot: {plot(res, a.plots)}')
    if a.json is not None:
        write_json(a.json, res, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
