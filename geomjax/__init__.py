"""geomjax: differentiable geometry operators for JAX.

Every op validates its inputs, then runs either its pure-JAX implementation (the specification)
or a Warp kernel from ``warp_ffi``; see each op's docstring for shapes, errors and backends.
"""

from ._compilation_cache import enable_compilation_cache as enable_compilation_cache
from ._errors import documented_errors as documented_errors
from .deform.displace import displace_points as displace_points
from .deform.ffd import free_form_deform_points as free_form_deform_points
from .deform.morph import morph_points as morph_points
from .deform.rbf import ThinPlateSplineFit as ThinPlateSplineFit
from .deform.rbf import radial_basis_function_deform_points as radial_basis_function_deform_points
from .deform.shrinkwrap import shrinkwrap_points as shrinkwrap_points
from .deform.sobolev import sobolev_deform_points as sobolev_deform_points
from .energy.bending import surface_bending_energy as surface_bending_energy
from .energy.inversion import simplex_inversion_energy as simplex_inversion_energy
from .energy.measure import simplex_measure_energy as simplex_measure_energy
from .energy.strain import simplex_strain_energy as simplex_strain_energy
from .energy.total_measure import total_measure_energy as total_measure_energy
from .energy.volume import closed_surface_volume_energy as closed_surface_volume_energy
from .mesh import Mesh as Mesh
from .mesh_io import read_mesh as read_mesh
from .mesh_io import write_mesh as write_mesh
from .primitives import icosphere as icosphere
from .primitives import polyline as polyline
from .primitives import rectangle as rectangle
from .primitives import tetrahedralized_box as tetrahedralized_box
from .query.bvh import MeshBVH as MeshBVH
from .query.bvh import build_bvh as build_bvh
from .query.ray import ray_mesh_intersect as ray_mesh_intersect
from .query.sdf import signed_distance_field as signed_distance_field
from .query.voxel import mesh_to_voxel_fraction as mesh_to_voxel_fraction
from .remesh.clustering import RemeshTopologyWarning as RemeshTopologyWarning
from .remesh.clustering import remeshing as remeshing
from .sample.farthest import farthest_point_sampling as farthest_point_sampling
from .sample.poisson import mesh_poisson_disk_sample as mesh_poisson_disk_sample

__version__ = "0.1.0"
