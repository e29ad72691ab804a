"""`ros2 run coop_bringup live_view`: the mission on a Foxglove WebSocket server (connect
Foxglove to ws://localhost:8765). A thin node: subscriptions and parameters here, the
conversions and rate limits in `coop_bringup.live` (no rclpy).

Subscribes (relative names) to each rover's left camera image, its base and camera pose
(`pose_source` truth: the sim's `sim/<r>/base_pose` / `camera_pose`; estimate: `<r>/odom` and
`<r>/stereo/pose`), its identifier's `<r>/dynamic_parameters`, the team's `map/voxels` and the
`insert` action's feedback and status.
"""
from __future__ import annotations

from action_msgs.msg import GoalStatusArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.qos import QoSProfile, qos_profile_action_status_default
from sensor_msgs.msg import Image

from coop_common.node_util import BadInputCounter, ParamSpec, declare_parameters, run_node
from coop_common.qos import LATCHED_QOS, SENSOR_QOS
from coop_msgs.action import Insert
from coop_msgs.msg import DynamicParameters, VoxelMap

from .live import (
    LiveView,
    LiveViewConfig,
    channel_topics,
    identification_state,
    image_array,
    insertion_state,
)

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
    'pose_rate_hz': ParamSpec(10.0, 'most poses sent per second and pose channel',
                              lo=0.5, hi=50.0, read_only=True),
    'state_rate_hz': ParamSpec(2.0, 'map, identification and insertion state re-sent at this '
                               'rate (wall clock; the protocol has no latching)',
                               lo=0.2, hi=20.0, read_only=True),
    'pose_source': ParamSpec('truth', "poses from the sim's truth or the rovers' estimates "
                             '(odometry, stereo/pose)', choices=('truth', 'estimate'),
                             read_only=True),
    'camera': ParamSpec('left', 'which camera of each stereo pair is shown',
                        choices=('left', 'right'), read_only=True),
    'map_frame': ParamSpec('map', 'frame of the map and of frame-less poses', read_only=True),
    'min_occupancy': ParamSpec(0.5, 'voxels at least this likely occupied are map points',
                               lo=0.5, hi=1.0, read_only=True),
}

#: the action server's feedback topic: rclpy's default (reliable, volatile, depth 10)
FEEDBACK_QOS = QoSProfile(depth=10)


def _t(stamp) -> float:
    return stamp.sec + 1e-9 * stamp.nanosec


class LiveViewNode(Node):
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
        for r in rovers:
            self.create_subscription(Image, f'{r}/stereo/{p["camera"]}/image_raw',
                                     lambda m, r=r: self._on_image(r, m), SENSOR_QOS)
            if p['pose_source'] == 'truth':
                for kind in ('base_pose', 'camera_pose'):
                    self.create_subscription(
                        PoseStamped, f'sim/{r}/{kind}',
                        lambda m, r=r, k=kind: self._on_pose(r, k, m.header, m.pose),
                        SENSOR_QOS)
            else:
                self.create_subscription(
                    Odometry, f'{r}/odom',
                    lambda m, r=r: self._on_pose(r, 'base_pose', m.header, m.pose.pose),
                    SENSOR_QOS)
                self.create_subscription(
                    PoseWithCovarianceStamped, f'{r}/stereo/pose',
                    lambda m, r=r: self._on_pose(r, 'camera_pose', m.header, m.pose.pose),
                    SENSOR_QOS)
            self.create_subscription(DynamicParameters, f'{r}/dynamic_parameters',
                                     lambda m, r=r: self._on_ident(r, m), LATCHED_QOS)
        self.create_subscription(VoxelMap, 'map/voxels', self._on_map, LATCHED_QOS)
        self.create_subscription(Insert.Impl.FeedbackMessage, 'insert/_action/feedback',
                                 self._on_feedback, FEEDBACK_QOS)
        self.create_subscription(GoalStatusArray, 'insert/_action/status', self._on_status,
                                 qos_profile_action_status_default)
        # wall clock: a paused or slow sim must not stop a connected client's map
        self.create_timer(1.0 / p['state_rate_hz'], self.view.republish,
                          clock=Clock(clock_type=ClockType.STEADY_TIME))
        self.get_logger().info(
            f'live view on ws://{p["host"]}:{self.view.port} (connect Foxglove to it); '
            f'channels {", ".join(channel_topics(rovers))}')

    def _on_image(self, rover: str, m: Image) -> None:
        if not self.view.images[rover].has_sinks():
            return
        try:
            img = image_array(m.encoding, m.height, m.width, m.step, m.data)
        except ValueError as exc:
            self.bad.reject('image', str(exc))
            return
        self.view.on_image(rover, img, _t(m.header.stamp), m.header.frame_id)

    def _on_pose(self, rover: str, kind: str, header, pose) -> None:
        q, p = pose.orientation, pose.position
        self.view.on_pose(rover, 'pose' if kind == 'base_pose' else 'camera_pose',
                          (p.x, p.y, p.z), (q.x, q.y, q.z, q.w), _t(header.stamp),
                          header.frame_id)

    def _on_ident(self, rover: str, m: DynamicParameters) -> None:
        self.view.on_identification(rover, identification_state(
            rover, list(m.names), m.values, m.std_devs, m.information_bits,
            samples=m.samples, strategy=m.strategy, stamp_s=_t(m.header.stamp)))

    def _on_map(self, m: VoxelMap) -> None:
        try:
            self.view.on_map(m.voxels.keys, m.voxels.occupancy, m.resolution_m,
                             _t(m.header.stamp), m.header.frame_id)
        except ValueError as exc:
            self.bad.reject('map', str(exc))
            return
        self.get_logger().debug(f'map {m.sequence}: {self.view.map_points} occupied voxels')

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
        super().destroy_node()


def main(args=None) -> int:
    return run_node(LiveViewNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
