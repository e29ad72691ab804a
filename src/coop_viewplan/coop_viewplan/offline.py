"""Next best views from recorded data without DDS: what the `view_planner` node answers, run on a
saved map or on the map `coop_mapping.offline.map_from_bag` fuses from a bag (no rclpy).

    python -m coop_viewplan.offline bags/mapping_two_rovers      # the map fused from the bag
    python -m coop_viewplan.offline bags/mapping_two_rovers --map out/team.cmap \
        -p camera_height_m=0.75                                  # a saved map, the bag's poses

The cameras are each rover's last `stereo/pose` in the bag; the rovers ask in name order, each
claiming the cells its view is expected to see for the next (as the node does on one map).
`--json OUT` writes the answers; the printed listing is `format_table` of that JSON.
"""
from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from coop_common.cli import enum_choices, output_path
from coop_common.files import write_json
from coop_common.params import check_values, choice, parse_value

from .frames import camera_pose
from .grid import MapError, OccupancyGrid, planning_grid
from .mast import BraidViews, MastKind, braid_views
from .nbv import (
    CameraState,
    Decision,
    MastView,
    NbvConfig,
    NextBestViewPlanner,
    PlanningError,
    ReachModel,
    StrategyName,
)
from .params import PARAMS, check_params

if TYPE_CHECKING:    # for annotations only
    from coop_mapping.voxelmap import VoxelMap

#: the node's parameters that the planning here reads (`nbv_config`, the grid, the seed); the
#: others (topics, frames, task placement) have nothing to act on off line
PLANNING_PARAMS = ('fov_deg', 'depth_m', 'rays_az', 'rays_el', 'k_rel', 'n_exp', 'candidates',
                   'headings', 'camera_height_m', 'clearance_m', 'p_empty', 'occupied_voxels',
                   'occupied_p', 'occupied_clamp', 'pad_m', 'ceiling_m', 'seed', 'ni_measure',
                   'free_gray', 'max_grid_cells')


def node_parameters(overrides: Sequence[str] = ()) -> dict:
    """The node's parameter values (its defaults, `params.PARAMS`) with `NAME=VALUE` overrides
    of PLANNING_PARAMS, typed and validated as the node does (its ranges, choices and rule):
    ValueError with the reason when one is not acceptable."""
    values = {k: s.default for k, s in PARAMS.items()}
    for kv in overrides:
        k, sep, v = kv.partition('=')
        if not sep:
            raise ValueError(f'{kv!r}: not NAME=VALUE')
        if k not in PLANNING_PARAMS:
            raise ValueError(f'unknown parameter {k!r}; one of {sorted(PLANNING_PARAMS)}')
        try:
            values[k] = parse_value(PARAMS[k], v)
        except ValueError as exc:
            raise ValueError(f'{k}: {exc}') from None
    bad = check_values(PARAMS, values, check_params)
    if bad:
        raise ValueError('; '.join(bad))
    return values


def node_braid_views(p: dict) -> BraidViews:
    """The BRAID mast's views from the node's parameter values (`mast.braid_views`, cached)."""
    return braid_views(int(p['braid_stages']),
                       heights_m=tuple(float(v) for v in p['braid_heights_m']),
                       pitches_deg=tuple(float(v) for v in p['braid_pitches_deg']))


def nbv_config(p: dict) -> NbvConfig:
    """The planner settings the node uses, from its parameter values. On the live stereo map
    constraints (i)/(ii) follow the 'evidence' model (nbv module docstring). With mast 'braid'
    the candidates are the views the BRAID's IK reaches (`mast.braid_views`; OptionError when
    it reaches none), the camera's own voxel checked at the lowest of them."""
    views: tuple[MastView, ...] = ()
    height = p['camera_height_m']
    if choice(MastKind, p.get('mast', MastKind.PAN_TILT), 'mast') is MastKind.BRAID:
        views = node_braid_views(p).views
        height = min(v.height_m for v in views)
    return NbvConfig(
        mast_views=views,
        fov_deg=p['fov_deg'], depth_m=p['depth_m'], n_az=p['rays_az'], n_el=p['rays_el'],
        step_cells=1.0, k_rel=p['k_rel'], n_exp=p['n_exp'], n_positions=p['candidates'],
        n_yaw=p['headings'], camera_height_m=height,
        clearance_m=p['clearance_m'], p_empty=p['p_empty'],
        reach_model=ReachModel.EVIDENCE,
        occupied_voxels=p['occupied_voxels'], occupied_p=p['occupied_p'],
        occupied_clamp=p['occupied_clamp'],
        ni_measure=p['ni_measure'], free_gray=p['free_gray'])


def grid_from_voxelmap(vm: VoxelMap, p: dict) -> OccupancyGrid:
    """coop_mapping VoxelMap -> dense planning grid, with the node's checks and its parameter
    values `p` (`grid.planning_grid`, as the node converts the map topic)."""
    from coop_mapping.voxelmap import unpack_keys  # noqa: PLC0415 - see map_from_bag below
    return planning_grid(unpack_keys(vm.keys), vm.probability(), vm.resolution, pad_m=p['pad_m'],
                         ceiling_m=p['ceiling_m'], camera_height_m=p['camera_height_m'],
                         max_cells=p['max_grid_cells'])


def last_camera_poses(bag: str | Path) -> dict[str, CameraState]:
    """Each rover's last `<rover>/stereo/pose` in a bag as a CameraState."""
    # rosbags: only the offline paths read bags; the view_planner node imports this module
    from rover_bag.bagio import bag_info, read_messages  # noqa: PLC0415
    topics = sorted(t for t in bag_info(bag).topics if t.endswith('/stereo/pose'))
    last = {}
    for rec in read_messages(bag, topics):
        last[rec.topic.split('/')[1]] = rec.msg.pose.pose
    out = {}
    for rover, pose in sorted(last.items()):
        q, t = pose.orientation, pose.position
        try:
            position, yaw, pitch = camera_pose([t.x, t.y, t.z], [q.x, q.y, q.z, q.w])
        except ValueError as exc:      # as the node answers such a request
            raise ValueError(f'{rover}: last stereo/pose: {exc}') from None
        out[rover] = CameraState(position, yaw, pitch)
    return out


@dataclass
class Answer:
    """One rover's answer: its decision, or None with the reason."""

    rover: str
    decision: Decision | None
    message: str


def plan_team(grid: OccupancyGrid, cameras: dict[str, CameraState], params: dict, *,
              strategy: StrategyName | str = StrategyName.MAX_INFORMATION) -> list[Answer]:
    """The node's answers to each rover in turn on one map (later rovers see earlier claims)."""
    strategy = choice(StrategyName, strategy, 'strategy')
    planner = NextBestViewPlanner(nbv_config(params))
    rng = np.random.default_rng(int(params['seed']))
    claimed = np.zeros(grid.shape, bool)
    out = []
    for rover, cam in cameras.items():
        try:
            d = planner.plan(grid, cam, strategy=strategy, rng=rng, claimed=claimed,
                             free_footprint=True)
        except (MapError, PlanningError, ValueError) as exc:    # as the node answers
            out.append(Answer(rover, None, str(exc)))
            continue
        claimed |= planner.expected_cells(grid, d)
        out.append(Answer(rover, d, f'{strategy}: {len(d.candidates)} candidates'))
    return out


def answer_json(ans: Answer) -> dict:
    """One rover's answer as `--json` writes it: the chosen view and its terms, or the reason."""
    d = ans.decision
    if d is None:
        return {'rover': ans.rover, 'success': False, 'message': ans.message}
    c, i = d.candidates, d.index
    return {'rover': ans.rover, 'success': True, 'message': ans.message,
            'position_m': [float(v) for v in d.position], 'yaw_deg': math.degrees(d.yaw),
            'ni_bits': float(d.scores.ni[i]), 'distance_m': float(c.distance[i]),
            'path_m': float(d.path_length), 'collision_p': float(c.collision_p[i]),
            'rating': float(d.rating[i])}


def format_table(res: dict) -> str:
    """The printed listing of a run, from the JSON `--json` writes."""
    lines = [f"{res['source']}: {res['voxels']} voxels at {res['resolution_m']} m; poses: last "
             f"stereo/pose in {res['bag']}"]
    for a in res['answers']:
        if not a['success']:
            lines.append(f"{a['rover']}: none ({a['message']})")
            continue
        p = a['position_m']
        lines.append(f"{a['rover']}: {a['message']}, camera at ({p[0]:+.2f}, {p[1]:+.2f}, "
                     f"{p[2]:+.2f}) m yaw {a['yaw_deg']:+.0f} deg, NI {a['ni_bits']:.3f} bits, "
                     f"d {a['distance_m']:.2f} m, path {a['path_m']:.2f} m, "
                     f"P {a['collision_p']:.3f}, RF {a['rating']:.3f}")
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    """`python -m coop_viewplan.offline`: next best views on a bag's map."""
    ap = argparse.ArgumentParser(description="next best views on a bag's map, without DDS")
    ap.add_argument('bag', type=Path, help='bag with <rover>/stereo/* (poses, and the map '
                                           'unless --map)')
    ap.add_argument('--map', type=Path, default=None, help='a saved coop_mapping map instead')
    ap.add_argument('--strategy', default=StrategyName.MAX_INFORMATION.value,
                    choices=enum_choices(StrategyName))
    ap.add_argument('-p', action='append', default=[], metavar='NAME=VALUE',
                    help='node parameter override, e.g. -p camera_height_m=0.75')
    ap.add_argument('--json', type=output_path, default=None,
                    help='write the answers here (the printed listing is made from it)')
    a = ap.parse_args(argv)
    try:
        params = node_parameters(a.p)
    except ValueError as exc:
        ap.error(f'-p: {exc}')
    if not a.bag.exists():
        ap.error(f'{a.bag}: no such bag')
    if a.map is not None:
        from coop_mapping.voxelmap import VoxelMap  # noqa: PLC0415 - see map_from_bag below
        vm = VoxelMap.load(a.map)
        src = str(a.map)
    else:
        # cv2 and rosbags: only this CLI reads bags; the view_planner node imports this module
        from coop_mapping.offline import map_from_bag  # noqa: PLC0415
        vm = map_from_bag(a.bag).map
        src = f'map_from_bag({a.bag})'
    try:
        grid = grid_from_voxelmap(vm, params)
        cameras = last_camera_poses(a.bag)
    except ValueError as exc:       # MapError included: what the node refuses
        print(f'{src}: {exc}', file=sys.stderr)
        return 1
    res = {'source': src, 'bag': str(a.bag), 'map': None if a.map is None else str(a.map),
           'voxels': len(vm), 'resolution_m': vm.resolution, 'strategy': str(a.strategy),
           'overrides': list(a.p),
           'answers': [answer_json(ans)
                       for ans in plan_team(grid, cameras, params, strategy=a.strategy)]}
    print(format_table(res))
    if a.json is not None:
        write_json(a.json, res, indent=1)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
