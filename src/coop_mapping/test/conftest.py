"""Fixtures of the coop_mapping node tests: a private rclpy context, and a stereo node under
/rover1 with a peer node that feeds it camera_info, poses and image pairs on one executor."""
from __future__ import annotations

from typing import ClassVar

import numpy as np
import pytest
import rclpy
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header

from coop_common.qos import SENSOR_QOS
from coop_common.testing import wait_for


@pytest.fixture
def ctx():
    c = Context()
    rclpy.init(context=c)
    yield c
    rclpy.try_shutdown(context=c)


def _image(a: np.ndarray, stamp, frame: str) -> Image:
    m = Image()
    m.header = Header(stamp=stamp, frame_id=frame)
    m.height, m.width = a.shape
    m.encoding, m.step = 'mono8', a.shape[1]
    m.data = a.tobytes()
    return m


class StereoRig:
    """The installed-node's class run in-process: publishes to its inputs, collects outputs."""

    INPUTS: ClassVar = [('l', Image, 'stereo/left/image_raw'),
                        ('r', Image, 'stereo/right/image_raw'),
                        ('li', CameraInfo, 'stereo/left/camera_info'),
                        ('ri', CameraInfo, 'stereo/right/camera_info'),
                        ('pose', PoseWithCovarianceStamped, 'stereo/pose')]

    def __init__(self, ctx: Context, cam, params: dict) -> None:
        from coop_mapping.stereo_node import StereoNode
        self.cam = cam
        self.node = StereoNode(context=ctx, namespace='rover1', parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        self.peer = Node('peer', context=ctx)
        self.ex = SingleThreadedExecutor(context=ctx)
        self.ex.add_node(self.node)
        self.ex.add_node(self.peer)
        self.pubs = {k: self.peer.create_publisher(t, f'/rover1/{n}', SENSOR_QOS)
                     for k, t, n in self.INPUTS}
        self._outputs: list[str] = []

    def spin(self, timeout_s: float) -> None:
        self.ex.spin_once(timeout_sec=timeout_s)

    def listen(self, msg_type, topic: str, qos) -> list:
        """Messages the node publishes on /rover1/<topic>, as they come."""
        got: list = []
        self.peer.create_subscription(msg_type, f'/rover1/{topic}', got.append, qos)
        self._outputs.append(f'/rover1/{topic}')
        return got

    def start(self) -> None:
        """Wait for discovery both ways, then give the node both camera_infos."""
        wait_for(lambda: all(p.get_subscription_count() > 0 for p in self.pubs.values())
                 and all(self.peer.count_publishers(t) > 0 for t in self._outputs), 10.0,
                 spin=self.spin, what='discovery')
        cam = self.cam
        for side, frame in (('li', 'left'), ('ri', 'right')):
            info = CameraInfo()
            info.width, info.height = cam.width, cam.height
            tx = 0.0 if side == 'li' else -cam.fx * cam.baseline
            info.p = [cam.fx, 0.0, cam.cx, tx, 0.0, cam.fy, cam.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
            info.header.frame_id = f'rover1/{frame}_camera_optical_frame'
            self.pubs[side].publish(info)
        wait_for(lambda: len(self.node.info) == 2, 10.0, spin=self.spin, what='camera_info')

    def send(self, left: np.ndarray, right: np.ndarray, stamp, R: np.ndarray, t,
             frame: str = 'map') -> None:
        """One stereo pair and the camera pose (rotation R, position t in `frame`) it was
        taken from, all with `stamp`."""
        from coop_common.frames import quat_of as _quat
        pose = PoseWithCovarianceStamped()
        pose.header = Header(stamp=stamp, frame_id=frame)
        p = pose.pose.pose
        p.position.x, p.position.y, p.position.z = (float(v) for v in t)
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = _quat(R)
        self.pubs['pose'].publish(pose)
        self.pubs['l'].publish(_image(left, stamp, 'rover1/left_camera_optical_frame'))
        self.pubs['r'].publish(_image(right, stamp, 'rover1/right_camera_optical_frame'))

    def close(self) -> None:
        self.ex.shutdown()
        self.node.destroy_node()
        self.peer.destroy_node()


@pytest.fixture
def stereo_rig(ctx):
    """make(cam, **node_parameters) -> StereoRig; every rig is closed after the test."""
    rigs: list[StereoRig] = []

    def make(cam, **params) -> StereoRig:
        rigs.append(StereoRig(ctx, cam, params))
        return rigs[-1]
    yield make
    for rig in rigs:
        rig.close()
