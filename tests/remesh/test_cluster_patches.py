"""The remesher's cluster patches: their faces, the plane quadrics summed over them, and the
nearest points on them (ties, both backends)."""

import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks import _quality as quality
from geomjax import icosphere
from geomjax.remesh._patch_projection import PatchProjector
from geomjax.remesh._quadrics import ClusterQuadrics, vertex_plane_terms
from geomjax.remesh._surface_clusters import ClusterPatches

pytest.importorskip("warp")

BACKENDS = ["jax", "warp"]
NUM_CLUSTERS = 12


def _sphere_with_clusters():
    """A jittered icosphere(2) and random cluster labels, cluster 5 left empty."""
    sphere = icosphere(2)
    rng = np.random.default_rng(0)
    vertices = np.asarray(sphere.points) * (1 + 0.05 * rng.uniform(-1, 1, (sphere.points.shape[0], 1)))
    faces = np.asarray(sphere.cells)
    labels = rng.integers(0, NUM_CLUSTERS - 1, vertices.shape[0])
    labels[labels == 5] = NUM_CLUSTERS - 1
    return vertices, faces, labels


def test_patches_are_the_faces_touching_each_cluster():
    vertices, faces, labels = _sphere_with_clusters()
    offsets, candidates, corners = ClusterPatches.of(faces, labels, NUM_CLUSTERS)
    assert offsets.dtype == candidates.dtype == corners.dtype == np.int32 and offsets.shape == (NUM_CLUSTERS + 1,)
    for k in range(NUM_CLUSTERS):
        patch = slice(offsets[k], offsets[k + 1])
        expected = [f for f in range(faces.shape[0]) if k in labels[faces[f]]]
        # An empty cluster gets face 0 with no corner: its vertex is unused, but it must land somewhere.
        np.testing.assert_array_equal(candidates[patch], expected if expected else [0])
        np.testing.assert_array_equal(corners[patch], [np.sum(labels[faces[f]] == k) for f in expected] if expected else [0])
    assert offsets[6] - offsets[5] == 1 and np.any(corners == 2)


def test_quadrics_sum_each_cluster_s_corner_planes(monkeypatch):
    vertices, faces, labels = _sphere_with_clusters()
    corners = vertices[faces]
    doubled = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(doubled, axis=1) / 2
    terms = vertex_plane_terms(faces, corners[:, 0], doubled, area, vertices.shape[0])
    quadrics = ClusterQuadrics.of(terms, labels, NUM_CLUSTERS)
    # Without warp-lang NumPy computes the same terms and sums them in the same order, to the
    # bit; faces with a repeated corner (zero area) add nothing.
    degenerate = np.concatenate([faces, [[3, 3, 7], [5, 5, 5]]])
    corners = vertices[degenerate]
    doubled = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    area = np.linalg.norm(doubled, axis=1) / 2
    with_kernel = vertex_plane_terms(degenerate, corners[:, 0], doubled, area, vertices.shape[0])
    monkeypatch.setattr("geomjax.remesh._quadrics.warp_available", lambda: False)
    np.testing.assert_array_equal(vertex_plane_terms(degenerate, corners[:, 0], doubled, area, vertices.shape[0]), with_kernel)
    # A plain loop: each corner of each face adds a third of the face's area times its plane.
    expected = np.zeros((NUM_CLUSTERS, 3, 3))
    expected_rhs = np.zeros((NUM_CLUSTERS, 3))
    expected_normals = np.zeros((NUM_CLUSTERS, 3))
    for f in range(faces.shape[0]):
        n = doubled[f] / np.linalg.norm(doubled[f])
        for vertex in faces[f]:
            expected[labels[vertex]] += area[f] / 3 * np.outer(n, n)
            expected_rhs[labels[vertex]] += area[f] / 3 * n * np.dot(n, corners[f, 0])
            expected_normals[labels[vertex]] += area[f] / 3 * n
    np.testing.assert_allclose(quadrics.quadric, expected, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(quadrics.rhs, expected_rhs, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(quadrics.normals, expected_normals, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(quadrics.quadric @ quadrics.basis, quadrics.basis * quadrics.weights[:, None, :], atol=1e-14)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_projection_is_the_nearest_point_of_the_patch(backend, dtype):
    vertices, faces, labels = _sphere_with_clusters()
    rng = np.random.default_rng(1)
    targets = rng.normal(size=(40, 3)) * rng.uniform(0.2, 1.5, (40, 1))
    clusters = rng.integers(0, NUM_CLUSTERS, 40)
    patches = ClusterPatches.of(faces, labels, NUM_CLUSTERS)
    project = PatchProjector(jnp.asarray(vertices, dtype), faces, patches, backend)
    positions, found, weights = project(targets.astype(dtype), clusters)
    assert positions.dtype == weights.dtype == dtype and found.dtype == np.int32
    offsets, candidates, _ = patches
    eps = float(jnp.finfo(dtype).eps)
    host = vertices.astype(dtype).astype(np.float64)
    for i, (target, k) in enumerate(zip(targets.astype(dtype).astype(np.float64), clusters, strict=True)):
        patch = candidates[offsets[k] : offsets[k + 1]]
        corners = host[faces[patch]]
        # Independent closest points (Ericson's Voronoi regions, float64) on every patch face.
        closest = quality._closest_points_on_triangles(np.broadcast_to(target, (patch.size, 3)), corners[:, 0], corners[:, 1], corners[:, 2])
        distances = np.linalg.norm(closest - target, axis=1)
        assert found[i] in patch
        # The chosen face is a nearest one, up to the rounding of the distances (scale ~ 1).
        assert distances[patch == found[i]][0] <= distances.min() + 64 * eps
        np.testing.assert_allclose(positions[i], closest[patch == found[i]][0], atol=64 * eps)
        np.testing.assert_allclose(np.einsum("k,kd->d", weights[i].astype(np.float64), host[faces[found[i]]]), positions[i], atol=64 * eps)


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_hint_does_not_change_the_nearest_face(backend):
    # The search may start from any face of the patch (the remesher passes a vertex's face before
    # it moved): the worst hint (the patch's face farthest from the target) and a random one give
    # the faces found without a hint, which test_projection_is_the_nearest_point_of_the_patch
    # checks against an independent computation.
    vertices, faces, labels = _sphere_with_clusters()
    rng = np.random.default_rng(1)
    targets = rng.normal(size=(40, 3)) * rng.uniform(0.2, 1.5, (40, 1))
    clusters = rng.integers(0, NUM_CLUSTERS, 40)
    patches = ClusterPatches.of(faces, labels, NUM_CLUSTERS)
    offsets, candidates, _ = patches
    project = PatchProjector(jnp.asarray(vertices), faces, patches, backend)
    farthest, random = [], []
    for target, k in zip(targets, clusters, strict=True):
        patch = candidates[offsets[k] : offsets[k + 1]]
        farthest.append(patch[np.argmax(np.linalg.norm(vertices[faces[patch]].mean(axis=1) - target, axis=1))])
        random.append(rng.choice(patch))
    expected = project(targets, clusters)
    for hints in (np.array(farthest), np.array(random)):
        found = project(targets, clusters, hints=hints)
        np.testing.assert_array_equal(found[1], expected[1])
        np.testing.assert_array_equal(found[0], expected[0])
    assert not np.array_equal(np.array(farthest), expected[1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_ties_go_to_the_lowest_face(backend):
    # A point straight out from a vertex: every face of the patch around that vertex has the
    # vertex as its closest point, at the same distance.
    vertices, faces, labels = _sphere_with_clusters()
    vertex = 7
    k = labels[vertex]
    project = PatchProjector(jnp.asarray(vertices), faces, ClusterPatches.of(faces, labels, NUM_CLUSTERS), backend)
    positions, found, _ = project(vertices[vertex][None] * 1.2, np.array([k]))
    around = np.flatnonzero(np.any(faces == vertex, axis=1))
    assert found[0] == around.min()
    # Starting from the highest of the tied faces changes nothing.
    assert project(vertices[vertex][None] * 1.2, np.array([k]), hints=around[-1:])[1][0] == around.min()
    np.testing.assert_allclose(positions[0], vertices[vertex], atol=1e-15)


def test_backends_agree():
    # One target per cluster (the remesher's call without clusters): row k is cluster k's.
    vertices, faces, labels = _sphere_with_clusters()
    targets = np.random.default_rng(2).normal(size=(NUM_CLUSTERS, 3))
    patches = ClusterPatches.of(faces, labels, NUM_CLUSTERS)
    jax_out, warp_out = (PatchProjector(jnp.asarray(vertices), faces, patches, backend)(targets) for backend in BACKENDS)
    np.testing.assert_array_equal(jax_out[1], warp_out[1])
    np.testing.assert_allclose(jax_out[0], warp_out[0], atol=1e-14)
    offsets, candidates, _ = patches
    assert all(jax_out[1][k] in candidates[offsets[k] : offsets[k + 1]] for k in range(NUM_CLUSTERS))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_near_ties_between_faces_go_alike_on_both_backends(dtype):
    # 300 valleys (two faces mirrored across the plane x = 0) in random orientations, each its
    # own cluster, and a target on each valley's mirror plane: in exact arithmetic it is as far
    # from both faces, at different closest points. The backends measure with different code, so
    # their rounding would pick different faces; within the tie tolerance both take the lower
    # index (here the first face of each valley), and the same position.
    rng = np.random.default_rng(4)
    count = 300
    valley = np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.8], [1.0, 0.0, 0.8]])
    rotations = np.linalg.qr(rng.normal(size=(count, 3, 3)))[0]
    centres = rng.uniform(-2, 2, (count, 3))
    vertices = (np.einsum("kij,vj->kvi", rotations, valley) + centres[:, None]).reshape(-1, 3).astype(dtype)
    faces = (4 * np.arange(count)[:, None, None] + np.array([[0, 1, 2], [1, 0, 3]])).reshape(-1, 3)
    labels = np.repeat(np.arange(count), 4)
    local = np.stack([np.zeros(count), rng.uniform(-0.5, 0.5, count), rng.uniform(0.9, 1.5, count)], axis=1)
    targets = (np.einsum("kij,kj->ki", rotations, local) + centres).astype(dtype)
    patches = ClusterPatches.of(faces, labels, count)
    jax_out, warp_out = (PatchProjector(jnp.asarray(vertices), faces, patches, backend)(targets) for backend in BACKENDS)
    np.testing.assert_array_equal(jax_out[1], 2 * np.arange(count))
    np.testing.assert_array_equal(warp_out[1], 2 * np.arange(count))
    np.testing.assert_array_equal(jax_out[0], warp_out[0])


@pytest.mark.parametrize("backend", BACKENDS)
def test_a_cluster_s_point_stays_on_its_own_sheet(backend):
    # Two parallel squares 0.01 apart, one cluster each: a target nearer the other sheet still
    # lands on its cluster's own sheet (the closest point of the whole surface would not).
    square = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]])
    vertices = np.concatenate([square, square + [0.0, 0.0, 0.01]])
    faces = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    labels = np.array([0, 0, 0, 0, 1, 1, 1, 1])
    project = PatchProjector(jnp.asarray(vertices), faces, ClusterPatches.of(faces, labels, 2), backend)
    positions, found, _ = project(np.array([[0.3, 0.6, 0.008], [0.3, 0.6, 0.002]]), np.array([0, 1]))
    np.testing.assert_allclose(positions, [[0.3, 0.6, 0.0], [0.3, 0.6, 0.01]], atol=1e-15)
    assert found[0] in (0, 1) and found[1] in (2, 3)
