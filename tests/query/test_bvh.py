"""MeshBVH: building, validation, lifetime, refit, the nearest-face search and orientation repair."""

import gc
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

pytest.importorskip("warp")

from geomjax import MeshBVH, build_bvh, icosphere  # noqa: E402
from geomjax.query.bvh import (  # noqa: E402
    closest_faces,
    closest_faces_brute_force,
    consistently_oriented_faces,
)
from geomjax._geometry import closest_point_on_triangle  # noqa: E402

DTYPES = [jnp.float32, jnp.float64]


def _sphere(dtype, subdivisions=2):
    mesh = icosphere(subdivisions, dtype=dtype)
    return mesh.points, jnp.asarray(mesh.cells, jnp.int32)


def _distances(points, vertices, faces, ids):
    tri = vertices[faces[jnp.maximum(ids, 0)]]
    closest, _ = closest_point_on_triangle(points, tri[:, 0], tri[:, 1], tri[:, 2])
    return np.where(np.asarray(ids) >= 0, np.linalg.norm(np.asarray(closest - points, np.float64), axis=-1), np.inf)


@pytest.mark.parametrize("dtype", DTYPES)
def test_closest_faces_equal_brute_force(dtype):
    vertices, faces = _sphere(dtype)
    bvh = build_bvh(vertices, faces)
    rng = np.random.default_rng(0)
    points = jnp.asarray(rng.normal(size=(500, 3)) * rng.uniform(0.2, 2.5, (500, 1)), dtype)
    ids = closest_faces(bvh, points)
    expected, d2 = closest_faces_brute_force(points, vertices, faces)
    assert ids.dtype == jnp.int32 and ids.shape == (500,)
    # Same distance always; same face wherever the nearest face is the only one at that distance.
    d_warp = _distances(points, vertices, faces, ids)
    tol = 1e-6 if dtype == jnp.float32 else 1e-14
    np.testing.assert_allclose(d_warp, np.sqrt(np.asarray(d2, np.float64)), rtol=tol, atol=tol)
    unique = _unique_nearest(points, vertices, faces, margin=1e-4)
    assert unique.sum() > 150  # many closest points lie on shared edges or vertices
    np.testing.assert_array_equal(np.asarray(ids)[unique], np.asarray(expected)[unique])


def _all_distances(points, vertices, faces):
    """``(points, faces)`` distances from every point to every face, in float64."""
    tri = vertices[faces]
    closest, _ = jax.jit(closest_point_on_triangle)(points[:, None], tri[None, :, 0], tri[None, :, 1], tri[None, :, 2])
    return np.linalg.norm(np.asarray(closest - points[:, None], np.float64), axis=-1)


def _unique_nearest(points, vertices, faces, margin):
    d = np.sort(_all_distances(points, vertices, faces), axis=1)
    return d[:, 1] - d[:, 0] > margin


@pytest.mark.parametrize("dtype", DTYPES)
def test_oriented_box_tree_search_is_exact_on_a_finely_tessellated_sphere(dtype):
    # 5,120 faces (a 12-level tree): queries near the centre (every face about equally far),
    # near the surface, far outside, and gated by max_distance.
    vertices, faces = _sphere(dtype, 4)
    bvh = build_bvh(vertices, faces)
    rng = np.random.default_rng(4)
    directions = rng.normal(size=(600, 3))
    radii = np.concatenate([rng.uniform(0.0, 0.2, 150), rng.uniform(0.95, 1.05, 300), rng.uniform(1.5, 4.0, 150)])
    points = jnp.asarray(directions / np.linalg.norm(directions, axis=1, keepdims=True) * radii[:, None], dtype)
    tol = 1e-6 if dtype == jnp.float32 else 1e-14
    # Brute force once (3 million point-triangle distances): the gated answer and the unique
    # nearest faces follow from the same matrix.
    distances = _all_distances(points, vertices, faces)
    nearest = np.argmin(distances, axis=1)
    nearest_distance = distances[np.arange(len(nearest)), nearest]
    for max_distance in (None, 0.5):
        ids = np.asarray(closest_faces(bvh, points, max_distance))
        found = nearest_distance <= (np.inf if max_distance is None else max_distance)
        np.testing.assert_array_equal(ids >= 0, found)
        d_tree = _distances(points, vertices, faces, ids)[found]
        np.testing.assert_allclose(d_tree, nearest_distance[found], rtol=tol, atol=tol)
    second = np.partition(distances, 1, axis=1)[:, 1]
    unique = second - nearest_distance > 1e-5
    np.testing.assert_array_equal(ids[unique], np.where(found, nearest, -1)[unique])  # gated at 0.5


def test_float32_ties_do_not_depend_on_the_other_queries():
    # Points straight out from the vertices: 5-6 faces tie at the vertex. The float32 search (no
    # refinement: signed_distance_field) starts from the previous query's face, yet ties must go
    # the same way whatever the neighbouring queries are.
    from geomjax import signed_distance_field

    vertices, faces = _sphere(jnp.float32, 2)
    ties = jnp.concatenate([vertices * 1.5, vertices * 0.5])
    # Neighbours just off each tie have one of the tied faces as their unique answer, and may
    # precede the tie in the search order.
    nudges = jnp.asarray(np.random.default_rng(6).normal(scale=0.01, size=(4,) + ties.shape), jnp.float32)
    points = jnp.concatenate([ties, *(ties + nudge for nudge in nudges)])

    def face_ids(p):
        return np.asarray(signed_distance_field(vertices, faces, p, implementation="warp")[2])

    ids = face_ids(points)
    permutation = np.random.default_rng(5).permutation(points.shape[0])
    np.testing.assert_array_equal(face_ids(points[permutation]), ids[permutation])
    alone = [int(face_ids(points[k : k + 1])[0]) for k in range(0, ties.shape[0], 7)]
    np.testing.assert_array_equal(alone, ids[: ties.shape[0] : 7])


@pytest.mark.parametrize("num_faces", [1, 2, 3, 5, 7, 9, 13, 33])
def test_tree_leaves_cover_every_face_count(num_faces):
    # The tree's leaves tile the sorted faces in 1-2 face ranges; odd counts leave uneven ones.
    rng = np.random.default_rng(num_faces)
    vertices = jnp.asarray(rng.uniform(-1, 1, (3 * num_faces, 3)))
    faces = jnp.arange(3 * num_faces, dtype=jnp.int32).reshape(-1, 3)
    points = jnp.asarray(rng.uniform(-2, 2, (300, 3)))
    ids = closest_faces(build_bvh(vertices, faces), points)
    np.testing.assert_array_equal(ids, closest_faces_brute_force(points, vertices, faces)[0])


def test_sliver_faces_are_searched():
    # The segment-like face is the only one within max_distance: it must be found.
    vertices = jnp.asarray([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [5.0, 5, 5], [5.5, 5.5, 5.5], [6.0, 6, 6]])
    faces = jnp.array([[0, 1, 2], [3, 4, 5]], jnp.int32)
    points = jnp.asarray([[5.5, 5.5, 5.6], [0.2, 0.2, 0.1]])
    np.testing.assert_array_equal(closest_faces(build_bvh(vertices, faces), points, max_distance=1.0), [1, 0])


def test_float64_search_is_exact_where_float32_cannot_tell():
    # Two parallel triangles 1 and 1 + 1e-12 below the query: only float64 separates them. The
    # nearer one has the higher index, so a float32 tie-break would pick the wrong one.
    tri = np.array([[-1.0, -1, 0], [1.0, -1, 0], [0.0, 1, 0]])
    vertices = jnp.asarray(np.concatenate([tri - [0, 0, 1e-12], tri]))
    faces = jnp.array([[0, 1, 2], [3, 4, 5]], jnp.int32)
    bvh = build_bvh(vertices, faces)
    points = jnp.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    np.testing.assert_array_equal(closest_faces(bvh, points), [1, 0])
    np.testing.assert_array_equal(closest_faces_brute_force(points, vertices, faces)[0], [1, 0])


@pytest.mark.parametrize("dtype", DTYPES)
def test_ties_go_to_the_lowest_face_and_degenerate_faces_count(dtype):
    vertices = jnp.asarray([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0.5, 0.5, 0.5], [0.6, 0.6, 0.5], [0.7, 0.7, 0.5]], dtype)
    faces = jnp.array([[1, 3, 2], [0, 1, 2], [4, 5, 6]], jnp.int32)  # the last one is a segment
    bvh = build_bvh(vertices, faces)
    points = jnp.asarray([[0.5, 0.5, 0.0], [1.0, 0.0, 1.0e-3], [0.6, 0.6, 0.6], [0.1, 0.1, -0.1]], dtype)
    np.testing.assert_array_equal(closest_faces(bvh, points), [0, 0, 2, 1])
    np.testing.assert_array_equal(closest_faces_brute_force(points, vertices, faces)[0], [0, 0, 2, 1])


@pytest.mark.parametrize("dtype", DTYPES)
def test_max_distance_non_finite_points_and_shapes(dtype):
    vertices, faces = _sphere(dtype, 1)
    bvh = build_bvh(vertices, faces)
    points = jnp.asarray([[[0.0, 0.0, 1.5], [0.0, 0.0, 3.0]], [[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0]]], dtype)
    ids = closest_faces(bvh, points, max_distance=1.0)
    assert ids.shape == (2, 2)
    np.testing.assert_array_equal(np.asarray(ids)[0, 1:], [-1]) and np.testing.assert_array_equal(ids[1], [-1, -1])
    assert int(ids[0, 0]) >= 0
    # The gate is exact: a vertex at distance exactly 1 is in, just beyond is out.
    top = vertices[int(jnp.argmax(vertices[:, 2]))]
    above = top + jnp.asarray([0.0, 0.0, 1.0], dtype)
    assert int(closest_faces(bvh, above[None], max_distance=1.0)[0]) >= 0
    assert int(closest_faces(bvh, above[None], max_distance=float(np.nextafter(dtype(1.0), dtype(0.0))))[0]) == -1
    assert closest_faces(bvh, jnp.zeros((0, 3), dtype)).shape == (0,)


def test_jit_does_not_retrace_for_a_new_mesh_and_vmap_matches():
    vertices, faces = _sphere(jnp.float64, 1)
    traces = []

    @jax.jit
    def query(bvh, points):
        traces.append(1)
        return closest_faces(bvh, points)

    points = jnp.asarray(np.random.default_rng(1).normal(size=(64, 3)))
    first = query(build_bvh(vertices, faces), points)
    second = query(build_bvh(vertices * 2, faces), points * 2)
    assert len(traces) == 1
    np.testing.assert_array_equal(first, second)
    bvh = build_bvh(vertices, faces)
    batched = jax.vmap(lambda p: closest_faces(bvh, p))(points.reshape(4, 16, 3))
    np.testing.assert_array_equal(batched.reshape(-1), first)
    closed_over = jax.jit(lambda p: closest_faces(bvh, p))(points)
    np.testing.assert_array_equal(closed_over, first)


def test_the_mesh_lives_as_long_as_its_handle():
    vertices, faces = _sphere(jnp.float32, 1)
    bvh = build_bvh(vertices, faces)
    mesh_ref = weakref.ref(bvh.warp_mesh)
    words = bvh.mesh_words
    del bvh
    gc.collect()
    assert mesh_ref() is not None  # the handle buffer owns the mesh
    del words
    gc.collect()
    assert mesh_ref() is None
    # A temporary BVH passed to a jitted query: nothing keeps it but the call's input buffer.
    points = jnp.asarray(np.random.default_rng(2).normal(size=(1000, 3)), jnp.float32)
    ids = jax.jit(closest_faces)(build_bvh(vertices, faces), points)
    gc.collect()
    np.testing.assert_array_equal(ids, closest_faces(build_bvh(vertices, faces), points))


@pytest.mark.parametrize("forge", ["zeros", "freed", "never built"])
def test_forged_or_freed_handles_raise_instead_of_crashing(forge):
    # The handle is pytree data: jax.tree.map, or a MeshBVH rebuilt from its fields, can name a
    # mesh that is gone or never existed. Warp would dereference it (a segfault before).
    from geomjax import documented_errors, shrinkwrap_points

    vertices, faces = _sphere(jnp.float64, 1)
    bvh = build_bvh(vertices, faces)
    if forge == "zeros":
        forged = jax.tree.map(jnp.zeros_like, bvh)
    elif forge == "freed":
        forged = jax.tree.map(lambda leaf: jnp.array(np.asarray(leaf)), bvh)  # copies, not the owning buffer
        mesh_ref = weakref.ref(bvh.warp_mesh)
        del bvh
        gc.collect()
        assert mesh_ref() is None
    else:
        forged = jax.tree.map(lambda leaf: leaf, bvh)
        forged = eqx.tree_at(lambda b: b.mesh_words, forged, jnp.array([0xDEADBEE0, 0x7F], jnp.uint32))
    origins, directions = jnp.array([[0.0, 0.0, 3.0]]), jnp.array([[0.0, 0.0, -1.0]])
    message = "the MeshBVH's Warp mesh is not alive"
    with pytest.raises(ValueError, match=f"ray_mesh_intersect: {message}"):
        ray_mesh_intersect(vertices, faces, origins, directions, warp_mesh=forged)
    with pytest.raises(ValueError, match=f"ray_mesh_intersect: {message}"), documented_errors():
        jax.jit(lambda b: ray_mesh_intersect(vertices, faces, origins, directions, warp_mesh=b))(forged)
    with pytest.raises(ValueError, match=f"shrinkwrap_points: {message}"):
        shrinkwrap_points(origins, vertices, faces, bvh=forged, implementation="warp")
    # A live handle still works next to a dead one.
    live = build_bvh(vertices, faces)
    hit = ray_mesh_intersect(vertices, faces, origins, directions, warp_mesh=live)
    assert bool(hit[0][0]) and abs(float(hit[1][0]) - 2.0) < 0.05


@pytest.mark.parametrize("forge", ["shifted indices", "stretched leaves", "empty leaves", "faces out of range", "ray-only faces"])
def test_forged_search_arrays_raise_instead_of_crashing(forge):
    # The faces and the oriented-box tree are pytree data too, and the Warp search indexes memory
    # with them: out-of-range indices or leaf ranges segfaulted before.
    from geomjax import documented_errors

    vertices, faces = _sphere(jnp.float64, 1)
    bvh = build_bvh(vertices, faces)
    nodes, leaf_starts, sorted_faces, corners = bvh.closest_tree
    if forge == "shifted indices":
        forged = jax.tree.map(lambda leaf: leaf + 1000 if leaf.dtype == jnp.int32 else leaf, bvh)
    elif forge == "stretched leaves":
        forged = eqx.tree_at(lambda b: b.closest_tree, bvh, (nodes, leaf_starts * 50, sorted_faces, corners))
    elif forge == "empty leaves":
        forged = eqx.tree_at(lambda b: b.closest_tree, bvh, (nodes, leaf_starts * 0, sorted_faces, corners))
    elif forge == "faces out of range":
        forged = eqx.tree_at(lambda b: b.faces, bvh, bvh.faces + vertices.shape[0])
    else:
        # Without its tree (as a MeshBVH for ray casts only) the search builds one from the faces.
        forged = eqx.tree_at(lambda b: (b.faces, b.closest_tree), bvh, (-bvh.faces, None), is_leaf=lambda x: x is None)
    points = jnp.asarray(np.random.default_rng(4).normal(size=(50, 3)))
    message = "closest_faces: the MeshBVH's faces or search tree are not those build_bvh made"
    with pytest.raises(ValueError, match=message):
        closest_faces(forged, points)
    with pytest.raises(ValueError, match=message), documented_errors():
        jax.block_until_ready(jax.jit(closest_faces)(forged, points))
    with pytest.raises(ValueError, match="search tree does not fit its"):
        closest_faces(eqx.tree_at(lambda b: b.closest_tree, bvh, (nodes, leaf_starts[:-1], sorted_faces, corners)), points)
    # The genuine MeshBVH still finds the nearest faces (the brute force's distances; ties at
    # shared edges may pick another face).
    corners = vertices[faces[closest_faces(bvh, points)]]
    nearest, _ = closest_point_on_triangle(points, corners[:, 0], corners[:, 1], corners[:, 2])
    expected = jnp.sqrt(closest_faces_brute_force(points, vertices, faces)[1])
    np.testing.assert_allclose(jnp.linalg.norm(nearest - points, axis=-1), expected, rtol=1e-12)


def test_refit_moves_the_bvh():
    vertices, faces = _sphere(jnp.float64, 1)
    bvh = build_bvh(vertices, faces)
    query = jax.jit(closest_faces)
    points = jnp.asarray(np.random.default_rng(3).normal(size=(200, 3))) + jnp.asarray([5.0, 0, 0])
    moved_vertices = vertices + jnp.asarray([5.0, 0, 0])
    moved = bvh.refit(moved_vertices)
    assert isinstance(moved, MeshBVH) and moved.vertices is moved_vertices
    fresh = build_bvh(moved_vertices, faces)
    np.testing.assert_array_equal(query(moved, points), query(fresh, points))
    with pytest.raises(ValueError, match="shape"):
        moved.refit(vertices[:-1])
    with pytest.raises(TypeError, match="dtype"):
        moved.refit(vertices.astype(jnp.float32))
    with pytest.raises(ValueError, match="finite"):
        moved.refit(vertices.at[0, 0].set(jnp.nan))
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda v: moved.refit(v).vertices)(vertices)


def test_build_bvh_validation():
    vertices, faces = _sphere(jnp.float32, 0)
    with pytest.raises(TypeError, match="mesh_vertices"):
        build_bvh(vertices.astype(jnp.int32), faces)
    with pytest.raises(TypeError, match="mesh_indices"):
        build_bvh(vertices, faces.astype(jnp.float32))
    with pytest.raises(TypeError, match="winding_number"):
        build_bvh(vertices, faces, winding_number=1)
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda v: build_bvh(v, faces).vertices)(vertices)
    with pytest.raises(ValueError, match="shape"):
        build_bvh(vertices[:, :2], faces)
    with pytest.raises(ValueError, match="shape"):
        build_bvh(jnp.zeros((0, 3)), faces)
    with pytest.raises(ValueError, match="mesh_indices"):
        build_bvh(vertices, faces[:0])
    with pytest.raises(ValueError, match="mesh_indices"):
        build_bvh(vertices, faces.reshape(-1)[:7])
    with pytest.raises(ValueError, match=r"\[0, 12\)"):
        build_bvh(vertices, faces.at[3, 1].set(12))
    with pytest.raises(ValueError, match=r"\[0, 12\)"):
        build_bvh(vertices, faces.at[3, 1].set(-1))
    with pytest.raises(ValueError, match="finite"):
        build_bvh(vertices.at[2, 2].set(jnp.inf), faces)
    with pytest.raises(ValueError, match="float32"):
        build_bvh(vertices.astype(jnp.float64).at[2, 2].set(1e40), faces)
    flat = build_bvh(vertices, faces.reshape(-1).astype(jnp.int64))
    assert flat.faces.shape == faces.shape and flat.faces.dtype == jnp.int32
    bvh = build_bvh(vertices, faces)
    with pytest.raises(TypeError, match="MeshBVH"):
        closest_faces(vertices, vertices)
    with pytest.raises(TypeError, match="dtype"):
        closest_faces(bvh, vertices.astype(jnp.float64))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        closest_faces(bvh, vertices[:, :2])
    with pytest.raises(ValueError, match="max_distance"):
        closest_faces(bvh, vertices, max_distance=-1.0)
    with pytest.raises(TypeError, match="max_distance"):
        closest_faces(bvh, vertices, max_distance=True)


def _imperfect_sphere(dtype=jnp.float64):
    vertices, faces = _sphere(dtype, 2)
    rng = np.random.default_rng(4)
    flipped = rng.choice(faces.shape[0], 12, replace=False)
    bad = np.asarray(faces).copy()
    bad[flipped] = bad[flipped][:, [0, 2, 1]]
    return vertices, faces, jnp.asarray(bad), flipped


def test_orientation_repair_restores_a_consistent_mesh():
    _, faces, bad, _ = _imperfect_sphere()
    np.testing.assert_array_equal(consistently_oriented_faces(bad), faces)
    np.testing.assert_array_equal(jax.jit(consistently_oriented_faces)(bad), faces)
    np.testing.assert_array_equal(consistently_oriented_faces(faces), faces)
    # A hole does not matter; two disjoint pieces are repaired independently.
    holed = np.delete(np.asarray(bad), [0, 5, 9], axis=0)
    np.testing.assert_array_equal(consistently_oriented_faces(holed), np.delete(np.asarray(faces), [0, 5, 9], axis=0))
    two = np.concatenate([np.asarray(bad), np.asarray(bad)[:, ::-1] + 1000])
    expected = np.concatenate([np.asarray(faces), np.asarray(faces)[:, ::-1] + 1000])
    repaired = np.asarray(consistently_oriented_faces(two))
    _assert_same_orientation(repaired, expected)


def _assert_same_orientation(faces, expected):
    # Same cyclic order per face (a swap of two indices is the only change the repair makes).
    def canonical(f):
        k = np.argmin(f, axis=1)
        return np.stack([np.roll(row, -i) for row, i in zip(f, k)])

    np.testing.assert_array_equal(canonical(faces), canonical(expected))


def test_winding_bvh_builds_on_repaired_faces_but_keeps_the_input_faces():
    _, faces, bad, _ = _imperfect_sphere()
    vertices = _sphere(jnp.float64, 2)[0]
    bvh = build_bvh(vertices, bad, winding_number=True)
    assert bvh.winding_number
    np.testing.assert_array_equal(bvh.faces, bad)
    _assert_same_orientation(bvh.warp_mesh.indices.numpy().reshape(-1, 3), np.asarray(faces))


# ---------------------------------------------------------------------------------------------
# Bad input never crashes: every query, both backends, random malformed arguments.

from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from geomjax import ray_mesh_intersect, signed_distance_field  # noqa: E402

DOCUMENTED = (TypeError, ValueError, KeyError, RuntimeError)
_float_dtypes = st.sampled_from([jnp.float32, jnp.float64, jnp.float16, jnp.int32])
_index_dtypes = st.sampled_from([jnp.int32, jnp.int64, jnp.int16, jnp.float32])
_shapes = st.lists(st.integers(0, 4), min_size=0, max_size=3).map(tuple)
_fills = st.sampled_from([0.0, 1.0, np.nan, np.inf, 1e30, 1e300, -7.0])


@pytest.mark.parametrize("implementation", ["jax", "warp"])
@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(v_shape=_shapes, f_shape=_shapes, q_shape=_shapes, v_dtype=_float_dtypes, q_dtype=_float_dtypes,
       f_dtype=_index_dtypes, fill=_fills, index=st.integers(-3, 6))  # fmt: skip
def test_queries_survive_bad_input(implementation, v_shape, f_shape, q_shape, v_dtype, q_dtype, f_dtype, fill, index):
    rng = np.random.default_rng(len(v_shape) + len(q_shape))
    vertices = rng.normal(size=v_shape)
    if vertices.size:
        vertices.flat[0] = fill
    faces = rng.integers(0, 4, size=f_shape)
    if faces.size:
        faces.flat[-1] = index
    queries = rng.normal(size=q_shape)
    if queries.size:
        queries.flat[-1] = fill
    with np.errstate(all="ignore"):  # converted by NumPy (no program per shape): NaN and 1e300 overflow
        vertices, faces, queries = (jax.device_put(a.astype(t)) for a, t in ((vertices, v_dtype), (faces, f_dtype), (queries, q_dtype)))
    for call in (
        lambda: signed_distance_field(vertices, faces, queries, implementation=implementation),
        lambda: signed_distance_field(vertices, faces, queries, use_sign_winding_number=True, implementation=implementation),
        lambda: ray_mesh_intersect(vertices, faces, queries, queries, implementation=implementation),
    ):
        try:
            outputs = jax.block_until_ready(call())
        except DOCUMENTED:
            continue
        assert outputs[0].shape == queries.shape[:-1]
