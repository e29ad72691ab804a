"""coop_common.rover_geometry: a heading from a quaternion, the camera's pose in the map, the
mast aimed at a point."""
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_common.rover_geometry import (
    BASE_HEIGHT_M,
    ReachError,
    camera_in_base,
    camera_in_map,
    mast_aim,
    yaw_of,
)


def test_yaw_of_a_quaternion_matches_scipy():
    for yaw in (-3.0, -0.4, 0.0, 1.2, 3.1):
        q = Rotation.from_euler('z', yaw).as_quat()
        assert math.isclose(yaw_of(*q), yaw, abs_tol=1e-12)


def test_camera_in_map_is_the_base_pose_times_camera_in_base():
    c = camera_in_map(1.0, -2.0, math.pi / 2, 0.3, 0.4)
    b = camera_in_base(0.3, 0.4)
    rz = Rotation.from_euler('z', math.pi / 2).as_matrix()
    np.testing.assert_allclose(c[:3, :3], rz @ b[:3, :3], atol=1e-12)
    np.testing.assert_allclose(c[:3, 3], rz @ b[:3, 3] + [1.0, -2.0, BASE_HEIGHT_M], atol=1e-12)


def test_the_mast_aimed_at_a_point_has_it_on_the_optical_axis():
    rng = np.random.default_rng(3)
    for _ in range(50):
        x, y, yaw = rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-math.pi, math.pi)
        # anywhere 0.3-2 m off the rover, from the ground to above the camera
        d, bearing = rng.uniform(0.3, 2.0), rng.uniform(-math.pi, math.pi)
        target = np.array([x + d * math.cos(bearing), y + d * math.sin(bearing),
                           rng.uniform(0.0, 1.0)])
        pan, tilt = mast_aim(x, y, yaw, target)
        cam = camera_in_map(x, y, yaw, pan, tilt)
        to = target - cam[:3, 3]
        # the target lies along the optical z, not off it (within 0.1 mm)
        assert to @ cam[:3, 2] > 0
        assert np.linalg.norm(to - (to @ cam[:3, 2]) * cam[:3, 2]) < 1e-4


def test_a_point_the_mast_cannot_aim_at_is_a_reach_error():
    with pytest.raises(ReachError, match='tilt limits'):
        mast_aim(0.0, 0.0, 0.0, [0.0, 0.05, -3.0])       # straight down below the rover
    with pytest.raises(ReachError, match="mast's reach"):
        mast_aim(0.0, 0.0, 0.0, camera_in_map(0.0, 0.0, 0.0, 0.0, 0.0)[:3, 3])
    with pytest.raises(ReachError, match='finite'):
        mast_aim(0.0, 0.0, 0.0, [math.nan, 0.0, 0.0])


def test_every_joint_group_has_its_joints():
    from typing import get_args

    from coop_common.rover_geometry import ARM_JOINTS, GROUP_JOINTS, MAST_JOINTS, JointGroup
    assert tuple(GROUP_JOINTS) == get_args(JointGroup) == ('arm', 'mast')
    assert GROUP_JOINTS['arm'] == ARM_JOINTS and GROUP_JOINTS['mast'] == MAST_JOINTS
