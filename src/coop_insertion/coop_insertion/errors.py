"""The package's one domain error."""
from __future__ import annotations


class InsertionError(ValueError):
    """Bad input or settings for a coop_insertion core (image, camera, options, frames)."""
