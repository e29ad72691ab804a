"""The package's one domain error."""
from __future__ import annotations


class MappingError(Exception):
    """Root of every error a coop_mapping core raises (each also keeps its builtin base)."""
