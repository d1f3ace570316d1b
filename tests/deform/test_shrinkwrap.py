"""shrinkwrap_points: closest-point projection onto the nearest valid target triangle."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from geomjax import build_bvh, icosphere, shrinkwrap_points
from geomjax.deform.shrinkwrap import _nearest_faces_warp, nearest_faces_jax, valid_triangles
from geomjax.query.bvh import closest_faces_brute_force

BACKENDS = ["jax", "warp"]
DTYPES = [jnp.float32, jnp.float64]
# Runtime checks under jit (equinox.error_if) raise JaxRuntimeError (a RuntimeError) on a first
# run and a ValueError from JAX's C++ dispatch on later runs; both carry the message.
TRACED_ERRORS = (RuntimeError, ValueError)

SQUARE = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
SQUARE_FACES = np.array([[0, 1, 2], [0, 2, 3]])


def _sphere(subdivisions=2, dtype=jnp.float64):
    mesh = icosphere(subdivisions, dtype=dtype)
    return mesh.points, jnp.asarray(mesh.cells, jnp.int32)


def _shell_points(num, dtype=jnp.float64, seed=0, low=0.7, high=1.4):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(num, 3))
    x *= rng.uniform(low, high, (num, 1)) / np.linalg.norm(x, axis=1, keepdims=True)
    return jnp.asarray(x, dtype)


def _interior_queries(vertices, faces, seed=0, height=0.2):
    """Points over face interiors (away from region boundaries and ties): FD-safe."""
    rng = np.random.default_rng(seed)
    v, f = np.asarray(vertices), np.asarray(faces)
    pick = rng.choice(len(f), 6, replace=False)
    weights = rng.dirichlet([4.0, 4.0, 4.0], 6)
    tri = v[f[pick]]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return jnp.asarray(np.einsum("nk,nkd->nd", weights, tri) + height * normal, vertices.dtype)


# ---------------------------------------------------------------------------------------------
# Values.


@pytest.mark.parametrize("implementation", BACKENDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_square_by_hand(implementation, dtype):
    target, faces = jnp.asarray(SQUARE, dtype), jnp.asarray(SQUARE_FACES)
    points = jnp.asarray([[0.25, 0.5, 2.0], [2.0, 0.5, -1.0], [-1.0, -2.0, 0.5], [0.5, 0.5, 0.0]], dtype)
    out = shrinkwrap_points(points, target, faces, implementation=implementation)
    np.testing.assert_allclose(out, [[0.25, 0.5, 0], [1, 0.5, 0], [0, 0, 0], [0.5, 0.5, 0]], atol=1e-6)
    # The offset follows the winding of the selected face (both faces point to +z here).
    out = shrinkwrap_points(points, target, faces, offset=0.25, implementation=implementation)
    np.testing.assert_allclose(out[:, 2], 0.25, atol=1e-6)
    flipped = shrinkwrap_points(points, target, faces[:, ::-1], offset=0.25, implementation=implementation)
    np.testing.assert_allclose(flipped[:, 2], -0.25, atol=1e-6)
    assert out.dtype == dtype


def test_projection_onto_sphere_lands_on_the_surface():
    # The default (Warp) search; the JAX search gives the same faces (test below).
    implementation = "warp"
    vertices, faces = _sphere(2)
    points = _shell_points(200)
    out = shrinkwrap_points(points, vertices, faces, implementation=implementation)
    # Independent reference: the minimum over all faces of the projection distance.
    _, d2 = closest_faces_brute_force(points, vertices, faces)
    np.testing.assert_allclose(np.linalg.norm(out - points, axis=1), np.sqrt(d2), rtol=1e-9, atol=1e-12)
    # Projected points are fixed points.
    np.testing.assert_allclose(shrinkwrap_points(out, vertices, faces, implementation=implementation), out, atol=1e-12)


@pytest.mark.parametrize("dtype", DTYPES)
def test_bvh_search_equals_brute_force(dtype):
    vertices, faces = _sphere(2, dtype)
    points = jnp.concatenate([_shell_points(600, dtype, seed=1), _shell_points(100, dtype, seed=2, low=0.0, high=3.0)])
    valid = valid_triangles(vertices, faces)
    brute = np.asarray(jax.jit(nearest_faces_jax)(points, vertices, faces, valid))
    search = jax.jit(lambda p, v, f, ok, b: _nearest_faces_warp(p, v, f, ok, None, b))
    bvh = np.asarray(search(points, vertices, faces, valid, None))
    prebuilt = np.asarray(search(points, vertices, faces, valid, build_bvh(vertices, faces)))
    np.testing.assert_array_equal(bvh, prebuilt)
    if dtype == jnp.float64:
        np.testing.assert_array_equal(bvh, brute)
    else:
        # float32: a face may differ only where two features are equally near up to rounding.
        differ = np.nonzero(bvh != brute)[0]
        assert len(differ) <= 3
        v, f, p = np.asarray(vertices, np.float64), np.asarray(faces), np.asarray(points, np.float64)
        for k in differ:
            d_bvh, d_brute = (np.linalg.norm(p[k] - _closest_numpy(p[k], v[f[i]])) for i in (bvh[k], brute[k]))
            assert abs(d_bvh - d_brute) <= 1e-6 * (1 + d_bvh)


def _closest_numpy(p, tri):
    """Closest point on a triangle by dense enumeration of its features (independent check)."""
    a, b, c = tri
    n = np.cross(b - a, c - a)
    q = p - np.dot(p - a, n) / np.dot(n, n) * n
    candidates = []
    weights = np.linalg.lstsq(np.stack([b - a, c - a], 1), q - a, rcond=None)[0]
    if weights.min() >= 0 and weights.sum() <= 1:
        candidates.append(q)
    for u, v in ((a, b), (b, c), (c, a)):
        t = np.clip(np.dot(p - u, v - u) / np.dot(v - u, v - u), 0, 1)
        candidates.append(u + t * (v - u))
    return min(candidates, key=lambda z: np.linalg.norm(p - z))


@pytest.mark.parametrize("implementation", BACKENDS)
def test_ties_at_shared_vertices_and_edges_go_to_the_lowest_face(implementation):
    vertices, faces = _sphere(1)
    v, f = np.asarray(vertices), np.asarray(faces)
    valid = valid_triangles(vertices, faces)
    search = jax.jit(nearest_faces_jax if implementation == "jax" else lambda *a: _nearest_faces_warp(*a, None, None))
    # Straight out from a vertex: every face around it is at the same distance.
    for vertex in (0, 5, 17):
        point = jnp.asarray(v[vertex][None] * 1.5)
        expected = np.nonzero((f == vertex).any(axis=1))[0].min()
        assert int(search(point, vertices, faces, valid)[0]) == expected
    # Out from an edge midpoint: the two faces sharing the edge tie.
    edge = f[7, :2]
    point = jnp.asarray(((v[edge[0]] + v[edge[1]]) / 2 * 1.5)[None])
    sharing = np.nonzero((f == edge[0]).any(axis=1) & (f == edge[1]).any(axis=1))[0]
    assert int(search(point, vertices, faces, valid)[0]) == sharing.min()


@pytest.mark.parametrize("implementation", BACKENDS)
def test_float64_near_ties_are_resolved_exactly(implementation):
    # Two parallel unit squares far from the origin (float32 cannot tell them apart), the
    # nearer one listed last: a query midway shifted by 1e-9 must pick the nearer one.
    shift = 1e7
    lower = SQUARE + [shift, shift, 0.0]
    upper = SQUARE + [shift, shift, 1.0]
    target = jnp.asarray(np.concatenate([lower, upper]))
    faces = jnp.asarray(np.concatenate([SQUARE_FACES, SQUARE_FACES + 4]))
    for delta, expected_z in ((1e-9, 1.0), (-1e-9, 0.0)):
        point = jnp.asarray([[shift + 0.3, shift + 0.6, 0.5 + delta]])
        out = shrinkwrap_points(point, target, faces, implementation=implementation)
        np.testing.assert_allclose(out[0, 2], expected_z, atol=1e-12)
    # An exact tie keeps the lowest face index (the lower square), for both dtypes.
    for dtype in DTYPES:
        point = jnp.asarray([[shift + 0.3, shift + 0.6, 0.5]], dtype)
        out = shrinkwrap_points(point, target.astype(dtype), faces, offset=0.1, implementation=implementation)
        np.testing.assert_allclose(out[0, 2], 0.1, atol=1e-3)


def _triangle(z, size, dtype):
    return [[-size, -size, z], [size, -size, z], [0.0, size, z]]


@pytest.mark.parametrize("implementation", BACKENDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_extreme_coordinates_keep_projections_and_face_order(implementation, dtype):
    eps, huge = float(jnp.finfo(dtype).eps), float(jnp.finfo(dtype).max) / 1.2
    faces = jnp.asarray([[0, 1, 2]], jnp.int32)

    def wrap(points, targets, target_faces=faces):
        return shrinkwrap_points(jnp.asarray(points, dtype), jnp.asarray(targets, dtype), target_faces, implementation=implementation)

    # A triangle whose edges span opposite signs near the largest float: its edges overflow
    # when subtracted directly. In-plane projections, to rounding of the triangle's size.
    out = np.asarray(wrap([[0.0, 0.0, 1.0], [huge / 2, -huge / 2, 5.0]], _triangle(0.0, huge, dtype)), np.float64)
    np.testing.assert_allclose(out, [[0.0, 0.0, 0.0], [huge / 2, -huge / 2, 0.0]], rtol=0, atol=8 * eps * huge)
    # 1e20 (float32: beyond sqrt(max)) from a unit triangle along its normal: the tangential
    # position is kept, and the derivative is the in-plane identity.
    unit = jnp.asarray(_triangle(0.0, 1.0, dtype), dtype)
    far = jnp.asarray([[0.25, 0.25, 1e20], [0.1, -0.2, -1e20]], dtype)
    np.testing.assert_allclose(np.asarray(wrap(far, unit)), [[0.25, 0.25, 0.0], [0.1, -0.2, 0.0]], rtol=0, atol=4 * eps)
    gradient = jax.grad(lambda p: jnp.sum(wrap(p, unit)))(far)
    np.testing.assert_allclose(np.asarray(gradient), [[1.0, 1.0, 0.0]] * 2, rtol=0, atol=4 * eps)
    # Distances whose squares overflow still order the faces: the nearer triangle (index 1)
    # wins at a tenth and at half of the largest coordinate.
    two = jnp.asarray([[0, 1, 2], [3, 4, 5]], jnp.int32)
    for near, query in ((huge / 10, huge / 5), (huge / 2, huge / 1.5)):
        targets = _triangle(0.0, 1.0, dtype) + _triangle(near, 1.0, dtype)
        out = np.asarray(wrap([[0.0, 0.0, query]], targets, two), np.float64)
        np.testing.assert_allclose(out, [[0.0, 0.0, near]], rtol=4 * eps, atol=0)


@pytest.mark.parametrize("implementation", BACKENDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_skinny_and_multiscale_targets(implementation, dtype):
    eps = float(jnp.finfo(dtype).eps)
    # The skinniest triangle the validity rule keeps (|AB x AC| > eps longest^2), with aspect
    # 1e7 in float64 (2e6 in float32): interior projections exact, derivative the in-plane identity.
    height = 1e-7 if dtype == jnp.float64 else 5e-7
    skinny = jnp.asarray([[0.0, 0, 0], [1, 0, 0], [0.5, height, 0]], dtype)
    faces = jnp.asarray([[0, 1, 2]], jnp.int32)
    assert bool(valid_triangles(skinny, faces)[0])
    inside = jnp.asarray([[0.5, 0.5 * height, 0.3], [0.25, 0.25 * height, -0.1]], dtype)
    out = shrinkwrap_points(inside, skinny, faces, implementation=implementation)
    np.testing.assert_allclose(np.asarray(out)[:, :2], np.asarray(inside)[:, :2], rtol=4 * eps, atol=0)
    np.testing.assert_allclose(np.asarray(out)[:, 2], 0.0, rtol=0, atol=4 * eps)  # moved along the normal: rounding of p
    jacobian = jax.jacobian(lambda p: shrinkwrap_points(p, skinny, faces, implementation=implementation)[0])(inside[:1])
    np.testing.assert_allclose(np.asarray(jacobian)[:, 0], np.diag([1.0, 1.0, 0.0]), rtol=0, atol=16 * eps)
    # Far-apart targets of very different sizes: a query at the millimetre triangle keeps its
    # local position (no loss to the metre triangle a million units away).
    targets = jnp.asarray(_triangle(0.0, 1e-3, dtype) + [[1e6 + x, 1e6 + y, z] for x, y, z in _triangle(0.0, 1.0, dtype)], dtype)
    two = jnp.asarray([[0, 1, 2], [3, 4, 5]], jnp.int32)
    queries = jnp.asarray([[2e-4, 3e-4, 1e-4], [1e6 + 0.2, 1e6 + 0.3, 0.5]], dtype)
    out = np.asarray(shrinkwrap_points(queries, targets, two, implementation=implementation), np.float64)
    expected = np.asarray(queries, np.float64) * [1, 1, 0]
    error = np.abs(out - expected)  # to rounding of each query's own coordinates
    assert np.all(error <= 4 * eps * np.abs(np.asarray(queries, np.float64))), error


@pytest.mark.parametrize("implementation", BACKENDS)
def test_invalid_triangles_are_ignored(implementation):
    target = np.concatenate([SQUARE, [[0.5, 0.5, 0.9], [0.6, 0.5, 0.9], [0.7, 0.5, 0.9], [np.nan, 0, 1], [0.5, 0.4, 1.0]]])
    faces = np.concatenate([SQUARE_FACES, [[4, 5, 6], [7, 8, 4], [4, 4, 4], [8, 4, 8]]])
    points = jnp.asarray([[0.5, 0.5, 1.0], [0.2, 0.7, 0.8]])
    valid = valid_triangles(jnp.asarray(target), jnp.asarray(faces))
    np.testing.assert_array_equal(valid, [True, True, False, False, False, False])
    out = shrinkwrap_points(points, jnp.asarray(target), jnp.asarray(faces), implementation=implementation)
    clean = shrinkwrap_points(points, jnp.asarray(SQUARE), jnp.asarray(SQUARE_FACES), implementation=implementation)
    np.testing.assert_array_equal(out, clean)


@pytest.mark.parametrize("implementation", BACKENDS)
@pytest.mark.parametrize("dtype", DTYPES)
def test_max_distance_gate_is_strict_on_the_unoffset_distance(implementation, dtype):
    target, faces = jnp.asarray(SQUARE, dtype), jnp.asarray(SQUARE_FACES)
    points = jnp.asarray([[0.5, 0.5, 1.0], [0.5, 0.5, 0.75], [3.0, 0.5, 0.0]], dtype)
    out = shrinkwrap_points(points, target, faces, offset=0.5, max_distance=1.0, implementation=implementation)
    np.testing.assert_array_equal(out[0], points[0])  # distance exactly 1: unchanged
    np.testing.assert_allclose(out[1], [0.5, 0.5, 0.5], atol=1e-6)  # gate ignores the offset
    np.testing.assert_array_equal(out[2], points[2])  # distance 2
    out = shrinkwrap_points(points, target, faces, max_distance=1.0 + 1e-6, implementation=implementation)
    np.testing.assert_allclose(out[0], [0.5, 0.5, 0.0], atol=1e-6)


def test_weights_bool_float_and_batches():
    # Weights act after the search, the same way for both backends.
    implementation = "warp"
    vertices, faces = _sphere(1)
    points = jnp.stack([_shell_points(5, seed=3), _shell_points(5, seed=4)])
    full = shrinkwrap_points(points, vertices, faces, offset=0.05, implementation=implementation)
    mask = jnp.array([[True, False, True, False, True], [False, False, True, True, True]])
    out = shrinkwrap_points(points, vertices, faces, offset=0.05, point_weights=mask, implementation=implementation)
    # A kept point is x + (p - x), not p itself: equal to a rounding of the coordinates' scale.
    atol = 4 * float(jnp.finfo(points.dtype).eps) * float(jnp.abs(full).max())
    np.testing.assert_allclose(out, jnp.where(mask[..., None], full, points), rtol=0, atol=atol)
    np.testing.assert_array_equal(out[~mask], points[~mask])  # a masked-out point is untouched
    w = jnp.asarray(np.random.default_rng(0).uniform(-0.5, 2.0, (2, 5)))
    out = shrinkwrap_points(points, vertices, faces, offset=0.05, point_weights=w, implementation=implementation)
    np.testing.assert_allclose(out, (1 - w[..., None]) * points + w[..., None] * full, atol=1e-12)


@pytest.mark.parametrize("implementation", BACKENDS)
def test_empty_points(implementation):
    vertices, faces = _sphere(0)
    for shape in ((0, 3), (2, 0, 3)):
        out = shrinkwrap_points(jnp.zeros(shape), vertices, faces, implementation=implementation)
        assert out.shape == shape
    grads = jax.grad(lambda t: shrinkwrap_points(jnp.zeros((0, 3)), t, faces, implementation=implementation).sum())(vertices)
    np.testing.assert_array_equal(grads, 0)


# ---------------------------------------------------------------------------------------------
# Transformations and gradients.


def test_gradients_match_finite_differences():
    # The replay is shared by both backends (their gradients agree: next test).
    vertices, faces = _sphere(1)
    points = _interior_queries(vertices, faces)
    weights = jnp.linspace(0.3, 1.2, points.shape[0])

    def f(x, t, offset, w):
        return shrinkwrap_points(x, t, faces, offset=offset, point_weights=w)

    check_grads(f, (points, vertices, jnp.asarray(0.1), weights), order=1, modes=("rev",), eps=1e-6)


def test_gradients_agree_between_backends_also_under_vmap():
    vertices, faces = _sphere(1)
    points = jnp.stack([_shell_points(30, seed=5), _shell_points(30, seed=6)])
    offset = jnp.asarray(0.05)

    def loss(implementation):
        def f(x, t, offset):
            return jnp.sum(jnp.sin(3 * shrinkwrap_points(x, t, faces, offset=offset, implementation=implementation)))

        return f

    batched = jax.grad(loss("jax"), argnums=(0, 1, 2))(points, vertices, offset)
    per_design = jax.vmap(jax.grad(loss("warp"), argnums=(0, 1, 2)), in_axes=(0, None, None))(points, vertices, offset)
    np.testing.assert_allclose(per_design[0], batched[0], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(per_design[1].sum(0), batched[1], rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(per_design[2].sum(0), batched[2], rtol=1e-10, atol=1e-12)
    assert np.abs(batched[1]).max() > 0 and np.abs(batched[2]) > 0


def test_jit_vmap_jvp_equal_eager():
    # The default (Warp) search; the JAX search is plain JAX and jit-tested below.
    implementation = "warp"
    vertices, faces = _sphere(1)
    points = jnp.stack([_shell_points(6, seed=7), _shell_points(6, seed=8), _shell_points(6, seed=9)])

    def f(x, t):
        return shrinkwrap_points(x, t, faces, offset=0.02, max_distance=0.5, implementation=implementation)

    eager = f(points, vertices)  # already jitted inside; user-level jit is covered by the bvh tests
    np.testing.assert_allclose(jax.vmap(f, in_axes=(0, None))(points, vertices), eager, atol=1e-12)
    tangent = jnp.ones_like(points)
    _, jvp = jax.jvp(lambda x: f(x, vertices), (points,), (tangent,))
    vjp = jax.vjp(lambda x: f(x, vertices), points)[1]
    # <J t, s> == <t, J^T s> for s = J t.
    np.testing.assert_allclose(jnp.vdot(jvp, jvp), jnp.vdot(tangent, vjp(jvp)[0]), rtol=1e-10)


def test_prebuilt_bvh_reuse_and_refit():
    vertices, faces = _sphere(2)
    bvh = build_bvh(vertices, faces)
    points = _shell_points(200)  # the shapes of test_projection_onto_sphere: a cached compile
    run = jax.jit(lambda x, t, b: shrinkwrap_points(x, t, faces, offset=0.03, bvh=b))
    np.testing.assert_allclose(run(points, vertices, bvh), shrinkwrap_points(points, vertices, faces, offset=0.03), atol=1e-12)
    moved = vertices * 1.3
    np.testing.assert_allclose(
        run(points, moved, bvh.refit(moved)), shrinkwrap_points(points, moved, faces, offset=0.03, implementation="jax"), atol=1e-12
    )


# ---------------------------------------------------------------------------------------------
# Errors.


def test_type_errors():
    target, faces = jnp.asarray(SQUARE), jnp.asarray(SQUARE_FACES)
    points = jnp.zeros((2, 3))
    with pytest.raises(TypeError, match="points"):
        shrinkwrap_points(jnp.zeros((2, 3), jnp.int32), target, faces)
    with pytest.raises(TypeError, match="target_points must have the same dtype"):
        shrinkwrap_points(points, target.astype(jnp.float32), faces)
    with pytest.raises(TypeError, match="target_faces"):
        shrinkwrap_points(points, target, faces.astype(jnp.int16))
    with pytest.raises(TypeError, match="offset"):
        shrinkwrap_points(points, target, faces, offset=True)
    with pytest.raises(TypeError, match="offset"):
        shrinkwrap_points(points, target, faces, offset=jnp.asarray(0.1, jnp.float32))
    with pytest.raises(TypeError, match="max_distance"):
        shrinkwrap_points(points, target, faces, max_distance="1")
    with pytest.raises(TypeError, match="point_weights"):
        shrinkwrap_points(points, target, faces, point_weights=jnp.ones(2, jnp.int32))
    with pytest.raises(TypeError, match="bvh"):
        shrinkwrap_points(points, target, faces, bvh="mesh")


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"points": jnp.zeros((2, 2))}, "3 coordinates"),
        ({"target_points": jnp.zeros((2, 4, 3))}, "target_points must have shape"),
        ({"target_faces": jnp.zeros((2, 4), jnp.int32)}, "target_faces must have shape"),
        ({"target_faces": jnp.zeros((0, 3), jnp.int32)}, "at least one triangle"),
        ({"target_faces": jnp.array([[0, 1, 4]])}, r"in \[0, 4\)"),
        ({"target_faces": jnp.array([[0, -1, 2]])}, r"in \[0, 4\)"),
        ({"points": jnp.array([[0.0, jnp.nan, 0.0]])}, "points must be finite"),
        ({"target_faces": jnp.array([[0, 1, 1]])}, "no valid triangle"),
        ({"offset": float("nan")}, "offset must be finite"),
        ({"offset": jnp.asarray(jnp.inf)}, "offset must be finite"),
        ({"offset": jnp.zeros(1)}, "0-d array"),
        ({"max_distance": 0.0}, "max_distance must be positive"),
        ({"max_distance": float("inf")}, "max_distance must be finite"),
        ({"point_weights": jnp.ones(3)}, "point_weights must have shape"),
        ({"bvh": "prebuilt"}, "bvh"),
    ],
)
def test_value_errors(kwargs, match):
    args = {"points": jnp.zeros((2, 3)), "target_points": jnp.asarray(SQUARE), "target_faces": jnp.asarray(SQUARE_FACES)}
    options = {k: v for k, v in kwargs.items() if k not in args}
    args.update({k: v for k, v in kwargs.items() if k in args})
    if "bvh" in options:
        options["bvh"] = build_bvh(jnp.asarray(SQUARE[:3]), jnp.asarray(SQUARE_FACES[:1]))
    with pytest.raises(ValueError, match=match):
        shrinkwrap_points(args["points"], args["target_points"], args["target_faces"], **options)


def test_implementation_errors():
    target, faces = jnp.asarray(SQUARE), jnp.asarray(SQUARE_FACES)
    with pytest.raises(KeyError):
        shrinkwrap_points(jnp.zeros((1, 3)), target, faces, implementation="cuda")
    out = shrinkwrap_points(jnp.ones((1, 3)), target, faces, implementation="torch")
    np.testing.assert_allclose(out, [[1.0, 1.0, 0.0]])


@pytest.mark.parametrize("implementation", BACKENDS)
def test_traced_bad_values_raise_at_run_time_without_crashing(implementation):
    target = jnp.asarray(SQUARE)
    run = jax.jit(lambda x, t, f: shrinkwrap_points(x, t, f, implementation=implementation))
    with pytest.raises(TRACED_ERRORS, match="target_faces indices must be in"):
        jax.block_until_ready(run(jnp.zeros((2, 3)), target, jnp.array([[0, 1, 9], [0, 2, 3]])))
    with pytest.raises(TRACED_ERRORS, match="points must be finite"):
        jax.block_until_ready(run(jnp.full((2, 3), jnp.inf), target, jnp.asarray(SQUARE_FACES)))
    with pytest.raises(TRACED_ERRORS, match="no valid triangle"):
        jax.block_until_ready(run(jnp.zeros((2, 3)), jnp.zeros((4, 3)), jnp.asarray(SQUARE_FACES)))


@pytest.mark.parametrize("implementation", BACKENDS)
@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    p_shape=st.sampled_from([(0, 3), (3, 3), (2, 3, 3), (3, 2), (3,)]),
    t_shape=st.sampled_from([(4, 3), (0, 3), (2, 4, 3), (4, 2)]),
    dtype=st.sampled_from([jnp.float32, jnp.float64, jnp.float16, jnp.int32]),
    fill=st.sampled_from([0.0, np.nan, np.inf, 1e30, -1e30, 1e-30]),
    faces=st.sampled_from([SQUARE_FACES, SQUARE_FACES + 2, -SQUARE_FACES, np.zeros((2, 3), int), np.zeros((0, 3), int)]),
    offset=st.sampled_from([0.0, np.nan, True, 1e300, -0.5]),
    max_distance=st.sampled_from([None, 0.5, 0.0, -1.0, 1e-300]),
)
def test_bad_input_never_crashes(implementation, p_shape, t_shape, dtype, fill, faces, offset, max_distance):
    rng = np.random.default_rng(len(p_shape))
    points = jnp.asarray(rng.normal(size=p_shape)).astype(dtype)
    target = jnp.asarray(rng.normal(size=t_shape)).astype(dtype)
    if target.size:
        target = target.at[(0,) * target.ndim].set(jnp.asarray(fill).astype(dtype))
    try:
        out = shrinkwrap_points(points, target, jnp.asarray(faces, jnp.int32), offset=offset, max_distance=max_distance, implementation=implementation)
    except (TypeError, ValueError, KeyError, RuntimeError):
        return
    assert out.shape == points.shape
