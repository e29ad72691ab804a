"""The self and teammate body filter: the volume by hand, the pose a cloud is filtered with."""
import numpy as np
import pytest

from coop_mapping.bodies import BodyFilter, pose_at


def test_body_volume_hand_computed():
    bf = BodyFilter(radius_m=0.5, above_camera_m=0.2)
    cams = [np.array([0.0, 0.0, 1.0]), np.array([3.0, 0.0, 0.5])]
    pts = np.array([[0.3, 0.3, 0.0],      # inside the first (r 0.42, below the camera)
                    [0.3, 0.3, 1.19],     # inside, just under the top 1.2
                    [0.3, 0.3, 1.21],     # above the top
                    [0.4, 0.4, 0.5],      # r 0.57: outside
                    [3.0, 0.49, 0.6],     # inside the second (top 0.7)
                    [3.0, 0.0, 0.8]])     # above the second
    assert bf.mask(pts, cams).tolist() == [True, True, False, False, True, False]
    assert not BodyFilter(radius_m=0.0).mask(pts, cams).any()
    assert not bf.mask(pts, []).any()
    with pytest.raises(ValueError):
        BodyFilter(radius_m=-1.0)
    with pytest.raises(ValueError):
        BodyFilter(pose_tolerance_s=float('nan'))


def test_the_teammate_pose_is_the_latest_not_after_the_cloud():
    poses = {100: np.array([1.0, 0, 0]), 300: np.array([3.0, 0, 0]),
             200: np.array([2.0, 0, 0])}
    assert pose_at(poses, 250, 1000)[0] == 2.0       # latest at or before 250
    assert pose_at(poses, 300, 1000)[0] == 3.0       # the same stamp counts
    assert pose_at(poses, 99, 1000) is None          # none before
    assert pose_at(poses, 250, 40) is None           # 200 is 50 old
    bf = BodyFilter(pose_tolerance_s=100e-9)
    own = np.array([9.0, 9, 9])
    cams = bf.cameras_at(250, own, [poses, {}])
    assert len(cams) == 2 and cams[0].tolist() == [9.0, 9, 9] and cams[1][0] == 2.0
