"""coop_common.rover_geometry: a heading from a quaternion, the camera's pose in the map."""
import math

import numpy as np
from scipy.spatial.transform import Rotation

from coop_common.rover_geometry import BASE_HEIGHT_M, camera_in_base, camera_in_map, yaw_of


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


def test_every_joint_group_has_its_joints():
    from typing import get_args

    from coop_common.rover_geometry import ARM_JOINTS, GROUP_JOINTS, MAST_JOINTS, JointGroup
    assert tuple(GROUP_JOINTS) == get_args(JointGroup) == ('arm', 'mast')
    assert GROUP_JOINTS['arm'] == ARM_JOINTS and GROUP_JOINTS['mast'] == MAST_JOINTS
