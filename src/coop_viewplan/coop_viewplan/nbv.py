"""Next-best-view selection for environment modelling (thesis §3.2.4, §3.3.1).

Candidates: a finite set of O(m) camera configurations (§3.3.1) on known free cells with
P < P_empty = 0.05 (constraint (i)), reachable through known free space (constraint (ii),
geodesic distance on the grid), rated by RF = (NI - K d^n)(1 - P) (Eq. 3-15) with d the weighted
configuration distance (Eq. 3-11) and NI the expected new information (Eq. 3-12b..3-14).

Reading of Eq. 3-12b..3-14 used here (the thesis leaves the details open):
* gray value of a cell: its occupancy p if known (0 if the map holds it free, p < 0.5: known
  empty space, `NbvConfig.free_gray`), else the Markov-chain estimate (neighbour average,
  `grid.gray_estimate` / `grid.markov_estimate`);
* the scene distribution is a uniform discretisation of p (the thesis's "alternatively (better)")
  into `n_gray` levels, evaluated separately for known and unknown cells (Eq. 3-12b); Eq. 3-14's
  stretching divides by the cell's distance d_voxel, making the level distance dependent - we
  realise it by also splitting each level into `n_shells` equal range shells, which keeps every
  q_k = f_k / N <= 1/e so NI grows with every extra unknown cell in view (as §3.2.4 requires);
* N is the number of cells in the unobstructed frustum (Eq. 3-13's "maximum number of voxels
  visible");
* each -q_k log2 q_k is premultiplied by -p_k log2 p_k, as §3.2.4 writes it, with p_k the mean
  over the cells in level k of -p log2 p (`entropy_weight='plogp'`, the default since
  2026-11-21); `entropy_weight='binary'` (the earlier reading, -p log2 p - (1-p) log2 (1-p),
  largest at p = 0.5) remains as an option. Either way a field of view that is entirely known
  (p = 0 or 1) gives NI = 0.
* `ni_measure='predictor5'` (App. C: predictor 5 "is extended to the information theoretic
  vision planning algorithm in chapter 3") bins the cells by the predictor-5 residual of the
  view's gray image instead of by level (`predictor5_codes`); the default is the histogram.

Occlusion by unknown space (`NbvConfig.unknown_occlusion`, beyond the thesis):
* 'none' (default, §3.2.4 (iv) "based on the known obstacles"): only known occupied cells block
  the expected view; every unknown cell behind other unknown cells counts in full.
* 'expected': each visible sample is weighted by the probability that it is seen,
  P(visible) = prod over the distinct cells j before it on its ray of (1 - p_j)
  (`raycast.expected_visibility`; Isler et al., ICRA 2016; Kriegel et al.), with p_j the
  occupancy estimate of `grid.occlusion_estimate` (`NbvConfig.occlusion_prior`: 'density'
  (default), the planner's Markov chain started from the known map's obstacle density - known
  occupied over known cells, i.e. the rate at which the scans' rays were stopped per cell
  crossed; 'markov', the planner's gray estimate as it is, 0.5 far from the map, which makes a
  ray through unknown space die within a few cells and took more scans in every Fig. 3-13
  run).
  NI's histogram counts f_k become expected counts sum w P(visible) (the quadrature weights w
  times the visibility), and the -p log2 p premultiplier the visibility-weighted mean over
  level k; N (the unobstructed frustum), the per-cell gray values and weights are unchanged.
  K's reference (`max_information`, a fully unknown unobstructed view) is unchanged too, so the
  same k_rel weighs distance relatively more. The cell counts of max_unmapped / min_mapped stay
  the thesis's (known occlusions only); `ViewScores.unknown_expected` holds the expected unknown
  count. The cells claimed for another camera are those seen with P >= 0.5.

Constraints (i) and (ii) on a map (`NbvConfig.reach_model`):
* 'known' (the planar experiments): a cell is navigable, and a candidate, when it is known and
  the largest occupancy within the rover's clearance is below P_empty (unknown counts 0.5; in
  3-D the whole slab column the rover sweeps must be known). P is that footprint maximum.
* 'evidence' (the node on the live stereo map): (ii) a rover may pass wherever its clearance
  disk holds no column with evidence of an obstacle - at least `occupied_voxels` slab voxels
  with P >= `occupied_p`, or one at the occupancy clamp (a lone stereo speckle does not block,
  a real surface does; 0.7 is one stereo hit that no later ray has crossed: far-range points
  that a nearer view carves are no obstacle); unobserved space is not an obstacle for the path.
  (i) is the thesis's test on the goal pose itself: the voxel at the camera's height is known
  with P < P_empty, and P of Eq. 3-15 is its occupancy (1 where an obstacle column is within the
  clearance).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, assert_never

import numpy as np
from numpy.typing import ArrayLike
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from coop_common.params import choice
from coop_common.rover_geometry import CAMERA_FROM_BASE_M

from .errors import OptionError, ViewplanError
from .grid import (
    FreeGray,
    MapError,
    OcclusionPrior,
    OccupancyGrid,
    gray_estimate,
    occlusion_estimate,
)
from .imageinfo import prediction
from .raycast import (
    Cast,
    RayTemplate,
    cast,
    expected_visibility,
    make_template,
    ray_prefix_visibility,
    transmission_table,
)

if TYPE_CHECKING:    # for annotations only
    from scipy.sparse import csr_matrix


class StrategyName(StrEnum):
    """The exploration strategies of Figs. 3-13/3-16/3-20 (the thesis's five) and frontier."""

    RANDOM = 'random'
    RASTER = 'raster'
    MAX_UNMAPPED = 'max_unmapped'
    MIN_MAPPED = 'min_mapped'
    MAX_INFORMATION = 'max_information'
    FRONTIER = 'frontier'


class UnknownOcclusion(StrEnum):
    """'none': unknown cells do not occlude (the thesis); 'expected': they occlude with their
    expected occupancy (beyond the thesis, module docstring)."""

    NONE = 'none'
    EXPECTED = 'expected'


class EntropyWeight(StrEnum):
    """The NI premultiplier: 'plogp' (§3.2.4 as written) or 'binary' (occupancy entropy)."""

    PLOGP = 'plogp'
    BINARY = 'binary'


class NiMeasure(StrEnum):
    """NI from the gray-level histogram (Eq. 3-13) or App. C's predictor 5."""

    HISTOGRAM = 'histogram'
    PREDICTOR5 = 'predictor5'


class DistanceMetric(StrEnum):
    """d of Eq. 3-15: 'configuration' (Eq. 3-11, the thesis) or the 'path' length."""

    CONFIGURATION = 'configuration'
    PATH = 'path'


class ReachModel(StrEnum):
    """Where a rover may go: 'known' free cells, or wherever no obstacle 'evidence' blocks."""

    KNOWN = 'known'
    EVIDENCE = 'evidence'


STRATEGIES = tuple(StrategyName)
UNKNOWN_OCCLUSIONS = tuple(UnknownOcclusion)


class PlanningError(ViewplanError, RuntimeError):
    """No admissible view (no free reachable candidate, camera outside the map, ...)."""


def plogp(p: np.ndarray) -> np.ndarray:
    """-p log2 p (the §3.2.4 premultiplier of q_k log2 q_k), 0 at p = 0 and 1."""
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        h = -p * np.log2(p)
    return np.nan_to_num(h, nan=0.0)


ENTROPY_WEIGHTS = tuple(EntropyWeight)


def occupancy_weight(p: np.ndarray, *,
                     weight: EntropyWeight | str = EntropyWeight.PLOGP) -> np.ndarray:
    """The weight of a cell of occupancy p in NI: 'plogp' (-p log2 p, §3.2.4 as written) or
    'binary' (the binary occupancy entropy); another weight is refused (OptionError)."""
    weight = choice(EntropyWeight, weight, 'entropy_weight', error=OptionError)
    match weight:
        case EntropyWeight.PLOGP:
            return plogp(p)
        case EntropyWeight.BINARY:
            return binary_entropy(p)
        case _:
            assert_never(weight)


def binary_entropy(p: np.ndarray) -> np.ndarray:
    """-p log2 p - (1 - p) log2 (1 - p), 0 at p = 0 and 1."""
    p = np.clip(np.asarray(p, dtype=np.float64), 0.0, 1.0)
    with np.errstate(divide='ignore', invalid='ignore'):
        h = -(p * np.log2(p) + (1 - p) * np.log2(1 - p))
    return np.nan_to_num(h, nan=0.0)


@dataclass(frozen=True)
class MastView:
    """A camera view a mast reaches, relative to its pan (turntable) axis: the camera's offset
    from the axis along the turntable's heading and to its left (m), its height above the
    ground (m), the heading of its optical axis relative to the turntable's (rad) and its
    nose-down pitch (rad). A planner given a tuple of them (`NbvConfig.mast_views`) places
    each candidate's camera where one of them puts it, with the turntable turned so that the
    optical axis has the candidate's heading (issue #37: the BRAID mast's reachable views,
    `coop_viewplan.mast`)."""

    forward_m: float
    lateral_m: float
    height_m: float
    heading_rad: float
    pitch_rad: float

    def __post_init__(self) -> None:
        for name in ('forward_m', 'lateral_m', 'height_m', 'heading_rad', 'pitch_rad'):
            if not np.isfinite(getattr(self, name)):
                raise OptionError(f'MastView.{name} must be finite, got {getattr(self, name)}')
        if not -np.pi / 2 < self.pitch_rad < np.pi / 2:
            raise OptionError(f'MastView.pitch_rad must be within +-90 deg, got '
                              f'{self.pitch_rad}')


@dataclass(frozen=True)
class NbvConfig:
    """Planner settings. K is given relative: moving one depth of field costs `k_rel` times the
    NI of a fully unknown, unobstructed view (so K has bits/m^n units without hand scaling)."""

    fov_deg: float = 90.0
    depth_m: float = 15.0
    vfov_deg: float | None = None
    n_az: int | None = None
    n_el: int | None = None
    step_cells: float = 0.5
    n_gray: int = 10
    n_shells: int = 8
    k_rel: float = 0.15
    n_exp: float = 1.0
    # Eq. 3-11 weights over (x, y, z, yaw, pitch): "alpha_i = 1 for this thesis" (§3.2.4 (iii));
    # metres and radians
    alpha: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0)
    entropy_weight: EntropyWeight = EntropyWeight.PLOGP     # the NI premultiplier
    ni_measure: NiMeasure = NiMeasure.HISTOGRAM            # Eq. 3-13, or App. C's predictor
    free_gray: FreeGray = FreeGray.EMPTY                   # known free cells' gray
    n_positions: int = 80
    near_fraction: float = 0.0    # share of the candidate positions taken nearest (path) first
    n_yaw: int = 8
    pitches_deg: tuple[float, ...] = (0.0,)
    camera_height_m: float = 1.0
    ground_clearance_m: float = 0.2
    p_empty: float = 0.05
    clearance_m: float = 1.0
    markov_iterations: int = 6
    raster_spacing_m: float | None = None
    raster_headings: int = 0      # > 0: raster sweeps this many headings at each location
    distance_metric: DistanceMetric = DistanceMetric.CONFIGURATION    # d of Eq. 3-15
    chunk_samples: int = 400_000
    reach_model: ReachModel = ReachModel.KNOWN     # where a rover may go (module docstring)
    occupied_voxels: int = 2                   # 'evidence': occupied slab voxels that block
    occupied_p: float = 0.7                    # 'evidence': P at which a slab voxel counts
    occupied_clamp: float = 0.97               # 'evidence': one voxel this sure blocks alone
    unknown_occlusion: UnknownOcclusion = UnknownOcclusion.NONE       # (module docstring)
    occlusion_prior: OcclusionPrior = OcclusionPrior.DENSITY  # 'expected': unknown cells' p
    ni_floor: float = 0.0                      # max_information: skip views below this share
                                               # of the decision's best NI (0: the thesis)
    # the views the camera's mast reaches (3-D only); empty: a pan/tilt head at
    # camera_height_m taking every pitch of pitches_deg
    mast_views: tuple[MastView, ...] = ()

    def __post_init__(self) -> None:
        """Every mode taken as its StrEnum member (OptionError naming the choices for any
        other value), the ranges checked."""
        if not 0.5 <= self.occupied_p <= 1.0:
            raise OptionError(f'occupied_p must be within [0.5, 1], got {self.occupied_p}')
        if not 0.0 <= self.ni_floor < 1.0:
            raise OptionError(f'ni_floor must be within [0, 1), got {self.ni_floor}')
        if not all(isinstance(v, MastView) for v in self.mast_views):
            raise OptionError('mast_views must be MastView instances')
        object.__setattr__(self, 'mast_views', tuple(self.mast_views))
        for name, kind in self._CHOICES.items():
            object.__setattr__(self, name, choice(kind, getattr(self, name), name,
                                                  error=OptionError))

    _CHOICES: ClassVar[dict[str, type[StrEnum]]] = {
        'entropy_weight': EntropyWeight, 'ni_measure': NiMeasure, 'free_gray': FreeGray,
        'distance_metric': DistanceMetric, 'reach_model': ReachModel,
        'unknown_occlusion': UnknownOcclusion, 'occlusion_prior': OcclusionPrior}

    @classmethod
    def thesis(cls, **changes: Any) -> NbvConfig:
        """The planner as ch. 3 specifies it: alpha_i = 1, -p log p, the gray-level NI, known
        empty space at NI 0, Eq. 3-11 distance, unknown space that does not occlude, every
        candidate rated (the defaults)."""
        return cls(**changes)

    @classmethod
    def best_measured(cls, **changes: Any) -> NbvConfig:
        """The opt-in settings beyond the thesis that measured best against nearest-frontier
        (docs/results/exploration.md): unknown space occludes with its expected occupancy, half
        the candidates taken nearest by path, path distance, K 0.8, and an information floor of
        a quarter of the decision's best NI."""
        return cls(**{'unknown_occlusion': UnknownOcclusion.EXPECTED, 'near_fraction': 0.5,
                      'distance_metric': DistanceMetric.PATH, 'k_rel': 0.8, 'ni_floor': 0.25,
                      **changes})

    def template(self, *, ndim: int, resolution: float) -> RayTemplate:
        return make_template(ndim=ndim, fov_deg=self.fov_deg, depth_m=self.depth_m,
                             resolution=resolution, n_az=self.n_az, n_el=self.n_el,
                             vfov_deg=self.vfov_deg, step_cells=self.step_cells)


@dataclass
class Candidates:
    """M candidate poses: positions (M, ndim), yaw, pitch (M,), path length to reach (M,),
    Eq. 3-11 distance d (M,), collision probability P (M,), and the index of the mast view
    (`NbvConfig.mast_views`) each is taken with (M,; -1: the pan/tilt head), None: all -1."""

    positions: np.ndarray
    yaw: np.ndarray
    pitch: np.ndarray
    path_length: np.ndarray
    distance: np.ndarray
    collision_p: np.ndarray
    view: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.positions.shape[0])

    def take(self, sel: np.ndarray) -> Candidates:
        pos, yaw, pitch, path, dist, coll = (np.asarray(a)[sel] for a in (
            self.positions, self.yaw, self.pitch, self.path_length, self.distance,
            self.collision_p))
        return Candidates(pos, yaw, pitch, path, dist, coll,
                          view=None if self.view is None else self.view[sel])


@dataclass
class ViewScores:
    """Per candidate: NI (bits), visible unknown and known cell counts (known occlusions only),
    and with unknown_occlusion 'expected' the expected count of unknown cells seen."""

    ni: np.ndarray
    unknown_cells: np.ndarray
    known_cells: np.ndarray
    unknown_expected: np.ndarray | None = None


@dataclass
class Decision:
    """The chosen view and the ranking it came from."""

    index: int
    candidates: Candidates
    scores: ViewScores
    rating: np.ndarray
    strategy: StrategyName
    extras: dict = field(default_factory=dict)

    @property
    def position(self) -> np.ndarray:
        return self.candidates.positions[self.index]

    @property
    def yaw(self) -> float:
        return float(self.candidates.yaw[self.index])

    @property
    def pitch(self) -> float:
        return float(self.candidates.pitch[self.index])

    @property
    def path_length(self) -> float:
        return float(self.candidates.path_length[self.index])

    @property
    def view(self) -> int:
        """Index of the mast view (`NbvConfig.mast_views`) the chosen pose is taken with; -1:
        the pan/tilt head."""
        v = self.candidates.view
        return -1 if v is None else int(v[self.index])

    def ranked(self) -> np.ndarray:
        return np.argsort(-self.rating, kind='stable')


@dataclass
class CameraState:
    """Where a camera is and what it has done: position (ndim,), yaw, pitch, scan positions."""

    position: np.ndarray
    yaw: float = 0.0
    pitch: float = 0.0
    visited: list = field(default_factory=list)
    raster_cursor: int = 0
    raster_sweep_left: int = 0


# ----------------------------------------------------------------------------- information


@dataclass
class InfoLookup:
    """Per-cell quantities NI needs, computed once per map: gray level code
    (unknown * n_gray + level) and occupancy entropy."""

    code: np.ndarray
    entropy: np.ndarray
    n_gray: int

    @classmethod
    def build(cls, grid: OccupancyGrid, estimate: np.ndarray, *, n_gray: int = 10,
              claimed: np.ndarray | None = None,
              weight: EntropyWeight | str = EntropyWeight.PLOGP) -> InfoLookup:
        if n_gray < 1:
            raise ValueError('n_gray must be >= 1')
        p = np.clip(estimate.reshape(-1).astype(np.float32), 0.0, 1.0)
        level = np.minimum((p * n_gray).astype(np.int16), n_gray - 1)
        unknown = ~grid.known.reshape(-1)
        # Weight by table over 1024 levels: exact to 1e-3 bits, 10x cheaper than logs.
        table = occupancy_weight(np.linspace(0, 1, 1025), weight=weight).astype(np.float32)
        h = table[np.rint(p * 1024).astype(np.int32)]
        if claimed is not None:
            h[np.asarray(claimed, bool).reshape(-1) & unknown] = 0.0
        return cls((unknown * np.int16(n_gray) + level).astype(np.int16), h, n_gray)


NI_MEASURES = tuple(NiMeasure)


def predictor5_codes(code: np.ndarray, visible: np.ndarray, n_gray: int) -> tuple[np.ndarray,
                                                                                  int]:
    """App. C's lossless-JPEG predictor 5 on the view's gray image (Table C-1 method 5, which
    App. C says "is extended to the information theoretic vision planning algorithm in chapter
    3"): the gray levels along each ray (range sample s, the image's "W" neighbour s - 1) and
    across rays (template ray r, "N" neighbour r - 1; in 3-D the ray order is azimuth-major, so
    r - 1 is the elevation neighbour) are replaced by the residual
    I(r, s) - (I(r, s-1) + I(r-1, s) - I(r-1, s-1)). Where a neighbour is not visible the
    sample keeps its own level, as lossless JPEG keeps the first row and column.
    `code` (M, R, S): unknown * n_gray + level, any value where not visible. Returns the codes
    unknown * n_res + (residual + 2 (n_gray - 1)) and n_res = 4 n_gray - 3."""
    level = (code % n_gray).astype(np.int64)
    unknown = code >= n_gray
    pred = np.zeros_like(level)
    has = np.zeros(level.shape, bool)
    has[:, 1:, 1:] = visible[:, 1:, :-1] & visible[:, :-1, 1:] & visible[:, :-1, :-1]
    pred[:, 1:, 1:] = prediction(level, 5)
    resid = np.where(has, level - pred, level) + 2 * (n_gray - 1)
    n_res = 4 * n_gray - 3
    return unknown * n_res + resid, n_res


def expected_information(grid: OccupancyGrid, estimate: np.ndarray, casting: Cast, *,
                         n_gray: int = 10, n_shells: int = 8,
                         claimed: np.ndarray | None = None,
                         lookup: InfoLookup | None = None,
                         weight: EntropyWeight | str = EntropyWeight.PLOGP,
                         measure: NiMeasure | str = NiMeasure.HISTOGRAM,
                         visibility: np.ndarray | None = None,
                         transmission: np.ndarray | None = None) -> ViewScores:
    """NI of every cast pose (Eq. 3-12b with Eq. 3-13 q_k = f_k / N and the entropy weighting;
    see the module docstring for the reading of Eq. 3-14). `claimed` cells (bool, grid shape)
    are about to be measured by another camera and count as known-certain (weight 0).
    `measure`: 'histogram' bins the cells by gray level; 'predictor5' by the App. C predictor-5
    residual of the view's gray image (`predictor5_codes`), known and unknown still apart.
    `visibility`: the probability each sample is seen (`expected_visibility`, unknown_occlusion
    'expected'), (M, R, S) or compact (the visible samples in np.nonzero order), or computed
    here from `transmission` (`raycast.transmission_table` of the per-cell stop
    probabilities); the histogram counts become expected counts. Another measure or weight is
    refused (OptionError naming the choices)."""
    if n_shells < 1:
        raise ValueError('n_shells must be >= 1')
    measure = choice(NiMeasure, measure, 'measure', error=OptionError)
    lk = lookup if lookup is not None else InfoLookup.build(grid, estimate, n_gray=n_gray,
                                                            claimed=claimed, weight=weight)
    tpl = casting.template
    m = casting.flat.shape[0]
    mi, ri, si = np.nonzero(casting.visible)
    cellv = casting.flat[mi, ri, si]
    match measure:
        case NiMeasure.PREDICTOR5:
            full = lk.code[np.maximum(casting.flat, 0)]
            codes, n_levels = predictor5_codes(full, casting.visible, lk.n_gray)
            code = codes[mi, ri, si]
        case NiMeasure.HISTOGRAM:
            code = lk.code[cellv].astype(np.int64)
            n_levels = lk.n_gray
        case _:
            assert_never(measure)
    h = lk.entropy[cellv]
    w0 = tpl.weights[ri, si]
    if visibility is None and transmission is not None:
        visibility = ray_prefix_visibility(cellv, si, transmission)
    if visibility is None:
        w = w0
    else:
        v = visibility[casting.visible] if visibility.ndim == 3 else visibility
        w = w0 * v
    shell = np.minimum((tpl.ranges / tpl.depth_m * n_shells).astype(np.int64), n_shells - 1)
    bins = 2 * n_levels * n_shells
    key = mi * bins + code * n_shells + shell[si]
    f = np.bincount(key, weights=w, minlength=m * bins).reshape(m, bins)
    hs = np.bincount(key, weights=w * h, minlength=m * bins).reshape(m, bins)
    q = f / tpl.frustum_cells
    with np.errstate(divide='ignore', invalid='ignore'):
        mean_h = np.where(f > 0, hs / f, 0.0)
        term = np.where(q > 0, -q * np.log2(q), 0.0)
    ni = (mean_h * term).sum(axis=1)
    half = n_levels * n_shells
    if visibility is None:
        kn = f[:, :half].sum(axis=1)
        unk = f[:, half:].sum(axis=1)
        return ViewScores(ni, unk, kn)
    # the thesis's counts (known occlusions only): per-pose sums over the samples, which
    # np.nonzero lists pose by pose
    unk = np.bincount(mi, weights=w0 * (code >= n_levels), minlength=m).astype(np.float64)
    kn = np.bincount(mi, weights=w0, minlength=m) - unk
    return ViewScores(ni, unk, kn, f[:, half:].sum(axis=1))


def max_information(template: RayTemplate, *, n_gray: int = 10, n_shells: int = 8,
                    weight: EntropyWeight | str = EntropyWeight.PLOGP) -> float:
    """NI of a fully unknown, unobstructed view (p = 0.5 everywhere): the scale of K."""
    shell = np.minimum((template.ranges / template.depth_m * n_shells).astype(int), n_shells - 1)
    f = np.bincount(shell, weights=template.weights.sum(axis=0), minlength=n_shells)
    q = f / template.frustum_cells
    with np.errstate(divide='ignore', invalid='ignore'):
        h = float(np.where(q > 0, -q * np.log2(q), 0.0).sum())
    return h * float(occupancy_weight(np.array([0.5]), weight=weight)[0])


def score_views(grid: OccupancyGrid, estimate: np.ndarray, positions: np.ndarray,
                yaw: np.ndarray, pitch: np.ndarray | None, template: RayTemplate, *,
                n_gray: int = 10, n_shells: int = 8, claimed: np.ndarray | None = None,
                chunk_samples: int = 400_000, lookup: InfoLookup | None = None,
                weight: EntropyWeight | str = EntropyWeight.PLOGP,
                measure: NiMeasure | str = NiMeasure.HISTOGRAM,
                occlusion: np.ndarray | None = None) -> ViewScores:
    """Cast and score many poses in chunks of at most `chunk_samples` ray samples
    (`lookup` reuses the per-map tables across calls). `occlusion` (grid shape): per-cell
    probability that a cell stops a ray (`grid.occlusion_estimate`); given, each sample counts
    with its probability of being seen (unknown_occlusion 'expected'), else the known obstacles
    alone occlude (the thesis)."""
    positions = np.asarray(positions, dtype=float).reshape(-1, grid.ndim)
    m = positions.shape[0]
    yaw = np.broadcast_to(np.asarray(yaw, float).reshape(-1), (m,))
    pitch_a = None if pitch is None else np.broadcast_to(np.asarray(pitch, float).reshape(-1),
                                                         (m,))
    per = template.weights.size
    step = max(1, chunk_samples // per)
    parts = []
    lk = lookup if lookup is not None else InfoLookup.build(grid, estimate, n_gray=n_gray,
                                                            claimed=claimed, weight=weight)
    block = grid.occupied()
    table = None if occlusion is None else transmission_table(occlusion)
    for s in range(0, m, step):
        c = cast(grid, positions[s:s + step], yaw[s:s + step],
                 None if pitch_a is None else pitch_a[s:s + step], template, blocking=block)
        parts.append(expected_information(grid, estimate, c, n_shells=n_shells, lookup=lk,
                                          measure=measure, transmission=table))
    if not parts:
        z = np.zeros(0)
        return ViewScores(z, z, z, None if occlusion is None else z)
    keys = ('ni', 'unknown_cells', 'known_cells') + (() if occlusion is None
                                                     else ('unknown_expected',))
    return ViewScores(*(np.concatenate([getattr(p, k) for p in parts]) for k in keys))


def configuration_distance(current: np.ndarray, new: np.ndarray,
                           alpha: tuple[float, ...] | np.ndarray) -> np.ndarray:
    """Eq. 3-11: d = (sum_i alpha_i (c_i - c'_i)^2)^(1/2); angle differences wrapped to +-pi.

    Configurations are (x, y, z, yaw, pitch) rows; `alpha` weights each degree of freedom."""
    cur = np.asarray(current, dtype=float)
    new = np.atleast_2d(np.asarray(new, dtype=float))
    a = np.asarray(alpha, dtype=float)[:new.shape[1]]
    diff = new - cur
    diff[:, 3:] = (diff[:, 3:] + np.pi) % (2 * np.pi) - np.pi
    return np.sqrt((a * diff ** 2).sum(axis=1))


def rating_function(ni: np.ndarray, distance: np.ndarray, collision_p: np.ndarray, *,
                    k: float, n: float) -> np.ndarray:
    """Eq. 3-15: RF = (NI - K d^n)(1 - P)."""
    return (np.asarray(ni) - k * np.asarray(distance) ** n) * (1 - np.asarray(collision_p))


# ----------------------------------------------------------------------------- candidates


def _disk(radius_cells: int, ndim: int) -> np.ndarray:
    r = max(0, int(radius_cells))
    ax = np.arange(-r, r + 1)
    g = np.meshgrid(*([ax] * ndim), indexing='ij')
    return np.asarray(sum(x ** 2 for x in g) <= r * r + 1e-9)


def footprint_probability(grid2d_prob: np.ndarray, known2d: np.ndarray,
                          clearance_cells: int) -> np.ndarray:
    """Collision probability P of a rover standing on each cell: the largest occupancy within
    the clearance disk (unknown cells count 0.5, cells beyond the border 1)."""
    p = np.where(known2d, grid2d_prob, 0.5)
    return ndimage.maximum_filter(p, footprint=_disk(clearance_cells, 2), mode='constant',
                                  cval=1.0)


def _grid_graph(nav: np.ndarray, resolution: float) -> tuple[csr_matrix, np.ndarray]:
    """8-connected graph of the navigable cells: (CSR matrix of step lengths, cell ids)."""
    h, w = nav.shape
    ids = np.full(nav.shape, -1, np.int64)
    ids[nav] = np.arange(int(nav.sum()))
    rows, cols, vals = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        a = nav[max(0, -di):h - max(0, di), max(0, -dj):w - max(0, dj)]
        b = nav[max(0, di):h + min(0, di), max(0, dj):w + min(0, dj)]
        ok = a & b
        ia = ids[max(0, -di):h - max(0, di), max(0, -dj):w - max(0, dj)][ok]
        ib = ids[max(0, di):h + min(0, di), max(0, dj):w + min(0, dj)][ok]
        rows.append(ia)
        cols.append(ib)
        vals.append(np.full(ia.shape, np.hypot(di, dj) * resolution))
    n = int(nav.sum())
    mat = coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                     shape=(n, n)).tocsr()
    return mat, ids


def _check_start(nav: np.ndarray, start: Sequence[int] | np.ndarray) -> bool:
    if nav.ndim != 2:
        raise ValueError('navigable must be 2-D')
    si, sj = (int(v) for v in start)
    return 0 <= si < nav.shape[0] and 0 <= sj < nav.shape[1] and bool(nav[si, sj])


def geodesic_distance(navigable: np.ndarray, start: tuple[int, int], *,
                      resolution: float) -> np.ndarray:
    """Path length (m) through 8-connected navigable cells from `start`; inf if unreachable
    (constraint (ii): the goal is reached by a collision free path)."""
    nav = np.asarray(navigable, bool)
    if not _check_start(nav, start):
        return np.full(nav.shape, np.inf)
    mat, ids = _grid_graph(nav, resolution)
    d = dijkstra(mat, directed=False, indices=int(ids[start[0], start[1]]))
    out = np.full(nav.shape, np.inf)
    out[nav] = d
    return out


def geodesic_path(navigable: np.ndarray, start: tuple[int, int], goal: tuple[int, int], *,
                  resolution: float) -> np.ndarray:
    """The shortest 8-connected path of navigable cells from `start` to `goal` as (K, 2) cell
    indices, start and goal included; PlanningError if the goal cannot be reached."""
    nav = np.asarray(navigable, bool)
    if not (_check_start(nav, start) and _check_start(nav, goal)):
        raise PlanningError('start or goal not navigable')
    mat, ids = _grid_graph(nav, resolution)
    _, pred = dijkstra(mat, directed=False, indices=int(ids[start[0], start[1]]),
                       return_predecessors=True)
    cells = np.argwhere(nav)          # row-major, the order of ids
    node, s = int(ids[goal[0], goal[1]]), int(ids[start[0], start[1]])
    path = [node]
    while node != s:
        node = int(pred[node])
        if node < 0:
            raise PlanningError('goal not reachable')
        path.append(node)
    return cells[np.array(path[::-1])]


@dataclass
class Traversal:
    """Constraints (i) and (ii) on the 2-D ground plane of one map: `navigable` cells a rover
    may pass through on its way (ii), `candidate` cells a camera may be placed over (i), and
    `collision_p` the P of Eq. 3-15 of a camera placed over each cell."""

    navigable: np.ndarray
    collision_p: np.ndarray
    candidate: np.ndarray
    blocked: np.ndarray | None = None     # 'evidence': obstacle columns before the clearance
    clearance_cells: int = 0

    def _disk(self, cell: np.ndarray, radius_cells: int) -> np.ndarray:
        ii, jj = np.ogrid[:self.navigable.shape[0], :self.navigable.shape[1]]
        return (ii - int(cell[0])) ** 2 + (jj - int(cell[1])) ** 2 <= radius_cells ** 2

    def with_free_disk(self, cell: np.ndarray, radius_cells: int) -> Traversal:
        """The rover's own footprint is free: it stands there. The disk becomes passable and,
        where the obstacle columns are known ('evidence'), any column inside it is taken for
        a ghost (the rover itself seen by a teammate, speckle) and no longer blocks the ring
        of clearance around it either. Only the path mask changes."""
        disk = self._disk(cell, radius_cells)
        nav = self.navigable | disk
        if self.blocked is not None and (self.blocked & disk).any():
            st = _disk(self.clearance_cells, 2)
            near_all = ndimage.binary_dilation(self.blocked, structure=st)
            near_rest = ndimage.binary_dilation(self.blocked & ~disk, structure=st)
            nav |= near_all & ~near_rest
        return Traversal(nav, self.collision_p, self.candidate, self.blocked,
                         self.clearance_cells)

    def with_blocked_disk(self, cell: np.ndarray, radius_cells: int) -> Traversal:
        """Another rover stands (or will stand) there: neither path nor goal."""
        disk = self._disk(cell, radius_cells)
        return Traversal(self.navigable & ~disk, np.where(disk, 1.0, self.collision_p),
                         self.candidate & ~disk, self.blocked, self.clearance_cells)


@dataclass
class PlanContext:
    """Everything a strategy needs for one camera's decision."""

    grid: OccupancyGrid
    estimate: np.ndarray
    template: RayTemplate
    config: NbvConfig
    camera: CameraState
    navigable: np.ndarray          # 2-D
    reach: np.ndarray              # 2-D geodesic distance (m) from the camera
    collision_p: np.ndarray        # 2-D footprint P
    claimed: np.ndarray | None
    k: float
    rng: np.random.Generator
    candidate: np.ndarray | None = None   # 2-D goal cells (constraint (i)); None: navigable
    occlusion: np.ndarray | None = None   # unknown_occlusion 'expected': per-cell stop p

    @property
    def placeable(self) -> np.ndarray:
        return self.navigable if self.candidate is None else self.candidate

    def position_of(self, cells2d: np.ndarray) -> np.ndarray:
        """Camera positions above 2-D cells (z = camera height in 3-D)."""
        xy = self.grid.origin[:2] + (np.asarray(cells2d, float) + 0.5) * self.grid.resolution
        if self.grid.ndim == 2:
            return xy
        z = np.full((xy.shape[0], 1), self.config.camera_height_m)
        return np.hstack([xy, z])

    def candidates_at(self, cells2d: np.ndarray, yaws: np.ndarray | None = None) -> Candidates:
        """All (cell, yaw, pitch) combinations, or cell-wise given yaws (one per cell); with
        `mast_views`, all (cell, yaw, view) combinations instead (each view its own camera
        offset, height and pitch)."""
        cells2d = np.asarray(cells2d, np.int64).reshape(-1, 2)
        cfg = self.config
        use_mast = bool(cfg.mast_views) and self.grid.ndim == 3
        # a mast's views carry their own pitches (below): one per (cell, heading) here
        pitches = np.radians(np.asarray(cfg.pitches_deg if self.grid.ndim == 3 and not use_mast
                                        else (0.0,)))
        if yaws is None:
            yaw_set = np.arange(cfg.n_yaw) * 2 * np.pi / cfg.n_yaw
            cg, yi, pi = np.meshgrid(np.arange(len(cells2d)), np.arange(len(yaw_set)),
                                     np.arange(len(pitches)), indexing='ij')
            ci, yaw, pitch = cg.ravel(), yaw_set[yi.ravel()], pitches[pi.ravel()]
        else:
            ci = np.repeat(np.arange(len(cells2d)), len(pitches))
            yaw = np.repeat(np.asarray(yaws, float), len(pitches))
            pitch = np.tile(pitches, len(cells2d))
        c = cells2d[ci]
        pos = self.position_of(c)
        view = None
        if use_mast:
            # every (cell, heading) with each view the mast reaches, its camera where the
            # view puts it with the turntable turned to give the optical axis that heading
            mv = cfg.mast_views
            nv = len(mv)
            c, pos = np.repeat(c, nv, axis=0), np.repeat(pos, nv, axis=0)
            yaw = np.repeat(yaw, nv)
            view = np.tile(np.arange(nv), len(ci))
            fwd, lat, hgt, head, pit = (np.array([getattr(v, k) for v in mv])[view] for k in (
                'forward_m', 'lateral_m', 'height_m', 'heading_rad', 'pitch_rad'))
            turn = yaw - head
            pos = pos.copy()
            pos[:, 0] += np.cos(turn) * fwd - np.sin(turn) * lat
            pos[:, 1] += np.sin(turn) * fwd + np.cos(turn) * lat
            pos[:, 2] = hgt
            pitch = pit
        cur = np.r_[self.camera.position, [0.0] * (3 - self.grid.ndim),
                    self.camera.yaw, self.camera.pitch]
        new = np.hstack([pos, np.zeros((len(pos), 3 - self.grid.ndim)), yaw[:, None],
                         pitch[:, None]])
        d = configuration_distance(cur, new, self.config.alpha)
        path = self.reach[c[:, 0], c[:, 1]]
        if self.config.distance_metric is DistanceMetric.PATH:
            # Eq. 3-11 with the translation measured along the collision-free path (ii).
            ang = configuration_distance(cur * np.r_[0, 0, 0, 1, 1], new * np.r_[0, 0, 0, 1, 1],
                                         self.config.alpha)
            d = np.sqrt(path ** 2 + ang ** 2)
        return Candidates(pos, yaw, pitch, path, d,
                          self.collision_p[c[:, 0], c[:, 1]], view=view)

    def reachable_cells(self) -> np.ndarray:
        return np.argwhere(np.isfinite(self.reach) & self.placeable)

    def score(self, cands: Candidates) -> ViewScores:
        cfg = self.config
        return score_views(self.grid, self.estimate, cands.positions, cands.yaw,
                           cands.pitch if self.grid.ndim == 3 else None, self.template,
                           n_gray=cfg.n_gray, n_shells=cfg.n_shells, claimed=self.claimed,
                           chunk_samples=cfg.chunk_samples, weight=cfg.entropy_weight,
                           measure=cfg.ni_measure, occlusion=self.occlusion)


class Strategy(Protocol):
    """One camera pose selection method of §3.3.1 (or the frontier baseline)."""

    name: StrategyName

    def choose(self, ctx: PlanContext) -> Decision: ...


def _sample_cells(ctx: PlanContext) -> np.ndarray:
    """The finite candidate set of §3.3.1: n_positions reachable goal cells, "selected in
    several ways (random, closest to current pose, etc.)": the `near_fraction` nearest by path
    length, the rest at random (default: all at random)."""
    cells = ctx.reachable_cells()
    n = ctx.config.n_positions
    if len(cells) <= n:
        return cells
    n_near = round(np.clip(ctx.config.near_fraction, 0.0, 1.0) * n)
    if n_near == 0:
        return cells[ctx.rng.choice(len(cells), n, replace=False)]
    order = np.argsort(ctx.reach[cells[:, 0], cells[:, 1]], kind='stable')
    near, rest = order[:n_near], order[n_near:]
    pick = ctx.rng.choice(rest, n - n_near, replace=False) if n > n_near else rest[:0]
    return cells[np.r_[near, pick]]


def _decide(ctx: PlanContext, name: StrategyName, cands: Candidates, key: np.ndarray,
            scores: ViewScores | None = None, rating: np.ndarray | None = None) -> Decision:
    if scores is None:
        scores = ctx.score(cands)
    if rating is None:
        rating = rating_function(scores.ni, cands.distance, cands.collision_p, k=ctx.k,
                                 n=ctx.config.n_exp)
    return Decision(int(np.argmax(key)), cands, scores, np.asarray(rating, float), name)


class RandomStrategy:
    """(i) the next pose is random within the known (free, reachable) environment."""

    name = StrategyName.RANDOM

    def choose(self, ctx: PlanContext) -> Decision:
        cells = ctx.reachable_cells()
        pick = cells[ctx.rng.integers(len(cells))][None]
        yaw = ctx.rng.uniform(0, 2 * np.pi, size=1)
        cands = ctx.candidates_at(pick, yaw)
        return _decide(ctx, self.name, cands, np.zeros(len(cands)))


class RasterStrategy:
    """(ii) sequential/raster: the next free location of a boustrophedon lattice (spacing half
    the depth of field) from which no measurement has been made, looking along the raster.

    With `raster_headings` = n > 0 (a pan/tilt camera) the raster runs over poses: at each
    location the camera first sweeps n headings 2 pi / n apart (starting along the raster),
    one per scan, then moves on."""

    name = StrategyName.RASTER

    def choose(self, ctx: PlanContext) -> Decision:
        n_h = int(ctx.config.raster_headings)
        cam = ctx.camera
        if n_h > 0 and cam.raster_sweep_left > 0:
            cam.raster_sweep_left -= 1
            here = ctx.grid.to_index(cam.position)[:2]
            cands = ctx.candidates_at(here[None], np.array([cam.yaw + 2 * np.pi / n_h]))
            return _decide(ctx, self.name, cands, np.zeros(len(cands)))
        if n_h > 0:
            cam.raster_sweep_left = n_h - 1
        return self._next_location(ctx)

    def _next_location(self, ctx: PlanContext) -> Decision:
        g = ctx.grid
        spacing = ctx.config.raster_spacing_m or ctx.config.depth_m / 2
        step = max(1, round(spacing / g.resolution))
        rows = np.arange(step // 2, g.shape[0], step)
        cols = np.arange(step // 2, g.shape[1], step)
        sweep: list[tuple[int, int]] = []
        heading: list[float] = []
        for k, i in enumerate(rows):
            cs = cols if k % 2 == 0 else cols[::-1]
            sweep += [(int(i), int(j)) for j in cs]
            heading += [np.pi / 2 if k % 2 == 0 else -np.pi / 2] * len(cs)
        order = np.array(sweep)
        visited = np.array(ctx.camera.visited).reshape(-1, 2) if ctx.camera.visited else None
        n = len(order)
        for t in range(n):
            j = (ctx.camera.raster_cursor + t) % n
            cell = order[j]
            if not (np.isfinite(ctx.reach[cell[0], cell[1]]) and ctx.placeable[tuple(cell)]):
                continue
            if visited is not None and np.min(np.abs(visited - cell).max(axis=1)) < step / 2:
                continue
            ctx.camera.raster_cursor = j + 1
            # The grid's first axis is x: moving along a row changes y, hence yaw = +-pi/2.
            cands = ctx.candidates_at(cell[None], np.array([heading[j]]))
            return _decide(ctx, self.name, cands, np.zeros(len(cands)))
        # Every lattice point done or unreachable: fall back to the nearest unvisited free cell.
        cells = ctx.reachable_cells()
        if visited is not None:
            far = np.abs(cells[:, None, :] - visited[None]).max(axis=2).min(axis=1) >= step / 2
            cells = cells[far] if far.any() else cells
        pick = cells[np.argmin(ctx.reach[cells[:, 0], cells[:, 1]] + 1e-9 * np.arange(len(cells)))]
        move = pick - ctx.grid.to_index(ctx.camera.position)[:2]
        yaw = float(np.arctan2(move[1], move[0])) if np.any(move) else ctx.camera.yaw
        cands = ctx.candidates_at(pick[None], np.array([yaw]))   # looking where it goes
        return _decide(ctx, self.name, cands, np.zeros(len(cands)))


class MaxUnmappedStrategy:
    """(iii) the pose with the largest expected unmapped region, accounting for known
    occlusions."""

    name = StrategyName.MAX_UNMAPPED

    def choose(self, ctx: PlanContext) -> Decision:
        cands = ctx.candidates_at(_sample_cells(ctx))
        s = ctx.score(cands)
        return _decide(ctx, self.name, cands, s.unknown_cells, s)


class MinMappedStrategy:
    """(iv) the pose that will see the smallest known (already mapped) region."""

    name = StrategyName.MIN_MAPPED

    def choose(self, ctx: PlanContext) -> Decision:
        cands = ctx.candidates_at(_sample_cells(ctx))
        s = ctx.score(cands)
        return _decide(ctx, self.name, cands, -s.known_cells, s)


class MaxInformationStrategy:
    """(v) maximum expected information: argmax RF = (NI - K d^n)(1 - P), Eq. 3-15.

    `NbvConfig.ni_floor` > 0 (beyond the thesis): only the candidates whose NI is at least that
    share of the best NI among this decision's candidates compete. The additive RF lets a view
    worth nothing win once NI - K d < 0 for every informative one: with a large K the camera
    stays where it is (the current cell is a candidate, NI 0, d 0, RF 0) or crawls through
    views worth hundredths of a bit, and exploration stalls. With no candidate above the floor
    (nothing informative anywhere) the plain argmax RF decides."""

    name = StrategyName.MAX_INFORMATION

    def choose(self, ctx: PlanContext) -> Decision:
        cands = ctx.candidates_at(_sample_cells(ctx))
        s = ctx.score(cands)
        rf = rating_function(s.ni, cands.distance, cands.collision_p, k=ctx.k,
                             n=ctx.config.n_exp)
        key = rf
        floor = ctx.config.ni_floor
        if floor > 0 and len(s.ni) and np.max(s.ni) > 0:
            ni = np.asarray(s.ni, float)
            key = np.where(ni >= floor * ni.max(), rf, -np.inf)
        return _decide(ctx, self.name, cands, key, s, rf)


class FrontierStrategy:
    """Nearest-frontier baseline (Yamauchi 1997): drive to the closest reachable free cell that
    borders unknown space and look at the unknown."""

    name = StrategyName.FRONTIER

    def choose(self, ctx: PlanContext) -> Decision:
        g = ctx.grid
        if g.ndim == 2:
            unknown2d, free2d = ~g.known, g.free(p_empty=ctx.config.p_empty)
        else:
            unknown2d = np.asarray(~g.known.any(axis=2))
            free2d = np.asarray(g.free(p_empty=ctx.config.p_empty).any(axis=2))
        # Frontier: unknown cells bordering known free space (not obstacle interiors).
        # 4-adjacency: an obstacle's interior cell touching free space only at a corner is
        # hidden behind the obstacle's known faces and never observable.
        frontier = unknown2d & ndimage.binary_dilation(free2d)
        # The rover stands on a navigable cell within its clearance of the frontier.
        r = max(1, int(np.ceil(ctx.config.clearance_m / g.resolution))) + 1
        near = ndimage.binary_dilation(frontier, structure=_disk(r, 2))
        cells = ctx.reachable_cells()
        is_front = near[cells[:, 0], cells[:, 1]]
        cur = g.to_index(ctx.camera.position)[:2]
        keep = is_front & (np.abs(cells - cur).max(axis=1) > 0)
        if ctx.camera.visited:
            # Blacklist goals already scanned from (a frontier that did not clear from there).
            vis = np.array(ctx.camera.visited).reshape(-1, 2)
            keep &= np.abs(cells[:, None, :] - vis[None]).max(axis=2).min(axis=1) > 1
        front = cells[keep]
        if len(front) == 0:
            return RandomStrategy().choose(ctx)
        pick = front[np.argmin(ctx.reach[front[:, 0], front[:, 1]])]
        win = 2 * r + 1
        lo = np.maximum(pick - win, 0)
        sub = frontier[lo[0]:pick[0] + win + 1, lo[1]:pick[1] + win + 1]
        uv = np.argwhere(sub) + lo - pick
        yaw = float(np.arctan2(uv[:, 1].mean(), uv[:, 0].mean())) if len(uv) else ctx.camera.yaw
        cands = ctx.candidates_at(pick[None], np.array([yaw]))
        return _decide(ctx, self.name, cands, np.zeros(len(cands)))


#: the class of each StrategyName
STRATEGY_CLASSES: dict[StrategyName, type[Strategy]] = {
    s.name: s for s in (RandomStrategy, RasterStrategy, MaxUnmappedStrategy, MinMappedStrategy,
                        MaxInformationStrategy, FrontierStrategy)}


def make_strategy(name: StrategyName | str) -> Strategy:
    """The strategy called `name` (a StrategyName or its string); OptionError naming them
    otherwise."""
    if name not in STRATEGY_CLASSES:
        raise OptionError(f'unknown strategy {name!r}: strategy must be one of '
                          f'{[s.value for s in StrategyName]}')
    return STRATEGY_CLASSES[StrategyName(name)]()


# ----------------------------------------------------------------------------- planner


class NextBestViewPlanner:
    """Plans the next view of one or several cameras on one shared map (Fig. 3-9)."""

    def __init__(self, config: NbvConfig | None = None) -> None:
        self.config = config or NbvConfig()
        self._templates: dict[tuple[int, float], RayTemplate] = {}

    def template(self, grid: OccupancyGrid) -> RayTemplate:
        key = (grid.ndim, float(grid.resolution))
        if key not in self._templates:
            self._templates[key] = self.config.template(ndim=grid.ndim,
                                                        resolution=grid.resolution)
        return self._templates[key]

    def k_value(self, grid: OccupancyGrid) -> float:
        """K of Eq. 3-15 from k_rel (see NbvConfig)."""
        cfg = self.config
        ni_max = max_information(self.template(grid), n_gray=cfg.n_gray, n_shells=cfg.n_shells,
                                 weight=cfg.entropy_weight)
        return cfg.k_rel * ni_max / cfg.depth_m ** cfg.n_exp

    def _slab(self, grid: OccupancyGrid) -> tuple[int, int]:
        """Layers [bot, top) the rover and mast sweep: above the ground clearance, up to the
        camera (a small tolerance so 0.2 m on a 0.1 m grid is layer 2, not 3)."""
        cfg = self.config
        eps = 1e-6
        bot = int(np.clip(np.ceil((cfg.ground_clearance_m - grid.origin[2]) / grid.resolution
                                  - eps), 0, grid.shape[2] - 1))
        top = int(np.clip(np.ceil((cfg.camera_height_m - grid.origin[2]) / grid.resolution
                                  - eps), bot + 1, grid.shape[2]))
        return bot, top

    def traversability(self, grid: OccupancyGrid) -> Traversal:
        """Constraints (i) and (ii) on the ground plane, per `config.reach_model` (see the
        module docstring)."""
        cfg = self.config
        match cfg.reach_model:
            case ReachModel.EVIDENCE:
                return self._evidence_traversability(grid)
            case ReachModel.KNOWN:
                return self._known_traversability(grid)
            case _:
                assert_never(cfg.reach_model)

    def _known_traversability(self, grid: OccupancyGrid) -> Traversal:
        """'known' model: a rover passes and stands only where the map knows it free."""
        cfg = self.config
        if grid.ndim == 2:
            prob2, known2 = grid.prob, grid.known
        else:
            # in 3-D a column is as occupied as its most occupied cell in the slab
            bot, top = self._slab(grid)
            p = np.where(grid.known[:, :, bot:top], grid.prob[:, :, bot:top], 0.5)
            prob2 = p.max(axis=2)
            known2 = grid.known[:, :, bot:top].all(axis=2) | (prob2 >= 0.5)
        clear = int(np.ceil(cfg.clearance_m / grid.resolution))
        pcol = footprint_probability(prob2, known2, clear)
        nav = known2 & (pcol < cfg.p_empty)
        return Traversal(nav, pcol, nav)

    def _evidence_traversability(self, grid: OccupancyGrid) -> Traversal:
        """'evidence' model: obstacle columns block the path, unknown does not; the goal's
        camera voxel must be known free (P < P_empty)."""
        cfg = self.config
        if cfg.occupied_voxels < 1:
            raise ValueError('occupied_voxels must be >= 1')
        if grid.ndim == 2:
            blocked = grid.occupied()
            cam_known, cam_p = grid.known, grid.prob
        else:
            bot, top = self._slab(grid)
            kn = grid.known[:, :, bot:top]
            pr = grid.prob[:, :, bot:top]
            occ = kn & (pr >= cfg.occupied_p)
            blocked = ((occ.sum(axis=2) >= cfg.occupied_voxels)
                       | (kn & (pr >= cfg.occupied_clamp)).any(axis=2))
            kc = int(np.floor((cfg.camera_height_m - grid.origin[2]) / grid.resolution + 1e-6))
            if 0 <= kc < grid.shape[2]:
                cam_known, cam_p = grid.known[:, :, kc], grid.prob[:, :, kc]
            else:       # the camera's layer is outside the map: nothing known there
                cam_known = np.zeros(grid.shape[:2], bool)
                cam_p = np.full(grid.shape[:2], 0.5, np.float32)
        clear = int(np.ceil(cfg.clearance_m / grid.resolution))
        near = ndimage.binary_dilation(blocked, structure=_disk(clear, 2)) if clear else blocked
        nav = ~near
        p_cam = np.where(cam_known, cam_p, 0.5)
        candidate = nav & cam_known & (p_cam < cfg.p_empty)
        return Traversal(nav, np.where(near, 1.0, p_cam), candidate, blocked, clear)

    def _footprint_freed(self, grid: OccupancyGrid, cell: np.ndarray) -> OccupancyGrid:
        """The grid with the unknown cells within one rover length (twice the clearance) of
        the camera's ground cell, all heights, set to known free: the rover stands there and got
        there; its outward-looking cameras cannot see it. Known obstacles stay."""
        r = int(np.ceil(2.0 * self.config.clearance_m / grid.resolution))
        ii, jj = np.ogrid[:grid.shape[0], :grid.shape[1]]
        disk = (ii - int(cell[0])) ** 2 + (jj - int(cell[1])) ** 2 <= r * r
        if grid.ndim == 3:
            disk = np.broadcast_to(disk[:, :, None], grid.shape)
        free = disk & ~grid.known
        return OccupancyGrid(np.where(free, 0.0, grid.prob), grid.known | free,
                             resolution=grid.resolution, origin=grid.origin)

    def plan(self, grid: OccupancyGrid, camera: CameraState, *,
             strategy: StrategyName | str | Strategy,
             rng: np.random.Generator, claimed: np.ndarray | None = None,
             estimate: np.ndarray | None = None,
             traversability: Traversal | None = None,
             free_footprint: bool = False,
             occlusion: np.ndarray | None = None,
             teammates: Sequence[ArrayLike] = ()) -> Decision:
        """Choose one camera's next view. Raises PlanningError when no admissible view exists
        and OptionError for an unknown strategy (a StrategyName's string, or a Strategy).

        free_footprint: the rover stands where the camera is, so its own footprint is free. With
        reach_model 'known' the unseen ground within one rover length of the camera counts as
        known free (`_footprint_freed`); with 'evidence' (where unseen ground is passable
        anyway) the cells within the clearance of the rover are passable whatever the map says
        there. Off in the experiments, on in the node.

        occlusion: the per-cell stop probability of unknown_occlusion 'expected' if already
        computed (`occlusion_map`); ignored with 'none'.

        teammates: map xy where the team's other rovers stand or will stand: no view whose
        rover would stand in one's keep-out (`keep_out_cells`, as `team_route` refuses such a
        goal; the camera stands up to CAMERA_FROM_BASE_M from its rover). Only the candidates
        change: the path round them is the route's to plan."""
        strat = make_strategy(strategy) if isinstance(strategy, str) else strategy
        if not grid.known.any():
            raise MapError('empty map: nothing known, no free candidate')
        trav = traversability if traversability is not None else self.traversability(grid)
        cell = grid.to_index(np.asarray(camera.position, float))[:2]
        if not np.all((cell >= 0) & (cell < np.array(trav.navigable.shape))):
            raise PlanningError('camera outside the map')
        if free_footprint:
            if self.config.reach_model is ReachModel.KNOWN:
                if traversability is None:
                    trav = self.traversability(self._footprint_freed(grid, cell))
            else:
                trav = trav.with_free_disk(cell, int(np.ceil(self.config.clearance_m
                                                             / grid.resolution)))
        if len(teammates):
            keep = keep_out_cells(self.config.clearance_m, grid.resolution) + \
                math.ceil(CAMERA_FROM_BASE_M / grid.resolution)
            near = np.zeros(trav.candidate.shape, bool)
            for xy in teammates:
                near |= trav._disk(plane_index(grid, xy), keep)
            trav = replace(trav, candidate=trav.candidate & ~near)
        nav = trav.navigable
        start_nav = nav.copy()
        start_nav[cell[0], cell[1]] = True     # the rover is where it is, even if hemmed in
        reach = geodesic_distance(start_nav, (int(cell[0]), int(cell[1])),
                                  resolution=grid.resolution)
        reach[cell[0], cell[1]] = np.inf if not nav[cell[0], cell[1]] else 0.0
        if not (np.isfinite(reach) & trav.candidate).any():
            raise PlanningError(f'no free reachable candidate (P < {self.config.p_empty:.2f})')
        est = gray_estimate(grid, free_gray=self.config.free_gray,
                            iterations=self.config.markov_iterations) \
            if estimate is None else estimate
        occ = None
        if self.config.unknown_occlusion is UnknownOcclusion.EXPECTED:
            occ = occlusion if occlusion is not None else self.occlusion_map(grid, gray=est)
        ctx = PlanContext(grid, est, self.template(grid), self.config, camera, nav, reach,
                          trav.collision_p, claimed, self.k_value(grid), rng,
                          candidate=trav.candidate, occlusion=occ)
        return strat.choose(ctx)

    def occlusion_map(self, grid: OccupancyGrid, *, gray: np.ndarray | None = None
                      ) -> np.ndarray | None:
        """Per-cell stop probability of unknown_occlusion 'expected' (`grid.occlusion_estimate`
        with `config.occlusion_prior`; `gray`: the planner's gray estimate if at hand); None
        with 'none'."""
        cfg = self.config
        if cfg.unknown_occlusion is UnknownOcclusion.NONE:
            return None
        return occlusion_estimate(grid, prior=cfg.occlusion_prior, free_gray=cfg.free_gray,
                                  iterations=cfg.markov_iterations, gray=gray)

    def expected_cells(self, grid: OccupancyGrid, decision: Decision, *,
                       occlusion: np.ndarray | None = None) -> np.ndarray:
        """Cells the chosen view is expected to see (bool, grid shape): what a second camera
        planning on the same map should not count again. With unknown_occlusion 'expected',
        the cells seen with probability >= 0.5 (`occlusion` as in `plan`)."""
        c = decision.candidates
        i = decision.index
        casting = cast(grid, c.positions[i:i + 1], c.yaw[i:i + 1],
                       c.pitch[i:i + 1] if grid.ndim == 3 else None, self.template(grid))
        seen = casting.visible
        if self.config.unknown_occlusion is UnknownOcclusion.EXPECTED:
            occ = occlusion if occlusion is not None else self.occlusion_map(grid)
            seen = expected_visibility(casting, occ) >= 0.5
        out = np.zeros(grid.prob.size, bool)
        out[casting.flat[seen]] = True
        return out.reshape(grid.shape)


def plan_cameras(planner: NextBestViewPlanner, grid: OccupancyGrid, cameras: list[CameraState],
                 *, strategy: StrategyName | str | Strategy,
                 rng: np.random.Generator) -> list[Decision]:
    """Several cameras on one shared map: each plans in turn, the cells the earlier cameras are
    expected to see are claimed so the later ones look elsewhere."""
    est = gray_estimate(grid, free_gray=planner.config.free_gray,
                        iterations=planner.config.markov_iterations)
    trav = planner.traversability(grid)
    occ = planner.occlusion_map(grid, gray=est)
    claimed = np.zeros(grid.shape, bool)
    out = []
    for cam in cameras:
        d = planner.plan(grid, cam, strategy=strategy, rng=rng, claimed=claimed, estimate=est,
                         traversability=trav, occlusion=occ)
        claimed |= planner.expected_cells(grid, d, occlusion=occ)
        out.append(d)
    return out


__all__ = [
    'ENTROPY_WEIGHTS',
    'STRATEGIES',
    'STRATEGY_CLASSES',
    'UNKNOWN_OCCLUSIONS',
    'CameraState',
    'Candidates',
    'Decision',
    'NbvConfig',
    'NextBestViewPlanner',
    'PlanningError',
    'Traversal',
    'ViewScores',
    'binary_entropy',
    'configuration_distance',
    'expected_information',
    'geodesic_distance',
    'geodesic_path',
    'make_strategy',
    'max_information',
    'occupancy_weight',
    'plan_cameras',
    'plogp',
    'rating_function',
    'score_views',
    'waypoints',
]


def waypoints(cells: np.ndarray, grid: OccupancyGrid) -> list[np.ndarray]:
    """Cell path -> map xy waypoints at its corners (and every ~1 m on long straights)."""
    xy = plane_world(grid, cells)
    if len(xy) <= 2:
        return [xy[-1]]
    out = []
    step = np.diff(cells, axis=0)
    run = 0
    for k in range(1, len(cells) - 1):
        run += 1
        if np.any(step[k] != step[k - 1]) or run * grid.resolution >= 1.0:
            out.append(xy[k])
            run = 0
    out.append(xy[-1])
    return out


def keep_out_cells(clearance_m: float, resolution: float) -> int:
    """A teammate's keep-out radius on the ground plane (cells): the rovers' clearance and two
    cells. No rover's goal lies within it (`team_route`), nor a view's rover (`plan`)."""
    return math.ceil(clearance_m / resolution) + 2


def team_route(trav: Traversal, grid: OccupancyGrid, start_xy: ArrayLike,
               goal_xy: ArrayLike, *, others: Sequence[ArrayLike] = (),
               moving: Sequence[ArrayLike] = (), clearance_m: float,
               snap_m: float = 1.0, last_leg: bool = True,
               blocked: np.ndarray | None = None) -> list[np.ndarray]:
    """Waypoints (map xy) for a rover from start_xy to goal_xy on `trav`'s navigable cells,
    round the other rovers of its team, each kept out of by the clearance and two cells:
    `others` stand (or will stand) where they are, and no goal may lie beside them; `moving`
    stand there now but leave as this rover drives (its path keeps off, its goal need not).
    Never through a `blocked` ground-plane cell (even in the rover's own footprint: the cells
    whoever drives the route refuses). The route passes through its start cell's and its last
    cell's centres (within a cell of where the rover and the goal are), so that every leg runs
    along the cells the path was planned on. A goal off the navigable cells is reached by a
    straight last leg from the nearest navigable cell within `snap_m` that the rover can reach
    (without `last_leg` the route ends on that cell). PlanningError when the start or the goal
    lies off the grid, the goal in another rover's keep-out, or it cannot be reached."""
    clear = math.ceil(clearance_m / grid.resolution)
    keep = keep_out_cells(clearance_m, grid.resolution)
    start = plane_index(grid, start_xy)
    goal = plane_index(grid, goal_xy)
    plane = np.asarray(trav.navigable.shape)
    for what, cell in (('start', start), ('goal', goal)):
        if not np.all((cell >= 0) & (cell < plane)):
            raise PlanningError(f"the {what} lies off the map's grid")
    for xy in others:
        if np.hypot(*(goal - plane_index(grid, xy))) <= keep:
            # the straight last leg would end beside (or on) the other rover
            raise PlanningError(f'the goal is within {keep * grid.resolution:.1f} m of '
                                f'another rover at {np.round(np.asarray(xy, float), 2)}')
    for xy in (*others, *moving):
        cell = plane_index(grid, xy)
        # a rover close to this one (side by side, or within the odometry's error) keeps out
        # of a smaller disk, one that leaves a way out of this rover's own footprint (freed
        # below): walled in only once the disk reaches clear + 1 cells past the start
        radius = min(keep, int(np.hypot(*(start - cell))) + clear - 1)
        if radius > 0:
            trav = trav.with_blocked_disk(cell, radius)
    nav = trav.with_free_disk(start, clear).navigable
    if blocked is not None:
        nav = nav & ~blocked
        nav[tuple(start)] = True                # where the rover stands, it can leave
    if not nav[tuple(goal)]:
        # a goal inside the clearance of an obstacle (a base a little off its camera's column,
        # a staging pose close to the site), never a speck of free cells among the obstacles
        reach, _ = ndimage.label(nav, structure=np.ones((3, 3), bool))    # 8-connected
        r = math.ceil(snap_m / grid.resolution)
        lo = np.maximum(goal - r, 0)
        window = reach[lo[0]:goal[0] + r + 1, lo[1]:goal[1] + r + 1]
        near = np.argwhere(window == reach[tuple(start)]) + lo
        if not len(near):
            raise PlanningError(f'no navigable cell within {snap_m} m of the goal that the '
                                'rover can reach')
        goal = near[np.argmin(np.hypot(*(near - goal).T))]
    cells = geodesic_path(nav, tuple(start), tuple(goal), resolution=grid.resolution)
    route = [plane_world(grid, start), *waypoints(cells, grid)] if len(cells) > 1 else \
        [plane_world(grid, goal)]
    if last_leg:
        route.append(np.asarray(goal_xy, float)[:2])
    return route


def plane_index(grid: OccupancyGrid, xy: ArrayLike) -> np.ndarray:
    """The ground-plane cells (..., 2) of map points xy (..., 2+), for a 3-D or a 2-D grid."""
    p = np.asarray(xy, float)[..., :2]
    if grid.ndim == 3:
        p = np.concatenate([p, np.zeros((*p.shape[:-1], 1))], -1)
    return grid.to_index(p)[..., :2]


def plane_world(grid: OccupancyGrid, cells: ArrayLike) -> np.ndarray:
    """The map xy (..., 2) of ground-plane cells' centres (..., 2), for a 3-D or a 2-D grid."""
    c = np.asarray(cells)
    if grid.ndim == 3:
        c = np.concatenate([c, np.zeros((*c.shape[:-1], 1), c.dtype)], -1)
    return grid.to_world(c)[..., :2]
