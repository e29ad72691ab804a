"""Bring-up of the cooperative rover graph: launch files and their parameter files."""
