"""Node `master`: the rover that watches the task (thesis ch. 4-5) and runs the `insert` action.

Runs in the team's namespace (like the mapper) for the rover named by `rover`:

- tracks the card's and the slot's markers in `<rover>/stereo/{left,right}/image_raw` (every
  frame, or at most `vision_rate_hz`), triangulates them and publishes the four labelled
  centres with their covariances and the vertical from the mast encoders on `<rover>/markers`;
- action `insert` (coop_msgs/action/Insert): PLACE_CAMERA: the master is told only a rough
  region the slot is in (`site_position`, `site_search_m`); it places its camera at the best
  views over the region (coop_insertion.locate; the same search for the optimal and random
  placements; the given placement looks from its own pose alone), panning its mast at each,
  until it sees the slot's markers (averaged over half a second of frames), takes the site's
  pose
  from them, then places the camera for the task at the site so located (the team's
  `viewplan/task_view`: its best, or one drawn from the same feasible poses for the random
  placement; or the goal's own pose; the rover drives there on its odometry and tilts its
  mast; where the planner has no view of the located site, the camera stays where it saw the
  slot, its mast aimed at the task's target); then it hands the task with the located site to
  the slave's `<slave>/insert_card` action, relays its feedback and result, and places its
  camera again when the fixes stop (optimal and random; with no pose to place it at, the mast
  aimed at the task's target from where it stands).
"""
from __future__ import annotations

import math
import time

import numpy as np
from geometry_msgs.msg import Point, PoseStamped, Twist
from nav_msgs.msg import Odometry
from rclpy.action import ActionClient, ActionServer, CancelResponse, GoalResponse
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from rclpy.task import Future
from sensor_msgs.msg import CameraInfo, Image, JointState
from trajectory_msgs.msg import JointTrajectory, JointTrajectoryPoint

from coop_common.frames import FRAME_PARAMS, check_prefix
from coop_common.lockstep_node import Lockstep
from coop_common.node_util import BadInputCounter, declare_parameters, run_node, stamp
from coop_common.params import ParamSpec, choice
from coop_common.qos import COMMAND_QOS, LATCHED_QOS, SENSOR_QOS
from coop_common.rover_geometry import (
    MAST_JOINTS,
    ReachError,
    camera_in_base,
    camera_in_map,
    camera_mount,
    mast_aim,
    yaw_of,
)
from coop_mapping.stereo import StereoCamera, StereoError
from coop_mapping.stereo_node import image_to_array
from coop_msgs.action import Insert
from coop_msgs.msg import MarkerObservation, TaskTarget, ViewRating
from coop_msgs.srv import TaskView
from coop_viewplan.frames import yaw_pitch_from_optical

from .drive import GoToPose, wrap
from .errors import InsertionError
from .frames import invert
from .locate import SiteEstimate, search_points
from .markers import (
    DEFAULT_MAX_RESIDUAL_PX,
    DEFAULT_MIN_CONTRAST,
    DEFAULT_MIN_COVERAGE,
    DEFAULT_RADIUS_PX,
    DETECTORS,
    DetectorKind,
    make_detector,
)
from .task import (
    LABELS,
    SlotPair,
    TaskModel,
    find_slot,
    label_markers,
    site_from_slot,
    slot_from_site,
)
from .triangulate import triangulate_markers

PARAMS = {
    'rover': ParamSpec('rover1', 'The master rover (its topics are <rover>/...)', read_only=True),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'slot_width_m': ParamSpec(TaskModel.slot_width_m, "The slot's width (the task's given, as "
                              "the slave's): it sets how far apart the slot's markers are",
                              lo=0.1080, hi=0.25),
    'detector': ParamSpec('default', 'Marker detector (coop_insertion.markers)',
                          choices=DETECTORS, read_only=True),
    'marker_min_coverage': ParamSpec(DEFAULT_MIN_COVERAGE, "Default detector: least fraction "
                                     "of a marker's rim with edge points", lo=0.05, hi=1.0,
                                     read_only=True),
    'marker_max_residual_px': ParamSpec(DEFAULT_MAX_RESIDUAL_PX, 'Default detector: largest '
                                        'RMS ellipse-fit residual (px) of a marker kept',
                                        lo=0.05, hi=5.0, read_only=True),
    'marker_min_contrast': ParamSpec(DEFAULT_MIN_CONTRAST, 'Default detector: least '
                                     'marker-to-surround contrast (grey levels)', lo=1.0,
                                     hi=254.0, read_only=True),
    'remember_slot': ParamSpec(True, 'Label the card against the slot pair seen before while '
                               'the camera stands still (the card hides or shades a slot '
                               'marker as it comes to the mouth); dropped when the camera '
                               'moves'),
    'slot_wait_s': ParamSpec(5.0, 'Once the camera stands, look at this long (s, by the '
                             "frames' stamps) of its frames for the slot pair alone in view "
                             'at the task view, before the slave brings the card (the pair '
                             'that locates the site again and that remember_slot labels '
                             'against)', lo=0.25, hi=60.0),
    'search_look_s': ParamSpec(1.0, 'As slot_wait_s, at each view over the region (and each '
                               'mast pan there) while the master looks for the slot (the '
                               'frames of a camera standing still differ by noise alone)',
                               lo=0.25, hi=60.0),
    'search_pans_rad': ParamSpec([0.0, -0.3, 0.3, -0.6, 0.6, -0.45, 0.45, -0.15, 0.15],
                                 'The mast pans the master looks from in turn at each view over '
                                 'the region (rad, 0 the pose the view planner chose): a slot '
                                 'beside the view is turned to; the steps of 0.3 first, then '
                                 'those between (a slot marker imaged a sliver at one pan is '
                                 'whole at the next)'),
    'vision_rate_hz': ParamSpec(0.0, 'Process at most this many stereo frames per second '
                                '(0: every frame)', lo=0.0, hi=100.0),
    'site_position': ParamSpec([3.0572, 0.0, 0.4], "The centre of the region the slot's "
                               "mouth is in (map frame, m): where the master looks for it"),
    'site_normal': ParamSpec([0.0, 1.0, 0.0], "The outward normal of the site's marked faces "
                             '(map frame), as roughly known: the side the master looks from'),
    'site_search_m': ParamSpec(0.3, 'The region the slot is in: this far (m) either side of '
                               'site_position, along the marked faces and across them',
                               lo=0.0, hi=2.0),
    'search_spacing_m': ParamSpec(0.3, 'The spacing (m) of the targets the master places its '
                                  'camera for while it looks for the slot over the region',
                                  lo=0.05, hi=2.0),
    'max_search_views': ParamSpec(9, 'Search points to try (each a view planned and looked '
                                  'from at every pan; a point with no view costs nothing) '
                                  'before the goal aborts (the region has '
                                  '(1 + ceil(2 site_search_m / search_spacing_m))^2)',
                                  lo=1, hi=100),
    'target_sigma_m': ParamSpec(0.01, 'Position uncertainty of the located site in the map '
                                '(m)', lo=0.0, hi=1.0),
    'max_speed_m_s': ParamSpec(0.2, 'Driving speed to the camera pose (m/s)', lo=0.01,
                               hi=0.25),
    'view_target_offset_m': ParamSpec([0.0, 0.15, 0.1], "The task view's primary target "
                                      'relative to site_position (map axes, m): in front of the '
                                      'marked faces and above the mouth, so that a camera aimed '
                                      "at it has the card's markers and the slot's in view"),
    'marker_min_diameter_px': ParamSpec(6.0, "The smallest slot marker's image (px across) "
                                        'the detector identifies reliably (>= 97 % up to '
                                        'marker_max_incidence_deg, measured on the '
                                        "simulator's renders: coop_insertion.detector_limits): "
                                        "with the focal length it bounds the task's depth of "
                                        'field (thesis section 4.2.3.1)', lo=2.0, hi=100.0),
    'marker_max_incidence_deg': ParamSpec(60.0, "The largest angle between the view ray and "
                                          "the markers' face normal at which the detector "
                                          'identifies them reliably (measured as '
                                          'marker_min_diameter_px): task_view admits no '
                                          'camera pose beyond it', lo=1.0, hi=90.0),
    'target_radius_m': ParamSpec(0.03, "The primary target's extent (m)", lo=0.0, hi=1.0),
    'secondary_weight': ParamSpec(0.5, "Weight of the secondary target (the site's marked "
                                  'face at site_position, with target_sigma_m): watched when '
                                  'the primary is occluded (Eq. 4-4)', lo=0.01, hi=1.0),
    'replace_after_s': ParamSpec(3.0, 'Re-place the camera (optimal: the next best pose; '
                                 'random: a new draw) when no fix '
                                 'came for this long (sim s) once the card should be in view '
                                 "(the slave's approach done, or a fix came)", lo=0.5,
                                 hi=60.0),
    'max_replacements': ParamSpec(2, 'Re-placements per goal (optimal and random placement)',
                                  lo=0, hi=20),
    'replace_range_factor': ParamSpec(0.85, "Each re-placement shrinks the markers' range by "
                                      'this factor (a closer view)', lo=0.3, hi=1.0),
    'seed': ParamSpec(0, "Seed of the random placement's draws", lo=0, hi=2**31 - 1),
    'lockstep': ParamSpec(False, "Answer rover_sim's lockstep rounds (a participant in its "
                          'lockstep_participants): frames, odometry and the action advance '
                          'round by round, so the outcome does not depend on load',
                          read_only=True),
    'place_timeout_s': ParamSpec(120.0, "Give up placing the camera after this (the node's "
                                 'clock: sim s with use_sim_time)',
                                 lo=1.0, hi=3600.0),
}


#: the placements this master serves, and those it re-places when the fixes stop
PLACEMENTS = (Insert.Goal.PLACEMENT_OPTIMAL, Insert.Goal.PLACEMENT_RANDOM,
              Insert.Goal.PLACEMENT_RANDOM_FIXED, Insert.Goal.PLACEMENT_GIVEN)
REPLACED = (Insert.Goal.PLACEMENT_OPTIMAL, Insert.Goal.PLACEMENT_RANDOM)


#: the mast stands at a commanded pan and tilt within this (rad), waited for at most
#: MAST_WAIT_S of the clock
MAST_TOLERANCE_RAD = 0.02
MAST_WAIT_S = 5.0
#: once the slot pair is first seen standing, the site is averaged over this much more of the
#: frames' time (s)
SITE_AVERAGE_S = 0.5
#: a sensor stamp this far behind the latest one is time jumping back (a simulator reset, a
#: looped bag), not a late message
TIME_JUMP_BACK_S = 0.5


def _check(p: dict) -> str | None:
    if (bad := check_prefix(p['frame_prefix'])) is not None:
        return bad
    for name in ('site_position', 'site_normal', 'view_target_offset_m'):
        v = p[name]
        if len(v) != 3 or not all(math.isfinite(x) for x in v):
            return f'{name} must be three finite numbers'
    if np.linalg.norm(p['site_normal'][:2]) < 1e-6:
        return 'site_normal must not be vertical (the marked faces stand)'
    pans = p['search_pans_rad']
    if not pans or not all(math.isfinite(x) and abs(x) <= 3.0 for x in pans):
        return 'search_pans_rad must be one or more pans within +-3 rad'
    return None


def _stamp(msg) -> float:
    return msg.header.stamp.sec + 1e-9 * msg.header.stamp.nanosec


class MasterNode(Node):
    """The master: tracks the card's and the slot's markers in its stereo images, places its
    camera, and guides the slave (the insert action)."""

    def __init__(self, **kwargs) -> None:
        super().__init__('master', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self._on_params, check_all=_check)
        self.bad = BadInputCounter(self)
        r = self.p['rover']
        # the team's map frame (frame_prefix: team_a/map), of the poses it sends and takes
        self.map_frame = self.p['frame_prefix'] + 'map'
        self.model = TaskModel(slot_width_m=self.p['slot_width_m'])
        self.detector = None
        self.camera: StereoCamera | None = None
        self.info: dict[str, CameraInfo] = {}
        self.frames: dict[int, dict[str, Image]] = {}
        self.mast = (0.0, 0.0)
        self._mast_t = -math.inf           # stamp of the joint state self.mast is from
        self._arrived_t = -math.inf        # odometry stamp of the last arrival
        self._tilt = 0.0                   # the tilt the last placement commanded
        self.odom: tuple[float, float, float] | None = None
        self._last_vision = -math.inf
        self._image_t = -math.inf          # stamp of the last stereo pair (s)
        self._fix_t = -math.inf            # stamp of the last published fix (s)
        self._sensor_t: dict[str, float] = {}     # each stream's latest stamp (s)
        self.card_in_map: np.ndarray | None = None    # card markers' midpoint, last fix
        self.looked = 0                    # stereo pairs looked at
        self.tracked = 0                   # of them, those that gave a fix
        self.remembered = 0                # fixes labelled against the remembered slot pair
        self.predicted = 0                 # ... against the slot pair the located site predicts
        self.replacements = 0
        self.search_views = 0
        # the site's pose from the slot pairs seen since the camera was placed, and the site
        # the running goal located (4x4 in the map; None: not yet)
        self.site_seen = SiteEstimate()
        self.site: np.ndarray | None = None
        # the slot pair last seen since the camera was placed (dropped when it moves again)
        self._slot: SlotPair | None = None
        # stamp of the odometry at which the rover stopped at its camera pose (inf while it
        # drives): a frame is taken standing by its stamp, not by when it is processed (a
        # master behind its image queue processes frames from the drive after the stop)
        self._stood_t = math.inf
        self.rng = np.random.default_rng(int(self.p['seed']))
        # in lockstep a round's messages come in stamp order, and within one stamp in the
        # order of these subscriptions: the camera's info before its images
        self.ls = Lockstep(self, self.p['lockstep'])
        for side in ('left', 'right'):
            self.ls.subscription(CameraInfo, f'{r}/stereo/{side}/camera_info',
                                 lambda m, s=side: self.info.__setitem__(s, m), SENSOR_QOS)
        self.ls.subscription(JointState, f'{r}/joint_states', self._on_joints, SENSOR_QOS)
        self.ls.subscription(Odometry, f'{r}/odom', self._on_odom, SENSOR_QOS)
        for side in ('left', 'right'):
            self.ls.subscription(Image, f'{r}/stereo/{side}/image_raw',
                                 lambda m, s=side: self._on_image(s, m), SENSOR_QOS)
        self.pub_markers = self.ls.publisher(MarkerObservation, f'{r}/markers', SENSOR_QOS)
        self.pub_cmd = self.ls.publisher(Twist, f'{r}/cmd_vel', COMMAND_QOS)
        self.pub_placement = self.create_publisher(ViewRating, f'{r}/camera_placement',
                                                   LATCHED_QOS)
        self.pub_mast = self.ls.publisher(JointTrajectory, f'{r}/mast/command', COMMAND_QOS)
        self.task_view = self.create_client(TaskView, 'viewplan/task_view')
        self._busy = False
        self._drive: GoToPose | None = None
        self._wake: Future | None = None
        self._slaves: dict[str, ActionClient] = {}
        # the action looks again at every round in lockstep, else four times a second
        if self.ls.enabled:
            self.ls.on_round(self._wakeup)
        else:
            self.create_timer(0.25, self._wakeup, clock=Clock(clock_type=ClockType.STEADY_TIME))
        ActionServer(self, Insert, 'insert', execute_callback=self._execute,
                     goal_callback=self._on_goal,
                     cancel_callback=lambda _g: CancelResponse.ACCEPT)
        self.get_logger().info(f'master ready: {r} watches, action insert')

    def _on_params(self, changed: dict) -> None:
        self.p.update(changed)
        if 'slot_width_m' in changed:
            self.model = TaskModel(slot_width_m=self.p['slot_width_m'])

    # -- vision -------------------------------------------------------------------------------
    def _on_joints(self, msg: JointState) -> None:
        idx = {n: i for i, n in enumerate(msg.name)}
        if all(n in idx for n in MAST_JOINTS) and len(msg.position) == len(msg.name):
            pan, tilt = (float(msg.position[idx[n]]) for n in MAST_JOINTS)
            if math.isfinite(pan) and math.isfinite(tilt):
                self.mast = (pan, tilt)
                self._mast_t = _stamp(msg)

    def _sensor_time(self, stream: str, t: float) -> None:
        """Follow a sensor stream's time; where it jumps back (a simulator reset between
        goals, a looped bag), forget the stamps kept from before: else the last image's stamp
        would stand ahead of every new frame, and a look at the slot end before it began."""
        last = self._sensor_t.get(stream, -math.inf)
        if t < last - TIME_JUMP_BACK_S:
            self.get_logger().info(f'{stream} time jumped back from {last:.3f} s to {t:.3f} s: '
                                   'the stamps kept from before are dropped')
            self._arrived_t = self._last_vision = self._image_t = self._fix_t = -math.inf
            self._stood_t = math.inf
            self.frames.clear()
            self._sensor_t.clear()
            last = -math.inf
        self._sensor_t[stream] = max(last, t)

    def _on_image(self, side: str, msg: Image) -> None:
        self._sensor_time(side, _stamp(msg))
        st = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
        f = self.frames.setdefault(st, {})
        f[side] = msg
        for old in [s for s in self.frames if s < st - 2 * 10**9]:
            del self.frames[old]
        if len(f) == 2:
            del self.frames[st]
            rate = self.p['vision_rate_hz']
            t = _stamp(msg)
            self._image_t = max(self._image_t, t)
            if rate > 0 and t - self._last_vision < 1.0 / rate - 1e-6:
                return
            self._last_vision = t
            self.looked += 1
            try:
                self._track(f['left'], f['right'])
            except (InsertionError, StereoError) as exc:
                self.bad.reject('frame', str(exc))

    def _setup_camera(self) -> None:
        li, ri = self.info['left'], self.info['right']
        fx, cx, cy, fy = li.p[0], li.p[2], li.p[6], li.p[5]
        baseline = -ri.p[3] / ri.p[0]
        self.camera = StereoCamera(fx=fx, fy=fy, cx=cx, cy=cy, baseline=baseline,
                                   width=li.width, height=li.height)
        k = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        # a string on the wire, checked against DETECTORS when declared (read-only)
        kind = choice(DetectorKind, self.p['detector'], 'detector', error=InsertionError)
        opts = {'radius_px': DEFAULT_RADIUS_PX}
        if kind is DetectorKind.DEFAULT:
            opts.update(K=k, min_coverage=self.p['marker_min_coverage'],
                        max_residual_px=self.p['marker_max_residual_px'],
                        min_contrast=self.p['marker_min_contrast'])
        self.detector = make_detector(kind, **opts)

    def _track(self, left: Image, right: Image) -> None:
        if 'left' not in self.info or 'right' not in self.info:
            raise InsertionError('no camera_info yet')
        if self.camera is None or self.camera.width != self.info['left'].width:
            self._setup_camera()
        ml = self.detector.detect(image_to_array(left))
        mr = self.detector.detect(image_to_array(right))
        st = triangulate_markers(ml, mr, self.camera)
        up = camera_in_base(*self.mast)[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        radii = [ml[m.left].radius_px for m in st]
        # the camera moves only when the master places it: a slot pair seen while it stands is
        # where the slot is for as long as it stands
        standing = _stamp(left) >= self._stood_t
        memory = self._slot if standing and self.p['remember_slot'] else None
        predicted = memory is None and standing and self.site is not None
        if predicted:
            memory = self._slot_out_of_view()
            predicted = memory is not None
        try:
            lab = label_markers(st, radii, self.camera.fx, up, self.model, slot_memory=memory)
        except InsertionError as exc:
            slot = find_slot(st, radii, self.camera.fx, up, self.model)
            if slot is not None and standing:
                self._saw_slot(slot, up)
            self.get_logger().info(f'markers: {exc}', throttle_duration_sec=5.0)
            return
        if lab.slot_remembered and predicted:
            self.predicted += 1
        elif lab.slot_remembered:
            self.remembered += 1
        elif standing:
            self._saw_slot(lab.slot, up)
        msg = MarkerObservation()
        msg.header = left.header
        msg.labels = list(LABELS)
        for p, c in zip(lab.points, lab.covariances, strict=False):
            msg.positions.append(Point(x=float(p[0]), y=float(p[1]), z=float(p[2])))
            msg.covariances.extend(float(v) for v in c.ravel())
            u = self.camera.cx + self.camera.fx * p[0] / p[2]
            v = self.camera.cy + self.camera.fy * p[1] / p[2]
            msg.u.append(float(u))
            msg.v.append(float(v))
            msg.radius_px.append(float('nan'))
        msg.up.x, msg.up.y, msg.up.z = (float(x) for x in lab.up)
        self.pub_markers.publish(msg)
        self.tracked += 1
        self._fix_t = _stamp(left)
        if self.odom is not None:
            cam = camera_in_map(*self.odom, *self.mast)
            mid = 0.5 * (lab.points[0] + lab.points[1])
            self.card_in_map = cam[:3, :3] @ mid + cam[:3, 3]

    def _slot_out_of_view(self) -> SlotPair | None:
        """The slot's markers in the camera frame where the located site puts them (through
        the camera's pose by odometry and the mast), when that is out of the image: the card
        seen alone then still gives a fix, which relates the slave's odometry frame to this
        rover's (thesis Fig. 5-4). None when the site would be in view (its own markers give
        the fixes there, both in the image) or the pose is unknown."""
        if self.site is None or self.odom is None or self.camera is None:
            return None
        cam = camera_in_map(*self.odom, *self.mast)
        pair = slot_from_site(invert(cam) @ self.site, self.model,
                              sigma_m=self.p['target_sigma_m'])
        c = self.camera
        x, y, z = pair.points.T
        z = np.maximum(z, 1e-9)
        u, v = c.cx + c.fx * x / z, c.cy + c.fy * y / z
        inside = (pair.points[:, 2] > 0) & (u >= 0) & (u < c.width) & (v >= 0) & (v < c.height)
        return None if inside.all() else pair

    def _saw_slot(self, slot: SlotPair, up: np.ndarray) -> None:
        """The slot pair seen from where the camera stands: remembered, and the site's pose in
        the map it gives (the camera's pose from odometry and the mast) added to site_seen."""
        self._slot = slot
        if self.odom is None:
            return
        try:
            self.site_seen.add(camera_in_map(*self.odom, *self.mast)
                               @ site_from_slot(slot, up, self.model))
        except InsertionError as exc:
            self.bad.reject('slot', str(exc))

    # -- driving ------------------------------------------------------------------------------
    def _on_odom(self, msg: Odometry) -> None:
        self._sensor_time('odom', _stamp(msg))
        q = msg.pose.pose.orientation
        self.odom = (msg.pose.pose.position.x, msg.pose.pose.position.y,
                     yaw_of(q.x, q.y, q.z, q.w))
        if self._drive is not None:
            c = self._drive.command(*self.odom)
            t = Twist()
            t.linear.x, t.angular.z = c.linear_x, c.angular_z
            self.pub_cmd.publish(t)
            if c.arrived:
                self._drive = None
                self._arrived_t = _stamp(msg)
                self.get_logger().info(f'camera placed: base at ({self.odom[0]:.2f}, '
                                       f'{self.odom[1]:.2f}) heading {self.odom[2]:.2f} by '
                                       'odometry')
                self._wakeup()

    def _wakeup(self) -> None:
        if self._wake is not None and not self._wake.done():
            self._wake.set_result(None)

    def _now_s(self) -> float:
        """Sim time as this node knows it: the round's stamp in lockstep, else its clock."""
        return self.ls.now_s(lambda: self.get_clock().now().nanoseconds * 1e-9)

    async def _sleep_until_wake(self) -> None:
        self._wake = Future()
        await self._wake

    # -- the action ---------------------------------------------------------------------------
    def _on_goal(self, goal: Insert.Goal) -> GoalResponse:
        if self._busy:
            self.get_logger().warn('insert: a goal is running; rejected')
            return GoalResponse.REJECT
        if goal.master and goal.master != self.p['rover']:
            self.get_logger().warn(f'insert: this master is {self.p["rover"]}, not '
                                   f'{goal.master}; rejected')
            return GoalResponse.REJECT
        if not goal.slave or goal.slave == self.p['rover']:
            self.get_logger().warn('insert: the goal names no slave (or the master); rejected')
            return GoalResponse.REJECT
        if goal.placement not in PLACEMENTS:
            self.get_logger().warn(f'insert: unknown placement {goal.placement}; rejected')
            return GoalResponse.REJECT
        self._busy = True
        return GoalResponse.ACCEPT

    async def _execute(self, handle) -> Insert.Result:
        t0 = time.monotonic()
        try:
            res = await self._run(handle)
        except Exception as exc:   # noqa: BLE001  an action must end with a result
            self.get_logger().error(f'insert failed: {exc!r}')
            handle.abort()
            res = Insert.Result(success=False, reason=f'master error: {exc}',
                                ended=stamp(self._now_s()), replacements=self.replacements)
            self._report_site(res)
        finally:
            self._busy = False
            self._drive = None
            self.pub_cmd.publish(Twist())
        res.duration_s = time.monotonic() - t0 if res.duration_s == 0 else res.duration_s
        return res

    def _feedback(self, handle, phase: int, **kw) -> None:
        fb = Insert.Feedback(phase=phase, displacement_error_m=kw.get('d', math.nan),
                             angle_error_rad=kw.get('a', math.nan))
        handle.publish_feedback(fb)

    async def _run(self, handle) -> Insert.Result:
        goal = handle.request
        self.replacements = 0
        self.search_views = 0
        self.site = None
        self.card_in_map = None
        # each goal draws its random poses afresh from the seed: an attempt's placement
        # depends on its seed alone, not on the goals before it
        self.rng = np.random.default_rng(int(self.p['seed']))
        self._feedback(handle, Insert.Feedback.PHASE_PLACE_CAMERA)
        if goal.placement != Insert.Goal.PLACEMENT_GIVEN:
            failed = await self._locate(handle, goal)
            if failed:
                return self._end(handle, failed)
        where = await self._choose_pose(goal)
        if isinstance(where, str) and self.site is not None:
            # the located site carries the odometry's drift: where the planner finds no view of
            # it, the camera stays where it saw the slot (and sees it), its mast aimed at the
            # task's target (the search's tilt may leave the card above the image)
            self.get_logger().info(f'{where}: the camera stays where it found the slot')
            failed = await self._aim(handle, self._task_target())
            if failed and handle.is_cancel_requested:
                return self._end(handle, failed)
            if failed:
                self.get_logger().warn(f'{failed}: the mast stays as it is')
        else:
            failed = await self._place(handle, where)
            if failed:
                return self._end(handle, failed)
        # the site's markers while the view is clear (the card, once at the mouth, may hide
        # one): the site again, from the task's view
        if await self._see_slot(handle, self.p['slot_wait_s']):
            self.site = self.site_seen.pose
            self.get_logger().info('slot pair seen from where the camera stands: the site at '
                                   f'{np.round(self.site[:3, 3], 3).tolist()}')
        elif handle.is_cancel_requested:
            return self._end(handle, 'canceled while looking for the slot')
        else:
            self.get_logger().info(f'no slot pair seen in {self.p["slot_wait_s"]:g} s '
                                   'standing: the card is brought without it')
        # hand over to the slave
        client = self._slaves.get(goal.slave)
        if client is None:
            client = ActionClient(self, Insert, f'{goal.slave}/insert_card')
            self._slaves[goal.slave] = client
        if not client.wait_for_server(timeout_sec=10.0):
            return self._end(handle, f'no {goal.slave}/insert_card server')
        sub = Insert.Goal(master=self.p['rover'], slave=goal.slave, placement=goal.placement,
                          tolerance_m=goal.tolerance_m,
                          angle_tolerance_rad=goal.angle_tolerance_rad,
                          max_force_n=goal.max_force_n, timeout_s=goal.timeout_s,
                          stamp=stamp(self._now_s()))
        if self.site is not None:
            sub.site = _pose_stamped(self.site, self.map_frame)
        phase = [Insert.Feedback.PHASE_PLACE_CAMERA]
        awaiting = [False]
        relocating = [False]
        seen = (self.looked, self.tracked, self.remembered, self.predicted)

        def relay(fb) -> None:
            phase[0] = fb.feedback.phase
            awaiting[0] = fb.feedback.awaiting_fix
            relocating[0] = fb.feedback.relocating
            handle.publish_feedback(fb.feedback)

        sh = await self.ls.hold(client.send_goal_async(sub, feedback_callback=relay))
        if not sh.accepted:
            return self._end(handle, f'{goal.slave} rejected the task')
        res_future = sh.get_result_async()
        # the fix is judged lost from when the card should be in view: the slave's coarse
        # approach done (it holds for the first fix), or a fix of this goal had come; while
        # the card is still on its way (or the slave's base relocates it) the camera stays
        # where it was placed. No fix yet in this goal: the mast pans for the card once per
        # placement (the slave's odometry frame may disagree with this rover's by more than
        # the view is wide); then, as when fixes are lost, the camera is placed again
        since, started = -math.inf, self._image_t
        searched = False
        while not res_future.done():
            await self._sleep_until_wake()
            if handle.is_cancel_requested:
                await self.ls.hold(sh.cancel_goal_async())
                continue
            if phase[0] != Insert.Feedback.PHASE_VISUAL_SERVO:
                continue
            if since == -math.inf:
                if not (awaiting[0] or self._fix_t > started):
                    continue
                since = self._image_t
            if relocating[0]:
                since = self._image_t
                continue
            lost = self._image_t - max(self._fix_t, since)
            if lost <= self.p['replace_after_s']:
                continue
            if not searched and self._fix_t <= started:
                searched = True
                if await self._look_for_card(handle):
                    since = self._image_t
                    continue
                if handle.is_cancel_requested:
                    continue
                since = self._image_t
            if (goal.placement in REPLACED and
                    self.replacements < self.p['max_replacements']):
                searched = False
                self.replacements += 1
                self.get_logger().info(f'no fix for {lost:.1f} s while the slave servos: '
                                       f're-placing the camera ({self.replacements})')
                where = await self._choose_pose(goal, card=self.card_in_map,
                                                closer=self.replacements)
                if isinstance(where, str) and self.card_in_map is not None:
                    # the target half-way to the card may lie in the card's (or the slave's)
                    # voxels: the site's own target, nearer
                    where = await self._choose_pose(goal, closer=self.replacements)
                if isinstance(where, str):
                    # no pose to drive to: the mast aimed at the task's target from where the
                    # camera stands (the slave brings the card there)
                    self.get_logger().warn(f're-placement: {where}: aiming the mast from '
                                           'where the camera stands')
                    failed = await self._aim(handle, self._task_target())
                else:
                    failed = await self._place(handle, where)
                if failed and handle.is_cancel_requested:
                    await self.ls.hold(sh.cancel_goal_async())
                elif failed:
                    self.get_logger().warn(f're-placement: {failed}')
                since = self._image_t
        res = res_future.result().result
        res.frames = self.looked - seen[0]
        res.fixes = self.tracked - seen[1]
        res.replacements = self.replacements
        self._report_site(res)
        self.get_logger().info(
            f'goal ended ({res.reason}): {res.fixes} fixes in {res.frames} frames, '
            f'{self.remembered - seen[2]} of them against the remembered slot pair, '
            f'{self.predicted - seen[3]} against the one the located site predicts')
        if handle.is_cancel_requested:
            handle.canceled()
        elif res.success:
            handle.succeed()
        else:
            handle.abort()
        return res

    async def _look_for_card(self, handle) -> bool:
        """No fix while the slave holds where its map puts the site: the two rovers' odometry
        frames disagree by more than the view is wide. Pan the mast through search_pans_rad
        (search_look_s of frames at each) until the card gives fixes (against the slot pair the
        located site predicts, out of view: they relate the slave's frame to this rover's),
        then back to the task's pan; True when the card was seen."""
        task_pan, before = self.mast[0], self._fix_t
        found = None
        for pan in self.p['search_pans_rad']:
            if abs(pan) <= MAST_TOLERANCE_RAD:
                continue
            self._command_mast(task_pan + pan, self._tilt)
            if not await self._mast_at(handle, task_pan + pan, self._tilt):
                return False
            look = self._image_t
            while self._image_t < look + self.p['search_look_s'] and self._fix_t <= before:
                await self._sleep_until_wake()
                if handle.is_cancel_requested:
                    return False
            if self._fix_t > before:
                found = pan
                # a few more of the card's fixes for the slave's goal
                first = self._image_t
                while self._image_t < first + SITE_AVERAGE_S and \
                        not handle.is_cancel_requested:
                    await self._sleep_until_wake()
                break
        where = '' if self.card_in_map is None or self.site is None else \
            f', {1e3 * float(np.linalg.norm(self.card_in_map[:2] - self.site[:2, 3])):.0f} mm ' \
            'from the site'
        self.get_logger().info(
            f'no fix for {self.p["replace_after_s"]:g} s: the card ' +
            ('not seen at any pan' if found is None else f'seen at pan {found:+.2f} rad{where}')
            + ": the mast back to the task's view")
        self._command_mast(task_pan, self._tilt)
        if not await self._mast_at(handle, task_pan, self._tilt):
            return False
        return found is not None

    async def _see_slot(self, handle, seconds: float) -> bool:
        """Look at `seconds` of the frames taken standing (by their stamps: a master behind
        its image queue still looks at as many) for the slot pair (it is then remembered);
        False once they are seen without it, after 4 x `seconds` of the clock without them,
        or on a cancel."""
        started = self._now_s()
        while self._slot is None:
            if self._image_t >= self._stood_t + seconds or \
                    self._now_s() - started >= 4 * seconds:
                return False
            await self._sleep_until_wake()
            if handle.is_cancel_requested:
                return False
        # a little more of the frames for the site's mean
        first, started = self._image_t, self._now_s()
        while self._image_t < first + SITE_AVERAGE_S and \
                self._now_s() - started < 4 * SITE_AVERAGE_S:
            await self._sleep_until_wake()
            if handle.is_cancel_requested:
                return False
        return True

    def _end(self, handle, reason: str) -> Insert.Result:
        if handle.is_cancel_requested:
            handle.canceled()
        else:
            handle.abort()
        res = Insert.Result(success=False, reason=reason, ended=stamp(self._now_s()),
                            replacements=self.replacements)
        self._report_site(res)
        return res

    def _report_site(self, res: Insert.Result) -> None:
        site = self.site[:3, 3] if self.site is not None else np.full(3, math.nan)
        res.site.x, res.site.y, res.site.z = (float(v) for v in site)
        res.search_views = self.search_views

    async def _locate(self, handle, goal: Insert.Goal) -> str | None:
        """Look for the slot over the rough region (site_position, site_search_m): the camera
        placed at the best view of each of the region's search points in turn (whatever the
        goal's placement: the placements differ in the task's view, not in the search), the
        mast panned there, until a slot pair is seen standing; the site located from it
        (self.site). None once located, else why not."""
        centre = np.asarray(self.p['site_position'], float)
        normal = np.asarray(self.p['site_normal'], float)
        normal = normal / np.linalg.norm(normal)
        hw = self.p['site_search_m']
        points = search_points(centre, normal, half_width_m=hw,
                               spacing_m=self.p['search_spacing_m'])
        last = ''
        for target in points[:self.p['max_search_views']]:
            where = await self._choose_pose(goal, site=target, normal=normal,
                                            sigma=0.5 * self.p['search_spacing_m'], best=True)
            failed = await self._place(handle, where)
            if handle.is_cancel_requested:
                return 'canceled while looking for the slot'
            if failed:
                last = failed
                self.get_logger().info(f'looking for the slot at {np.round(target, 2).tolist()}'
                                       f': {failed}')
                continue
            self.search_views += 1
            if await self._look_around(handle):
                self.site = self.site_seen.pose
                self.get_logger().info(
                    f'slot located from view {self.search_views} at '
                    f'{np.round(self.site[:3, 3], 3).tolist()} ({len(self.site_seen)} frames, '
                    f'spread {1e3 * self.site_seen.spread_m:.1f} mm)')
                return None
            if handle.is_cancel_requested:
                return 'canceled while looking for the slot'
        return (f'slot not found: no slot pair seen from {self.search_views} views over the '
                f'region {hw:g} m either side of ({centre[0]:.2f}, {centre[1]:.2f})'
                + (f' (last: {last})' if last else ''))

    async def _place(self, handle, where) -> str | None:
        """Drive the rover to the camera pose `where` and tilt its mast; the reason on failure."""
        if isinstance(where, str):
            return where
        xy, yaw, pitch, how = where
        self._slot = None
        self.site_seen.clear()
        self._stood_t = math.inf
        try:
            mount = camera_mount(xy, yaw, pitch)
        except ReachError as exc:
            return f'camera pose out of reach: {exc}'
        self.get_logger().info(f'placing the camera ({how}): base at ({mount.base_xy[0]:.2f}, '
                               f'{mount.base_xy[1]:.2f}) heading {mount.base_yaw:.2f}, '
                               f'tilt {mount.tilt:.2f}')
        self._tilt = mount.tilt
        self._command_mast(0.0, mount.tilt)
        self._drive = GoToPose(mount.base_xy, mount.base_yaw,
                               max_speed_m_s=self.p['max_speed_m_s'])
        started = self._now_s()
        try:
            while self._drive is not None:
                await self._sleep_until_wake()
                if handle.is_cancel_requested:
                    return 'canceled while placing the camera'
                if self._now_s() - started > self.p['place_timeout_s']:
                    return f'timed out placing the camera ({self.p["place_timeout_s"]:g} s)'
        finally:
            self._drive = None
            self._slot = None
            self.pub_cmd.publish(Twist())
        if not await self._mast_at(handle, 0.0, mount.tilt):
            return 'canceled while placing the camera'
        return None

    def _task_target(self, site: np.ndarray | None = None, card: np.ndarray | None = None
                     ) -> np.ndarray:
        """The task view's primary target (map, this rover's frame): view_target_offset_m from
        `site` (by default the located one), or half-way from there to `card` (the card's last
        fix)."""
        if site is None:
            assert self.site is not None
            site = self.site[:3, 3]
        target = np.asarray(site, float) + np.asarray(self.p['view_target_offset_m'], float)
        return target if card is None else 0.5 * (target + card)

    async def _aim(self, handle, target: np.ndarray) -> str | None:
        """Turn the mast to put `target` on the camera's axis from where the rover stands (by
        its odometry, the frame the site was located in); the reason when it cannot."""
        if self.odom is None:
            return 'no odometry to aim the mast from'
        try:
            pan, tilt = mast_aim(*self.odom, target)
        except ReachError as exc:
            return f'the mast cannot aim at the task target: {exc}'
        self.get_logger().info(f"the mast aimed at the task's target from where the camera "
                               f'stands: pan {pan:.2f}, tilt {tilt:.2f}')
        self._tilt = tilt
        self._command_mast(pan, tilt)
        if not await self._mast_at(handle, pan, tilt):
            return 'canceled while aiming the camera'
        return None

    def _command_mast(self, pan: float, tilt: float) -> None:
        cmd = JointTrajectory(joint_names=list(MAST_JOINTS))
        cmd.points = [JointTrajectoryPoint(positions=[float(pan), float(tilt)])]
        cmd.points[0].time_from_start.sec = 1
        self.pub_mast.publish(cmd)

    async def _mast_at(self, handle, pan: float, tilt: float) -> bool:
        """Wait until the mast's encoders read (pan, tilt) within MAST_TOLERANCE_RAD (or
        MAST_WAIT_S of the clock passed: a warning), then count frames as standing from that
        joint state's stamp on (the slot pair and the site seen so far dropped); False on a
        cancel."""
        self._stood_t = math.inf
        self._slot = None
        self.site_seen.clear()
        started = self._now_s()
        while max(abs(self.mast[0] - pan), abs(self.mast[1] - tilt)) > MAST_TOLERANCE_RAD:
            await self._sleep_until_wake()
            if handle.is_cancel_requested:
                return False
            if self._now_s() - started > MAST_WAIT_S:
                self.get_logger().warn(f'the mast reads ({self.mast[0]:.3f}, '
                                       f'{self.mast[1]:.3f}), not ({pan:.3f}, {tilt:.3f})')
                break
        self._stood_t = max(self._mast_t, self._arrived_t)
        return True

    async def _look_around(self, handle) -> bool:
        """From where the camera stands, look for the slot pair at each of search_pans_rad in
        turn (the mast at the tilt its placement commanded; frames counted once the encoders
        read the pan); True once seen (self._slot, self.site_seen)."""
        for pan in self.p['search_pans_rad']:
            if abs(pan - self.mast[0]) > MAST_TOLERANCE_RAD:
                self._stood_t = math.inf
                self._command_mast(pan, self._tilt)
                if not await self._mast_at(handle, pan, self._tilt):
                    return False
            if await self._see_slot(handle, self.p['search_look_s']):
                return True
            if handle.is_cancel_requested:
                return False
        return False

    def marker_range_m(self) -> float:
        """The farthest range at which the slot's markers span marker_min_diameter_px: the
        far limit of the task's depth of field, which the view planner's camera pose must keep
        the markers within (the primary target's offset from them taken off)."""
        li = self.info.get('left')
        if li is None or li.p[0] <= 0:
            raise InsertionError('no camera_info yet: the focal length sets the task range')
        return 2 * self.model.slot_marker_radius_m * li.p[0] / self.p['marker_min_diameter_px']

    async def _choose_pose(self, goal: Insert.Goal, *, site: np.ndarray | None = None,
                           normal: np.ndarray | None = None, sigma: float | None = None,
                           card: np.ndarray | None = None, closer: int = 0,
                           best: bool = False):
        """The camera pose (xy, yaw, pitch, how) or the reason there is none. Given: the goal's
        camera_pose. Optimal: the view planner's best for the primary target (in front of
        `site`, by default the located one; re-placing, half-way to the card's last fix) with
        the site's marked face as the secondary, within the range where the slot markers span
        marker_min_diameter_px and the incidence the detector handles; `closer` re-placements
        shrink that range by replace_range_factor each (the markers were not resolved from
        there); `sigma` the site's position uncertainty (by default target_sigma_m). Random: a
        pose drawn uniformly from the same request's feasible ones (the view planner draws
        it). `best`: the best pose whatever the placement (the search for the slot is the same
        for every placement: they differ in the task's view)."""
        if goal.placement == Insert.Goal.PLACEMENT_GIVEN:
            pose = goal.camera_pose
            if pose.header.frame_id not in ('', self.map_frame):
                return (f'camera_pose must be in the map frame {self.map_frame!r}, not '
                        f'{pose.header.frame_id!r}')
            try:
                return (*_optical_pose(pose.pose), 'given')
            except ValueError as exc:
                return f'camera_pose: {exc}'
        if site is None:
            if self.site is None:
                return 'the site is not located'
            site, normal = self.site[:3, 3], self.site[:3, 1]
        normal = np.asarray(normal, float) / np.linalg.norm(normal)
        sigma = self.p['target_sigma_m'] if sigma is None else float(sigma)
        if not self.task_view.wait_for_service(timeout_sec=10.0):
            return 'no viewplan/task_view service'
        offset = np.asarray(self.p['view_target_offset_m'], float)
        try:
            far = self.marker_range_m() * self.p['replace_range_factor'] ** closer - \
                float(np.linalg.norm(offset))
        except InsertionError as exc:
            return str(exc)
        if far <= 0:
            return (f'the slot markers are below {self.p["marker_min_diameter_px"]:g} px '
                    'from every camera pose')
        optimal = best or goal.placement == Insert.Goal.PLACEMENT_OPTIMAL
        req = TaskView.Request(robot=self.p['rover'], tolerance=0.1, far_m=far,
                               max_incidence_deg=float(self.p['marker_max_incidence_deg']),
                               choose=(TaskView.Request.CHOOSE_BEST if optimal
                                       else TaskView.Request.CHOOSE_RANDOM),
                               seed=0 if optimal else int(self.rng.integers(2**32)))
        t = TaskTarget()
        t.header.frame_id = self.map_frame
        target = self._task_target(site, card)
        t.position.x, t.position.y, t.position.z = (float(v) for v in target)
        t.normal.x, t.normal.y, t.normal.z = (float(v) for v in normal)
        t.radius_m = self.p['target_radius_m']
        t.position_sigma_m = sigma
        t.weight = 1.0
        req.primary = t
        sec = TaskTarget()
        sec.header.frame_id = self.map_frame
        sec.position.x, sec.position.y, sec.position.z = (float(v) for v in site)
        sec.normal = t.normal
        sec.radius_m = self.p['target_radius_m']
        sec.position_sigma_m = sigma
        sec.weight = self.p['secondary_weight']
        req.secondary = [sec]
        resp = await self.ls.hold(self.task_view.call_async(req))
        if not resp.success:
            return f'task_view: {resp.message}'
        self.pub_placement.publish(resp.best)
        return (*_optical_pose(resp.best.pose.pose),
                f'{"optimal" if optimal else "random"}, {resp.message}')


def _pose_stamped(t: np.ndarray, frame: str) -> PoseStamped:
    """A level 4x4 pose in the map (frame `frame`) as a PoseStamped (its heading about z)."""
    msg = PoseStamped()
    msg.header.frame_id = frame
    h = math.atan2(t[1, 0], t[0, 0])
    msg.pose.position.x, msg.pose.position.y, msg.pose.position.z = (float(v) for v in t[:3, 3])
    msg.pose.orientation.z, msg.pose.orientation.w = math.sin(h / 2), math.cos(h / 2)
    return msg


def _optical_pose(pose) -> tuple[np.ndarray, float, float]:
    """(xy, yaw, pitch) of a left optical frame's pose (its z the viewing direction)."""
    q = pose.orientation
    yaw, pitch = yaw_pitch_from_optical(np.array([q.x, q.y, q.z, q.w]))
    return np.array([pose.position.x, pose.position.y]), wrap(yaw), pitch


def main(args: list[str] | None = None) -> int:
    """`ros2 run coop_insertion master`."""
    return run_node(MasterNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
