"""Thin-plate-spline RBF: the Warp evaluator against the JAX path and an independent formula."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from geomjax import ThinPlateSplineFit, radial_basis_function_deform_points

pytest.importorskip("warp")
from warp_ffi.rbf import thin_plate_spline_field  # noqa: E402

rbf = radial_basis_function_deform_points


def _random(shape, dtype=jnp.float64, seed=0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-1.0, 1.0, size=shape), dtype=dtype)


def _formula(points, controls, weights, constant, linear):
    """The field written out directly (all pairs at once, log(0) avoided with a where)."""
    diff = points[:, :, None, :] - controls[:, None, :, :]
    s = jnp.sum(diff * diff, axis=-1)
    phi = 0.5 * s * jnp.log(jnp.where(s > 0, s, jnp.ones((), s.dtype)))
    return jnp.einsum("bnc,bcd->bnd", phi, weights) + constant[:, None, :] + jnp.einsum("bnk,bkd->bnd", points, linear)


TOLERANCE = {jnp.float32: 2e-5, jnp.float64: 1e-12}


@pytest.mark.parametrize(
    "num_dims, dtype, batched",
    [(1, jnp.float64, False), (2, jnp.float32, True), (3, jnp.float64, True), (3, jnp.float32, False), (4, jnp.float64, False)],
)
def test_values_match_the_jax_path(num_dims, dtype, batched):
    lead = (2,) if batched else ()
    points = _random(lead + (33, num_dims), dtype, seed=1)
    controls, displacements = _random(lead + (12, num_dims), dtype, seed=2), _random(lead + (12, num_dims), dtype, seed=3)
    points = points.at[..., 0, :].set(controls[..., 5, :])  # a query on a control
    weights = _random(lead + (33,), dtype, seed=4)
    warp = rbf(points, controls, displacements, point_weights=weights, smoothing=0.01, implementation="warp")
    jax_ = rbf(points, controls, displacements, point_weights=weights, smoothing=0.01, implementation="jax")
    assert warp.dtype == dtype and warp.shape == points.shape
    np.testing.assert_allclose(warp, jax_, rtol=0, atol=TOLERANCE[dtype])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_kernel_and_its_adjoint_match_the_direct_formula(dtype):
    """All five cotangents (points, controls, weights, constant, linear), against autodiff of an
    independent all-pairs formula."""
    args = (
        _random((2, 40, 3), dtype, seed=5),
        _random((2, 7, 3), dtype, seed=6),
        _random((2, 7, 3), dtype, seed=7),
        _random((2, 3), dtype, seed=8),
        _random((2, 3, 3), dtype, seed=9),
    )
    args = (args[0].at[1, 3].set(args[1][1, 2]),) + args[1:]  # exact coincidence in batch item 1
    out, vjp_warp = jax.vjp(thin_plate_spline_field, *args)
    expected, vjp_formula = jax.vjp(_formula, *args)
    np.testing.assert_allclose(out, expected, rtol=0, atol=TOLERANCE[dtype])
    cotangent = _random(out.shape, dtype, seed=10)
    for got, want in zip(vjp_warp(cotangent), vjp_formula(cotangent)):
        assert got.dtype == dtype
        scale = 1.0 + float(jnp.abs(want).max())
        np.testing.assert_allclose(got, want, rtol=0, atol=10 * TOLERANCE[dtype] * scale)


@pytest.mark.parametrize("polynomial", [True, False])
def test_vjps_through_the_fit_match_the_jax_path(polynomial):
    points, controls, displacements = _random((2, 20, 2), seed=11), _random((2, 9, 2), seed=12), _random((2, 9, 2), seed=13)
    weights = _random((2, 20), seed=14)
    points = points.at[0, 4].set(controls[0, 1])

    def function(implementation):
        return lambda p, c, d, w: rbf(p, c, d, point_weights=w, polynomial=polynomial, smoothing=0.02, implementation=implementation)

    out_warp, vjp_warp = jax.vjp(function("warp"), points, controls, displacements, weights)
    out_jax, vjp_jax = jax.vjp(function("jax"), points, controls, displacements, weights)
    np.testing.assert_allclose(out_warp, out_jax, rtol=0, atol=1e-12)
    cotangent = _random(out_jax.shape, seed=15)
    for got, want in zip(vjp_warp(cotangent), vjp_jax(cotangent)):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_gradients_match_finite_differences():
    points, controls, displacements = _random((6, 3), seed=16), _random((8, 3), seed=17), _random((8, 3), seed=18)
    check_grads(
        jax.jit(lambda p, c, d: rbf(p, c, d, implementation="warp") ** 2), (points, controls, displacements), order=1, modes=("rev",)
    )


def test_jit_vmap_and_vmap_of_grad_match_the_jax_path():
    points, controls, displacements = _random((3, 10, 2), seed=19), _random((3, 6, 2), seed=20), _random((3, 6, 2), seed=21)

    def loss(implementation):
        return lambda p, c, d: jnp.sum(jnp.sin(rbf(p, c, d, implementation=implementation)))

    for transform in (jax.vmap, lambda f: jax.jit(jax.vmap(f))):
        np.testing.assert_allclose(
            transform(lambda p, c, d: rbf(p, c, d, implementation="warp"))(points, controls, displacements),
            transform(lambda p, c, d: rbf(p, c, d, implementation="jax"))(points, controls, displacements),
            rtol=0,
            atol=1e-12,
        )
    grads_warp = jax.jit(jax.vmap(jax.grad(loss("warp"), argnums=(0, 1, 2))))(points, controls, displacements)
    grads_jax = jax.vmap(jax.grad(loss("jax"), argnums=(0, 1, 2)))(points, controls, displacements)
    for got, want in zip(grads_warp, grads_jax):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_vmap_over_fits_with_the_warp_evaluator():
    controls, displacements, points = _random((3, 8, 2), seed=22), _random((3, 8, 2), seed=23), _random((3, 5, 2), seed=24)
    fits = jax.vmap(ThinPlateSplineFit.fit)(controls, displacements)
    warp = jax.vmap(lambda f, p: f(p, implementation="warp"))(fits, points)
    np.testing.assert_allclose(warp, np.stack([rbf(points[b], controls[b], displacements[b]) for b in range(3)]), rtol=0, atol=1e-12)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_empty_inputs(dtype):
    points, controls = _random((4, 3), dtype, seed=25), _random((5, 3), dtype, seed=26)
    empty_points = jnp.zeros((0, 3), dtype)
    assert rbf(empty_points, controls, controls, implementation="warp").shape == (0, 3)
    grads = jax.grad(lambda p, c: rbf(p, c, c, implementation="warp").sum(), argnums=(0, 1))(empty_points, controls)
    assert grads[0].shape == (0, 3)
    np.testing.assert_array_equal(grads[1], 0.0)
    no_controls = jnp.zeros((0, 3), dtype)
    np.testing.assert_array_equal(rbf(points, no_controls, no_controls, implementation="warp"), points)
    grads = jax.grad(lambda p, c: rbf(p, c, c, implementation="warp").sum(), argnums=(0, 1))(points, no_controls)
    np.testing.assert_array_equal(grads[0], 1.0)
    assert grads[1].shape == (0, 3)


def test_singular_layout_raises_before_the_kernel_runs():
    controls = _random((6, 2), seed=27)
    controls = controls.at[3].set(controls[0])
    with pytest.raises(RuntimeError):
        rbf(_random((3, 2)), controls, jnp.ones_like(controls), implementation="warp")
