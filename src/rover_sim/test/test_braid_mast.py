"""The BRAID mast option of the world (issue #37, deliverable 5): the camera renders from the
pan link times the chain's forward kinematics of the state in effect, a new state takes effect
after the settle time, the rover's own estimate uses the nominal kinematics, the pan/tilt
rover is unchanged."""
import numpy as np
import pybullet as pb
import pytest

from coop_braid.mast import BraidMast
from coop_common.dynparams import load_truth
from rover_sim.compliance import quat_to_matrix
from rover_sim.config import ConfigError, NoiseConfig, SimConfig
from rover_sim.trajectory import TrajectoryError
from rover_sim.world import World

QUIET = NoiseConfig(fraction=0.0)
BENT = [1, 0, 6, 0, 3]


@pytest.fixture(scope='module')
def braid_world():
    w = World(SimConfig(rovers=1, noise=QUIET, stereo_rate_hz=0.0, mast='braid',
                        braid_stages=5, braid_settle_s=0.5), [load_truth()])
    yield w
    w.close()


def _pan_frame(w: World) -> tuple[np.ndarray, np.ndarray]:
    r = w.rovers[0]
    st = pb.getLinkState(r.body, r.pan_index, computeForwardKinematics=1,
                         physicsClientId=w.client)
    return np.array(st[4]), quat_to_matrix(st[5])


def test_camera_follows_the_commanded_state_after_the_settle_time(braid_world):
    w = braid_world
    mast = BraidMast.rover(5)
    for _ in range(20):
        w.step()
    p0, _ = w.camera_pose(0)
    at = w.command_braid(0, BENT)
    assert at == pytest.approx(w.time_s + 0.5)
    for _ in range(round(0.4 / w.dt)):
        w.step()
    np.testing.assert_allclose(w.camera_pose(0)[0], p0, atol=2e-3)   # not switched yet
    np.testing.assert_array_equal(w.braid_state(0), np.zeros(5))
    for _ in range(round(0.2 / w.dt)):
        w.step()
    np.testing.assert_array_equal(w.braid_state(0), BENT)
    pos, rot = w.camera_pose(0)
    pp, pr = _pan_frame(w)
    t = mast.optical_in_pan(BENT)
    np.testing.assert_allclose(pos, pp + pr @ t[:3, 3], atol=1e-12)
    np.testing.assert_allclose(rot, pr @ t[:3, :3], atol=1e-12)
    assert np.linalg.norm(pos - p0) > 0.02          # the bent chain moved the camera
    # the rover's own estimate: odometry, pan encoder, nominal FK; blind only to the base's
    # deflection on its compliance (millimetres at rest)
    ep, er, _ = w.estimated_camera_pose(0)
    assert np.linalg.norm(ep - pos) < 0.01
    assert np.degrees(np.arccos(np.clip((np.trace(er.T @ rot) - 1) / 2, -1, 1))) < 1.0


def test_pan_turns_the_braid_camera_and_tilt_is_refused(braid_world):
    w = braid_world
    _, r0 = w.camera_pose(0)
    w.command_mast(0, ['mast_pan'], [0.5], [[0.8]])
    for _ in range(round(1.0 / w.dt)):
        w.step()
    _, r1 = w.camera_pose(0)
    h0, h1 = (np.arctan2(r[1, 2], r[0, 2]) for r in (r0, r1))
    assert h1 - h0 == pytest.approx(0.8, abs=0.02)
    with pytest.raises(TrajectoryError, match='no tilt joint'):
        w.command_mast(0, ['mast_pan', 'mast_tilt'], [0.5], [[0.0, 0.3]])


def test_bad_braid_commands_are_refused(braid_world):
    w = braid_world
    with pytest.raises(ValueError, match='5 integers'):
        w.command_braid(0, [0, 1, 2])
    with pytest.raises(ValueError, match=r'0\.\.7'):
        w.command_braid(0, [0, 1, 2, 3, 8])
    with pytest.raises(ValueError, match='5 integers'):
        w.command_braid(0, [0.0, 1.0, 2.0, 3.0, 4.0])
    with pytest.raises(ConfigError, match='mast'):
        SimConfig(mast='telescope')
    with pytest.raises(ConfigError, match='braid_stages'):
        SimConfig(braid_stages=0)


def test_the_default_rover_keeps_its_pan_tilt_mast():
    w = World(SimConfig(rovers=1, noise=QUIET, stereo_rate_hz=0.0), [load_truth()])
    try:
        assert w.braid is None and w.braid_state(0) is None
        with pytest.raises(ValueError, match='pan_tilt mast'):
            w.command_braid(0, [0] * 10)
        w.command_mast(0, ['mast_pan', 'mast_tilt'], [0.3], [[0.0, 0.2]])
        for _ in range(round(0.6 / w.dt)):
            w.step()
        _, rot = w.camera_pose(0)
        assert -np.degrees(np.arcsin(rot[2, 2])) == pytest.approx(np.degrees(0.2), abs=1.0)
    finally:
        w.close()
