"""Point deformations: one public op per module."""
