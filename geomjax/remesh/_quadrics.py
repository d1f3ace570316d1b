"""Plane quadrics of surface clusters: where the remesher puts a cluster's vertex and how it may move.

Host NumPy, shared by both backends of :func:`geomjax.remeshing`. A cluster's centroid lies
inside the surface's curvature, and its closest surface point falls short of a tip or a sharp
edge, which the remesh then cuts off; a relaxation that moves vertices in the tangent plane
slides them off creases. The quadric of a cluster's triangle planes knows both: its strong
eigendirections are the directions in which the surface bends within the cluster (one for a
flat patch, two along a crease, three at a corner or tip).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .._dispatch import warp_available
from ._triangulation import row_dot

__all__ = ["ClusterQuadrics", "face_plane_terms", "vertex_plane_terms"]

# A direction counts as constrained when its eigenvalue is at least this fraction of the largest.
# Placement uses the lower threshold (it reaches for tips and creases), relaxation the higher one
# (it keeps gently curved patches free to move in their tangent plane).
PLACEMENT_THRESHOLD = 0.01
MOVEMENT_THRESHOLD = 0.03
# The 3x3 symmetric quadric's six entries, as index pairs.
_ROWS, _COLUMNS = np.triu_indices(3)


class ClusterQuadrics(NamedTuple):
    """Per cluster: ``Q = sum a n n^T`` and ``b = sum a n (n . p)`` over its triangles' planes.

    ``|x^T Q x - 2 b . x + c|`` is the area-weighted sum of squared distances from ``x`` to the
    planes (normal ``n``, point ``p``, area ``a``); each triangle's area is split over its
    corners' clusters.
    """

    quadric: np.ndarray  # (K, 3, 3) float64
    rhs: np.ndarray  # (K, 3) float64
    weights: np.ndarray  # (K, 3) eigenvalues of Q, ascending
    basis: np.ndarray  # (K, 3, 3) the eigenvectors, as columns
    normals: np.ndarray  # (K, 3) sum a n: the cluster's mean normal times its area

    @classmethod
    def of(cls, vertex_terms: np.ndarray, labels: np.ndarray, num: int) -> ClusterQuadrics:
        """From the vertices' plane terms (:func:`vertex_plane_terms`) and their ``labels``
        ``(V,)`` in ``[0, num)``."""
        # Per cluster, the sum over its vertices: over its patch, each face counted once per
        # corner in the cluster.
        labels = labels.astype(np.intp, copy=False)  # once, not in each bincount
        sums = np.stack([np.bincount(labels, weights=row, minlength=num) for row in vertex_terms], axis=1)
        quadric = np.zeros((num, 3, 3))
        quadric[:, _ROWS, _COLUMNS] = quadric[:, _COLUMNS, _ROWS] = sums[:, : _ROWS.size]
        rhs, normals = sums[:, _ROWS.size : _ROWS.size + 3], sums[:, _ROWS.size + 3 :]
        return cls(quadric, rhs, *np.linalg.eigh(quadric), normals)

    def snap(self, start: np.ndarray, limit: float) -> np.ndarray:
        """``(K, 3)``: from ``start``, each cluster's least-squares point of its planes.

        The step is taken in the eigenbasis of ``Q``, along the directions whose eigenvalue is
        at least ``PLACEMENT_THRESHOLD`` times the largest (a flat cluster moves along its
        normal only, a crease's across the crease, a tip's onto it); a step longer than
        ``limit`` (nearly parallel planes, an ill-determined point) is not taken.
        """
        weights, basis = self.weights, self.basis
        strong = weights > PLACEMENT_THRESHOLD * weights[:, -1:]
        inverse = np.where(strong, 1.0 / np.where(strong, weights, 1.0), 0.0)
        start = start.astype(np.float64)
        residual = np.einsum("kji,kj->ki", basis, self.rhs - np.einsum("kij,kj->ki", self.quadric, start))
        step = np.einsum("kij,kj->ki", basis, inverse * residual)
        step[np.linalg.norm(step, axis=1) > limit] = 0.0
        return start + step

    def free_moves(self, moves: np.ndarray, clusters: np.ndarray | None = None) -> np.ndarray:
        """``moves (M, 3)`` of ``clusters (M,)`` (default: all ``K``, in order) restricted to
        each cluster's weak eigendirections (eigenvalue below ``MOVEMENT_THRESHOLD`` times the
        largest): in the plane of a flat cluster, along a crease, not at all at a corner or tip."""
        weights, basis = (self.weights, self.basis) if clusters is None else (self.weights[clusters], self.basis[clusters])
        free = weights < MOVEMENT_THRESHOLD * weights[:, -1:]
        return np.einsum("kij,kj->ki", basis, free * np.einsum("kji,kj->ki", basis, moves))

    def crease_strength(self) -> np.ndarray:
        """``(K,)`` second eigenvalue over the largest: 0 on a flat cluster, up to 1 at a corner."""
        return self.weights[:, 1] / np.maximum(self.weights[:, 2], np.finfo(np.float64).tiny)


def vertex_plane_terms(faces: np.ndarray, first_corners: np.ndarray, doubled_normals: np.ndarray, face_area: np.ndarray, num_vertices: int) -> np.ndarray:
    """``(12, V)`` float64: per vertex, the :func:`face_plane_terms` of its faces ``(F, 3)``,
    summed once per corner. They do not depend on the clusters: the remesher computes them on
    its background thread during the Lloyd iterations; with warp-lang in a kernel outside the
    GIL (``warp_ffi.remesh.vertex_plane_terms``, the same bits: the same roundings, in the
    same order), so that they hold the main thread up as little as possible."""
    if warp_available():
        from warp_ffi.remesh import vertex_plane_terms as kernel

        return kernel(faces, first_corners, doubled_normals, face_area, num_vertices)
    terms = face_plane_terms(first_corners, doubled_normals, face_area)
    corners = faces.reshape(-1)
    return np.stack([np.bincount(corners, weights=np.repeat(terms[:, j], 3), minlength=num_vertices) for j in range(terms.shape[1])])


def face_plane_terms(first_corners: np.ndarray, doubled_normals: np.ndarray, face_area: np.ndarray) -> np.ndarray:
    """``(F, 12)`` float64: per face, a third of its area times its plane's six quadric entries
    (``n n^T``, upper triangle), ``(n . p) n`` and ``n``, from the faces' first corners ``p``,
    ``(b - a) x (c - a)`` and areas (float64)."""
    normal = doubled_normals / np.where(face_area > 0, 2 * face_area, 1.0)[:, None]
    third = face_area / 3
    offset = row_dot(normal, first_corners)
    # Filled column by column (stacking the columns costs several times more).
    terms = np.empty((face_area.size, _ROWS.size + 6))
    for column, (i, j) in enumerate(zip(_ROWS, _COLUMNS)):
        np.multiply(third * normal[:, i], normal[:, j], out=terms[:, column])
    for k in range(3):
        np.multiply(third * offset, normal[:, k], out=terms[:, _ROWS.size + k])
        np.multiply(third, normal[:, k], out=terms[:, _ROWS.size + 3 + k])
    return terms
