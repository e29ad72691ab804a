"""OctoMap (octomap-python) as the comparison peer: its leaves as this package's voxel keys.

No octomap import here: the functions take an `octomap.OcTree` built by the caller (the
benchmark and the tests, where the peer is installed).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from .voxelmap import FREE, OCCUPIED, pack_keys


def leaf_states(tree: Any, res: float) -> tuple[np.ndarray, np.ndarray]:
    """(packed keys, FREE/OCCUPIED) of every voxel at resolution `res` covered by a leaf of
    `tree` (a pruned leaf of size s covers (s / res)^3 voxels), sorted by key."""
    keys, occ = [], []
    for leaf in tree.begin_leafs():
        c = np.array(leaf.getCoordinate())
        s = leaf.getSize()
        n = round(s / res)
        lo = np.round((c - s / 2) / res).astype(np.int64)
        g = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing='ij'), -1).reshape(-1, 3) + lo
        keys.append(g)
        occ.append(np.full(len(g), tree.isNodeOccupied(leaf)))
    k = pack_keys(np.concatenate(keys))
    o = np.concatenate(occ)
    i = np.argsort(k)
    return k[i], np.where(o[i], OCCUPIED, FREE).astype(np.int8)
