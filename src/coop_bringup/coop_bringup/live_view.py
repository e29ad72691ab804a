"""`ros2 run coop_bringup live_view`: the mission on a Foxglove WebSocket server (connect
Foxglove to ws://localhost:8765). A thin node: subscriptions and parameters here, the
conversions and rate limits in `coop_bringup.live` (no rclpy).

Subscribes (relative names) to each rover's left camera image, its base and camera pose
(`pose_source` truth: the sim's `sim/<r>/base_pose` / `camera_pose`; estimate: `<r>/odom` and
`<r>/stereo/pose`), its identifier's `<r>/dynamic_parameters`, the team's `map/voxels` and the
`insert` action's feedback and status.
"""
from __future__ import annotations

from typing import Literal, assert_never, get_args

from action_msgs.msg import GoalStatusArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_action_status_default
from rclpy.serialization import deserialize_message
from sensor_msgs.msg import Image

from coop_common.frames import CAMERA_SIDES
from coop_common.node_util import BadInputCounter, ParamSpec, declare_parameters, run_node
from coop_common.qos import LATCHED_QOS, SENSOR_QOS, with_depth
from coop_common.tf_tree import TF_QOS, TF_STATIC_LISTENER_QOS
from coop_msgs.action import Insert
from coop_msgs.msg import DynamicParameters, VoxelMap

from .live import (
    LiveView,
    LiveViewConfig,
    PoseChannel,
    channel_topics,
    identification_state,
    image_array,
    insertion_state,
    voxel_map_cdr,
)

#: where the rovers' poses come from: the simulator's truth or the rovers' own estimates
PoseSource = Literal['truth', 'estimate']

PARAMS = {
    'rovers': ParamSpec(['rover1', 'rover2'], 'rover namespaces shown', read_only=True),
    'host': ParamSpec('127.0.0.1', 'address the WebSocket server binds to (0.0.0.0: every '
                      'interface)', read_only=True),
    'port': ParamSpec(8765, 'WebSocket port (0: any free port, logged)', lo=0, hi=65535,
                      read_only=True),
    'image_rate_hz': ParamSpec(4.0, 'most camera images sent per second and rover',
                               lo=0.1, hi=30.0, read_only=True),
    'image_scale': ParamSpec(0.5, 'images downscaled by this before JPEG encoding',
                             lo=0.1, hi=1.0, read_only=True),
    'jpeg_quality': ParamSpec(70, 'JPEG quality of the images', lo=10, hi=100, read_only=True),
    'pose_rate_hz': ParamSpec(5.0, 'most poses sent per second and pose channel',
                              lo=0.5, hi=50.0, read_only=True),
    'state_rate_hz': ParamSpec(2.5, 'map, identification and insertion state re-sent at this '
                               'rate (wall clock; the protocol has no latching)',
                               lo=0.2, hi=20.0, read_only=True),
    'pose_source': ParamSpec('truth', "poses from the sim's truth or the rovers' estimates "
                             '(odometry, stereo/pose)', choices=get_args(PoseSource),
                             read_only=True),
    'camera': ParamSpec('left', 'which camera of each stereo pair is shown',
                        choices=CAMERA_SIDES, read_only=True),
    'map_frame': ParamSpec('map', 'frame of the map and of frame-less poses', read_only=True),
    'min_occupancy': ParamSpec(0.5, 'voxels at least this likely occupied are map points',
                               lo=0.5, hi=1.0, read_only=True),
}

#: the action server's feedback topic: rclpy's default (reliable, volatile, depth 10)
FEEDBACK_QOS = QoSProfile(depth=10)
#: polled streams keep only the latest sample
POLLED_QOS = with_depth(SENSOR_QOS, 1)


def _ignore(_msg) -> None:
    """The callback of a polled subscription (never run: no executor waits on it)."""


def _t(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


class LiveViewNode(Node):
    """The live view's node: the mission's topics into `coop_bringup.live`'s Foxglove server."""

    def __init__(self) -> None:
        super().__init__('live_view')
        p = declare_parameters(self, PARAMS)
        rovers = tuple(p['rovers'])
        self.view = LiveView(LiveViewConfig(
            rovers=rovers, host=p['host'], port=p['port'], image_rate_hz=p['image_rate_hz'],
            image_scale=p['image_scale'], jpeg_quality=p['jpeg_quality'],
            pose_rate_hz=p['pose_rate_hz'], state_rate_hz=p['state_rate_hz'],
            map_frame=p['map_frame'], min_occupancy=p['min_occupancy']))
        self.bad = BadInputCounter(self)
        # Everything but the images is taken, the latest sample only, on wall-clock timers
        # from a node no executor waits on: rclpy's executor costs ~1 ms of Python per message
        # here, and the two 50 Hz truth poses alone cost 10 % of a core as callbacks
        # (bench/live_view.py). Polled: (subscription, handler of the latest message).
        self._poller = Node('live_view_poller', context=self.context)
        self._poses: dict = {}
        self._state: dict = {}
        poll = self._poller.create_subscription
        for r in rovers:
            # serialized: an image is deserialized only when it is to be sent
            self.create_subscription(Image, f'{r}/stereo/{p["camera"]}/image_raw',
                                     lambda m, r=r: self._on_image(r, m), SENSOR_QOS,
                                     raw=True)
            source: PoseSource = p['pose_source']       # one of its choices (read only)
            match source:
                case 'truth':
                    for truth, channel in (('base_pose', 'pose'), ('camera_pose', 'camera_pose')):
                        self._poses[f'{r}/{truth}'] = (
                            poll(PoseStamped, f'sim/{r}/{truth}', _ignore, POLLED_QOS),
                            lambda m, r=r, c=channel: self._on_pose(r, c, m.header, m.pose))
                case 'estimate':
                    self._poses[f'{r}/base_pose'] = (
                        poll(Odometry, f'{r}/odom', _ignore, POLLED_QOS),
                        lambda m, r=r: self._on_pose(r, 'pose', m.header, m.pose.pose))
                    self._poses[f'{r}/camera_pose'] = (
                        poll(PoseWithCovarianceStamped, f'{r}/stereo/pose', _ignore,
                             POLLED_QOS),
                        lambda m, r=r: self._on_pose(r, 'camera_pose', m.header, m.pose.pose))
                case _:
                    assert_never(source)
            self._state[f'{r}/ident'] = (
                poll(DynamicParameters, f'{r}/dynamic_parameters', _ignore, LATCHED_QOS),
                lambda m, r=r: self._on_ident(r, m))
        # serialized: only the keys and occupancies of the latest map are read, when a client
        # is there to see it (rclpy would build every array of a 5.6 MB map each time)
        self._map_raw: bytes | None = None
        self._map_sub = poll(VoxelMap, 'map/voxels', _ignore, LATCHED_QOS, raw=True)
        self._state['feedback'] = (
            poll(Insert.Impl.FeedbackMessage, 'insert/_action/feedback', _ignore,
                 FEEDBACK_QOS), self._on_feedback)
        # the transform tree, every message that waits (one per source and rover each time);
        # without tf2_msgs the 3-D panel places only what is stamped in the map
        self._tf_subs = []
        try:
            from tf2_msgs.msg import TFMessage  # noqa: PLC0415 - an optional dependency
        except ImportError:
            self.get_logger().info('tf2_msgs is not installed: no /tf channel')
        else:
            self._tf_subs = [poll(TFMessage, '/tf', _ignore, TF_QOS),
                             poll(TFMessage, '/tf_static', _ignore, TF_STATIC_LISTENER_QOS)]
        self._state['status'] = (
            poll(GoalStatusArray, 'insert/_action/status', _ignore,
                 qos_profile_action_status_default), self._on_status)
        # wall clock: a paused or slow sim must not stop a connected client's map
        steady = Clock(clock_type=ClockType.STEADY_TIME)
        self.create_timer(1.0 / p['state_rate_hz'], self._republish, clock=steady)
        self.create_timer(1.0 / p['pose_rate_hz'], self._on_pose_timer, clock=steady)
        self.get_logger().info(
            f'live view on ws://{p["host"]}:{self.view.port} (connect Foxglove to it); '
            f'channels {", ".join(channel_topics(rovers))}')

    def _on_image(self, rover: str, raw: bytes) -> None:
        if not self.view.image_due(rover):
            return
        m = deserialize_message(raw, Image)
        try:
            img = image_array(m.encoding, m.height, m.width, m.step, m.data)
        except ValueError as exc:
            self.bad.reject('image', str(exc))
            return
        self.view.log_image(rover, img, _t(m.header.stamp), m.header.frame_id)

    @staticmethod
    def _latest(sub):
        """The newest message waiting on a polled subscription (the older ones dropped), or
        None."""
        last = None
        with sub.handle:
            while (got := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                last = got[0]
        return last

    def _on_pose_timer(self) -> None:
        self._poll(self._poses)
        for sub in self._tf_subs:
            with sub.handle:
                while (got := sub.handle.take_message(sub.msg_type, sub.raw)) is not None:
                    self.view.on_transforms(
                        (t.header.frame_id, t.child_frame_id,
                         (t.transform.translation.x, t.transform.translation.y,
                          t.transform.translation.z),
                         (t.transform.rotation.x, t.transform.rotation.y,
                          t.transform.rotation.z, t.transform.rotation.w),
                         _t(t.header.stamp)) for t in got[0].transforms)
        self.view.send_transforms()

    def _poll(self, subs: dict) -> None:
        for sub, handle in subs.values():
            m = self._latest(sub)
            if m is not None:
                handle(m)

    def _on_pose(self, rover: str, channel: PoseChannel, header, pose) -> None:
        q, p = pose.orientation, pose.position
        self.view.on_pose(rover, channel, (p.x, p.y, p.z), (q.x, q.y, q.z, q.w),
                          _t(header.stamp), header.frame_id)

    def _on_ident(self, rover: str, m: DynamicParameters) -> None:
        self.view.on_identification(rover, identification_state(
            rover, list(m.names), m.values, m.std_devs, m.information_bits,
            samples=m.samples, strategy=m.strategy, stamp_s=_t(m.header.stamp)))

    def _republish(self) -> None:
        self._poll(self._state)
        new = self._latest(self._map_sub)
        if new is not None:
            self._map_raw = new                     # kept until a client is there to see it
        if self._map_raw is not None and self.view.map.has_sinks():
            raw, self._map_raw = self._map_raw, None
            try:
                stamp, frame, res, keys, occ = voxel_map_cdr(raw)
            except ValueError:                       # another encoding: the slow way
                m = deserialize_message(raw, VoxelMap)
                stamp, frame, res = _t(m.header.stamp), m.header.frame_id, m.resolution_m
                keys, occ = m.voxels.keys, m.voxels.occupancy
            try:
                self.view.on_map(keys, occ, res, stamp, frame)
            except ValueError as exc:
                self.bad.reject('map', str(exc))
        self.view.republish()

    def _on_feedback(self, m) -> None:
        f = m.feedback
        self.view.on_insertion(insertion_state(
            phase=f.phase, displacement_error_m=f.displacement_error_m,
            angle_error_rad=f.angle_error_rad,
            force_n=(f.wrench.force.x, f.wrench.force.y, f.wrench.force.z),
            stamp_s=_t(self.get_clock().now().to_msg())))

    def _on_status(self, m: GoalStatusArray) -> None:
        if m.status_list:
            self.view.on_insertion(insertion_state(goal_status=m.status_list[-1].status))

    def destroy_node(self) -> None:
        self.view.close()
        self._poller.destroy_node()
        super().destroy_node()


def main(args=None) -> int:
    """`ros2 run coop_bringup live_view`."""
    return run_node(LiveViewNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
