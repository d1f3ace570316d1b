"""Clusters as regions of the surface: the remesher's graph Lloyd rounds and tear mending.

Host NumPy and SciPy (``scipy.sparse.csgraph``), shared by both backends of
:func:`geomjax.remeshing`. A cluster is a set of input vertices with one label; the remesh has
a vertex per cluster and a triangle per input triangle whose corners carry three labels. That
triangle set is a closed surface of the input's topology when every cluster is a disk on the
surface and two clusters meet along at most one arc. Euclidean nearest-centroid clusters break
this on real meshes (a cluster takes in vertices across a thin part); the functions here make
each cluster connected on the surface and mend the two remaining defects.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph

from .._dispatch import warp_available
from ._triangulation import first_occurrences, half_edges, relabelled_triangles, row_dot

__all__ = ["ClusterPatches", "MeshEdges", "SeedForest", "VertexMoments", "cluster_means", "connected_clusters", "mend_tears"]


class MeshEdges(NamedTuple):
    """The undirected edges of a triangle mesh, computed once per remesh.

    Attributes:
        graph: ``(V, V)`` symmetric CSR matrix of edge lengths (at least ``tiny``: SciPy reads a
            stored zero as no edge, and duplicated vertices must stay connected).
        boundary: indices of the vertices on an edge of a single triangle.
        euler: Euler characteristic ``V' - E + F`` of the vertices the triangles use.
    """

    graph: sparse.csr_matrix
    boundary: np.ndarray
    euler: int

    @classmethod
    def of(cls, x: np.ndarray, faces: np.ndarray) -> MeshEdges:
        num = x.shape[0]
        # A plain sort of the undirected keys (min * V + max) decodes to the edges: a third of
        # np.unique's time with indices and counts.
        key = np.sort(half_edges(faces, num)[2])
        starts = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
        counts = np.diff(np.append(starts, key.size))
        a, b = np.divmod(key[starts], num)
        # np.take gathers rows several times faster than fancy indexing.
        offset = np.take(x, a, axis=0).astype(np.float64) - np.take(x, b, axis=0)
        length = np.maximum(np.sqrt(row_dot(offset, offset)), np.finfo(np.float64).tiny)
        # The upper triangle, already in CSR order (rows a ascending, columns b within a row),
        # plus its transpose: the symmetric matrix that Dijkstra walks as a directed graph.
        upper = sparse.csr_matrix((length, b, np.searchsorted(a, np.arange(num + 1))), shape=(num, num))
        graph = (upper + upper.T).tocsr()
        single = counts == 1
        boundary = np.unique(np.concatenate([a[single], b[single]]))
        used = np.count_nonzero(np.bincount(faces.reshape(-1), minlength=num))
        return cls(graph, boundary, int(used - starts.size + faces.shape[0]))


class ClusterPatches(NamedTuple):
    """Each cluster's *patch*: the faces with a corner in it, as CSR over the clusters.

    Attributes:
        offsets: ``(K + 1,)`` int32; patch ``k`` is ``faces[offsets[k]:offsets[k + 1]]``.
        faces: int32 face indices, ascending within each patch.
        corners: int32, how many corners of that face are in that cluster (1 to 3). An empty
            cluster (no vertex) gets face 0 with 0 corners, so every patch has a face; its
            vertex is used by no triangle, so where it lands does not matter.
    """

    offsets: np.ndarray
    faces: np.ndarray
    corners: np.ndarray

    @classmethod
    def of(cls, faces: np.ndarray, labels: np.ndarray, num: int) -> ClusterPatches:
        # One entry per face corner at (its cluster, the face): SciPy's conversion to CSR is a
        # counting sort that sums the entries of a face with several corners in one cluster and
        # leaves each row's faces ascending (three times faster than masks and an argsort).
        num_faces = faces.shape[0]
        corner_faces = np.repeat(np.arange(num_faces, dtype=np.int32), 3)
        counts = sparse.csr_matrix((np.ones(3 * num_faces, np.int32), (np.take(labels, faces).reshape(-1), corner_faces)), shape=(num, num_faces))
        offsets, face, corners = (a.astype(np.int32, copy=False) for a in (counts.indptr, counts.indices, counts.data))
        empty = np.flatnonzero(offsets[1:] == offsets[:-1])
        if empty.size:
            face, corners = np.insert(face, offsets[empty], 0), np.insert(corners, offsets[empty], 0)
            offsets[1:] += np.cumsum(offsets[1:] == offsets[:-1], dtype=np.int32)
        return cls(offsets, face, corners)


class SeedForest:
    """The clusters as a shortest-path forest of the mesh's edge graph, kept as their seeds move.

    Each vertex belongs to the seed nearest along the edges, reached from a neighbour of its own
    cluster (so every cluster is connected); a vertex that no seed reaches keeps its label with
    an infinite distance. With warp-lang installed a Warp kernel grows the forest
    (label-correcting shortest paths on a queue of distance buckets, no heap): from nothing the
    first time (60% of SciPy's time on the armadillo), then only where it changes: it clears
    the vertices of the labels whose seed changed and grows them back from their kept
    neighbours and the new seeds, so its cost follows what changes (the graph Lloyd and mending
    rounds move a fifth of the seeds or fewer). Otherwise each assignment is SciPy's
    multi-source Dijkstra. The distances are the
    same either way; between seeds at exactly the same distance each picks one,
    deterministically (SciPy by its heap order, the kernel the lowest label among a changed
    vertex's).

    Attributes:
        labels: ``(V,)`` int32, each vertex's cluster.
        distance: ``(V,)`` float64, its distance from the cluster's seed along the edges.
    """

    def __init__(self, edges: MeshEdges, labels: np.ndarray, num_clusters: int):
        self.graph = edges.graph
        self.labels = labels.astype(np.int32)
        self.distance = np.full(labels.shape[0], np.inf)
        self.parents = np.full(labels.shape[0], -1, np.int32)
        self.seed_of: np.ndarray | None = None  # (K,) the seed of each label, -1 for none
        self.num_clusters = num_clusters
        self._kernel_graph: Any = None  # warp_ffi's EdgeGraph, made on the first assignment

    def assign(self, seeds: np.ndarray, seed_labels: np.ndarray) -> None:
        """Every vertex joins the cluster of the nearest of ``seeds`` (vertex indices, one per
        label in ``seed_labels``)."""
        seed_of = np.full(self.num_clusters, -1, np.int64)
        seed_of[seed_labels] = seeds
        previous, self.seed_of = self.seed_of, seed_of
        if warp_available():
            from warp_ffi.remesh import EdgeGraph, grow_forest

            if self._kernel_graph is None:
                self._kernel_graph = EdgeGraph(self.graph.indptr, self.graph.indices, self.graph.data)
            # A label whose seed changed loses all its vertices: none may keep a current seed's
            # label along a path that no longer is the shortest. The first time, all go.
            cleared = np.arange(self.labels.size) if previous is None else np.flatnonzero((seed_of != previous)[self.labels])
            if grow_forest(self._kernel_graph, self.distance, self.labels, self.parents, cleared, seeds, seed_labels):
                return
        # The graph is symmetric: as a directed graph it needs no symmetrised copy (a quarter faster).
        distance, parents, source = csgraph.dijkstra(self.graph, directed=True, indices=seeds, min_only=True, return_predecessors=True)
        label_at = np.full(self.labels.shape[0], -1, np.int64)
        label_at[seeds] = seed_labels
        self.labels = np.where(source >= 0, label_at[np.maximum(source, 0)], self.labels).astype(np.int32)
        self.distance, self.parents = distance, parents.astype(np.int32)


def connected_clusters(forest: SeedForest, x, moments: VertexMoments, centroids, rounds: int):
    """Lloyd rounds in which each cluster is a region of the surface, not of space.

    Every vertex joins the cluster whose seed (the member closest to its centroid) is nearest
    along the mesh's edges (multi-source Dijkstra), so each cluster is connected through its own
    vertices; centroids then move to their clusters' mass-weighted means, ``rounds`` times, and
    a last assignment gives the labels (in ``forest``, with each vertex's distance from its
    cluster's seed along the edges). Returns the centroids.
    """
    for round_index in range(rounds + 1):
        seeds = _cluster_seeds(x, centroids, forest.labels)
        forest.assign(seeds, forest.labels[seeds])
        if round_index < rounds:
            centroids = cluster_means(moments, forest.labels, centroids)
    return centroids


def mend_tears(edges: MeshEdges, forest: SeedForest, x, corners, moments: VertexMoments, centroids, max_rounds: int):
    """Reassign clusters until their relabelled triangles have no fin and no pinch.

    * A *fin*: a cluster C squeezed between two others A and B (a thin strip across their
      border) meets them at two junctions of opposite orientation. One is dropped as a
      duplicate; the other is a triangle whose two edges at C have no second triangle, away
      from any boundary of the input. C gives up its seed (its vertices join the nearest
      remaining seeds), so that A and B meet along one arc.
    * A *pinch*: two clusters meeting along two separate arcs (both wrap around a thin part),
      so that their edge has more than two triangles. Both are split by a new seed at their
      vertex farthest from their seed (the forest's distance, from the last assignment); to
      keep the number of clusters, the smallest clusters not involved give up their seeds and
      labels.

    At most ``max_rounds`` rounds; fins go first (a fin also crowds an edge). ``corners``:
    the input triangles as :func:`relabelled_triangles` takes them. Updates ``forest`` and
    returns the centroids and the relabelled triangles of its final labels; what is left shows
    in the remesh's topology check.
    """
    num = centroids.shape[0]
    for _ in range(max_rounds):
        labels = forest.labels
        triangles = relabelled_triangles(labels, corners)
        if triangles.shape[0] == 0:
            return centroids, triangles
        tail, head, key = half_edges(triangles, num)
        first, counts = first_occurrences(key)
        on_boundary = np.zeros(num, bool)
        on_boundary[labels[edges.boundary]] = True
        single = first[counts == 1]
        torn = single[~(on_boundary[tail[single]] & on_boundary[head[single]])]
        fins = np.flatnonzero(np.bincount(np.concatenate([tail[torn], head[torn]]), minlength=num) >= 2)
        crowded = first[counts > 2]
        if fins.size == 0 and crowded.size == 0:
            return centroids, triangles
        seeds = _cluster_seeds(x, centroids, labels)
        seed_of = np.full(num, -1, np.int64)
        seed_of[labels[seeds]] = seeds
        seed_of[fins] = -1
        if fins.size == 0:
            sizes = np.bincount(labels, weights=moments.mass, minlength=num)
            pairs = np.stack([tail[crowded], head[crowded]], axis=1)
            involved = np.zeros(num, bool)
            involved[pairs.reshape(-1)] = True
            split = np.unique(pairs)
            by_size = np.argsort(sizes, kind="stable")
            donors = by_size[(seed_of[by_size] >= 0) & ~involved[by_size]]
            distance = forest.distance
            for cluster, donor in zip(split, donors):
                members = np.flatnonzero(labels == cluster)
                reach = np.where(np.isfinite(distance[members]), distance[members], -1.0)
                seed_of[donor] = members[np.argmax(reach)]
        live = np.flatnonzero(seed_of >= 0)
        forest.assign(seed_of[live], live)
        centroids = cluster_means(moments, forest.labels, centroids)
    return centroids, relabelled_triangles(forest.labels, corners)


def _cluster_seeds(x, centroids, labels) -> np.ndarray:
    """Per non-empty cluster (in label order), the member vertex closest to its centroid (ties:
    the lowest vertex index). With warp-lang from a sequential kernel
    (``warp_ffi.remesh.cluster_seeds``, the same answer: the same distances)."""
    if warp_available():
        from warp_ffi.remesh import cluster_seeds

        return cluster_seeds(x, centroids, labels)
    offset = x.astype(np.float64, copy=False) - np.take(centroids, labels, axis=0)
    distance2 = row_dot(offset, offset)
    # Linear time (a sort by label and distance costs twenty times more): each cluster's
    # smallest distance, then the lowest index that attains it.
    nearest = np.full(centroids.shape[0], np.inf)
    np.minimum.at(nearest, labels, distance2)
    members = np.flatnonzero(distance2 == nearest[labels])
    seed = np.full(centroids.shape[0], x.shape[0], np.int64)
    np.minimum.at(seed, labels[members], members)
    return seed[seed < x.shape[0]]


class VertexMoments(NamedTuple):
    """The vertices' integration masses ``(V,)`` and mass-weighted coordinates ``(3, V)`` (one
    contiguous row per coordinate: the weights of one ``np.bincount``), computed once for all
    the cluster means of a remesh."""

    mass: np.ndarray
    weighted: np.ndarray

    @classmethod
    def of(cls, x: np.ndarray, mass: np.ndarray) -> VertexMoments:
        return cls(mass, np.stack([mass * x[:, k] for k in range(3)]))


def cluster_means(moments: VertexMoments, labels, centroids):
    """Mass-weighted mean of each cluster's vertices (an empty cluster keeps its centroid), in
    the centroids' dtype."""
    num = centroids.shape[0]
    labels = labels.astype(np.intp, copy=False)  # once, not in each bincount
    total = np.bincount(labels, weights=moments.mass, minlength=num)
    sums = np.stack([np.bincount(labels, weights=weighted, minlength=num) for weighted in moments.weighted], axis=1)
    occupied = total > 0
    centroids = centroids.copy()
    centroids[occupied] = (sums[occupied] / total[occupied, None]).astype(centroids.dtype)
    return centroids
