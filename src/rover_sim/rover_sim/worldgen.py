"""Seeded generator of the site: rocks and drums at a given occlusion density, the 4.25 in card
with its two white circular markers, and the insertion site: two jaws forming the slot of
Table 5-1, with its markers (ch. 5.2)."""
from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np

from coop_common.params import choice

from .errors import SimError

INCH = 0.0254


class ObstacleKind(StrEnum):
    """The site's obstacles: a rock (a sphere, sunk 30 % into the ground) or a drum (an
    upright cylinder)."""

    ROCK = 'rock'
    DRUM = 'drum'


@dataclass(frozen=True)
class Obstacle:
    """One obstacle of the generated world."""

    kind: ObstacleKind
    position: tuple[float, float, float]
    radius: float
    height: float              # drum height; rock: 2 * radius
    shade: float               # grey level 0..1 of its texture

    def __post_init__(self) -> None:
        object.__setattr__(self, 'kind', choice(ObstacleKind, self.kind, 'kind', error=SimError))


SITE_MARKER_RADIUS_M = 0.02
CARD_WIDTH_M = 4.25 * INCH
#: Table 5-1's insertion sites for the 4.25 in card: ~18 %, ~6 %, ~3 % of its width in clearance
TABLE_5_1_GAPS_M = (5.0 * INCH, 4.5 * INCH, 4.375 * INCH)
JAW_DEPTH_M = 0.10             # each jaw's length along x
JAW_HALF_WIDTH_M = 0.10        # the jaws' and the slot's extent along y is +-this
SITE_TOP_M = 0.40              # height of the jaw tops (the slot's mouth)
SEAT_DEPTH_M = 0.03            # floor of the slot below the mouth: the card is seated on it
FIDUCIAL_OFFSET_M = 0.062      # the fiducials' y either side of the site's centre line
FIDUCIAL_HEIGHT_M = 0.25
SLOT_MARKER_RADIUS_M = 0.125 * INCH     # ch. 5.3: markers of 0.25 in diameter
SLOT_MARKER_DEPTH_M = 0.03     # slot markers' centres below the mouth, on the jaws' +y faces
SLOT_MARKER_INSET_M = 0.03     # ... and this far from the slot's edges along x


@dataclass(frozen=True)
class Box:
    """A static box: centre and half extents (world axes)."""

    centre: tuple[float, float, float]
    half_extents: tuple[float, float, float]


@dataclass(frozen=True)
class Site:
    """The insertion site (ch. 5.2, Table 5-1). Two jaws stand side by side along world x with
    `gap_m` between them: the slot the card's width goes into, open at the top and through y,
    with a floor `seat_depth_m` below the mouth. The card is lowered into it edge first; the
    motion is planar in x-z, as the thesis assumes.

    - `position`, `yaw`: the site frame of the §3.2.2 target-frame initialisation (origin at
      (x, y, 0.2), x out of the near jaw's face towards -x, z up); `markers`: the two white
      fiducials (radius `marker_radius_m`) on that face, the frame's known points.
    - `slot_markers`: two markers (radius `slot_marker_radius_m`) on the jaws' +y faces either
      side of the slot mouth (near jaw first), watched with the card's markers during the
      insertion (ch. 5.3); `slot_centre`: the centre of the mouth.
    - `jaws`: the near jaw, the far jaw and the floor, the collision bodies."""

    position: tuple[float, float, float]
    yaw: float
    gap_m: float
    markers: tuple[tuple[float, float, float], ...]   # world marker centres
    marker_radius_m: float
    slot_markers: tuple[tuple[float, float, float], ...]
    slot_marker_radius_m: float
    slot_centre: tuple[float, float, float]
    jaws: tuple[Box, Box, Box]
    seat_depth_m: float = SEAT_DEPTH_M


@dataclass(frozen=True)
class Card:
    """The 4.25 in card carried by the slave rover, with two white circular markers on its +y
    face. Held by rover 2's gripper with its width along the last arm link's x, its height
    along z, its thickness along y (the card frame: centre, x width, y normal, z height)."""

    width_m: float = 4.25 * INCH
    height_m: float = 2.75 * INCH
    thickness_m: float = 0.003
    marker_radius_m: float = 0.25 * INCH
    marker_offsets: tuple[tuple[float, float], ...] = ((-1.25 * INCH, 0.0), (1.25 * INCH, 0.0))


@dataclass(frozen=True)
class WorldLayout:
    """A generated world: its obstacles, the work site, the card and the extent."""

    obstacles: tuple[Obstacle, ...]
    site: Site
    card: Card = field(default_factory=Card)
    extent_m: float = 10.0


def generate_world(*, seed: int, occlusion_density: float, extent_m: float = 10.0,
                   keep_clear: tuple[tuple[float, float, float], ...] = (),
                   slot_gap_m: float = TABLE_5_1_GAPS_M[1],
                   site_position: tuple[float, float] = (3.0, 0.0)) -> WorldLayout:
    """Obstacles covering `occlusion_density` of the extent_m x extent_m square (footprint area),
    none overlapping another, the site, or any keep-clear disc (x, y, radius)."""
    if not (0.0 <= occlusion_density <= 0.5):
        raise ValueError(f'occlusion_density must be in [0, 0.5], got {occlusion_density}')
    if not (extent_m > 0):
        raise ValueError('extent_m must be > 0')
    if not (CARD_WIDTH_M < slot_gap_m <= 0.25):
        raise ValueError(f'slot_gap_m must be in ({CARD_WIDTH_M:.5f}, 0.25] (wider than the '
                         f'{CARD_WIDTH_M:.5f} m card), got {slot_gap_m}')
    rng = np.random.default_rng(seed)
    clear = [tuple(map(float, k)) for k in keep_clear]
    clear.append((site_position[0], site_position[1], 0.8))
    target_area = occlusion_density * extent_m ** 2
    area = 0.0
    obstacles: list[Obstacle] = []
    placed: list[tuple[float, float, float]] = []
    attempts = 0
    while area < target_area and attempts < 20000:
        attempts += 1
        rock = rng.random() < 0.6
        kind = ObstacleKind.ROCK if rock else ObstacleKind.DRUM
        radius = float(rng.uniform(0.15, 0.45) if rock else rng.uniform(0.25, 0.35))
        x, y = rng.uniform(-extent_m / 2, extent_m / 2, size=2)
        if any((x - cx) ** 2 + (y - cy) ** 2 < (cr + radius + 0.05) ** 2 for cx, cy, cr in
               clear + placed):
            continue
        height = 2 * radius if rock else float(rng.uniform(0.8, 0.9))
        z = radius * 0.7 if rock else height / 2
        obstacles.append(Obstacle(kind, (float(x), float(y), float(z)), radius, height,
                                  float(rng.uniform(0.25, 0.75))))
        placed.append((float(x), float(y), radius))
        area += np.pi * radius ** 2
    return WorldLayout(tuple(obstacles), make_site(site_position, slot_gap_m), Card(), extent_m)


def make_site(position: tuple[float, float], gap_m: float) -> Site:
    """The insertion site with its near jaw's face at x - 0.1 (where the fiducials are, for any
    gap), the slot from x to x + gap_m, the far jaw beyond it."""
    sx, sy = (float(v) for v in position)
    face_x = sx - JAW_DEPTH_M
    half_h = SITE_TOP_M / 2
    floor_h = (SITE_TOP_M - SEAT_DEPTH_M) / 2
    jaws = (Box((sx - JAW_DEPTH_M / 2, sy, half_h), (JAW_DEPTH_M / 2, JAW_HALF_WIDTH_M, half_h)),
            Box((sx + gap_m + JAW_DEPTH_M / 2, sy, half_h),
                (JAW_DEPTH_M / 2, JAW_HALF_WIDTH_M, half_h)),
            Box((sx + gap_m / 2, sy, floor_h), (gap_m / 2, JAW_HALF_WIDTH_M, floor_h)))
    fiducials = ((face_x, sy - FIDUCIAL_OFFSET_M, FIDUCIAL_HEIGHT_M),
                 (face_x, sy + FIDUCIAL_OFFSET_M, FIDUCIAL_HEIGHT_M))
    z = SITE_TOP_M - SLOT_MARKER_DEPTH_M
    y = sy + JAW_HALF_WIDTH_M
    slot_markers = ((sx - SLOT_MARKER_INSET_M, y, z), (sx + gap_m + SLOT_MARKER_INSET_M, y, z))
    return Site((sx, sy, 0.2), float(np.pi), float(gap_m), fiducials, SITE_MARKER_RADIUS_M,
                slot_markers, SLOT_MARKER_RADIUS_M, (sx + gap_m / 2, sy, SITE_TOP_M), jaws)


def occlusion_fraction(layout: WorldLayout) -> float:
    """Footprint area of the obstacles over the extent's area."""
    a = sum(np.pi * o.radius ** 2 for o in layout.obstacles)
    return a / layout.extent_m ** 2
