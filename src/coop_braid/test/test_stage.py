"""Stage forward kinematics (E.3.1) against hand computations and an independent solve."""
import math

import numpy as np
import pytest
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from coop_braid.errors import BraidError
from coop_braid.stage import (
    LEG_AZIMUTHS,
    LegState,
    StageGeometry,
    leg_states,
    stage_transform,
    symmetric_tilt,
)


def rot_z(a):
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@pytest.mark.parametrize('state', [0, 7])
def test_equal_legs_are_a_pure_z_translation(state):
    g = StageGeometry()
    a = g.transform(state)
    length = g.leg_long if state == 7 else g.leg_short
    np.testing.assert_allclose(a[:3, :3], np.eye(3), atol=1e-13)
    np.testing.assert_allclose(a[:3, 3], [0.0, 0.0, length], atol=1e-13)


def test_equal_legs_between_unequal_disks_lean_inwards():
    a = stage_transform(np.array([0.05, 0.05, 0.05]), base_radius=0.05, platform_radius=0.03)
    np.testing.assert_allclose(a[:3, :3], np.eye(3), atol=1e-13)
    np.testing.assert_allclose(a[:3, 3], [0.0, 0.0, math.sqrt(0.05 ** 2 - 0.02 ** 2)],
                               atol=1e-13)


@pytest.mark.parametrize('odd_leg', [0, 1, 2])
@pytest.mark.parametrize('odd_long', [True, False])
def test_one_leg_different_is_the_closed_form_tilt_about_its_axis(odd_leg, odd_long):
    """Legs j != odd equal: the platform tilts about the axis perpendicular to leg odd's plane,
    by the closed form of `symmetric_tilt` (Fig. E-3's section), rotated to that leg."""
    g = StageGeometry()
    state = (1 << odd_leg) if odd_long else 7 ^ (1 << odd_leg)
    odd, pair = (g.leg_long, g.leg_short) if odd_long else (g.leg_short, g.leg_long)
    _, tilt, height = symmetric_tilt(odd, pair, radius=g.base_radius)
    a = g.transform(state)
    rz = rot_z(LEG_AZIMUTHS[odd_leg])
    local = rz.T @ a[:3, :3] @ rz                  # the tilt seen in leg odd's own frame
    c, s = math.cos(tilt), math.sin(tilt)
    np.testing.assert_allclose(local, [[c, 0, -s], [0, 1, 0], [s, 0, c]], atol=1e-12)
    assert a[2, 3] == pytest.approx(height, abs=1e-12)
    # the centroid stays in leg odd's vertical plane
    assert abs(np.dot(a[:2, 3], [-math.sin(LEG_AZIMUTHS[odd_leg]),
                                 math.cos(LEG_AZIMUTHS[odd_leg])])) < 1e-12
    assert (tilt > 0) == odd_long


def _independent_pose(lengths, rb, rp):
    """The stage pose from a least-squares solve of the six constraints in (rotation vector,
    translation): platform point j in leg j's vertical plane, at distance l_j from its base
    point."""
    u = np.stack([np.cos(LEG_AZIMUTHS), np.sin(LEG_AZIMUTHS), np.zeros(3)], axis=1)
    v = np.stack([-np.sin(LEG_AZIMUTHS), np.cos(LEG_AZIMUTHS), np.zeros(3)], axis=1)
    base, plat = rb * u, rp * u

    def resid(x):
        r = Rotation.from_rotvec(x[:3]).as_matrix()
        p = x[3:] + plat @ r.T
        return np.concatenate([np.sum(p * v, axis=1),
                               np.linalg.norm(p - base, axis=1) - lengths])

    x0 = np.array([0, 0, 0, 0, 0, float(np.mean(lengths))])
    sol = least_squares(resid, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15, method='lm')
    return Rotation.from_rotvec(sol.x[:3]).as_matrix(), sol.x[3:]


@pytest.mark.parametrize('lengths,rb,rp', [
    ((0.045, 0.06, 0.052), 0.04, 0.04),
    ((0.06, 0.045, 0.045), 0.04, 0.04),
    ((0.07, 0.05, 0.061), 0.05, 0.035),
    ((0.03, 0.034, 0.037), 0.03, 0.045),
])
def test_fk_matches_an_independent_numeric_solve_to_1e_9_m(lengths, rb, rp):
    lengths = np.array(lengths)
    a = stage_transform(lengths, base_radius=rb, platform_radius=rp)
    r, t = _independent_pose(lengths, rb, rp)
    assert np.max(np.abs(a[:3, 3] - t)) < 1e-9
    assert np.max(np.abs(a[:3, :3] - r)) < 1e-9
    # and every platform point of ours satisfies the constraints to 1e-12
    u = np.stack([np.cos(LEG_AZIMUTHS), np.sin(LEG_AZIMUTHS), np.zeros(3)], axis=1)
    p = a[:3, 3] + (rp * u) @ a[:3, :3].T
    np.testing.assert_allclose(np.linalg.norm(p - rb * u, axis=1), lengths, atol=1e-12)


def test_the_eight_states_are_precomputed_and_read_only():
    g = StageGeometry()
    assert g.transforms.shape == (8, 4, 4)
    with pytest.raises(ValueError):
        g.transforms[0, 0, 0] = 2.0
    assert leg_states(6) == (LegState.SHORT, LegState.LONG, LegState.LONG)
    np.testing.assert_allclose(g.leg_lengths(1), [g.leg_long, g.leg_short, g.leg_short])
    with pytest.raises(BraidError, match=r'0\.\.7'):
        g.transform(8)


@pytest.mark.parametrize('kwargs,reason', [
    ({'leg_short': -0.01}, 'leg_short'),
    ({'base_radius': float('nan')}, 'base_radius'),
    ({'leg_short': 0.06, 'leg_long': 0.06}, 'shorter than'),
    ({'leg_short': 0.005, 'leg_long': 0.2}, 'cannot be assembled'),
])
def test_invalid_geometry_is_refused_with_the_reason(kwargs, reason):
    with pytest.raises(BraidError, match=reason):
        StageGeometry(**kwargs)
