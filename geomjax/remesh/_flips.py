"""Edge flips of the remesher: Delaunay flips on the surface, and fold flips that bring a pair of
triangles closer to the surface.

Host NumPy, shared by both backends of :func:`geomjax.remeshing`. A flip replaces the diagonal
``uv`` of two consistently oriented triangles ``(u, v, p)`` and ``(v, u, q)`` by ``pq``; every
flip pass follows the same rules (:class:`_Pairs`): never onto an existing edge, never leaving a
vertex with fewer than three edges, never folding the pair, and flips of one round share no
triangle.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .._dispatch import warp_available
from ._triangulation import corner_angles_at, half_edges, min_angles, rotated_corners, row_cross, row_dot, row_norm, unit_rows

__all__ = ["delaunay_flips", "fold_flips"]

FLIP_ROUNDS = 32  # rounds of parallel Delaunay edge flips per flip pass
FLIP_TOLERANCE = 1e-6  # radians: opposite angles must exceed pi by this much (co-circular quads stay)
# Edges between triangles whose normals differ by more than this are creases of the surface:
# flipping them would cut the crease, so they stay (a flat pair flips at any shape).
FLIP_MAX_DIHEDRAL_DEGREES = 20.0
# A pair is flat when its new diagonal passes within this fraction of its length from the old
# one: tan(dihedral / 2) / 2 across a symmetric crease of that dihedral angle.
FLAT_FACTOR = 0.5 * math.tan(math.radians(FLIP_MAX_DIHEDRAL_DEGREES) / 2)

# Fold flips: of the pairs with the largest estimated heights over the surface, this many are
# measured; one is flipped where its largest measured distance drops by FOLD_GAIN and both new
# triangles have no angle below FOLD_MIN_ANGLE_DEGREES.
FOLD_CHECKED = 16
FOLD_GAIN = 0.1
FOLD_MIN_ANGLE_DEGREES = 20.0


def delaunay_flips(positions: np.ndarray, triangles: np.ndarray, rounds: int = FLIP_ROUNDS) -> np.ndarray:
    """Flip interior edges whose opposite angles sum to more than pi (Delaunay on the surface).

    Only edges shared by exactly two consistently oriented triangles are flipped, never onto an
    existing edge, never leaving a vertex with fewer than three edges, and never folding the
    pair (both new triangles must face like the old ones). Each round flips an independent set
    of edges (no two share a triangle), the most violating first, for at most ``rounds`` rounds.
    """
    x = positions.astype(np.float64)
    triangles = triangles.copy()
    stride = np.int64(positions.shape[0])
    for _ in range(rounds):
        pairs = _Pairs.of(triangles, stride)
        u, v = np.tile(pairs.u, 2), np.tile(pairs.v, 2)
        opposite = corner_angles_at(x, np.concatenate([pairs.p, pairs.q]), u, v)
        excess = opposite[: pairs.p.size] + opposite[pairs.p.size :] - np.pi
        pairs = pairs.subset(excess > FLIP_TOLERANCE)
        excess = excess[excess > FLIP_TOLERANCE]
        flat, flippable = pairs.rules(x, stride)
        candidates = np.flatnonzero(flippable & flat)
        if candidates.size == 0:
            break
        pairs.flip(triangles, candidates, -excess[candidates], stride)
    return triangles


def fold_flips(positions: np.ndarray, triangles: np.ndarray, normals: np.ndarray, surface_distance) -> np.ndarray:
    """Flip the interior edges where the other diagonal lies closer to the surface.

    Delaunay flips choose the diagonal of a pair of triangles by its angles alone; on a curved
    surface (a saddle, a ridge at an angle to the triangles) the other diagonal can bend with the
    surface and bring the pair several times closer to it. With surface normals ``n`` at the
    vertices (``normals`` ``(V, 3)``, any length), the height of the surface over a triangle is
    estimated by the quadratic through its corners whose height over an edge ``ab`` peaks at
    the sagitta ``(b - a) . (n_b - n_a) / 8`` (exact to second order on a circle): the largest
    of the three and 4/9 of their sum (at the centroid). The ``FOLD_CHECKED`` pairs with the
    largest estimated heights whose other diagonal is estimated ``FOLD_GAIN`` lower are then
    measured: ``surface_distance(points (M, 3), vertices (M,)) -> (M,)`` is the distance from
    each point to the surface near a vertex, taken at the triangles' centroids and the
    diagonals' midpoints, the smallest over the pair's four corners. A pair whose measured
    largest distance drops by ``FOLD_GAIN`` is flipped if both new triangles keep every angle
    above ``FOLD_MIN_ANGLE_DEGREES``, under the rules of :func:`delaunay_flips` (independent
    flips, the largest drop first); one round.
    """
    x = positions.astype(np.float64)
    unit = unit_rows(normals.astype(np.float64))
    triangles = triangles.copy()
    stride = np.int64(positions.shape[0])
    pairs = _Pairs.of(triangles, stride)
    u, v, p, q = pairs.u, pairs.v, pairs.p, pairs.q
    if warp_available():
        from warp_ffi.remesh import fold_heights

        old, new = fold_heights(x, unit, triangles, pairs.first, pairs.second, u, v, p, q)
    else:
        old, new = _fold_heights(x, unit, triangles, pairs)
    promising = np.flatnonzero(new < (1 - FOLD_GAIN) * old)
    promising = promising[np.argsort(-old[promising], kind="stable")[:FOLD_CHECKED]]
    u, v, p, q = u[promising], v[promising], p[promising], q[promising]
    fair = np.minimum(min_angles(x, np.stack([u, q, p], 1)), min_angles(x, np.stack([q, v, p], 1))) >= FOLD_MIN_ANGLE_DEGREES
    keep = fair & pairs.subset(promising).rules(x, stride)[1]
    promising, u, v, p, q = promising[keep], u[keep], v[keep], p[keep], q[keep]
    if promising.size == 0:
        return triangles
    # Old pair: its two centroids and the midpoint of uv; new pair: the same with pq.
    samples = np.stack(
        [(x[u] + x[v] + x[p]) / 3, (x[u] + x[v] + x[q]) / 3, (x[u] + x[v]) / 2, (x[u] + x[q] + x[p]) / 3, (x[q] + x[v] + x[p]) / 3, (x[p] + x[q]) / 2], axis=1
    )
    corners = np.stack([u, v, p, q], axis=1)
    distance = surface_distance(np.repeat(samples.reshape(-1, 3), 4, axis=0), np.repeat(corners, samples.shape[1], axis=0).reshape(-1))
    distance = distance.reshape(promising.size, samples.shape[1], 4).min(axis=2)
    measured_old, measured_new = distance[:, :3].max(axis=1), distance[:, 3:].max(axis=1)
    better = measured_new < (1 - FOLD_GAIN) * measured_old
    if np.any(better):
        pairs.flip(triangles, promising[better], measured_new[better] - measured_old[better], stride)
    return triangles


def _fold_heights(x: np.ndarray, unit: np.ndarray, triangles: np.ndarray, pairs: _Pairs) -> tuple[np.ndarray, np.ndarray]:
    """Per pair, the estimated height of the surface over its two triangles, now and flipped
    (see :func:`fold_flips`; the NumPy twin of ``warp_ffi.remesh.fold_heights``)."""
    # Signed sagittas of the half-edges, as (F, 3) in corner order (edge k runs from corner k).
    a, b = triangles.reshape(-1), rotated_corners(triangles, 1).reshape(-1)
    sagitta = (row_dot(x[b] - x[a], unit[b] - unit[a]) / 8).reshape(-1, 3)

    def height(ab, bc, ca):
        return np.maximum(np.maximum(np.abs(ab), np.abs(bc)), np.maximum(np.abs(ca), 4 / 9 * np.abs(ab + bc + ca)))

    # The pair's outer edges keep their sagittas: v->p and p->u follow u->v in the first
    # triangle, u->q and q->v follow v->u in the second.
    vp, pu = (sagitta.reshape(-1)[_next_half_edge(pairs.first, k)] for k in (1, 2))
    uq, qv = (sagitta.reshape(-1)[_next_half_edge(pairs.second, k)] for k in (1, 2))
    pq = row_dot(x[pairs.q] - x[pairs.p], unit[pairs.q] - unit[pairs.p]) / 8
    old = np.maximum(height(*sagitta[pairs.first // 3].T), height(*sagitta[pairs.second // 3].T))
    new = np.maximum(height(uq, pq, pu), height(qv, vp, pq))  # sagittas are symmetric in their ends
    return old, new


def _next_half_edge(half_edge: np.ndarray, step: int) -> np.ndarray:
    return half_edge // 3 * 3 + (half_edge % 3 + step) % 3


class _Pairs(NamedTuple):
    """Interior edges shared by exactly two consistently oriented triangles: half-edge ``first``
    ``u -> v`` (third corner ``p``) and its twin ``second`` ``v -> u`` (third corner ``q``),
    half-edge ``h`` being edge ``h % 3`` of triangle ``h // 3``; ``edges``: every undirected
    edge key of the triangles, sorted."""

    first: np.ndarray
    second: np.ndarray
    u: np.ndarray
    v: np.ndarray
    p: np.ndarray
    q: np.ndarray
    edges: np.ndarray

    @classmethod
    def of(cls, triangles: np.ndarray, stride: np.int64) -> _Pairs:
        tail, head, key = half_edges(triangles, int(stride))
        opposite = rotated_corners(triangles, 2).reshape(-1)
        order = np.argsort(key, kind="stable")
        sorted_key = key[order]
        starts = np.flatnonzero(np.concatenate([[True], sorted_key[1:] != sorted_key[:-1]]))
        counts = np.diff(np.append(starts, key.size))
        paired = starts[counts == 2]
        first, second = order[paired], order[paired + 1]
        consistent = (tail[first] == head[second]) & (head[first] == tail[second])
        first, second = first[consistent], second[consistent]
        return cls(first, second, tail[first], head[first], opposite[first], opposite[second], sorted_key[starts])

    def subset(self, rows: np.ndarray) -> _Pairs:
        return _Pairs(self.first[rows], self.second[rows], self.u[rows], self.v[rows], self.p[rows], self.q[rows], self.edges)

    def rules(self, x: np.ndarray, stride: np.int64) -> tuple[np.ndarray, np.ndarray]:
        """Per pair, whether it is *flat* (the distance between the new diagonal ``pq`` and
        ``uv``, relative to ``|pq|``, is at most ``FLAT_FACTOR``: that ratio is 0 for a flat
        pair or a sliver, ``tan(dihedral / 2) / 2`` across a symmetric crease) and *flippable*
        (``pq`` is not an edge already, ``u`` and ``v`` keep three edges or more, and both new
        triangles face like the old pair). With warp-lang from a kernel
        (``warp_ffi.remesh.flip_rules``, the same answers)."""
        degree = np.bincount(np.concatenate([self.edges // stride, self.edges % stride]), minlength=int(stride))
        if warp_available():
            from warp_ffi.remesh import flip_rules

            return flip_rules(x, self.u, self.v, self.p, self.q, self.edges, degree, FLAT_FACTOR)
        return _flip_rules(x, self.u, self.v, self.p, self.q, self.edges, degree, stride)

    def flip(self, triangles: np.ndarray, candidates: np.ndarray, priority: np.ndarray, stride: np.int64) -> None:
        """Flip, in place, the ``candidates`` (rows) that share no triangle with one of lower
        ``priority`` and create no edge that one of them creates."""
        rank = np.empty(candidates.size, np.int64)
        rank[np.argsort(priority, kind="stable")] = np.arange(candidates.size)
        face_a, face_b = self.first[candidates] // 3, self.second[candidates] // 3
        best = np.full(triangles.shape[0], candidates.size)
        np.minimum.at(best, face_a, rank)
        np.minimum.at(best, face_b, rank)
        chosen = (best[face_a] == rank) & (best[face_b] == rank)
        u, v, p, q = (a[candidates] for a in (self.u, self.v, self.p, self.q))
        new_keys = np.minimum(p, q) * stride + np.maximum(p, q)
        # Two flips of one round must not create the same edge.
        chosen &= _first_occurrence(np.where(chosen, new_keys, -1 - np.arange(candidates.size)))
        triangles[face_a[chosen]] = np.stack([u[chosen], q[chosen], p[chosen]], axis=1)
        triangles[face_b[chosen]] = np.stack([q[chosen], v[chosen], p[chosen]], axis=1)


def _flip_rules(x, u, v, p, q, edges, degree, stride) -> tuple[np.ndarray, np.ndarray]:
    """:meth:`_Pairs.rules` in NumPy (the twin of ``warp_ffi.remesh.flip_rules``)."""
    across = row_cross(x[v] - x[u], x[q] - x[p])
    gap = np.abs(row_dot(x[p] - x[u], across)) / np.maximum(row_norm(across), np.finfo(np.float64).tiny)
    flat = gap <= FLAT_FACTOR * row_norm(x[q] - x[p])
    new_keys = np.minimum(p, q) * stride + np.maximum(p, q)
    existing = edges[np.minimum(np.searchsorted(edges, new_keys), edges.size - 1)] == new_keys
    old_normal = unit_rows(row_cross(x[v] - x[u], x[p] - x[u])) + unit_rows(row_cross(x[u] - x[v], x[q] - x[v]))
    unfolded = (row_dot(row_cross(x[q] - x[u], x[p] - x[u]), old_normal) > 0) & (row_dot(row_cross(x[v] - x[q], x[p] - x[q]), old_normal) > 0)
    return flat, ~existing & (degree[u] > 3) & (degree[v] > 3) & unfolded


def _first_occurrence(values: np.ndarray) -> np.ndarray:
    _, first = np.unique(values, return_index=True)
    mask = np.zeros(values.shape, bool)
    mask[first] = True
    return mask
