"""The live view's core, without rclpy: the mission's state as Foxglove messages on a Foxglove
WebSocket server (`foxglove-sdk`), rate-limited so the camera images never starve the small
channels.

`LiveView` owns a private `foxglove.Context` and its server; the node (`live_view_node`) only
turns ROS messages into the numpy arrays and numbers its methods take. Images are JPEG-encoded
(downscaled) at most `image_rate_hz` per rover and only while a client subscribes to them; the
map, the identification and the insertion state are re-sent at `state_rate_hz`, since the
WebSocket protocol has no latching and a client that connects late must still see them.
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any, Literal, assert_never, get_args

import foxglove
import numpy as np
from foxglove.channels import (
    CompressedImageChannel,
    FrameTransformsChannel,
    PointCloudChannel,
    PoseInFrameChannel,
)
from foxglove.messages import (
    CompressedImage,
    FrameTransform,
    FrameTransforms,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    Pose,
    PoseInFrame,
    Quaternion,
    Timestamp,
    Vector3,
)
from numpy.typing import ArrayLike

__all__ = ['INSERT_PHASES', 'LiveView', 'LiveViewConfig', 'RateGate', 'channel_topics',
           'encode_jpeg', 'voxel_cloud', 'voxel_map_cdr']

#: coop_msgs/action/Insert feedback phases, by value
INSERT_PHASES = ('place_camera', 'visual_servo', 'force_insert', 'done')
#: action_msgs/GoalStatus codes
GOAL_STATUS = ('unknown', 'accepted', 'executing', 'canceling', 'succeeded', 'canceled',
               'aborted')
_F32 = PackedElementFieldNumericType.Float32


class RateGate:
    """At most `rate_hz` openings per second of the monotonic clock (`ready(now)`)."""

    def __init__(self, rate_hz: float) -> None:
        if not rate_hz > 0:
            raise ValueError(f'rate_hz must be > 0, got {rate_hz}')
        self.period_s = 1.0 / rate_hz
        self._next = -math.inf

    def ready(self, now_s: float | None = None) -> bool:
        now = time.monotonic() if now_s is None else now_s
        if now < self._next:
            return False
        # on a schedule, not one period after the last opening: a source at the gate's own
        # rate is let through whole despite its jitter (else every early sample is dropped
        # and the next one comes a period later: 4 Hz through a 4 Hz gate gave 2.3 Hz); a
        # source that paused earns no burst, at most one early opening
        self._next = max(self._next + self.period_s, now + 0.5 * self.period_s)
        return True


def image_array(encoding: str, height: int, width: int, step: int,
                data: Any) -> np.ndarray:
    """A sensor_msgs/Image's pixels as an (h, w) or (h, w, 3) uint8 array (mono8, rgb8, bgr8);
    ValueError for another encoding or a short buffer."""
    channels = {'mono8': 1, '8UC1': 1, 'rgb8': 3, 'bgr8': 3}.get(encoding)
    if channels is None:
        raise ValueError(f'unsupported image encoding {encoding!r} (mono8, rgb8, bgr8)')
    buf = np.frombuffer(data, np.uint8)
    if step < width * channels or buf.size < step * height:
        raise ValueError(f'image data of {buf.size} bytes too short for {height} x {step}')
    img = buf[:step * height].reshape(height, step)[:, :width * channels]
    img = img.reshape(height, width, channels) if channels == 3 else img
    return img[..., ::-1] if encoding == 'rgb8' else img        # cv2 wants BGR


def encode_jpeg(img: np.ndarray, *, quality: int = 70, scale: float = 0.5) -> bytes:
    """`img` (uint8, mono or BGR) downscaled by `scale` (area averaging) as JPEG bytes."""
    import cv2  # noqa: PLC0415 - the only user; keeps `import coop_bringup.live` light
    if scale != 1.0:
        h, w = img.shape[:2]
        img = cv2.resize(img, (max(1, round(w * scale)), max(1, round(h * scale))),
                         interpolation=cv2.INTER_AREA)
    ok, buf = cv2.imencode('.jpg', np.ascontiguousarray(img),
                           [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise ValueError('JPEG encoding failed')
    return buf.tobytes()


def voxel_cloud(keys: ArrayLike, occupancy: ArrayLike, resolution_m: float, *,
                min_occupancy: float = 0.5) -> tuple[bytes, int]:
    """The occupied voxels of a VoxelSet (flat int32 keys, 3 per voxel) as a packed cloud of
    float32 (x, y, z, occupancy) at the voxel centres, 16 bytes a point; and the point count."""
    keys = np.asarray(keys, np.int32).reshape(-1, 3)
    occ = np.asarray(occupancy, np.float32)
    if len(occ) != len(keys):
        raise ValueError(f'{len(keys)} keys but {len(occ)} occupancies')
    sel = occ >= min_occupancy
    pts = np.empty((int(sel.sum()), 4), np.float32)
    pts[:, :3] = (keys[sel] + 0.5) * resolution_m
    pts[:, 3] = occ[sel]
    return pts.tobytes(), len(pts)


def voxel_map_cdr(buf: bytes | memoryview) -> tuple[float, str, float, np.ndarray, np.ndarray]:
    """(stamp s, frame id, resolution, keys, occupancy) straight from a serialized
    coop_msgs/VoxelMap (little-endian plain CDR, as rclpy and Fast DDS write it), without
    deserializing the rest: a 100k-voxel map is 5.6 MB, of which the cloud needs 1.6 MB, and
    rclpy takes ~35 ms to build every array of it. Views into `buf`, not copies. ValueError for
    another encoding or a truncated message."""
    b = memoryview(buf)
    if len(b) < 4 or bytes(b[:2]) != b'\x00\x01':
        raise ValueError('not a little-endian plain CDR message')
    # offsets are aligned relative to the payload after the 4-byte encapsulation header
    o = 4

    def align(o: int, n: int) -> int:
        return 4 + -(-(o - 4) // n) * n

    def u32(o: int) -> int:
        if o + 4 > len(b):
            raise ValueError('truncated VoxelMap')
        return int.from_bytes(b[o:o + 4], 'little')

    sec, nsec = np.frombuffer(b, np.int32, 1, o)[0], u32(o + 4)
    o += 8
    n = u32(o)
    frame = bytes(b[o + 4:o + 4 + max(n - 1, 0)]).decode()
    o = align(o + 4 + n, 8)
    res = float(np.frombuffer(b, np.float64, 1, o)[0])
    o += 16                                         # resolution_m, sequence
    n = u32(o)
    if o + 4 + 4 * n > len(b):
        raise ValueError('truncated VoxelMap')
    keys = np.frombuffer(b, np.int32, n, o + 4)
    o += 4 + 4 * n
    m = u32(o)
    if o + 4 + 4 * m > len(b):
        raise ValueError('truncated VoxelMap')
    occ = np.frombuffer(b, np.float32, m, o + 4)
    return float(sec) + 1e-9 * nsec, frame, res, keys, occ


def _stamp(t_s: float) -> Timestamp:
    sec = math.floor(t_s)
    return Timestamp(int(sec), round((t_s - sec) * 1e9) % 1_000_000_000)


def _pose(xyz: Sequence[float], quat_xyzw: Sequence[float]) -> Pose:
    return Pose(position=Vector3(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                orientation=Quaternion(x=float(quat_xyzw[0]), y=float(quat_xyzw[1]),
                                       z=float(quat_xyzw[2]), w=float(quat_xyzw[3])))


#: a rover's pose channels: its base ('pose') and its left camera's optical frame
PoseChannel = Literal['pose', 'camera_pose']
POSE_CHANNELS: tuple[str, ...] = get_args(PoseChannel)


def channel_topics(rovers: Sequence[str]) -> list[str]:
    """Every Foxglove channel the live view advertises for these rovers."""
    per = ('camera/compressed', *POSE_CHANNELS, 'identification')
    return ['/map', '/insertion', '/tf', *(f'/{r}/{c}' for r in rovers for c in per)]


@dataclass(frozen=True)
class LiveViewConfig:
    """The server's address and the rate limits (the node's parameters of the same names)."""

    rovers: tuple[str, ...] = ('rover1', 'rover2')
    host: str = '127.0.0.1'
    port: int = 8765                  # 0: any free port (`LiveView.port` tells which)
    image_rate_hz: float = 4.0        # per rover
    image_scale: float = 0.5
    jpeg_quality: int = 70
    pose_rate_hz: float = 5.0         # per pose channel
    state_rate_hz: float = 2.5        # map, identification, insertion re-sent
    map_frame: str = 'map'
    min_occupancy: float = 0.5

    def __post_init__(self) -> None:
        for name in ('image_rate_hz', 'pose_rate_hz', 'state_rate_hz', 'image_scale'):
            if not getattr(self, name) > 0:
                raise ValueError(f'{name} must be > 0, got {getattr(self, name)}')
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f'jpeg_quality must be 1..100, got {self.jpeg_quality}')
        if not self.rovers:
            raise ValueError('no rovers')


class LiveView:
    """A Foxglove WebSocket server with the mission's channels; `close()` stops it.

    Every `on_*` method may be called at any rate: it drops what its channel's rate limit does
    not let through (returning False) and logs the rest (True)."""

    def __init__(self, cfg: LiveViewConfig) -> None:
        self.cfg = cfg
        self.ctx = foxglove.Context()
        c = self.ctx
        self.images = {r: CompressedImageChannel(f'/{r}/camera/compressed', context=c)
                       for r in cfg.rovers}
        self.poses = {r: PoseInFrameChannel(f'/{r}/pose', context=c) for r in cfg.rovers}
        self.cam_poses = {r: PoseInFrameChannel(f'/{r}/camera_pose', context=c)
                          for r in cfg.rovers}
        self.ident = {r: foxglove.Channel(f'/{r}/identification', context=c)
                      for r in cfg.rovers}
        self.map = PointCloudChannel('/map', context=c)
        self.insertion = foxglove.Channel('/insertion', context=c)
        # the graph's transform tree (/tf and /tf_static), each frame's latest transform
        self.tf = FrameTransformsChannel('/tf', context=c)
        self._tf: dict[str, FrameTransform] = {}
        self._gates = {('image', r): RateGate(cfg.image_rate_hz) for r in cfg.rovers}
        self._gates.update({(k, r): RateGate(cfg.pose_rate_hz) for r in cfg.rovers
                            for k in POSE_CHANNELS})
        self._last_map: PointCloud | None = None
        self._last_ident: dict[str, dict] = {}
        self._fresh: set[str] = set()       # logged since the last republish()
        self._last_insertion: dict | None = None
        self.sent: dict[str, int] = dict.fromkeys(channel_topics(cfg.rovers), 0)
        self.map_points = 0
        self.server = foxglove.start_server(name='coop mission', host=cfg.host, port=cfg.port,
                                            context=c)

    @property
    def port(self) -> int:
        return self.server.port

    def close(self) -> None:
        self.server.stop()

    # -- streams: rate-limited ------------------------------------------------------------------
    def image_due(self, rover: str, now_s: float | None = None) -> bool:
        """Whether the next image of `rover` is to be sent (a client subscribed, its rate
        limit open); when True the caller must send it (`log_image`). No client watching: not
        even the message's deserialization or the JPEG encoding is paid for."""
        return self.images[rover].has_sinks() and self._gates[('image', rover)].ready(now_s)

    def log_image(self, rover: str, img: np.ndarray, stamp_s: float, frame_id: str) -> None:
        data = encode_jpeg(img, quality=self.cfg.jpeg_quality, scale=self.cfg.image_scale)
        self.images[rover].log(CompressedImage(timestamp=_stamp(stamp_s), frame_id=frame_id,
                                               data=data, format='jpeg'))
        self.sent[f'/{rover}/camera/compressed'] += 1

    def on_image(self, rover: str, img: np.ndarray, stamp_s: float, frame_id: str,
                 now_s: float | None = None) -> bool:
        if not self.image_due(rover, now_s):
            return False
        self.log_image(rover, img, stamp_s, frame_id)
        return True

    def on_pose(self, rover: str, kind: PoseChannel, xyz: Sequence[float],
                quat_xyzw: Sequence[float], stamp_s: float, frame_id: str = '',
                now_s: float | None = None) -> bool:
        """kind: 'pose' (the rover's base) or 'camera_pose' (its left optical frame)."""
        match kind:
            case 'pose':
                ch = self.poses[rover]
            case 'camera_pose':
                ch = self.cam_poses[rover]
            case _:
                assert_never(kind)
        if not ch.has_sinks() or not self._gates[(kind, rover)].ready(now_s):
            return False
        ch.log(PoseInFrame(timestamp=_stamp(stamp_s), frame_id=frame_id or self.cfg.map_frame,
                           pose=_pose(xyz, quat_xyzw)))
        self.sent[f'/{rover}/{kind}'] += 1
        return True

    def on_transforms(self, transforms: Iterable[Any]) -> None:
        """Keep each child frame's latest transform: `transforms` of (parent, child, xyz,
        quat_xyzw, stamp_s); sent by `send_transforms`."""
        for parent, child, xyz, q, stamp_s in transforms:
            self._tf[child] = FrameTransform(
                timestamp=_stamp(stamp_s), parent_frame_id=parent, child_frame_id=child,
                translation=Vector3(x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])),
                rotation=Quaternion(x=float(q[0]), y=float(q[1]), z=float(q[2]),
                                    w=float(q[3])))

    def send_transforms(self) -> bool:
        """Every frame's latest transform, static ones too (the protocol has no latching), to
        a client that watches the tree; False when none does or nothing is known yet."""
        if not self._tf or not self.tf.has_sinks():
            return False
        self.tf.log(FrameTransforms(transforms=list(self._tf.values())))
        self.sent['/tf'] += 1
        return True

    # -- state: kept and re-sent at state_rate_hz -------------------------------------------------
    def on_map(self, keys: ArrayLike, occupancy: ArrayLike, resolution_m: float, stamp_s: float,
               frame_id: str = '') -> None:
        data, n = voxel_cloud(keys, occupancy, resolution_m,
                              min_occupancy=self.cfg.min_occupancy)
        fields = [PackedElementField(name=name, offset=4 * i, type=_F32)
                  for i, name in enumerate(('x', 'y', 'z', 'occupancy'))]
        self._last_map = PointCloud(timestamp=_stamp(stamp_s),
                                    frame_id=frame_id or self.cfg.map_frame,
                                    pose=_pose((0, 0, 0), (0, 0, 0, 1)), point_stride=16,
                                    fields=fields, data=data)
        self.map_points = n

    def on_identification(self, rover: str, estimate: dict) -> None:
        """estimate: `identification_state(...)`'s dict."""
        self._last_ident[rover] = estimate
        self.ident[rover].log(estimate)
        self.sent[f'/{rover}/identification'] += 1
        self._fresh.add(f'/{rover}/identification')

    def on_insertion(self, state: dict) -> None:
        """state: `insertion_state(...)`'s dict (merged into the last one)."""
        self._last_insertion = {**(self._last_insertion or {}), **state}
        self.insertion.log(self._last_insertion)
        self.sent['/insertion'] += 1
        self._fresh.add('/insertion')

    def republish(self) -> None:
        """Send the latest map, identification and insertion state again (call at
        state_rate_hz): the protocol has no latching. A state logged since the last call is
        not sent twice."""
        fresh, self._fresh = self._fresh, set()
        if self._last_map is not None and self.map.has_sinks():
            self.map.log(self._last_map)
            self.sent['/map'] += 1
        for r, est in self._last_ident.items():
            if self.ident[r].has_sinks() and f'/{r}/identification' not in fresh:
                self.ident[r].log(est)
                self.sent[f'/{r}/identification'] += 1
        if self._last_insertion is not None and self.insertion.has_sinks() and \
                '/insertion' not in fresh:
            self.insertion.log(self._last_insertion)
            self.sent['/insertion'] += 1


def identification_state(rover: str, names: Sequence[str], values: Sequence[float],
                         std_devs: Sequence[float], information_bits: Sequence[float], *,
                         samples: int, strategy: str, stamp_s: float) -> dict:
    """A coop_msgs/DynamicParameters estimate as the JSON the Plot panel reads:
    `params.<name>.value` / `.std` / `.bits` (e.g. `/rover1/identification.params.mass.value`)."""
    def num(v: float) -> float | None:
        return float(v) if math.isfinite(v) else None

    params = {n: {'value': num(v), 'std': num(s), 'bits': num(b)}
              for n, v, s, b in zip(names, values, std_devs, information_bits, strict=False)}
    return {'rover': rover, 'stamp_s': stamp_s, 'samples': int(samples), 'strategy': strategy,
            'params': params}


def insertion_state(*, phase: int | None = None, displacement_error_m: float | None = None,
                    angle_error_rad: float | None = None, force_n: Sequence[float] | None = None,
                    goal_status: int | None = None, stamp_s: float | None = None) -> dict:
    """The insertion's feedback / goal status as JSON (only the fields given)."""
    out: dict = {}
    if phase is not None:
        out['phase'] = INSERT_PHASES[phase] if 0 <= phase < len(INSERT_PHASES) else str(phase)
        out['phase_index'] = int(phase)
    if displacement_error_m is not None:
        out['displacement_error_mm'] = 1e3 * float(displacement_error_m)
    if angle_error_rad is not None:
        out['angle_error_deg'] = math.degrees(float(angle_error_rad))
    if force_n is not None:
        f = [float(v) for v in force_n]
        out['force_n'] = {'x': f[0], 'y': f[1], 'z': f[2], 'norm': float(np.linalg.norm(f))}
    if goal_status is not None:
        out['goal_status'] = GOAL_STATUS[goal_status] if 0 <= goal_status < len(GOAL_STATUS) \
            else str(goal_status)
    if stamp_s is not None:
        out['stamp_s'] = float(stamp_s)
    return out
