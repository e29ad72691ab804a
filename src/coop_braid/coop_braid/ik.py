"""Inverse kinematics of BRAID (thesis §E.3.2): the chain state whose end pose is nearest a
target pose, by one of four searches behind one interface, `solve`.

The metric (E.3.2: "minimize the error between the end-effector and desired pose") is the
weighted pose error

    cost = w_pos |p - p*| + w_ang angle(R*^T R)          (metres)

with w_pos dimensionless and w_ang in m/rad (`Weights`). Every method returns the nearest pose it
found with its errors; a target that no state reaches is answered the same way, never with an
exception.

- `Method.EXHAUSTIVE`: every one of the 8^n states (n <= 6), vectorised; the reference.
- `Method.GENETIC`: the thesis's genetic search over the 3n-bit leg string (tournament
  selection, one-point crossover, bit-flip mutation, elitism).
- `Method.COMBINATORIAL`: the thesis's combinatorial heuristic search, read as a local search
  that exhaustively tries every combination of a small window of consecutive stages (8^w
  states) with the rest held, sweeping the window along the chain until no window improves,
  from a few starts.
- `Method.BEAM`: beyond the thesis: a beam search stage by stage from the base, with a
  meet-in-the-middle finish. A partial chain A_0d is ranked by the least error of it completed
  by a fixed sample of the remaining stages' states (`BeamScore.SAMPLED`, the default; or by
  `BeamScore.DENSITY`, Lees & Chirikjian's workspace-density idea: the Mahalanobis distance of
  the target under the exact mean and covariance of what the remaining stages reach,
  `Chain.suffix_moments`). The last 5 stages are not searched but looked up: their 8^5 end
  frames sit in a k-d tree, and every partial chain A_0,n-5 takes the nearest of what it needs,
  A_0,n-5^-1 T*. Optionally (`BeamOptions.polish`) the best chain is then polished by the
  combinatorial window search.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import Enum
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from coop_braid.chain import MAX_WORKSPACE_STAGES, Chain
from coop_braid.errors import BraidError
from coop_braid.stage import StageGeometry

Array = NDArray[np.float64]
States = NDArray[np.int64]


class Method(Enum):
    """The inverse-kinematics searches `solve` runs."""

    EXHAUSTIVE = 'exhaustive'
    GENETIC = 'genetic'
    COMBINATORIAL = 'combinatorial'
    BEAM = 'beam'


@dataclass(frozen=True)
class Weights:
    """The pose metric's weights: cost = position |dp| + orientation * angle, in metres
    (`orientation` in m/rad: the position error one radian of orientation error is worth)."""

    position: float = 1.0
    orientation: float = 0.01

    def __post_init__(self) -> None:
        for name in ('position', 'orientation'):
            v = getattr(self, name)
            if not math.isfinite(v) or v < 0.0:
                raise BraidError(f'Weights.{name} = {v!r}: finite and >= 0')
        if self.position == 0.0 and self.orientation == 0.0:
            raise BraidError('Weights: at least one of position and orientation is > 0')


def _check_options(obj: object, ranges: dict[str, tuple[float, float]]) -> None:
    """BraidError naming the first option of `obj` outside its [lo, hi]."""
    for name, (lo, hi) in ranges.items():
        v = getattr(obj, name)
        if v is not None and not lo <= v <= hi:
            raise BraidError(f'{type(obj).__name__}.{name} = {v!r}: {lo:g} .. {hi:g}')


@dataclass(frozen=True)
class GeneticOptions:
    """The genetic search's budget and operators (`mutation` None: 1 / (3n) per bit)."""

    population: int = 64
    generations: int = 60
    crossover: float = 0.9
    mutation: float | None = None
    tournament: int = 2
    elite: int = 2

    def __post_init__(self) -> None:
        _check_options(self, {'population': (4, 1e6), 'generations': (0, 1e6),
                              'crossover': (0.0, 1.0), 'mutation': (0.0, 1.0),
                              'tournament': (1, 64), 'elite': (0, self.population - 1)})


@dataclass(frozen=True)
class CombinatorialOptions:
    """The combinatorial search: window of `window` consecutive stages (8^window states tried
    each), `starts` starting states (the straight, retracted chain and random ones), at most
    `max_sweeps` sweeps along the chain per start."""

    window: int = 2
    starts: int = 3
    max_sweeps: int = 20

    def __post_init__(self) -> None:
        _check_options(self, {'window': (1, 4), 'starts': (1, 1e4), 'max_sweeps': (1, 1e4)})


class BeamScore(Enum):
    """How the beam search ranks a partial chain A_0d: `sampled`, the least cost of it
    completed by a fixed sample of the remaining stages' states (a sampled bound of the best
    completion); `density`, the Mahalanobis distance of the target's frame under the exact
    mean and covariance of what the remaining stages reach (Lees & Chirikjian's
    workspace-density idea)."""

    SAMPLED = 'sampled'
    DENSITY = 'density'


@dataclass(frozen=True)
class BeamOptions:
    """The beam search: `width` partial chains kept per stage (ranked by `score`, the sampled one
    over `samples` states of the remaining stages); the last `tail_stages` stages completed
    from their enumerated workspace (8^tail_stages frames in a k-d tree: the `neighbours`
    nearest of what each partial chain needs, re-ranked by the exact error); then `polish`
    sweeps of the window search (window `polish_window`) on the best chain (default none: with
    a window of 2 they found nothing to improve in the Monte Carlo)."""

    width: int = 32
    tail_stages: int = 5
    neighbours: int = 16
    samples: int = 256
    score: BeamScore = BeamScore.SAMPLED

    def __post_init__(self) -> None:
        _check_options(self, {'width': (1, 1e5), 'tail_stages': (1, MAX_WORKSPACE_STAGES),
                              'neighbours': (1, 4096),
                              'samples': (1, 1e6), 'polish': (0, 1e4),
                              'polish_window': (1, 4)})
    polish: int = 0
    polish_window: int = 2


@dataclass(frozen=True)
class IKResult:
    """A search's answer: the stage states (n,), their end pose A_0n (4x4), its position error
    (m), orientation error (rad) and weighted cost, and how many end poses it evaluated."""

    method: Method
    states: States
    pose: Array
    pos_err_m: float
    ang_err_rad: float
    cost: float
    evaluations: int = field(default=0)


def check_target(target: NDArray[np.floating]) -> Array:
    """`target` as a 4x4 homogeneous pose, or BraidError: finite, a proper rotation (to 1e-6)
    and a bottom row (0, 0, 0, 1)."""
    t = np.asarray(target, dtype=float)
    if t.shape != (4, 4) or not np.all(np.isfinite(t)):
        raise BraidError(f'target pose: a finite 4x4 matrix, not {t.shape}')
    r = t[:3, :3]
    if (np.max(np.abs(r.T @ r - np.eye(3))) > 1e-6 or np.linalg.det(r) < 0.0
            or np.max(np.abs(t[3] - (0.0, 0.0, 0.0, 1.0))) > 1e-12):
        raise BraidError('target pose: its rotation is not orthonormal with det +1, or its '
                         'bottom row is not (0, 0, 0, 1)')
    return t


def pose_errors(poses: Array, target: Array) -> tuple[Array, Array]:
    """Position error (m) and orientation error (rad, the angle of R*^T R) of poses (..., 4, 4)
    from the target pose."""
    pos = np.linalg.norm(poses[..., :3, 3] - target[:3, 3], axis=-1)
    tr = np.einsum('...ij,ij->...', poses[..., :3, :3], target[:3, :3])
    ang = np.arccos(np.clip((tr - 1.0) * 0.5, -1.0, 1.0))
    return pos, ang


def pose_cost(poses: Array, target: Array, weights: Weights) -> Array:
    """The weighted pose error of poses (..., 4, 4): w_pos |dp| + w_ang angle."""
    pos, ang = pose_errors(poses, target)
    return weights.position * pos + weights.orientation * ang


# --- precomputed tables of a chain (cached per chain geometry) --------------------------------

def _window_table(chain: Chain, first: int, k: int) -> Array:
    """A_{first, first+k} of all 8^k states of those stages (cached by the stages' geometry:
    every window of a uniform chain shares one table)."""
    return _stages_table(chain.stages[first:first + k])


@lru_cache(maxsize=64)
def _stages_table(stages: tuple[StageGeometry, ...]) -> Array:
    return Chain(stages).workspace()


#: end-frame features whose distribution scores a partial chain: x axis, z axis, position
_FEATURES = [(i, 0) for i in range(3)] + [(i, 2) for i in range(3)] + [(i, 3) for i in range(3)]


@lru_cache(maxsize=64)
def _suffix_gauss(chain: Chain, first: int) -> tuple[Array, Array]:
    """Mean (9,) and inverse covariance (9, 9) of the end frame's features (x axis, z axis,
    position) of stages first+1 .. n over their uniformly random states, in the frame they
    start from; exact moments (`Chain.suffix_moments`), positions scaled to the stage length
    and the covariance regularised so that it inverts."""
    mom = chain.suffix_moments(first)
    scale = _feature_scale(chain)
    mean = np.array([mom.mean[i, j] for i, j in _FEATURES]) * scale
    cov = np.empty((9, 9))
    for a, (i, j) in enumerate(_FEATURES):
        for b, (k, m) in enumerate(_FEATURES):
            cov[a, b] = mom.second[4 * i + k, 4 * j + m] * scale[a] * scale[b]
    cov -= np.outer(mean, mean)
    cov = 0.5 * (cov + cov.T) + 1e-6 * np.eye(9)
    prec = np.asarray(np.linalg.inv(cov), dtype=np.float64)
    return mean, prec


def _feature_scale(chain: Chain) -> Array:
    """Scale of the features (x axis, z axis, position): positions in extended leg lengths."""
    length = float(np.mean([s.leg_long for s in chain.stages]))
    return np.array([1.0] * 6 + [1.0 / length] * 3)


def _density_score(chain: Chain, first: int, cand: Array, target: Array) -> Array:
    """Mahalanobis distance^2 of the target's frame seen from each candidate A_0d under the
    distribution of A_{first,n} (`_suffix_gauss`)."""
    mean, prec = _suffix_gauss(chain, first)
    scale = _feature_scale(chain)
    rt = np.swapaxes(cand[:, :3, :3], 1, 2)
    q_pos = np.einsum('bij,bj->bi', rt, target[:3, 3] - cand[:, :3, 3])
    q_rot = rt @ target[:3, :3]
    diff = np.concatenate([q_rot[:, :, 0], q_rot[:, :, 2], q_pos], axis=1) * scale - mean
    return np.einsum('bi,ij,bj->b', diff, prec, diff)


def _fk(table: Array, states: States) -> Array:
    """A_0n of a batch of state vectors (B, n) -> (B, 4, 4), no checks."""
    out = table[0, states[:, 0]]
    for i in range(1, states.shape[1]):
        out = out @ table[i, states[:, i]]
    return out


def _result(chain: Chain, method: Method, states: States, target: Array, weights: Weights,
            evaluations: int) -> IKResult:
    pose = chain.pose(states)
    pos, ang = pose_errors(pose, target)
    return IKResult(method=method, states=np.asarray(states, dtype=np.int64).copy(), pose=pose,
                    pos_err_m=float(pos), ang_err_rad=float(ang),
                    cost=float(weights.position * pos + weights.orientation * ang),
                    evaluations=evaluations)


# --- the searches -----------------------------------------------------------------------------

def _exhaustive(chain: Chain, target: Array, weights: Weights) -> tuple[States, int]:
    if chain.n > MAX_WORKSPACE_STAGES:
        raise BraidError(f'exhaustive search: at most {MAX_WORKSPACE_STAGES} stages '
                         f'(8^{MAX_WORKSPACE_STAGES} states), not {chain.n}')
    ws = _window_table(chain, 0, chain.n)
    cost = pose_cost(ws, target, weights)
    best = int(np.argmin(cost))
    return Chain.flat_to_states(best, chain.n), ws.shape[0]


def _genetic(chain: Chain, target: Array, weights: Weights, rng: np.random.Generator,
             opt: GeneticOptions) -> tuple[States, int]:
    n, pop = chain.n, opt.population
    nbits = 3 * n
    mut = opt.mutation if opt.mutation is not None else 1.0 / nbits
    weights3 = np.array([1, 2, 4])
    table = chain.table

    def fitness(bits: NDArray[np.int64]) -> Array:
        states = (bits.reshape(-1, n, 3) * weights3).sum(axis=2)
        return pose_cost(_fk(table, states), target, weights)

    bits = rng.integers(0, 2, size=(pop, nbits))
    cost = fitness(bits)
    evals = pop
    for _ in range(opt.generations):
        order = np.argsort(cost)
        elite = bits[order[:opt.elite]]
        # tournament selection of the parents
        cand = rng.integers(0, pop, size=(pop - opt.elite, opt.tournament))
        winners = cand[np.arange(cand.shape[0]), np.argmin(cost[cand], axis=1)]
        parents = bits[winners]
        mates = parents[rng.permutation(parents.shape[0])]
        # one-point crossover
        cut = rng.integers(1, nbits, size=parents.shape[0])
        do = rng.random(parents.shape[0]) < opt.crossover
        mask = (np.arange(nbits)[None, :] >= cut[:, None]) & do[:, None]
        children = np.where(mask, mates, parents)
        # bit-flip mutation
        children ^= (rng.random(children.shape) < mut).astype(children.dtype)
        bits = np.concatenate([elite, children])
        cost = np.concatenate([cost[order[:opt.elite]], fitness(children)])
        evals += children.shape[0]
    best = bits[int(np.argmin(cost))]
    return (best.reshape(n, 3) * weights3).sum(axis=1), evals


def _descend(chain: Chain, states: States, target: Array, weights: Weights, *, window: int,
             max_sweeps: int) -> tuple[States, float, int]:
    """Window search: sweep a window of `window` consecutive stages along the chain, trying all
    8^window states of the window with the rest held (prefix A_0i and suffix A_{i+w,n} of the
    current states), keep the best; until a sweep improves nothing."""
    n, table = chain.n, chain.table
    w = min(window, n)
    s = states.copy()
    cost = float(pose_cost(chain.pose(s), target, weights))
    evals = 1
    for _ in range(max_sweeps):
        improved = False
        suffix = [np.eye(4)] * (n + 1)
        for i in range(n - 1, -1, -1):
            suffix[i] = table[i, s[i]] @ suffix[i + 1]
        prefix = np.eye(4)
        for i in range(n - w + 1):
            cands = prefix @ _window_table(chain, i, w) @ suffix[i + w]
            c = pose_cost(cands, target, weights)
            evals += c.shape[0]
            j = int(np.argmin(c))
            if c[j] < cost - 1e-15:
                s[i:i + w] = Chain.flat_to_states(j, w)
                cost = float(c[j])
                improved = True
            prefix = prefix @ table[i, s[i]]
        if not improved:
            break
    return s, cost, evals


def _combinatorial(chain: Chain, target: Array, weights: Weights, rng: np.random.Generator,
                   opt: CombinatorialOptions) -> tuple[States, int]:
    starts = [np.zeros(chain.n, dtype=np.int64)]
    starts += [rng.integers(0, 8, size=chain.n) for _ in range(max(0, opt.starts - 1))]
    best, best_cost, evals = starts[0], math.inf, 0
    for s0 in starts:
        s, c, e = _descend(chain, s0, target, weights, window=opt.window,
                           max_sweeps=opt.max_sweeps)
        evals += e
        if c < best_cost:
            best, best_cost = s, c
    return best, evals


def _cost_matrix(frames: Array, tail_pos: Array, tail_rot: Array, target: Array,
                 weights: Weights, *, exact: bool = True) -> Array:
    """Cost (B, S) of every frame A_0d (B, 4, 4) completed by every tail A_dn of a set
    (positions (S, 3), rotations flattened (S, 9)), without forming the products: the position
    error is |p_s - R^T (p* - o)| and the trace of R*^T R R_s is the inner product of R^T R*
    with R_s. Not `exact`: the angle is the chordal 2 sin(angle / 2) = sqrt(3 - trace), within
    5 % of it below 60 deg and many times cheaper than arccos (for ranking candidates)."""
    rt = np.swapaxes(frames[:, :3, :3], 1, 2)
    q = np.einsum('bij,bj->bi', rt, target[:3, 3] - frames[:, :3, 3])
    d2 = (np.sum(q * q, axis=1)[:, None] + np.sum(tail_pos * tail_pos, axis=1)[None, :]
          - 2.0 * q @ tail_pos.T)
    pos = np.sqrt(np.maximum(d2, 0.0))
    tr = (rt @ target[:3, :3]).reshape(-1, 9) @ tail_rot.T
    if exact:
        ang = np.arccos(np.clip((tr - 1.0) * 0.5, -1.0, 1.0))
    else:
        ang = np.sqrt(np.maximum(3.0 - tr, 0.0))
    return weights.position * pos + weights.orientation * ang


@lru_cache(maxsize=64)
def _tail_set(chain: Chain, first: int, samples: int) -> tuple[Array, Array]:
    """Positions (S, 3) and flattened rotations (S, 9) of A_{first,n} for a fixed set of tail
    states: all 8^(n - first) when there are at most `samples`, else `samples` uniformly random
    ones (seeded by the chain's length and `first`, so a search is repeatable)."""
    k = chain.n - first
    if 8 ** k <= samples:
        ends = _window_table(chain, first, k)
    else:
        rng = np.random.default_rng(1000 * chain.n + first)
        ends = _fk(chain.table[first:], rng.integers(0, 8, size=(samples, k)))
    return ends[:, :3, 3].copy(), ends[:, :3, :3].reshape(-1, 9).copy()


@lru_cache(maxsize=16)
def _tail_tree(chain: Chain, first: int, weights: Weights) -> tuple[Any, Array, Array]:
    """A k-d tree over the enumerated workspace of stages first+1 .. n (8^(n - first) end
    frames in the frame they start from), in features (w_pos p, w_ang / sqrt 2 R) whose
    Euclidean distance approximates the weighted pose error (|R1 - R2|_F = 2 sqrt 2 sin(a / 2)),
    with the frames' positions (S, 3) and flattened rotations (S, 9)."""
    from scipy.spatial import cKDTree  # noqa: PLC0415 - only the beam search needs it
    ends = _window_table(chain, first, chain.n - first)
    pos, rot = ends[:, :3, 3].copy(), ends[:, :3, :3].reshape(-1, 9).copy()
    feats = np.concatenate([weights.position * pos,
                            weights.orientation / math.sqrt(2.0) * rot], axis=1)
    return cKDTree(feats), pos, rot


def _complete(chain: Chain, frames: Array, target: Array, weights: Weights, first: int,
              neighbours: int) -> tuple[int, int, float, int]:
    """Complete each frame A_0,first (B, 4, 4) with the tail (stages first+1 .. n) nearest
    what it needs, A_0,first^-1 T*, among the `neighbours` nearest in the k-d tree, re-ranked
    by the exact weighted error: (frame index, tail flat index, cost, evaluations)."""
    tree, tail_pos, tail_rot = _tail_tree(chain, first, weights)
    rt = np.swapaxes(frames[:, :3, :3], 1, 2)
    q = np.einsum('bij,bj->bi', rt, target[:3, 3] - frames[:, :3, 3])
    qr = (rt @ target[:3, :3]).reshape(-1, 9)
    feats = np.concatenate([weights.position * q,
                            weights.orientation / math.sqrt(2.0) * qr], axis=1)
    k = min(neighbours, tail_pos.shape[0])
    _, idx = tree.query(feats, k=k)
    idx = np.asarray(idx).reshape(frames.shape[0], k)
    pos = np.linalg.norm(tail_pos[idx] - q[:, None, :], axis=2)
    tr = np.einsum('bkj,bj->bk', tail_rot[idx], qr)
    ang = np.arccos(np.clip((tr - 1.0) * 0.5, -1.0, 1.0))
    cost = weights.position * pos + weights.orientation * ang
    b, j = np.unravel_index(int(np.argmin(cost)), cost.shape)
    return int(b), int(idx[b, j]), float(cost[b, j]), int(cost.size)


def _beam(chain: Chain, target: Array, weights: Weights, opt: BeamOptions) -> tuple[States, int]:
    n, table = chain.n, chain.table
    m = min(opt.tail_stages, n)
    head = n - m
    frames = np.eye(4)[None]
    states = np.zeros((1, 0), dtype=np.int64)
    evals = 0
    for d in range(head):
        if frames.shape[0] > opt.width:
            if opt.score is BeamScore.SAMPLED:
                tail_pos, tail_rot = _tail_set(chain, d, opt.samples)
                score = _cost_matrix(frames, tail_pos, tail_rot, target, weights,
                                     exact=False).min(axis=1)
                evals += score.size * tail_pos.shape[0]
            else:
                score = _density_score(chain, d, frames, target)
            keep = np.argpartition(score, opt.width)[:opt.width]
            frames, states = frames[keep], states[keep]
        frames = (frames[:, None] @ table[d][None]).reshape(-1, 4, 4)
        states = np.concatenate(
            [np.repeat(states, 8, axis=0), np.tile(np.arange(8), states.shape[0])[:, None]],
            axis=1)
    b, j, _, e = _complete(chain, frames, target, weights, head, opt.neighbours)
    evals += e
    best = np.concatenate([states[b], Chain.flat_to_states(j, m)])
    if opt.polish > 0:
        best, _, e = _descend(chain, best, target, weights, window=opt.polish_window,
                              max_sweeps=opt.polish)
        evals += e
    return best, evals


Options = GeneticOptions | CombinatorialOptions | BeamOptions


def solve(chain: Chain, target: NDArray[np.floating], *, method: Method = Method.BEAM,
          weights: Weights | None = None,
          rng: np.random.Generator | int | Sequence[int] | None = None,
          options: Options | None = None) -> IKResult:
    """The chain state whose end pose A_0n is nearest `target` (4x4) under the weighted pose
    error, by `method` (see the module docstring); `rng` seeds the randomised searches (genetic,
    combinatorial); `options` the method's own options (its *Options class; None: defaults).
    An unreachable target gets the nearest pose found, not an exception; BraidError for a
    malformed target, options of another method, or exhaustive search of more than 6 stages."""
    target = check_target(target)
    weights = Weights() if weights is None else weights
    gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    method = Method(method)
    kinds: dict[Method, type | None] = {
        Method.EXHAUSTIVE: None, Method.GENETIC: GeneticOptions,
        Method.COMBINATORIAL: CombinatorialOptions, Method.BEAM: BeamOptions}
    kind = kinds[method]
    if options is not None and (kind is None or not isinstance(options, kind)):
        raise BraidError(f'{method.value}: options of type '
                         f'{kind.__name__ if kind else "None"}, not {type(options).__name__}')
    if method is Method.EXHAUSTIVE:
        states, evals = _exhaustive(chain, target, weights)
    elif method is Method.GENETIC:
        states, evals = _genetic(chain, target, weights, gen,
                                 options if isinstance(options, GeneticOptions)
                                 else GeneticOptions())
    elif method is Method.COMBINATORIAL:
        states, evals = _combinatorial(chain, target, weights, gen,
                                       options if isinstance(options, CombinatorialOptions)
                                       else CombinatorialOptions())
    else:
        states, evals = _beam(chain, target, weights,
                              options if isinstance(options, BeamOptions) else BeamOptions())
    return _result(chain, method, states, target, weights, evals)
