"""The planner's mast views (issue #37, deliverable 5): candidates placed where a BRAID mast's
reachable views put the camera, and those views from BRAID IK (`coop_viewplan.mast`)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coop_braid.mast import BraidMast, heading_pitch
from coop_viewplan.errors import OptionError
from coop_viewplan.grid import OccupancyGrid
from coop_viewplan.mast import PAN_HEIGHT_M, braid_views
from coop_viewplan.nbv import CameraState, MastView, NbvConfig, NextBestViewPlanner

VIEWS = (MastView(forward_m=0.1, lateral_m=-0.05, height_m=0.9, heading_rad=0.2,
                  pitch_rad=0.1),
         MastView(forward_m=0.0, lateral_m=0.0, height_m=1.4, heading_rad=0.0,
                  pitch_rad=0.5))


def _site() -> OccupancyGrid:
    """3-D grid, 0.25 m cells: a known free floor layer over a known ground, unknown above."""
    g = OccupancyGrid.empty((40, 40, 8), resolution=0.25)
    g.known[:, :, :3] = True
    g.prob[:, :, :3] = 0.0
    g.prob[:, :, 0] = 1.0
    return g


def _plan(views: tuple[MastView, ...]):
    planner = NextBestViewPlanner(NbvConfig(
        fov_deg=60, depth_m=3.0, n_az=12, n_el=8, n_positions=12, n_yaw=4,
        pitches_deg=(5.0, 20.0), camera_height_m=0.6, clearance_m=0.3, p_empty=0.45,
        mast_views=views))
    cam = CameraState(np.array([5.0, 5.0, 0.6]))
    return planner.plan(_site(), cam, strategy='max_information',
                        rng=np.random.default_rng(3))


def test_candidates_take_each_mast_view_at_each_cell_and_heading():
    d = _plan(VIEWS)
    c = d.candidates
    assert c.view is not None and len(c) == 12 * 4 * 2
    np.testing.assert_array_equal(c.view, np.tile([0, 1], len(c) // 2))
    for v, view in enumerate(VIEWS):
        sel = c.view == v
        assert np.all(c.positions[sel, 2] == view.height_m)
        assert np.all(c.pitch[sel] == view.pitch_rad)
    # the camera stands off the cell centre by the view's offset, turned by the turntable
    # (candidate heading less the view's heading offset)
    centre = (np.floor(c.positions[:, :2] / 0.25) + 0.5) * 0.25
    first = c.view == 0
    turn = c.yaw[first] - VIEWS[0].heading_rad
    want = centre[first] + np.c_[np.cos(turn) * 0.1 + np.sin(turn) * 0.05,
                                 np.sin(turn) * 0.1 - np.cos(turn) * 0.05]
    np.testing.assert_allclose(c.positions[first, :2], want, atol=1e-12)
    assert d.view in (0, 1) and d.position[2] == VIEWS[d.view].height_m


def test_without_mast_views_the_pan_tilt_head_takes_every_pitch():
    d = _plan(())
    assert d.candidates.view is None and d.view == -1
    assert len(d.candidates) == 12 * 4 * 2
    assert set(np.round(np.degrees(d.candidates.pitch), 6)) == {5.0, 20.0}
    assert np.all(d.candidates.positions[:, 2] == 0.6)


def test_mast_view_is_checked():
    with pytest.raises(OptionError, match='pitch_rad'):
        MastView(forward_m=0.0, lateral_m=0.0, height_m=1.0, heading_rad=0.0, pitch_rad=2.0)
    with pytest.raises(OptionError, match='height_m'):
        MastView(forward_m=0.0, lateral_m=0.0, height_m=math.nan, heading_rad=0.0,
                 pitch_rad=0.0)


def test_braid_views_are_the_poses_the_ik_states_give():
    # a 5-stage mast: the straight, retracted chain's camera 0.625 m above the ground
    heights = (0.65, 0.70)
    bv = braid_views(5, heights_m=heights, pitches_deg=(5.0, 20.0))
    assert len(bv.tried) == 4 and len(bv.views) == sum(t.reached for t in bv.tried) >= 2
    mast = BraidMast.rover(5)
    for view, states in zip(bv.views, bv.states, strict=True):
        t = mast.optical_in_pan(states)
        np.testing.assert_allclose([view.forward_m, view.lateral_m, view.height_m],
                                   t[:3, 3] + [0.0, 0.0, PAN_HEIGHT_M], atol=1e-12)
        assert (view.heading_rad, view.pitch_rad) == pytest.approx(heading_pitch(t), abs=1e-12)
    reached = [t for t in bv.tried if t.reached]
    for view, t in zip(bv.views, reached, strict=True):
        assert abs(view.height_m - PAN_HEIGHT_M - t.height_m) <= 0.03 + 1e-12
        assert abs(view.pitch_rad - t.pitch_rad) <= math.radians(2.5) + 1e-12


def test_a_mast_that_reaches_no_wanted_view_is_refused():
    with pytest.raises(OptionError, match='reaches none'):
        braid_views(3, heights_m=(2.0,), pitches_deg=(5.0,))
