"""The package's one domain error."""
from __future__ import annotations


class CoopCommonError(ValueError):
    """Root of every error a coop_common module raises: an unreachable pose, a bad truth file."""
