"""The wire form of a map contribution (coop_msgs/MapContribution, no rclpy), small enough for a
field radio: a 320x240 stereo frame's cloud is about 1.8 MB, its contribution about 50 kB.

Keys: sorted packed keys differ from their neighbours mostly by 1 (the next voxel up a column)
or by one row, so delta-coded as int64 their upper bytes are mostly zero. Grouping each byte
position together (the shuffle of HDF5's and Blosc's filters) puts those zeros in runs that zlib
takes to nearly nothing: under 1 byte per key instead of 8.
Gaussians: per voxel, the scan's points' own Gaussian (Eq. 3-10 over its points, without the
map's voxel prior) as the map stores its voxels: the mean's offset from the voxel centre and
the Cholesky factor of the covariance, both in voxel units as IEEE half floats (18 bytes a
voxel, 1/2048 of a voxel's precision: 0.05 mm at 0.1 m voxels), shuffled and compressed the
same way. The mapper turns them back into information sums.
"""
from __future__ import annotations

import zlib
from dataclasses import replace

import numpy as np

from .bodies import BodyFilter
from .gauss import NotPositiveDefinite, sym6_cholesky, sym6_from_cholesky, sym6_inv, sym6_matvec
from .voxelmap import Contribution, MapInputError, ScanLimits, ScanRejected, VoxelMap

__all__ = ['ContributionFormatError', 'decode_array', 'decode_gaussians', 'decode_keys',
           'decode_mask', 'drop_voxels', 'encode_array', 'encode_gaussians', 'encode_keys',
           'encode_mask', 'make_contribution']

#: the most a decoded list may hold (a scan of 5 M points carves fewer voxels than this)
MAX_KEYS = 50_000_000


class ContributionFormatError(MapInputError):
    """A contribution message this package cannot read."""


def _inflate(data: bytes, size: int, what: str) -> bytes:
    """zlib data that must inflate to exactly `size` bytes (never more is inflated: a small
    message cannot make the mapper allocate gigabytes)."""
    try:
        z = zlib.decompressobj()
        raw = z.decompress(bytes(data), size + 1)
    except zlib.error as exc:
        raise ContributionFormatError(f'{what}: {exc}') from exc
    if len(raw) != size or not z.eof:
        raise ContributionFormatError(f'{what}: {len(raw)} bytes, expected {size}')
    return raw


def encode_array(a: np.ndarray, dtype: str, *, level: int = 6) -> bytes:
    """An array as `dtype` (little endian, e.g. '<f2'), byte-shuffled, zlib-compressed."""
    dt = np.dtype(dtype)
    flat = np.ascontiguousarray(np.asarray(a).astype(dt).reshape(-1))
    return zlib.compress(flat.view(np.uint8).reshape(-1, dt.itemsize).T.tobytes(), level)


def decode_array(data: bytes, dtype: str, n: int, what: str) -> np.ndarray:
    """The inverse of encode_array for `n` values; ContributionFormatError when the bytes do not
    hold exactly that."""
    dt = np.dtype(dtype)
    if not 0 <= n <= MAX_KEYS * 9:
        raise ContributionFormatError(f'{what}: {n} values is out of range')
    raw = _inflate(data, n * dt.itemsize, what)
    return np.frombuffer(raw, np.uint8).reshape(dt.itemsize, n).T.copy().view(dt).reshape(n)


def encode_keys(keys: np.ndarray, *, level: int = 6) -> bytes:
    """Sorted int64 keys -> bytes (the module docstring's coding)."""
    k = np.asarray(keys, np.int64)
    return encode_array(np.diff(k, prepend=np.int64(0)), '<i8', level=level)


def decode_keys(data: bytes, n: int) -> np.ndarray:
    """The inverse of encode_keys for `n` keys; ContributionFormatError when the bytes do not
    hold n strictly increasing keys."""
    if not 0 <= n <= MAX_KEYS:
        raise ContributionFormatError(f'{n} keys is out of range')
    d = decode_array(data, '<i8', n, 'keys')
    keys = np.cumsum(d).astype(np.int64)
    if n > 1 and np.any(d[1:] <= 0):
        raise ContributionFormatError('keys are not strictly increasing')
    return keys


def encode_mask(mask: np.ndarray, *, level: int = 6) -> bytes:
    """A bool array -> np.packbits, zlib-compressed."""
    return zlib.compress(np.packbits(np.asarray(mask, bool)).tobytes(), level)


def decode_mask(data: bytes, n: int) -> np.ndarray:
    """The inverse of encode_mask for n entries."""
    if not 0 <= n <= MAX_KEYS:
        raise ContributionFormatError(f'mask: {n} entries is out of range')
    raw = _inflate(data, (n + 7) // 8, 'mask')
    return np.unpackbits(np.frombuffer(raw, np.uint8), count=n).astype(bool)


def encode_gaussians(info: np.ndarray, info_offset: np.ndarray, resolution: float, *,
                     level: int = 6) -> bytes:
    """Information sums (K, 6), (K, 3) -> each voxel's Gaussian of its scan points: mean offset
    and covariance Cholesky factor in voxel units, (K, 9) half floats, shuffled and compressed
    (the module docstring)."""
    cov = sym6_inv(np.asarray(info, np.float64))
    mean = sym6_matvec(cov, np.asarray(info_offset, np.float64)) / resolution
    L = sym6_cholesky(cov / (resolution * resolution))
    return encode_array(np.concatenate([mean, L], axis=1), '<f2', level=level)


def decode_gaussians(data: bytes, k: int, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """The inverse of encode_gaussians: the information sums (K, 6) and (K, 3);
    ContributionFormatError for values that are not k Gaussians."""
    g = decode_array(data, '<f2', 9 * k, 'gaussians').astype(np.float64).reshape(k, 9)
    if not np.all(np.isfinite(g)):
        raise ContributionFormatError('gaussians: non-finite values')
    if k and np.any(g[:, [3, 6, 8]] <= 0):
        raise ContributionFormatError('gaussians: a covariance factor that is not positive')
    try:
        info = sym6_inv(sym6_from_cholesky(g[:, 3:]) * resolution * resolution,
                        require_pd=True)
    except NotPositiveDefinite as exc:
        raise ContributionFormatError(f'gaussians: {exc}') from exc
    return info, sym6_matvec(info, g[:, :3] * resolution)


def make_contribution(vm: VoxelMap, points: np.ndarray, covariances: np.ndarray | None,
                      origin: np.ndarray, *, limits: ScanLimits, bodies: BodyFilter
                      ) -> tuple[Contribution, int]:
    """A rover's side of the mapping: one scan, checked as the mapper checks a cloud
    (`limits`), without the points on the rover's own body (`bodies` about its camera), as a
    contribution made by `vm` (of the mapper's settings). Returns it and the points dropped
    as body; ScanRejected for a scan the mapper would not fuse."""
    limits.check(points, covariances, origin)
    pts, cov, dropped = bodies.drop(points, covariances, [origin])
    if len(pts) == 0:
        raise ScanRejected('body_only', 'every point on the rover body')
    return vm.contribution(pts, origin, covariances=cov), dropped


def drop_voxels(c: Contribution, mask: np.ndarray) -> tuple[Contribution, int]:
    """The contribution without the points of the voxels `mask` (over c.keys) marks: their
    Gaussian sums and hits go; the free space the scan's rays carved stays (the mapper's
    teammate-body filter on a contribution, which no longer has the points). Returns it and
    the points dropped."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return c, 0
    keep = ~mask
    return replace(c, hit=c.hit[np.isin(c.hit, c.keys[mask], assume_unique=True,
                                        invert=True)],
                   keys=c.keys[keep], info=c.info[keep], info_offset=c.info_offset[keep],
                   counts=c.counts[keep]), int(c.counts[mask].sum())
