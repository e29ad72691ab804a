"""Fusion in stamp order when some contributions come late (no rclpy).

OctoMap's clamped log-odds make a map depend on the order its scans are fused in: a voxel hit
five times and then missed three times is not the voxel missed first. Rovers whose links drop
out deliver the scans they made meanwhile late, all at once, after their teammates' later ones:
fused as they come, the map of a run with a cut differs from the same run without one (0.1-0.2 %
of the voxels of `bags/mapping_two_rovers` for a 4 s cut).

`OrderedFusion` keeps the map as if every scan had come in stamp order, for scans up to
`horizon_s` late. It keeps the contributions of the last `horizon_s` in the order they are in
the map (a journal) and a copy of the map every `checkpoint_s` of stamps. A contribution no more
than `late_s` behind the newest stamp fused is fused at once, in arrival order (the jitter of
streams that run together). A later one is put into the journal at its stamp, and `settle` (the
mapper calls it from its timer, so a burst of backlog costs one rebuild) rebuilds the map from
the last checkpoint before it by fusing the journal again from there. One older than the horizon
is fused at once at the end (counted by the caller as `beyond_horizon`). While late ones wait,
the ones that come after them wait too, and the same rebuild fuses them after.
"""
from __future__ import annotations

import bisect
from dataclasses import dataclass

import numpy as np

from .voxelmap import Contribution, InsertResult, VoxelMap

__all__ = ['Fused', 'OrderedFusion']


@dataclass(frozen=True)
class _Entry:
    stamp_ns: int
    source: str
    contribution: Contribution


@dataclass(frozen=True)
class Fused:
    """What `add` did: `result` when the contribution is in the map now; `deferred` when it
    waits for `settle`; `beyond_horizon` when it came too late to be put in order."""

    result: InsertResult | None
    deferred: bool = False
    beyond_horizon: bool = False


class OrderedFusion:
    """A VoxelMap fed contributions in stamp order (the module docstring)."""

    def __init__(self, vm: VoxelMap, *, horizon_s: float = 30.0, late_s: float = 1.0,
                 checkpoint_s: float = 5.0) -> None:
        if not (horizon_s >= 0 and late_s >= 0 and checkpoint_s > 0):
            raise ValueError('horizon_s and late_s must be >= 0, checkpoint_s > 0')
        self.map = vm
        self.horizon_ns = round(horizon_s * 1e9)
        self.late_ns = round(late_s * 1e9)
        self.checkpoint_ns = round(checkpoint_s * 1e9)
        self.newest_ns: int | None = None
        self.journal: list[_Entry] = []
        # (journal index, stamp when taken, the map before journal[index])
        self.checkpoints: list[tuple[int, int, VoxelMap]] = []
        self._rebuild_from: int | None = None
        self.rebuilds = 0

    @property
    def pending(self) -> bool:
        """Whether late contributions wait for `settle`."""
        return self._rebuild_from is not None

    def add(self, c: Contribution, *, stamp_ns: int, source: str) -> Fused:
        """Fuse `c` (taken at stamp_ns by `source`) in its place (the module docstring)."""
        entry = _Entry(int(stamp_ns), source, c)
        if self.horizon_ns == 0:
            return Fused(self.map.apply(c, source=source))
        if self.newest_ns is None or entry.stamp_ns >= self.newest_ns - self.late_ns:
            if self.pending:        # after the late ones, by the same rebuild
                self.journal.append(entry)
                self.newest_ns = max(self.newest_ns or entry.stamp_ns, entry.stamp_ns)
                return Fused(None, deferred=True)
            return Fused(self._append(entry))
        # late: after the last entry of the journal not later than it
        stamps = [e.stamp_ns for e in self.journal]
        pos = len(stamps)
        while pos > 0 and stamps[pos - 1] > entry.stamp_ns:
            pos -= 1
        if not self.checkpoints or pos < self.checkpoints[0][0] or \
                entry.stamp_ns < self.newest_ns - self.horizon_ns:
            return Fused(self._append(entry), beyond_horizon=True)
        self.journal.insert(pos, entry)
        # checkpoints after the insertion no longer hold the map before their entry
        self.checkpoints = [cp for cp in self.checkpoints if cp[0] <= pos]
        self._rebuild_from = pos if self._rebuild_from is None else min(self._rebuild_from, pos)
        return Fused(None, deferred=True)

    def _append(self, entry: _Entry) -> InsertResult:
        if self._due_checkpoint(entry.stamp_ns):
            self.checkpoints.append((len(self.journal), entry.stamp_ns, self.map.copy()))
        res = self.map.apply(entry.contribution, source=entry.source)
        self.journal.append(entry)
        self.newest_ns = entry.stamp_ns if self.newest_ns is None else \
            max(self.newest_ns, entry.stamp_ns)
        self._trim()
        return res

    def _due_checkpoint(self, stamp_ns: int) -> bool:
        return not self.checkpoints or stamp_ns - self.checkpoints[-1][1] >= self.checkpoint_ns

    def _trim(self) -> None:
        """Forget the checkpoints (and the journal before them) older than the horizon, keeping
        the newest such one: the place the horizon's oldest scan can be put back from."""
        if self.newest_ns is None:
            return
        edge = self.newest_ns - self.horizon_ns
        while len(self.checkpoints) >= 2 and self.checkpoints[1][1] <= edge:
            self.checkpoints.pop(0)
        first = self.checkpoints[0][0] if self.checkpoints else len(self.journal)
        if first:
            del self.journal[:first]
            self.checkpoints = [(i - first, s, m) for i, s, m in self.checkpoints]

    def settle(self) -> np.ndarray | None:
        """Rebuild the map with the late contributions in their place, if any wait: the sorted
        keys of every voxel the rebuild may have changed (None: nothing to do)."""
        if self._rebuild_from is None:
            return None
        pos = self._rebuild_from
        self._rebuild_from = None
        k = bisect.bisect_right([cp[0] for cp in self.checkpoints], pos) - 1
        start, _, snapshot = self.checkpoints[k]
        del self.checkpoints[k + 1:]
        ledger, limit = self.map.ledger, self.map.max_points
        vm = snapshot.copy()
        vm.ledger, vm.max_points = ledger, limit   # what has been admitted stays admitted
        changed = []
        for i in range(start, len(self.journal)):
            e = self.journal[i]
            if i > start and self._due_checkpoint(e.stamp_ns):
                self.checkpoints.append((i, e.stamp_ns, vm.copy()))
            changed.append(vm.apply(e.contribution, source=e.source).changed)
        self.map = vm
        self.rebuilds += 1
        self._trim()
        return np.unique(np.concatenate(changed)) if changed else np.empty(0, np.int64)
