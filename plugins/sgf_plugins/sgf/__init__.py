"""Salient ground features: detection (eq. 5-8), polar description (eq. 9) and online grouping (eq. 10)."""
