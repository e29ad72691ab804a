"""The package's one domain error."""
from __future__ import annotations


class ViewplanError(Exception):
    """Root of every error a coop_viewplan core raises (each also keeps its builtin base)."""
