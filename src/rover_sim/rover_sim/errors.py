"""The package's one domain error."""
from __future__ import annotations


class SimError(ValueError):
    """Root of every error a rover_sim core raises: a config, world or trajectory it cannot use."""
