"""Observers that draw a run: the SGF figures (paper Fig. 4 and 5) and the Rerun recording."""
