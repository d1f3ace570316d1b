"""Surface remeshing: integration-mass-weighted centroidal clustering."""
