"""morph_points (JAX path and the public API): compact Wendland-C2 Shepard morphing.

Warp parity lives in ``test_morph_warp.py``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import geomjax._dispatch as dispatch
from geomjax import morph_points


def _random(shape, dtype=jnp.float64, seed=0, scale=1.0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-scale, scale, size=shape), dtype=dtype)


def _phi(q):
    return (1 - q) ** 4 * (4 * q + 1)


def _naive(points, controls, displacements, radius):
    """Independent float64 reference: the defining quotient, one point at a time."""
    points, controls, displacements = (np.asarray(a, np.float64) for a in (points, controls, displacements))
    radius = np.broadcast_to(np.asarray(radius, np.float64), controls.shape[:1])
    out = np.zeros_like(points)
    for i, x in enumerate(points):
        q = np.linalg.norm(x - controls, axis=1) / radius
        if np.any(q == 0):
            out[i] = displacements[q == 0].mean(axis=0)
            continue
        active = q < 1
        a = np.where(active, _phi(np.where(active, q, 0.5)) / np.where(active, q, 0.5) ** 2, 0.0)
        out[i] = a @ displacements / (1 + a.sum())
    return out


def _example():
    x = jnp.linspace(0.0, 1.0, 9)
    points = jnp.stack((x, jnp.zeros_like(x)), axis=-1)
    controls = points[jnp.array([0, 8])]
    displacements = jnp.array([[0.0, 0.25], [0.0, -0.15]])
    return points, controls, displacements, jnp.array([0.8, 0.8])


def test_reference_example_values_hand_checked():
    points, controls, displacements, radii = _example()
    out = morph_points(points, controls, displacements, radius=radii, implementation="jax")
    u = np.asarray(out - points)
    # x = 0 and x = 1 sit on the controls: exact interpolation.
    np.testing.assert_array_equal(u[0], [0.0, 0.25])
    np.testing.assert_array_equal(u[8], [0.0, -0.15])
    # x = 0.5: both controls at q = 0.5 / 0.8, a = phi(q) / q^2 each.
    q = 0.625
    a = (0.375**4 * 3.5) / q**2
    np.testing.assert_allclose(u[4], [0.0, a * (0.25 - 0.15) / (1 + 2 * a)], rtol=1e-14)
    # x = 0.125: only the first control is in range (the second is at q = 1.09375).
    q = 0.125 / 0.8
    a = _phi(q) / q**2
    np.testing.assert_allclose(u[1], [0.0, 0.25 * a / (1 + a)], rtol=1e-14)
    np.testing.assert_allclose(u, _naive(points, controls, displacements, radii), rtol=1e-13, atol=1e-15)
    # Gradients of the reference's loss flow to every input.
    grads = jax.grad(
        lambda p, c, d: jnp.mean(jnp.square(morph_points(p, c, d, radius=radii, implementation="jax"))), argnums=(0, 1, 2)
    )(points, controls, displacements)
    assert all(bool(jnp.all(jnp.isfinite(g))) and bool(jnp.any(g != 0)) for g in grads)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("dim", [1, 2, 3, 5])
def test_matches_independent_formula(dtype, dim):
    points = _random((40, dim), dtype, 1)
    controls = _random((7, dim), dtype, 2)
    displacements = _random((7, dim), dtype, 3)
    radius = jnp.asarray(np.random.default_rng(4).uniform(0.3, 1.2, 7), dtype)
    out = morph_points(points, controls, displacements, radius=radius, implementation="jax")
    assert out.dtype == dtype and out.shape == points.shape
    expected = np.asarray(points, np.float64) + _naive(points, controls, displacements, radius)
    tol = 1e-5 if dtype == jnp.float32 else 1e-12
    np.testing.assert_allclose(out, expected, rtol=tol, atol=tol)


def test_zero_outside_every_support():
    controls, displacements = _random((5, 3), seed=1), _random((5, 3), seed=2)
    far = _random((20, 3), seed=3) + 10.0
    out = morph_points(far, controls, displacements, radius=0.5, implementation="jax")
    np.testing.assert_array_equal(out, far)
    # Exactly on a support boundary (q = 1) a control contributes nothing either.
    boundary = controls[:1] + jnp.array([[0.5, 0.0, 0.0]])
    lone = morph_points(boundary, controls[:1], displacements[:1], radius=0.5, implementation="jax")
    np.testing.assert_array_equal(lone, boundary)


def test_interpolates_controls_exactly():
    controls, displacements = _random((6, 3), seed=4), _random((6, 3), seed=5)
    out = morph_points(controls, controls, displacements, radius=1.5, implementation="jax")
    np.testing.assert_array_equal(out, controls + displacements)


def test_duplicated_controls_give_their_mean():
    controls = jnp.array([[0.0, 0.0], [0.0, 0.0], [0.3, 0.0]])
    displacements = jnp.array([[1.0, 0.0], [0.0, 3.0], [5.0, 5.0]])
    out = morph_points(jnp.zeros((1, 2)), controls, displacements, radius=1.0, implementation="jax")
    np.testing.assert_array_equal(out, [[0.5, 1.5]])


def test_constant_displacement_follows_background_partition():
    points, controls = _random((30, 3), seed=6), _random((8, 3), seed=7)
    radius = jnp.asarray(np.random.default_rng(8).uniform(0.5, 1.5, 8))
    constant = jnp.array([0.3, -1.0, 2.0])
    out = morph_points(points, controls, jnp.broadcast_to(constant, controls.shape), radius=radius, implementation="jax")
    q = np.linalg.norm(np.asarray(points)[:, None] - np.asarray(controls)[None], axis=-1) / np.asarray(radius)
    a = np.where(q < 1, _phi(np.minimum(q, 1)) / q**2, 0.0).sum(axis=1)
    np.testing.assert_allclose(out - points, np.asarray(constant) * (a / (1 + a))[:, None], rtol=1e-13, atol=1e-15)


def test_stable_and_differentiable_next_to_a_control_in_float64():
    controls, displacements = _random((4, 3), seed=9), _random((4, 3), seed=10)
    radius = jnp.full((4,), 0.7)
    offsets = jnp.array([[1e-30, 0.0, 0.0], [-3e-31, 2e-30, 1e-31], [1e-300, 1e-300, 0.0]]) * 0.7
    points = controls[:1] + offsets

    def loss(p, c, d, r):
        return jnp.sum(jnp.square(morph_points(p, c, d, radius=r, implementation="jax")))

    out = morph_points(points, controls, displacements, radius=radius, implementation="jax")
    np.testing.assert_allclose(out - points, jnp.broadcast_to(displacements[0], points.shape), rtol=1e-14)
    for g in jax.grad(loss, argnums=(0, 1, 2, 3))(points, controls, displacements, radius):
        assert bool(jnp.all(jnp.isfinite(g)))


@pytest.mark.parametrize("implementation", ["jax", "warp"])
@pytest.mark.parametrize("dtype, exponent", [(jnp.float64, -1030), (jnp.float32, -140)])
def test_subnormal_problem_keeps_its_values_and_radius_gradient(implementation, dtype, exponent):
    """Every length below the normal range (XLA flushes subnormals): the unit-scale answer, scaled."""
    if implementation == "warp":
        pytest.importorskip("warp")
    scale = 2.0**exponent
    unit_points = np.array([[0.3, 0.1, 0.0], [0.9, -0.4, 0.2], [-0.2, 0.5, 0.1], [4.0, 0.0, 0.0]])
    unit_controls = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    unit_displacements = np.array([[1.0, 2.0, 3.0], [-1.0, 0.5, 0.0]])
    unit_radius = np.array([1.0, 0.75])
    points, controls, displacements, radius = (jnp.asarray(a * scale, dtype) for a in (unit_points, unit_controls, unit_displacements, unit_radius))
    assert bool(np.all(np.asarray(radius) < np.finfo(np.dtype(dtype)).tiny))  # subnormal radii
    # The inputs as stored (subnormals keep fewer bits), back at unit scale (exact: a power of two).
    unit_points, unit_controls, unit_displacements, unit_radius = (
        np.asarray(a, np.float64) / scale for a in (points, controls, displacements, radius)
    )

    out = morph_points(points, controls, displacements, radius=radius, implementation=implementation)
    expected = unit_points + _naive(unit_points, unit_controls, unit_displacements, unit_radius)
    eps = float(np.finfo(np.dtype(dtype)).eps)
    # One rounding to the subnormal grid (spacing 2^-1074 / 2^-149) after a unit-scale evaluation.
    spacing = float(np.finfo(np.dtype(dtype)).smallest_subnormal)
    np.testing.assert_allclose(np.asarray(out, np.float64), expected * scale, rtol=64 * eps, atol=4 * spacing)

    # d/dr of sum(out) is scale-free (out is homogeneous of degree one in every length): the
    # unit-scale derivative, by central differences of the float64 reference.
    def unit_loss(r):
        return np.sum(_naive(unit_points, unit_controls, unit_displacements, r))

    step = 1e-6
    expected_gradient = [(unit_loss(unit_radius + step * e) - unit_loss(unit_radius - step * e)) / (2 * step) for e in np.eye(2)]
    gradient = jax.grad(lambda r: jnp.sum(morph_points(points, controls, displacements, radius=r, implementation=implementation)))(radius)
    assert np.all(np.abs(expected_gradient) > 0.1)
    np.testing.assert_allclose(np.asarray(gradient, np.float64), expected_gradient, rtol=max(1e-6, 64 * eps))


def test_per_control_and_batched_tensor_radius():
    points, controls, displacements = _random((2, 15, 3), seed=11), _random((2, 5, 3), seed=12), _random((2, 5, 3), seed=13)
    per_control = jnp.array([0.4, 0.6, 0.8, 1.0, 1.2])
    batched = jnp.stack([per_control, per_control[::-1]])
    out_shared = morph_points(points, controls, displacements, radius=per_control, implementation="jax")
    out_batched = morph_points(points, controls, displacements, radius=batched, implementation="jax")
    for b in range(2):
        design = (points[b], controls[b], displacements[b])
        np.testing.assert_allclose(out_shared[b], points[b] + _naive(*design, per_control), rtol=1e-12)
        np.testing.assert_allclose(out_batched[b], points[b] + _naive(*design, batched[b]), rtol=1e-12)


def test_scalar_and_zero_dim_radius_agree():
    points, controls, displacements = _random((10, 3), seed=14), _random((4, 3), seed=15), _random((4, 3), seed=16)
    a = morph_points(points, controls, displacements, radius=0.9, implementation="jax")
    b = morph_points(points, controls, displacements, radius=jnp.asarray(0.9), implementation="jax")
    c = morph_points(points, controls, displacements, radius=jnp.full((4,), 0.9), implementation="jax")
    d = morph_points(points, controls, displacements, radius=np.float64(0.9), implementation="jax")
    np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(a, c)
    np.testing.assert_array_equal(a, d)
    e = morph_points(points, controls, displacements, radius=1, implementation="jax")
    np.testing.assert_array_equal(e, morph_points(points, controls, displacements, radius=1.0, implementation="jax"))


def test_infinite_and_negative_tensor_radius():
    points, controls, displacements = _random((10, 3), seed=17), _random((3, 3), seed=18), _random((3, 3), seed=19)
    radius = jnp.array([0.5, jnp.inf, 0.7])
    out = morph_points(points, controls, displacements, radius=radius, implementation="jax")
    # difference / inf = 0: every finite point coincides with the infinite-radius control.
    np.testing.assert_array_equal(out, points + displacements[1])
    negative = morph_points(points, controls, displacements, radius=-jnp.array([0.5, 0.6, 0.7]), implementation="jax")
    positive = morph_points(points, controls, displacements, radius=jnp.array([0.5, 0.6, 0.7]), implementation="jax")
    np.testing.assert_allclose(negative, positive, rtol=1e-14)


def test_point_weights():
    points, controls, displacements = _random((12, 3), seed=20), _random((4, 3), seed=21), _random((4, 3), seed=22)
    field = morph_points(points, controls, displacements, radius=1.0, implementation="jax") - points
    weights = jnp.linspace(-1.0, 2.0, 12)
    out = morph_points(points, controls, displacements, radius=1.0, point_weights=weights, implementation="jax")
    np.testing.assert_allclose(out, points + weights[:, None] * field, rtol=1e-14)
    mask = jnp.arange(12) % 2 == 0
    out = morph_points(points, controls, displacements, radius=1.0, point_weights=mask, implementation="jax")
    np.testing.assert_array_equal(out, jnp.where(mask[:, None], points + field, points))


def test_empty_points():
    controls, displacements = _random((4, 3), seed=23), _random((4, 3), seed=24)
    points = jnp.zeros((0, 3))
    assert morph_points(points, controls, displacements, radius=0.5).shape == (0, 3)
    grads = jax.grad(lambda p, c, d: morph_points(p, c, d, radius=0.5).sum(), argnums=(0, 1, 2))(points, controls, displacements)
    assert grads[0].shape == (0, 3)
    np.testing.assert_array_equal(grads[1], jnp.zeros_like(controls))
    np.testing.assert_array_equal(grads[2], jnp.zeros_like(displacements))
    assert morph_points(jnp.zeros((2, 0, 3)), jnp.zeros((2, 4, 3)), jnp.zeros((2, 4, 3)), radius=0.5).shape == (2, 0, 3)


@pytest.mark.parametrize("implementation", ["jax", None])
def test_zero_controls_is_identity_and_ignores_scalar_radius_value(implementation):
    points = _random((6, 3), seed=25)
    empty = jnp.zeros((0, 3))
    for radius in (-1.0, 0.0, float("inf"), jnp.zeros((0,))):
        out = morph_points(points, empty, empty, radius=radius, implementation=implementation)
        np.testing.assert_array_equal(out, points)
    grad = jax.grad(lambda p: morph_points(p, empty, empty, radius=-1.0).sum())(points)
    np.testing.assert_array_equal(grad, jnp.ones_like(points))
    with pytest.raises(TypeError):
        morph_points(points, empty, empty, radius=True)


def _grad_case():
    points = jnp.array([[0.1, 0.2, 0.0], [0.5, -0.3, 0.2], [-0.4, 0.1, 0.3], [0.05, 0.05, -0.1]])
    controls = jnp.array([[0.0, 0.1, 0.0], [0.4, -0.2, 0.1], [-0.3, 0.3, 0.2]])
    displacements = _random((3, 3), seed=26)
    radius = jnp.array([0.6, 0.5, 0.7])
    weights = jnp.array([1.0, 0.5, -0.7, 2.0])
    return points, controls, displacements, radius, weights


def test_gradients_match_finite_differences_to_second_order():
    points, controls, displacements, radius, weights = _grad_case()

    def f(p, c, d, r, w):
        return morph_points(p, c, d, radius=r, point_weights=w, implementation="jax")

    # Reverse mode to second order here; forward mode is checked against reverse in test_jvp_matches_vjp.
    check_grads(f, (points, controls, displacements, radius, weights), order=2, modes=("rev",), atol=1e-5, rtol=1e-5)


def test_jvp_matches_vjp():
    points, controls, displacements, radius, _ = _grad_case()

    def f(p, c, d, r):
        return morph_points(p, c, d, radius=r, implementation="jax")

    tangents = tuple(_random(a.shape, seed=30 + i) for i, a in enumerate((points, controls, displacements, radius)))
    out, jvp = jax.jvp(f, (points, controls, displacements, radius), tangents)
    cotangent = _random(out.shape, seed=40)
    _, vjp = jax.vjp(f, points, controls, displacements, radius)
    lhs = jnp.sum(jvp * cotangent)
    rhs = sum(jnp.sum(t * g) for t, g in zip(tangents, vjp(cotangent), strict=True))
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12)


def test_jit_and_vmap_match_eager_loops():
    points, controls, displacements = _random((3, 20, 3), seed=41), _random((6, 3), seed=42), _random((4, 6, 3), seed=43)

    def f(p, d):
        return morph_points(p, controls, d, radius=0.8, implementation="jax")

    np.testing.assert_allclose(jax.jit(f)(points[0], displacements[0]), f(points[0], displacements[0]), rtol=1e-14)
    over_points = jax.vmap(f, in_axes=(0, None))(points, displacements[0])
    np.testing.assert_allclose(over_points, jnp.stack([f(p, displacements[0]) for p in points]), rtol=1e-14)
    over_designs = jax.jit(jax.vmap(f, in_axes=(None, 0)))(points[0], displacements)
    np.testing.assert_allclose(over_designs, jnp.stack([f(points[0], d) for d in displacements]), rtol=1e-14)
    moved_controls = controls[None] + 0.1 * _random((4, 6, 3), seed=44)
    def with_controls(c):
        return morph_points(points[0], c, displacements[0], radius=0.8, implementation="jax")

    over_control_sets = jax.vmap(with_controls)(moved_controls)
    expected = jnp.stack([with_controls(c) for c in moved_controls])
    np.testing.assert_allclose(over_control_sets, expected, rtol=1e-14)


def test_batched_matches_loop_and_float32_tracks_float64():
    points, controls, displacements = _random((3, 25, 3), seed=45), _random((3, 5, 3), seed=46), _random((3, 5, 3), seed=47)
    out = morph_points(points, controls, displacements, radius=0.9, implementation="jax")
    for b in range(3):
        single_design = morph_points(points[b], controls[b], displacements[b], radius=0.9, implementation="jax")
        np.testing.assert_allclose(out[b], single_design, rtol=1e-14)
    single = morph_points(*(a.astype(jnp.float32) for a in (points, controls, displacements)), radius=0.9, implementation="jax")
    assert single.dtype == jnp.float32
    np.testing.assert_allclose(single, out, rtol=1e-5, atol=1e-5)


def test_blocked_evaluation_matches_single_block():
    from geomjax.deform import morph as morph_module

    points, controls, displacements = _random((1, 37, 3), seed=48), _random((1, 9, 3), seed=49), _random((1, 9, 3), seed=50)
    radius = jnp.full((1, 9), 0.8)
    whole = morph_module._shepard_block(points[0], controls[0], displacements[0], radius[0])
    blocked = morph_module.map_query_blocks(
        lambda x: morph_module._shepard_block(x, controls[0], displacements[0], radius[0]), (points[0],), block_size=5
    )
    np.testing.assert_allclose(blocked, whole, rtol=1e-13, atol=1e-16)


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    num_controls=st.integers(1, 6),
    radius=st.floats(0.05, 3.0),
)
def test_field_is_a_convex_blend_of_zero_and_the_displacements(seed, num_controls, radius):
    """u is sum_j a_j d_j / (1 + sum_j a_j) or a mean: each component lies in [min(0, d), max(0, d)]."""
    rng = np.random.default_rng(seed)
    points = jnp.asarray(rng.uniform(-1, 1, (16, 2)))
    controls = jnp.asarray(rng.uniform(-1, 1, (num_controls, 2)))
    points = points.at[0].set(controls[0])
    displacements = jnp.asarray(rng.normal(size=(num_controls, 2)))
    u = np.asarray(morph_points(points, controls, displacements, radius=radius, implementation="jax") - points)
    low = np.minimum(0.0, np.asarray(displacements).min(axis=0))
    high = np.maximum(0.0, np.asarray(displacements).max(axis=0))
    assert np.all(u >= low - 1e-12) and np.all(u <= high + 1e-12)
    np.testing.assert_allclose(u[0], np.asarray(displacements[0]), rtol=0, atol=1e-15)  # coincidence overrides the others


def test_translation_moves_everything_together():
    points, controls, displacements = _random((20, 3), seed=51), _random((5, 3), seed=52), _random((5, 3), seed=53)
    shift = jnp.array([0.25, -0.5, 0.125])
    base = morph_points(points, controls, displacements, radius=0.9, implementation="jax")
    moved = morph_points(points + shift, controls + shift, displacements, radius=0.9, implementation="jax")
    np.testing.assert_allclose(moved, base + shift, rtol=1e-12, atol=1e-12)


# ---------------------------------------------------------------------------------------------
# Errors.


def _args(dtype=jnp.float64):
    return _random((5, 3), dtype, 60), _random((3, 3), dtype, 61), _random((3, 3), dtype, 62)


@pytest.mark.parametrize(
    "make",
    [
        lambda p, c, d: (p.astype(jnp.int32), c, d, {}),
        lambda p, c, d: (p.astype(jnp.float16), c.astype(jnp.float16), d.astype(jnp.float16), {}),
        lambda p, c, d: (p, c.astype(jnp.float32), d, {}),
        lambda p, c, d: (p, c, d.astype(jnp.float32), {}),
        lambda p, c, d: (p.tolist(), c, d, {}),
        lambda p, c, d: (p, c, d, {"radius": jnp.full((3,), 0.5, jnp.float32)}),
        lambda p, c, d: (p, c, d, {"radius": jnp.ones((3,), jnp.int32)}),
        lambda p, c, d: (p, c, d, {"radius": True}),
        lambda p, c, d: (p, c, d, {"radius": "0.5"}),
        lambda p, c, d: (p, c, d, {"radius": None}),
        lambda p, c, d: (p, c, d, {"point_weights": jnp.ones((5,), jnp.int32)}),
        lambda p, c, d: (p, c, d, {"point_weights": jnp.ones((5,), jnp.float32)}),
    ],
)
def test_type_errors(make):
    points, controls, displacements, kwargs = make(*_args())
    kwargs.setdefault("radius", 0.5)
    with pytest.raises(TypeError):
        morph_points(points, controls, displacements, **kwargs)


@pytest.mark.parametrize(
    "make",
    [
        lambda p, c, d: (p[0], c, d, {}),
        lambda p, c, d: (p[None, None], c, d, {}),
        lambda p, c, d: (p[None], c, d, {}),
        lambda p, c, d: (jnp.stack([p, p]), jnp.stack([c, c, c]), jnp.stack([d, d, d]), {}),
        lambda p, c, d: (p, c[:, :2], d[:, :2], {}),
        lambda p, c, d: (p, c, d[:2], {}),
        lambda p, c, d: (p[:, :0], c[:, :0], d[:, :0], {}),
        lambda p, c, d: (p, c, d, {"radius": float("nan")}),
        lambda p, c, d: (p, c, d, {"radius": float("inf")}),
        lambda p, c, d: (p, c, d, {"radius": 0.0}),
        lambda p, c, d: (p, c, d, {"radius": -0.5}),
        lambda p, c, d: (p, c, d, {"radius": jnp.ones((4,))}),
        lambda p, c, d: (p, c, d, {"radius": jnp.ones((1, 3))}),
        lambda p, c, d: (p, c, d, {"radius": jnp.ones((3, 1))}),
        lambda p, c, d: (p, c, d, {"kernel": "gaussian"}),
        lambda p, c, d: (p, c, d, {"kernel": None}),
        lambda p, c, d: (p, c, d, {"point_weights": jnp.ones((4,))}),
        lambda p, c, d: (p, c, d, {"point_weights": jnp.ones((1, 5))}),
    ],
)
def test_value_errors(make):
    points, controls, displacements, kwargs = make(*_args())
    kwargs.setdefault("radius", 0.5)
    with pytest.raises(ValueError):
        morph_points(points, controls, displacements, **kwargs)


@pytest.mark.parametrize("radius", [1e-46, 1e39, 2**-149 / 4])
def test_scalar_radius_checked_against_float32_range(radius):
    points, controls, displacements = _args(jnp.float32)
    with pytest.raises(ValueError):
        morph_points(points, controls, displacements, radius=radius)
    # The same value is fine in float64 (and any value is accepted without controls).
    morph_points(*_args(), radius=radius, implementation="jax")
    empty = jnp.zeros((0, 3), jnp.float32)
    morph_points(points, empty, empty, radius=radius)


def test_batched_radius_needs_batched_inputs_of_matching_size():
    points, controls, displacements = (jnp.stack([a, a]) for a in _args())
    with pytest.raises(ValueError):
        morph_points(points, controls, displacements, radius=jnp.ones((3, 3)))
    morph_points(points, controls, displacements, radius=jnp.ones((2, 3)), implementation="jax")


def test_unknown_implementation_is_a_key_error():
    with pytest.raises(KeyError):
        morph_points(*_args(), radius=0.5, implementation="cuda")
    with pytest.raises(KeyError):
        morph_points(*_args(), radius=0.5, implementation=1)


def test_torch_means_jax_and_missing_warp(monkeypatch):
    points, controls, displacements = _args()
    np.testing.assert_array_equal(
        morph_points(points, controls, displacements, radius=0.5, implementation="torch"),
        morph_points(points, controls, displacements, radius=0.5, implementation="jax"),
    )
    monkeypatch.setattr(dispatch, "warp_available", lambda: False)
    with pytest.raises(ImportError):
        morph_points(points, controls, displacements, radius=0.5, implementation="warp")
    # Without Warp the default falls back to the JAX path.
    np.testing.assert_array_equal(
        morph_points(points, controls, displacements, radius=0.5),
        morph_points(points, controls, displacements, radius=0.5, implementation="jax"),
    )
