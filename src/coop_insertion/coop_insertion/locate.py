"""Finding the site from a rough region: the master is told only roughly where the slot is (an
operator's region, or a map's), looks for the slot's markers from views over that region, and
takes the site's pose from the markers it finds (task.site_from_slot) with its camera's pose.

- `search_points`: the targets the master places its camera for, covering the region, the
  region's centre first;
- `SiteEstimate`: the site's pose in the map, averaged over the frames that saw the slot.

No rclpy.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from .errors import InsertionError
from .frames import homogeneous, rot_z

__all__ = ['SiteEstimate', 'search_points']


def search_points(centre: ArrayLike, normal: ArrayLike, *, half_width_m: float, spacing_m: float
                  ) -> np.ndarray:
    """(n, 3) targets over the square region `half_width_m` either side of `centre` in the
    horizontal plane (its sides along the site's face and along its outward `normal`), no two
    neighbours more than `spacing_m` apart, the region's edges included: the centre first,
    then by distance from it (ties: the nearer side of the face first, then along the face)."""
    c = np.asarray(centre, float)
    n = np.asarray(normal, float)
    if c.shape != (3,) or n.shape != (3,) or not (np.all(np.isfinite(c)) and
                                                  np.all(np.isfinite(n))):
        raise InsertionError('centre and normal must be finite 3-vectors')
    n = np.array([n[0], n[1], 0.0])
    if np.linalg.norm(n) < 1e-9:
        raise InsertionError('the normal must not be vertical: the region lies along the face')
    if not (half_width_m >= 0 and spacing_m > 0):
        raise InsertionError('half_width_m must be >= 0 and spacing_m > 0')
    n /= np.linalg.norm(n)
    along = np.array([-n[1], n[0], 0.0])
    k = math.ceil(2 * half_width_m / spacing_m - 1e-9) if half_width_m > 0 else 0
    steps = np.linspace(-half_width_m, half_width_m, k + 1) if k else np.zeros(1)
    offsets = [(a, b) for a in steps for b in steps]
    offsets.sort(key=lambda ab: (round(math.hypot(*ab), 9), -ab[1], ab[0]))
    return np.array([c + a * along + b * n for a, b in offsets])


class SiteEstimate:
    """The site frame in the map (x across the slot, z up) from the frames that saw the slot:
    their mean position and heading."""

    def __init__(self) -> None:
        self._positions: list[np.ndarray] = []
        self._headings: list[float] = []

    def __len__(self) -> int:
        return len(self._positions)

    def clear(self) -> None:
        self._positions.clear()
        self._headings.clear()

    def add(self, site_in_map: np.ndarray) -> None:
        t = np.asarray(site_in_map, float)
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            raise InsertionError('the site pose must be a finite 4x4 matrix')
        self._positions.append(t[:3, 3].copy())
        self._headings.append(math.atan2(t[1, 0], t[0, 0]))

    @property
    def position(self) -> np.ndarray:
        if not self._positions:
            raise InsertionError('the site has not been seen')
        return np.mean(self._positions, axis=0)

    @property
    def heading(self) -> float:
        """The site's x axis heading in the map (rad)."""
        if not self._headings:
            raise InsertionError('the site has not been seen')
        return math.atan2(float(np.mean(np.sin(self._headings))),
                          float(np.mean(np.cos(self._headings))))

    @property
    def pose(self) -> np.ndarray:
        """The site frame in the map (4x4, level): the mean position and heading."""
        return homogeneous(rot_z(self.heading), self.position)

    @property
    def normal(self) -> np.ndarray:
        """The marked faces' outward normal in the map (the site's y axis)."""
        h = self.heading
        return np.array([-math.sin(h), math.cos(h), 0.0])

    @property
    def spread_m(self) -> float:
        """The largest distance of a frame's position from the mean (m)."""
        p = self.position
        return float(max(np.linalg.norm(q - p) for q in self._positions))
