"""free_form_deform_points: JAX path (the specification), validation and dispatch."""

from __future__ import annotations

import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import geomjax._dispatch as dispatch
import geomjax.deform.ffd as ffd_module
from geomjax import free_form_deform_points

BASES = ("bernstein", "bspline", "linear", "cubic_hermite", "quintic_hermite")
LOCAL_BASES = ("bspline", "linear", "cubic_hermite", "quintic_hermite")
INTERPOLATING = ("linear", "cubic_hermite", "quintic_hermite")


def ffd(points, lattice, basis="bernstein", origin=None, extent=None, **kwargs):
    dims = points.shape[-1]
    origin = [0.0] * dims if origin is None else origin
    extent = [1.0] * dims if extent is None else extent
    kwargs.setdefault("implementation", "jax")
    return free_form_deform_points(points, lattice, origin=origin, extent=extent, basis=basis, **kwargs)


def resolution_for(basis, dims):
    return (4, 5, 6, 4)[:dims] if basis == "bspline" else (3, 4, 5, 2)[:dims]


def rng_array(seed, shape, low=0.0, high=1.0, dtype=jnp.float64):
    return jnp.asarray(np.random.default_rng(seed).uniform(low, high, size=shape), dtype)


# ------------------------------------------------------------------------------------------
# Independent NumPy references


def bernstein_closed_form(points, lattice, origin, extent):
    """sum_i prod_d C(p_d, i_d) u^i (1-u)^(p-i) P_i, evaluated node by node in float64."""
    u = (np.asarray(points) - np.asarray(origin)) / np.asarray(extent)
    lattice = np.asarray(lattice)
    resolution = lattice.shape[:-1]
    field = np.zeros_like(u)
    for node in itertools.product(*(range(n) for n in resolution)):
        weight = np.ones(len(u))
        for d, i in enumerate(node):
            p = resolution[d] - 1
            weight *= math.comb(p, i) * u[:, d] ** i * (1 - u[:, d]) ** (p - i)
        field += weight[:, None] * lattice[node]
    return np.asarray(points) + field


def local_reference(points, lattice, basis):
    """Local bases on the unit box, one point at a time with explicit loops."""
    lattice = np.asarray(lattice)
    resolution = lattice.shape[:-1]
    out = []
    for x in np.asarray(points):
        if not np.all((x >= 0) & (x <= 1)):
            out.append(x)
            continue
        per_axis = []
        for d, n in enumerate(resolution):
            spans = n - 3 if basis == "bspline" else n - 1
            s = x[d] * spans
            cell = min(max(int(np.floor(s)), 0), spans - 1)
            t = s - cell
            if basis == "bspline":
                w = [(1 - t) ** 3 / 6, (3 * t**3 - 6 * t**2 + 4) / 6, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6]
            else:
                h = {"linear": t, "cubic_hermite": 3 * t**2 - 2 * t**3, "quintic_hermite": 6 * t**5 - 15 * t**4 + 10 * t**3}[basis]
                w = [1 - h, h]
            per_axis.append([(cell + k, wk) for k, wk in enumerate(w)])
        field = np.zeros(len(x))
        for combo in itertools.product(*per_axis):
            field += np.prod([w for _, w in combo]) * lattice[tuple(i for i, _ in combo)]
        out.append(x + field)
    return np.array(out)


# ------------------------------------------------------------------------------------------
# Values and invariants


@pytest.mark.parametrize("basis", BASES)
def test_zero_lattice_is_exact_identity(basis):
    points = rng_array(0, (40, 3), -0.3, 1.3)
    lattice = jnp.zeros(resolution_for(basis, 3) + (3,))
    out = ffd(points, lattice, basis, origin=[0.1, -0.2, 0.0], extent=[0.7, 1.3, 0.9])
    np.testing.assert_array_equal(np.asarray(out), np.asarray(points))


@pytest.mark.parametrize("basis", BASES)
def test_constant_lattice_translates_inside_and_fixes_outside(basis):
    origin, extent = np.array([0.5, -1.0, 2.0]), np.array([2.0, 0.5, 1.0])
    inside = origin + extent * np.random.default_rng(1).uniform(0, 1, size=(30, 3))
    corners = origin + extent * np.array(list(itertools.product([0.0, 1.0], repeat=3)))  # faces inclusive
    outside = np.array([origin - 1e-9, origin + extent * 1.0000001, [0.4, -0.9, 2.5], [1.0, -1.1, 2.5]])
    points = jnp.asarray(np.concatenate([inside, corners, outside]))
    shift = np.array([0.3, -0.7, 1.1])
    lattice = jnp.broadcast_to(jnp.asarray(shift), resolution_for(basis, 3) + (3,))
    out = np.asarray(ffd(points, lattice, basis, origin=list(origin), extent=list(extent)))
    n_in = len(inside) + len(corners)
    # Partition of unity holds to rounding (the weights sum to 1 within a few ulps).
    np.testing.assert_allclose(out[:n_in], np.asarray(points)[:n_in] + shift, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(out[n_in:], np.asarray(points)[n_in:])


@pytest.mark.parametrize("basis", INTERPOLATING + ("bernstein",))
def test_bases_reproduce_node_values(basis):
    resolution = (3, 4, 5)
    lattice = rng_array(2, resolution + (3,), -1, 1)
    origin, extent = np.array([-1.0, 0.5, 2.0]), np.array([2.0, 3.0, 0.5])
    if basis == "bernstein":  # Bernstein interpolates only the box corners
        nodes = list(itertools.product(*((0, n - 1) for n in resolution)))
    else:
        nodes = list(itertools.product(*(range(n) for n in resolution)))
    positions = np.array([origin + extent * np.array(node) / (np.array(resolution) - 1) for node in nodes])
    out = ffd(jnp.asarray(positions), lattice, basis, origin=list(origin), extent=list(extent))
    expected = positions + np.array([np.asarray(lattice)[node] for node in nodes])
    np.testing.assert_allclose(np.asarray(out), expected, rtol=0, atol=1e-13)


def test_bspline_origin_corner_value():
    lattice = jnp.zeros((4, 4, 4, 3)).at[1, 1, 1].set(1.0)
    out = ffd(jnp.zeros((1, 3)), lattice, "bspline")
    np.testing.assert_allclose(np.asarray(out), np.full((1, 3), (4 / 6) ** 3), rtol=1e-15)
    assert abs(float(out[0, 0]) - 0.2963) < 1e-4


# (3, 8, 6): small enough for the node-by-node value path (derivatives from the contracted form);
# (8, 7, 6): above that limit, the blocked contraction with an einsum axis (8, 7) and an unrolled
# axis (6) evaluates the value too.
@pytest.mark.parametrize("resolution", [(3, 8, 6), (8, 7, 6)])
def test_bernstein_matches_closed_form_binomial_formula(resolution):
    assert (math.prod(resolution) <= ffd_module._UNROLLED_MAX_NODES) == (resolution == (3, 8, 6))
    points = rng_array(3, (25, 3), 0.02, 0.98)
    origin, extent = np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0])
    lattice = rng_array(4, resolution + (3,), -0.5, 0.5)
    out = ffd(points, lattice, "bernstein")
    np.testing.assert_allclose(np.asarray(out), bernstein_closed_form(points, lattice, origin, extent), rtol=0, atol=1e-13)
    # The jvp of the fast value path is the contracted form's: it must agree with finite
    # differences of the value, to second order in forward mode (the rule's own derivative) and
    # to first order in reverse. Reverse over reverse of the unrolled path is checked on a smaller
    # lattice by test_finite_difference_gradients_second_order; here it costs 5x the compile time
    # of the rest (73 s against 15 s, jitted).
    jitted = jax.jit(lambda p, lat: ffd(p, lat, "bernstein"))
    check_grads(jitted, (points, lattice), order=2, modes=("fwd",))
    check_grads(jitted, (points, lattice), order=1, modes=("rev",))


def test_high_degree_bernstein_axis_compiles_fast_and_matches_closed_form():
    # 133 nodes (degree 132) on one axis: the basis is a loop over the degree, not 8,778 written-out
    # operations (minutes of XLA compile before; well under a second now, measured in
    # benchmarks). All weights are positive and sum to 1: the value is accurate to ~n eps.
    points = rng_array(5, (40, 1), 0.0, 1.0)
    lattice = rng_array(6, (133, 1), -0.5, 0.5)
    origin, extent = np.array([0.0]), np.array([1.0])
    out = ffd(points, lattice, "bernstein")
    np.testing.assert_allclose(np.asarray(out), bernstein_closed_form(points, lattice, origin, extent), rtol=0, atol=133 * 8 * np.finfo(np.float64).eps)
    # d(sum of the field)/d(node i) = sum over the points of the node's weight.
    gradient = jax.grad(lambda lat: jnp.sum(ffd(points, lat, "bernstein")))(lattice)
    unit = np.eye(133)[:, :, None]
    expected = [bernstein_closed_form(points, unit[i], origin, extent).sum() - np.asarray(points).sum() for i in range(133)]
    np.testing.assert_allclose(np.asarray(gradient)[:, 0], expected, rtol=1e-12, atol=1e-14)
    # Point derivatives of a degree-132 polynomial are ~n^2 times its values: a small step.
    check_grads(lambda p: ffd(p, lattice, "bernstein"), (points,), order=1, modes=("fwd", "rev"), eps=1e-6)
    assert np.isfinite(np.asarray(jax.hessian(lambda p: jnp.sum(ffd(p, lattice, "bernstein")))(points[:2]))).all()


@pytest.mark.parametrize("basis", LOCAL_BASES)
def test_local_bases_match_loop_reference(basis):
    points = rng_array(5, (30, 3), -0.1, 1.1)
    lattice = rng_array(6, resolution_for(basis, 3) + (3,), -0.5, 0.5)
    np.testing.assert_allclose(np.asarray(ffd(points, lattice, basis)), local_reference(points, lattice, basis), atol=1e-13)


@pytest.mark.parametrize("basis", ("linear", "bernstein", "bspline"))
def test_affine_lattice_is_reproduced(basis):
    # Linear, Bernstein (nodes at i/(n-1)) and cubic B-splines (Greville nodes) have linear precision.
    resolution = (4, 5, 6) if basis == "bspline" else (3, 4, 5)
    origin, extent = np.array([0.2, -0.4, 1.0]), np.array([1.5, 0.8, 2.0])
    a = np.array([[0.1, -0.2, 0.3], [0.05, 0.2, -0.1], [-0.3, 0.1, 0.15]])
    b = np.array([0.2, -0.1, 0.4])
    axes = []
    for n in resolution:
        axes.append((np.arange(n) - 1) / (n - 3) if basis == "bspline" else np.arange(n) / (n - 1))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)  # local node coordinates
    node_positions = origin + extent * grid
    lattice = jnp.asarray(node_positions @ a.T + b)
    points = origin + extent * np.random.default_rng(7).uniform(0, 1, (30, 3))
    out = ffd(jnp.asarray(points), lattice, basis, origin=list(origin), extent=list(extent))
    np.testing.assert_allclose(np.asarray(out), points + points @ a.T + b, rtol=0, atol=1e-13)


def test_hermite_does_not_reproduce_affine_fields():
    # Guards the test above: a C1 cell blend is not affine inside a cell.
    lattice = jnp.asarray(np.linspace(0.0, 1.0, 3)[:, None])
    out = ffd(jnp.array([[0.25]]), lattice, "cubic_hermite")
    np.testing.assert_allclose(float(out[0, 0]), 0.25 + 0.5 * (3 * 0.25 - 2 * 0.125), rtol=1e-15)


def test_one_dimensional_hand_values():
    lattice = jnp.array([[0.0], [1.0], [0.0]])
    points = jnp.array([[0.5], [0.25], [1.0], [1.5]])
    out = ffd(points, lattice, "bernstein")
    # B^2_1(u) = 2 u (1 - u)
    np.testing.assert_allclose(np.asarray(out)[:, 0], [1.0, 0.25 + 0.375, 1.0, 1.5], rtol=1e-15)
    out = ffd(points, lattice, "linear")
    np.testing.assert_allclose(np.asarray(out)[:, 0], [1.5, 0.75, 1.0, 1.5], rtol=1e-15)


def test_two_dimensional_hand_values():
    lattice = jnp.zeros((2, 2, 2)).at[1, 0].set(jnp.array([1.0, 0.0])).at[1, 1].set(jnp.array([0.0, 2.0]))
    points = jnp.array([[0.5, 0.5], [1.0, 0.0], [0.25, 1.0]])
    for basis in ("bernstein", "linear"):  # identical for two nodes per axis
        out = ffd(points, lattice, basis, origin=[0.0, 0.0], extent=[1.0, 1.0])
        expected = np.array([[0.5 + 0.25, 0.5 + 0.5], [2.0, 0.0], [0.25, 1.0 + 0.5]])
        np.testing.assert_allclose(np.asarray(out), expected, rtol=1e-15)


@pytest.mark.parametrize("basis", ("bernstein", "bspline", "quintic_hermite"))
def test_four_dimensional_points(basis):
    resolution = resolution_for(basis, 4)
    lattice = rng_array(8, resolution + (4,), -0.5, 0.5)
    points = rng_array(9, (10, 4), 0.0, 1.0)
    out = ffd(points, lattice, basis)
    if basis == "bernstein":
        expected = bernstein_closed_form(points, lattice, np.zeros(4), np.ones(4))
    else:
        expected = local_reference(points, lattice, basis)
    np.testing.assert_allclose(np.asarray(out), expected, atol=1e-13)


def test_boundary_is_inclusive_and_outside_is_fixed():
    lattice = jnp.ones((3, 3, 3, 3))
    points = jnp.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [1.0, 0.5, 0.0], [1.0 + 1e-12, 0.5, 0.5], [-1e-12, 0.5, 0.5]])
    out = np.asarray(ffd(points, lattice))
    np.testing.assert_allclose(out[:3], np.asarray(points[:3]) + 1.0, atol=1e-15)
    np.testing.assert_array_equal(out[3:], np.asarray(points[3:]))


@pytest.mark.parametrize("basis", BASES)
def test_nan_and_outside_points_unchanged_with_zero_gradients(basis):
    points = jnp.array([[0.3, 0.4, 0.5], [jnp.nan, 0.5, 0.5], [0.5, jnp.inf, 0.5], [2.0, 0.5, 0.5]])
    lattice = rng_array(10, resolution_for(basis, 3) + (3,), -0.5, 0.5)
    out = ffd(points, lattice, basis)
    np.testing.assert_array_equal(np.asarray(out[1:]), np.asarray(points[1:]))

    def loss(points, lattice):
        return jnp.sum(ffd(points, lattice, basis) ** 2)  # NaN/inf rows give NaN cotangents

    g_points, g_lattice = jax.grad(loss, argnums=(0, 1))(points, lattice)
    g_ref = jax.grad(lambda lat: jnp.sum(ffd(points[:1], lat, basis) ** 2))(lattice)
    np.testing.assert_allclose(np.asarray(g_lattice), np.asarray(g_ref), rtol=1e-14, atol=1e-15)
    assert np.all(np.isfinite(np.asarray(g_points[0])))
    # Outside point: the field contributes nothing, the gradient is the identity's.
    np.testing.assert_array_equal(np.asarray(g_points[3]), 2 * np.asarray(points[3]))
    g_masked = jax.grad(lambda p: jnp.sum(jnp.where(jnp.isfinite(ffd(p, lattice, basis)), ffd(p, lattice, basis), 0.0)))(points)
    np.testing.assert_array_equal(np.asarray(g_masked[1:3]), np.array([[0.0, 1.0, 1.0], [1.0, 0.0, 1.0]]))


def test_point_weights_bool_and_float():
    points = rng_array(11, (6, 2), 0.1, 0.9)
    lattice = rng_array(12, (3, 3, 2), -1, 1)
    field = ffd(points, lattice) - points
    w = jnp.array([0.0, 1.0, -0.5, 2.0, 0.25, 1.0])
    np.testing.assert_allclose(np.asarray(ffd(points, lattice, point_weights=w)), np.asarray(points + w[:, None] * field), atol=1e-15)
    mask = jnp.array([True, False, True, False, True, False])
    nan_lattice = lattice.at[1, 1].set(jnp.nan)
    out = ffd(points, nan_lattice, point_weights=mask)
    np.testing.assert_array_equal(np.asarray(out[~np.asarray(mask)]), np.asarray(points[~np.asarray(mask)]))
    g = jax.grad(lambda w: jnp.sum(ffd(points, lattice, point_weights=w)))(w)
    np.testing.assert_allclose(np.asarray(g), np.asarray(field.sum(-1)), atol=1e-15)


# ------------------------------------------------------------------------------------------
# Batches, boxes, dtypes, empties


@pytest.mark.parametrize("basis", ("bernstein", "bspline", "linear"))
def test_batched_with_aligned_boxes_equals_loop(basis):
    points = rng_array(13, (3, 20, 3), -0.5, 2.0)
    lattice = rng_array(14, (3,) + resolution_for(basis, 3) + (3,), -0.3, 0.3)
    origin = rng_array(15, (3, 3), -0.5, 0.0)
    extent = rng_array(16, (3, 3), 1.0, 2.0)
    weights = rng_array(17, (3, 20), -1, 1)
    out = ffd(points, lattice, basis, origin=origin, extent=extent, point_weights=weights)
    for b in range(3):
        one = ffd(points[b], lattice[b], basis, origin=origin[b], extent=extent[b], point_weights=weights[b])
        np.testing.assert_allclose(np.asarray(out[b]), np.asarray(one), rtol=1e-14, atol=1e-15)
    shared = ffd(points, lattice, basis, origin=origin[0], extent=extent[0])
    for b in range(3):
        one = ffd(points[b], lattice[b], basis, origin=origin[0], extent=extent[0])
        np.testing.assert_allclose(np.asarray(shared[b]), np.asarray(one), rtol=1e-14, atol=1e-15)


def test_sequences_and_arrays_are_equivalent():
    points = rng_array(18, (15, 3), -0.5, 1.5)
    lattice = rng_array(19, (3, 4, 3, 3), -0.3, 0.3)
    a = ffd(points, lattice, origin=[-0.25, 0.0, 0.1], extent=(1.5, 1, np.float64(0.75)))
    b = ffd(points, lattice, origin=jnp.array([-0.25, 0.0, 0.1]), extent=np.array([1.5, 1.0, 0.75]))
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.parametrize("dtype", (jnp.float32, jnp.float64))
@pytest.mark.parametrize("basis", BASES)
def test_dtypes(dtype, basis):
    points = rng_array(20, (2, 12, 3), -0.2, 1.2, dtype)
    lattice = rng_array(21, (2,) + resolution_for(basis, 3) + (3,), -0.3, 0.3, dtype)
    out = ffd(points, lattice, basis, origin=jnp.zeros(3, dtype), extent=jnp.ones(3, dtype))
    assert out.dtype == dtype and out.shape == points.shape
    ref = ffd(points.astype(jnp.float64), lattice.astype(jnp.float64), basis)
    np.testing.assert_allclose(np.asarray(out, np.float64), np.asarray(ref), atol=5e-6 if dtype == jnp.float32 else 1e-15)


@pytest.mark.parametrize("basis", ("bernstein", "bspline"))
def test_empty_inputs(basis):
    lattice = rng_array(22, resolution_for(basis, 3) + (3,))
    empty = jnp.zeros((0, 3))
    assert ffd(empty, lattice, basis).shape == (0, 3)
    g = jax.grad(lambda lat: jnp.sum(ffd(empty, lat, basis)))(lattice)
    np.testing.assert_array_equal(np.asarray(g), np.zeros(lattice.shape))
    batched = jnp.zeros((0, 5, 3))
    assert ffd(batched, jnp.zeros((0,) + lattice.shape), basis).shape == (0, 5, 3)
    no_points = jnp.zeros((2, 0, 3))
    g = jax.grad(lambda lat: jnp.sum(ffd(no_points, lat, basis)))(jnp.stack([lattice, lattice]))
    assert g.shape == (2,) + lattice.shape and not np.any(np.asarray(g))


@pytest.mark.parametrize("basis", ("bernstein", "bspline", "cubic_hermite"))
def test_blocked_evaluation_matches_single_block(basis, monkeypatch):
    points = rng_array(23, (2, 53, 3), -0.2, 1.2)
    lattice = rng_array(24, (2,) + resolution_for(basis, 3) + (3,), -0.3, 0.3)

    def loss(points, lattice):
        return jnp.sum(jnp.sin(ffd(points, lattice, basis)))

    whole = ffd(points, lattice, basis)
    whole_grads = jax.grad(loss, argnums=(0, 1))(points, lattice)
    block_sizes = []
    original_map = ffd_module.map_query_blocks

    def spy(fn, queries, *, block_size):
        block_sizes.append(block_size)
        return original_map(fn, queries, block_size=block_size)

    monkeypatch.setattr(ffd_module, "query_block_size", lambda n, b, **k: 8)
    monkeypatch.setattr(ffd_module, "map_query_blocks", spy)
    compiled = (ffd_module.ffd_field, ffd_module._free_form_deform)  # the block size is fixed at trace time
    for fn in compiled:
        fn.clear_cache()
    try:
        blocked = ffd(points, lattice, basis)
        blocked_grads = jax.grad(loss, argnums=(0, 1))(points, lattice)
    finally:
        for fn in compiled:
            fn.clear_cache()
    assert block_sizes and set(block_sizes) == {8}  # 53 points: 6 blocks of 8 and a remainder of 5
    np.testing.assert_allclose(np.asarray(blocked), np.asarray(whole), atol=1e-15)
    for a, b in zip(blocked_grads, whole_grads):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-14)


# ------------------------------------------------------------------------------------------
# Transformations


def test_finite_difference_gradients_second_order():
    # All five bases in one function (one set of compilations). Coordinates stay at least 0.05
    # from every cell boundary of these resolutions (kinks of "linear" at multiples of 1/2, 1/3,
    # 1/4) and from the box faces.
    coords = np.array([0.1, 0.2, 0.4, 0.6, 0.8, 0.9])
    points = jnp.asarray(np.random.default_rng(25).choice(coords, size=(4, 3)))
    lattices = tuple(rng_array(26 + i, resolution_for(b, 3) + (3,), -0.3, 0.3) for i, b in enumerate(BASES))
    weights = rng_array(27, (4,), 0.5, 1.5)

    @jax.jit
    def fn(p, w, *lats):
        return jnp.concatenate([ffd(p, lat, b, point_weights=w) for b, lat in zip(BASES, lats)])

    # Reverse mode to second order here; forward mode is checked against the VJP in test_jit_vmap_and_jvp.
    check_grads(fn, (points, weights) + lattices, order=2, modes=("rev",), eps=1e-4, atol=2e-5, rtol=2e-5)


def test_gradients_are_finite_at_box_faces_and_cell_boundaries():
    points = jnp.array([[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [0.5, 0.0, 1.0]])
    lattices = tuple(rng_array(28, resolution_for(b, 3) + (3,), -0.3, 0.3) for b in BASES)

    def loss(p):
        return [jnp.sum(ffd(p, lat, b) ** 2) for b, lat in zip(BASES, lattices)]

    for basis, hess in zip(BASES, jax.jit(jax.hessian(loss))(points)):
        assert np.all(np.isfinite(np.asarray(hess))), basis


@pytest.mark.parametrize("basis", ("bernstein", "bspline", "quintic_hermite"))
def test_jit_vmap_and_jvp(basis):
    points = rng_array(29, (3, 10, 3), -0.2, 1.2)
    lattice = rng_array(30, (3,) + resolution_for(basis, 3) + (3,), -0.3, 0.3)
    eager = ffd(points, lattice, basis)
    jitted = jax.jit(lambda p, lat: ffd(p, lat, basis))(points, lattice)
    np.testing.assert_allclose(np.asarray(jitted), np.asarray(eager), atol=1e-15)
    # vmap over points and designs together, then over designs with shared points.
    vmapped = jax.vmap(lambda p, lat: ffd(p, lat, basis))(points, lattice)
    np.testing.assert_allclose(np.asarray(vmapped), np.asarray(eager), atol=1e-15)
    designs = jax.vmap(lambda lat: ffd(points[0], lat, basis))(lattice)
    loop = np.stack([np.asarray(ffd(points[0], lattice[b], basis)) for b in range(3)])
    np.testing.assert_allclose(np.asarray(designs), loop, atol=1e-15)
    # jvp equals the linearisation built from the reverse-mode Jacobian.
    tangent = rng_array(31, lattice.shape, -1, 1)
    _, jvp_out = jax.jvp(lambda lat: ffd(points, lat, basis), (lattice,), (tangent,))
    np.testing.assert_allclose(np.asarray(jvp_out), np.asarray(ffd(points, tangent, basis) - points), atol=1e-14)
    # jvp in the points against central differences (points away from cell boundaries).
    x = jnp.asarray(np.random.default_rng(36).choice([0.1, 0.2, 0.4, 0.6, 0.8, 0.9], size=(6, 3)))
    dx = rng_array(37, x.shape, -1, 1)
    _, jvp_points = jax.jvp(lambda p: ffd(p, lattice[0], basis), (x,), (dx,))
    h = 1e-6
    central = (ffd(x + h * dx, lattice[0], basis) - ffd(x - h * dx, lattice[0], basis)) / (2 * h)
    np.testing.assert_allclose(np.asarray(jvp_points), np.asarray(central), atol=1e-7)
    grads = jax.vmap(jax.grad(lambda lat: jnp.sum(ffd(points[0], lat, basis) ** 2)))(lattice)
    for b in range(3):
        one = jax.grad(lambda lat: jnp.sum(ffd(points[0], lat, basis) ** 2))(lattice[b])
        np.testing.assert_allclose(np.asarray(grads[b]), np.asarray(one), atol=1e-14)


def test_box_is_not_differentiated():
    points = rng_array(32, (5, 3), 0.1, 0.9)
    lattice = rng_array(33, (3, 3, 3, 3), -0.3, 0.3)
    g_origin, g_extent = jax.grad(
        lambda o, e: jnp.sum(free_form_deform_points(points, lattice, origin=o, extent=e, implementation="jax") ** 2),
        argnums=(0, 1),
    )(jnp.zeros(3), jnp.ones(3))
    np.testing.assert_array_equal(np.asarray(g_origin), np.zeros(3))
    np.testing.assert_array_equal(np.asarray(g_extent), np.zeros(3))


@settings(max_examples=12, deadline=None)
@given(
    basis=st.sampled_from(BASES),
    dims=st.integers(1, 3),
    extra_nodes=st.integers(0, 2),
    seed=st.integers(0, 2**31 - 1),
    shift=st.floats(-10, 10, allow_nan=False),
)
def test_property_constant_lattice_is_translation(basis, dims, extra_nodes, seed, shift):
    rng = np.random.default_rng(seed)
    resolution = tuple(int(n) + extra_nodes for n in rng.integers(4 if basis == "bspline" else 2, 6, size=dims))
    origin = rng.uniform(-2, 2, size=dims)
    extent = rng.uniform(0.1, 3, size=dims)
    points = origin + extent * rng.uniform(-0.5, 1.5, size=(20, dims))
    inside = np.all((points >= origin) & (points <= origin + extent), axis=1)
    lattice = jnp.full(resolution + (dims,), shift)
    out = np.asarray(ffd(jnp.asarray(points), lattice, basis, origin=list(origin), extent=list(extent)))
    np.testing.assert_allclose(out[inside], points[inside] + shift, rtol=0, atol=1e-13 * (1 + abs(shift) + np.abs(points).max()))
    np.testing.assert_array_equal(out[~inside], points[~inside])


# ------------------------------------------------------------------------------------------
# Errors and dispatch


def good():
    return jnp.zeros((4, 3)), jnp.zeros((3, 3, 3, 3))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"points": jnp.zeros((4, 3), jnp.int32)},
        {"points": jnp.zeros((4, 3), jnp.float16)},
        {"points": [[0.0, 0.0, 0.0]]},
        {"lattice": jnp.zeros((3, 3, 3, 3), jnp.float32)},
        {"lattice": jnp.zeros((3, 3, 3, 3), jnp.int32)},
        {"origin": jnp.zeros(3, jnp.float32)},
        {"extent": jnp.ones(3, jnp.int32)},
        {"origin": 0.0},
        {"origin": "abc"},
        {"origin": [0.0, True, 0.0]},
        {"extent": [1.0, "1", 1.0]},
        {"origin": [0.0, 0.0]},  # the reference's type: "must contain exactly D real values"
        {"extent": [1.0, 1.0, 1.0, 1.0]},
        {"point_weights": jnp.ones(4, jnp.int32)},
        {"point_weights": jnp.ones(4, jnp.float32)},
        {"point_weights": [1.0, 1.0, 1.0, 1.0]},
    ],
)
def test_type_errors(kwargs):
    points, lattice = good()
    args = {"points": points, "lattice": lattice, "origin": [0.0] * 3, "extent": [1.0] * 3, "point_weights": None}
    args.update(kwargs)
    with pytest.raises(TypeError):
        free_form_deform_points(
            args["points"], args["lattice"], origin=args["origin"], extent=args["extent"], point_weights=args["point_weights"]
        )


@pytest.mark.parametrize(
    "kwargs",
    [
        {"points": jnp.zeros((4,))},
        {"points": jnp.zeros((1, 1, 4, 3))},
        {"points": jnp.zeros((4, 0))},
        {"lattice": jnp.zeros((3, 3, 3))},  # rank too small
        {"lattice": jnp.zeros((1, 3, 3, 3, 3))},  # batched lattice, unbatched points
        {"points": jnp.zeros((2, 4, 3)), "lattice": jnp.zeros((3, 3, 3, 3))},  # unbatched lattice, batched points
        {"points": jnp.zeros((2, 4, 3)), "lattice": jnp.zeros((3, 3, 3, 3, 3))},  # batch mismatch
        {"lattice": jnp.zeros((3, 3, 3, 2))},  # last axis != D
        {"lattice": jnp.zeros((3, 1, 3, 3))},  # one node on an axis
        {"lattice": jnp.zeros((3, 3, 3, 3)), "basis": "bspline"},  # bspline needs 4
        {"basis": "cubic"},
        {"basis": None},
        {"origin": [0.0, float("nan"), 0.0]},
        {"origin": [0.0, 1e400, 0.0]},
        {"extent": [1.0, 0.0, 1.0]},
        {"extent": [1.0, -1.0, 1.0]},
        {"extent": [1.0, float("inf"), 1.0]},
        {"origin": jnp.zeros((1, 3))},  # batched box with unbatched points
        {"origin": jnp.zeros(2)},
        {"origin": jnp.zeros(())},
        {"points": jnp.zeros((2, 4, 3)), "lattice": jnp.zeros((2, 3, 3, 3, 3)), "extent": jnp.ones((3, 3))},
        {"points": jnp.zeros((2, 4, 3)), "lattice": jnp.zeros((2, 3, 3, 3, 3)), "extent": jnp.ones((2, 2, 3))},
        {"point_weights": jnp.ones(5)},
        {"points": jnp.zeros((2, 4, 3)), "lattice": jnp.zeros((2, 3, 3, 3, 3)), "point_weights": jnp.ones(4)},
    ],
)
def test_value_errors(kwargs):
    points, lattice = good()
    args = {"points": points, "lattice": lattice, "origin": [0.0] * 3, "extent": [1.0] * 3, "basis": "bernstein", "point_weights": None}
    args.update(kwargs)
    with pytest.raises(ValueError):
        free_form_deform_points(
            args["points"],
            args["lattice"],
            origin=args["origin"],
            extent=args["extent"],
            basis=args["basis"],
            point_weights=args["point_weights"],
        )


def test_float32_extent_underflow_is_checked_in_points_dtype():
    points = jnp.zeros((2, 1), jnp.float32)
    with pytest.raises(ValueError):
        free_form_deform_points(points, jnp.zeros((2, 1), jnp.float32), origin=[0.0], extent=[1e-45])


def test_unknown_implementation_is_key_error():
    points, lattice = good()
    for implementation in ("cuda", 3):
        with pytest.raises(KeyError):
            free_form_deform_points(points, lattice, origin=[0.0] * 3, extent=[1.0] * 3, implementation=implementation)


def test_torch_alias_and_missing_warp(monkeypatch):
    points, lattice = good()
    out = free_form_deform_points(points, lattice, origin=[0.0] * 3, extent=[1.0] * 3, implementation="torch")
    np.testing.assert_array_equal(np.asarray(out), np.asarray(points))
    monkeypatch.setattr(dispatch, "warp_available", lambda: False)
    with pytest.raises(ImportError):
        free_form_deform_points(points, lattice, origin=[0.0] * 3, extent=[1.0] * 3, implementation="warp")
    # The default falls back to JAX without Warp, even for bases whose CPU default is Warp.
    out = free_form_deform_points(points, jnp.ones((4, 4, 4, 3)), origin=[0.0] * 3, extent=[1.0] * 3, basis="bspline")
    np.testing.assert_allclose(np.asarray(out), np.asarray(points) + 1.0, atol=1e-15)
