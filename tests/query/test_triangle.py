"""Point-triangle projection, ray-triangle intersection and normals against independent NumPy math."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import _geometry as _triangle

# Jitted once per module: op-by-op dispatch of the many small ops would dominate the test time.
closest_point_on_triangle = jax.jit(_triangle.closest_point_on_triangle)
ray_triangle_intersection = jax.jit(_triangle.ray_triangle_intersection)
triangle_normal = jax.jit(_triangle.triangle_normal)

DTYPES = [jnp.float32, jnp.float64]
TOL = {jnp.dtype(jnp.float32): 2e-5, jnp.dtype(jnp.float64): 1e-12}


def _closest_numpy(p, a, b, c):
    """Feature enumeration: interior projection (2x2 normal equations) or the best of 3 vertices / 3 edges."""
    e1, e2 = b - a, c - a
    gram = np.array([[e1 @ e1, e1 @ e2], [e1 @ e2, e2 @ e2]])
    candidates = [a, b, c]
    if abs(np.linalg.det(gram)) > 1e-300:
        u, v = np.linalg.solve(gram, [e1 @ (p - a), e2 @ (p - a)])
        if u >= 0 and v >= 0 and u + v <= 1:
            return a + u * e1 + v * e2
    for s, e in ((a, b), (a, c), (b, c)):
        d = e - s
        t = np.clip((p - s) @ d / (d @ d), 0, 1) if d @ d > 0 else 0.0
        candidates.append(s + t * d)
    return min(candidates, key=lambda q: np.sum((q - p) ** 2))


def _random_cases(rng, n):
    tri = rng.normal(size=(n, 3, 3))
    p = rng.normal(size=(n, 3)) * 1.5
    return p, tri[:, 0], tri[:, 1], tri[:, 2]


@pytest.mark.parametrize("dtype", DTYPES)
def test_closest_point_matches_feature_enumeration(dtype):
    rng = np.random.default_rng(0)
    p, a, b, c = _random_cases(rng, 400)
    point, weights = closest_point_on_triangle(*(jnp.asarray(x, dtype) for x in (p, a, b, c)))
    expected = np.stack([_closest_numpy(*args) for args in zip(p, a, b, c)])
    tol = TOL[jnp.dtype(dtype)]
    np.testing.assert_allclose(np.asarray(point, np.float64), expected, atol=10 * tol)
    w = np.asarray(weights, np.float64)
    assert np.all(w >= -tol) and np.allclose(w.sum(-1), 1, atol=tol)
    recombined = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    np.testing.assert_allclose(recombined, expected, atol=10 * tol)
    assert point.dtype == dtype and weights.dtype == dtype


def test_closest_point_regions_by_hand():
    a, b, c = jnp.array([0.0, 0, 0]), jnp.array([2.0, 0, 0]), jnp.array([0.0, 2, 0])
    queries = jnp.array([[0.5, 0.5, 3.0], [-1.0, -1.0, 0.0], [3.0, -1.0, 1.0], [1.0, -1.0, 0.0], [2.0, 2.0, 0.0], [-1.0, 1.0, 0.0]])
    point, weights = closest_point_on_triangle(queries, a, b, c)
    np.testing.assert_allclose(point, [[0.5, 0.5, 0], [0, 0, 0], [2, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], atol=1e-15)
    np.testing.assert_allclose(weights[1], [1, 0, 0]) and np.testing.assert_allclose(weights[4], [0, 0.5, 0.5])


@pytest.mark.parametrize("scale", [1e-30, 1e30, 1e150])
def test_closest_point_is_scale_invariant_float64(scale):
    rng = np.random.default_rng(1)
    p, a, b, c = _random_cases(rng, 50)
    unit, _ = closest_point_on_triangle(*(jnp.asarray(x) for x in (p, a, b, c)))
    scaled, _ = closest_point_on_triangle(*(jnp.asarray(x * scale) for x in (p, a, b, c)))
    np.testing.assert_allclose(np.asarray(scaled) / scale, unit, rtol=1e-12, atol=1e-12)


def test_closest_point_near_float_max_does_not_overflow():
    big = np.finfo(np.float32).max / 2
    p = jnp.asarray([[0.0, 0.0, 1.0]], jnp.float32) * big
    tri = [jnp.asarray(v, jnp.float32) * big for v in ([-1.0, -1, 0], [1.0, -1, 0], [0.0, 1, 0])]
    point, _ = closest_point_on_triangle(p, *tri)
    assert np.all(np.isfinite(np.asarray(point)))
    np.testing.assert_allclose(np.asarray(point, np.float64) / big, [[0, 0, 0]], atol=1e-6)


def _distance(p, a, b, c):
    q, _ = closest_point_on_triangle(p, a, b, c)
    return jnp.sqrt(jnp.sum((q - p) ** 2))


def test_closest_point_gradients_match_finite_differences():
    rng = np.random.default_rng(2)
    args = tuple(jnp.asarray(x) for x in _random_cases(rng, 40))
    check_grads(lambda *x: closest_point_on_triangle(*x)[0], args, order=1, modes=("rev", "fwd"), eps=1e-6)
    check_grads(jax.jit(jax.vmap(_distance)), args, order=1, modes=("rev",), eps=1e-6)


def test_distance_gradient_is_the_unit_offset():
    # Envelope theorem: d|p - q(p)| / dp = (p - q) / |p - q| in every region.
    rng = np.random.default_rng(3)
    p, a, b, c = (jnp.asarray(x) for x in _random_cases(rng, 200))
    grad = jax.jit(jax.vmap(jax.grad(_distance)))(p, a, b, c)
    q, _ = closest_point_on_triangle(p, a, b, c)
    offset = np.asarray(p - q)
    np.testing.assert_allclose(grad, offset / np.linalg.norm(offset, axis=-1, keepdims=True), atol=1e-10)


@pytest.mark.parametrize("dtype", DTYPES)
def test_degenerate_triangles_and_boundary_points_have_finite_gradients(dtype):
    cases = [
        ([0.3, 0.2, 1.0], [0, 0, 0], [1, 0, 0], [2, 0, 0]),  # collinear
        ([0.3, 0.2, 1.0], [1, 1, 1], [1, 1, 1], [1, 1, 1]),  # a point
        ([0.5, 0.5, 0.0], [0, 0, 0], [1, 0, 0], [0, 1, 0]),  # on the hypotenuse
        ([0.0, 0.0, 0.0], [0, 0, 0], [1, 0, 0], [0, 1, 0]),  # on a vertex
        ([0.2, 0.2, 0.0], [0, 0, 0], [1, 0, 0], [0, 1, 0]),  # inside, distance zero
    ]
    for case in cases:
        args = tuple(jnp.asarray(x, dtype) for x in case)
        value, weights = closest_point_on_triangle(*args)
        assert np.all(np.isfinite(value)) and np.all(np.isfinite(weights))
        grads = jax.grad(lambda *x: jnp.sum(closest_point_on_triangle(*x)[0] ** 2), argnums=(0, 1, 2, 3))(*args)
        assert all(np.all(np.isfinite(g)) for g in grads)
    point, _ = closest_point_on_triangle(*(jnp.asarray(x, dtype) for x in cases[0]))
    np.testing.assert_allclose(point, [0.3, 0, 0], atol=1e-6)


def test_closest_point_jit_vmap_and_broadcasting():
    rng = np.random.default_rng(4)
    p, a, b, c = (jnp.asarray(x) for x in _random_cases(rng, 30))
    direct = closest_point_on_triangle(p, a, b, c)
    jitted = jax.jit(closest_point_on_triangle)(p, a, b, c)
    mapped = jax.vmap(closest_point_on_triangle)(p, a, b, c)
    for x, y in ((direct, jitted), (direct, mapped)):
        np.testing.assert_allclose(x[0], y[0], atol=1e-14)
        np.testing.assert_allclose(x[1], y[1], atol=1e-14)
    grid, _ = closest_point_on_triangle(p[:, None], a[None], b[None], c[None])
    assert grid.shape == (30, 30, 3)
    np.testing.assert_allclose(jnp.diagonal(grid, axis1=0, axis2=1).T, direct[0], atol=1e-14)


# ---------------------------------------------------------------------------------------------
# Rays.


def _ray_numpy(o, d, a, b, c):
    matrix = np.stack([b - a, c - a, -d], axis=1)
    if abs(np.linalg.det(matrix)) < 1e-12:
        return np.inf, None
    u, v, t = np.linalg.solve(matrix, o - a)
    if u >= 0 and v >= 0 and u + v <= 1 and t >= 0:
        return t, np.array([1 - u - v, u, v])
    return np.inf, None


@pytest.mark.parametrize("dtype", DTYPES)
def test_ray_intersection_matches_linear_solve(dtype):
    rng = np.random.default_rng(5)
    n = 400
    tri = rng.normal(size=(n, 3, 3))
    o = rng.normal(size=(n, 3)) * 2
    target = np.einsum("nk,nkd->nd", rng.dirichlet([1, 1, 1], n) * 1.4 - 0.2, tri)  # some inside, some outside
    d = (target - o) * rng.uniform(0.1, 10, (n, 1)) * np.where(rng.uniform(size=(n, 1)) < 0.2, -1, 1)
    t, weights, hit = ray_triangle_intersection(*(jnp.asarray(x, dtype) for x in (o, d, tri[:, 0], tri[:, 1], tri[:, 2])))
    expected = [_ray_numpy(*args) for args in zip(o, d, tri[:, 0], tri[:, 1], tri[:, 2])]
    expected_t = np.array([e[0] for e in expected])
    tol = TOL[jnp.dtype(dtype)] * 50
    # Rays passing within rounding of an edge may go either way; compare the clear ones.
    clear = np.array([e[1] is None or np.min(e[1]) > 1e-3 for e in expected])
    clear &= np.array([e[1] is not None or _ray_margin(*args) > 1e-3 for e, args in zip(expected, zip(o, d, tri[:, 0], tri[:, 1], tri[:, 2]))])
    assert clear.sum() > 300
    np.testing.assert_array_equal(np.asarray(hit)[clear], np.isfinite(expected_t)[clear])
    hits = clear & np.isfinite(expected_t)
    np.testing.assert_allclose(np.asarray(t, np.float64)[hits], expected_t[hits], rtol=tol)
    np.testing.assert_allclose(np.asarray(weights, np.float64)[hits], np.stack([expected[i][1] for i in np.flatnonzero(hits)]), atol=tol)
    assert np.all(np.isinf(np.asarray(t)[~np.asarray(hit)])) and np.all(np.asarray(weights)[~np.asarray(hit)] == 0)


def _ray_margin(o, d, a, b, c):
    matrix = np.stack([b - a, c - a, -d], axis=1)
    u, v, t = np.linalg.solve(matrix, o - a)
    return min(abs(u), abs(v), abs(1 - u - v), abs(t) / (1 + abs(t)))


def test_ray_special_cases():
    a, b, c = jnp.array([0.0, 0, 0]), jnp.array([1.0, 0, 0]), jnp.array([0.0, 1, 0])
    origins = jnp.array([[0.2, 0.2, 1.0], [0.2, 0.2, 1.0], [0.2, 0.2, 1.0], [0.2, 0.2, 0.0], [-1.0, 0.2, 0.0], [0.2, 0.2, -1.0]])
    directions = jnp.array([[0.0, 0, -4], [0.0, 0, 0], [0.0, 0, 1], [0.0, 0, 1], [1.0, 0, 0], [0.0, 0, 1e-30]])
    t, _, hit = ray_triangle_intersection(origins, directions, a, b, c)
    np.testing.assert_array_equal(hit, [True, False, False, True, False, True])  # zero direction, behind, t=0, in-plane
    np.testing.assert_allclose(t[0], 0.25) and np.testing.assert_allclose(t[3], 0.0) and np.testing.assert_allclose(t[5], 1e30)


def test_ray_gradients_match_finite_differences():
    rng = np.random.default_rng(6)
    tri = rng.normal(size=(20, 3, 3))
    o = rng.normal(size=(20, 3)) * 2
    d = np.einsum("nk,nkd->nd", rng.dirichlet([3, 3, 3], 20), tri) - o
    args = tuple(jnp.asarray(x) for x in (o, d, tri[:, 0], tri[:, 1], tri[:, 2]))
    assert np.all(ray_triangle_intersection(*args)[2])

    def hit_point(o, d, a, b, c):
        t, _, _ = _triangle.ray_triangle_intersection(o, d, a, b, c)
        return o + t[:, None] * d

    check_grads(jax.jit(hit_point), args, order=1, modes=("rev", "fwd"), eps=1e-6)


def test_missed_rays_have_zero_finite_gradients():
    a, b, c = jnp.array([0.0, 0, 0]), jnp.array([1.0, 0, 0]), jnp.array([0.0, 1, 0])
    for o, d in (([5.0, 5.0, 1.0], [0.0, 0, -1]), ([0.2, 0.2, 1.0], [0.0, 0, 0]), ([0.2, 0.2, 1.0], [1.0, 0, 0])):
        g = jax.grad(lambda o, d: jnp.sum(jnp.where(jnp.isfinite(ray_triangle_intersection(o, d, a, b, c)[0]), 1.0, 0.0)
                                           + ray_triangle_intersection(o, d, a, b, c)[1]), argnums=(0, 1))(jnp.asarray(o), jnp.asarray(d))
        assert all(np.all(np.asarray(x) == 0) for x in g)


# ---------------------------------------------------------------------------------------------
# Normals.


@pytest.mark.parametrize("dtype", DTYPES)
def test_triangle_normal(dtype):
    rng = np.random.default_rng(7)
    tri = rng.normal(size=(100, 3, 3))
    n = triangle_normal(*(jnp.asarray(tri[:, k], dtype) for k in range(3)))
    expected = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    expected /= np.linalg.norm(expected, axis=-1, keepdims=True)
    np.testing.assert_allclose(np.asarray(n, np.float64), expected, atol=TOL[jnp.dtype(dtype)] * 10)
    tiny = triangle_normal(*(jnp.asarray(tri[0, k] * 1e-40, jnp.float64) for k in range(3)))
    np.testing.assert_allclose(tiny, expected[0], atol=1e-12)
    flat = jnp.asarray([[0.0, 0, 0], [1.0, 1, 1], [2.0, 2, 2]], dtype)
    assert np.all(np.asarray(triangle_normal(*flat)) == 0)
    g = jax.grad(lambda v: jnp.sum(triangle_normal(v[0], v[1], v[2])))(flat)
    assert np.all(np.isfinite(np.asarray(g)))


def test_triangle_normal_gradient():
    rng = np.random.default_rng(8)
    tri = tuple(jnp.asarray(x) for x in rng.normal(size=(3, 3)))
    check_grads(triangle_normal, tri, order=1, modes=("rev", "fwd"), eps=1e-6)
