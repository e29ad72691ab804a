"""coop_mapping.offline: frames assembled as the stereo node does, the map built with the
nodes' defaults, from plain message objects (no DDS)."""
from __future__ import annotations

from types import SimpleNamespace as Msg

import numpy as np
import pytest

from coop_mapping.offline import (
    MapSettings,
    StereoSettings,
    build_map,
    image_array,
    stereo_frames,
    stereo_topics,
)
from coop_mapping.stereo import StereoCamera


def _stamp(ns: int):
    return Msg(sec=ns // 10**9, nanosec=ns % 10**9)


def _image(img: np.ndarray, ns: int, as_bytes: bool = False):
    h, w = img.shape
    return Msg(header=Msg(stamp=_stamp(ns), frame_id='cam'), height=h, width=w, encoding='mono8',
              step=w, data=img.tobytes() if as_bytes else img.reshape(-1).copy())


def _info(cam: StereoCamera, right: bool, ns: int):
    p = [cam.fx, 0.0, cam.cx, -cam.fx * cam.baseline if right else 0.0,
         0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return Msg(header=Msg(stamp=_stamp(ns)), p=np.array(p), width=cam.width, height=cam.height)


def _pose(ns: int, frame: str = 'map'):
    return Msg(header=Msg(stamp=_stamp(ns), frame_id=frame),
              pose=Msg(pose=Msg(position=Msg(x=0.0, y=0.0, z=1.0),
                              orientation=Msg(x=0.0, y=0.0, z=0.0, w=1.0))))


def _pair(cam: StereoCamera, shift_px: int = 8, seed: int = 0):
    """A textured fronto-parallel plane: the right image is the left shifted by the disparity."""
    rng = np.random.default_rng(seed)
    tex = rng.integers(0, 255, (cam.height, cam.width + shift_px), dtype=np.uint8)
    tex = np.repeat(np.repeat(tex[::2, ::2], 2, 0), 2, 1)[:cam.height, :cam.width + shift_px]
    return tex[:, :cam.width].copy(), tex[:, shift_px:].copy()


def test_image_array_takes_bytes_and_arrays():
    img = np.arange(12, dtype=np.uint8).reshape(3, 4)
    assert np.array_equal(image_array(_image(img, 0)), img)
    assert np.array_equal(image_array(_image(img, 0, as_bytes=True)), img)


def test_frames_pair_by_stamp_and_wait_for_camera_info():
    cam = StereoCamera.from_fov(64, 48, np.radians(41.2), 0.038)
    left, right = _pair(cam)
    msgs = []
    for k, ns in enumerate((250_000_000, 500_000_000)):
        msgs += [('/rover1/stereo/left/image_raw', _image(left, ns)),
                 ('/rover1/stereo/pose', _pose(ns)),
                 ('/rover1/stereo/right/image_raw', _image(right, ns))]
        if k == 0:        # the first frame completes before any camera_info
            msgs += [('/rover1/stereo/left/camera_info', _info(cam, False, ns)),
                     ('/rover1/stereo/right/camera_info', _info(cam, True, ns))]
    msgs.insert(0, ('/rover2/stereo/pose', _pose(0)))         # other rover, incomplete
    msgs.append(('/rover1/stereo/left/image_raw', _image(left, 750_000_000)))   # incomplete
    frames = list(stereo_frames(msgs))
    assert [(f.rover, f.stamp_ns) for f in frames] == [('rover1', 250_000_000),
                                                       ('rover1', 500_000_000)]
    assert list(stereo_frames(msgs, ['rover2'])) == []
    assert len(stereo_topics(['rover1', 'rover2'])) == 10


def test_build_map_fuses_each_frame_with_the_node_defaults():
    cam = StereoCamera.from_fov(160, 120, np.radians(41.2), 0.038)
    left, right = _pair(cam, shift_px=12)
    msgs = [('/rover1/stereo/left/camera_info', _info(cam, False, 0)),
            ('/rover1/stereo/right/camera_info', _info(cam, True, 0))]
    for ns in (250_000_000, 500_000_000):
        msgs += [('/rover1/stereo/left/image_raw', _image(left, ns)),
                 ('/rover1/stereo/right/image_raw', _image(right, ns)),
                 ('/rover1/stereo/pose', _pose(ns))]
    msgs += [('/rover1/stereo/left/image_raw', _image(left, 10**9)),
             ('/rover1/stereo/right/image_raw', _image(right, 10**9)),
             ('/rover1/stereo/pose', _pose(10**9, frame='odom'))]     # rejected as the node
    out = build_map(msgs)
    assert out.scans == {'rover1': 2} and out.rejected == {'pose_frame': 1}
    assert out.map.sequence == 2 and out.map.resolution == MapSettings().resolution_m
    # the plane at z = 1 + fx * b / d in front of the camera (identity pose: optical z = map z)
    z_plane = 1.0 + cam.fx * cam.baseline / 12
    occ = out.map.occupied_centres()
    assert len(occ) > 0
    assert np.median(occ[:, 2]) == pytest.approx(z_plane, abs=2 * out.map.resolution)
    assert StereoSettings().max_range_m >= z_plane


def test_build_map_drops_a_teammate_body_as_the_mapper_does():
    """rover2's camera 0.5 m under the plane rover1 sees (both looking up the map z axis):
    rover1's clouds lie inside rover2's body volume (within 0.6 m of its camera horizontally,
    below 0.3 m over it) and are dropped from rover2's pose at 250 ms on, which is then at most
    2 s old; rover2's own cloud is above its volume. With the filter off, all are fused."""
    cam = StereoCamera.from_fov(160, 120, np.radians(41.2), 0.038)
    left, right = _pair(cam, shift_px=12)
    msgs = []
    for r in ('rover1', 'rover2'):
        msgs += [(f'/{r}/stereo/left/camera_info', _info(cam, False, 0)),
                 (f'/{r}/stereo/right/camera_info', _info(cam, True, 0))]
    pose2 = _pose(250_000_000)
    pose2.pose.pose.position.z = 1.5
    msgs += [('/rover2/stereo/left/image_raw', _image(left, 250_000_000)),
             ('/rover2/stereo/right/image_raw', _image(right, 250_000_000)),
             ('/rover2/stereo/pose', pose2)]
    for ns in (250_000_000, 500_000_000):
        msgs += [('/rover1/stereo/left/image_raw', _image(left, ns)),
                 ('/rover1/stereo/right/image_raw', _image(right, ns)),
                 ('/rover1/stereo/pose', _pose(ns))]
    out = build_map(msgs)
    assert out.scans == {'rover2': 1} and out.rejected == {'body_only': 2}
    off = build_map(msgs, mapping=MapSettings(body_radius_m=0.0))
    assert off.scans == {'rover1': 2, 'rover2': 1} and not off.rejected and off.body_points == 0
    # a pose older than the tolerance no longer counts: rover1's 500 ms cloud is fused
    old = build_map(msgs, mapping=MapSettings(body_pose_tolerance_s=0.1))
    assert old.scans == {'rover1': 1, 'rover2': 1} and old.rejected == {'body_only': 1}


def test_map_settings_are_the_mapper_parameters():
    from dataclasses import fields

    from coop_mapping.mapper_node import PARAMS
    for f in fields(MapSettings):
        assert PARAMS[f.name].default == f.default, f.name
