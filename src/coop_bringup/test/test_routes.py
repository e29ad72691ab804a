"""The mission's routes (coop_bringup.routes): planned on the view planner's grid, accepted by
the driver's own check of the mapper's map/grid, where the two grids disagree."""
from __future__ import annotations

import numpy as np
import pytest
from coop_bringup.routes import DriverRule, drivable_route, driver_blocked

from coop_insertion.drive import GridSlice, obstruction
from coop_viewplan.grid import OccupancyGrid
from coop_viewplan.nbv import PlanningError, Traversal

RULE = DriverRule(occupied_threshold=65, start_clear_m=0.3)


def _field(n: int = 60) -> tuple[OccupancyGrid, Traversal]:
    """The planning side: a 3-D grid of 0.1 m cells from (0, 0), every ground cell navigable."""
    g = OccupancyGrid.empty((n, n, 4), resolution=0.1)
    g.known[:] = True
    g.prob[:] = 0.0
    nav = np.ones((n, n), bool)
    return g, Traversal(nav, np.zeros((n, n)), nav.copy())


def _seen(cells_xy: list[tuple[int, int]], n: int = 60) -> GridSlice:
    """The driver's side: a map/grid on the same lattice (rows along y), free but for the
    cells (x index, y index) at 100 %."""
    occ = np.zeros((n, n), np.int8)
    for i, j in cells_xy:
        occ[j, i] = 100
    return GridSlice(occ, (0.0, 0.0), 0.1)


def test_the_route_keeps_off_a_wall_only_the_driver_sees():
    g, trav = _field()
    seen = _seen([(i, 30) for i in range(5, 50)])        # y 3.0-3.1 m, x 0.5-5.0 m
    start, goal = (2.0, 1.0), (2.0, 5.0)
    assert obstruction(np.array([start, goal]), seen) is not None   # straight: refused
    route = drivable_route(trav, g, start, goal, seen=seen, rule=RULE, clearance_m=0.3)
    assert obstruction(np.vstack([start, *route]), seen) is None
    assert np.allclose(route[-1], goal)
    # unseen (no map/grid yet): the planning grid's route, straight through
    route = drivable_route(trav, g, start, goal, seen=None, rule=RULE, clearance_m=0.3)
    assert obstruction(np.vstack([start, *route]), seen) is not None


def test_the_rovers_own_body_on_map_grid_does_not_hold_it_in():
    g, trav = _field()
    body = [(i, j) for i in range(18, 23) for j in range(8, 13)]   # 0.5 m round (2.05, 1.05)
    seen = _seen([*body, (20, 20)])                        # and a rock 1 m ahead
    blocked = driver_blocked(g, seen, (2.05, 1.05), RULE)
    assert np.argwhere(blocked).tolist() == [[20, 20]]      # within 0.3 m: its own body
    route = drivable_route(trav, g, (2.05, 1.05), (2.0, 5.0), seen=seen, rule=RULE,
                           clearance_m=0.3)
    assert obstruction(np.vstack([(2.05, 1.05), *route]), seen,
                       start_clear_m=RULE.start_clear_m) is None


def test_a_goal_in_an_occupied_cell_is_refused_with_the_last_leg_and_reached_without():
    g, trav = _field()
    seen = _seen([(40, 40)])
    start, goal = (2.05, 2.05), (4.05, 4.05)
    with pytest.raises(PlanningError, match='the goal meets a cell map/grid holds occupied'):
        drivable_route(trav, g, start, goal, seen=seen, rule=RULE, clearance_m=0.3)
    route = drivable_route(trav, g, start, goal, seen=seen, rule=RULE, clearance_m=0.3,
                           last_leg=False)
    assert obstruction(np.vstack([start, *route]), seen) is None
    assert np.hypot(*(route[-1] - np.array(goal))) <= 0.15


def test_every_route_returned_is_one_the_driver_accepts():
    """Over random fields of rocks only the driver's grid holds (some diagonal steps pass
    their corners), a route is either accepted by the driver's check or refused with a
    PlanningError, and most are found."""
    rng = np.random.default_rng(7)
    g, trav = _field()
    found = 0
    for _ in range(60):
        cells = rng.integers(0, 60, (90, 2))
        seen = _seen([tuple(c) for c in cells])
        start, goal = rng.uniform(0.2, 5.8, 2), rng.uniform(0.2, 5.8, 2)
        try:
            route = drivable_route(trav, g, start, goal, seen=seen, rule=RULE, clearance_m=0.3,
                                   last_leg=False)
        except PlanningError:
            continue
        found += 1
        assert obstruction(np.vstack([start, *route]), seen,
                           start_clear_m=RULE.start_clear_m) is None, (start, goal)
    assert found >= 50, found
