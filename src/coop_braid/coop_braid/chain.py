"""The BRAID chain (thesis Eq. E-3): A_0n as the product of its stages' A_{i-1,i}, batched over
many state vectors, and the workspace of all 2^(3n) states for a short chain (Fig. E-5).

A state of an n-stage chain is a vector of n stage states in 0..7 (stage 1 at the base; bit
j - 1 of a stage state is its leg j, `stage.leg_states`). A flat state index (the workspace's
order) reads those n digits base 8, stage 1 the most significant.
"""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from coop_braid.errors import BraidError
from coop_braid.stage import STATES_PER_STAGE, StageGeometry

#: the longest chain whose whole workspace is enumerated (8^6 = 262144 poses, 34 MB)
MAX_WORKSPACE_STAGES = 6


@dataclass(frozen=True)
class Moments:
    """First and second moments of the end frame of k stages in uniformly random states,
    expressed in the frame the k stages start from: `mean` E[A] (4x4) and `second`
    E[A (x) A] (16x16, Kronecker), exact (the stages are independent: E of a product of
    independent matrices is the product of the Es)."""

    mean: NDArray[np.float64]
    second: NDArray[np.float64]


@dataclass(frozen=True)
class Chain:
    """An n-stage BRAID: one StageGeometry per stage (base first)."""

    stages: tuple[StageGeometry, ...]
    _table: NDArray[np.float64] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not self.stages:
            raise BraidError('a BRAID chain has at least one stage')
        if not all(isinstance(s, StageGeometry) for s in self.stages):
            raise BraidError('Chain.stages: StageGeometry instances')
        table = np.stack([s.transforms for s in self.stages])
        table.setflags(write=False)
        object.__setattr__(self, '_table', table)

    @classmethod
    def uniform(cls, geometry: StageGeometry, n: int) -> Chain:
        """n identical stages."""
        if n < 1:
            raise BraidError(f'a BRAID chain has at least one stage, not {n}')
        return cls((geometry,) * n)

    @property
    def n(self) -> int:
        """Number of stages."""
        return len(self.stages)

    @property
    def table(self) -> NDArray[np.float64]:
        """A_{i-1,i} of every stage and state, (n, 8, 4, 4), read-only."""
        return self._table

    def check_states(self, states: NDArray[np.integer] | Sequence[int]) -> NDArray[np.int64]:
        """`states` as an int array whose last axis is the n stages, each in 0..7."""
        s = np.asarray(states)
        if s.ndim == 0 or s.shape[-1] != self.n or not np.issubdtype(s.dtype, np.integer):
            raise BraidError(f'states: integers with a last axis of {self.n} stages, '
                             f'not {s.dtype} {s.shape}')
        if s.size and (s.min() < 0 or s.max() >= STATES_PER_STAGE):
            raise BraidError('states: every stage state is in 0..7')
        return s.astype(np.int64)

    def pose(self, states: NDArray[np.integer] | Sequence[int]) -> NDArray[np.float64]:
        """A_0n (Eq. E-3) of one state vector, 4x4."""
        s = self.check_states(states)
        if s.ndim != 1:
            raise BraidError(f'pose: one state vector, not {s.shape}')
        out = np.eye(4)
        for i, k in enumerate(s):
            out = out @ self._table[i, k]
        return out

    def poses(self, states: NDArray[np.integer] | Sequence[int]) -> NDArray[np.float64]:
        """A_0n of a batch of state vectors (..., n) -> (..., 4, 4)."""
        s = self.check_states(states)
        flat = s.reshape(-1, self.n)
        out = np.broadcast_to(np.eye(4), (flat.shape[0], 4, 4)).copy()
        for i in range(self.n):
            out = out @ self._table[i, flat[:, i]]
        return out.reshape(*s.shape[:-1], 4, 4)

    def partial(self, states: NDArray[np.integer] | Sequence[int], start: int,
                stop: int) -> NDArray[np.float64]:
        """A_{start,stop}: the product of stages start+1 .. stop of one state vector."""
        s = self.check_states(states)
        out = np.eye(4)
        for i in range(start, stop):
            out = out @ self._table[i, s[i]]
        return out

    def workspace(self, *, first: int = 0, stop: int | None = None) -> NDArray[np.float64]:
        """A_{first,stop} of every one of the 8^(stop - first) states of stages first+1 .. stop
        (default the whole chain), (8^k, 4, 4), in flat-index order (Fig. E-5 for n = 5). Refused
        for more than MAX_WORKSPACE_STAGES stages."""
        stop = self.n if stop is None else stop
        k = stop - first
        if not 0 < k <= MAX_WORKSPACE_STAGES or first < 0 or stop > self.n:
            raise BraidError(f'workspace of stages {first + 1}..{stop}: 1 to '
                             f'{MAX_WORKSPACE_STAGES} stages of the {self.n}')
        out = self._table[first].copy()
        for i in range(first + 1, stop):
            out = (out[:, None] @ self._table[i][None]).reshape(-1, 4, 4)
        return out

    @staticmethod
    def flat_to_states(index: NDArray[np.integer] | int, k: int) -> NDArray[np.int64]:
        """Flat workspace indices -> state vectors (..., k) (stage 1 the most significant)."""
        idx = np.asarray(index, dtype=np.int64)
        shifts = 3 * np.arange(k - 1, -1, -1)
        return (idx[..., None] >> shifts) & 7

    def straight_reach(self) -> float:
        """Distance from the base to the end of the fully extended, straight chain (every leg
        long): the reach that `% of reach` is taken of."""
        return float(np.linalg.norm(self.pose(np.full(self.n, 7))[:3, 3]))

    @cached_property
    def _stage_moments(self) -> tuple[Moments, ...]:
        out = []
        for i in range(self.n):
            t = self._table[i]
            mean = t.mean(axis=0)
            second = np.mean([np.kron(a, a) for a in t], axis=0)
            out.append(Moments(mean, second))
        return tuple(out)

    def suffix_moments(self, first: int) -> Moments:
        """Moments of A_{first,n} over uniformly random states of stages first+1 .. n."""
        mean, second = np.eye(4), np.eye(16)
        for m in self._stage_moments[first:]:
            mean, second = mean @ m.mean, second @ m.second
        return Moments(mean, second)
