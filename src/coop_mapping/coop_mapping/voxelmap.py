"""Sparse probabilistic 3-D voxel map with a merged Gaussian per voxel (Sujan 2002, §3.2.3).

Every known voxel holds
  * an occupancy probability as fixed-point log-odds (int16, 1/4096 per unit) updated with
    OctoMap's hit/miss/clamp model (the default model here is OctoMap's default: hit 0.7,
    miss 0.4, clamp [0.1192, 0.971], occupied at P >= 0.5);
  * the Gaussian (mean, covariance) merged from every range point that fell into it (Eq. 3-8,
    Eq. 3-10, done in information form so a whole scan merges in one batched pass);
  * the number of points merged into it.
The points that fall into one voxel are different points of a surface patch, not repeated
measurements of one point. Fusing their raw covariances (Eq. 3-10 read literally) treats them as
the latter: stereo covariances are long and thin along the rays, so the fused mean is the
least-squares intersection of nearly parallel rays, slides along them, and ends up farther from
the surface than the voxel centre (1.0-1.4x its error on the voxels the true surface crosses,
bench/map_vs_octomap.py). So by default (voxel_prior=True) each point measures the voxel's
surface point with covariance C_i + V, and the voxel starts from N(centre, V), V = res^2/12 I
(the moment-matched uniform distribution over the voxel); both are Eq. 3-10 factors, so the
merge stays one information-form sum. Far points (C_i >> V) then barely move the estimate off
the centre, near points (C_i << V) put it on the surface.
Voxels in the field of view that a ray crosses are carved free and tabulated as known; they
carry no Gaussian (hits == 0), as in the thesis. Unknown voxels are simply absent.

Storage: parallel numpy arrays sorted by a packed int64 key (21 bits per axis), one row per
known voxel, no slack:
  key int64 (8 B) + log-odds int16 (2 B) + mean offset 3 x float16 (6 B, in voxel units from the
  voxel centre) + Cholesky factor of the covariance 6 x float16 (12 B, in voxel units) +
  hits uint32 (4 B) = 32 B per known voxel.
Storing the Cholesky factor rather than the covariance halves the dynamic range float16 must
cover (sigma, not sigma^2) and guarantees a positive-definite covariance on read-back.
Lookup is np.searchsorted on the sorted keys; new voxels are merged in with one np.insert per
array per scan, which is O(N) per scan but vectorised.

Free space is carved by an exact-set Amanatides-Woo traversal written in closed form: the k-th
crossing of axis a happens at t = t0_a + k dt_a, and the voxel entered there has, on every other
axis b, ceil((t - t0_b) / dt_b) crossings already done. So every visited voxel is computed
independently (np.repeat + arithmetic, no per-ray loop, no sort), as a linear index into a
dense bitmap over the scan's bounding box, whose set bits are the free keys (np.unique when the
box is too large). Like OctoMap's insertPointCloud(discretize=True),
rays are cast once per distinct end cell (edge resolution / ray_subdivision, default 4) to the
mean of the points in it (ray_subdivision=0: one ray per point, as insertPointCloud by default),
and a voxel that is an end point in this scan is never carved in the same scan (occupied
preference).

No rclpy in this module.
"""
from __future__ import annotations

import io
import itertools
import json
import math
import os
import zipfile
import zlib
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from typing import IO

import numpy as np

from coop_common.files import write_atomic

from .errors import MappingError
from .gauss import (
    NotPositiveDefinite,
    sym6_cholesky,
    sym6_from_cholesky,
    sym6_inv,
    sym6_matvec,
)
from .ledger import ContributionLedger

__all__ = [
    'FREE',
    'OCCUPIED',
    'UNKNOWN',
    'Contribution',
    'InsertResult',
    'MapFileError',
    'MapInputError',
    'OccupancyModel',
    'ScanLimits',
    'ScanRejected',
    'VoxelMap',
    'kernel_centroids',
    'pack_keys',
    'ray_voxel_keys',
    'state_agreement',
    'unpack_keys',
]

FILE_FORMAT = 'coop_mapping.voxelmap'
FILE_VERSION = 1
LOGODDS_SCALE = 4096.0          # int16 fixed point: 1/4096 log-odds units per count
_BITS = 21
_OFFSET = 1 << (_BITS - 1)       # keys in [-2^20, 2^20)
_MASK = (1 << _BITS) - 1
UNKNOWN, FREE, OCCUPIED = -1, 0, 1
#: VoxelMap.surface_points' kernel: bandwidth (voxels) and block radius (voxels)
SURFACE_BANDWIDTH, SURFACE_RADIUS = 0.8, 2
_EYE6 = np.array([1.0, 0.0, 0.0, 1.0, 0.0, 1.0])     # the identity as xx xy xz yy yz zz


class MapInputError(MappingError, ValueError):
    """Bad scan given to the map (NaN, wrong shape, out of the key range...)."""


class ScanRejected(MapInputError):
    """A scan the mappers do not fuse; `reason` is the short key they count it under."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass(frozen=True)
class ScanLimits:
    """The input checks the `mapper` node and `coop_mapping.offline` both apply to a scan
    before fusing it (the map's own checks in `insert_scan` come after): each raises
    ScanRejected with the reason key and what is wrong."""

    max_points: int = 1_000_000
    max_range_m: float = 30.0

    def check_count(self, n: int) -> None:
        """Before decoding a cloud of `n` points: not empty, at most max_points."""
        if n == 0:
            raise ScanRejected('empty', 'no points')
        if n > self.max_points:
            raise ScanRejected('too_large', f'{n} points > max_points {self.max_points}')

    def check(self, points: np.ndarray, covariances: np.ndarray | None,
              origin: np.ndarray) -> None:
        """A decoded scan: `check_count`, every number finite, no point farther than
        max_range_m from the camera at `origin` (an absurd range is a broken cloud)."""
        self.check_count(len(points))
        if not (np.all(np.isfinite(points))
                and (covariances is None or np.all(np.isfinite(covariances)))):
            raise ScanRejected('nan', 'points or covariances not finite')
        far = float(np.max(np.linalg.norm(points - origin, axis=1)))
        if far > self.max_range_m:
            raise ScanRejected('absurd_range', f'a point {far:.1f} m from the camera > '
                                               f'max_range_m {self.max_range_m}')


class MapFileError(MappingError, RuntimeError):
    """A map file that cannot be read: missing, truncated, corrupted, wrong version."""


def _logodds(p: float) -> float:
    return float(np.log(p / (1.0 - p)))


@dataclass(frozen=True)
class OccupancyModel:
    """OctoMap's sensor model: log-odds increments per hit/miss, clamping, occupied threshold."""

    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971
    occupied_threshold: float = 0.5

    def __post_init__(self) -> None:
        if not 0.5 < self.prob_hit < 1.0:
            raise ValueError(f'prob_hit must be in (0.5, 1), got {self.prob_hit}')
        if not 0.0 < self.prob_miss < 0.5:
            raise ValueError(f'prob_miss must be in (0, 0.5), got {self.prob_miss}')
        lim = 1.0 / (1.0 + np.exp(-32767 / LOGODDS_SCALE))
        if not (1 - lim < self.clamp_min < self.occupied_threshold < self.clamp_max < lim):
            raise ValueError('need 1-pmax < clamp_min < occupied_threshold < clamp_max < pmax '
                             f'with pmax={lim:.5f} (int16 log-odds range)')

    def _q(self, p: float) -> int:
        return round(_logodds(p) * LOGODDS_SCALE)

    @property
    def hit_q(self) -> int:
        return self._q(self.prob_hit)

    @property
    def miss_q(self) -> int:
        return self._q(self.prob_miss)

    @property
    def min_q(self) -> int:
        return self._q(self.clamp_min)

    @property
    def max_q(self) -> int:
        return self._q(self.clamp_max)

    @property
    def thr_q(self) -> int:
        return self._q(self.occupied_threshold)


def pack_keys(k: np.ndarray) -> np.ndarray:
    """(N, 3) integer voxel keys -> (N,) int64, ordered by x, then y, then z."""
    k = np.asarray(k, dtype=np.int64)
    if k.size and (k.min() < -_OFFSET or k.max() >= _OFFSET):
        raise MapInputError(f'voxel key outside +-{_OFFSET} (point too far from the origin)')
    u = k + _OFFSET
    return (u[:, 0] << (2 * _BITS)) | (u[:, 1] << _BITS) | u[:, 2]


def unpack_keys(p: np.ndarray) -> np.ndarray:
    """(N,) packed int64 -> (N, 3) int64 keys."""
    p = np.asarray(p, dtype=np.int64)
    return np.stack([(p >> (2 * _BITS)) & _MASK, (p >> _BITS) & _MASK, p & _MASK], -1) - _OFFSET


def state_agreement(keys_a: np.ndarray, states_a: np.ndarray, keys_b: np.ndarray,
                    states_b: np.ndarray) -> float:
    """Share of the voxels known in either of two maps (packed keys, FREE/OCCUPIED states)
    whose state (free / occupied / unknown) agrees."""
    union = np.union1d(keys_a, keys_b)

    def on_union(keys: np.ndarray, states: np.ndarray) -> np.ndarray:
        out = np.full(len(union), UNKNOWN, np.int8)
        out[np.searchsorted(union, keys)] = states
        return out
    return float(np.mean(on_union(keys_a, states_a) == on_union(keys_b, states_b)))


def _pack_unchecked(kx: np.ndarray, ky: np.ndarray, kz: np.ndarray) -> np.ndarray:
    return ((kx + _OFFSET) << (2 * _BITS)) | ((ky + _OFFSET) << _BITS) | (kz + _OFFSET)


def _ray_visits(origins: np.ndarray, ends: np.ndarray, resolution: float, *,
                drop_end: bool = False) -> Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Yield (kx, ky, kz) int64 arrays of voxels crossed by segments origins[i] -> ends[i]:
    first the start voxels, then, per axis a, the voxel entered at every crossing of an
    a-boundary. The last crossing of a ray enters its end voxel: dropped if `drop_end`.

    The k-th crossing of axis a is at t = t0_a + k dt_a (t in [0, 1] along the segment); the
    voxel entered there has ceil((t - t0_b) / dt_b) crossings done on each other axis b."""
    inv_res = 1.0 / resolution
    origins = np.broadcast_to(origins, ends.shape)
    s = np.floor(origins * inv_res).astype(np.int64)
    e = np.floor(ends * inv_res).astype(np.int64)
    diff = e - s
    n = np.abs(diff)
    step = np.sign(diff)
    d = ends - origins
    moving = n > 0
    with np.errstate(divide='ignore', invalid='ignore'):
        t0 = np.where(moving, ((s + (step > 0)) * resolution - origins) / d, np.inf)
        dt = np.where(moving, resolution / np.abs(d), 1.0)
    notsame = n.sum(1) > 0
    yield s[notsame, 0], s[notsame, 1], s[notsame, 2]
    for a in range(3):
        reps = n[:, a]
        total = int(reps.sum())
        if total == 0:
            continue
        first = np.cumsum(reps) - reps
        k1 = np.arange(1, total + 1, dtype=np.int64) - np.repeat(first, reps)
        t = np.repeat(t0[:, a], reps) + (k1 - 1) * np.repeat(dt[:, a], reps)
        out: dict[int, np.ndarray] = {}
        out[a] = np.repeat(s[:, a], reps) + np.repeat(step[:, a], reps) * k1
        for b in range(3):
            if b == a:
                continue
            cnt = np.ceil((t - np.repeat(t0[:, b], reps)) / np.repeat(dt[:, b], reps))
            np.clip(cnt, 0, np.repeat(n[:, b], reps), out=cnt)
            out[b] = np.repeat(s[:, b], reps) + np.repeat(step[:, b], reps) * cnt.astype(np.int64)
        if drop_end:
            keep = ((out[0] != np.repeat(e[:, 0], reps)) | (out[1] != np.repeat(e[:, 1], reps))
                    | (out[2] != np.repeat(e[:, 2], reps)))
            out = {b: o[keep] for b, o in out.items()}
        yield out[0], out[1], out[2]


def _ray_lin(origin: np.ndarray, ends: np.ndarray, resolution: float, k0: np.ndarray,
             strides: tuple[int, int, int], batch_visits: int = 1 << 17
             ) -> Iterator[np.ndarray]:
    """As _ray_visits for one origin, but yield linear indices sum_c (key_c - k0_c) stride_c
    into a dense box: the index is linear in the per-axis crossing counts, so each visit costs
    one multiply-add per axis instead of three keys to build and pack.

    The crossings of b before the k-th crossing of a are ceil(alpha + k beta) in float32. To
    keep the per-visit work small:
      * rays are grouped by octant (sign of the step on each axis, 0 counted as +), so the
        per-axis index steps are scalars, not per-visit arrays;
      * fl(fl(beta k) + alpha) is non-decreasing in k (beta >= 0, rounding is monotone), so the
        clip of the count to [0, n_b] can only bite on a ray whose first or last count is out of
        range: those few rays are found per ray and corrected afterwards, the others skip it;
      * rays are processed in batches of about `batch_visits` visits, so the temporaries stay
        in the L2 cache.
    The yielded set is bit-identical to the plain per-visit evaluation with clipping."""
    inv_res = 1.0 / resolution
    s = np.floor(origin * inv_res).astype(np.int64)
    st = np.asarray(strides, np.int64)
    lin_s = int(((s - k0) * st).sum())
    yield np.array([lin_s], np.int64)
    if len(ends) == 0:
        return
    diff = np.floor(ends * inv_res).astype(np.int64)
    diff -= s
    # octant of every ray (sign of the step per axis, 0 counted as +); rays sorted by it and
    # held per axis as contiguous rows
    neg = diff < 0
    octant = neg[:, 0] * 4 + neg[:, 1] * 2 + neg[:, 2]
    order = np.argsort(octant, kind='stable')
    octant = octant[order]
    diff = diff[order].T.copy()
    d = (ends[order] - origin).T.copy()
    n = np.abs(diff)
    # int32 indices and float32 crossing counts halve the memory traffic, which is what a
    # visit costs in numpy; float32 is exact enough for counts up to ~10^4 crossings per ray
    ity: type[np.signedinteger] = \
        np.int32 if lin_s + int(np.abs(st).sum() * (n.max(initial=0) + 1)) < 2 ** 31 else np.int64
    n_i = n.astype(ity)
    nf = n_i.astype(np.float32)
    mov = n_i > 0
    t0 = np.empty(d.shape)
    dt = np.empty(d.shape)
    with np.errstate(divide='ignore', invalid='ignore'):
        for a in range(3):  # the arithmetic of _ray_visits, per axis
            t0[a] = ((s[a] + (diff[a] > 0)) * resolution - origin[a]) / d[a]
            t0[a, ~mov[a]] = np.inf
            dt[a] = resolution / np.abs(d[a])
            dt[a, ~mov[a]] = 1.0
    alpha, beta, dirty = {}, {}, {}
    for a in range(3):
        kl = np.maximum(n_i[a] - 1, 0).astype(np.float32)  # last k of every ray on axis a
        for b in range(3):
            if b == a:
                continue
            with np.errstate(invalid='ignore'):
                al = ((t0[a] - t0[b]) / dt[b]).astype(np.float32)
                be = (dt[a] / dt[b]).astype(np.float32)
            al[~mov[b]] = 0.0
            be[~mov[b]] = 0.0
            hi = be * kl
            hi += al
            bad = np.ceil(al) < 0
            bad |= np.ceil(hi) > nf[b]
            bad &= mov[a]
            alpha[a, b], beta[a, b], dirty[a, b] = al, be, bad
    cum = np.cumsum(n_i[0].astype(np.int64) + n_i[1] + n_i[2])
    gb = np.flatnonzero(np.r_[True, octant[1:] != octant[:-1], True])
    for g0, g1 in itertools.pairwise(gb):
        oc = int(octant[g0])
        sg = np.array([-1 if oc & 4 else 1, -1 if oc & 2 else 1, -1 if oc & 1 else 1])
        ss = [int(v) for v in sg * st]
        base = int(cum[g0 - 1]) if g0 else 0
        # batches of about batch_visits visits (at least one ray each)
        lc = (cum[g0:g1] - base) // batch_visits
        edges = np.r_[0, np.flatnonzero(lc[1:] != lc[:-1]) + 1, g1 - g0] + g0
        for i, j in itertools.pairwise(edges):
            for a in range(3):
                reps = n_i[a, i:j]
                csum = np.cumsum(reps, dtype=ity)
                total = int(csum[-1])
                if total == 0:
                    continue
                first = csum - reps
                k = np.arange(total, dtype=ity)
                k -= np.repeat(first, reps)
                kf = k.astype(np.float32)
                # the index in intp: numpy converts any other index type before a scatter
                lin = k.astype(np.intp)
                lin *= ss[a]
                lin += lin_s + ss[a]
                for b in range(3):
                    if b == a:
                        continue
                    cnt = np.repeat(beta[a, b][i:j], reps)
                    cnt *= kf
                    cnt += np.repeat(alpha[a, b][i:j], reps)
                    ci = np.ceil(cnt, out=np.empty(total, ity), casting='unsafe')
                    if ss[b] != 1:
                        ci *= ss[b]
                    lin += ci
                    bad = np.flatnonzero(dirty[a, b][i:j])
                    if bad.size:  # rare: redo the clipped counts of these rays
                        rb = reps[bad]
                        idx = (np.arange(int(rb.sum()), dtype=np.int64)
                               - np.repeat(np.cumsum(rb) - rb, rb) + np.repeat(first[bad], rb))
                        c = np.repeat(beta[a, b][i:j][bad], rb)
                        c *= kf[idx]
                        c += np.repeat(alpha[a, b][i:j][bad], rb)
                        np.ceil(c, out=c)
                        un = c.astype(ity)
                        np.maximum(c, 0, out=c)
                        np.minimum(c, np.repeat(nf[b, i:j][bad], rb), out=c)
                        lin[idx] += (c.astype(ity) - un) * ity(ss[b])
                yield lin


def ray_voxel_keys(origins: np.ndarray, ends: np.ndarray, resolution: float) -> np.ndarray:
    """Keys (packed int64, with repeats) of every voxel a segment origin->end crosses, the
    origin's voxel included and the end's voxel excluded (OctoMap computeRayKeys semantics).

    origins: (3,) or (M, 3); ends: (M, 3). Exact-set 3-D DDA (Amanatides-Woo) in closed form:
    no loop over rays or steps. Where a ray passes exactly through an edge or corner both
    neighbouring voxels are reported (a superset of the single voxel a sequential DDA picks)."""
    ends = np.asarray(ends, dtype=np.float64).reshape(-1, 3)
    origins = np.broadcast_to(np.asarray(origins, dtype=np.float64), ends.shape)
    for p in (origins, ends):  # range check of the extreme keys
        pack_keys(np.floor(p * (1.0 / resolution)).astype(np.int64))
    return np.concatenate([_pack_unchecked(*v) for v in
                           _ray_visits(origins, ends, resolution, drop_end=True)])


def kernel_centroids(keys: np.ndarray, points: np.ndarray, weights: np.ndarray,
                     query: np.ndarray, *, bandwidth: float, radius: int) -> np.ndarray:
    """(M, 3): for each `query` voxel key, the centroid of the `points` of the voxels around it,
    weighted by `weights` x exp(-|o|^2 / (2 bandwidth^2)), o the integer offset (voxels) within
    the (2 radius + 1)^3 block. `keys` sorted packed keys with one point and weight each; every
    query key must be among them (it then weighs itself in)."""
    if not bandwidth > 0 or radius < 0:
        raise ValueError('bandwidth must be > 0 and radius >= 0')
    query = np.asarray(query, np.int64)
    acc = np.zeros((len(query), 3))
    if len(query) == 0:
        return acc
    kq = unpack_keys(query)
    wsum = np.zeros(len(query))
    w_all = np.asarray(weights, np.float64)
    r = np.arange(-radius, radius + 1)
    for o in np.stack(np.meshgrid(r, r, r, indexing='ij'), axis=-1).reshape(-1, 3):
        nb = pack_keys(kq + o)
        i = np.minimum(np.searchsorted(keys, nb), len(keys) - 1)
        w = np.where(keys[i] == nb, w_all[i], 0.0) * \
            np.exp(-float(o @ o) / (2.0 * bandwidth * bandwidth))
        acc += w[:, None] * points[i]
        wsum += w
    if not np.all(wsum > 0):
        raise ValueError('query keys must be among the keys, with weights > 0')
    return acc / wsum[:, None]


@dataclass
class InsertResult:
    """What one scan changed: sorted packed keys of every voxel updated, counts."""

    changed: np.ndarray
    n_points: int
    n_rays: int
    n_free_updates: int
    n_occupied_updates: int
    n_new: int


@dataclass(frozen=True, eq=False)
class Contribution:
    """What one scan does to any map of the settings it was made with (`VoxelMap.contribution`),
    whatever that map holds: a rover computes it where its stereo is and sends it, much smaller
    than the cloud, to the team's mapper, which `apply`s it. Keys are sorted packed keys."""

    origin: np.ndarray          # (3,) the camera, in the map frame
    free: np.ndarray            # voxels carved free (one miss each)
    hit: np.ndarray             # end voxels (one hit each)
    keys: np.ndarray            # voxels that take points into their Gaussian
    info: np.ndarray            # (K, 6) sum of the points' information (xx xy xz yy yz zz)
    info_offset: np.ndarray     # (K, 3) sum of information x (point - voxel centre)
    counts: np.ndarray          # (K,) points per voxel
    n_points: int
    n_rays: int


class VoxelMap:
    """Sparse probabilistic voxel map (see the module docstring)."""

    def __init__(self, resolution: float, *, model: OccupancyModel | None = None,
                 default_sigma: float | None = None, max_points: int = 5_000_000,
                 ray_subdivision: int = 4, voxel_prior: bool = True) -> None:
        if not (np.isfinite(resolution) and 1e-4 <= resolution <= 100.0):
            raise ValueError(f'resolution must be in [1e-4, 100] m, got {resolution}')
        self.resolution = float(resolution)
        self.model = model or OccupancyModel()
        #: isotropic sigma given to points passed without covariance (m)
        self.default_sigma = float(default_sigma if default_sigma is not None
                                   else resolution / 4.0)
        if not self.default_sigma > 0:
            raise ValueError('default_sigma must be > 0')
        self.max_points = int(max_points)
        if not 0 <= ray_subdivision <= 16:
            raise ValueError('ray_subdivision must be in 0..16')
        #: rays are cast once per end cell of size resolution / ray_subdivision (to the mean of
        #: its points); 0 casts one ray per point, exactly as OctoMap's insertPointCloud
        self.ray_subdivision = int(ray_subdivision)
        #: the voxel-extent model of the per-voxel Gaussian (module docstring); False merges the
        #: raw point covariances only (Eq. 3-10 read literally)
        self.voxel_prior = bool(voxel_prior)
        self.sequence = 0
        self.contributions: Counter[str] = Counter()
        #: the contributions (`apply` with a session and sequence) fused, per source
        self.ledger = ContributionLedger()
        self._init_arrays(0)

    # ------------------------------------------------------------------ storage
    def _init_arrays(self, n: int) -> None:
        self.keys = np.empty(n, np.int64)
        self.logodds = np.empty(n, np.int16)
        self.mean_off = np.zeros((n, 3), np.float16)
        self.chol = np.zeros((n, 6), np.float16)
        self.hits = np.zeros(n, np.uint32)

    def copy(self) -> VoxelMap:
        """An independent copy: voxels, settings, sequence, contributions and ledger."""
        out = VoxelMap(self.resolution, model=self.model, default_sigma=self.default_sigma,
                       max_points=self.max_points, ray_subdivision=self.ray_subdivision,
                       voxel_prior=self.voxel_prior)
        for name, arr in self._arrays().items():
            setattr(out, name, arr.copy())
        out.sequence = self.sequence
        out.contributions = Counter(self.contributions)
        out.ledger = self.ledger.copy()
        return out

    def _arrays(self) -> dict[str, np.ndarray]:
        return {'keys': self.keys, 'logodds': self.logodds, 'mean_off': self.mean_off,
                'chol': self.chol, 'hits': self.hits}

    def __len__(self) -> int:
        return int(self.keys.size)

    @property
    def nbytes(self) -> int:
        """Bytes held by the voxel arrays (the whole per-voxel state)."""
        return int(sum(a.nbytes for a in self._arrays().values()))

    def bytes_per_known_voxel(self) -> float:
        return self.nbytes / max(len(self), 1)

    def _find(self, packed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index of each packed key in storage and whether it is there."""
        pos = np.searchsorted(self.keys, packed)
        found = np.zeros(packed.shape, bool)
        inside = pos < self.keys.size
        found[inside] = self.keys[pos[inside]] == packed[inside]
        return pos, found

    # ------------------------------------------------------------------ insert
    def key_of(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) points -> (N, 3) int64 voxel keys floor(p / resolution)."""
        return np.floor(np.asarray(points, np.float64) * (1.0 / self.resolution)).astype(np.int64)

    def insert_scan(self, points: np.ndarray, origin: np.ndarray, *,
                    covariances: np.ndarray | None = None, source: str = '',
                    max_range: float | None = None) -> InsertResult:
        """Fuse one range scan taken from `origin` (all in the map frame).

        points: (N, 3) end points; covariances: (N, 6) xx, xy, xz, yy, yz, zz in the map frame
        (Eq. 3-8 after the Eq. 3-9 rotation), or None for the isotropic default_sigma.
        Occupancy: one hit per distinct end voxel, one miss per distinct voxel crossed by a
        ray and not an end voxel of this scan, clamped. Gaussians: Eq. 3-10 merge of every
        point into its voxel. Points beyond max_range carve free space up to max_range only.
        The same as `apply(contribution(...))`, which is how it is done."""
        return self.apply(self.contribution(points, origin, covariances=covariances,
                                            max_range=max_range), source=source)

    def contribution(self, points: np.ndarray, origin: np.ndarray, *,
                     covariances: np.ndarray | None = None,
                     max_range: float | None = None) -> Contribution:
        """What the scan does to a map of this one's settings (resolution, ray_subdivision,
        voxel prior, default_sigma), whatever the map holds: its misses, hits and per-voxel
        information sums (`Contribution`). Arguments and checks as `insert_scan`; the map is
        not changed."""
        pts = np.asarray(points, dtype=np.float64)
        org = np.asarray(origin, dtype=np.float64).reshape(-1)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MapInputError(f'points must be (N, 3), got {pts.shape}')
        if org.shape != (3,) or not np.all(np.isfinite(org)):
            raise MapInputError('origin must be 3 finite numbers')
        if len(pts) > self.max_points:
            raise MapInputError(f'{len(pts)} points > max_points {self.max_points}')
        if not np.all(np.isfinite(pts)):
            raise MapInputError('points contain NaN or inf')
        info = None
        if covariances is not None:
            cov = np.asarray(covariances, dtype=np.float64)
            if cov.shape != (len(pts), 6) or not np.all(np.isfinite(cov)):
                raise MapInputError('covariances must be finite (N, 6)')
            # each point's information (C_i + V)^-1 for the merge: a covariance that is not
            # positive definite rejects the scan whole
            v = self.extent_variance
            try:
                info = sym6_inv(cov + v * _EYE6 if v else cov, require_pd=True)
            except NotPositiveDefinite as exc:
                raise MapInputError(f'covariances: {exc}') from exc
        carve_only = np.zeros(len(pts), bool)
        if max_range is not None:
            rng = np.linalg.norm(pts - org, axis=1)
            carve_only = rng > max_range
            if carve_only.any():
                f = (max_range / rng[carve_only])[:, None]
                pts = pts.copy()
                pts[carve_only] = org + (pts[carve_only] - org) * f
        # --- end voxels: distinct keys (ray ends: mean of the points of each end cell)
        pk = pack_keys(self.key_of(pts))
        order = np.argsort(pk, kind='stable')  # order inside a voxel is irrelevant: sums only
        pk_s = pk[order]
        pts_s = pts[order]
        bounds = np.flatnonzero(np.r_[True, pk_s[1:] != pk_s[:-1]])
        counts = np.diff(np.r_[bounds, len(pk_s)])
        end_keys = pk_s[bounds]
        ray_end = np.add.reduceat(pts_s, bounds, axis=0) / counts[:, None] if len(pts) else \
            np.empty((0, 3))
        hit_mask = np.ones(len(end_keys), bool)
        if carve_only.any():
            co = carve_only[order]
            hit_mask = np.logical_and.reduceat(~co, bounds) if len(co) else hit_mask
        if self.ray_subdivision != 1:
            ray_end = self._ray_ends(pts)
        # --- free keys from the rays (end voxels of this scan excluded: occupied preference)
        free = self._carve(org, ray_end, end_keys)
        keep = ~carve_only[order]
        keys, lam, lam_off, cnt = self._point_sums(pk_s[keep], pts_s[keep],
                                                   None if info is None else info[order[keep]])
        return Contribution(origin=org, free=free, hit=end_keys[hit_mask], keys=keys, info=lam,
                            info_offset=lam_off, counts=cnt, n_points=len(pts),
                            n_rays=len(ray_end))

    def apply(self, c: Contribution, *, source: str = '') -> InsertResult:
        """Fuse a scan's contribution: its misses and hits into the occupancy (clamped), its
        information sums into the voxels' Gaussians (Eq. 3-10). Contributions made by a map of
        other settings give a map other than the raw scans would; the caller checks that."""
        m = self.model
        free, occ_keys = c.free, c.hit
        # --- occupancy update
        upd_keys = np.concatenate([free, occ_keys])
        delta = np.concatenate([np.full(free.size, m.miss_q, np.int32),
                                np.full(occ_keys.size, m.hit_q, np.int32)])
        srt = np.argsort(upd_keys)  # keys are distinct
        upd_keys, delta = upd_keys[srt], delta[srt]
        pos, found = self._find(upd_keys)
        lo = self.logodds[pos[found]].astype(np.int32) + delta[found]
        self.logodds[pos[found]] = np.clip(lo, m.min_q, m.max_q)
        new = ~found
        n_new = int(new.sum())
        if n_new:
            ins = pos[new]
            nk = upd_keys[new]
            self.keys = np.insert(self.keys, ins, nk)
            self.logodds = np.insert(self.logodds, ins,
                                     np.clip(delta[new], m.min_q, m.max_q).astype(np.int16))
            self.mean_off = np.insert(self.mean_off, ins, np.zeros((n_new, 3), np.float16),
                                      axis=0)
            self.chol = np.insert(self.chol, ins, np.zeros((n_new, 6), np.float16), axis=0)
            self.hits = np.insert(self.hits, ins, np.zeros(n_new, np.uint32))
        if len(c.keys):
            self._merge_sums(c.keys, c.info, c.info_offset, c.counts)
        self.sequence += 1
        if source:
            self.contributions[source] += 1
        return InsertResult(changed=upd_keys, n_points=c.n_points, n_rays=c.n_rays,
                            n_free_updates=int(free.size), n_occupied_updates=int(occ_keys.size),
                            n_new=n_new)

    def _ray_ends(self, pts: np.ndarray) -> np.ndarray:
        if self.ray_subdivision == 0 or len(pts) == 0:
            return pts
        sub = pack_keys(np.floor(pts * (self.ray_subdivision / self.resolution))
                        .astype(np.int64))
        _, inv, cnt = np.unique(sub, return_inverse=True, return_counts=True)
        return np.stack([np.bincount(inv, pts[:, i]) for i in range(3)], -1) / cnt[:, None]

    def _carve(self, org: np.ndarray, ray_end: np.ndarray, end_keys: np.ndarray
               ) -> np.ndarray:
        """Sorted packed keys of the voxels crossed by the rays org -> ray_end, minus
        `end_keys`. Visits are deduplicated in a dense bitmap over the scan's bounding box when
        that box is small compared with the number of visits (a scatter + flatnonzero is several
        times faster than hashing or sorting the visits), else with np.unique."""
        if len(ray_end) == 0:
            return np.empty(0, np.int64)
        res = self.resolution
        s_key = np.floor(org * (1.0 / res)).astype(np.int64)
        e_key = np.floor(ray_end * (1.0 / res)).astype(np.int64)
        pack_keys(s_key[None])
        n_visits = int(np.abs(e_key - s_key).sum()) + len(ray_end)
        k0 = np.minimum(e_key.min(0), s_key)
        dims = np.maximum(e_key.max(0), s_key) - k0 + 1
        box = int(np.prod(dims))
        if box <= max(4 * n_visits, 1 << 20) and box <= 1 << 26:
            bitmap = np.zeros(box, bool)
            dy, dz = int(dims[1]), int(dims[2])
            mark = bitmap.view(np.uint8)  # an integer scatter is cheaper than a bool one
            for lin in _ray_lin(org, ray_end, res, k0, (dy * dz, dz, 1)):
                mark[lin] = 1
            el = e_key - k0
            bitmap[(el[:, 0] * dy + el[:, 1]) * dz + el[:, 2]] = False
            lin = np.flatnonzero(bitmap)
            kz = lin % dz
            rest = lin // dz
            return _pack_unchecked(rest // dy + k0[0], rest % dy + k0[1], kz + k0[2])
        # bounded batches keep the per-visit temporaries under ~100 MB (_ray_lin batches itself)
        batch = max(1, 2_000_000 // max(1, n_visits // len(ray_end)))
        parts = []
        for i in range(0, len(ray_end), batch):
            parts.append(np.unique(np.concatenate(
                [_pack_unchecked(*v) for v in _ray_visits(org[None], ray_end[i:i + batch],
                                                          res)])))
        free = np.unique(np.concatenate(parts))
        return free[~np.isin(free, end_keys, assume_unique=True)]

    @property
    def extent_variance(self) -> float:
        """res^2 / 12: per-axis variance of a point uniform over the voxel (0 without the
        voxel prior)."""
        return self.resolution ** 2 / 12.0 if self.voxel_prior else 0.0

    def _point_sums(self, pk_s: np.ndarray, pts_s: np.ndarray, info_s: np.ndarray | None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Eq. 3-8/3-10 in information form, per voxel of the (key-sorted) points: the voxel
        keys, Lambda = sum C_i^-1 (K, 6), Lambda-weighted offsets sum C_i^-1 (x_i - centre)
        (K, 3) and the point counts. Any order of pairwise Eq. 3-10 products gives the same
        sums (the product is associative); offsets from the voxel centre keep them small.
        info_s: each point's information (C_i + V)^-1 (None: the isotropic default_sigma)."""
        if len(pk_s) == 0:
            return (np.empty(0, np.int64), np.empty((0, 6)), np.empty((0, 3)),
                    np.empty(0, np.int64))
        bounds = np.flatnonzero(np.r_[True, pk_s[1:] != pk_s[:-1]])
        keys = pk_s[bounds]
        cnt = np.diff(np.r_[bounds, len(pk_s)])
        centre = (unpack_keys(pk_s) + 0.5) * self.resolution
        off = pts_s - centre
        if info_s is None:
            w = 1.0 / (self.default_sigma ** 2 + self.extent_variance)
            lam = np.zeros((len(keys), 6))
            lam[:, [0, 3, 5]] = (w * cnt)[:, None]
            lam_off = np.add.reduceat(off, bounds, axis=0) * w
        else:
            lam = np.add.reduceat(info_s, bounds, axis=0)
            lam_off = np.add.reduceat(sym6_matvec(info_s, off), bounds, axis=0)
        return keys, lam, lam_off, cnt

    def _merge_sums(self, keys: np.ndarray, lam: np.ndarray, lam_off: np.ndarray,
                    cnt: np.ndarray) -> None:
        """Multiply each voxel's Gaussian by the points' factor (`_point_sums`); with the voxel
        prior, C_i + V and a first factor N(centre, V), V = res^2/12 I (module docstring)."""
        pos, found = self._find(keys)
        if not np.all(found):
            raise AssertionError('end voxels missing from the map after the occupancy update')
        res = self.resolution
        v = self.extent_variance
        lam = np.array(lam, np.float64)          # sums in the voxel-centre frame
        eta = np.array(lam_off, np.float64)
        old = self.hits[pos] > 0
        if old.any():
            c_old = sym6_from_cholesky(self.chol[pos[old]].astype(np.float64)) * res * res
            l_old = sym6_inv(c_old)
            lam[old] += l_old
            eta[old] += sym6_matvec(l_old, self.mean_off[pos[old]].astype(np.float64) * res)
        if v and not old.all():  # first points of a voxel: the prior factor, at the centre
            lam[~old, 0] += 1.0 / v
            lam[~old, 3] += 1.0 / v
            lam[~old, 5] += 1.0 / v
        c_new = sym6_inv(lam)
        self.mean_off[pos] = (sym6_matvec(c_new, eta) / res).astype(np.float16)
        try:
            L = sym6_cholesky(c_new / (res * res))
        except NotPositiveDefinite as exc:  # pragma: no cover - guarded by sym6_inv above
            raise MapInputError(str(exc)) from exc
        # float16 has a 6e-8 floor: keep tiny sigmas representable rather than zero
        L16 = L.astype(np.float16)
        diag = L16[:, [0, 3, 5]]
        L16[:, [0, 3, 5]] = np.maximum(diag, np.float16(6e-5))
        self.chol[pos] = L16
        self.hits[pos] = np.minimum(self.hits[pos].astype(np.uint64) + cnt,
                                    np.iinfo(np.uint32).max).astype(np.uint32)

    def largest_mean_distance(self, other: VoxelMap) -> float:
        """The largest distance (m) between this map's merged means and `other`'s, over the
        voxels with points here that `other` knows (nan: none): two maps of the same scans
        compared."""
        pos, found = other._find(self.keys)
        both = np.flatnonzero(found & (self.hits > 0))
        if not both.size:
            return float('nan')
        d = self.mean_off[both].astype(float) - other.mean_off[pos[both]].astype(float)
        return float(np.linalg.norm(d, axis=1).max() * self.resolution)

    # ------------------------------------------------------------------ fusion of maps
    def merge_map(self, other: VoxelMap) -> None:
        """Fuse another map of the same resolution and model (e.g. one rover's map into the
        team's): log-odds add with clamping, Gaussians multiply (Eq. 3-10)."""
        if (other.resolution != self.resolution or other.model != self.model
                or other.voxel_prior != self.voxel_prior):
            raise ValueError('maps differ in resolution, occupancy model or voxel prior')
        m = self.model
        pos, found = self._find(other.keys)
        lo = self.logodds[pos[found]].astype(np.int32) + other.logodds[found]
        self.logodds[pos[found]] = np.clip(lo, m.min_q, m.max_q)
        # Gaussians of voxels known to both
        both = found & (other.hits > 0)
        if both.any():
            p = pos[both]
            mine = self.hits[p] > 0
            res = self.resolution
            centre = (unpack_keys(other.keys[both]) + 0.5) * res
            c2 = sym6_from_cholesky(other.chol[both].astype(np.float64)) * res * res
            m2 = centre + other.mean_off[both].astype(np.float64) * res
            lam = sym6_inv(c2)
            eta = sym6_matvec(lam, m2)
            if mine.any():
                c1 = sym6_from_cholesky(self.chol[p[mine]].astype(np.float64)) * res * res
                l1 = sym6_inv(c1)
                lam[mine] += l1
                eta[mine] += sym6_matvec(l1, centre[mine]
                                         + self.mean_off[p[mine]].astype(np.float64) * res)
                v = self.extent_variance
                if v:  # both Gaussians hold the voxel prior: count it once
                    lam[mine, 0] -= 1.0 / v
                    lam[mine, 3] -= 1.0 / v
                    lam[mine, 5] -= 1.0 / v
                    eta[mine] -= centre[mine] / v
            c = sym6_inv(lam)
            self.mean_off[p] = ((sym6_matvec(c, eta) - centre) / res).astype(np.float16)
            self.chol[p] = sym6_cholesky(c / (res * res)).astype(np.float16)
            self.hits[p] = np.minimum(self.hits[p].astype(np.uint64) + other.hits[both],
                                      np.iinfo(np.uint32).max).astype(np.uint32)
        new = ~found
        if new.any():
            ins = pos[new]
            self.keys = np.insert(self.keys, ins, other.keys[new])
            self.logodds = np.insert(self.logodds, ins, other.logodds[new])
            self.mean_off = np.insert(self.mean_off, ins, other.mean_off[new], axis=0)
            self.chol = np.insert(self.chol, ins, other.chol[new], axis=0)
            self.hits = np.insert(self.hits, ins, other.hits[new])
        self.contributions.update(other.contributions)
        self.sequence += 1

    # ------------------------------------------------------------------ queries
    def probability(self) -> np.ndarray:
        """Occupancy probability of every stored voxel, parallel to `keys`."""
        return 1.0 / (1.0 + np.exp(-self.logodds.astype(np.float64) / LOGODDS_SCALE))

    def states(self) -> np.ndarray:
        """FREE / OCCUPIED per stored voxel, parallel to `keys`."""
        return np.where(self.logodds >= self.model.thr_q, OCCUPIED, FREE).astype(np.int8)

    def probability_at(self, points: np.ndarray) -> np.ndarray:
        """P(occupied) at each (N, 3) finite point, 0.5 where unknown (a point beyond the
        keys' range, which no voxel can hold, included)."""
        # the float keys as key_of computes them (the same voxel at a face), checked for range
        kf = np.floor(np.atleast_2d(np.asarray(points, np.float64)) * (1.0 / self.resolution))
        out = np.full(len(kf), 0.5)
        ok = np.all((kf >= -_OFFSET) & (kf < _OFFSET), axis=1)
        pos, found = self._find(pack_keys(kf[ok].astype(np.int64)))
        lo = self.logodds[pos[found]].astype(np.float64) / LOGODDS_SCALE
        out[np.flatnonzero(ok)[found]] = 1.0 / (1.0 + np.exp(-lo))
        return out

    def state_of_keys(self, packed: np.ndarray) -> np.ndarray:
        """UNKNOWN / FREE / OCCUPIED for packed keys."""
        pos, found = self._find(np.asarray(packed, np.int64))
        out = np.full(len(packed), UNKNOWN, np.int8)
        out[found] = np.where(self.logodds[pos[found]] >= self.model.thr_q, OCCUPIED, FREE)
        return out

    def box_counts(self, lo: np.ndarray, hi: np.ndarray) -> dict[str, int]:
        """Unknown / free / occupied voxel counts of the voxels whose centre is in [lo, hi]
        (of those the keys can address: the box is clipped to their range). Python ints:
        exact however large the box."""
        lo = np.asarray(lo, float)
        hi = np.asarray(hi, float)
        if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))) or np.any(hi <= lo):
            raise ValueError('box_max must exceed box_min on every axis, both finite')
        klo = np.clip(np.ceil(lo / self.resolution - 0.5), -_OFFSET, _OFFSET).astype(np.int64)
        khi = np.clip(np.floor(hi / self.resolution - 0.5), -_OFFSET - 1,
                      _OFFSET - 1).astype(np.int64)
        total = math.prod(max(int(b) - int(a) + 1, 0) for a, b in zip(klo, khi, strict=False))
        k = unpack_keys(self.keys)
        inside = np.all((k >= klo) & (k <= khi), axis=1)
        occ = int(np.count_nonzero(self.logodds[inside] >= self.model.thr_q))
        known = int(inside.sum())
        return {'unknown': total - known, 'free': known - occ, 'occupied': occ}

    def gaussians(self, packed: np.ndarray | None = None
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(keys, mean (N, 3), covariance (N, 6), hits) of the voxels with a Gaussian
        (hits > 0), optionally restricted to `packed` keys."""
        if packed is None:
            idx = np.flatnonzero(self.hits > 0)
        else:
            pos, found = self._find(np.asarray(packed, np.int64))
            idx = pos[found]
            idx = idx[self.hits[idx] > 0]
        res = self.resolution
        keys = self.keys[idx]
        centre = (unpack_keys(keys) + 0.5) * res
        mean = centre + self.mean_off[idx].astype(np.float64) * res
        cov = sym6_from_cholesky(self.chol[idx].astype(np.float64)) * res * res
        return keys, mean, cov, self.hits[idx]

    def surface_points(self, packed: np.ndarray | None = None, *,
                       bandwidth: float = SURFACE_BANDWIDTH, radius: int = SURFACE_RADIUS
                       ) -> tuple[np.ndarray, np.ndarray]:
        """(keys, points (N, 3)): a surface point for each voxel with a Gaussian (hits > 0),
        optionally only those among `packed`.

        Once the range noise exceeds the voxel size, the points of a surface straddle several
        voxels, and those that land in one voxel are a truncated sample of that spread: its
        mean is pulled towards the voxel centre (bench/map_vs_octomap.py: at 0.05 m the merged
        means err 0.8x as much as the leaf centres, where the noise is below the voxel 0.3x).
        Pooling the neighbours restores the whole spread: the point is the kernel-weighted
        centroid of the merged means of the voxels around this one, each weighted by the
        points it holds, hits x exp(-|o|^2 / (2 bandwidth^2)), o the integer offset of the
        neighbour (voxels) within the (2 radius + 1)^3 block: one mean-shift step from the
        voxel towards the local mode of the point density. `bandwidth` (voxels): the bench's
        stereo scene measured 0.6-1.0 alike; wider kernels blur curved surfaces."""
        keys_all, mean_all, _, hits_all = self.gaussians()
        keys = keys_all if packed is None else \
            keys_all[np.isin(keys_all, np.asarray(packed, np.int64))]
        return keys, kernel_centroids(keys_all, mean_all, hits_all, keys, bandwidth=bandwidth,
                                      radius=radius)

    def occupied_keys(self) -> np.ndarray:
        """Sorted packed keys of the occupied voxels."""
        return self.keys[self.logodds >= self.model.thr_q]

    def occupied_centres(self) -> np.ndarray:
        """(N, 3) centres of the occupied voxels."""
        return self.centres(self.occupied_keys())

    def slice_grid(self, z: float) -> tuple[np.ndarray, np.ndarray]:
        """2-D occupancy of the voxel layer containing height z over the map's x-y extent:
        (origin xy of cell (0, 0) corner, int8 grid [row = y, col = x]) with -1 unknown and
        0..100 the occupancy probability in percent (nav_msgs/OccupancyGrid convention)."""
        kz = int(np.floor(z / self.resolution))
        k = unpack_keys(self.keys)
        if len(k) == 0:
            return np.zeros(2), np.full((1, 1), -1, np.int8)
        lo, hi = k[:, :2].min(0), k[:, :2].max(0)
        grid = np.full((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), -1, np.int8)
        layer = k[:, 2] == kz
        p = self.probability()[layer]
        grid[k[layer, 1] - lo[1], k[layer, 0] - lo[0]] = np.round(100 * p).astype(np.int8)
        return lo * self.resolution, grid

    def centres(self, packed: np.ndarray) -> np.ndarray:
        return (unpack_keys(packed) + 0.5) * self.resolution

    def frustum(self, R_wc: np.ndarray, t_wc: np.ndarray, *, fov_x: float, fov_y: float,
                near: float, far: float, max_voxels: int = 20_000_000
                ) -> tuple[np.ndarray, np.ndarray]:
        """Packed keys of the (known, unknown) voxels whose centres lie in a camera frustum.

        R_wc, t_wc: optical frame (z forward, x right, y down) in the map frame; fov in rad."""
        R = np.asarray(R_wc, float)
        t = np.asarray(t_wc, float)
        if not (0 < fov_x < np.pi and 0 < fov_y < np.pi and 0 <= near < far):
            raise ValueError('need 0 < fov < pi and 0 <= near < far')
        tx, ty = np.tan(fov_x / 2), np.tan(fov_y / 2)
        corners = np.array([[sx * tx * z, sy * ty * z, z] for z in (near, far)
                            for sx in (-1, 1) for sy in (-1, 1)])
        cw = corners @ R.T + t
        klo = np.floor(cw.min(0) / self.resolution).astype(np.int64)
        khi = np.floor(cw.max(0) / self.resolution).astype(np.int64)
        dims = khi - klo + 1
        if int(np.prod(dims)) > max_voxels:
            raise ValueError(f'frustum bounding box has {int(np.prod(dims))} voxels '
                             f'> max_voxels {max_voxels}')
        known, unknown = [], []
        gy2, gz2 = np.meshgrid(np.arange(klo[1], khi[1] + 1), np.arange(klo[2], khi[2] + 1),
                               indexing='ij')
        gy, gz = gy2.ravel(), gz2.ravel()
        for x in range(klo[0], khi[0] + 1):  # one slab at a time bounds the memory
            k = np.stack([np.full(gy.size, x), gy, gz], -1)
            pc = ((k + 0.5) * self.resolution - t) @ R
            z = pc[:, 2]
            ok = (z >= near) & (z <= far) & (np.abs(pc[:, 0]) <= tx * z) & \
                (np.abs(pc[:, 1]) <= ty * z)
            pk = pack_keys(k[ok])
            _, found = self._find(pk)
            known.append(pk[found])
            unknown.append(pk[~found])
        return np.concatenate(known), np.concatenate(unknown)

    def raycast(self, origin: np.ndarray, direction: np.ndarray, max_range: float, *,
                unknown_is_occupied: bool = False) -> np.ndarray | None:
        """Centre of the first occupied voxel along a ray (or unknown, if asked), else None."""
        d = np.asarray(direction, float)
        nd = np.linalg.norm(d)
        if not nd > 0 or not max_range > 0:
            raise ValueError('direction must be non-zero and max_range > 0')
        o = np.asarray(origin, float)
        end = o + d / nd * max_range
        keys = ray_voxel_keys(o, end[None], self.resolution)
        keys = np.append(keys, pack_keys(self.key_of(end[None])))
        # order along the ray by the distance of the voxel centres from the origin
        cen = self.centres(keys)
        keys = keys[np.argsort(np.linalg.norm(cen - o, axis=1), kind='stable')]
        st = self.state_of_keys(keys)
        hit = (st == OCCUPIED) | ((st == UNKNOWN) if unknown_is_occupied else False)
        idx = np.flatnonzero(hit)
        return None if idx.size == 0 else self.centres(keys[idx[:1]])[0]

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike) -> None:
        """Versioned file (zip of .npy + JSON header), written to a temporary file in the same
        directory and moved into place with os.replace (coop_common.files.write_atomic): a
        reader never sees a half file."""
        header = {'format': FILE_FORMAT, 'version': FILE_VERSION,
                  'resolution': self.resolution, 'sequence': self.sequence,
                  'default_sigma': self.default_sigma, 'voxel_prior': self.voxel_prior,
                  'model': self.model.__dict__, 'contributions': dict(self.contributions),
                  'ledger': self.ledger.to_json(), 'voxels': len(self)}

        def write(f: IO[bytes]) -> None:
            with zipfile.ZipFile(f, 'w', compression=zipfile.ZIP_STORED) as z:
                z.writestr('header.json', json.dumps(header))
                for name, arr in self._arrays().items():
                    buf = io.BytesIO()
                    np.save(buf, arr, allow_pickle=False)
                    z.writestr(name + '.npy', buf.getvalue())
        write_atomic(path, 'wb', write)

    @classmethod
    def load(cls, path: str | os.PathLike) -> VoxelMap:
        """Read a file written by save(); MapFileError on any problem (CRC checked)."""
        try:
            with zipfile.ZipFile(path) as z:
                bad = z.testzip()
                if bad is not None:
                    raise MapFileError(f'{path}: corrupted member {bad}')
                header = json.loads(z.read('header.json'))
                if not isinstance(header, dict) or header.get('format') != FILE_FORMAT:
                    raise MapFileError(f'{path}: not a voxel map file')
                if header.get('version') != FILE_VERSION:
                    raise MapFileError(f'{path}: unsupported version {header.get("version")}')
                arrs = {name: np.load(io.BytesIO(z.read(name + '.npy')), allow_pickle=False)
                        for name in ('keys', 'logodds', 'mean_off', 'chol', 'hits')}
        except MapFileError:
            raise
        except FileNotFoundError as exc:
            raise MapFileError(f'{path}: no such file') from exc
        except (zipfile.BadZipFile, KeyError, ValueError, OSError, EOFError,
                json.JSONDecodeError, NotImplementedError, RuntimeError, zlib.error) as exc:
            # a flipped byte in a member's header can name a compression method zipfile lacks
            # (NotImplementedError), set the encryption flag (RuntimeError) or give deflate
            # a stored member (zlib.error)
            raise MapFileError(f'{path}: unreadable map file ({exc})') from exc
        try:
            n = int(header['voxels'])
            expect = {'keys': ((n,), np.int64), 'logodds': ((n,), np.int16),
                      'mean_off': ((n, 3), np.float16), 'chol': ((n, 6), np.float16),
                      'hits': ((n,), np.uint32)}
            for name, (shape, dt) in expect.items():
                if arrs[name].shape != shape or arrs[name].dtype != dt:
                    raise MapFileError(f'{path}: array {name} has shape {arrs[name].shape} '
                                       f'{arrs[name].dtype}, expected {shape} {np.dtype(dt)}')
            if n > 1 and np.any(np.diff(arrs['keys']) <= 0):
                raise MapFileError(f'{path}: keys not strictly sorted')
            m = cls(header['resolution'], model=OccupancyModel(**header['model']),
                    default_sigma=header['default_sigma'],
                    # files written before the voxel prior existed merged raw points only
                    voxel_prior=bool(header.get('voxel_prior', False)))
            for name, arr in arrs.items():
                setattr(m, name, arr)
            m.sequence = int(header['sequence'])
            m.contributions = Counter({str(k): int(v)
                                       for k, v in header['contributions'].items()})
            m.ledger = ContributionLedger.from_json(header.get('ledger', {}))
            # both go out as uint64 (VoxelMap message, MapFile answer)
            for what, v in [('sequence', m.sequence), *m.contributions.items()]:
                if not 0 <= v < 2 ** 64:
                    raise ValueError(f'{what} {v} outside 0 .. 2^64 - 1')
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            raise MapFileError(f'{path}: bad header ({exc!r})') from exc
        return m
