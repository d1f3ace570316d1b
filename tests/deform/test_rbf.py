"""radial_basis_function_deform_points and ThinPlateSplineFit: the JAX path and the public API."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import geomjax._dispatch
from geomjax import ThinPlateSplineFit, radial_basis_function_deform_points
from geomjax.deform import rbf as rbf_module

rbf = radial_basis_function_deform_points


def _random(shape, dtype=jnp.float64, seed=0, low=-1.0, high=1.0):
    return jnp.asarray(np.random.default_rng(seed).uniform(low, high, size=shape), dtype=dtype)


def _numpy_phi(s):
    return 0.5 * s * np.log(np.where(s > 0, s, 1.0))


def _numpy_sq(a, b):
    return ((a[:, None, :] - b[None, :, :]) ** 2).sum(-1)


def _numpy_tps(points, controls, displacements, *, polynomial=True, smoothing=0.0):
    """Independent float64 reference: the unscaled dense system of the reference API, numpy solve."""
    x, c, d = (np.asarray(a, np.float64) for a in (points, controls, displacements))
    num_controls, num_dims = c.shape
    matrix = _numpy_phi(_numpy_sq(c, c)) + smoothing * np.eye(num_controls)
    rhs = d
    if polynomial:
        tail = np.concatenate([np.ones((num_controls, 1)), c], axis=1)
        matrix = np.block([[matrix, tail], [tail.T, np.zeros((num_dims + 1, num_dims + 1))]])
        rhs = np.concatenate([d, np.zeros((num_dims + 1, num_dims))])
    solution = np.linalg.solve(matrix, rhs)
    field = _numpy_phi(_numpy_sq(x, c)) @ solution[:num_controls]
    if polynomial:
        field = field + solution[num_controls] + x @ solution[num_controls + 1 :]
    return x + field


# -- values --------------------------------------------------------------------------------------


def test_reference_example_matches_scipy_and_backpropagates():
    points = jnp.array([[0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [0.25, 0.75]])
    controls = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    displacements = jnp.array([[0.0, 0.0], [0.0, 0.0], [0.15, 0.25], [0.0, 0.0]])
    exact = rbf(points, controls, displacements, kernel="thin_plate_spline", polynomial=True, smoothing=0.0)
    # scipy.interpolate.RBFInterpolator(controls, displacements, kernel="thin_plate_spline", degree=1)
    expected = np.array([[0.01244542, 0.02074236], [0.02505458, 0.04175764], [0.08744542, 0.14574236], [0.02505458, 0.04175764]])
    np.testing.assert_allclose(exact - points, expected, atol=1e-8)
    grads = jax.grad(lambda p, c, d: jnp.mean(rbf(p, c, d) ** 2), argnums=(0, 1, 2))(points, controls, displacements)
    assert all(np.isfinite(g).all() for g in grads)
    assert np.abs(grads[1]).max() > 0 and np.abs(grads[2]).max() > 0


def test_matches_scipy_rbf_interpolator():
    scipy_interpolate = pytest.importorskip("scipy.interpolate")
    controls, displacements, points = _random((40, 3), seed=1), 0.1 * _random((40, 3), seed=2), _random((25, 3), seed=3)
    expected = scipy_interpolate.RBFInterpolator(
        np.asarray(controls), np.asarray(displacements), kernel="thin_plate_spline", degree=1
    )(np.asarray(points))
    np.testing.assert_allclose(rbf(points, controls, displacements) - points, expected, rtol=0, atol=1e-12)


@pytest.mark.parametrize(
    "num_dims, polynomial, smoothing",
    [(1, True, 0.0), (2, True, 0.3), (3, True, 0.0), (4, True, 0.0), (1, False, 0.05), (2, False, 0.0), (3, False, 0.05)],
)
def test_matches_unscaled_numpy_solve(num_dims, polynomial, smoothing):
    controls = _random((12, num_dims), seed=num_dims, low=-2.0, high=3.0)
    displacements = _random((12, num_dims), seed=10 + num_dims)
    points = _random((9, num_dims), seed=20 + num_dims, low=-3.0, high=4.0)
    points = points.at[0].set(controls[3])  # a query exactly on a control
    out = rbf(points, controls, displacements, polynomial=polynomial, smoothing=smoothing)
    expected = _numpy_tps(points, controls, displacements, polynomial=polynomial, smoothing=smoothing)
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-10)  # 1-D systems have cond ~1e5


@pytest.mark.parametrize(
    "scale, offset, dtype",
    [
        (1e-150, 0.0, jnp.float64),
        (1e-8, 3.0, jnp.float64),
        (1e8, 0.0, jnp.float64),
        (1e150, 3.0, jnp.float64),
        (1e-20, 3.0, jnp.float32),
        (1e20, 0.0, jnp.float32),
    ],
)
def test_internal_normalisation_gives_the_unscaled_field(scale, offset, dtype):
    """Centring and scaling is exact: same field as a float64 solve of the unscaled system.

    float32 at 1e+-20 would under/overflow r^2 without the internal normalisation.
    """
    controls = (np.asarray(_random((20, 3), seed=1)) + offset) * scale
    displacements = np.asarray(_random((20, 3), seed=2)) * 0.1 * scale
    points = (np.asarray(_random((15, 3), seed=3, low=-1.2, high=1.2)) + offset) * scale
    smoothing = 0.01 * scale**2 if dtype == jnp.float64 else 0.0
    expected = _numpy_tps(points, controls, displacements, smoothing=smoothing)
    out = rbf(jnp.asarray(points, dtype), jnp.asarray(controls, dtype), jnp.asarray(displacements, dtype), smoothing=smoothing)
    tolerance = (1e-11 if dtype == jnp.float64 else 3e-5) * scale
    np.testing.assert_allclose(np.asarray(out, np.float64) - points, expected - points, rtol=0, atol=tolerance)


@pytest.mark.parametrize("dtype, tolerance", [(jnp.float32, 2e-5), (jnp.float64, 1e-12)])
@pytest.mark.parametrize("batched", [False, True])
def test_interpolates_the_controls(dtype, tolerance, batched):
    shape = (2, 30, 3) if batched else (30, 3)
    controls, displacements = _random(shape, dtype, seed=4), 0.2 * _random(shape, dtype, seed=5)
    out = rbf(controls, controls, displacements)
    assert out.dtype == dtype and out.shape == shape
    np.testing.assert_allclose(out - controls, displacements, rtol=0, atol=tolerance)


@pytest.mark.parametrize("num_dims", [2, 3])
def test_reproduces_affine_fields(num_dims):
    controls = _random((25, num_dims), seed=6, low=-5.0, high=5.0)
    matrix, shift = _random((num_dims, num_dims), seed=7), _random((num_dims,), seed=8)
    displacements = controls @ matrix + shift
    points = _random((40, num_dims), seed=9, low=-8.0, high=8.0)
    out = rbf(points, controls, displacements)
    fit = ThinPlateSplineFit.fit(controls, displacements)
    # An exact affine field has zero radial weights; the solve leaves roundoff of about
    # eps * cond(system) * |rhs|, with the condition number of the normalised TPS system built
    # here in NumPy (it depends on the layout and on how the CPU's BLAS rounds, not on a machine).
    c = np.asarray(fit.normalised_controls)
    r2 = np.sum((c[:, None, :] - c[None, :, :]) ** 2, axis=-1)
    kernel = np.where(r2 > 0, 0.5 * r2 * np.log(np.where(r2 > 0, r2, 1.0)), 0.0)
    tail = np.concatenate([np.ones((len(c), 1)), c], axis=1)
    system = np.block([[kernel, tail], [tail.T, np.zeros((num_dims + 1, num_dims + 1))]])
    roundoff = np.finfo(np.float64).eps * np.linalg.cond(system)
    expected = np.asarray(points @ matrix + shift)
    np.testing.assert_allclose(out - points, expected, rtol=0, atol=roundoff * np.abs(expected).max())
    assert np.abs(fit.weights).max() < roundoff * float(np.abs(displacements).max())


def test_smoothing_relaxes_interpolation_towards_the_affine_least_squares_fit():
    controls, displacements = _random((30, 2), seed=10), 0.3 * _random((30, 2), seed=11)
    residuals = [
        float(np.abs(rbf(controls, controls, displacements, smoothing=s) - controls - displacements).max())
        for s in (0.0, 1e-3, 1e-1, 10.0)
    ]
    assert residuals[0] < 1e-12
    assert all(a < b for a, b in zip(residuals, residuals[1:]))
    # lambda -> infinity forces W -> 0: the field tends to the least-squares affine fit.
    tail = np.concatenate([np.ones((30, 1)), np.asarray(controls)], axis=1)
    coefficients = np.linalg.lstsq(tail, np.asarray(displacements), rcond=None)[0]
    points = _random((10, 2), seed=12)
    far = rbf(points, controls, displacements, smoothing=1e9) - points
    np.testing.assert_allclose(far, np.concatenate([np.ones((10, 1)), np.asarray(points)], axis=1) @ coefficients, atol=1e-7)


def test_single_control_without_tail_uses_the_smoothed_kernel():
    control, displacement = jnp.array([[0.5, -0.5]]), jnp.array([[0.2, 0.1]])
    points = jnp.array([[0.5, -0.5], [2.5, -0.5], [0.5, 2.5]])
    out = rbf(points, control, displacement, polynomial=False, smoothing=0.5)
    r = np.array([0.0, 2.0, 3.0])
    expected = (r**2 * np.log(np.where(r > 0, r, 1.0)))[:, None] * (np.asarray(displacement) / 0.5)
    np.testing.assert_allclose(out - points, expected, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("polynomial", [True, False])
@pytest.mark.parametrize("shape", [(0, 3), (2, 0, 3)])
def test_zero_controls_is_the_identity(polynomial, shape):
    points = _random(shape[:-2] + (5, 3), seed=13)
    empty = jnp.zeros(shape)
    out = rbf(points, empty, empty, polynomial=polynomial, smoothing=1.0)
    np.testing.assert_array_equal(out, points)
    grads = jax.grad(lambda p, c, d: rbf(p, c, d).sum(), argnums=(0, 1, 2))(points, empty, empty)
    np.testing.assert_array_equal(grads[0], np.ones(points.shape))
    assert grads[1].shape == shape and grads[2].shape == shape


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("batched", [False, True])
def test_empty_points(dtype, batched):
    lead = (2,) if batched else ()
    points = jnp.zeros(lead + (0, 3), dtype)
    controls, displacements = _random(lead + (6, 3), dtype, seed=14), _random(lead + (6, 3), dtype, seed=15)
    out = rbf(points, controls, displacements, point_weights=jnp.zeros(lead + (0,), bool))
    assert out.shape == points.shape and out.dtype == dtype
    grads = jax.grad(lambda p, c, d: rbf(p, c, d).sum(), argnums=(0, 1, 2))(points, controls, displacements)
    assert grads[0].shape == points.shape
    np.testing.assert_array_equal(grads[1], 0.0)
    np.testing.assert_array_equal(grads[2], 0.0)


def test_point_weights_scale_and_mask_the_field():
    points, controls, displacements = _random((6, 2), seed=16), _random((8, 2), seed=17), _random((8, 2), seed=18)
    field = rbf(points, controls, displacements) - points
    weights = jnp.array([0.0, 1.0, -2.0, 0.5, 3.0, 1.0])
    np.testing.assert_allclose(rbf(points, controls, displacements, point_weights=weights), points + weights[:, None] * field, atol=1e-14)
    mask = jnp.array([True, False, True, False, False, True])
    np.testing.assert_allclose(
        rbf(points, controls, displacements, point_weights=mask), points + jnp.where(mask[:, None], field, 0.0), atol=1e-14
    )
    masked = rbf(points, controls, displacements, point_weights=mask)
    np.testing.assert_array_equal(masked[~np.asarray(mask)], points[~np.asarray(mask)])


# -- singular layouts ----------------------------------------------------------------------------


def _duplicate():
    controls = _random((10, 3), seed=19)
    return controls.at[7].set(controls[2]), {}


def _coplanar():
    flat = _random((12, 2), seed=20)
    rotation = jnp.asarray(np.linalg.qr(np.random.default_rng(21).normal(size=(3, 3)))[0])
    return jnp.concatenate([flat, jnp.zeros((12, 1))], axis=1) @ rotation + 0.3, {}


def _collinear():
    t = jnp.linspace(0.0, 1.0, 9)
    return jnp.stack([t, 2.0 * t + 1.0], axis=1), {}


def _single_without_tail():
    return jnp.array([[0.3, 0.4]]), {"polynomial": False}


def _duplicate_without_tail():
    controls = _random((6, 2), seed=22)
    return controls.at[4].set(controls[1]), {"polynomial": False}


SINGULAR = [_duplicate, _coplanar, _collinear, _single_without_tail, _duplicate_without_tail]


@pytest.mark.parametrize(
    "layout, dtype", [(layout, jnp.float64) for layout in SINGULAR] + [(_duplicate, jnp.float32), (_coplanar, jnp.float32)]
)
def test_singular_layouts_raise_eagerly_and_under_jit(layout, dtype):
    controls, options = layout()
    controls = controls.astype(dtype)
    displacements = jnp.ones_like(controls)
    points = _random((4, controls.shape[1]), dtype, seed=23)
    with pytest.raises(RuntimeError, match="singular"):
        rbf(points, controls, displacements, **options)
    with pytest.raises(RuntimeError):
        jax.block_until_ready(jax.jit(lambda p, c, d: rbf(p, c, d, **options))(points, controls, displacements))
    with pytest.raises(RuntimeError):  # the check sits on the factors, which the adjoint solve reads too
        jax.block_until_ready(jax.jit(jax.grad(lambda d: rbf(points, controls, d, **options).sum()))(displacements))
    with pytest.raises(RuntimeError):
        ThinPlateSplineFit.fit(controls, displacements, **options)


def test_one_singular_fit_in_a_batch_raises():
    controls = jnp.stack([_random((10, 3), seed=24), _duplicate()[0]])
    with pytest.raises(RuntimeError):
        rbf(_random((2, 4, 3), seed=25), controls, jnp.ones_like(controls))


def test_nearly_degenerate_but_regular_layouts_do_not_raise():
    slab = _random((60, 3), seed=26) * jnp.array([1.0, 1.0, 1e-4])
    displacements = 0.1 * _random((60, 3), seed=27)
    out = rbf(slab, slab, displacements)
    np.testing.assert_allclose(out - slab, displacements, atol=1e-9)
    cube = _random((1000, 3), jnp.float32, seed=28)  # cond ~ 4e6, still accepted in float32
    rbf(cube[:5], cube, jnp.zeros_like(cube))


# -- fit reuse -----------------------------------------------------------------------------------


@pytest.mark.parametrize("batched", [False, True])
def test_fit_reuse_matches_the_one_shot_function(batched):
    lead = (3,) if batched else ()
    controls, displacements = _random(lead + (15, 2), seed=29), _random(lead + (15, 2), seed=30)
    fit = ThinPlateSplineFit.fit(controls, displacements, smoothing=0.01)
    for seed in (31, 32):
        points = _random(lead + (11, 2), seed=seed)
        weights = _random(lead + (11,), seed=seed + 10)
        np.testing.assert_array_equal(
            fit(points, point_weights=weights), rbf(points, controls, displacements, smoothing=0.01, point_weights=weights)
        )
        np.testing.assert_allclose(fit.displacement(points), fit(points) - points, rtol=0, atol=1e-15)


def test_fit_is_a_pytree_usable_under_jit_and_grad():
    controls, displacements, points = _random((12, 3), seed=33), _random((12, 3), seed=34), _random((7, 3), seed=35)
    fit = ThinPlateSplineFit.fit(controls, displacements)
    np.testing.assert_allclose(jax.jit(lambda f, p: f(p))(fit, points), fit(points), rtol=0, atol=1e-14)

    def loss(c, d):
        return jnp.sum(ThinPlateSplineFit.fit(c, d)(points) ** 2)

    grads = jax.jit(jax.grad(loss, argnums=(0, 1)))(controls, displacements)
    expected = jax.grad(lambda c, d: jnp.sum(rbf(points, c, d) ** 2), argnums=(0, 1))(controls, displacements)
    for got, want in zip(grads, expected):
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-10)


def test_vmap_over_a_batch_of_fits_matches_the_loop_and_the_batched_fit():
    controls, displacements, points = _random((4, 10, 2), seed=36), _random((4, 10, 2), seed=37), _random((4, 6, 2), seed=38)
    fits = jax.vmap(lambda c, d: ThinPlateSplineFit.fit(c, d, smoothing=0.1))(controls, displacements)
    vmapped = jax.vmap(lambda f, p: f(p))(fits, points)
    loop = np.stack([rbf(points[b], controls[b], displacements[b], smoothing=0.1) for b in range(4)])
    batched = ThinPlateSplineFit.fit(controls, displacements, smoothing=0.1)(points)
    np.testing.assert_allclose(vmapped, loop, rtol=0, atol=1e-14)
    np.testing.assert_allclose(batched, loop, rtol=0, atol=1e-14)


def test_fit_rejects_points_of_another_layout():
    fit = ThinPlateSplineFit.fit(_random((8, 3), seed=39), _random((8, 3), seed=40))
    with pytest.raises(ValueError):
        fit(_random((2, 5, 3)))  # batched points, unbatched fit
    with pytest.raises(ValueError):
        fit(_random((5, 2)))
    with pytest.raises(TypeError):
        fit(_random((5, 3), jnp.float32))
    with pytest.raises(KeyError):
        fit(_random((5, 3)), implementation="cuda")
    batched_fit = ThinPlateSplineFit.fit(_random((2, 8, 3), seed=41), _random((2, 8, 3), seed=42))
    with pytest.raises(ValueError):
        batched_fit(_random((3, 5, 3)))


# -- differentiation, transformations ------------------------------------------------------------


def test_gradients_through_the_fit_match_finite_differences_to_second_order():
    controls, displacements = _random((7, 2), seed=43), _random((7, 2), seed=44)
    points, weights = _random((5, 2), seed=45), _random((5,), seed=46)

    @jax.jit
    def f(p, c, d, w):
        return rbf(p, c, d, point_weights=w, smoothing=0.05) ** 2

    check_grads(f, (points, controls, displacements, weights), order=2, modes=("fwd", "rev"), atol=1e-5, rtol=1e-5)


def test_gradients_without_tail_match_finite_differences():
    controls, displacements, points = _random((6, 3), seed=47), _random((6, 3), seed=48), _random((4, 3), seed=49)
    check_grads(jax.jit(lambda p, c, d: rbf(p, c, d, polynomial=False)), (points, controls, displacements), order=1, modes=("fwd", "rev"))


def test_derivatives_at_a_control_are_finite_and_follow_the_safe_branch():
    controls, displacements = _random((8, 3), seed=50), _random((8, 3), seed=51)
    at_control = controls[2]
    field = lambda x: rbf(x[None], controls, displacements)[0]  # noqa: E731
    jacobian = jax.jit(jax.jacfwd(field))(at_control)
    hessian = jax.jit(jax.hessian(lambda x: field(x).sum()))(at_control)
    third = jax.jit(jax.jacfwd(jax.hessian(lambda x: field(x).sum())))(at_control)
    assert np.isfinite(jacobian).all() and np.isfinite(hessian).all() and np.isfinite(third).all()
    # The coincident control contributes nothing (value, first and second derivative zero), so
    # the derivatives equal those of the field built from the other controls' terms.
    fit = ThinPlateSplineFit.fit(controls, displacements)
    keep = np.arange(8) != 2
    others = ThinPlateSplineFit(
        fit.centre, fit.scale, fit.normalised_controls[keep], fit.weights[keep], fit.constant, fit.linear,
        polynomial=True, batched=False,
    )
    np.testing.assert_allclose(jacobian, jax.jacfwd(lambda x: others.displacement(x[None])[0])(at_control) + np.eye(3), atol=1e-12)
    np.testing.assert_allclose(hessian, jax.hessian(lambda x: (x + others.displacement(x[None])[0]).sum())(at_control), atol=1e-10)
    controls_grad = jax.grad(lambda c: rbf(at_control[None], c, displacements).sum())(controls)
    assert np.isfinite(controls_grad).all()


def test_jvp_matches_vjp():
    controls, displacements, points = _random((9, 3), seed=52), _random((9, 3), seed=53), _random((6, 3), seed=54)
    tangents = tuple(_random(a.shape, seed=55 + i) for i, a in enumerate((points, controls, displacements)))
    _, jvp_out = jax.jvp(rbf, (points, controls, displacements), tangents)
    out, vjp_fn = jax.vjp(rbf, points, controls, displacements)
    cotangent = _random(out.shape, seed=60)
    lhs = float(jnp.sum(jvp_out * cotangent))
    rhs = sum(float(jnp.sum(g * t)) for g, t in zip(vjp_fn(cotangent), tangents))
    np.testing.assert_allclose(lhs, rhs, rtol=1e-12)


def test_jit_and_vmap_match_the_eager_loop():
    points, controls, displacements = _random((3, 7, 3), seed=61), _random((3, 9, 3), seed=62), _random((3, 9, 3), seed=63)
    weights = _random((3, 7), seed=64)
    function = lambda p, c, d, w: rbf(p, c, d, point_weights=w, smoothing=0.01)  # noqa: E731
    loop = np.stack([function(points[b], controls[b], displacements[b], weights[b]) for b in range(3)])
    np.testing.assert_allclose(jax.vmap(function)(points, controls, displacements, weights), loop, rtol=0, atol=1e-14)
    np.testing.assert_allclose(jax.jit(function)(points, controls, displacements, weights), loop, rtol=0, atol=1e-14)
    # vmap over points only (shared controls)
    shared = jax.vmap(lambda p: rbf(p, controls[0], displacements[0]))(points)
    np.testing.assert_allclose(shared, np.stack([rbf(p, controls[0], displacements[0]) for p in points]), rtol=0, atol=1e-14)


def test_blocked_evaluation_equals_a_single_block(monkeypatch):
    points, controls, displacements = _random((1000, 3), seed=65), _random((40, 3), seed=66), _random((40, 3), seed=67)
    whole = rbf(points, controls, displacements, implementation="jax")
    monkeypatch.setitem(rbf_module._BLOCK_BYTES, "cpu", 40 * 8 * 64)  # 64-query blocks, a ragged tail
    blocked = rbf(points, controls, displacements, implementation="jax")
    np.testing.assert_allclose(blocked, whole, rtol=0, atol=1e-13)  # only the summation order differs
    grads = jax.grad(lambda c: rbf(points, c, displacements).sum())(controls)
    monkeypatch.setitem(rbf_module._BLOCK_BYTES, "cpu", 2**30)
    np.testing.assert_allclose(grads, jax.grad(lambda c: rbf(points, c, displacements).sum())(controls), rtol=1e-9, atol=1e-9)


def test_float64_log_is_accurate():
    rng = np.random.default_rng(68)
    powers = 2.0 ** np.arange(-1000, 1001)
    # Binade and range-reduction edges: 2^k, sqrt(1/2) 2^k and the doubles just below them.
    edges = np.concatenate([powers, np.nextafter(powers, 0), np.sqrt(0.5) * powers, np.nextafter(np.sqrt(0.5) * powers, 0)])
    x = np.concatenate(
        [
            rng.uniform(1e-300, 10.0, 5000),
            np.exp(rng.uniform(-700.0, 700.0, 5000)),
            rng.uniform(0.5, 2.0, 5000),
            edges,
            [np.finfo(np.float64).max, np.finfo(np.float64).tiny],
            [1.0, 2.0, 0.5],
        ]
    )
    got = np.asarray(jax.jit(rbf_module._log64)(jnp.asarray(x)))
    expected = np.log(x)
    assert np.all(np.abs(got - expected) <= 2 * np.spacing(np.abs(expected)) + 1e-300)
    assert got[-3] == 0.0


@settings(max_examples=20, deadline=None)
@given(
    angle=st.floats(0.0, 2 * np.pi),
    log_scale=st.floats(-6.0, 6.0),
    shift=st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)),
    smoothing=st.sampled_from([0.0, 0.1]),
)
def test_property_similarity_transforms_commute_with_the_deformation(angle, log_scale, shift, smoothing):
    """Moving, rotating and scaling the whole configuration (points, controls, displacements)
    moves the result the same way, with the smoothing scaled by s^2."""
    controls, displacements, points = _random((10, 2), seed=69), 0.2 * _random((10, 2), seed=70), _random((8, 2), seed=71)
    s = 10.0**log_scale
    rotation = jnp.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    offset = jnp.asarray(shift)

    def move(x):
        return s * x @ rotation.T + offset

    base = rbf(points, controls, displacements, smoothing=smoothing)
    moved = rbf(move(points), move(controls), s * displacements @ rotation.T, smoothing=smoothing * s * s)
    np.testing.assert_allclose(moved, move(base), rtol=0, atol=1e-10 * (s + float(jnp.abs(offset).max())))


# -- validation ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "kwargs, error",
    [
        (dict(kernel="gaussian"), ValueError),
        (dict(kernel=None), ValueError),
        (dict(polynomial=1), TypeError),
        (dict(polynomial="yes"), TypeError),
        (dict(smoothing=True), TypeError),
        (dict(smoothing="0.1"), TypeError),
        (dict(smoothing=-0.1), ValueError),
        (dict(smoothing=float("nan")), ValueError),
        (dict(smoothing=float("inf")), ValueError),
        (dict(smoothing=1e300), ValueError),  # outside float32
        (dict(implementation="cuda"), KeyError),
        (dict(implementation=3), KeyError),
        (dict(point_weights=jnp.ones((5,), jnp.int32)), TypeError),
        (dict(point_weights=jnp.ones((5,), jnp.float64)), TypeError),
        (dict(point_weights=jnp.ones((1, 5), jnp.float32)), ValueError),
        (dict(point_weights=[1.0] * 5), TypeError),
    ],
)
def test_invalid_options(kwargs, error):
    points, controls = _random((5, 3), jnp.float32), _random((6, 3), jnp.float32, seed=1)
    with pytest.raises(error):
        rbf(points, controls, controls, **kwargs)


@pytest.mark.parametrize(
    "points, controls, displacements, error",
    [
        (jnp.zeros((4, 3)), jnp.zeros((2, 6, 3)), jnp.zeros((2, 6, 3)), ValueError),  # no broadcasting
        (jnp.zeros((2, 4, 3)), jnp.zeros((6, 3)), jnp.zeros((6, 3)), ValueError),
        (jnp.zeros((2, 4, 3)), jnp.zeros((3, 6, 3)), jnp.zeros((3, 6, 3)), ValueError),
        (jnp.zeros((4, 3)), jnp.zeros((6, 2)), jnp.zeros((6, 2)), ValueError),
        (jnp.zeros((4, 3)), jnp.zeros((6, 3)), jnp.zeros((5, 3)), ValueError),
        (jnp.zeros((4, 3)), jnp.zeros((6, 3)), jnp.zeros((6, 3), jnp.float32), TypeError),
        (jnp.zeros((4, 3)), jnp.zeros((6, 3), jnp.float32), jnp.zeros((6, 3), jnp.float32), TypeError),
        (jnp.zeros((4, 3), jnp.float16), jnp.zeros((6, 3), jnp.float16), jnp.zeros((6, 3), jnp.float16), TypeError),
        (jnp.zeros((4, 3), jnp.int32), jnp.zeros((6, 3)), jnp.zeros((6, 3)), TypeError),
        (jnp.zeros((4,)), jnp.zeros((6, 3)), jnp.zeros((6, 3)), ValueError),
        (np.zeros((4, 3)).tolist(), jnp.zeros((6, 3)), jnp.zeros((6, 3)), TypeError),
        (jnp.zeros((4, 3)), jnp.zeros((3, 3)), jnp.zeros((3, 3)), ValueError),  # polynomial needs D + 1 controls
        (jnp.zeros((4, 2)), jnp.zeros((1, 2)), jnp.zeros((1, 2)), ValueError),
    ],
)
def test_invalid_arrays(points, controls, displacements, error):
    with pytest.raises(error):
        rbf(points, controls, displacements)


def test_too_few_controls_is_fine_without_the_tail():
    out = rbf(jnp.zeros((2, 3)), _random((2, 3), seed=72), jnp.ones((2, 3)), polynomial=False)
    assert np.isfinite(out).all()


def test_explicit_warp_without_warp_is_an_import_error(monkeypatch):
    monkeypatch.setattr(geomjax._dispatch, "warp_available", lambda: False)
    points = _random((3, 2))
    controls = _random((4, 2), seed=73)
    with pytest.raises(ImportError):
        rbf(points, controls, controls, implementation="warp")
    np.testing.assert_array_equal(rbf(points, controls, controls), rbf(points, controls, controls, implementation="jax"))


@pytest.mark.parametrize("implementation", [None, "jax", "torch"])
def test_portable_implementation_names(implementation):
    points, controls, displacements = _random((5, 2)), _random((6, 2), seed=74), _random((6, 2), seed=75)
    np.testing.assert_array_equal(
        rbf(points, controls, displacements, implementation=implementation), rbf(points, controls, displacements, implementation="jax")
    )
