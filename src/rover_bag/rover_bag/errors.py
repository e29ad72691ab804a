"""The package's one domain error."""
from __future__ import annotations


class BagError(Exception):
    """Root of every error a rover_bag core raises about a bag, its types or its remapping."""
