"""The package's one domain error."""
from __future__ import annotations


class HardwareError(ValueError):
    """Root of every error a rover_hw core raises: a bad frame or a refused command."""
