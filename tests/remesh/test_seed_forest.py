"""The remesher's clusters as a shortest-path forest of the edge graph (``SeedForest``), from
scratch and updated as seeds move (the Warp kernel; SciPy without it), checked against
single-source Dijkstra distances from every seed."""

import numpy as np
import pytest
from scipy.sparse import csgraph

import geomjax.remesh._surface_clusters as surface_clusters
from geomjax import icosphere
from geomjax.remesh._surface_clusters import MeshEdges, SeedForest


def _grid(n: int):
    """An n x n grid of unit squares, each cut along a diagonal: many paths of equal length."""
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    vertices = np.stack([i.ravel(), j.ravel(), np.zeros(n * n)], axis=1).astype(np.float64)
    corner = (i[:-1, :-1] * n + j[:-1, :-1]).ravel()
    faces = np.concatenate([np.stack([corner, corner + n, corner + n + 1], 1), np.stack([corner, corner + n + 1, corner + 1], 1)])
    return vertices, faces


def _jittered_spheres():
    """A jittered icosphere(2) and a second, smaller copy beside it (a piece no seed may reach)."""
    sphere = icosphere(2)
    rng = np.random.default_rng(1)
    one = np.asarray(sphere.points, np.float64) * (1 + 0.05 * rng.uniform(-1, 1, (sphere.points.shape[0], 1)))
    faces = np.asarray(sphere.cells)
    return np.concatenate([one, 0.5 * one + 3.0]), np.concatenate([faces, faces + one.shape[0]])


def _check_forest(forest: SeedForest, edges: MeshEdges, seed_of: np.ndarray, before: np.ndarray):
    """Distances equal the nearest seed's (single-source Dijkstra from each), each vertex's label
    is that of a seed at that distance, reached from a neighbour of the same label; unreached
    vertices keep their label."""
    live = np.flatnonzero(seed_of >= 0)
    each = csgraph.dijkstra(edges.graph, directed=True, indices=seed_of[live])
    nearest = each.min(axis=0)
    np.testing.assert_array_equal(forest.distance, nearest)
    reached = np.isfinite(nearest)
    assert reached.any() and np.all(seed_of[forest.labels[reached]] >= 0)
    from_own_seed = each[np.searchsorted(live, forest.labels[reached]), np.flatnonzero(reached)]
    np.testing.assert_array_equal(from_own_seed, nearest[reached])
    np.testing.assert_array_equal(forest.labels[~reached], before[~reached])
    graph = edges.graph.tocoo()
    # A vertex is on a shortest path from a neighbour of its own label, or is its label's seed.
    via = (forest.labels[graph.row] == forest.labels[graph.col]) & (forest.distance[graph.row] + graph.data == forest.distance[graph.col])
    supported = np.zeros(nearest.size, bool)
    supported[graph.col[via]] = True
    supported[seed_of[live]] = True
    assert np.all(supported[reached])


def _moves(edges: MeshEdges, num_clusters: int, rng):
    """A forest and a sequence of seed layouts as the remesher makes them: a fresh layout, seeds
    moved within their clusters, labels that lose their seed, a donor's seed given to a vertex
    of another cluster."""
    num = edges.graph.shape[0]
    reachable = np.flatnonzero(csgraph.connected_components(edges.graph)[1] == 0)
    seed_of = rng.choice(reachable, num_clusters, replace=False)
    forest = SeedForest(edges, rng.integers(0, num_clusters, num), num_clusters)
    yield forest, seed_of
    for step in range(6):
        seed_of = seed_of.copy()
        labels = forest.labels
        if step % 3 == 0:
            for k in rng.choice(np.flatnonzero(seed_of >= 0), num_clusters // 3, replace=False):
                seed_of[k] = rng.choice(np.flatnonzero(labels == k))
        elif step % 3 == 1:
            seed_of[rng.choice(np.flatnonzero(seed_of >= 0), 2, replace=False)] = -1
        else:
            donor, host = rng.choice(np.flatnonzero(seed_of >= 0), 2, replace=False)
            seed_of[donor] = rng.choice(np.setdiff1d(np.flatnonzero(labels == host), seed_of[host]))
        yield forest, seed_of


def _grid_with_coincident_columns():
    """The grid with its columns 4 and 5 at the same place: zero-length edges (stored as the
    smallest positive float) and ties everywhere beyond them."""
    vertices, faces = _grid(12)
    vertices[vertices[:, 0] == 5, 0] = 4.0
    return vertices, faces


@pytest.mark.parametrize("surface", ["grid", "coincident", "spheres"])
@pytest.mark.parametrize("with_warp", [True, False])
def test_forest_is_the_nearest_seed_along_the_edges(surface, with_warp, monkeypatch):
    if with_warp:
        pytest.importorskip("warp")
    else:  # SciPy every time
        monkeypatch.setattr(surface_clusters, "warp_available", lambda: False)
    vertices, faces = {"grid": lambda: _grid(12), "coincident": _grid_with_coincident_columns, "spheres": _jittered_spheres}[surface]()
    edges = MeshEdges.of(vertices, faces)
    for forest, seed_of in _moves(edges, 16, np.random.default_rng(0)):
        before = forest.labels.copy()
        live = np.flatnonzero(seed_of >= 0)
        forest.assign(seed_of[live], live)
        _check_forest(forest, edges, seed_of, before)


def test_kernel_from_scratch_takes_the_lowest_label_at_ties():
    pytest.importorskip("warp")
    from warp_ffi.remesh import EdgeGraph, grow_forest

    vertices, faces = _grid(12)
    graph = MeshEdges.of(vertices, faces).graph
    num = graph.shape[0]
    rng = np.random.default_rng(2)
    seeds = rng.choice(num, 20, replace=False)
    seed_labels = rng.permutation(20)
    distance, labels, parents = np.full(num, np.inf), np.zeros(num, np.int32), np.full(num, -1, np.int32)
    assert grow_forest(EdgeGraph(graph.indptr, graph.indices, graph.data), distance, labels, parents, np.arange(num), seeds, seed_labels)
    each = csgraph.dijkstra(graph, directed=True, indices=seeds)
    nearest = each.min(axis=0)
    np.testing.assert_array_equal(distance, nearest)
    lowest = np.where(each == nearest, seed_labels[:, None], np.iinfo(np.int32).max).min(axis=0)
    assert np.sum(np.sum(each == nearest, axis=0) > 1) > 10  # the grid has ties to break
    np.testing.assert_array_equal(labels, lowest)


def test_a_full_queue_falls_back_to_scipy(monkeypatch):
    pytest.importorskip("warp")
    from warp_ffi.remesh import EdgeGraph

    vertices, faces = _jittered_spheres()
    edges = MeshEdges.of(vertices, faces)
    small_queues = []

    class SmallQueue(EdgeGraph):
        def __init__(self, *args):
            super().__init__(*args)
            self.entries = [(np.empty(4, values.dtype), dtype) for values, dtype in self.entries]
            small_queues.append(self)

    monkeypatch.setattr("warp_ffi.remesh.EdgeGraph", SmallQueue)
    for forest, seed_of in _moves(edges, 16, np.random.default_rng(3)):
        before = forest.labels.copy()
        live = np.flatnonzero(seed_of >= 0)
        forest.assign(seed_of[live], live)
        _check_forest(forest, edges, seed_of, before)
    assert small_queues and small_queues[0].overflow[0] == 1


@pytest.mark.parametrize("start", ["kept", "cleared"])
def test_a_vertex_follows_its_parent_to_a_rounded_tie(start):
    """v's path from the old seed a is one unit in the last place longer than from the new seed
    b, but j = v + 1 rounds to 2.0 either way: j must follow v to b's label (its only neighbour
    of a's label was v), kept or cleared (then regrown from v)."""
    pytest.importorskip("warp")
    from scipy import sparse

    from warp_ffi.remesh import EdgeGraph, grow_forest

    a, v, j, b, c = range(5)
    ulp_over = 1.0 + 2.0**-52
    assert ulp_over + 1.0 == 1.0 + 1.0  # the tie the test is about
    pairs = [(a, v, ulp_over), (v, j, 1.0), (b, v, 1.0), (c, j, 1.5)]
    rows, cols, lengths = zip(*pairs)
    upper = sparse.coo_matrix((lengths, (rows, cols)), shape=(5, 5))
    graph = (upper + upper.T).tocsr()
    kernel_graph = EdgeGraph(graph.indptr, graph.indices, graph.data)
    distance, labels, parents = np.full(5, np.inf), np.zeros(5, np.int32), np.full(5, -1, np.int32)
    old_seeds, old_labels = ([a], [0]) if start == "kept" else ([a, c], [0, 2])
    assert grow_forest(kernel_graph, distance, labels, parents, np.arange(5), np.array(old_seeds), np.array(old_labels))
    assert labels[j] == (0 if start == "kept" else 2) and labels[v] == 0
    cleared = np.flatnonzero(labels == 2)  # label 2 loses its seed c
    assert grow_forest(kernel_graph, distance, labels, parents, cleared, np.array([a, b]), np.array([0, 1]))
    np.testing.assert_array_equal(distance, [0.0, 1.0, 2.0, 0.0, 3.5])
    np.testing.assert_array_equal(labels, [0, 1, 1, 1, 1])
    np.testing.assert_array_equal(parents[[v, j, c]], [b, v, j])


@pytest.mark.parametrize("with_warp", [True, False])
def test_cluster_seeds_are_the_members_nearest_their_centroids(with_warp, monkeypatch):
    # Grid points (many exact ties: points at equal distances from a centroid on a grid node
    # or between nodes) in 12 clusters, one of them empty, float32 points with float64
    # centroids: per non-empty cluster, in label order, the member nearest its centroid, the
    # lowest index among equals, as a loop over the clusters finds it.
    if with_warp:
        pytest.importorskip("warp")
    else:
        monkeypatch.setattr(surface_clusters, "warp_available", lambda: False)
    vertices, _ = _grid(9)
    rng = np.random.default_rng(2)
    labels = rng.integers(0, 12, vertices.shape[0]).astype(np.int32)
    labels[labels == 7] = 3
    centroids = np.round(rng.uniform(0, 8, (12, 3)) * 2) / 2 * [1, 1, 0]
    expected, tied = [], 0
    for cluster in range(12):
        members = np.flatnonzero(labels == cluster)
        if members.size:
            distance2 = np.sum((vertices[members] - centroids[cluster]) ** 2, axis=1)
            nearest = np.flatnonzero(distance2 == distance2.min())
            expected.append(members[nearest[0]])
            tied += nearest.size > 1
    assert tied > 0 and len(expected) == 11
    seeds = surface_clusters._cluster_seeds(vertices.astype(np.float32), centroids, labels)
    np.testing.assert_array_equal(seeds, expected)
