"""Shape optimisation on optimistix: Sobolev gradient descent (see DESIGN.md)."""

from ._sobolev_descent import SobolevDescent as SobolevDescent
from ._sobolev_descent import SobolevGradientDescent as SobolevGradientDescent

__all__ = ["SobolevDescent", "SobolevGradientDescent"]
