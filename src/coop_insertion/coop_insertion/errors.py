"""The package's one domain error."""
from __future__ import annotations


class InsertionError(ValueError):
    """Bad input or settings for a coop_insertion core: an image, camera, option, frame or wrench
    of the wrong shape, a non-finite value, or degenerate geometry."""
