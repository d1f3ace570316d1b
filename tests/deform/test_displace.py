"""displace_points: x' = x + w * d."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

from geomjax import displace_points


def _random(shape, dtype=jnp.float64, seed=0):
    return jnp.asarray(np.random.default_rng(seed).normal(size=shape), dtype=dtype)


def test_reference_example_values():
    points = jnp.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
    displacement = jnp.array([[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]])
    out = displace_points(points, displacement, point_weights=jnp.array([0.0, 0.5, 1.0]))
    np.testing.assert_array_equal(out, [[0.0, 0.0], [1.0, 0.5], [2.0, 1.0]])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("shape", [(7, 3), (2, 7, 3), (5, 1), (4, 6)])
def test_unweighted_is_sum_and_keeps_dtype(shape, dtype):
    points, displacement = _random(shape, dtype, 1), _random(shape, dtype, 2)
    out = displace_points(points, displacement)
    assert out.dtype == dtype and out.shape == shape
    np.testing.assert_array_equal(out, np.asarray(points) + np.asarray(displacement))


def test_zero_displacement_is_identity():
    points = _random((2, 9, 3))
    np.testing.assert_array_equal(displace_points(points, jnp.zeros_like(points)), points)


def test_bool_mask_ignores_non_finite_displacement_and_its_gradient():
    points = _random((3, 2))
    displacement = jnp.array([[jnp.nan, 1.0], [jnp.inf, 0.0], [1.0, 2.0]])
    mask = jnp.array([False, False, True])
    out = displace_points(points, displacement, point_weights=mask)
    np.testing.assert_array_equal(out[:2], points[:2])
    np.testing.assert_array_equal(out[2], points[2] + jnp.array([1.0, 2.0]))
    grad_d = jax.grad(lambda d: displace_points(points, d, point_weights=mask).sum())(displacement)
    np.testing.assert_array_equal(grad_d, [[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]])


def test_signed_and_amplifying_float_weights_are_used_as_given():
    points, displacement = _random((3, 2)), _random((3, 2), seed=3)
    weights = jnp.array([-1.0, 2.5, 0.0])
    out = displace_points(points, displacement, point_weights=weights)
    np.testing.assert_allclose(out, points + weights[:, None] * displacement, rtol=0, atol=0)


def test_batched_weights_align_with_batch():
    points, displacement = _random((2, 4, 3)), _random((2, 4, 3), seed=5)
    weights = jnp.array([[1.0, 0.0, 1.0, 0.0], [0.5, 0.5, 0.5, 0.5]])
    out = displace_points(points, displacement, point_weights=weights)
    for b in range(2):
        np.testing.assert_allclose(out[b], displace_points(points[b], displacement[b], point_weights=weights[b]))


def test_empty_points():
    points = jnp.zeros((0, 3))
    out = displace_points(points, points, point_weights=jnp.zeros((0,), bool))
    assert out.shape == (0, 3)
    grads = jax.grad(lambda p, d: displace_points(p, d).sum(), argnums=(0, 1))(points, points)
    assert all(g.shape == (0, 3) for g in grads)


def test_gradients_match_finite_differences_to_second_order():
    points, displacement, weights = _random((4, 3)), _random((4, 3), seed=1), _random((4,), seed=2)
    check_grads(
        lambda p, d, w: displace_points(p, d, point_weights=w) ** 2, (points, displacement, weights), order=2, modes=("fwd", "rev")
    )


def test_jit_and_vmap_match_eager_loop():
    points, displacement, weights = _random((5, 6, 2)), _random((5, 6, 2), seed=1), _random((5, 6), seed=2)
    eager = [displace_points(points[b], displacement[b], point_weights=weights[b]) for b in range(5)]
    vmapped = jax.vmap(lambda p, d, w: displace_points(p, d, point_weights=w))(points, displacement, weights)
    jitted = jax.jit(lambda p, d, w: displace_points(p, d, point_weights=w))(points, displacement, weights)
    # jit may fuse w * d + x into one FMA, so allow float64 roundoff rather than bit equality.
    np.testing.assert_allclose(vmapped, np.stack(eager), rtol=1e-15, atol=1e-15)
    np.testing.assert_allclose(jitted, np.stack(eager), rtol=1e-15, atol=1e-15)


@pytest.mark.parametrize("implementation", [None, "jax", "torch"])
def test_portable_implementation_names(implementation):
    points = _random((3, 2))
    np.testing.assert_array_equal(displace_points(points, points, implementation=implementation), 2 * points)


@pytest.mark.parametrize(
    "kwargs, error",
    [
        (dict(implementation="warp"), KeyError),  # as in the reference: no Warp backend
        (dict(implementation="cuda"), KeyError),
        (dict(point_weights=jnp.ones((4,), jnp.int32)), TypeError),
        (dict(point_weights=jnp.ones((4,), jnp.float32)), TypeError),  # float32 weights, float64 points
        (dict(point_weights=jnp.ones((1, 4))), ValueError),
        (dict(point_weights=[1.0, 1.0, 1.0, 1.0]), TypeError),
    ],
)
def test_invalid_options(kwargs, error):
    points = _random((4, 3))
    with pytest.raises(error):
        displace_points(points, points, **kwargs)


@pytest.mark.parametrize(
    "points, displacement, error",
    [
        (jnp.zeros((4, 3)), jnp.zeros((1, 4, 3)), ValueError),  # no broadcasting of an added batch axis
        (jnp.zeros((4, 3)), jnp.zeros((4, 2)), ValueError),
        (jnp.zeros((4,)), jnp.zeros((4,)), ValueError),
        (jnp.zeros((4, 3)), jnp.zeros((4, 3), jnp.float32), TypeError),
        (jnp.zeros((4, 3), jnp.float16), jnp.zeros((4, 3), jnp.float16), TypeError),
        (jnp.zeros((4, 3), jnp.int32), jnp.zeros((4, 3), jnp.int32), TypeError),
        (np.zeros((4, 3)).tolist(), jnp.zeros((4, 3)), TypeError),
    ],
)
def test_invalid_arrays(points, displacement, error):
    with pytest.raises(error):
        displace_points(points, displacement)


@settings(max_examples=25, deadline=None)
@given(
    n=st.integers(0, 6),
    d=st.integers(1, 4),
    scale=st.floats(-1e3, 1e3, allow_nan=False),
)
def test_property_weight_scales_the_move(n, d, scale):
    points, displacement = _random((n, d), seed=n), _random((n, d), seed=n + 1)
    weights = jnp.full((n,), scale)
    out = displace_points(points, displacement, point_weights=weights)
    np.testing.assert_allclose(out - points, scale * displacement, rtol=1e-9, atol=1e-9 * (1 + abs(scale)))
