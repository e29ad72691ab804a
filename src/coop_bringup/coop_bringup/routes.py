"""The mission's routes for its rovers: planned on the view planner's grid of the team's map
(`coop_viewplan.nbv.team_route`), and accepted by the rovers' `drive_to_pose`, which refuses a
path across a cell of the mapper's 2-D `map/grid` it takes for occupied
(`coop_insertion.drive.obstruction`). The two grids come from one map but need not agree on a
cell (the planning grid's clearance and obstacle columns against one height layer), so the
route keeps off the driver's occupied cells and is checked by the driver's own rule."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from coop_insertion.drive import GridSlice, obstruction
from coop_viewplan.grid import OccupancyGrid
from coop_viewplan.nbv import PlanningError, Traversal, plane_index, plane_world, team_route

#: routes planned again round a cell a leg cut, at most
REROUTES = 3


@dataclass(frozen=True)
class DriverRule:
    """What `drive_to_pose` refuses (its parameters of the same names)."""

    occupied_threshold: int = 65
    start_clear_m: float = 0.3


def driver_blocked(grid: OccupancyGrid, seen: GridSlice, start_xy: ArrayLike,
                   rule: DriverRule) -> np.ndarray:
    """The ground-plane cells of `grid` whose centre `seen` holds occupied by `rule`, but for
    those within its start_clear_m of the start (the rover's own body as the team saw it)."""
    plane = grid.shape[:2]
    xy = plane_world(grid, np.stack(np.meshgrid(*map(np.arange, plane), indexing='ij'), -1))
    occupied = seen.occupied(xy.reshape(-1, 2), rule.occupied_threshold).reshape(plane)
    return occupied & (np.hypot(*(xy - np.asarray(start_xy, float)[:2]).transpose(2, 0, 1))
                       > rule.start_clear_m)


def drivable_route(trav: Traversal, grid: OccupancyGrid, start_xy: ArrayLike,
                   goal_xy: ArrayLike, *, seen: GridSlice | None, rule: DriverRule,
                   others: Sequence[ArrayLike] = (), moving: Sequence[ArrayLike] = (),
                   clearance_m: float,
                   snap_m: float = 1.0, last_leg: bool = True) -> list[np.ndarray]:
    """`team_route`'s waypoints from start_xy to goal_xy through no cell the driver refuses on
    `seen` (its map/grid; None: none yet, the route as planned). A leg that still cuts an
    occupied cell (a diagonal step past its corner) has the route's cells round that one
    blocked and is planned again, up to REROUTES times. PlanningError when no route the
    driver accepts is found (a straight last leg to a goal among occupied cells: try again
    without `last_leg`)."""
    start = np.asarray(start_xy, float)[:2]
    if seen is None:
        return team_route(trav, grid, start, goal_xy, others=others, moving=moving,
                          clearance_m=clearance_m, snap_m=snap_m, last_leg=last_leg)
    blocked = driver_blocked(grid, seen, start, rule)
    tries = 0
    while True:
        route = team_route(trav, grid, start, goal_xy, others=others, moving=moving,
                           clearance_m=clearance_m, snap_m=snap_m, last_leg=last_leg,
                           blocked=blocked)
        hit = obstruction(np.vstack([start, *route]), seen, threshold=rule.occupied_threshold,
                          start_clear_m=rule.start_clear_m)
        if hit is None:
            return route
        # the goal in an occupied cell, or the straight last leg to it: no other route helps
        if hit.kind == 'point' or (last_leg and hit.index == len(route)) or tries == REROUTES:
            raise PlanningError(
                f'no route to {np.round(np.asarray(goal_xy, float), 2)} that the driver '
                f'accepts: the {"goal" if hit.kind == "point" else "path"} meets a cell '
                f'map/grid holds occupied at {np.round(hit.xy, 2)}')
        cell = plane_index(grid, hit.xy)
        lo = np.maximum(cell - 1, 0)
        blocked[lo[0]:cell[0] + 2, lo[1]:cell[1] + 2] = True
        tries += 1
