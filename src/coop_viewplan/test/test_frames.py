"""Optical-frame conversions."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coop_viewplan.frames import look_at_quaternion, optical_quaternion, yaw_pitch_from_optical


def test_optical_axis_points_along_heading():
    q = optical_quaternion(np.pi / 2, 0.0)
    r = Rotation.from_quat(q).as_matrix()
    assert r[:, 2] == pytest.approx([0, 1, 0], abs=1e-12)     # optical z = map +y
    assert r[:, 1] == pytest.approx([0, 0, -1], abs=1e-12)    # optical y = down


@pytest.mark.parametrize('yaw,pitch', [(0.3, 0.2), (-2.0, -0.5), (3.0, 0.0)])
def test_round_trip(yaw, pitch):
    y, p = yaw_pitch_from_optical(optical_quaternion(yaw, pitch))
    assert (y, p) == pytest.approx((yaw, pitch))


def test_look_at_down():
    q = look_at_quaternion(np.array([0, 0, 1.0]), np.array([1.0, 0, 0]))
    y, p = yaw_pitch_from_optical(q)
    assert y == pytest.approx(0) and p == pytest.approx(np.pi / 4)
