"""Cooperative insertion (thesis ch. 5, app. A): marker identification, frames, force-feedback
finish."""
