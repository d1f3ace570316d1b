"""geomjax: differentiable geometry operators for JAX.

Every op validates its inputs, then runs either its pure-JAX implementation (the specification)
or a Warp kernel from ``warp_ffi``; see each op's docstring for shapes, errors and backends.
"""

from .deform.displace import displace_points as displace_points
from .deform.ffd import free_form_deform_points as free_form_deform_points
from .deform.morph import morph_points as morph_points
from .deform.rbf import ThinPlateSplineFit as ThinPlateSplineFit
from .deform.rbf import radial_basis_function_deform_points as radial_basis_function_deform_points

__version__ = "0.1.0"
