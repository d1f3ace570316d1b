"""Closest points on a triangle surface for the eager host-side algorithms (remeshing, sampling).

Shared by the remesher and the Poisson sampler's relaxation, so neither package imports the
other.
"""

from __future__ import annotations

import jax
import numpy as np

from ._geometry import closest_point_on_triangle

__all__ = ["SurfaceProjector"]


class SurfaceProjector:
    """Closest points on a triangle surface: ``targets (K, 3)`` -> positions, faces, weights.

    The nearest face comes from a Warp search tree (``backend="warp"``, built once per projector) or a
    brute-force JAX search (``"jax"``); the point on it from :func:`closest_point_on_triangle`.
    Results are host NumPy arrays in the dtype of ``vertices``. ``op_name`` names the op in
    the ``ValueError`` for vertices beyond the float32 range of Warp's tree.
    """

    def __init__(self, vertices: jax.Array, faces: np.ndarray, backend: str, op_name: str):
        self.device = next(iter(vertices.devices()))
        self.vertices = vertices
        self.faces = jax.device_put(faces.astype(np.int32), self.device)
        self.tree = None
        if backend == "warp":
            from .query.bvh import closest_face_tree

            # The search tree alone: a full build_bvh would also build a Warp mesh for rays.
            self.tree = closest_face_tree(op_name, vertices, faces)

    def __call__(self, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        points = jax.device_put(targets.astype(self.vertices.dtype), self.device)
        if self.tree is not None:
            out = _project_with_tree(self.tree, self.vertices, self.faces, points)
        else:
            out = _project_brute_force(self.vertices, self.faces, points)
        positions, faces, barycentric = out
        return np.asarray(positions), np.asarray(faces), np.asarray(barycentric)


@jax.jit
def _project_with_tree(tree, vertices, faces, points):
    from .query.bvh import search_closest_faces

    face = search_closest_faces(tree, vertices, faces, points)
    corners = vertices[faces[face]]
    position, weights = closest_point_on_triangle(points, corners[:, 0], corners[:, 1], corners[:, 2])
    return position, face, weights


@jax.jit
def _project_brute_force(vertices, faces, points):
    from .query.bvh import closest_faces_brute_force

    face = closest_faces_brute_force(points, vertices, faces)[0]
    corners = vertices[faces[face]]
    position, weights = closest_point_on_triangle(points, corners[:, 0], corners[:, 1], corners[:, 2])
    return position, face, weights
