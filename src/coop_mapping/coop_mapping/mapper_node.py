"""Node `mapper` (one per team): fuses every rover's stereo clouds into one VoxelMap.

Subscribes, per rover name r in the `rovers` parameter: `<r>/stereo/points` (PointCloud2 in
the map frame with the covariance fields, sensor QoS) and `<r>/camera_pose`
(PoseWithCovarianceStamped, the pose the cloud was taken from, matched by stamp; its position is
the ray origin). Publishes `map/voxels` (coop_msgs/VoxelMap, latched, at most every
`publish_period_s`), `map/updates` (coop_msgs/VoxelMapUpdate per fused cloud), `map/occupied`
(PointCloud2 of occupied voxel centres, latched), `map/surface` (PointCloud2 of the occupied
voxels' surface points, `VoxelMap.surface_points`: sub-voxel, computed only while somebody
subscribes, latched) and `map/grid` (nav_msgs/OccupancyGrid slice at `grid_z_m`, latched).
With `map_input` `contributions` it subscribes `<r>/map_contribution`
(coop_msgs/MapContribution, made by each rover's stereo node from its cloud: what crosses a
field radio) instead, fuses each (source, session, sequence) once (the map's ledger) and
reports a rover silent for `silent_after_s`.
Before fusing a cloud it drops the points inside the body volume of its own rover and of every
teammate whose camera pose it holds (`bodies.BodyFilter`: `body_radius_m` about each camera,
0 = off). Services `map/save`, `map/load` (coop_msgs/srv/MapFile),
`map/query` (coop_msgs/srv/QueryMap), `map/reset` (std_srvs/Trigger). Autosaves every
`autosave_period_s` to `map_file`, and once more when it stops cleanly (Ctrl-C, SIGTERM,
shutdown), and loads it at start if it is there.
"""
from __future__ import annotations

import enum
import os
import time
from collections import Counter, OrderedDict, deque

import numpy as np
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import OccupancyGrid
from rclpy.clock import Clock, ClockType
from rclpy.exceptions import InvalidTopicNameException
from rclpy.node import Node
from rclpy.validate_full_topic_name import validate_full_topic_name
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import Header
from std_srvs.srv import Trigger

from coop_common.frames import FRAME_PARAMS, check_frame_params
from coop_common.node_util import BadInputCounter, ParamSpec, declare_parameters, run_node
from coop_common.qos import (
    COMMAND_QOS,
    CONTRIBUTION_QOS,
    LATCHED_QOS,
    SENSOR_QOS,
    overridable,
    with_depth,
)
from coop_common.seqgaps import SequenceGaps
from coop_msgs.msg import MapContribution, VoxelMapUpdate
from coop_msgs.msg import VoxelMap as VoxelMapMsg
from coop_msgs.srv import MapFile, QueryMap

from .bodies import BodyFilter
from .contribution import ContributionFormatError, drop_voxels
from .ledger import Admission
from .offline import stamp_ns
from .ordering import OrderedFusion
from .ros_conv import CloudFormatError, cloud_to_msg, msg_to_cloud, msg_to_contribution, voxelset
from .voxelmap import (
    Contribution,
    MapFileError,
    MapInputError,
    ScanLimits,
    ScanRejected,
    VoxelMap,
    unpack_keys,
)

#: late scans wait for their rebuild until none has come for this long (s) ...
SETTLE_QUIET_S = 0.5
#: ... or the first of them has waited this long (s)
SETTLE_MAX_WAIT_S = 5.0


class MapInput(enum.Enum):
    """What the mapper fuses (`map_input`)."""

    CLOUDS = 'clouds'                  # <rover>/stereo/points + <rover>/camera_pose
    CONTRIBUTIONS = 'contributions'    # <rover>/map_contribution


PARAMS = {
    'rovers': ParamSpec(['rover1', 'rover2'], 'rover namespaces whose clouds are fused',
                        read_only=True),
    'map_input': ParamSpec(MapInput.CLOUDS.value, "what is fused: each rover's stereo clouds, "
                           "or the contributions its stereo node makes from them (`contribute`:"
                           ' a field radio carries those)', choices=[m.value for m in MapInput],
                           read_only=True),
    'contribution_history': ParamSpec(CONTRIBUTION_QOS.depth, 'contributions queued per rover '
                                      '(a rejoining link delivers its backlog at once)', lo=1,
                                      hi=100_000, read_only=True),
    'reorder_horizon_s': ParamSpec(30.0, 'scans up to this late (stamp time: a link that was '
                                   'cut) are fused in their stamp order, by rebuilding the map '
                                   'from a checkpoint (coop_mapping.ordering; 0 = in arrival '
                                   'order)', lo=0.0, hi=3600.0, read_only=True),
    'reorder_late_s': ParamSpec(1.0, 'a scan this far behind the newest fused one is late; '
                                'closer ones are fused as they come', lo=0.0, hi=60.0,
                                read_only=True),
    'reorder_checkpoint_s': ParamSpec(5.0, 'a copy of the map every this much stamp time '
                                      '(where a rebuild starts)', lo=0.01, hi=600.0,
                                      read_only=True),
    'silent_after_s': ParamSpec(30.0, 'a rover that has sent nothing for this long is reported '
                                '(wall time; 0 = never)', lo=0.0, hi=86400.0),
    'resolution_m': ParamSpec(0.1, 'voxel edge (m)', lo=0.005, hi=10.0, read_only=True),
    'map_frame': ParamSpec('map', 'common frame of clouds and map, after frame_prefix',
                           read_only=True),
    'frame_prefix': FRAME_PARAMS['frame_prefix'],
    'map_file': ParamSpec('', 'autosave / default save-load file ("" = no autosave)',
                          read_only=True),
    'autosave_period_s': ParamSpec(30.0, 'autosave period (0 = off)', lo=0.0, hi=86400.0),
    'publish_period_s': ParamSpec(1.0, 'minimum period of full-map publications', lo=0.0,
                                  hi=3600.0),
    'max_points': ParamSpec(1_000_000, 'clouds with more points are rejected', lo=1,
                            hi=50_000_000),
    'max_range_m': ParamSpec(30.0, 'clouds with a point farther from the camera are rejected',
                             lo=0.1, hi=1000.0),
    'ray_subdivision': ParamSpec(4, 'rays per end voxel edge (0 = one ray per point)', lo=0,
                                 hi=16, read_only=True),
    'grid_z_m': ParamSpec(0.2, 'height of the OccupancyGrid slice (m)', lo=-1000.0, hi=1000.0),
    'pose_wait_s': ParamSpec(1.0, 'how long a cloud waits for its camera pose', lo=0.0,
                             hi=60.0),
    'body_radius_m': ParamSpec(BodyFilter.radius_m, "rover body volume's horizontal radius "
                               'about each camera; its points are not fused (0 = off)',
                               lo=0.0, hi=10.0),
    'body_above_camera_m': ParamSpec(BodyFilter.above_camera_m,
                                     "the body volume's top over the camera (m)", lo=0.0,
                                     hi=10.0),
    'body_pose_tolerance_s': ParamSpec(BodyFilter.pose_tolerance_s, "how old a teammate's "
                                       'camera pose may be, before the cloud, to filter its '
                                       'body', lo=0.0, hi=600.0),
}


def _check_params(p: dict) -> str | None:
    """Rover names: each a namespace its topics can live under, none twice (a rover listed
    twice would have every cloud fused twice); a map frame."""
    if not p['map_frame']:
        return 'map_frame must not be empty'
    if why := check_frame_params(p):
        return why
    rovers = list(p['rovers'])
    if len(set(rovers)) != len(rovers):
        return f'rovers {rovers}: a name is listed twice'
    for r in rovers:
        try:
            validate_full_topic_name(f'/{r}/stereo/points')
        except InvalidTopicNameException as exc:
            return f'rovers: {r!r} is not a namespace ({str(exc).splitlines()[0]})'
    return None


def _free_name(path: str) -> str:
    """path, or path.1, path.2, ... : the first that does not exist."""
    name, i = path, 0
    while os.path.exists(name):
        i += 1
        name = f'{path}.{i}'
    return name


class MapperNode(Node):
    """The mapper: fuses the rovers' stereo clouds into the team's voxel map and serves it."""

    def __init__(self, **kwargs) -> None:
        super().__init__('mapper', **kwargs)
        self.p = declare_parameters(self, PARAMS, on_change=self.p_update,
                                    check_all=_check_params)
        self.map_frame = self.p['frame_prefix'] + self.p['map_frame']
        self.bad = BadInputCounter(self)
        # what map_file holds, as (map generation, sequence): a reset or a load starts a new
        # generation (its sequence may come back to the one saved: a reset starts at 0)
        self._generation = 0
        self._saved = (0, 0)
        self.fusion = self._fusion(VoxelMap(self.p['resolution_m'],
                                            max_points=self.p['max_points'],
                                            ray_subdivision=self.p['ray_subdivision']))
        self._load_at_start()
        self.pub_map = self.create_publisher(VoxelMapMsg, 'map/voxels', LATCHED_QOS)
        self.pub_upd = self.create_publisher(VoxelMapUpdate, 'map/updates', COMMAND_QOS)
        self.pub_occ = self.create_publisher(PointCloud2, 'map/occupied', LATCHED_QOS)
        self.pub_grid = self.create_publisher(OccupancyGrid, 'map/grid', LATCHED_QOS)
        self.pub_surf = self.create_publisher(PointCloud2, 'map/surface', LATCHED_QOS)
        self._surface_dirty = True
        self.poses: dict[str, OrderedDict[int, np.ndarray]] = {}
        self.pending: dict[str, OrderedDict[int, tuple[PointCloud2, float]]] = {}
        self.input = MapInput(self.p['map_input'])
        self.last_heard: dict[str, float] = {}     # rover -> monotonic time of its last input
        self._reported_silent: set[str] = set()
        for r in self.p['rovers']:
            self.poses[r] = OrderedDict()
            self.pending[r] = OrderedDict()
            if self.input is MapInput.CONTRIBUTIONS:
                self.create_subscription(
                    MapContribution, f'{r}/map_contribution',
                    lambda m, info, r=r: self.on_contribution(r, m, info),
                    with_depth(CONTRIBUTION_QOS, self.p['contribution_history']))
                continue
            # both may be overridden (qos_overrides.<topic>.subscription.<policy>), as the
            # stereo node's publishers, for a pipeline that must not drop a cloud
            self.create_subscription(PointCloud2, f'{r}/stereo/points',
                                     lambda m, info, r=r: self.on_cloud(r, m, info),
                                     **overridable(SENSOR_QOS))
            # latched (a late mapper gets the last pose) but a stream of one pose per
            # cloud: a queue, so a busy callback does not lose the pose of a cloud
            self.create_subscription(PoseWithCovarianceStamped, f'{r}/camera_pose',
                                     lambda m, r=r: self.on_pose(r, m),
                                     **overridable(with_depth(LATCHED_QOS, 10)))
        self.create_service(MapFile, 'map/save', self.srv_save)
        self.create_service(MapFile, 'map/load', self.srv_load)
        self.create_service(QueryMap, 'map/query', self.srv_query)
        self.create_service(Trigger, 'map/reset', self.srv_reset)
        self._last_pub = -np.inf
        self._dirty = True
        # wall-clock timer: publishing, pose timeouts and autosave are wall-time duties (their
        # periods are measured with time.monotonic); with use_sim_time a timer on the ROS clock
        # stops when /clock does (a paused sim, the end of a replayed bag) and the last clouds
        # fused would never be published
        self.create_timer(0.1, self.on_timer, clock=Clock(clock_type=ClockType.STEADY_TIME))
        self._last_save = time.monotonic()
        self.fused = 0
        self._late_since = self._late_last = 0.0     # monotonic times of the waiting late scans
        #: clouds per rover the middleware dropped before they reached this node
        self.cloud_gaps = SequenceGaps()
        #: seconds from a contribution's publication on its rover to its update of the map
        self.link_latency_s: deque[float] = deque(maxlen=10_000)
        self.body_points = 0
        self.last_latency_s = float('nan')
        self.get_logger().info(
            f'mapper up: rovers {self.p["rovers"]}, {self.p["resolution_m"]} m voxels, '
            f'{len(self.map)} voxels loaded')

    @property
    def map(self) -> VoxelMap:
        """The team's map (a rebuild replaces the object: never keep it)."""
        return self.fusion.map

    def _fusion(self, vm: VoxelMap) -> OrderedFusion:
        return OrderedFusion(vm, horizon_s=self.p['reorder_horizon_s'],
                             late_s=self.p['reorder_late_s'],
                             checkpoint_s=self.p['reorder_checkpoint_s'])

    def p_update(self, changed: dict) -> None:
        self.p.update(changed)
        self.map.max_points = self.p['max_points']

    # ---------------------------------------------------------------- start / persistence
    def _load_at_start(self) -> None:
        """The last save, if map_file holds one. One it cannot take (corrupt, another version
        or resolution) is moved aside, never overwritten by the next autosave."""
        path = self.p['map_file']
        if not path or not os.path.exists(path):
            return
        if not os.path.isfile(path):
            raise ValueError(f'map_file {path} is not a file')
        try:
            self._adopt(self._read(path))
            self._saved = (self._generation, self.map.sequence)
        except MapFileError as exc:
            aside = _free_name(f'{path}.refused')
            try:
                os.replace(path, aside)
                kept = f'moved to {aside}'
            except OSError as mv:
                kept = f'could not move it aside ({mv}): autosave off'
                self.p['autosave_period_s'] = 0.0
            self.get_logger().error(f'not loading the last save: {exc}; {kept}')
            return
        self.get_logger().info(f'loaded {len(self.map)} voxels (sequence {self.map.sequence}) '
                               f'from {path}')

    def _read(self, path: str) -> VoxelMap:
        m = VoxelMap.load(path)
        if m.resolution != self.p['resolution_m']:
            raise MapFileError(f'{path}: resolution {m.resolution} differs from the '
                               f"node's {self.p['resolution_m']}")
        return m

    def _adopt(self, m: VoxelMap) -> None:
        m.max_points = self.p['max_points']
        m.ray_subdivision = self.p['ray_subdivision']
        self.fusion = self._fusion(m)
        self._generation += 1

    @property
    def unsaved(self) -> bool:
        """Whether the map differs from what map_file holds (or would hold: an empty map
        where there is no file)."""
        return (self._generation, self.map.sequence) != self._saved

    # ---------------------------------------------------------------- inputs
    def on_pose(self, rover: str, msg: PoseWithCovarianceStamped) -> None:
        if msg.header.frame_id != self.map_frame:
            self.bad.reject('pose_frame', f'{rover}: frame {msg.header.frame_id!r}')
            return
        p = msg.pose.pose.position
        origin = np.array([p.x, p.y, p.z])
        if not np.all(np.isfinite(origin)):
            self.bad.reject('pose_nan', rover)
            return
        st = stamp_ns(msg.header.stamp)
        poses = self.poses[rover]
        poses[st] = origin
        while len(poses) > 50:
            poses.popitem(last=False)
        cloud = self.pending[rover].pop(st, None)
        if cloud is not None:
            self.fuse(rover, cloud[0], origin, cloud[1])

    def on_cloud(self, rover: str, msg: PointCloud2, info: dict | None = None) -> None:
        """A rover's cloud (best effort): fused once its camera pose is there. Clouds the
        middleware dropped are counted from the writer's sequence numbers (`info`)."""
        t_arrival = time.monotonic()
        self.last_heard[rover] = t_arrival
        if info and info.get('publication_sequence_number') is not None:
            self._count_missed(rover, int(info['publication_sequence_number']))
        if msg.header.frame_id != self.map_frame:
            self.bad.reject('unknown_frame', f'{rover}: frame {msg.header.frame_id!r}')
            return
        st = stamp_ns(msg.header.stamp)
        origin = self.poses[rover].get(st)
        if origin is None:
            pend = self.pending[rover]
            pend[st] = (msg, t_arrival)
            while len(pend) > 5:
                pend.popitem(last=False)
                self.bad.reject('no_pose', f'{rover}: cloud without a camera pose')
            return
        self.fuse(rover, msg, origin, t_arrival)

    def fuse(self, rover: str, msg: PointCloud2, origin: np.ndarray, t_arrival: float) -> None:
        limits = ScanLimits(self.p['max_points'], self.p['max_range_m'])
        try:
            limits.check_count(msg.width * msg.height)     # before decoding it
            pts, cov = msg_to_cloud(msg)
            limits.check(pts, cov, origin)
        except CloudFormatError as exc:
            self.bad.reject('format', f'{rover}: {exc}')
            return
        except ScanRejected as exc:
            self.bad.reject(exc.reason, f'{rover}: {exc}')
            return
        bodies = BodyFilter(self.p['body_radius_m'], self.p['body_above_camera_m'],
                            self.p['body_pose_tolerance_s'])
        if bodies.enabled:
            cams = bodies.cameras_at(stamp_ns(msg.header.stamp), origin,
                                     [self.poses[r] for r in self.poses if r != rover])
            pts, cov, dropped = bodies.drop(pts, cov, cams)
            if len(pts) == 0:
                self.bad.reject('body_only', f'{rover}: every point on a rover body')
                return
            self.body_points += dropped
        try:
            c = self.map.contribution(pts, origin, covariances=cov)
        except MapInputError as exc:
            self.bad.reject('map_input', f'{rover}: {exc}')
            return
        self._fuse(rover, msg.header.stamp, c, t_arrival)

    def _count_missed(self, rover: str, seq: int) -> None:
        """Clouds of `rover` the middleware never delivered: the gaps in its writer's
        sequence numbers (coop_common.seqgaps; a restarted stereo node starts again)."""
        self.cloud_gaps.seen(rover, seq)

    @property
    def cloud_seq(self) -> dict:
        return self.cloud_gaps.last

    @property
    def clouds_missed(self) -> Counter:
        return self.cloud_gaps.missed

    def _fuse(self, rover: str, stamp, c: Contribution, t_arrival: float,
              source_ns: int | None = None) -> None:
        """Into the map in stamp order (`fusion`): now, or at the next settle if late.
        `source_ns`: when the rover published it (wall clock), for the link latency."""
        base = self.map.sequence
        f = self.fusion.add(c, stamp_ns=stamp_ns(stamp), source=rover)
        if f.beyond_horizon:
            self.bad.reject('beyond_horizon', f'{rover}: a scan older than reorder_horizon_s, '
                            'fused at the end')
        if f.result is None:
            now = time.monotonic()
            self._late_since = self._late_since or now
            self._late_last = now
            return
        self._publish_update(rover, stamp, base, f.result.changed)
        if source_ns is not None:
            # from the rover's publish to the map's update: the link and the fusion (wall
            # clocks: the rovers' and the base's must be synchronised, e.g. by chrony)
            self.link_latency_s.append(1e-9 * (time.time_ns() - source_ns))
        self.last_latency_s = time.monotonic() - t_arrival
        self.get_logger().debug(f'{rover}: {f.result.n_points} points, {f.result.n_new} new '
                                f'voxels, {1e3 * self.last_latency_s:.1f} ms')

    def _publish_update(self, source: str, stamp, base: int, changed: np.ndarray) -> None:
        upd = VoxelMapUpdate()
        upd.header = Header(stamp=stamp, frame_id=self.map_frame)
        upd.resolution_m = self.map.resolution
        upd.base_sequence = base
        upd.sequence = self.map.sequence
        upd.source = source
        upd.changed = voxelset(self.map, changed)
        self.pub_upd.publish(upd)
        self.fused += self.map.sequence - base
        self._dirty = True

    def _settle(self, *, now: float | None = None) -> None:
        """Late scans into their place: one rebuild for all that came since the last. From the
        timer (`now` given), once the backlog has stopped coming for SETTLE_QUIET_S or the
        first late scan has waited SETTLE_MAX_WAIT_S: a link that comes back delivers it one
        scan at a time, and each rebuild fuses the whole journal after its place again."""
        if not self.fusion.pending:
            return
        if now is not None and now - self._late_last < SETTLE_QUIET_S and \
                now - self._late_since < SETTLE_MAX_WAIT_S:
            return
        self._late_since = self._late_last = 0.0
        base, t0 = self.map.sequence, time.monotonic()
        changed = self.fusion.settle()
        if changed is None:
            return
        self._publish_update('', self.get_clock().now().to_msg(), base, changed)
        self.get_logger().info(f'{self.map.sequence - base} late scans put in their stamp '
                               f'order: map rebuilt in {time.monotonic() - t0:.2f} s')

    def on_contribution(self, rover: str, msg: MapContribution, info: dict | None = None
                        ) -> None:
        """A scan made into a contribution on the rover: checked, fused once (the map's
        ledger), without the voxels inside a teammate's body (this rover's own body left it
        on the rover). `info`: rclpy's message info (the writer's source timestamp gives the
        link latency)."""
        t_arrival = time.monotonic()
        self.last_heard[rover] = t_arrival
        if msg.header.frame_id != self.map_frame:
            self.bad.reject('unknown_frame', f'{rover}: frame {msg.header.frame_id!r}')
            return
        if msg.source != rover:
            self.bad.reject('source', f'{rover}/map_contribution from {msg.source!r}')
            return
        try:
            c = msg_to_contribution(msg, self.map)
        except ContributionFormatError as exc:
            self.bad.reject('format', f'{rover}: {exc}')
            return
        adm = self.map.ledger.admit(rover, msg.session, msg.sequence)
        if adm is not Admission.NEW:
            # a resent backlog or a replay after a restart: counted, never fused twice
            self.bad.reject(adm.value, f'{rover}: session {msg.session} sequence '
                            f'{msg.sequence}')
            return
        st = stamp_ns(msg.header.stamp)
        poses = self.poses[rover]
        poses[st] = c.origin
        while len(poses) > 50:
            poses.popitem(last=False)
        c = self._without_teammates(rover, st, c)
        self._fuse(rover, msg.header.stamp, c, t_arrival,
                   int(info['source_timestamp']) if info else None)

    def _without_teammates(self, rover: str, stamp: int, c: Contribution) -> Contribution:
        bodies = BodyFilter(self.p['body_radius_m'], self.p['body_above_camera_m'],
                            self.p['body_pose_tolerance_s'])
        if not bodies.enabled or len(c.keys) == 0:
            return c
        cams = bodies.cameras_at(stamp, c.origin,
                                 [self.poses[r] for r in self.poses if r != rover])[1:]
        if not cams:
            return c
        centres = (unpack_keys(c.keys) + 0.5) * self.map.resolution
        c, dropped = drop_voxels(c, bodies.mask(centres, cams))
        self.body_points += dropped
        return c

    # ---------------------------------------------------------------- outputs
    def publish_map(self) -> None:
        now = self.get_clock().now().to_msg()
        hdr = Header(stamp=now, frame_id=self.map_frame)
        m = VoxelMapMsg()
        m.header = hdr
        m.resolution_m = self.map.resolution
        m.sequence = self.map.sequence
        m.voxels = voxelset(self.map)
        names = sorted(self.map.contributions)
        m.contributors = names
        m.contributions = [int(self.map.contributions[n]) for n in names]
        self.pub_map.publish(m)
        self.pub_occ.publish(cloud_to_msg(self.map.occupied_centres(), None, hdr))
        origin, grid = self.map.slice_grid(self.p['grid_z_m'])
        g = OccupancyGrid()
        g.header = hdr
        g.info.resolution = float(self.map.resolution)
        g.info.width = int(grid.shape[1])
        g.info.height = int(grid.shape[0])
        g.info.origin.position.x = float(origin[0])
        g.info.origin.position.y = float(origin[1])
        g.info.origin.position.z = float(self.p['grid_z_m'])
        g.info.origin.orientation.w = 1.0
        g.data = grid.reshape(-1).tolist()
        self.pub_grid.publish(g)
        self._dirty = False
        self._last_pub = time.monotonic()
        self._surface_dirty = True
        self.publish_surface()

    def publish_surface(self) -> None:
        """The occupied voxels' surface points, if the map changed since the last ones and
        somebody listens (the kernel query costs ~7 us per occupied voxel, ~0.2 s for the
        demo's 28,000: not spent for nobody)."""
        if not self._surface_dirty or self.pub_surf.get_subscription_count() == 0:
            return
        _, pts = self.map.surface_points(self.map.occupied_keys())
        hdr = Header(stamp=self.get_clock().now().to_msg(), frame_id=self.map_frame)
        self.pub_surf.publish(cloud_to_msg(pts, None, hdr))
        self._surface_dirty = False

    def on_timer(self) -> None:
        now = time.monotonic()
        self._settle(now=now)
        if self._dirty and now - self._last_pub >= self.p['publish_period_s']:
            self.publish_map()
        elif not self._dirty:
            self.publish_surface()      # a subscriber that came after the last publication
        # clouds whose pose never came
        for rover, pend in self.pending.items():
            for st in [s for s, (_, t) in pend.items() if now - t > self.p['pose_wait_s']]:
                del pend[st]
                self.bad.reject('no_pose', f'{rover}: cloud without a camera pose')
        self._report_silent(now)
        per = self.p['autosave_period_s']
        if per > 0 and self.p['map_file'] and now - self._last_save >= per:
            self._last_save = now
            if self.unsaved:
                self._save(self.p['map_file'])

    def _report_silent(self, now: float) -> None:
        """A rover heard from before and silent for silent_after_s: said once (and once
        more when it is back); the map keeps what it sent."""
        limit = self.p['silent_after_s']
        for rover, t in self.last_heard.items():
            silent = limit > 0 and now - t > limit
            if silent and rover not in self._reported_silent:
                self._reported_silent.add(rover)
                self.get_logger().warn(
                    f'{rover}: nothing for {now - t:.0f} s; the map keeps its '
                    f'{self.map.contributions[rover]} scans, {self.map.ledger.missing(rover)} '
                    f'of its contributions missing, {self.clouds_missed[rover]} clouds dropped '
                    'so far')
            elif not silent and rover in self._reported_silent:
                self._reported_silent.discard(rover)
                self.get_logger().info(f'{rover}: heard again')

    def _save(self, path: str) -> str | None:
        self._settle()              # late scans waiting for their place go in first
        try:
            self.map.save(path)
        except OSError as exc:
            self.get_logger().error(f'save to {path} failed: {exc}')
            return str(exc)
        if self._is_map_file(path):
            self._saved = (self._generation, self.map.sequence)
        self.get_logger().info(f'saved {len(self.map)} voxels to {path} ({self.body_points} '
                               'points on rover bodies not fused so far)')
        return None

    def destroy_node(self) -> None:
        """A clean stop saves what the last autosave does not hold (with autosave on), so a
        restart loses nothing; a killed mapper loses what came after its last autosave."""
        self.fusion.settle()
        if self.clouds_missed:
            self.get_logger().info(f'clouds the middleware dropped: {dict(self.clouds_missed)}')
        if self.link_latency_s:
            lat = 1e3 * np.asarray(self.link_latency_s)
            self.get_logger().info(
                f'contributions fused at once: {len(lat)}, from publication to map update '
                f'p50 {np.percentile(lat, 50):.1f} ms, p99 {np.percentile(lat, 99):.1f} ms; '
                f'{self.fusion.rebuilds} rebuilds for late ones; skipped: '
                f'{dict(self.bad.counts)}')
        if self.p['autosave_period_s'] > 0 and self.p['map_file'] and self.unsaved:
            self._save(self.p['map_file'])
        super().destroy_node()

    def _is_map_file(self, path: str) -> bool:
        return bool(self.p['map_file']) and \
            os.path.realpath(path) == os.path.realpath(self.p['map_file'])

    # ---------------------------------------------------------------- services
    def srv_save(self, req, resp):
        path = req.path or self.p['map_file']
        if not path:
            resp.success, resp.message = False, 'no path given and no map_file parameter'
            return resp
        err = self._save(path)
        resp.success = err is None
        resp.message = err or f'saved to {path}'
        resp.voxels, resp.sequence = len(self.map), self.map.sequence
        return resp

    def srv_load(self, req, resp):
        path = req.path or self.p['map_file']
        try:
            m = self._read(path)
        except MapFileError as exc:
            resp.success, resp.message = False, f'{exc} (current map kept)'
            resp.voxels, resp.sequence = len(self.map), self.map.sequence
            self.get_logger().warn(resp.message)
            return resp
        self._adopt(m)
        self._dirty = True
        if self._is_map_file(path):
            self._saved = (self._generation, m.sequence)
        resp.success, resp.message = True, f'loaded {path}'
        resp.voxels, resp.sequence = len(m), m.sequence
        self.get_logger().info(resp.message)
        return resp

    def srv_query(self, req, resp):
        pts = np.array([[p.x, p.y, p.z] for p in req.points], float).reshape(-1, 3)
        if not np.all(np.isfinite(pts)):
            resp.success, resp.message = False, 'non-finite query point'
            return resp
        resp.occupancy = self.map.probability_at(pts).astype(np.float32).tolist() \
            if len(pts) else []
        lo = np.array([req.box_min.x, req.box_min.y, req.box_min.z])
        hi = np.array([req.box_max.x, req.box_max.y, req.box_max.z])
        if np.all(hi > lo):
            try:
                c = self.map.box_counts(lo, hi)
            except ValueError as exc:
                resp.success, resp.message = False, str(exc)
                return resp
            resp.box_unknown, resp.box_free, resp.box_occupied = (
                c['unknown'], c['free'], c['occupied'])
        resp.success = True
        return resp

    def srv_reset(self, req, resp):
        self._adopt(VoxelMap(self.map.resolution))
        self._dirty = True
        resp.success, resp.message = True, 'map cleared'
        self.get_logger().info('map reset')
        return resp


def main(args=None) -> int:
    """`ros2 run coop_mapping mapper`."""
    return run_node(MapperNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
