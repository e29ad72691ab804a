"""Shared pieces of the cooperative field robot graph (no algorithm lives here)."""
