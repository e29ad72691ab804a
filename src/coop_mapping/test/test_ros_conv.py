"""PointCloud2 <-> arrays (coop_mapping.ros_conv): our layout, foreign layouts, bad layouts."""
import numpy as np
import pytest
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import Header

from coop_mapping.ros_conv import CloudFormatError, cloud_to_msg, msg_to_cloud


def _cloud(fields, point_step, width, height, rows: list[bytes], row_step=None):
    m = PointCloud2()
    m.header = Header(frame_id='map')
    m.fields = [PointField(name=n, offset=o, datatype=PointField.FLOAT32, count=1)
                for n, o in fields]
    m.point_step, m.width, m.height = point_step, width, height
    m.row_step = row_step if row_step is not None else point_step * width
    m.data = b''.join(rows)
    return m


def test_round_trip_of_our_layout():
    rng = np.random.default_rng(0)
    pts, cov = rng.normal(size=(50, 3)), rng.uniform(size=(50, 6))
    p, c = msg_to_cloud(cloud_to_msg(pts, cov, Header(frame_id='map')))
    np.testing.assert_allclose(p, pts, rtol=1e-6)
    np.testing.assert_allclose(c, cov, rtol=1e-6)
    p, c = msg_to_cloud(cloud_to_msg(pts, None, Header(frame_id='map')))
    assert c is None and p.shape == (50, 3)


def test_a_foreign_organised_cloud_with_padded_rows():
    """z y x order with 4 bytes of padding per point, 2 x 2 points, 4 bytes of padding per
    row: every point read from its own row."""
    pad = b'\xff' * 4

    def point(x, y, z):
        return np.array([z, y, x], '<f4').tobytes() + pad
    rows = [point(1, 2, 3) + point(4, 5, 6) + pad, point(7, 8, 9) + point(10, 11, 12) + pad]
    m = _cloud([('z', 0), ('y', 4), ('x', 8)], 16, 2, 2, rows, row_step=36)
    p, c = msg_to_cloud(m)
    assert c is None
    np.testing.assert_array_equal(p, [[1, 2, 3], [4, 5, 6], [7, 8, 9], [10, 11, 12]])


@pytest.mark.parametrize('case', ['field past the point', 'short data', 'row_step too small',
                                  'big-endian', 'some covariance fields'])
def test_bad_layouts_are_a_format_error(case):
    xyz = np.arange(6, dtype='<f4').tobytes()
    m = _cloud([('x', 0), ('y', 4), ('z', 8)], 12, 2, 1, [xyz])
    if case == 'some covariance fields':      # five of six: not fused without its variances
        m = cloud_to_msg(np.ones((2, 3)), np.tile([1.0, 0, 0, 1, 0, 1], (2, 1)), m.header)
        m.fields = [f for f in m.fields if f.name != 'cov_zz']
    elif case == 'field past the point':
        m.fields[2].offset = 10
    elif case == 'short data':
        m.data = xyz[:20]
    elif case == 'row_step too small':
        m.row_step = 12
    else:
        m.is_bigendian = True
    with pytest.raises(CloudFormatError):
        msg_to_cloud(m)


def test_published_quaternions_round_trip_at_180_degrees():
    """The stereo node's rotation -> quaternion and ros_conv's quaternion -> rotation agree,
    the half turns included (a level optical frame looking along -y is one: the old sign-copy
    formula turned it to look along +y)."""
    from geometry_msgs.msg import Pose

    from coop_common.frames import quat_of as _quat
    from coop_mapping.ros_conv import pose_to_rt
    look_minus_y = np.array([[-1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, -1.0, 0.0]])
    rng = np.random.default_rng(0)
    half_turns = []
    for axis in ([0, 1, 1], [1, -1, 0], [1, 2, -3], [0, 0, 1]):
        a = np.asarray(axis, float) / np.linalg.norm(axis)
        half_turns.append(2 * np.outer(a, a) - np.eye(3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    for R in [look_minus_y, *half_turns, q * np.sign(np.linalg.det(q))]:
        p = Pose()
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = _quat(R)
        np.testing.assert_allclose(pose_to_rt(p)[0], R, atol=1e-12)
