"""ray_mesh_intersect: conventions, Warp BVH against the brute-force JAX path, gradients, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import MeshBVH, icosphere, ray_mesh_intersect

BACKENDS = ["jax", pytest.param("warp", marks=pytest.mark.filterwarnings("ignore"))]
DTYPES = [jnp.float32, jnp.float64]


def _sphere(dtype, subdivisions=2):
    mesh = icosphere(subdivisions, dtype=dtype)
    return mesh.points, jnp.asarray(mesh.cells, jnp.int32)


def _aimed_rays(vertices, faces, n, seed, dtype):
    """Rays from outside the unit sphere aimed at random points of random faces (plus misses)."""
    rng = np.random.default_rng(seed)
    v, f = np.asarray(vertices, np.float64), np.asarray(faces)
    chosen = rng.integers(0, f.shape[0], n)
    weights = rng.dirichlet([2, 2, 2], n)
    targets = np.einsum("nk,nkd->nd", weights, v[f[chosen]])
    origins = rng.normal(size=(n, 3))
    origins = origins / np.linalg.norm(origins, axis=1, keepdims=True) * rng.uniform(1.5, 3, (n, 1))
    directions = (targets - origins) * rng.uniform(0.01, 100, (n, 1))
    directions[: n // 8] = rng.normal(size=(n // 8, 3))  # some miss
    return jnp.asarray(origins, dtype), jnp.asarray(directions, dtype)


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_reference_conventions(implementation):
    vertices, faces = _sphere(jnp.float64)
    origins = jnp.array([[0.0, 0, 0], [0.0, 0, -3], [0.0, 0, -3], [5.0, 5, 0], [0.0, 0, 0], [0.0, 0, -3]])
    directions = jnp.array([[0.0, 0, 1], [0.0, 0, 7], [0.0, 0, -1], [1.0, 0, 0], [0.0, 0, 0], [0.0, 0, 1]])
    hit, distance, points, face_ids, normals = ray_mesh_intersect(vertices, faces, origins, directions, implementation=implementation)
    np.testing.assert_array_equal(hit, [True, True, False, False, False, True])
    np.testing.assert_allclose(distance[:2], [1.0, 2.0], rtol=1e-12)  # Euclidean, not in units of |d|
    np.testing.assert_allclose(points[1], [0, 0, -1], atol=1e-12)
    assert normals[0, 2] > 0.95 and normals[1, 2] < -0.95  # winding normals, not flipped toward the ray
    np.testing.assert_allclose(np.linalg.norm(normals[hit], axis=-1), 1, rtol=1e-12)
    missed = ~np.asarray(hit)
    assert np.all(np.isinf(distance[missed])) and np.all(np.asarray(points)[missed] == 0)
    assert np.all(np.asarray(normals)[missed] == 0) and np.all(np.asarray(face_ids)[missed] == -1)
    assert face_ids.dtype == jnp.int32 and hit.dtype == jnp.bool_
    # max_distance: the hit at 2.0 is a miss with max_distance 1.5.
    hit, distance, *_ = ray_mesh_intersect(vertices, faces, origins, directions, max_distance=1.5, implementation=implementation)
    np.testing.assert_array_equal(hit, [True, False, False, False, False, False])


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_rays_of_any_floating_dtype_against_either_mesh_dtype(implementation):
    # As the reference: any floating rays, whatever the mesh dtype; float32 arithmetic (float64
    # where rays and mesh are both float64); distances, points and normals in the rays' dtype.
    for mesh_dtype in (jnp.float32, jnp.float64):
        vertices, faces = _sphere(mesh_dtype)
        for ray_dtype, other in ((jnp.float16, jnp.bfloat16), (jnp.bfloat16, jnp.float32), (jnp.float32, jnp.float64), (jnp.float64, jnp.float16)):
            origins = jnp.array([[0.0, 0, 0], [0.0, 0, -3]], ray_dtype)
            directions = jnp.array([[0.0, 0, 1], [0.0, 0, 7]], other)  # directions of another dtype
            hit, distance, points, face_ids, normals = ray_mesh_intersect(vertices, faces, origins, directions, implementation=implementation)
            assert distance.dtype == points.dtype == normals.dtype == ray_dtype and face_ids.dtype == jnp.int32
            working = jnp.float64 if ray_dtype == mesh_dtype == jnp.float64 else jnp.float32
            tolerance = 4 * max(float(jnp.finfo(ray_dtype).eps), float(jnp.finfo(working).eps))
            np.testing.assert_array_equal(hit, [True, True])
            # (0, 0, +-1) are vertices of the icosphere: the hits are at 1 and 2, exactly.
            np.testing.assert_allclose(np.asarray(distance, np.float64), [1.0, 2.0], rtol=tolerance)
            np.testing.assert_allclose(np.asarray(points, np.float64), [[0, 0, 1], [0, 0, -1]], atol=tolerance)


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_non_finite_rays_miss_with_the_documented_encoding(implementation):
    # NaN or infinite origins and directions are misses: mask False, face -1, distance +inf, zero
    # point and normal (Warp wrote NaN points and normals for them); the finite rays still hit.
    vertices, faces = _sphere(jnp.float64)
    nan, inf = np.nan, np.inf
    origins = jnp.array([[nan, 0, 0], [inf, 0, 0], [0.0, 0, 0], [0.0, 0, 0], [0.0, -inf, 0], [0.0, 0, -3]])
    directions = jnp.array([[0.0, 0, 1], [0.0, 0, 1], [nan, 0, 1], [0.0, inf, 0], [0.0, 1, 0], [0.0, 0, 1]])
    hit, distance, points, face_ids, normals = ray_mesh_intersect(vertices, faces, origins, directions, implementation=implementation)
    np.testing.assert_array_equal(hit, [False] * 5 + [True])
    np.testing.assert_array_equal(np.asarray(distance)[:5], np.inf)
    np.testing.assert_array_equal(np.asarray(face_ids)[:5], -1)
    np.testing.assert_array_equal(np.asarray(points)[:5], 0.0)
    np.testing.assert_array_equal(np.asarray(normals)[:5], 0.0)
    np.testing.assert_allclose(np.asarray(points)[5], [0, 0, -1], atol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
def test_warp_matches_brute_force(dtype):
    vertices, faces = _sphere(dtype)
    origins, directions = _aimed_rays(vertices, faces, 600, 0, dtype)
    expected = ray_mesh_intersect(vertices, faces, origins, directions, implementation="jax")
    actual = ray_mesh_intersect(vertices, faces, origins, directions, implementation="warp")
    tol = 5e-5 if dtype == jnp.float32 else 1e-12
    np.testing.assert_array_equal(actual[0], expected[0])
    assert 400 < int(expected[0].sum()) < 600
    hit = np.asarray(expected[0])
    np.testing.assert_allclose(actual[1][hit], expected[1][hit], rtol=tol)
    np.testing.assert_allclose(actual[2], expected[2], atol=tol)
    # Face ids agree except for rays through a shared edge (then the hit point agrees anyway).
    assert np.mean(np.asarray(actual[3]) == np.asarray(expected[3])) > 0.98
    same = np.asarray(actual[3]) == np.asarray(expected[3])
    np.testing.assert_allclose(actual[4][same], expected[4][same], atol=tol)
    assert all(a.dtype == e.dtype for a, e in zip(actual, expected))


def test_batched_shapes_int64_indices_and_empty_rays():
    vertices, faces = _sphere(jnp.float64, 1)
    origins, directions = _aimed_rays(vertices, faces, 24, 1, jnp.float64)
    flat = ray_mesh_intersect(vertices, faces, origins, directions)
    shaped = ray_mesh_intersect(vertices, faces.reshape(-1).astype(jnp.int64), origins.reshape(2, 3, 4, 3), directions.reshape(2, 3, 4, 3))
    assert shaped[3].dtype == jnp.int64 and shaped[0].shape == (2, 3, 4) and shaped[2].shape == (2, 3, 4, 3)
    for a, b in zip(flat, shaped):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b).reshape(np.asarray(a).shape))
    for implementation in ("jax", "warp"):
        empty = ray_mesh_intersect(vertices, faces, jnp.zeros((0, 3)), jnp.zeros((0, 3)), implementation=implementation)
        assert [x.shape for x in empty] == [(0,), (0,), (0, 3), (0,), (0, 3)]


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_gradients_match_finite_differences(implementation):
    vertices, faces = _sphere(jnp.float64, 1)
    origins, directions = _aimed_rays(vertices, faces, 16, 2, jnp.float64)
    origins, directions = origins[2:], directions[2:]  # aimed rays only
    hit = ray_mesh_intersect(vertices, faces, origins, directions, implementation=implementation)[0]
    assert bool(jnp.all(hit))

    def hit_geometry(v, o, d):
        _, distance, points, _, normals = ray_mesh_intersect(v, faces, o, d, implementation=implementation)
        return distance, points, normals

    check_grads(hit_geometry, (vertices, origins, directions), order=1, modes=("rev", "fwd"), eps=1e-6)


def test_warp_and_jax_gradients_agree_under_jit_and_vmap():
    vertices, faces = _sphere(jnp.float64, 1)
    origins, directions = _aimed_rays(vertices, faces, 64, 3, jnp.float64)

    def loss(v, o, d, implementation):
        _, distance, points, _, _ = ray_mesh_intersect(v, faces, o, d, implementation=implementation)
        return jnp.sum(jnp.where(jnp.isfinite(distance), distance, 0)) + jnp.sum(points**2)

    grads = {impl: jax.grad(loss, argnums=(0, 1, 2))(vertices, origins, directions, impl) for impl in ("jax", "warp")}
    for a, b in zip(grads["jax"], grads["warp"]):
        np.testing.assert_allclose(a, b, atol=1e-10)
    # vmap over ray batches equals the loop (Warp runs the batch sequentially).
    batched = jax.vmap(lambda o, d: ray_mesh_intersect(vertices, faces, o, d)[1])(origins.reshape(4, 16, 3), directions.reshape(4, 16, 3))
    looped = jnp.stack([ray_mesh_intersect(vertices, faces, o, d)[1] for o, d in zip(origins.reshape(4, 16, 3), directions.reshape(4, 16, 3))])
    np.testing.assert_array_equal(batched, looped)
    # vmap over meshes: each design builds its own BVH inside the call.
    scaled = jax.vmap(lambda s: ray_mesh_intersect(vertices * s, faces, origins, directions)[1])(jnp.array([1.0, 1.2]))
    np.testing.assert_allclose(scaled, jnp.stack([looped.reshape(-1), ray_mesh_intersect(vertices * 1.2, faces, origins, directions)[1]]))


def test_prepared_bvh_round_trip():
    vertices, faces = _sphere(jnp.float32)
    origins, directions = _aimed_rays(vertices, faces, 100, 4, jnp.float32)
    *first, bvh = ray_mesh_intersect(vertices, faces, origins, directions, return_warp_mesh=True)
    assert isinstance(bvh, MeshBVH)
    again = ray_mesh_intersect(vertices, faces, origins, directions, warp_mesh=bvh)
    jitted = jax.jit(lambda b, o, d: ray_mesh_intersect(vertices, faces, o, d, warp_mesh=b))(bvh, origins, directions)
    for a, b, c in zip(first, again, jitted):
        np.testing.assert_array_equal(a, b) and np.testing.assert_array_equal(a, c)
    *_, same = ray_mesh_intersect(vertices, faces, origins, directions, warp_mesh=bvh, return_warp_mesh=True)
    assert same is bvh
    # The BVH is used for the search only; the hit geometry is replayed on the given vertices.
    moved = ray_mesh_intersect(vertices * 1.001, faces, origins, directions, warp_mesh=bvh.refit(vertices * 1.001))
    np.testing.assert_array_equal(moved[0], first[0])
    small_vertices, small_faces = _sphere(jnp.float32, 1)
    with pytest.raises(ValueError, match="warp_mesh"):
        ray_mesh_intersect(small_vertices, small_faces, origins, directions, warp_mesh=bvh)
    with pytest.raises(TypeError, match="warp_mesh"):
        ray_mesh_intersect(vertices, faces, origins, directions, warp_mesh=bvh.warp_mesh)
    with pytest.raises(TypeError, match="concrete"):
        jax.jit(lambda v: ray_mesh_intersect(v, faces, origins, directions, return_warp_mesh=True)[1])(vertices)


def test_traced_mesh_under_jit():
    vertices, faces = _sphere(jnp.float32)
    origins, directions = _aimed_rays(vertices, faces, 50, 5, jnp.float32)
    eager = ray_mesh_intersect(vertices, faces, origins, directions)
    traced = jax.jit(ray_mesh_intersect)(vertices, faces, origins, directions)
    for a, b in zip(eager, traced):  # fusion under jit changes float32 rounding
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-5)
    with pytest.raises(Exception, match=r"mesh_indices must lie in"):
        jax.block_until_ready(jax.jit(ray_mesh_intersect)(vertices, faces.at[0, 0].set(10**6), origins, directions))


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_errors(implementation):
    vertices, faces = _sphere(jnp.float32, 0)
    rays = jnp.zeros((4, 3), jnp.float32)
    call = lambda *a, **k: ray_mesh_intersect(*a, implementation=implementation, **k)  # noqa: E731
    with pytest.raises(TypeError, match="ray_origins"):
        call(vertices, faces, rays.astype(jnp.int32), rays)
    with pytest.raises(TypeError, match="ray_directions"):
        call(vertices, faces, rays, rays.astype(jnp.int32))
    with pytest.raises(TypeError, match="mesh_indices"):
        call(vertices, faces.astype(jnp.float32), rays, rays)
    with pytest.raises(ValueError, match="ray_directions"):
        call(vertices, faces, rays, rays[:2])
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        call(vertices, faces, rays[:, :2], rays[:, :2])
    with pytest.raises(ValueError, match="max_distance"):
        call(vertices, faces, rays, rays, max_distance=0.0)
    with pytest.raises(TypeError, match="max_distance"):
        call(vertices, faces, rays, rays, max_distance=True)
    with pytest.raises(TypeError, match="return_warp_mesh"):
        call(vertices, faces, rays, rays, return_warp_mesh=1)
    with pytest.raises(ValueError, match="mesh_indices"):
        call(vertices, faces.at[1, 1].set(12), rays, rays)
    with pytest.raises(ValueError, match="mesh_indices"):
        call(vertices, faces.reshape(-1)[:5], rays, rays)
    with pytest.raises(ValueError, match="mesh_vertices"):
        call(vertices[:0], faces, rays, rays)
    with pytest.raises(KeyError):
        ray_mesh_intersect(vertices, faces, rays, rays, implementation="embree")
    # A NaN vertex gave hits whose distance, point and normal disagreed: rejected.
    with pytest.raises(ValueError, match="ray_mesh_intersect: mesh_vertices must be finite"):
        call(vertices.at[0, 2].set(jnp.nan), faces, rays, rays)
