"""The package's one domain error."""
from __future__ import annotations


class BraidError(ValueError):
    """Bad input or settings for a coop_braid core: a stage geometry that cannot be assembled,
    a leg state out of range, a pose of the wrong shape, an option out of range, or a search
    asked for on a chain too long for it."""
