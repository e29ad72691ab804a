"""Tip-over stability (app. A.3, Eq. A-5): the zero-moment point against hand-computed cases
and the moment balance it is defined by, the footprint's margin, the motion limiter."""
from __future__ import annotations

import numpy as np
import pytest

from coop_insertion.tipover import Footprint, Loads, TipOverError, limit_motion, limit_path, zmp

G = 9.81
WHEELS = [[0.25, 0.18], [0.25, -0.18], [-0.25, -0.18], [-0.25, 0.18]]   # rover_sim's base


def test_a_mass_at_rest_stands_on_its_own_point():
    assert np.allclose(zmp(Loads.of([3.0], [[0.1, -0.2, 0.5]])), [0.1, -0.2])
    # two masses: the weighted mean of their ground points
    p = zmp(Loads.of([1.0, 3.0], [[0.0, 0.0, 0.2], [0.4, 0.4, 1.0]]))
    assert np.allclose(p, [0.3, 0.3])


def test_acceleration_moves_the_point_back_by_height_over_g():
    """A mass h high accelerating forward at a: the point moves back by h a / g."""
    h, a = 0.8, 2.0
    p = zmp(Loads.of([5.0], [[0.0, 0.0, h]], [[a, 0.0, 0.0]]))
    assert p == pytest.approx([-h * a / G, 0.0])
    p = zmp(Loads.of([5.0], [[0.0, 0.0, h]], [[0.0, a, 0.0]]))
    assert p == pytest.approx([0.0, -h * a / G])
    # upward acceleration adds weight, not moment
    p = zmp(Loads.of([5.0], [[0.2, 0.1, h]], [[0.0, 0.0, 3.0]]))
    assert p == pytest.approx([0.2, 0.1])


def test_a_push_on_the_arm_moves_the_point():
    """10 kg at the origin; the environment pushes the gripper 1 m ahead, 0.5 m up, down with
    20 N and back with 10 N: by hand, x = (0 + 0.5 (-10) - 1.0 (-20)) / (98.1 + 20)."""
    p = zmp(Loads.of([10.0], [[0.0, 0.0, 0.3]], forces=[[-10.0, 0.0, -20.0]],
                     force_points=[[1.0, 0.0, 0.5]]))
    assert p == pytest.approx([(-5.0 + 20.0) / (98.1 + 20.0), 0.0])
    # the same turned by 90 deg about z: the y row is the x row turned
    q = zmp(Loads.of([10.0], [[0.0, 0.0, 0.3]], forces=[[0.0, -10.0, -20.0]],
                     force_points=[[0.0, 1.0, 0.5]]))
    assert q == pytest.approx([0.0, p[0]])


def test_the_point_is_where_the_horizontal_moments_vanish():
    """Random masses, accelerations, forces and moments: about the computed point the
    moment of every load (Eq. A-5's first line, T) has no horizontal part."""
    rng = np.random.default_rng(1)
    for _ in range(20):
        n, k = 5, 2
        ld = Loads.of(rng.uniform(1, 10, n), rng.uniform(-1, 1, (n, 3)) + [0, 0, 1],
                      rng.normal(0, 2, (n, 3)), forces=rng.normal(0, 10, (k, 3)),
                      force_points=rng.uniform(-1, 1, (k, 3)), moments=rng.normal(0, 3, (1, 3)),
                      gravity=[0.3, -0.2, -G])
        p = np.r_[zmp(ld), 0.0]
        A = ld.masses[:, None] * (ld.accelerations - ld.gravity)
        T = (np.cross(ld.positions - p, A).sum(0) - np.cross(ld.force_points - p,
                                                               ld.forces).sum(0)
             - ld.moments.sum(0))
        assert np.allclose(T[:2], 0.0, atol=1e-9)


def test_no_point_when_the_ground_carries_nothing():
    with pytest.raises(TipOverError, match='off the ground'):
        zmp(Loads.of([1.0], [[0, 0, 1]], [[0, 0, -G]]))          # free fall
    with pytest.raises(TipOverError, match='shape'):
        Loads.of([1.0, 2.0], [[0, 0, 1]])
    with pytest.raises(TipOverError, match='finite'):
        Loads.of([1.0], [[0, 0, np.nan]])


def test_footprint_margin():
    fp = Footprint.of(WHEELS + [[0.0, 0.0]])                      # an inner point is dropped
    assert len(fp.vertices) == 4
    assert np.allclose(fp.centroid, 0.0)
    assert fp.depth == pytest.approx(0.18)
    assert fp.margin([0.0, 0.0]) == pytest.approx(0.18)
    assert fp.margin([0.25, 0.0]) == pytest.approx(0.0)
    assert fp.margin([0.35, 0.0]) == pytest.approx(-0.10)
    assert fp.margin_fraction([0.0, 0.09]) == pytest.approx(0.5)
    with pytest.raises(TipOverError, match='one line'):
        Footprint.of([[0, 0], [1, 1], [2, 2]])


def test_the_limiter_scales_a_motion_to_the_margin():
    """A 40 kg load 0.8 m up on a 60 kg base; the command swings the load hard backwards. The
    limiter's scale leaves exactly the required margin, a bit more motion would not."""
    fp = Footprint.of(WHEELS)
    masses, pos = [60.0, 40.0], [[0.0, 0.0, 0.2], [0.0, 0.0, 0.8]]
    rest = Loads.of(masses, pos)
    cmd = Loads.of(masses, pos, [[0.0, 0.0, 0.0], [-10.0, 0.0, 0.0]])
    assert fp.margin_fraction(zmp(cmd)) < 0                       # as given it tips
    lim = limit_motion(rest, cmd, fp, min_fraction=0.2)
    assert not lim.stop and 0 < lim.scale < 1
    assert lim.margin_fraction == pytest.approx(0.2)
    more = Loads.of(masses, pos, [[0.0, 0.0, 0.0], [-10.0 * lim.scale * 1.01, 0.0, 0.0]])
    assert fp.margin_fraction(zmp(more)) < 0.2
    # a gentle command passes whole
    gentle = Loads.of(masses, pos, [[0.0, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    assert limit_motion(rest, gentle, fp).scale == 1.0


def test_the_limiter_stops_when_already_outside():
    """At rest beyond the margin (a load hanging out over the side): no motion at all."""
    fp = Footprint.of(WHEELS)
    masses, pos = [60.0, 40.0], [[0.0, 0.0, 0.2], [0.0, 0.7, 0.8]]
    rest = Loads.of(masses, pos)
    lim = limit_motion(rest, Loads.of(masses, pos, [[0, 0, 0], [0.0, -1.0, 0.0]]), fp)
    assert lim.stop and lim.scale == 0.0 and lim.margin_fraction < 0.2


def test_a_path_is_limited_by_its_worst_instant_and_stopped_by_an_unsafe_pose():
    """limit_path: the smallest limit_motion scale over the plan's instants; a plan with an
    instant below the margin standing still is stopped, not slowed."""
    fp = Footprint.of(WHEELS)
    still = Loads.of([10.0], [[0.0, 0.0, 0.5]])
    gentle = Loads.of([10.0], [[0.0, 0.0, 0.5]], [[1.0, 0.0, 0.0]])
    hard = Loads.of([10.0], [[0.0, 0.0, 0.5]], [[6.0, 0.0, 0.0]])
    one = limit_motion(still, hard, fp, min_fraction=0.2)
    both = limit_path([(still, gentle), (still, hard)], fp, min_fraction=0.2)
    assert both.scale == pytest.approx(one.scale) and 0.0 < both.scale < 1.0
    assert both.margin_fraction == pytest.approx(0.2)
    leaning = Loads.of([10.0], [[0.24, 0.0, 0.5]])           # 1 cm from the front edge
    stopped = limit_path([(still, gentle), (leaning, leaning)], fp, min_fraction=0.2)
    assert stopped.stop and stopped.scale == 0.0
    with pytest.raises(TipOverError):
        limit_path([], fp)
