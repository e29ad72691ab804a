"""Message <-> numpy conversions for the coop_mapping nodes (message types only, no rclpy).

PointCloud2 layout of `stereo/points`: float32 x, y, z and the six unique covariance terms
cov_xx, cov_xy, cov_xz, cov_yy, cov_yz, cov_zz (m^2, same frame as the points), 36 B per point,
little endian, dense (no NaN points).
"""
from __future__ import annotations

import array
from typing import Any

import numpy as np
from geometry_msgs.msg import Pose
from sensor_msgs.msg import PointCloud2, PointField

from coop_msgs.msg import MapContribution, VoxelSet

from .contribution import (
    ContributionFormatError,
    decode_array,
    decode_gaussians,
    decode_keys,
    decode_mask,
    encode_array,
    encode_gaussians,
    encode_keys,
    encode_mask,
)
from .errors import MappingError
from .gauss import sym6_from_cholesky
from .voxelmap import LOGODDS_SCALE, Contribution, VoxelMap, unpack_keys

CLOUD_FIELDS = ('x', 'y', 'z', 'cov_xx', 'cov_xy', 'cov_xz', 'cov_yy', 'cov_yz', 'cov_zz')


class CloudFormatError(MappingError, ValueError):
    """A PointCloud2 this package cannot read."""


def _arr(code: str, a: np.ndarray) -> array.array:
    out = array.array(code)
    out.frombytes(np.ascontiguousarray(a).tobytes())
    return out


def cloud_to_msg(points: np.ndarray, covariances: np.ndarray | None, header: Any) -> PointCloud2:
    """Points (N, 3) and their sym6 covariances (N, 6) or None as a PointCloud2 under `header`."""
    n = len(points)
    fields = CLOUD_FIELDS if covariances is not None else CLOUD_FIELDS[:3]
    data = np.empty((n, len(fields)), np.float32)
    data[:, :3] = points
    if covariances is not None:
        data[:, 3:] = covariances
    msg = PointCloud2()
    msg.header = header
    msg.height = 1
    msg.width = n
    msg.fields = [PointField(name=f, offset=4 * i, datatype=PointField.FLOAT32, count=1)
                  for i, f in enumerate(fields)]
    msg.is_bigendian = False
    msg.point_step = 4 * len(fields)
    msg.row_step = msg.point_step * n
    msg.is_dense = True
    msg.data = _arr('B', data.view(np.uint8).reshape(-1))
    return msg


def msg_to_cloud(msg: PointCloud2) -> tuple[np.ndarray, np.ndarray | None]:
    """(N, 3) float64 points and (N, 6) covariances (None if the cloud has no covariance
    fields). Raises CloudFormatError on a layout it cannot read."""
    names = {f.name: f for f in msg.fields}
    for f in ('x', 'y', 'z'):
        if f not in names or names[f].datatype != PointField.FLOAT32:
            raise CloudFormatError(f'field {f} missing or not float32')
    if msg.is_bigendian:
        raise CloudFormatError('big-endian clouds are not supported')
    n = msg.width * msg.height
    step = msg.point_step
    row = msg.width * step
    if step <= 0 or msg.row_step < row or len(msg.data) < msg.row_step * msg.height:
        raise CloudFormatError(f'data has {len(msg.data)} bytes in rows of {msg.row_step}, '
                               f'need {msg.height} rows of {msg.width} x {step}')
    if msg.row_step == row:
        buf = np.frombuffer(msg.data, np.uint8, count=n * step)
    else:          # an organised cloud with padded rows: the points of each row
        buf = np.frombuffer(msg.data, np.uint8, count=msg.row_step * msg.height).reshape(
            msg.height, msg.row_step)[:, :row].reshape(-1)
    has_cov = [f in names for f in CLOUD_FIELDS[3:]]
    if any(has_cov) and not all(has_cov):
        missing = [f for f, h in zip(CLOUD_FIELDS[3:], has_cov, strict=False) if not h]
        raise CloudFormatError(f'covariance fields {", ".join(missing)} missing (all six or '
                               'none)')
    want = CLOUD_FIELDS if all(has_cov) else CLOUD_FIELDS[:3]
    for f in want:
        if names[f].offset + 4 > step:
            raise CloudFormatError(f'field {f} at offset {names[f].offset} runs past the '
                                   f'point ({step} bytes)')
    if step % 4 == 0 and all(names[f].offset == 4 * i and names[f].datatype == PointField.FLOAT32
                             for i, f in enumerate(want)):
        # our own layout: one strided view, one conversion
        flat = buf.view('<f4').reshape(n, step // 4)[:, :len(want)].astype(np.float64)
        return flat[:, :3], (flat[:, 3:] if len(want) == 9 else None)
    raw = buf.reshape(n, step)

    def col(name: str) -> np.ndarray:
        if names[name].datatype != PointField.FLOAT32:
            raise CloudFormatError(f'field {name} is not float32')
        o = names[name].offset
        return raw[:, o:o + 4].copy().view('<f4').reshape(n)

    pts = np.stack([col('x'), col('y'), col('z')], -1).astype(np.float64)
    cov = None
    if len(want) == 9:
        cov = np.stack([col(f) for f in CLOUD_FIELDS[3:]], -1).astype(np.float64)
    return pts, cov


def pose_to_rt(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    """geometry_msgs/Pose -> (R (3, 3), t (3,))."""
    q = pose.orientation
    x, y, z, w = q.x, q.y, q.z, q.w
    n = x * x + y * y + z * z + w * w
    if not np.isfinite(n):
        raise ValueError('non-finite quaternion')
    if not n > 0:
        raise ValueError('zero quaternion')
    s = 2.0 / n
    R = np.array([[1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
                  [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
                  [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)]])
    p = pose.position
    return R, np.array([p.x, p.y, p.z])


def voxelset(vm: VoxelMap, packed: np.ndarray | None = None) -> VoxelSet:
    """The map's voxels (all, or the given packed keys that are known) as a VoxelSet."""
    if packed is None:
        idx = np.arange(len(vm))
    else:
        pos, found = vm._find(np.asarray(packed, np.int64))
        idx = pos[found]
    keys = vm.keys[idx]
    res = vm.resolution
    k = unpack_keys(keys)
    mean = (k + 0.5) * res + vm.mean_off[idx].astype(np.float64) * res
    cov = sym6_from_cholesky(vm.chol[idx].astype(np.float64)) * res * res
    vs = VoxelSet()
    vs.keys = _arr('i', k.astype(np.int32).reshape(-1))
    p = 1.0 / (1.0 + np.exp(-vm.logodds[idx] / LOGODDS_SCALE))
    vs.occupancy = _arr('f', p.astype(np.float32))
    vs.mean = _arr('f', mean.astype(np.float32).reshape(-1))
    vs.covariance = _arr('f', cov.astype(np.float32).reshape(-1))
    vs.hits = _arr('I', vm.hits[idx].astype(np.uint32))
    return vs


def contribution_to_msg(c: Contribution, vm: VoxelMap, header: Any, *, source: str,
                        session: int, sequence: int) -> MapContribution:
    """A contribution made by `vm` (whose settings it carries) as a MapContribution."""
    m = MapContribution()
    m.header = header
    m.source = source
    m.session, m.sequence = int(session), int(sequence)
    m.resolution_m = vm.resolution
    m.ray_subdivision = vm.ray_subdivision
    m.voxel_prior = vm.voxel_prior
    m.origin.x, m.origin.y, m.origin.z = (float(v) for v in c.origin)
    m.n_points, m.n_rays = int(c.n_points), int(c.n_rays)
    m.n_free, m.n_keys = int(c.free.size), int(c.keys.size)
    m.free_keys = encode_keys(c.free)
    m.keys = encode_keys(c.keys)
    m.hit = encode_mask(np.isin(c.keys, c.hit, assume_unique=True))
    m.gaussians = encode_gaussians(c.info, c.info_offset, vm.resolution)
    m.counts = encode_array(np.minimum(c.counts, np.iinfo(np.uint32).max), '<u4')
    return m


def msg_to_contribution(msg: MapContribution, vm: VoxelMap) -> Contribution:
    """A MapContribution for `vm`: ContributionFormatError when it is malformed or was made
    with other settings than vm's (its update would not be the scan's)."""
    if (msg.resolution_m != vm.resolution or msg.ray_subdivision != vm.ray_subdivision
            or bool(msg.voxel_prior) != vm.voxel_prior):
        raise ContributionFormatError(
            f'made for {msg.resolution_m} m voxels, ray_subdivision {msg.ray_subdivision}, '
            f'voxel_prior {bool(msg.voxel_prior)}; this map has {vm.resolution}, '
            f'{vm.ray_subdivision}, {vm.voxel_prior}')
    k = int(msg.n_keys)
    free = decode_keys(msg.free_keys, int(msg.n_free))
    keys = decode_keys(msg.keys, k)
    hit = decode_mask(msg.hit, k)
    info, off = decode_gaussians(msg.gaussians, k, vm.resolution)
    counts = decode_array(msg.counts, '<u4', k, 'counts').astype(np.int64)
    origin = np.array([msg.origin.x, msg.origin.y, msg.origin.z])
    if not np.all(np.isfinite(origin)):
        raise ContributionFormatError('non-finite origin')
    if k and np.any(counts <= 0):
        raise ContributionFormatError('a voxel without points')
    if free.size and keys.size and np.isin(free, keys, assume_unique=True).any():
        raise ContributionFormatError('a voxel both carved free and hit')
    return Contribution(origin=origin, free=free, hit=keys[hit], keys=keys, info=info,
                        info_offset=off, counts=counts,
                        n_points=int(msg.n_points), n_rays=int(msg.n_rays))
