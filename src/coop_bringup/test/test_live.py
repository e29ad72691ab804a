"""The live view's core without DDS: rate gates, conversions, and a LiveView on a free port
that a WebSocket client reads."""
from __future__ import annotations

import json
import struct
import threading

import numpy as np
import pytest
from coop_bringup.live import (
    LiveView,
    LiveViewConfig,
    RateGate,
    encode_jpeg,
    identification_state,
    image_array,
    insertion_state,
    voxel_cloud,
)
from coop_bringup.ws_client import receive


def test_rate_gate_lets_through_at_most_its_rate():
    g = RateGate(2.0)
    opened = [t for t in np.arange(0.0, 10.0, 0.01) if g.ready(float(t))]
    assert len(opened) <= 21                     # 2 Hz, and one early opening at most
    assert np.allclose(np.diff(opened)[1:], 0.5, atol=0.011)
    # a source at the gate's rate, with jitter: every sample through
    g = RateGate(4.0)
    t = np.arange(1, 201) * 0.25 + np.random.default_rng(0).uniform(-0.02, 0.02, 200)
    assert sum(g.ready(float(x)) for x in t) == 200
    # a source that paused earns no burst
    assert g.ready(100.0) and not g.ready(100.1)
    with pytest.raises(ValueError):
        RateGate(0.0)


def test_voxel_cloud_keeps_the_occupied_voxel_centres():
    keys = np.array([1, 2, 3, -1, 0, 0, 5, 5, 5], np.int32)
    data, n = voxel_cloud(keys, [0.9, 0.2, 0.5], 0.1)
    pts = np.frombuffer(data, np.float32).reshape(-1, 4)
    assert n == 2
    assert np.allclose(pts[0], [0.15, 0.25, 0.35, 0.9])
    assert np.allclose(pts[1], [0.55, 0.55, 0.55, 0.5])
    with pytest.raises(ValueError):
        voxel_cloud(keys, [0.9], 0.1)


def test_images_are_read_by_encoding_and_shrink_as_jpeg():
    import cv2
    img = (np.arange(120 * 160) % 251).astype(np.uint8).reshape(120, 160)
    padded = np.zeros((120, 164), np.uint8)
    padded[:, :160] = img
    assert np.array_equal(image_array('mono8', 120, 160, 164, padded.tobytes()), img)
    rgb = np.dstack([img, img // 2, img // 3])
    assert np.array_equal(image_array('rgb8', 120, 160, 480, rgb.tobytes()), rgb[..., ::-1])
    with pytest.raises(ValueError, match='encoding'):
        image_array('16UC1', 120, 160, 320, bytes(120 * 320))
    with pytest.raises(ValueError, match='short'):
        image_array('mono8', 120, 160, 160, bytes(100))
    jpg = encode_jpeg(img, quality=70, scale=0.5)
    back = cv2.imdecode(np.frombuffer(jpg, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.shape == (60, 80)
    assert len(jpg) < img.size


def test_state_json():
    s = identification_state('rover1', ['mass', 'Ixx'], [60.0, float('nan')], [1.0, 2.0],
                             [9.0, 0.0], samples=10, strategy='information', stamp_s=1.5)
    assert s['params']['mass'] == {'value': 60.0, 'std': 1.0, 'bits': 9.0}
    assert s['params']['Ixx']['value'] is None           # NaN is not JSON
    json.dumps(s, allow_nan=False)
    i = insertion_state(phase=2, displacement_error_m=0.004, force_n=(3.0, 4.0, 0.0),
                        goal_status=4)
    assert i['phase'] == 'force_insert' and i['goal_status'] == 'succeeded'
    assert i['force_n']['norm'] == pytest.approx(5.0)
    with pytest.raises(ValueError):
        LiveViewConfig(image_rate_hz=0.0)


def test_a_client_gets_the_state_channels_resent():
    view = LiveView(LiveViewConfig(rovers=('rover1',), port=0))
    try:
        view.on_map(np.array([10, 0, 2], np.int32), np.array([0.9], np.float32), 0.1, 3.0)
        view.on_identification('rover1', identification_state(
            'rover1', ['mass'], [60.0], [1.0], [9.0], samples=1, strategy='constant',
            stamp_s=3.0))
        view.on_insertion(insertion_state(phase=0))
        assert not view.send_transforms()           # nothing known, nobody watching
        view.on_transforms([('map', 'rover1/odom', (0, 0, 0), (0, 0, 0, 1), 3.0),
                            ('rover1/odom', 'rover1/base_link', (1, 2, 0.3), (0, 0, 0, 1), 3.0),
                            ('rover1/odom', 'rover1/base_link', (1, 3, 0.3), (0, 0, 0, 1), 3.1)])
        assert sorted(view._tf) == ['rover1/base_link', 'rover1/odom']   # the latest of each
        stop = threading.Event()

        def ticker() -> None:
            while not stop.wait(0.1):
                view.republish()
                view.on_pose('rover1', 'pose', (1, 2, 0), (0, 0, 0, 1), 3.0)
                view.send_transforms()

        th = threading.Thread(target=ticker, daemon=True)
        th.start()
        try:
            got = receive(f'ws://127.0.0.1:{view.port}', duration_s=20.0, until_each=True,
                          topics=['/map', '/rover1/identification', '/insertion',
                                  '/rover1/pose', '/tf'])
        finally:
            stop.set()
            th.join()
        assert all(got.arrivals[t] for t in got.channels), got.arrivals
        # the map's packed cloud: its one point at the voxel centre, 16 bytes, at the end
        x, y, z, occ = struct.unpack('<4f', got.first['/map'][-16:])
        assert (x, y, z) == pytest.approx((1.05, 0.05, 0.25)) and occ == pytest.approx(0.9)
        assert json.loads(got.first['/insertion'])['phase'] == 'place_camera'
        assert got.channels['/tf']['schemaName'] == 'foxglove.FrameTransforms'
        # nobody subscribed to the images: none encoded
        assert view.sent['/rover1/camera/compressed'] == 0
    finally:
        view.close()


@pytest.mark.parametrize('frame_id', ['', 'map', 'map_frame'])
def test_the_map_is_read_straight_from_its_cdr(frame_id):
    from coop_bringup.live import voxel_map_cdr
    from rclpy.serialization import serialize_message

    from coop_msgs.msg import VoxelMap
    rng = np.random.default_rng(1)
    keys = rng.integers(-300, 300, (50, 3)).astype(np.int32)
    m = VoxelMap(resolution_m=0.05, sequence=9)
    m.header.frame_id, m.header.stamp.sec, m.header.stamp.nanosec = frame_id, 7, 250_000_000
    m.voxels.keys, m.voxels.occupancy = keys.ravel(), rng.random(50).astype(np.float32)
    m.voxels.hits = np.ones(50, np.uint32)
    stamp, frame, res, k, occ = voxel_map_cdr(serialize_message(m))
    assert (stamp, frame, res) == (7.25, frame_id, 0.05)
    assert np.array_equal(k, keys.ravel()) and np.array_equal(occ, m.voxels.occupancy)
    with pytest.raises(ValueError):
        voxel_map_cdr(serialize_message(m)[:60])
