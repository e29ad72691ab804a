"""The package's one domain error."""
from __future__ import annotations


class MappingError(Exception):
    """Root of every error a coop_mapping core raises (each also keeps its builtin base)."""


class OptionError(MappingError, ValueError):
    """An option a core cannot take: a mode that is not one of its choices (the message names
    them), or a setting out of its range."""
