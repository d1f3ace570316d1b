"""Warp triangle-mesh searches for JAX: the names geomjax imports, in one place.

* Preparing a mesh (host side, :mod:`warp_ffi.host`): :func:`closest_tree` (the oriented-box
  tree of the closest-point searches, about 3x faster than Warp's axis-aligned BVH on curved
  surfaces), :func:`build_mesh` (a float32 ``wp.Mesh``, for rays and winding numbers),
  :func:`mesh_handle` (its id as JAX ``mesh_words``, keeping it alive) and :func:`refit_mesh`;
  :func:`tree_shapes` gives the shapes of a tree's arrays (for checking a tree handed back).
  Kernels read a handle with the Warp function :func:`mesh_id`.
* Searching (JAX functions): :func:`point_faces` (:mod:`warp_ffi.closest`: closest face, sign
  and distance) and :func:`ray_hits` (:mod:`warp_ffi.rays`: first hits). Both also accept the
  float32 vertices and flat indices instead of a prepared structure and then build it inside
  the FFI call, so the whole query traces under ``jit``.
"""

from ._grid import DEAD_MESH_FACE as DEAD_MESH_FACE
from ._grid import build_mesh as build_mesh
from ._grid import mesh_id as mesh_id
from ._obb_tree import tree_shapes as tree_shapes
from .closest import SIGN_MODES as SIGN_MODES
from .closest import point_faces as point_faces
from .host import closest_tree as closest_tree
from .host import mesh_handle as mesh_handle
from .host import refit_mesh as refit_mesh
from .rays import ray_hits as ray_hits

__all__ = ["DEAD_MESH_FACE", "build_mesh", "closest_tree", "mesh_handle", "mesh_id", "refit_mesh", "point_faces", "ray_hits", "SIGN_MODES", "tree_shapes"]
