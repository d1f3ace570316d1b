"""Shape optimisation on optimistix: Sobolev gradient descent, least-squares fits and surface registration (see DESIGN.md)."""

from ._fits import fit_free_form_deformation as fit_free_form_deformation
from ._fits import fit_morph as fit_morph
from ._registration import register_surface as register_surface
from ._sobolev_descent import SobolevDescent as SobolevDescent
from ._sobolev_descent import SobolevGradientDescent as SobolevGradientDescent

__all__ = ["SobolevDescent", "SobolevGradientDescent", "fit_free_form_deformation", "fit_morph", "register_surface"]
