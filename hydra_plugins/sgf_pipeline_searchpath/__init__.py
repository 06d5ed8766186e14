"""Hydra search-path plugin: config folders contributed by sgf-pipeline plugin packages."""
