"""free_form_deform_points: Warp backend parity with the JAX specification."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

pytest.importorskip("warp")

import warp_ffi.ffd as warp_ffd  # noqa: E402
from geomjax import free_form_deform_points  # noqa: E402

BASES = ("bernstein", "bspline", "linear", "cubic_hermite", "quintic_hermite")


def resolution_for(basis, dims):
    return (4, 5, 6)[:dims] if basis == "bspline" else (3, 4, 5)[:dims]


def rng_array(seed, shape, low=0.0, high=1.0, dtype=jnp.float64):
    return jnp.asarray(np.random.default_rng(seed).uniform(low, high, size=shape), dtype)


def ffd(points, lattice, basis, implementation, **kwargs):
    dims = points.shape[-1]
    kwargs.setdefault("origin", [0.0] * dims)
    kwargs.setdefault("extent", [1.0] * dims)
    return free_form_deform_points(points, lattice, basis=basis, implementation=implementation, **kwargs)


@functools.cache
def _value_and_vjp(basis, implementation):
    """Jitted ``(points, lattice, weights, origin, extent, cotangent) -> (value, VJP)``: one
    program per case, where eagerly each step of the JAX path and its transpose compiles alone."""

    def run(points, lattice, weights, origin, extent, cotangent):
        def fn(p, lat, w):
            return ffd(p, lat, basis, implementation, origin=origin, extent=extent, point_weights=w)

        out, pullback = jax.vjp(fn, points, lattice, weights)
        return out, pullback(cotangent)

    return jax.jit(run)


@pytest.mark.parametrize("dtype", (jnp.float32, jnp.float64))
@pytest.mark.parametrize("dims", (1, 2, 3))
def test_values_and_vjps_match_jax(dtype, dims):
    tol = {"atol": 2e-5, "rtol": 2e-5} if dtype == jnp.float32 else {"atol": 1e-12, "rtol": 1e-12}
    origin = rng_array(1, (2, dims), -0.5, 0.0, dtype)
    extent = rng_array(2, (2, dims), 1.0, 2.0, dtype)
    points = rng_array(3, (2, 30, dims), -0.8, 2.2, dtype)
    points = points.at[0, 0].set(origin[0]).at[1, 1].set(origin[1] + extent[1])  # corners: inside
    weights = rng_array(4, (2, 30), -1.0, 2.0, dtype)
    cotangent = rng_array(5, points.shape, -1.0, 1.0, dtype)
    for i, basis in enumerate(BASES):
        lattice = rng_array(10 + i, (2,) + resolution_for(basis, dims) + (dims,), -0.5, 0.5, dtype)
        outs, vjps = {}, {}
        for impl in ("jax", "warp"):
            outs[impl], vjps[impl] = _value_and_vjp(basis, impl)(points, lattice, weights, origin, extent, cotangent)
        assert outs["warp"].dtype == dtype
        np.testing.assert_allclose(np.asarray(outs["warp"]), np.asarray(outs["jax"]), **tol, err_msg=basis)
        for name, a, b in zip(("points", "lattice", "weights"), vjps["warp"], vjps["jax"]):
            assert a.dtype == dtype
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), **tol, err_msg=f"{basis} {name}")


def test_unbatched_shared_box_and_bool_weights():
    points = rng_array(20, (40, 3), -0.5, 1.5)
    mask = jnp.asarray(np.random.default_rng(21).uniform(size=40) > 0.3)
    for basis in BASES:
        lattice = rng_array(22, resolution_for(basis, 3) + (3,), -0.5, 0.5)
        kwargs = {"origin": jnp.array([-0.2, 0.0, 0.1]), "extent": [1.2, 1.0, 0.8], "point_weights": mask}
        np.testing.assert_allclose(
            np.asarray(ffd(points, lattice, basis, "warp", **kwargs)),
            np.asarray(ffd(points, lattice, basis, "jax", **kwargs)),
            atol=1e-13,
            err_msg=basis,
        )


def test_bspline_corner_value_and_exact_identity():
    lattice = jnp.zeros((4, 4, 4, 3)).at[1, 1, 1].set(1.0)
    out = ffd(jnp.zeros((1, 3)), lattice, "bspline", "warp")
    np.testing.assert_allclose(np.asarray(out), np.full((1, 3), (4 / 6) ** 3), rtol=1e-15)
    points = rng_array(23, (20, 3), -0.5, 1.5)
    for basis in BASES:
        zero = jnp.zeros(resolution_for(basis, 3) + (3,))
        np.testing.assert_array_equal(np.asarray(ffd(points, zero, basis, "warp")), np.asarray(points))


def test_nan_and_outside_points_unchanged_with_zero_gradients():
    points = jnp.array([[0.3, 0.4, 0.5], [jnp.nan, 0.5, 0.5], [2.0, 0.5, 0.5], [1.0, 1.0, 1.0]])
    for basis in BASES:
        lattice = rng_array(24, resolution_for(basis, 3) + (3,), -0.5, 0.5)
        out = ffd(points, lattice, basis, "warp")
        np.testing.assert_array_equal(np.asarray(out[1:3]), np.asarray(points[1:3]))
        g_points, g_lattice = jax.grad(lambda p, lat: jnp.sum(ffd(p, lat, basis, "warp") ** 2), argnums=(0, 1))(points, lattice)
        keep = jnp.array([0, 3])
        g_ref = jax.grad(lambda lat: jnp.sum(ffd(points[keep], lat, basis, "jax") ** 2))(lattice)
        np.testing.assert_allclose(np.asarray(g_lattice), np.asarray(g_ref), atol=1e-13, err_msg=basis)
        np.testing.assert_array_equal(np.asarray(g_points[2]), 2 * np.asarray(points[2]))
        assert np.all(np.isfinite(np.asarray(g_points[keep])))


def test_jit_vmap_and_vmap_grad_match_jax():
    points = rng_array(25, (3, 12, 3), -0.2, 1.2)
    for basis in ("bernstein", "bspline", "quintic_hermite"):
        lattice = rng_array(26, (3,) + resolution_for(basis, 3) + (3,), -0.3, 0.3)
        eager = ffd(points, lattice, basis, "warp")
        jitted = jax.jit(lambda p, lat: ffd(p, lat, basis, "warp"))(points, lattice)  # noqa: B023
        np.testing.assert_array_equal(np.asarray(jitted), np.asarray(eager))
        designs = jax.jit(jax.vmap(lambda lat: ffd(points[0], lat, basis, "warp")))(lattice)  # noqa: B023
        reference = jax.vmap(lambda lat: ffd(points[0], lat, basis, "jax"))(lattice)  # noqa: B023
        np.testing.assert_allclose(np.asarray(designs), np.asarray(reference), atol=1e-14)
        both = jax.vmap(lambda p, lat: ffd(p, lat, basis, "warp"))(points, lattice)  # noqa: B023
        np.testing.assert_allclose(np.asarray(both), np.asarray(eager), atol=1e-14)

        def loss(impl):
            return lambda p, lat: jnp.sum(jnp.sin(ffd(p, lat, basis, impl)))  # noqa: B023

        g_warp = jax.jit(jax.vmap(jax.grad(loss("warp"), argnums=(0, 1))))(points, lattice)
        g_jax = jax.vmap(jax.grad(loss("jax"), argnums=(0, 1)))(points, lattice)
        for a, b in zip(g_warp, g_jax):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-13, err_msg=basis)


def test_finite_difference_gradients_first_order():
    coords = np.array([0.1, 0.2, 0.4, 0.6, 0.8, 0.9])  # away from cell boundaries and faces
    points = jnp.asarray(np.random.default_rng(27).choice(coords, size=(5, 3)))
    lattices = tuple(rng_array(28 + i, resolution_for(b, 3) + (3,), -0.3, 0.3) for i, b in enumerate(BASES))

    def fn(p, *lats):
        return jnp.concatenate([ffd(p, lat, b, "warp") for b, lat in zip(BASES, lats)])

    check_grads(fn, (points,) + lattices, order=1, modes=("rev",), eps=1e-5, atol=1e-6, rtol=1e-6)


def test_empty_inputs():
    for basis in ("bernstein", "linear"):
        lattice = rng_array(33, resolution_for(basis, 3) + (3,))
        empty = jnp.zeros((0, 3))
        assert ffd(empty, lattice, basis, "warp").shape == (0, 3)
        g = jax.grad(lambda lat: jnp.sum(ffd(empty, lat, basis, "warp")))(lattice)  # noqa: B023
        np.testing.assert_array_equal(np.asarray(g), np.zeros(lattice.shape))
        assert ffd(jnp.zeros((0, 4, 3)), jnp.zeros((0,) + lattice.shape), basis, "warp").shape == (0, 4, 3)


def _spy_on_the_warp_field(monkeypatch) -> list:
    """The bases of the calls that reach the Warp field from now on."""
    calls = []
    original = warp_ffd.free_form_deform_field

    def spy(*args, **kwargs):
        calls.append(kwargs["basis"])
        return original(*args, **kwargs)

    monkeypatch.setattr(warp_ffd, "free_form_deform_field", spy)
    return calls


def test_default_backend_rule_on_cpu(monkeypatch):
    calls = _spy_on_the_warp_field(monkeypatch)
    points = rng_array(34, (6, 3), 0, 1)
    free_form_deform_points(points, jnp.zeros((4, 4, 4, 3)), origin=[0.0] * 3, extent=[1.0] * 3, basis="bspline")
    free_form_deform_points(points, jnp.zeros((3, 3, 3, 3)), origin=[0.0] * 3, extent=[1.0] * 3, basis="bernstein")
    if jax.default_backend() == "cpu":
        assert calls == ["bspline"]  # CPU: Warp for local bases, JAX for Bernstein (bench_ffd.py)
    else:
        assert calls == ["bspline", "bernstein"]


# Lattices beyond the fixed kernels (more than 3 axes, more than 32 Bernstein nodes on an axis):
# the general kernels, against the closed forms of test_ffd.py (binomial Bernstein weights,
# explicit local-basis loops) and finite differences.
GENERAL_CASES = {
    "4-D bernstein float64": ("bernstein", (3, 4, 5, 2), jnp.float64),
    "4-D bspline float32": ("bspline", (4, 5, 6, 4), jnp.float32),
    "4-D quintic_hermite float64": ("quintic_hermite", (3, 4, 5, 2), jnp.float64),
    "1-D bernstein, 133 nodes, float64": ("bernstein", (133,), jnp.float64),
    "2-D bernstein, 40 x 3 nodes, float32": ("bernstein", (40, 3), jnp.float32),
}


@pytest.mark.parametrize("case", GENERAL_CASES)
def test_general_kernels_match_the_closed_forms(case):
    from .test_ffd import bernstein_closed_form, local_reference

    basis, resolution, dtype = GENERAL_CASES[case]
    dims = len(resolution)
    assert warp_ffd._needs_general((1, *resolution, dims), basis)
    points = rng_array(40, (12, dims), -0.1, 1.1, dtype)  # some outside the unit box
    lattice = rng_array(41, resolution + (dims,), -0.5, 0.5, dtype)
    out = ffd(points, lattice, basis, "warp")
    assert out.dtype == dtype
    p64, lat64 = np.asarray(points, np.float64), np.asarray(lattice, np.float64)
    if basis == "bernstein":
        inside = np.all((p64 >= 0) & (p64 <= 1), axis=1)
        expected = np.where(inside[:, None], bernstein_closed_form(p64, lat64, np.zeros(dims), np.ones(dims)), p64)
    else:
        expected = local_reference(p64, lat64, basis)
    # Convex combinations of lattice values (|v| <= 1/2): rounding grows with the sum of the
    # node counts (one recurrence step each) times eps, plus the points' own rounding.
    eps = float(jnp.finfo(dtype).eps)
    np.testing.assert_allclose(np.asarray(out, np.float64), expected, rtol=0, atol=8 * sum(resolution) * eps)
    if dtype == jnp.float64:
        # Reverse mode (the Warp adjoint kernels) against finite differences, away from faces.
        inner = rng_array(42, (4, dims), 0.1, 0.9, dtype)
        step = 1e-6 if max(resolution) > 32 else 1e-5  # degree-132 derivatives are ~n^2 larger
        check_grads(lambda p, lat: ffd(p, lat, basis, "warp"), (inner, lattice), order=1, modes=("rev",), eps=step, atol=1e-5, rtol=1e-5)


def test_default_runs_jax_beyond_the_fixed_kernels(monkeypatch):
    import geomjax.deform.ffd as ffd_module

    # geomjax decides without importing Warp: its copy of the fixed kernels' limits must match.
    assert (ffd_module.WARP_MAX_DIMS, ffd_module.WARP_MAX_BERNSTEIN_NODES) == (warp_ffd.MAX_FIXED_DIMS, warp_ffd.MAX_AXIS_NODES)
    calls = _spy_on_the_warp_field(monkeypatch)
    points4 = rng_array(34, (5, 4), 0, 1)
    lattice4 = rng_array(35, (2, 2, 2, 2, 4), -0.1, 0.1)
    default = free_form_deform_points(points4, lattice4, origin=[0.0] * 4, extent=[1.0] * 4, basis="linear")
    np.testing.assert_array_equal(np.asarray(default), np.asarray(ffd(points4, lattice4, "linear", "jax")))
    free_form_deform_points(jnp.zeros((3, 1)), jnp.zeros((33, 1)), origin=[0.0], extent=[1.0])
    assert calls == []  # neither lattice went to Warp by default
    ffd(points4, lattice4, "linear", "warp")
    assert calls == ["linear"]
