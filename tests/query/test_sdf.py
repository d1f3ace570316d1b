"""signed_distance_field: values, signs (also on open and imperfect meshes), Warp vs JAX, gradients."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import icosphere, signed_distance_field
from geomjax.query.sdf import winding_numbers

DTYPES = [jnp.float32, jnp.float64]
IMPLEMENTATIONS = ["jax", "warp"]


def _sphere(dtype, subdivisions=2):
    mesh = icosphere(subdivisions, dtype=dtype)
    return mesh.points, jnp.asarray(mesh.cells, jnp.int32)


def _points(n, seed, dtype, low=0.2, high=1.8):
    """Points off the medial centre and off the surface (|p| in [low, 0.9] or [1.1, high])."""
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = np.where(rng.uniform(size=n) < 0.5, rng.uniform(low, 0.9, n), rng.uniform(1.1, high, n))
    return jnp.asarray(u * r[:, None], dtype)


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
@pytest.mark.parametrize("winding", [False, True])
def test_hand_checked_values(implementation, winding):
    vertices, faces = _sphere(jnp.float64, 3)
    points = jnp.array([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0], [0.0, 0.0, -0.25], [3.0, 0.0, 0.0]])
    sdf, closest, face_ids = signed_distance_field(vertices, faces, points, max_dist=1.5, use_sign_winding_number=winding, implementation=implementation)
    # The centre is equidistant from many faces: still inside (|value| = inscribed radius).
    assert -1.0 < float(sdf[0]) < -0.99
    np.testing.assert_allclose(sdf[1], 1.0, rtol=1e-12)  # (1, 0, 0) is a vertex
    np.testing.assert_allclose(closest[1], [1, 0, 0], atol=1e-12)
    assert float(sdf[2]) < -0.7
    assert np.isnan(sdf[3]) and np.all(np.isnan(closest[3])) and int(face_ids[3]) == -1  # beyond max_dist
    assert face_ids.dtype == jnp.int32 and sdf.dtype == jnp.float64


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_queries_of_any_floating_dtype_against_either_mesh_dtype(implementation):
    # As the reference: float64 (or float16, bfloat16) queries against a float32 mesh; float32
    # arithmetic (float64 where queries and mesh are both float64); outputs in the queries' dtype.
    for mesh_dtype in (jnp.float32, jnp.float64):
        vertices, faces = _sphere(mesh_dtype, 3)
        for dtype in (jnp.float16, jnp.bfloat16, jnp.float32, jnp.float64):
            points = jnp.array([[2.0, 0.0, 0.0], [0.0, 0.0, -0.25]], dtype)
            sdf, closest, face_ids = signed_distance_field(vertices, faces, points, implementation=implementation)
            assert sdf.dtype == closest.dtype == dtype and face_ids.dtype == jnp.int32
            working = jnp.float64 if dtype == mesh_dtype == jnp.float64 else jnp.float32
            tolerance = 4 * max(float(jnp.finfo(dtype).eps), float(jnp.finfo(working).eps))
            np.testing.assert_allclose(float(sdf[0]), 1.0, rtol=tolerance)  # (1, 0, 0) is a vertex
            np.testing.assert_allclose(np.asarray(closest[0], np.float64), [1, 0, 0], atol=tolerance)
            assert -0.76 < float(sdf[1]) < -0.7  # inside: the inscribed sphere of icosphere(3) has radius 0.995


@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("winding", [False, True])
def test_warp_matches_brute_force(dtype, winding):
    vertices, faces = _sphere(dtype)
    points = _points(500, 0, dtype)
    expected = signed_distance_field(vertices, faces, points, use_sign_winding_number=winding, implementation="jax")
    actual = signed_distance_field(vertices, faces, points, use_sign_winding_number=winding, implementation="warp")
    tol = 1e-5 if dtype == jnp.float32 else 1e-13
    np.testing.assert_allclose(actual[0], expected[0], rtol=tol, atol=tol)
    inside = np.linalg.norm(np.asarray(points, np.float64), axis=1) < 0.95
    np.testing.assert_array_equal(np.asarray(actual[0]) < 0, inside)
    same = np.asarray(actual[2]) == np.asarray(expected[2])
    assert same.mean() > 0.4  # the rest are ties at shared edges and vertices...
    np.testing.assert_allclose(actual[1], expected[1], atol=1e-4 if dtype == jnp.float32 else 1e-12)  # ... with one closest point
    assert all(a.dtype == e.dtype for a, e in zip(actual, expected))


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_normal_sign_is_right_in_the_middle_of_a_thin_slab(implementation):
    # A closed 2 x 2 x 0.01 box: its mid-plane is equidistant from the two big faces, where an
    # accumulation of every nearly-as-close face (Warp's own sign query) cancels out.
    corners = np.array([[x, y, z] for z in (-0.005, 0.005) for y in (-1, 1) for x in (-1, 1)], np.float64)
    quads = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    faces = jnp.asarray([t for a, b, c, d in quads for t in ((a, b, c), (a, c, d))], jnp.int32)
    vertices = jnp.asarray(corners)
    rng = np.random.default_rng(1)
    points = jnp.asarray(np.concatenate([rng.uniform(-0.9, 0.9, (50, 2)), np.zeros((50, 1))], axis=1))
    sdf, _, _ = signed_distance_field(vertices, faces, points, implementation=implementation)
    np.testing.assert_allclose(sdf, -0.005, rtol=1e-9)
    outside = signed_distance_field(vertices, faces, points + jnp.array([0.0, 0.0, 0.01]), implementation=implementation)[0]
    np.testing.assert_allclose(outside, 0.005, rtol=1e-9)


def _imperfect_sphere():
    vertices, faces = _sphere(jnp.float64, 3)
    rng = np.random.default_rng(2)
    f = np.asarray(faces)
    holes = rng.choice(f.shape[0], 12, replace=False)
    good = np.delete(f, holes, axis=0)
    bad = good.copy()
    flipped = rng.choice(good.shape[0], 40, replace=False)
    bad[flipped] = bad[flipped][:, [0, 2, 1]]
    return vertices, jnp.asarray(good), jnp.asarray(bad)


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_winding_sign_is_right_on_open_meshes_with_flipped_faces(implementation):
    vertices, good, bad = _imperfect_sphere()
    rng = np.random.default_rng(3)
    points = jnp.asarray(rng.uniform(-1.3, 1.3, (1500, 3)))
    # Ground truth: exact winding numbers of the consistently oriented mesh with its holes.
    truth = np.asarray(winding_numbers(points, vertices[good]))
    clear = np.abs(truth - 0.5) > 0.1
    assert clear.mean() > 0.9
    raw = np.asarray(winding_numbers(points, vertices[bad]))
    assert np.any((raw > 0.5) != (truth > 0.5))  # the flipped faces do break a naive winding number
    sdf, _, _ = signed_distance_field(vertices, bad, points, use_sign_winding_number=True, implementation=implementation)
    np.testing.assert_array_equal((np.asarray(sdf) < 0)[clear], (truth > 0.5)[clear])
    radius = np.linalg.norm(np.asarray(points), axis=1)
    np.testing.assert_array_equal((np.asarray(sdf) < 0)[radius < 0.9], True)
    np.testing.assert_array_equal((np.asarray(sdf) < 0)[radius > 1.1], False)


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_gradients(implementation):
    vertices, faces = _sphere(jnp.float64, 1)
    points = _points(12, 4, jnp.float64, low=0.6, high=1.4)

    def sdf_and_closest(v, p):
        sdf, closest, _ = signed_distance_field(v, faces, p, implementation=implementation)
        return sdf, closest

    check_grads(sdf_and_closest, (vertices, points), order=1, modes=("rev", "fwd"), eps=1e-6)
    # d sdf / dp = sign * (p - q) / |p - q|.
    grad = jax.grad(lambda p: jnp.sum(signed_distance_field(vertices, faces, p, implementation=implementation)[0]))(points)
    sdf, closest, _ = signed_distance_field(vertices, faces, points, implementation=implementation)
    offset = np.asarray(points - closest)
    expected = np.sign(np.asarray(sdf))[:, None] * offset / np.linalg.norm(offset, axis=1, keepdims=True)
    np.testing.assert_allclose(grad, expected, atol=1e-12)


def test_warp_and_jax_gradients_agree_jit_vmap_and_traced_mesh():
    vertices, faces = _sphere(jnp.float64, 2)
    points = _points(64, 5, jnp.float64)

    def loss(v, p, implementation):
        sdf, closest, _ = signed_distance_field(v, faces, p, implementation=implementation)
        return jnp.sum(sdf**2) + jnp.sum(closest)

    jax_grads = jax.grad(loss, argnums=(0, 1))(vertices, points, "jax")
    warp_grads = jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2)(vertices, points, "warp")
    for a, b in zip(jax_grads, warp_grads):
        np.testing.assert_allclose(a, b, atol=1e-10)
    batched = jax.vmap(lambda p: signed_distance_field(vertices, faces, p)[0])(points.reshape(4, 16, 3))
    np.testing.assert_allclose(batched.reshape(-1), signed_distance_field(vertices, faces, points)[0], rtol=1e-14)
    shaped = signed_distance_field(vertices, faces.reshape(-1).astype(jnp.int64), points.reshape(2, 32, 3))
    assert shaped[0].shape == (2, 32) and shaped[1].shape == (2, 32, 3) and shaped[2].dtype == jnp.int64


@pytest.mark.parametrize("implementation", IMPLEMENTATIONS)
def test_non_finite_and_empty_points(implementation):
    vertices, faces = _sphere(jnp.float32, 1)
    points = jnp.asarray([[np.nan, 0, 0], [np.inf, 0, 0], [0.0, 0.0, 2.0]], jnp.float32)
    sdf, closest, face_ids = signed_distance_field(vertices, faces, points, implementation=implementation)
    assert np.all(np.isnan(sdf[:2])) and np.all(np.asarray(face_ids[:2]) == -1)
    np.testing.assert_allclose(sdf[2], 1.0, rtol=1e-6)
    empty = signed_distance_field(vertices, faces, jnp.zeros((0, 3), jnp.float32), implementation=implementation)
    assert [x.shape for x in empty] == [(0,), (0, 3), (0,)]


def test_errors():
    vertices, faces = _sphere(jnp.float32, 0)
    points = jnp.zeros((4, 3), jnp.float32)
    with pytest.raises(TypeError, match="input_points"):
        signed_distance_field(vertices, faces, points.astype(jnp.int32))
    with pytest.raises(TypeError, match="mesh_vertices"):
        signed_distance_field(vertices.astype(jnp.float16), faces, points.astype(jnp.float16))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        signed_distance_field(vertices, faces, points[:, :2])
    with pytest.raises(ValueError, match="max_dist"):
        signed_distance_field(vertices, faces, points, max_dist=-1.0)
    with pytest.raises(ValueError, match="max_dist"):
        signed_distance_field(vertices, faces, points, max_dist=float("inf"))
    with pytest.raises(TypeError, match="use_sign_winding_number"):
        signed_distance_field(vertices, faces, points, use_sign_winding_number=None)
    with pytest.raises(ValueError, match="mesh_indices"):
        signed_distance_field(vertices, faces.at[0, 0].set(-3), points)
    with pytest.raises(ValueError, match="mesh_indices"):
        signed_distance_field(vertices, faces.reshape(-1)[:4], points)
    with pytest.raises(KeyError):
        signed_distance_field(vertices, faces, points, implementation="open3d")
    # A NaN vertex flipped signs at queries far from it: non-finite vertices are rejected.
    for implementation in IMPLEMENTATIONS:
        with pytest.raises(ValueError, match="signed_distance_field: mesh_vertices must be finite"):
            signed_distance_field(vertices.at[0, 1].set(jnp.nan), faces, points, implementation=implementation)
    with pytest.raises(Exception, match="signed_distance_field: mesh_vertices must be finite"):  # traced: JAX's runtime error
        jax.block_until_ready(jax.jit(lambda v: signed_distance_field(v, faces, points))(vertices.at[3, 0].set(jnp.inf)))
    with pytest.raises(Exception, match="mesh_indices must lie in"):
        jax.block_until_ready(jax.jit(signed_distance_field)(vertices, faces.at[0, 0].set(99), points))
