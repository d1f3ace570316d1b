"""Closest points on a cluster's own patch of the source surface (remeshing's steps 4 and 6).

A cluster's *patch* is every source triangle with a corner in the cluster: the cluster's region
of the surface and the ring of triangles around it. The remesher puts each cluster's vertex at
the closest point of its patch rather than of the whole surface. That keeps the vertex on its
own sheet where the surface passes close to itself (a thin part, a narrow gap: the nearest
point of the whole surface may lie on the other side), and it needs no search tree: a patch has
about ``1.5 F / K`` triangles, so one projection of all ``K`` vertices costs about ``1.5 F``
point-triangle distances, where building a tree over the ``F`` triangles costs more than all
the projections of a remesh.

The nearest candidate comes from a Warp kernel (``warp_ffi.remesh.patch_closest_faces``, which
skips the faces whose bounding sphere rules them out) or a JAX twin over the flattened (point,
candidate) pairs; both measure distances in the working dtype and take the lowest face index
among the faces within ``PATCH_TIE_EPSILONS`` epsilons of the coordinates' magnitude (``M``, the
largest absolute vertex coordinate, plus the point's) of the nearest distance: an exact tie in
exact arithmetic (a point on the mirror plane of two faces, common on regular meshes) then goes
the same way on both backends, whose distance codes round differently. The point and its
barycentric weights on the chosen triangle come from
:func:`geomjax._geometry.closest_point_on_triangle` on both backends.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .._geometry import closest_point_on_triangle
from ._surface_clusters import ClusterPatches
from ._triangulation import column_max, column_min

__all__ = ["PatchProjector"]

# Padded sizes are powers of two from these: the JAX programs compile once per bucket of sizes.
MIN_PAIRS = 1024
MIN_POINTS = 64
# Tie tolerance of the nearest face, in epsilons of the working dtype times the coordinates'
# magnitude: well above the rounding of a point-triangle distance (a few epsilons of it).
PATCH_TIE_EPSILONS = 64


class PatchProjector:
    """Closest points on cluster patches: ``targets (Q, 3)`` of clusters ``(Q,)`` -> positions, faces, weights.

    ``vertices`` ``(V, 3)`` is the source surface (a JAX array, in the frame of the targets),
    ``faces`` ``(F, 3)`` its validated host indices, ``patches`` its clusters' patches;
    ``backend`` is ``"warp"`` or ``"jax"``. Calls return host NumPy arrays: positions
    ``(Q, 3)`` in the dtype of ``vertices``, int32 source faces ``(Q,)`` and barycentric weights
    ``(Q, 3)``.
    """

    def __init__(self, vertices: jax.Array, faces: np.ndarray, patches: ClusterPatches, backend: str):
        self.device = next(iter(vertices.devices()))
        self.vertices = vertices
        self.host_vertices = np.asarray(vertices)
        # Host faces go into the JAX programs as they are (see __call__): a device_put of them
        # here cost more than their transfers in all the calls of a remesh.
        self.host_faces = np.ascontiguousarray(faces, np.int32)
        self.offsets, self.candidates = patches.offsets, patches.faces
        magnitude = float(np.max(np.maximum(-column_min(self.host_vertices), column_max(self.host_vertices))))
        self.tie = (PATCH_TIE_EPSILONS * float(np.finfo(self.host_vertices.dtype).eps), magnitude)
        self.search = None
        if backend == "warp":
            import warp

            from warp_ffi.remesh import PatchSearch

            device = str(warp.device_from_jax(self.device))
            self.search = PatchSearch(self.host_vertices, self.host_faces, self.offsets, self.candidates, device, self.tie)

    def __call__(self, targets: np.ndarray, clusters: np.ndarray | None = None, hints: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``hints`` ``(Q,)``: optionally a face of each target's patch near it (the source face
        of a point that moved a little); the Warp search starts from it, the result is the same."""
        targets = np.ascontiguousarray(targets, self.host_vertices.dtype)
        count = targets.shape[0]
        clusters = np.arange(count, dtype=np.int32) if clusters is None else np.asarray(clusters, np.int32)
        if self.search is not None:
            from warp_ffi.remesh import patch_closest_faces

            faces = patch_closest_faces(self.search, targets, clusters, hints)
        else:
            faces = self._closest_faces_jax(targets, clusters)
        size = _bucket(count, MIN_POINTS)
        # Host arrays go in as they are: jit puts them on the device of the vertices (committed
        # there), at a third of the cost of explicit device_put calls.
        positions, weights = _closest_on_faces(self.vertices, self.host_faces, _pad(targets, size), _pad(faces, size))
        return np.asarray(positions)[:count], faces, np.asarray(weights)[:count]

    def _closest_faces_jax(self, targets: np.ndarray, clusters: np.ndarray) -> np.ndarray:
        """The JAX twin of the Warp kernel: every (point, candidate) pair at once."""
        count = targets.shape[0]
        starts, stops = self.offsets[clusters], self.offsets[clusters + 1]
        sizes = stops - starts
        pair_point = np.repeat(np.arange(count, dtype=np.int32), sizes)
        first = np.cumsum(sizes) - sizes
        pair_face = self.candidates[starts[pair_point] + np.arange(pair_point.size) - first[pair_point]]
        # Padding: extra points (copies of the first) and extra pairs on the last, unused point.
        num_points = _bucket(count + 1, MIN_POINTS)
        num_pairs = _bucket(pair_point.size, MIN_PAIRS)
        pair_point = np.concatenate([pair_point, np.full(num_pairs - pair_point.size, num_points - 1, np.int32)])
        pair_face = _pad(pair_face, num_pairs)
        tie = np.asarray(self.tie, targets.dtype)
        found = _nearest_pair_faces(self.vertices, self.host_faces, _pad(targets, num_points), pair_point, pair_face, tie)
        return np.asarray(found)[:count]


def _bucket(size: int, minimum: int) -> int:
    return max(minimum, 1 << max(size - 1, 0).bit_length())


def _pad(rows: np.ndarray, size: int) -> np.ndarray:
    """``rows`` followed by copies of its first row up to ``size`` rows."""
    return np.concatenate([rows, np.broadcast_to(rows[:1], (size - rows.shape[0], *rows.shape[1:]))])


@jax.jit
def _nearest_pair_faces(vertices, faces, points, pair_point, pair_face, tie):
    """The nearest candidate face of each point (ties, within ``tie = (relative, magnitude)``:
    the lowest face index), as the Warp kernel decides."""
    num_points = points.shape[0]
    corners = vertices[faces[pair_face]]
    at = points[pair_point]
    closest, _ = closest_point_on_triangle(at, corners[:, 0], corners[:, 1], corners[:, 2])
    offset = at - closest
    distance2 = jnp.sum(offset * offset, axis=-1)
    nearest2 = jax.ops.segment_min(distance2, pair_point, num_segments=num_points)
    limit = jnp.sqrt(nearest2) + tie[0] * (tie[1] + jnp.max(jnp.abs(points), axis=-1))
    tied = jnp.where(distance2 <= jnp.square(limit)[pair_point], pair_face, faces.shape[0])
    return jax.ops.segment_min(tied, pair_point, num_segments=num_points)


@jax.jit
def _closest_on_faces(vertices, faces, points, face):
    corners = vertices[faces[face]]
    return closest_point_on_triangle(points, corners[:, 0], corners[:, 1], corners[:, 2])
