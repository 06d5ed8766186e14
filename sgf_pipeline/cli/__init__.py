"""Console scripts (Hydra apps)."""
