"""The transform tree's core: names, prefixes, and transforms that compose to the geometry the
nodes reason with (rover_geometry.camera_in_map)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from coop_common import frames
from coop_common.rover_geometry import BASE_HEIGHT_M, STEREO_BASELINE_M, camera_in_map


def _chain(transforms: list[frames.Transform], root: str, leaf: str) -> np.ndarray:
    """`leaf`'s pose in `root` by walking the parents of `transforms` up from `leaf`."""
    by_child = {t.child: t for t in transforms}
    m = np.eye(4)
    frame = leaf
    while frame != root:
        t = by_child[frame]          # KeyError: leaf not below root
        m = t.matrix() @ m
        frame = t.parent
    return m


def _tree(fr: frames.RoverFrames, x: float, y: float, yaw: float, pan: float, tilt: float
          ) -> list[frames.Transform]:
    return [frames.Transform(fr.map, fr.odom, (0.0, 0.0, 0.0)),
            frames.odom_transform(fr, x, y, yaw),
            *frames.mast_transforms(fr, ['arm_joint_1', 'mast_pan', 'mast_tilt'],
                                    [0.3, pan, tilt]),
            *frames.static_transforms(fr)]


@pytest.mark.parametrize('pose', [(0.0, 0.0, 0.0, 0.0, 0.0), (1.2, -0.4, 2.1, -0.6, 0.45),
                                  (3.0, 2.0, -math.pi + 0.01, 0.9, -1.1)])
def test_the_tree_puts_the_left_camera_where_the_geometry_does(pose):
    fr = frames.RoverFrames('rover1')
    x, y, yaw, pan, tilt = pose
    got = _chain(_tree(fr, *pose), fr.map, fr.optical('left'))
    np.testing.assert_allclose(got, camera_in_map(x, y, yaw, pan, tilt), atol=1e-12)
    right = _chain(_tree(fr, *pose), fr.map, fr.optical('right'))
    # the right eye a baseline along the left's optical x (rover_sim renders it there)
    np.testing.assert_allclose(right[:3, 3], got[:3, 3] + STEREO_BASELINE_M * got[:3, 0],
                               atol=1e-12)
    assert frames.odom_transform(fr, x, y, yaw).translation[2] == BASE_HEIGHT_M


def test_every_frame_of_a_rover_hangs_from_the_map_with_one_parent():
    fr = frames.RoverFrames('rover2', 'team_a/')
    tree = _tree(fr, 0.5, 0.5, 0.3, 0.1, 0.2)
    children = [t.child for t in tree]
    assert len(children) == len(set(children))
    assert set(children) == set(fr.all())
    for f in fr.all():
        _chain(tree, 'team_a/map', f)
    assert fr.base_link == 'team_a/rover2/base_link'
    assert fr.truth('base_link') == 'team_a/truth/rover2/base_link'


def test_two_teams_share_no_frame_name():
    a = {f for r in ('rover1', 'rover2') for f in frames.RoverFrames(r, 'team_a/').all()}
    b = {f for r in ('rover1', 'rover2') for f in frames.RoverFrames(r, 'team_b/').all()}
    assert not a & b
    team_a = frames.RoverFrames('rover1', 'team_a/')
    team_b = frames.RoverFrames('rover1', 'team_b/')
    assert team_a.map != team_b.map


def test_a_namespace_names_the_rover():
    assert frames.RoverFrames.of_namespace('/team_a/rover1').base_link == 'rover1/base_link'
    assert frames.RoverFrames.of_namespace('/rover2', 'team_b/').odom == 'team_b/rover2/odom'
    assert frames.RoverFrames.of_namespace('/').base_link == 'base_link'


@pytest.mark.parametrize('prefix', ['/team_a/', 'team_a', 'team a/', 'a//', '1a/'])
def test_a_bad_prefix_is_refused_with_the_reason(prefix):
    assert 'frame prefix' in frames.check_prefix(prefix)
    with pytest.raises(frames.FrameError, match='frame prefix'):
        frames.RoverFrames('rover1', prefix)


@pytest.mark.parametrize('prefix', ['', 'team_a/', 'site_3/team_a/'])
def test_good_prefixes_pass(prefix):
    assert frames.check_prefix(prefix) is None
    assert frames.check_frame_params({'frame_prefix': prefix}) is None


def test_a_joint_state_without_the_mast_or_with_nan_gives_no_transform():
    fr = frames.RoverFrames('rover1')
    with pytest.raises(frames.FrameError, match='without mast_tilt'):
        frames.mast_transforms(fr, ['mast_pan'], [0.1])
    with pytest.raises(frames.FrameError, match='not finite'):
        frames.mast_transforms(fr, ['mast_pan', 'mast_tilt'], [0.1, math.nan])
    with pytest.raises(frames.FrameError, match='names and'):
        frames.mast_transforms(fr, ['mast_pan', 'mast_tilt'], [0.1])
    with pytest.raises(frames.FrameError, match='odometry'):
        frames.odom_transform(fr, math.inf, 0.0, 0.0)


def test_truth_hangs_from_the_map_apart_from_the_estimate():
    fr = frames.RoverFrames('rover1')
    base = np.eye(4)
    base[:3, 3] = (1.0, 2.0, 0.3)
    cam = camera_in_map(1.0, 2.0, 0.0, 0.0, 0.2)
    truth = frames.truth_transforms(fr, base, cam)
    assert {t.parent for t in truth} == {'map'}
    assert {t.child for t in truth} == {'truth/rover1/base_link',
                                       'truth/rover1/left_camera_optical_frame'}
    assert not {t.child for t in truth} & set(fr.all())
    np.testing.assert_allclose(truth[1].matrix(), cam, atol=1e-12)
    bad = base.copy()
    bad[0, 3] = math.nan
    with pytest.raises(frames.FrameError, match='finite'):
        frames.truth_transforms(fr, bad, cam)


def test_without_tf2_msgs_the_broadcaster_is_off_and_says_so(monkeypatch):
    """The pinned venv alone has no tf2_msgs: a node runs as before, its tree off."""
    import sys

    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    from coop_common.tf_tree import TreeBroadcaster
    monkeypatch.setitem(sys.modules, 'tf2_msgs.msg', None)     # import fails
    monkeypatch.setitem(sys.modules, 'tf2_msgs', None)
    ctx = Context()
    rclpy.init(context=ctx)
    node = Node('no_tree', context=ctx)
    try:
        tree = TreeBroadcaster(node, check_s=1.0)
        assert not tree.enabled and not tree.listened
        tree.send_static(frames.static_transforms(frames.RoverFrames('rover1')),
                         node.get_clock().now().to_msg())
        tree.send([frames.odom_transform(frames.RoverFrames('rover1'), 0.0, 0.0, 0.0)],
                  node.get_clock().now().to_msg())
        assert not node.get_publisher_names_and_types_by_node('no_tree', '/') or all(
            t not in ('/tf', '/tf_static')
            for t, _ in node.get_publisher_names_and_types_by_node('no_tree', '/'))
    finally:
        node.destroy_node()
        rclpy.shutdown(context=ctx)


def test_quaternions_have_w_non_negative_and_round_trip():
    from coop_common.rover_geometry import OPTICAL_IN_TILT
    for m in (OPTICAL_IN_TILT, np.diag([1.0, -1.0, -1.0]), np.eye(3)):
        q = frames.quat_of(m)
        assert q[3] >= 0 and abs(np.linalg.norm(q) - 1.0) < 1e-12
        np.testing.assert_allclose(frames.Transform('a', 'b', (0, 0, 0), q).matrix()[:3, :3], m,
                                   atol=1e-12)


def test_a_camera_side_is_left_or_right():
    fr = frames.RoverFrames('rover1', 'team_a/')
    assert fr.optical('right') == 'team_a/rover1/right_camera_optical_frame'
    with pytest.raises(frames.FrameError, match=r"camera side must be one of \['left', 'right'\], "
                       r"got 'centre'"):
        fr.optical('centre')
