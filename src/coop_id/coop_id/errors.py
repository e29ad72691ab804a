"""The package's one domain error."""
from __future__ import annotations


class CoopIdError(ValueError):
    """Root of every error a coop_id core raises: bad model, estimator, excitation or bag input."""
