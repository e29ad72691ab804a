"""The live view over DDS and WebSocket (issue #23, item 3): the installed `coop_bringup
live_view` against the installed `rover_sim sim` (images and poses of two rovers) and a probe
that publishes what the rest of the mission would (the team's map, both identifiers'
estimates, the insertion's feedback); a WebSocket client speaking `foxglove.sdk.v1` subscribes
to every channel and must receive each."""
from __future__ import annotations

import json
import socket
import threading

import numpy as np
import pytest
import rclpy
from coop_bringup.live import channel_topics
from coop_bringup.live_view import FEEDBACK_QOS
from coop_bringup.ws_client import receive
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from coop_common.dynparams import PARAM_NAMES
from coop_common.qos import LATCHED_QOS
from coop_common.testing import NodeProcess, wait_for
from coop_msgs.action import Insert
from coop_msgs.msg import DynamicParameters, VoxelMap

pytestmark = pytest.mark.graph
ROVERS = ('rover1', 'rover2')


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


class Source:
    """The map, the estimates and the insertion feedback, published from a private context."""

    def __init__(self) -> None:
        self.ctx = Context()
        rclpy.init(context=self.ctx)
        self.node = Node('live_view_source', context=self.ctx)
        self.ex = SingleThreadedExecutor(context=self.ctx)
        self.ex.add_node(self.node)
        n = self.node
        self.map = n.create_publisher(VoxelMap, 'map/voxels', LATCHED_QOS)
        self.ident = {r: n.create_publisher(DynamicParameters, f'{r}/dynamic_parameters',
                                            LATCHED_QOS) for r in ROVERS}
        self.feedback = n.create_publisher(Insert.Impl.FeedbackMessage,
                                           'insert/_action/feedback', FEEDBACK_QOS)

    def publish(self) -> None:
        m = VoxelMap(resolution_m=0.1, sequence=1)
        m.header.frame_id = 'map'
        keys = np.array([[30, 0, 2], [30, 1, 2], [31, 0, 3], [0, 0, 0]], np.int32)
        m.voxels.keys = keys.ravel().tolist()
        m.voxels.occupancy = [0.9, 0.8, 0.7, 0.1]
        self.map.publish(m)
        for p in self.ident.values():
            k = len(PARAM_NAMES)
            p.publish(DynamicParameters(names=list(PARAM_NAMES), values=[1.0] * k,
                                        std_devs=[0.1] * k, information_bits=[5.0] * k,
                                        samples=100, strategy='information'))
        fb = Insert.Impl.FeedbackMessage()
        fb.feedback.phase = Insert.Feedback.PHASE_VISUAL_SERVO
        fb.feedback.displacement_error_m = 0.012
        fb.feedback.wrench.force.z = -3.0
        self.feedback.publish(fb)

    def spin(self, s: float) -> None:
        self.ex.spin_once(timeout_sec=s)

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


def test_a_client_receives_every_channel(tmp_path):
    port = free_port()
    sim_args = ['-p', 'rovers:=2', '-p', 'image_width:=160', '-p', 'image_height:=120',
                '-p', 'stereo_rate_hz:=4.0', '-p', 'real_time_factor:=1.0']
    live_args = ['-p', f'port:={port}', '-p', 'use_sim_time:=true', '-p', 'state_rate_hz:=4.0']
    source = Source()
    procs = [NodeProcess('rover_sim', 'sim', sim_args, log_path=tmp_path / 'sim.log'),
             NodeProcess('coop_bringup', 'live_view', live_args,
                         log_path=tmp_path / 'live_view.log')]
    try:
        for p in procs:
            p.__enter__()
        live = procs[1]
        wait_for(lambda: 'live view on ws://' in live.log_text() or not live.alive(), 60,
                 what='the live view up')
        assert live.alive(), live.log_text()
        # the feedback is volatile: publish until the client has it (latched topics once)
        source.publish()
        stop = threading.Event()

        def keep_publishing() -> None:
            while not stop.wait(0.5):
                source.publish()
                source.spin(0.01)

        th = threading.Thread(target=keep_publishing, daemon=True)
        th.start()
        try:
            want = channel_topics(ROVERS)
            got = receive(f'ws://127.0.0.1:{port}', topics=want, duration_s=90.0,
                          until_each=True)
        finally:
            stop.set()
            th.join(timeout=5)
        missing = [t for t in want if not got.arrivals.get(t)]
        assert not missing, (missing, live.log_text()[-3000:])
        image = got.channels['/rover1/camera/compressed']
        assert image['schemaName'] == 'foxglove.CompressedImage'
        assert got.channels['/map']['schemaName'] == 'foxglove.PointCloud'
        # the simulator's transform tree, passed on for the 3-D panel
        assert got.channels['/tf']['schemaName'] == 'foxglove.FrameTransforms'
        assert b'rover2/right_camera_optical_frame' in got.first['/tf']
        # the JSON channels carry the numbers sent
        ident = json.loads(got.first['/rover2/identification'])
        assert ident['params']['mass'] == {'value': 1.0, 'std': 0.1, 'bits': 5.0}
        ins = json.loads(got.first['/insertion'])
        assert ins['phase'] == 'visual_servo'
        assert ins['displacement_error_mm'] == pytest.approx(12.0)
        assert ins['force_n']['norm'] == pytest.approx(3.0)
        # the map: the three occupied voxels of four (16 bytes a point, plus the header fields)
        assert got.arrivals['/map'][0][1] > 3 * 16
    finally:
        for p in reversed(procs):
            p.__exit__(None, None, None)
        source.close()
    assert all(not p.alive() for p in procs)
