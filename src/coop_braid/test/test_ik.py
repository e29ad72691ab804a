"""Inverse kinematics (E.3.2): every method behind `solve` against exhaustive search."""
import numpy as np
import pytest

from coop_braid.chain import Chain
from coop_braid.errors import BraidError
from coop_braid.ik import (
    BeamOptions,
    BeamScore,
    GeneticOptions,
    Method,
    Weights,
    pose_errors,
    solve,
)
from coop_braid.stage import StageGeometry


@pytest.fixture(scope='module')
def geometry():
    return StageGeometry()


def test_exhaustive_finds_the_exact_state_of_a_two_stage_target(geometry):
    chain = Chain.uniform(geometry, 2)
    for states in ([5, 2], [0, 7], [3, 3], [6, 1]):
        res = solve(chain, chain.pose(states), method=Method.EXHAUSTIVE)
        np.testing.assert_array_equal(res.states, states)
        assert res.pos_err_m < 1e-12 and res.ang_err_rad < 1e-6 and res.evaluations == 64


@pytest.mark.parametrize('method', [Method.BEAM, Method.COMBINATORIAL, Method.GENETIC])
def test_heuristics_agree_with_exhaustive_on_small_chains(geometry, method):
    chain = Chain.uniform(geometry, 3)
    rng = np.random.default_rng(3)
    worse = []
    for i in range(12):
        goal = chain.pose(rng.integers(0, 8, 3))
        goal[:3, 3] = chain.pose(rng.integers(0, 8, 3))[:3, 3]   # not exactly reachable
        ref = solve(chain, goal, method=Method.EXHAUSTIVE)
        res = solve(chain, goal, method=method, rng=i)
        assert res.cost >= ref.cost - 1e-12
        worse.append(res.cost > 1.1 * ref.cost + 1e-12)
    assert sum(worse) <= 2, method


def test_beam_matches_exhaustive_on_five_stages(geometry):
    chain = Chain.uniform(geometry, 5)
    rng = np.random.default_rng(5)
    for _ in range(5):
        goal = chain.pose(rng.integers(0, 8, 5))
        goal[:3, 3] = chain.pose(rng.integers(0, 8, 5))[:3, 3]
        ref = solve(chain, goal, method=Method.EXHAUSTIVE)
        res = solve(chain, goal, method=Method.BEAM)
        assert res.cost <= 1.1 * ref.cost + 1e-12


def test_the_density_score_ranks_partial_chains_too(geometry):
    chain = Chain.uniform(geometry, 7)
    goal = chain.pose([1, 5, 7, 0, 2, 2, 6])
    res = solve(chain, goal, options=BeamOptions(score=BeamScore.DENSITY, width=64))
    assert res.pos_err_m < 3e-3 and res.evaluations > 0


def test_a_reachable_target_of_a_long_chain_is_found_closely(geometry):
    chain = Chain.uniform(geometry, 8)
    goal = chain.pose([1, 5, 7, 0, 2, 2, 6, 3])
    res = solve(chain, goal)
    assert res.pos_err_m < 2e-3 and res.ang_err_rad < np.radians(10)
    pos, ang = pose_errors(res.pose, goal)
    assert res.pos_err_m == pytest.approx(float(pos)) and res.cost == pytest.approx(
        float(pos) + 0.01 * float(ang))


@pytest.mark.parametrize('method', list(Method))
def test_an_unreachable_target_gets_the_nearest_pose_not_an_exception(geometry, method):
    chain = Chain.uniform(geometry, 3)
    goal = np.eye(4)
    goal[:3, 3] = (1.0, 0.0, -2.0)                    # metres away, below the base
    res = solve(chain, goal, method=method, rng=0)
    assert res.pos_err_m > 1.5 and np.isfinite(res.cost)
    ref = solve(chain, goal, method=Method.EXHAUSTIVE)
    assert res.cost <= ref.cost * 1.01


def test_weights_trade_position_for_orientation(geometry):
    chain = Chain.uniform(geometry, 4)
    goal = chain.pose([1, 1, 1, 1])
    goal[:3, 3] = chain.pose([0, 0, 0, 0])[:3, 3]
    pos_only = solve(chain, goal, method=Method.EXHAUSTIVE, weights=Weights(orientation=0.0))
    ang_only = solve(chain, goal, method=Method.EXHAUSTIVE,
                     weights=Weights(position=0.0, orientation=1.0))
    assert pos_only.pos_err_m < ang_only.pos_err_m
    assert ang_only.ang_err_rad < pos_only.ang_err_rad


def test_seeded_searches_repeat(geometry):
    chain = Chain.uniform(geometry, 6)
    goal = chain.pose([1, 2, 3, 4, 5, 6])
    a = solve(chain, goal, method=Method.GENETIC, rng=7,
              options=GeneticOptions(population=16, generations=10))
    b = solve(chain, goal, method=Method.GENETIC, rng=np.random.default_rng(7),
              options=GeneticOptions(population=16, generations=10))
    np.testing.assert_array_equal(a.states, b.states)


def test_bad_targets_and_options_are_refused(geometry):
    chain = Chain.uniform(geometry, 7)
    with pytest.raises(BraidError, match='4x4'):
        solve(chain, np.eye(3))
    bad = np.eye(4)
    bad[0, 0] = 2.0
    with pytest.raises(BraidError, match='orthonormal'):
        solve(chain, bad)
    with pytest.raises(BraidError, match='at most 6 stages'):
        solve(chain, np.eye(4), method=Method.EXHAUSTIVE)
    with pytest.raises(BraidError, match='BeamOptions'):
        solve(chain, np.eye(4), method=Method.BEAM, options=GeneticOptions())
    with pytest.raises(BraidError, match='width'):
        BeamOptions(width=0)
    with pytest.raises(BraidError, match='orientation'):
        Weights(orientation=-1.0)
