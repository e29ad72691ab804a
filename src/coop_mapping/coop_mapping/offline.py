"""Maps from recorded data without DDS: what the `stereo` nodes and the `mapper` compute, run on
a bag's messages with the same cores and the same defaults (no rclpy).

    from coop_mapping.offline import map_from_bag
    result = map_from_bag('bags/mapping_two_rovers')       # rovers found in the bag
    result.map, result.scans                               # VoxelMap, scans fused per rover

`build_map` takes any time-ordered (topic, message) stream (rosbags-deserialized or rclpy
messages alike). Frames are assembled as the stereo node does (left image, right image and
`stereo/pose` of one stamp, the latest camera_info of each side), each cloud goes through the
float32 PointCloud2 layout the node publishes, and scans are fused in stamp order with the
mapper's checks. `test/test_bag_replay.py` checks the nodes fed by `rover_bag play` give this map.
"""
from __future__ import annotations

import re
from collections import Counter, OrderedDict
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from coop_common.params import choice

from .bodies import BodyFilter
from .stereo import (
    FULL_WIDTH_DEFAULT,
    SUBPIXEL_DEFAULT,
    ErrorModel,
    StereoCamera,
    StereoError,
    StereoRanger,
    Subpixel,
)
from .voxelmap import MapInputError, ScanLimits, ScanRejected, VoxelMap

__all__ = [
    'MapSettings',
    'OfflineMap',
    'StereoFrame',
    'StereoSettings',
    'build_map',
    'frame_scan',
    'image_array',
    'map_from_bag',
    'stereo_frames',
    'stereo_topics',
]

_SIDES = ('left', 'right')
#: a rover's stereo topic in a bag: groups `rover` and `what`
STEREO_TOPIC = re.compile(r'^/(?P<rover>[^/]+)/stereo/(?P<what>left/image_raw|right/image_raw|'
                    r'left/camera_info|right/camera_info|pose)$')


@dataclass(frozen=True)
class StereoSettings:
    """The `stereo` node's ranging parameters (same names and defaults as its PARAMS)."""

    num_disparities: int = 64
    block_size: int = 5
    stride: int = 1
    min_range_m: float = 0.2
    max_range_m: float = 10.0
    sigma_disparity_px: float = 0.5
    error_T_lateral: float = 0.1    # noqa: N815 - the stereo node's parameter (Eq. 3-7's T)
    error_n: float = 2.0
    subpixel: Subpixel = SUBPIXEL_DEFAULT
    full_width: bool = FULL_WIDTH_DEFAULT

    def __post_init__(self) -> None:
        object.__setattr__(self, 'subpixel', choice(Subpixel, self.subpixel, 'subpixel',
                                                    error=StereoError))

    def ranger(self, left_p: Sequence[float] | np.ndarray, right_p: Sequence[float] | np.ndarray,
               width: int,
               height: int) -> StereoRanger:
        """The StereoRanger the node builds from a camera_info pair."""
        cam = StereoCamera.from_projection(np.asarray(left_p, float), np.asarray(right_p, float),
                                           int(width), int(height))
        em = ErrorModel.from_stereo(cam, sigma_d_px=self.sigma_disparity_px,
                                    lateral=self.error_T_lateral, n=self.error_n)
        return StereoRanger(cam, error_model=em, num_disparities=self.num_disparities,
                            block_size=self.block_size | 1, stride=self.stride,
                            min_range=self.min_range_m, max_range=self.max_range_m,
                            subpixel=self.subpixel, full_width=self.full_width)


@dataclass(frozen=True)
class MapSettings:
    """The `mapper` node's fusion parameters (same names and defaults as its PARAMS)."""

    resolution_m: float = 0.1
    max_points: int = 1_000_000
    max_range_m: float = 30.0
    ray_subdivision: int = 4
    body_radius_m: float = BodyFilter.radius_m
    body_above_camera_m: float = BodyFilter.above_camera_m
    body_pose_tolerance_s: float = BodyFilter.pose_tolerance_s

    def new_map(self) -> VoxelMap:
        return VoxelMap(self.resolution_m, max_points=self.max_points,
                        ray_subdivision=self.ray_subdivision)

    def limits(self) -> ScanLimits:
        """The mapper's input checks with these settings."""
        return ScanLimits(self.max_points, self.max_range_m)

    def body_filter(self) -> BodyFilter:
        return BodyFilter(self.body_radius_m, self.body_above_camera_m,
                          self.body_pose_tolerance_s)


@dataclass
class StereoFrame:
    """One complete stereo frame of one rover: images, the pose message, the camera infos."""

    rover: str
    stamp_ns: int
    left: Any
    right: Any
    pose: Any
    left_info: Any
    right_info: Any


@dataclass
class OfflineMap:
    """The map and what went into it."""

    map: VoxelMap
    scans: Counter = field(default_factory=Counter)      # fused scans per rover
    rejected: Counter = field(default_factory=Counter)   # reason -> count
    frames: list[tuple[str, int]] = field(default_factory=list)   # (rover, stamp) fused
    body_points: int = 0                                 # points dropped as rover bodies


def stamp_ns(stamp: Any) -> int:
    """A builtin_interfaces/Time as integer nanoseconds (the nodes key frames by it too)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def image_array(msg: Any) -> np.ndarray:
    """mono8 Image (rclpy or rosbags message) -> (height, width) uint8."""
    if msg.encoding not in ('mono8', '8UC1'):
        raise StereoError(f'encoding {msg.encoding!r}, need mono8')
    data = np.frombuffer(bytes(msg.data), np.uint8) if not isinstance(msg.data, np.ndarray) \
        else np.asarray(msg.data, np.uint8).reshape(-1)
    if msg.step < msg.width or data.size < msg.step * msg.height:
        raise StereoError('image data shorter than step * height')
    return data[:msg.step * msg.height].reshape(msg.height, msg.step)[:, :msg.width].copy()


def stereo_topics(rovers: Iterable[str]) -> list[str]:
    """The bag topics the stereo nodes of `rovers` subscribe to."""
    return [f'/{r}/stereo/{w}' for r in rovers for w in (
        'left/image_raw', 'right/image_raw', 'left/camera_info', 'right/camera_info', 'pose')]


def stereo_frames(messages: Iterable[tuple[str, Any]], rovers: Iterable[str] | None = None,
                  *, buffer: int = 10) -> Iterator[StereoFrame]:
    """Complete frames from a time-ordered (topic, message) stream, as the stereo node pairs
    them: left, right and pose of one stamp; a completed frame drops older unmatched parts;
    each side's latest camera_info. A frame completed before any camera_info waits for it."""
    wanted = None if rovers is None else set(rovers)
    bufs: dict[str, dict[str, OrderedDict[int, Any]]] = {}
    infos: dict[str, dict[str, Any]] = {}
    waiting: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    for topic, msg in messages:
        m = STEREO_TOPIC.match(topic)
        if m is None or (wanted is not None and m['rover'] not in wanted):
            continue
        rover, what = m['rover'], m['what']
        info = infos.setdefault(rover, {})
        if what.endswith('camera_info'):
            info[what.split('/')[0]] = msg
            if len(info) == 2 and waiting.get(rover):
                for st, parts in waiting.pop(rover):
                    yield StereoFrame(rover, st, parts['left'], parts['right'], parts['pose'],
                                      info['left'], info['right'])
            continue
        kind = 'pose' if what == 'pose' else what.split('/')[0]
        b = bufs.setdefault(rover, {'left': OrderedDict(), 'right': OrderedDict(),
                                    'pose': OrderedDict()})
        st = stamp_ns(msg.header.stamp)
        b[kind][st] = msg
        while len(b[kind]) > buffer:
            b[kind].popitem(last=False)
        if all(st in b[k] for k in b):
            parts = {k: b[k].pop(st) for k in b}
            for k in b:
                for s in [s for s in b[k] if s < st]:
                    del b[k][s]
            if len(info) == 2:
                yield StereoFrame(rover, st, parts['left'], parts['right'], parts['pose'],
                                  info['left'], info['right'])
            else:
                waiting.setdefault(rover, []).append((st, parts))


def frame_scan(frame: StereoFrame, settings: StereoSettings = StereoSettings(), *,
               ranger: StereoRanger | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One frame -> (points (N, 3), covariances (N, 6), camera origin (3,)) in the map frame,
    points and covariances rounded through float32 as in the node's PointCloud2."""
    from .ros_conv import pose_to_rt  # noqa: PLC0415 - message types only, not needed above

    li, ri = frame.left_info, frame.right_info
    if ranger is None:
        ranger = settings.ranger(li.p, ri.p, li.width, li.height)
    R, t = pose_to_rt(frame.pose.pose.pose)
    scan = ranger.process(image_array(frame.left), image_array(frame.right), R, t)
    pts = scan.points.astype(np.float32).astype(np.float64)
    cov = scan.covariances.astype(np.float32).astype(np.float64)
    return pts, cov, np.asarray(t, float)


def build_map(messages: Iterable[tuple[str, Any]], rovers: Iterable[str] | None = None, *,
              stereo: StereoSettings = StereoSettings(), mapping: MapSettings = MapSettings(),
              map_frame: str = 'map') -> OfflineMap:
    """Fuse every complete stereo frame of `rovers` (None: all found) into one VoxelMap, in
    stamp order (ties: rover name), with the mapper's body filter (every frame's camera pose
    is a pose the mapper would hold) and rejections (`voxelmap.ScanLimits`: empty cloud, too
    many points, non-finite numbers, absurd range; clouds of rover bodies only; bad input)."""
    from .ros_conv import pose_to_rt  # noqa: PLC0415 - message types only, not needed above

    frames = sorted(stereo_frames(messages, rovers), key=lambda f: (f.stamp_ns, f.rover))
    out = OfflineMap(mapping.new_map())
    rangers: dict[tuple, StereoRanger] = {}
    bodies = mapping.body_filter()
    limits = mapping.limits()
    poses: dict[str, dict[int, np.ndarray]] = {}
    for fr in frames:
        if fr.pose.header.frame_id == map_frame:
            t = np.asarray(pose_to_rt(fr.pose.pose.pose)[1], float)
            if np.all(np.isfinite(t)):
                poses.setdefault(fr.rover, {})[fr.stamp_ns] = t
    for fr in frames:
        if fr.pose.header.frame_id != map_frame:
            out.rejected['pose_frame'] += 1
            continue
        key = (tuple(np.asarray(fr.left_info.p, float)), tuple(np.asarray(fr.right_info.p, float)),
               int(fr.left_info.width), int(fr.left_info.height))
        try:
            if key not in rangers:
                rangers[key] = stereo.ranger(*key)
            cov: np.ndarray | None
            pts, cov, origin = frame_scan(fr, stereo, ranger=rangers[key])
        except (StereoError, ValueError, cv2.error):       # as the stereo node counts them
            out.rejected['stereo'] += 1
            continue
        try:
            limits.check(pts, cov, origin)
        except ScanRejected as exc:                         # as the mapper counts them
            out.rejected[exc.reason] += 1
            continue
        if bodies.enabled:
            cams = bodies.cameras_at(fr.stamp_ns, origin,
                                     [p for r, p in poses.items() if r != fr.rover])
            pts, cov, dropped = bodies.drop(pts, cov, cams)
            if len(pts) == 0:
                out.rejected['body_only'] += 1
                continue
            out.body_points += dropped
        try:
            out.map.insert_scan(pts, origin, covariances=cov, source=fr.rover)
        except MapInputError:
            out.rejected['map_input'] += 1
            continue
        out.scans[fr.rover] += 1
        out.frames.append((fr.rover, fr.stamp_ns))
    return out


def map_from_bag(bag: str | Path, rovers: Iterable[str] | None = None, *,
                 stereo: StereoSettings = StereoSettings(),
                 mapping: MapSettings = MapSettings()) -> OfflineMap:
    """`build_map` on a rosbag2 bag (read with rover_bag.bagio, no DDS)."""
    # rosbags: only bag reading needs it; the mapper node imports this module
    from rover_bag.bagio import bag_info, read_messages  # noqa: PLC0415

    names = list(rovers) if rovers is not None else sorted(
        {m['rover'] for t in bag_info(bag).topics if (m := STEREO_TOPIC.match(t))})
    topics = [t for t in stereo_topics(names) if t in bag_info(bag).topics]
    msgs = ((m.topic, m.msg) for m in read_messages(bag, topics))
    return build_map(msgs, names, stereo=stereo, mapping=mapping)
