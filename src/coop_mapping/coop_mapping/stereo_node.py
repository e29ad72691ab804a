"""Node `stereo` (one per rover, run under its namespace): rectified pair -> 3-D points with the
Eq. 3-7 covariances in the map frame.

Subscribes `stereo/left/image_raw`, `stereo/right/image_raw` (mono8), `stereo/left/camera_info`,
`stereo/right/camera_info`, `stereo/pose` (PoseWithCovarianceStamped of the left optical frame
in `map`, stamped with the image stamp). Publishes `stereo/points` (PointCloud2 in `map` with the
covariance fields, see ros_conv) and `camera_pose` (the pose the cloud was computed with, same
stamp; the mapper takes its position as the ray origin).

With `fiducial_correction` set to a g01 method (`pnp`, `rigid`, `linear`, `linear_so3`), the
pose is corrected by scene fiducials (§3.2.5, fiducial_odometry): the first frame's
`stereo/pose` is taken as known (§3.2.2), later frames are predicted with the dead-reckoned
increment between successive `stereo/pose` messages and corrected by the fiducials;
`camera_pose` then carries the corrected pose with the Eq. 3-19 translation covariance. `none`
passes `stereo/pose` through.

With `initialise` (§3.2.2, off by default), `stereo/pose` is the rover's own dead-reckoned
frame (whatever its frame_id), not yet the common one: each pair is searched for the known
target's markers (`target_markers` in the target frame, which sits at `target_pose` in
`map_frame`) and the camera located from them (target_frame.Initialiser); every fix is
published on `~/target_pose` (camera in `map_frame`, 6x6 covariance). Until a fix's largest
predicted position sigma is below `init_max_position_sigma_m` nothing else is published; then
the own -> common transform is fixed (`~/alignment`: the own frame's origin in `map_frame`,
latched), logged, and every later pose and cloud is expressed in `map_frame` with the
alignment's uncertainty added to `camera_pose`.
"""
from __future__ import annotations

import time
from collections import OrderedDict
from dataclasses import fields

import cv2
import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_msgs.msg import Header

from coop_common.frames import FRAME_PARAMS, RoverFrames, Transform, check_frame_params, quat_of
from coop_common.node_util import BadInputCounter, ParamSpec, declare_parameters, run_node
from coop_common.qos import (
    CONTRIBUTION_QOS,
    LATCHED_QOS,
    SENSOR_QOS,
    overridable,
    with_depth,
)
from coop_common.tf_tree import TreeBroadcaster
from coop_msgs.msg import MapContribution

from .bodies import BodyFilter
from .contribution import make_contribution
from .fiducial_odometry import FiducialOdometry, OdometryConfig, PoseMethod
from .offline import MapSettings, StereoSettings, stamp_ns
from .ros_conv import cloud_to_msg, contribution_to_msg, pose_to_rt
from .stereo import FULL_WIDTH_DEFAULT, SUBPIXEL_DEFAULT, SUBPIXEL_MODES, StereoError, StereoRanger
from .target_frame import Initialiser, TargetFrameError, TargetGeometry
from .voxelmap import ScanLimits, ScanRejected, VoxelMap

# rover_sim's insertion site (worldgen, slot 4 mm): its frame has the origin at the block's
# centre, x out of the marker face, z up; the block sits at (3, 0, 0.2) with yaw pi in `map`
SIM_SITE_MARKERS = [0.1, 0.062, 0.05, 0.1, -0.062, 0.05]
SIM_SITE_POSE = [3.0, 0.0, 0.2, float(np.pi)]

#: fiducial_correction's value for no correction (the others: a PoseMethod)
NO_CORRECTION = 'none'

PARAMS = {
    'num_disparities': ParamSpec(64, 'StereoSGBM disparity range (multiple of 16)', lo=16,
                                 hi=256),
    'block_size': ParamSpec(5, 'StereoSGBM block size (odd)', lo=1, hi=21),
    'stride': ParamSpec(1, 'use every stride-th pixel in u and v', lo=1, hi=16),
    'subpixel': ParamSpec(SUBPIXEL_DEFAULT, "sub-pixel disparity: SGBM's own, 'equalise', or "
                          "'shift2' / 'shift4' (mean over 2 / 4 sub-pixel shifts of the right "
                          'image), see stereo.compute_disparity', choices=list(SUBPIXEL_MODES)),
    'full_width': ParamSpec(FULL_WIDTH_DEFAULT, 'also range the left num_disparities columns '
                            '(images padded, left-right checked: stereo.compute_disparity)'),
    'min_range_m': ParamSpec(0.2, 'nearest point kept (m)', lo=0.0, hi=100.0),
    'max_range_m': ParamSpec(10.0, 'farthest point kept (m)', lo=0.1, hi=1000.0),
    'sigma_disparity_px': ParamSpec(0.5, 'disparity sigma of Eq. 3-6 (px), gives S', lo=0.01,
                                    hi=10.0),
    'error_T_lateral': ParamSpec(0.1, 'Eq. 3-7 T_x = T_y relative to T_z = 1', lo=1e-3, hi=10.0),
    'error_n': ParamSpec(2.0, 'Eq. 3-7 exponent n', lo=0.0, hi=4.0),
    'map_frame': ParamSpec('map', 'frame of stereo/pose and of the published cloud, after '
                           'frame_prefix',
                           read_only=True),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'publish_tf': ParamSpec(True, "Publish map -> <rover>/odom on /tf from this node's estimate "
                            '(needs tf2_msgs)', read_only=True),
    'tf_rate_hz': ParamSpec(10.0, 'Rate of map -> <rover>/odom on /tf with fiducial_correction '
                            '(Hz, node clock; else it is fixed, on /tf_static)', lo=0.1,
                            hi=100.0, read_only=True),
    'fiducial_correction': ParamSpec(NO_CORRECTION, 'camera pose correction by scene '
                                     'fiducials: g01 method or none',
                                     choices=[NO_CORRECTION, *(m.value for m in PoseMethod)],
                                     read_only=True),
    'n_fiducials': ParamSpec(40, 'fiducials kept in view', lo=4, hi=500, read_only=True),
    'scene_distance_m': ParamSpec(1.1, 'typical scene distance (sets the fiducial map voxel)',
                                  lo=0.05, hi=100.0, read_only=True),
    'initialise': ParamSpec(False, '§3.2.2: stereo/pose is the own dead-reckoned frame; find '
                            'the target to put it into map_frame first', read_only=True),
    'init_max_position_sigma_m': ParamSpec(0.1, 'accept the first target fix whose largest '
                                           'predicted position sigma is below this (m)',
                                           lo=1e-4, hi=10.0, read_only=True),
    'init_up_sigma_rad': ParamSpec(0.01, 'sigma of the up direction taken from the '
                                   'dead-reckoned camera orientation (0: not used)', lo=0.0,
                                   hi=1.0, read_only=True),
    'target_markers': ParamSpec(SIM_SITE_MARKERS, 'marker centres x1 y1 z1 x2 ... in the '
                                'target frame (m)', read_only=True),
    'target_facing': ParamSpec([1.0, 0.0, 0.0], 'outward normal of the marker face, target '
                               'frame (0 0 0: none)', read_only=True),
    'target_up': ParamSpec([0.0, 0.0, 1.0], 'up direction in the target frame',
                           read_only=True),
    'target_pose': ParamSpec(SIM_SITE_POSE, 'x y z yaw of the target frame in map_frame',
                             read_only=True),
    'marker_min_radius_px': ParamSpec(1.0, 'smallest marker disc radius detected (px)',
                                      lo=0.5, hi=100.0, read_only=True),
    'marker_max_radius_px': ParamSpec(25.0, 'largest marker disc radius detected (px)',
                                      lo=1.0, hi=200.0, read_only=True),
    'contribute': ParamSpec(False, 'also send every scan as a map contribution '
                            '(`map_contribution`, coop_msgs/MapContribution) for a mapper with '
                            'map_input contributions: what crosses a field radio instead of '
                            'the cloud', read_only=True),
    'map_resolution_m': ParamSpec(0.1, "the mapper's resolution_m (contributions)", lo=0.005,
                                  hi=10.0, read_only=True),
    'ray_subdivision': ParamSpec(4, "the mapper's ray_subdivision (contributions)", lo=0,
                                 hi=16, read_only=True),
    'max_points': ParamSpec(1_000_000, "the mapper's max_points (contributions)", lo=1,
                            hi=50_000_000),
    'body_radius_m': ParamSpec(BodyFilter.radius_m, "the mapper's body_radius_m: this rover's "
                               'body volume, dropped from its contributions (0 = off)',
                               lo=0.0, hi=10.0),
    'body_above_camera_m': ParamSpec(BodyFilter.above_camera_m, "the mapper's "
                                     'body_above_camera_m (contributions)', lo=0.0, hi=10.0),
    'contribution_history': ParamSpec(CONTRIBUTION_QOS.depth, 'contributions kept for a '
                                      'mapper that is cut off or restarts (reliable, transient '
                                      'local)', lo=1, hi=100_000, read_only=True),
    'ranging': ParamSpec(True, 'false: pairs are dropped unranged (no cloud, no camera_pose; '
                         'the map keeps what it has), as once a site is mapped'),
}


def image_to_array(msg: Image) -> np.ndarray:
    """A mono8 Image as an (height, width) uint8 array; StereoError for another encoding."""
    if msg.encoding not in ('mono8', '8UC1'):
        raise StereoError(f'encoding {msg.encoding!r}, need mono8')
    if msg.step < msg.width or len(msg.data) < msg.step * msg.height:
        raise StereoError('image data shorter than step * height')
    a = np.frombuffer(bytes(msg.data), np.uint8, count=msg.step * msg.height)
    return a.reshape(msg.height, msg.step)[:, :msg.width].copy()


def _check_params(p: dict) -> str | None:
    """The rules between parameters: each range's lower end below its upper one; StereoSGBM's
    disparity range a multiple of 16."""
    if p['num_disparities'] % 16:
        return f"num_disparities must be a multiple of 16, got {p['num_disparities']}"
    if why := check_frame_params(p):
        return why
    for lo, hi in (('min_range_m', 'max_range_m'),
                   ('marker_min_radius_px', 'marker_max_radius_px')):
        if not p[lo] < p[hi]:
            return f'{lo} ({p[lo]}) must be below {hi} ({p[hi]})'
    return None


class StereoNode(Node):
    """The stereo node: a rover's image pairs into range clouds with covariances (Eq. 3-7) and the
    camera's pose."""

    def __init__(self, **kwargs) -> None:
        super().__init__('stereo', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._changed,
                                    check_all=_check_params)
        # fiducial_correction (validated against its choices, read only) as the core's mode
        self.fiducial_method: PoseMethod | None = (
            None if self.p['fiducial_correction'] == NO_CORRECTION
            else PoseMethod(self.p['fiducial_correction']))
        self.bad = BadInputCounter(self)
        self.info: dict[str, CameraInfo] = {}
        self.ranger: StereoRanger | None = None
        self.buf: dict[str, OrderedDict[int, object]] = {
            'left': OrderedDict(), 'right': OrderedDict(), 'pose': OrderedDict()}
        # QoS overrides (qos_overrides.<topic>.publisher.<policy>) may change both, as on
        # the sensor inputs below
        self.pub_cloud = self.create_publisher(PointCloud2, 'stereo/points',
                                               **overridable(SENSOR_QOS))
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, 'camera_pose',
                                              **overridable(LATCHED_QOS))
        # the rover's place in the map (REP 105's map -> odom), from what this node estimates:
        # stereo/pose's frame is the rover's odometry frame, and the map is where `initialise`
        # found the target or the fiducials put the camera; without either the two are one
        self.rover_frames = RoverFrames.of_namespace(self.get_namespace(),
                                                     self.p['frame_prefix'], self.p['map_frame'])
        self.map_frame = self.rover_frames.map
        # a fixed estimate (the identity; the alignment once found) is static, on /tf_static
        # (a tf2 listener keeps it after this node has stopped, as the insertion rig stops it
        # after the survey); the fiducial correction's moves, on /tf
        self.map_from_odom: np.ndarray | None = (
            None if self.p['initialise'] else np.eye(4))
        self.tree = TreeBroadcaster(self, enabled=self.p['publish_tf'])
        if self.tree.enabled and self.fiducial_method is not None:
            self.create_timer(1.0 / self.p['tf_rate_hz'], self._send_tree)
        elif self.map_from_odom is not None:
            self._send_static_tree()
        # sensor streams, whose QoS a replay that must not drop a frame overrides
        # (coop_common.qos.durable_overrides)
        self.create_subscription(Image, 'stereo/left/image_raw',
                                 lambda m: self._put('left', m), **overridable(SENSOR_QOS))
        self.create_subscription(Image, 'stereo/right/image_raw',
                                 lambda m: self._put('right', m), **overridable(SENSOR_QOS))
        self.create_subscription(CameraInfo, 'stereo/left/camera_info',
                                 lambda m: self._info('left', m), **overridable(SENSOR_QOS))
        self.create_subscription(CameraInfo, 'stereo/right/camera_info',
                                 lambda m: self._info('right', m), **overridable(SENSOR_QOS))
        self.create_subscription(PoseWithCovarianceStamped, 'stereo/pose',
                                 lambda m: self._put('pose', m), **overridable(SENSOR_QOS))
        self.frames = 0
        self.contributions = 0
        if self.p['contribute']:
            # a session per start (ns since the epoch): the mapper tells a restart by it
            self.session = time.time_ns()
            self.source = self.get_namespace().rstrip('/').rsplit('/', 1)[-1] or 'rover'
            self.contribution_map = VoxelMap(self.p['map_resolution_m'],
                                             ray_subdivision=self.p['ray_subdivision'])
            self.pub_contribution = self.create_publisher(
                MapContribution, 'map_contribution',
                with_depth(CONTRIBUTION_QOS, self.p['contribution_history']))
        self._waiting: list[dict] = []     # complete frames that came before any camera_info
        self.odometry: FiducialOdometry | None = None
        self._prev_dr: np.ndarray | None = None
        self.initialiser: Initialiser | None = None
        if self.p['initialise']:
            self.initialiser = self._make_initialiser()
            self.pub_target = self.create_publisher(PoseWithCovarianceStamped, '~/target_pose',
                                                    LATCHED_QOS)
            self.pub_alignment = self.create_publisher(PoseWithCovarianceStamped,
                                                       '~/alignment', LATCHED_QOS)

    def _make_initialiser(self) -> Initialiser:
        m = np.asarray(self.p['target_markers'], float)
        facing = np.asarray(self.p['target_facing'], float)
        x, y, z, yaw = (float(v) for v in self.p['target_pose'])
        c, s = np.cos(yaw), np.sin(yaw)
        if m.size < 6 or m.size % 3 or len(self.p['target_pose']) != 4:
            raise ValueError('target_markers needs x y z per marker (>= 2 markers), '
                             'target_pose x y z yaw')
        geom = TargetGeometry(m.reshape(-1, 3), up=np.asarray(self.p['target_up'], float),
                              facing=facing if facing.size == 3 and np.any(facing) else None)
        return Initialiser(geom, R_ct=np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]),
                           t_ct=np.array([x, y, z]),
                           max_position_sigma_m=self.p['init_max_position_sigma_m'],
                           up_sigma_rad=self.p['init_up_sigma_rad'],
                           min_radius_px=self.p['marker_min_radius_px'],
                           max_radius_px=self.p['marker_max_radius_px'])

    def _changed(self, changed: dict) -> None:
        self.p.update(changed)
        self.ranger = None  # rebuilt with the new settings at the next frame

    def _info(self, side: str, msg: CameraInfo) -> None:
        old = self.info.get(side)
        if old is None or list(old.p) != list(msg.p) or old.width != msg.width:
            self.ranger = None
        self.info[side] = msg
        if 'left' in self.info and 'right' in self.info:
            waiting, self._waiting = self._waiting, []
            for m in waiting:
                self._process(m)

    def _make_ranger(self) -> StereoRanger:
        li, ri = self.info['left'], self.info['right']
        settings = StereoSettings(**{f.name: self.p[f.name] for f in fields(StereoSettings)})
        return settings.ranger(li.p, ri.p, li.width, li.height)

    def _put(self, kind: str, msg) -> None:
        st = stamp_ns(msg.header.stamp)
        b = self.buf[kind]
        b[st] = msg
        if len(b) > 10:
            self._drop_unmatched([next(iter(b))])
        if all(st in self.buf[k] for k in ('left', 'right', 'pose')):
            msgs = {k: self.buf[k].pop(st) for k in ('left', 'right', 'pose')}
            # older unmatched frames will never complete
            self._drop_unmatched(sorted({s for k in self.buf for s in self.buf[k] if s < st}))
            self._process(msgs)

    def _drop_unmatched(self, stamps: list[int]) -> None:
        """Forget the frames at `stamps`, each missing a part (left, right or pose) that a
        lossy link or a stalled publisher never delivered: counted as 'unmatched'."""
        for s in stamps:
            have = [k for k in self.buf if self.buf[k].pop(s, None) is not None]
            self.bad.reject('unmatched', f'frame at {s * 1e-9:.3f} s: only '
                            f'{" + ".join(have)} arrived')

    def _process(self, m: dict) -> None:
        if not self.p['ranging']:
            return
        if 'left' not in self.info or 'right' not in self.info:
            # the first frame may complete before its camera_info (other topics, no order
            # between them): hold it until the calibration arrives, as the offline path does
            self._waiting.append(m)
            if len(self._waiting) > 10:
                self._waiting.pop(0)
                self.bad.reject('no_camera_info')
            return
        pose: PoseWithCovarianceStamped = m['pose']
        if self.initialiser is not None:
            pose = self._initialise(m, pose)
            if pose is None:
                return
        if pose.header.frame_id != self.map_frame:
            self.bad.reject('pose_frame', pose.header.frame_id)
            return
        try:
            if self.ranger is None:
                self.ranger = self._make_ranger()
            left, right = image_to_array(m['left']), image_to_array(m['right'])
            # checked before the fiducial filter sees the frame: a bad one must not reach it
            self.ranger.check_images(left, right)
            R, t = pose_to_rt(pose.pose.pose)
            if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
                raise StereoError('camera pose not finite')
            disp = None
            if self.fiducial_method is not None:
                disp = self.ranger.disparity(left, right)
                R, t, pose = self._correct(left, disp, R, t, pose)
            scan = self.ranger.process(left, right, R, t, disparity=disp)
        except (StereoError, ValueError, cv2.error) as exc:
            self.bad.reject('stereo', str(exc))
            return
        hdr = Header(stamp=m['left'].header.stamp, frame_id=self.map_frame)
        self.pub_pose.publish(pose)
        self.pub_cloud.publish(cloud_to_msg(scan.points, scan.covariances, hdr))
        self.frames += 1
        if self.p['contribute']:
            self._contribute(scan.points, scan.covariances, t, hdr)

    def _contribute(self, points: np.ndarray, covariances: np.ndarray, origin: np.ndarray,
                    hdr: Header) -> None:
        """The scan as the mapper would fuse the cloud (its float32 numbers, its checks,
        this rover's body dropped), sent as a contribution."""
        pts = points.astype(np.float32).astype(np.float64)
        cov = covariances.astype(np.float32).astype(np.float64)
        try:
            c, _ = make_contribution(
                self.contribution_map, pts, cov, np.asarray(origin, float),
                limits=ScanLimits(self.p['max_points'], MapSettings.max_range_m),
                bodies=BodyFilter(self.p['body_radius_m'], self.p['body_above_camera_m']))
        except ScanRejected as exc:
            self.bad.reject(exc.reason, str(exc))
            return
        self.contributions += 1
        self.pub_contribution.publish(contribution_to_msg(
            c, self.contribution_map, hdr, source=self.source, session=self.session,
            sequence=self.contributions))

    def _initialise(self, m: dict, pose: PoseWithCovarianceStamped
                    ) -> PoseWithCovarianceStamped | None:
        """§3.2.2: before the alignment is fixed, look for the target (None: publish nothing);
        after, the own-frame pose in map_frame with the alignment's covariance added."""
        init = self.initialiser
        R_oc, t_oc = pose_to_rt(pose.pose.pose)
        if init.initialised:
            R, t, cov = init.to_common(R_oc, t_oc, np.array(pose.pose.covariance, float))
            return _pose_msg(pose.header.stamp, self.map_frame, R, t, cov)
        try:
            if self.ranger is None:
                self.ranger = self._make_ranger()
            left, right = image_to_array(m['left']), image_to_array(m['right'])
            step = init.observe(left, right, self.ranger.camera, R_oc, t_oc,
                                error_model=self.ranger.error_model)
        except (StereoError, TargetFrameError, ValueError) as exc:
            self.bad.reject('stereo', str(exc))
            return None
        if step.R is None:
            self.get_logger().info(f'initialisation: target not found ({step.n_markers} '
                                   f'marker candidates: {step.reason})',
                                   throttle_duration_sec=5.0)
            return None
        self.pub_target.publish(_pose_msg(pose.header.stamp, self.map_frame, step.R,
                                          step.t, _ros_cov(step.covariance)))
        if not step.accepted:
            self.get_logger().info(f'initialisation: target found, position sigma '
                                   f'{step.position_sigma_m:.3f} m > '
                                   f'{init.max_position_sigma_m:.3f} m, waiting for a '
                                   'closer view', throttle_duration_sec=5.0)
            return None
        R_a, t_a = init.alignment
        self.map_from_odom = np.eye(4)
        self.map_from_odom[:3, :3], self.map_from_odom[:3, 3] = R_a, t_a
        if self.fiducial_method is None:
            self._send_static_tree()
        self.pub_alignment.publish(_pose_msg(pose.header.stamp, self.map_frame, R_a, t_a,
                                             _ros_cov(init.alignment_covariance)))
        self.get_logger().info(
            f'initialised after {init.attempts} pair(s): camera at '
            f'{np.array2string(step.t, precision=3)} in {self.map_frame} (position sigma '
            f'{step.position_sigma_m:.3f} m); own frame ({pose.header.frame_id}) -> '
            f'{self.map_frame}: yaw {np.degrees(np.arctan2(R_a[1, 0], R_a[0, 0])):.2f} '
            f'deg, t {np.array2string(t_a, precision=3)}')
        R, t, cov = init.to_common(R_oc, t_oc, np.array(pose.pose.covariance, float))
        return _pose_msg(pose.header.stamp, self.map_frame, R, t, cov)

    def _send_static_tree(self) -> None:
        fr = self.rover_frames
        self.tree.send_static([Transform.from_matrix(fr.map, fr.odom, self.map_from_odom)],
                              self.get_clock().now().to_msg())

    def _send_tree(self) -> None:
        """map -> <rover>/odom, stamped now (a localisation node's habit: the estimate holds
        until the next one); nothing before `initialise` has found the target."""
        now = self.get_clock().now()
        if self.map_from_odom is None or now.nanoseconds == 0 or not self.tree.listened:
            return
        fr = self.rover_frames
        self.tree.send([Transform.from_matrix(fr.map, fr.odom, self.map_from_odom)],
                       now.to_msg())

    def _correct(self, left, disp, R, t, pose: PoseWithCovarianceStamped):
        """§3.2.5 on the live stream: dead-reckoned increment as prediction, fiducials as
        correction. Returns the corrected (R, t, pose message)."""
        T_dr = np.eye(4)
        T_dr[:3, :3], T_dr[:3, 3] = R, t
        if self.odometry is None:
            cfg = OdometryConfig(n_fiducials=self.p['n_fiducials'],
                                 method=self.fiducial_method,
                                 scene_distance=self.p['scene_distance_m'],
                                 spacing_px=left.shape[1] / 16)
            odometry = FiducialOdometry(self.ranger.camera, cfg, T_dr)
            odometry.first(left, disp)       # kept only once it has started
            self.odometry = odometry
            self.get_logger().info(f'fiducial correction ({cfg.method}) started with '
                                   f'{len(self.odometry.x)} fiducials')
            T = T_dr
        else:
            delta = np.linalg.inv(self._prev_dr) @ T_dr
            T = self.odometry.step([(left, disp)], delta)
        self._prev_dr = T_dr
        self.map_from_odom = T @ np.linalg.inv(T_dr)
        out = PoseWithCovarianceStamped()
        out.header = pose.header
        p = out.pose.pose
        p.position.x, p.position.y, p.position.z = (float(v) for v in T[:3, 3])
        q = quat_of(T[:3, :3])
        p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = q
        if self.odometry.S.any():      # the filter's pose covariance, (theta, c) -> ROS order
            out.pose.covariance = _ros_cov(self.odometry.S).reshape(-1).tolist()
        else:                          # the first frame: the pose given, with its covariance
            out.pose.covariance = pose.pose.covariance
        return T[:3, :3], T[:3, 3], out


def _ros_cov(c: np.ndarray) -> np.ndarray:
    """(theta, dt) 6x6 -> ROS order (position, rotation)."""
    P = np.zeros((6, 6))
    P[:3, 3:] = P[3:, :3] = np.eye(3)
    return P @ c @ P.T


def _pose_msg(stamp, frame: str, R: np.ndarray, t: np.ndarray, cov: np.ndarray
              ) -> PoseWithCovarianceStamped:
    out = PoseWithCovarianceStamped()
    out.header = Header(stamp=stamp, frame_id=frame)
    p = out.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in t)
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = quat_of(R)
    out.pose.covariance = [float(v) for v in np.asarray(cov, float).reshape(-1)]
    return out


def main(args=None) -> int:
    """`ros2 run coop_mapping stereo`."""
    return run_node(StereoNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
