"""Seeded generator of the site: rocks and drums at a given occlusion density, the 4.25 in card
with its two white circular markers, and the insertion site with its slot and markers (ch. 5.2)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

INCH = 0.0254


@dataclass(frozen=True)
class Obstacle:
    kind: str                  # 'rock' (sphere) or 'drum' (upright cylinder)
    position: tuple[float, float, float]
    radius: float
    height: float              # drum height; rock: 2 * radius
    shade: float               # grey level 0..1 of its texture


SITE_MARKER_RADIUS_M = 0.02


@dataclass(frozen=True)
class Site:
    """The insertion site: a block with a vertical slot, two white markers either side of it."""

    position: tuple[float, float, float]
    yaw: float
    slot_width_m: float
    markers: tuple[tuple[float, float, float], ...]   # world marker centres
    marker_radius_m: float


@dataclass(frozen=True)
class Card:
    """The 4.25 in card carried by the slave rover, with two white circular markers."""

    width_m: float = 4.25 * INCH
    height_m: float = 2.75 * INCH
    thickness_m: float = 0.003
    marker_radius_m: float = 0.25 * INCH
    marker_offsets: tuple[tuple[float, float], ...] = ((-1.25 * INCH, 0.0), (1.25 * INCH, 0.0))


@dataclass(frozen=True)
class WorldLayout:
    obstacles: tuple[Obstacle, ...]
    site: Site
    card: Card = field(default_factory=Card)
    extent_m: float = 10.0


def generate_world(*, seed: int, occlusion_density: float, extent_m: float = 10.0,
                   keep_clear: tuple[tuple[float, float, float], ...] = (),
                   slot_width_m: float = 0.004, site_position: tuple[float, float] = (3.0, 0.0)
                   ) -> WorldLayout:
    """Obstacles covering `occlusion_density` of the extent_m x extent_m square (footprint area),
    none overlapping another, the site, or any keep-clear disc (x, y, radius)."""
    if not (0.0 <= occlusion_density <= 0.5):
        raise ValueError(f'occlusion_density must be in [0, 0.5], got {occlusion_density}')
    if not (extent_m > 0):
        raise ValueError('extent_m must be > 0')
    if not (0.0 < slot_width_m < 0.05):
        raise ValueError(f'slot_width_m must be in (0, 0.05), got {slot_width_m}')
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
        kind = 'rock' if rng.random() < 0.6 else 'drum'
        radius = float(rng.uniform(0.15, 0.45) if kind == 'rock' else rng.uniform(0.25, 0.35))
        x, y = rng.uniform(-extent_m / 2, extent_m / 2, size=2)
        if any((x - cx) ** 2 + (y - cy) ** 2 < (cr + radius + 0.05) ** 2 for cx, cy, cr in
               clear + placed):
            continue
        height = 2 * radius if kind == 'rock' else float(rng.uniform(0.8, 0.9))
        z = radius * 0.7 if kind == 'rock' else height / 2
        obstacles.append(Obstacle(kind, (float(x), float(y), float(z)), radius, height,
                                  float(rng.uniform(0.25, 0.75))))
        placed.append((float(x), float(y), radius))
        area += np.pi * radius ** 2
    yaw = np.pi
    sx, sy = site_position
    marker_h = 0.25
    off = 0.06 + slot_width_m / 2
    # markers either side of the slot on the site's face towards -x (the rovers' side)
    face_x = sx - 0.1
    markers = ((face_x, sy - off, marker_h), (face_x, sy + off, marker_h))
    # the discs world.py draws (and the sim's /sim/world markers show) are 0.02 m in radius
    site = Site((sx, sy, 0.2), yaw, slot_width_m, markers, SITE_MARKER_RADIUS_M)
    return WorldLayout(tuple(obstacles), site, Card(), extent_m)


def occlusion_fraction(layout: WorldLayout) -> float:
    """Footprint area of the obstacles over the extent's area."""
    a = sum(np.pi * o.radius ** 2 for o in layout.obstacles)
    return a / layout.extent_m ** 2
