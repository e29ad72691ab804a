"""The camera mast the view planner places views for (issue #37, deliverable 5): the pan/tilt
head (the default rover) or a BRAID chain, whose reachable views come from BRAID IK.

`braid_views` asks `coop_braid.mast.view_table` for a lattice of wanted views (camera heights
above the ground x the planner's pitches) and gives the planner the views the mast reaches as
`nbv.MastView`s: each the pose the IK's chain state really gives (offset from the turntable's
axis, height, heading offset, pitch), kept only when it is within the tolerance of the wanted
one. The planner then proposes no other camera pose, and rates each at the pose the mast will
give, residual included; the chosen view's `states` are what the mast is commanded to.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from coop_braid.errors import BraidError
from coop_braid.ik import Weights
from coop_braid.mast import BraidMast, MastKind, Tolerance, Tried, view_table
from coop_common.rover_geometry import BASE_HEIGHT_M, MAST_POSITION

from .errors import OptionError
from .nbv import MastView

#: the pan joint's height above the ground on the rover at rest (m)
PAN_HEIGHT_M = BASE_HEIGHT_M + MAST_POSITION[2]
#: the wanted camera heights above the ground of the rover's BRAID mast (m): from the straight,
#: retracted chain's 0.85 m (0.05 m above the pan/tilt head's camera; the chain reaches no lower
#: with its camera near level) in 5 cm steps to 0.95 (the extended chain's 1.00 m only straight)
BRAID_HEIGHTS_M = (0.85, 0.90, 0.95)
#: the wanted poses IK is given for each view (view_table): forward offsets (m), headings and
#: rolls (deg) that serve the same view
FORWARDS_M = (-0.05, 0.0, 0.05)
HEADINGS_DEG = (-8.0, 0.0, 8.0)
ROLLS_DEG = (-12.0, 0.0, 12.0)
#: the IK's orientation weight for a camera: one degree is worth 5 mm of position
ORIENTATION_WEIGHT_M = 0.3

__all__ = ['BRAID_HEIGHTS_M', 'PAN_HEIGHT_M', 'BraidViews', 'MastKind', 'braid_views']


@dataclass(frozen=True)
class BraidViews:
    """The planner's views of a BRAID mast (`views`, for `NbvConfig.mast_views`), the chain
    state of each (`states`, (V, n)), and what was tried (`tried`: every wanted view with its
    residual and whether it was reached)."""

    views: tuple[MastView, ...]
    states: NDArray[np.int64]
    tried: tuple[Tried, ...]


@lru_cache(maxsize=8)
def braid_views(stages: int, *, heights_m: Sequence[float] = BRAID_HEIGHTS_M,
                pitches_deg: Sequence[float] = (5.0, 20.0),
                tolerance: Tolerance | None = None) -> BraidViews:
    """The views the rover's `stages`-stage BRAID mast (`BraidMast.rover`) reaches among the
    wanted heights (above the ground, m) x pitches (deg, nose down), by BRAID IK (beam search,
    `ORIENTATION_WEIGHT_M`); cached (the IK takes seconds). OptionError: no wanted view is
    reached, or bad input (the reason)."""
    try:
        mast = BraidMast.rover(stages)
        table = view_table(
            mast, heights_m=[h - PAN_HEIGHT_M for h in heights_m],
            pitches_rad=[math.radians(p) for p in pitches_deg], forwards_m=FORWARDS_M,
            headings_rad=[math.radians(h) for h in HEADINGS_DEG],
            rolls_rad=[math.radians(r) for r in ROLLS_DEG], tolerance=tolerance,
            weights=Weights(orientation=ORIENTATION_WEIGHT_M))
    except BraidError as exc:
        raise OptionError(f'BRAID mast of {stages} stages: {exc}') from None
    if not table.views:
        raise OptionError(f'BRAID mast of {stages} stages reaches none of the wanted views '
                          f'(heights {list(heights_m)} m, pitches {list(pitches_deg)} deg)')
    views = tuple(MastView(forward_m=float(v.offset[0]), lateral_m=float(v.offset[1]),
                           height_m=PAN_HEIGHT_M + float(v.offset[2]), heading_rad=v.heading,
                           pitch_rad=v.pitch) for v in table.views)
    states = np.stack([v.states for v in table.views]).astype(np.int64)
    return BraidViews(views, states, table.tried)
