"""The chain A_0n (Eq. E-3) and its workspace (Fig. E-5)."""
import numpy as np
import pytest

from coop_braid.chain import Chain
from coop_braid.errors import BraidError
from coop_braid.stage import StageGeometry


@pytest.fixture(scope='module')
def chain3():
    return Chain((StageGeometry(), StageGeometry(leg_long=0.065), StageGeometry()))


def test_pose_is_the_product_of_the_stage_transforms(chain3):
    s = [3, 6, 1]
    want = chain3.stages[0].transform(3) @ chain3.stages[1].transform(6) \
        @ chain3.stages[2].transform(1)
    np.testing.assert_allclose(chain3.pose(s), want, atol=1e-15)
    np.testing.assert_allclose(chain3.partial(s, 1, 3),
                               chain3.stages[1].transform(6) @ chain3.stages[2].transform(1))


def test_straight_chain_is_the_sum_of_leg_lengths(chain3):
    assert chain3.straight_reach() == pytest.approx(0.06 + 0.065 + 0.06, abs=1e-13)
    np.testing.assert_allclose(chain3.pose([0, 0, 0])[:3, 3], [0, 0, 0.135], atol=1e-13)


def test_workspace_enumerates_every_state_in_flat_order(chain3):
    ws = chain3.workspace()
    assert ws.shape == (512, 4, 4)
    idx = np.array([0, 1, 8, 77, 511])
    states = Chain.flat_to_states(idx, 3)
    np.testing.assert_array_equal(states[3], [1, 1, 5])
    np.testing.assert_allclose(ws[idx], chain3.poses(states), atol=1e-15)
    np.testing.assert_allclose(chain3.workspace(first=1)[8 * 6 + 1],
                               chain3.partial([0, 6, 1], 1, 3), atol=1e-15)


def test_suffix_moments_are_the_workspace_mean(chain3):
    ws = chain3.workspace()
    mom = chain3.suffix_moments(0)
    np.testing.assert_allclose(mom.mean, ws.mean(axis=0), atol=1e-14)
    second = np.mean([np.kron(a, a) for a in ws], axis=0)
    np.testing.assert_allclose(mom.second, second, atol=1e-14)


def test_bad_states_and_sizes_are_refused(chain3):
    with pytest.raises(BraidError, match=r'0\.\.7'):
        chain3.pose([0, 8, 0])
    with pytest.raises(BraidError, match='3 stages'):
        chain3.pose([0, 1])
    with pytest.raises(BraidError, match='at least one'):
        Chain.uniform(StageGeometry(), 0)
    with pytest.raises(BraidError, match='1 to 6 stages'):
        Chain.uniform(StageGeometry(), 7).workspace()
