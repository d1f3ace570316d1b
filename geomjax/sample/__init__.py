"""Surface sampling: Poisson-disk samples, farthest-point sampling, sample and mesh quality measures."""
