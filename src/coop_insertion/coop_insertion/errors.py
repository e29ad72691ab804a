class InsertionError(ValueError):
    """Bad input to a coop_insertion core: shape, non-finite value or degenerate geometry."""
