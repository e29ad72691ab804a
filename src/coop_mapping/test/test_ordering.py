"""Fusion in stamp order whatever the order contributions come in (coop_mapping.ordering)."""
from __future__ import annotations

import numpy as np
import pytest

from coop_mapping.ordering import OrderedFusion
from coop_mapping.voxelmap import VoxelMap

S = 1_000_000_000


def _scans(n: int, seed: int = 1):
    """n scans of a scene whose middle changes (a box there in some scans, not in others), from
    origins that move: clamped log-odds make the map depend on the order they are fused in."""
    rng = np.random.default_rng(seed)
    maker = VoxelMap(0.1)
    out = []
    for _ in range(n):
        org = np.array([0.0, rng.uniform(-0.5, 0.5), 0.8])
        wall = np.c_[np.full(800, 3.0), rng.uniform(-1.5, 1.5, 800), rng.uniform(0, 1.5, 800)]
        parts = [wall]
        if rng.random() < 0.5:
            parts.append(np.c_[np.full(300, 1.5), rng.uniform(-0.3, 0.3, 300),
                               rng.uniform(0.2, 0.8, 300)])
        pts = np.vstack(parts) + rng.normal(0, 0.01, (sum(len(p) for p in parts), 3))
        out.append(maker.contribution(pts, org))
    return out


def _same(a: VoxelMap, b: VoxelMap) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(a._arrays().values(),
                                                    b._arrays().values(), strict=True))


def test_late_contributions_are_fused_in_their_place():
    """Two rovers at 4 Hz; rover1 cut off for 2.5 s: its scans of that time come after
    rover2's later ones. The map is the map fused in stamp order, not the one fused as they
    came."""
    scans = _scans(24)
    sources = ['rover1' if i % 2 == 0 else 'rover2' for i in range(24)]
    stamps = [(i // 2) * S // 4 + (i % 2) * 1_000_000 for i in range(24)]
    ordered = VoxelMap(0.1)
    for c, s in zip(scans, sources, strict=True):
        ordered.apply(c, source=s)
    late = [i for i in range(24) if sources[i] == 'rover1' and 6 <= i <= 15]
    arrival = [i for i in range(24) if i not in late] + late
    naive = VoxelMap(0.1)
    for i in arrival:
        naive.apply(scans[i], source=sources[i])
    assert not _same(naive, ordered), 'the scene must make the order matter'
    fusion = OrderedFusion(VoxelMap(0.1), horizon_s=30.0, late_s=0.3, checkpoint_s=0.5)
    outcomes = [fusion.add(scans[i], stamp_ns=stamps[i], source=sources[i]) for i in arrival]
    assert sum(f.deferred for f in outcomes) == len(late)
    assert not any(f.beyond_horizon for f in outcomes)
    changed = fusion.settle()
    assert changed is not None and changed.size
    assert fusion.settle() is None and fusion.rebuilds == 1
    assert _same(fusion.map, ordered)
    assert fusion.map.sequence == 24
    assert fusion.map.contributions == {'rover1': 12, 'rover2': 12}
    # within late_s, the order they come in is the order they are fused in (jitter)
    jitter = OrderedFusion(VoxelMap(0.1), late_s=1.0)
    swapped = [1, 0, 3, 2, 5, 4]
    for i in swapped:
        assert jitter.add(scans[i], stamp_ns=stamps[i], source=sources[i]).result is not None
    plain = VoxelMap(0.1)
    for i in swapped:
        plain.apply(scans[i], source=sources[i])
    assert _same(jitter.map, plain)


def test_a_burst_of_late_ones_gives_the_map_fused_in_stamp_order():
    scans = _scans(30, seed=2)
    stamps = [i * S // 4 for i in range(30)]
    ordered = VoxelMap(0.1)
    for c in scans:
        ordered.apply(c, source='r')
    # scans 10..19 arrive after 20..29, more than late_s behind
    arrival = [*range(10), *range(20, 30), *range(10, 20)]
    fusion = OrderedFusion(VoxelMap(0.1), horizon_s=30.0, late_s=0.5, checkpoint_s=1.0)
    fusion.map.ledger.admit('r', 1, 1)
    for k, i in enumerate(arrival):
        fusion.add(scans[i], stamp_ns=stamps[i], source='r')
        if k % 3 == 0:
            fusion.settle()                    # the mapper's timer, in the middle of the burst
    fusion.settle()
    assert _same(fusion.map, ordered)
    assert fusion.map.ledger.sources['r'].fused == 1       # the ledger is kept across rebuilds
    # and the journal keeps only the horizon
    assert len(fusion.journal) <= 30


def test_older_than_the_horizon_is_fused_at_the_end():
    scans = _scans(12, seed=3)
    fusion = OrderedFusion(VoxelMap(0.1), horizon_s=1.0, late_s=0.2, checkpoint_s=0.25)
    for i in range(1, 12):
        fusion.add(scans[i], stamp_ns=i * S // 2, source='r')
    f = fusion.add(scans[0], stamp_ns=0, source='r')
    assert f.beyond_horizon and f.result is not None
    assert fusion.map.sequence == 12
    assert len(fusion.journal) <= 5


def test_horizon_zero_fuses_in_arrival_order():
    scans = _scans(6, seed=4)
    fusion = OrderedFusion(VoxelMap(0.1), horizon_s=0.0)
    plain = VoxelMap(0.1)
    for i in (3, 4, 5, 0, 1, 2):
        assert fusion.add(scans[i], stamp_ns=i * S, source='r').result is not None
        plain.apply(scans[i], source='r')
    assert _same(fusion.map, plain)
    with pytest.raises(ValueError):
        OrderedFusion(VoxelMap(0.1), checkpoint_s=0.0)
