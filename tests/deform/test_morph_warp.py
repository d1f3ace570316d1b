"""morph_points: the Warp backend (hash-grid kernels, hand-written adjoint) against the JAX path.

The JAX path evaluates every point/control pair, so it is an independent brute-force check of
the Warp backend's spatial hash grid.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

pytest.importorskip("warp")

from geomjax import morph_points  # noqa: E402
from warp_ffi import morph as warp_morph  # noqa: E402

TOLERANCE = {jnp.dtype(jnp.float32): 2e-5, jnp.dtype(jnp.float64): 1e-11}


def _close(actual, expected, dtype, scale=None):
    actual, expected = np.asarray(actual, np.float64), np.asarray(expected, np.float64)
    scale = max(1.0, float(np.nanmax(np.abs(expected)))) if scale is None else scale
    tol = TOLERANCE[jnp.dtype(dtype)]
    np.testing.assert_allclose(actual, expected, rtol=tol, atol=tol * scale)


def _case(shape_points, shape_controls, dtype, seed, radius_range=(0.05, 0.6)):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1, 1, shape_points)
    controls = rng.uniform(-1, 1, shape_controls)
    points[..., 0, :] = controls[..., 0, :]  # an exact coincidence
    controls[..., 1, :] = controls[..., 2, :]  # duplicated controls
    points[..., 1, :] = controls[..., 2, :]  # ... and a point on them
    displacements = rng.normal(size=shape_controls)
    low, high = np.log(radius_range[0]), np.log(radius_range[1])
    radius = np.exp(rng.uniform(low, high, shape_controls[:-1]))
    return tuple(jnp.asarray(a, dtype) for a in (points, controls, displacements, radius))


def _loss(implementation):
    def loss(points, controls, displacements, radius, weights):
        out = morph_points(points, controls, displacements, radius=radius, point_weights=weights, implementation=implementation)
        return jnp.sum(jnp.sin(3 * out))

    return loss


@functools.cache
def _values_and_gradients(implementation):
    """Jitted ``args -> (morphed points, gradients of the loss)``: one program per case, where
    eagerly each of the JAX path's steps and their transposes would compile on their own."""

    def run(points, controls, displacements, radius, weights):
        out = morph_points(points, controls, displacements, radius=radius, point_weights=weights, implementation=implementation)
        grads = jax.grad(_loss(implementation), argnums=(0, 1, 2, 3, 4))(points, controls, displacements, radius, weights)
        return out, grads

    return jax.jit(run)


@pytest.mark.parametrize(
    ("dtype", "dim", "batched"),
    [(jnp.float32, 3, True), (jnp.float64, 3, False), (jnp.float64, 1, True), (jnp.float32, 2, False), (jnp.float64, 5, False)],
)
def test_values_and_vjps_match_jax(dtype, dim, batched):
    lead = (2,) if batched else ()
    points, controls, displacements, radius = _case((*lead, 120, dim), (*lead, 30, dim), dtype, seed=dim + 10 * batched)
    weights = jnp.asarray(np.random.default_rng(1).uniform(-1, 2, points.shape[:-1]), dtype)
    args = (points, controls, displacements, radius, weights)
    expected, grads_jax = _values_and_gradients("jax")(*args)
    actual, grads_warp = _values_and_gradients("warp")(*args)
    assert actual.dtype == dtype and actual.shape == points.shape
    _close(actual, expected, dtype)
    for g_warp, g_jax in zip(grads_warp, grads_jax, strict=True):
        _close(g_warp, g_jax, dtype)


def test_hash_grid_matches_brute_force_with_radius_spread():
    # Radii spread over 1.5 decades: the cell is sized by the largest, and small supports sit
    # anywhere in their cell, so neighbour cells and the cell culling both matter.
    points, controls, displacements, radius = _case((1500, 3), (600, 3), jnp.float64, seed=3, radius_range=(0.01, 0.3))
    rng = np.random.default_rng(4)
    # Points just either side of cell boundaries of the grid the backend builds.
    cell = float(jnp.max(radius)) * (1 + warp_morph.CELL_SLACK)
    edges = (np.round(rng.uniform(-1, 1, (200, 3)) / cell) * cell) + rng.choice([-1e-12, 0.0, 1e-12], (200, 3))
    points = jnp.concatenate([points, jnp.asarray(edges)])
    for r in (radius, jnp.max(radius)):
        expected = morph_points(points, controls, displacements, radius=r, implementation="jax")
        actual = morph_points(points, controls, displacements, radius=r, implementation="warp")
        _close(actual, expected, jnp.float64)
    assert int(jnp.sum(jnp.any(expected != points, axis=-1))) > 1000  # the supports are really hit


def test_many_controls_and_far_from_origin_in_float32():
    rng = np.random.default_rng(5)
    offset = 1000.0
    points = jnp.asarray(offset + rng.uniform(-1, 1, (3000, 3)), jnp.float32)
    controls = jnp.asarray(offset + rng.uniform(-1, 1, (4000, 3)), jnp.float32)
    displacements = jnp.asarray(rng.normal(size=(4000, 3)), jnp.float32)
    radius = jnp.asarray(rng.uniform(0.02, 0.08, 4000), jnp.float32)
    expected = morph_points(points, controls, displacements, radius=radius, implementation="jax") - points
    actual = morph_points(points, controls, displacements, radius=radius, implementation="warp") - points
    np.testing.assert_allclose(actual, expected, rtol=1e-4, atol=1e-4)
    assert float(jnp.max(jnp.abs(expected))) > 0.1


def test_special_values_agree():
    points, controls, displacements, _ = _case((40, 3), (8, 3), jnp.float64, seed=6)
    points = points.at[3].set(jnp.nan).at[4, 1].set(jnp.inf).at[5, 2].set(-jnp.inf)
    controls = controls.at[7, 0].set(jnp.nan)
    radius = jnp.array([0.5, -0.7, 0.6, 0.0, 0.4, jnp.nan, 0.9, 0.5])
    expected = morph_points(points, controls, displacements, radius=radius, implementation="jax")
    actual = morph_points(points, controls, displacements, radius=radius, implementation="warp")
    np.testing.assert_allclose(actual, expected, rtol=1e-12, atol=1e-12)  # NaNs in the same places
    assert bool(jnp.all(jnp.isnan(actual[3])))


def test_infinite_tensor_radius_agrees_with_gradients():
    points, controls, displacements, radius = _case((50, 3), (6, 3), jnp.float64, seed=7)
    radius = radius.at[4].set(jnp.inf)
    expected = morph_points(points, controls, displacements, radius=radius, implementation="jax")
    actual = morph_points(points, controls, displacements, radius=radius, implementation="warp")
    # Every finite point coincides with the infinite-radius control (points 0 and 1 also sit on
    # other controls: they get the mean over all the controls they coincide with).
    np.testing.assert_array_equal(actual[2:], points[2:] + displacements[4])
    np.testing.assert_allclose(actual[0], points[0] + (displacements[0] + displacements[4]) / 2, rtol=1e-15)
    _close(actual, expected, jnp.float64)
    weights = jnp.ones(points.shape[:-1])
    args = (points, controls, displacements, radius, weights)
    grads_warp = jax.grad(_loss("warp"), argnums=(0, 1, 2, 3))(*args)
    grads_jax = jax.grad(_loss("jax"), argnums=(0, 1, 2, 3))(*args)
    for g_warp, g_jax in zip(grads_warp, grads_jax, strict=True):
        _close(g_warp, g_jax, jnp.float64)


def test_stable_next_to_a_control_in_float64():
    _, controls, displacements, radius = _case((4, 3), (5, 3), jnp.float64, seed=8, radius_range=(0.5, 0.8))
    offsets = jnp.array([[1e-30, 0.0, 0.0], [-3e-31, 2e-30, 1e-31], [1e-300, -1e-300, 0.0], [1e-8, 0.0, 1e-8]])
    points = controls[3] + offsets * radius[3]
    weights = jnp.ones(4)
    args = (points, controls, displacements, radius, weights)
    actual = morph_points(points, controls, displacements, radius=radius, implementation="warp")
    _close(actual, morph_points(points, controls, displacements, radius=radius, implementation="jax"), jnp.float64)
    grads_warp = jax.grad(_loss("warp"), argnums=(0, 1, 2, 3))(*args)
    grads_jax = jax.grad(_loss("jax"), argnums=(0, 1, 2, 3))(*args)
    for g_warp, g_jax in zip(grads_warp, grads_jax, strict=True):
        assert bool(jnp.all(jnp.isfinite(g_warp)))
        _close(g_warp, g_jax, jnp.float64)


def test_jit_vmap_and_vmap_of_grad_match_jax():
    points, controls, displacements, radius = _case((4, 60, 3), (4, 12, 3), jnp.float64, seed=9)
    points = points[:3]

    def field(implementation):
        return lambda p, c, d: morph_points(p, c, d, radius=radius[0], implementation=implementation)

    warp_field, jax_field = field("warp"), field("jax")
    first = (points[0], controls[0], displacements[0])
    np.testing.assert_array_equal(jax.jit(warp_field)(*first), warp_field(*first))
    over_points = jax.vmap(warp_field, in_axes=(0, None, None))(points, controls[0], displacements[0])
    _close(over_points, jnp.stack([jax_field(p, controls[0], displacements[0]) for p in points]), jnp.float64)
    over_designs = jax.jit(jax.vmap(warp_field, in_axes=(None, 0, 0)))(points[0], controls, displacements)
    _close(over_designs, jax.vmap(jax_field, in_axes=(None, 0, 0))(points[0], controls, displacements), jnp.float64)

    def design_grad(implementation):
        loss = lambda c, d: jnp.sum(jnp.square(field(implementation)(points[0], c, d)))  # noqa: E731
        return jax.vmap(jax.grad(loss, argnums=(0, 1)))

    grads_warp, grads_jax = (design_grad(name)(controls, displacements) for name in ("warp", "jax"))
    for g_warp, g_jax in zip(grads_warp, grads_jax, strict=True):
        _close(g_warp, g_jax, jnp.float64)


def test_first_order_gradients_match_finite_differences():
    points = jnp.array([[0.1, 0.2, 0.0], [0.5, -0.3, 0.2], [-0.4, 0.1, 0.3], [0.05, 0.05, -0.1]])
    controls = jnp.array([[0.0, 0.1, 0.0], [0.4, -0.2, 0.1], [-0.3, 0.3, 0.2]])
    displacements = jnp.asarray(np.random.default_rng(10).normal(size=(3, 3)))
    radius = jnp.array([0.6, 0.5, 0.7])

    def f(p, c, d, r):
        return morph_points(p, c, d, radius=r, implementation="warp")

    check_grads(f, (points, controls, displacements, radius), order=1, modes=("rev",), atol=1e-5, rtol=1e-5)


def test_threaded_launch_matches_single_thread(monkeypatch):
    points, controls, displacements, radius = _case((2, 9000, 3), (2, 200, 3), jnp.float64, seed=11)
    weights = jnp.ones(points.shape[:-1])
    args = (points, controls, displacements, radius, weights)
    results = {}
    for threads in ("1", "3"):
        monkeypatch.setenv("GEOMJAX_WARP_CPU_THREADS", threads)
        value = morph_points(points, controls, displacements, radius=radius, implementation="warp")
        results[threads] = (value, jax.grad(_loss("warp"), argnums=(0, 1, 2, 3))(*args))
    np.testing.assert_array_equal(results["1"][0], results["3"][0])
    for a, b in zip(results["1"][1], results["3"][1], strict=True):
        _close(a, b, jnp.float64)  # control gradients are summed in another order
    _close(results["1"][0], morph_points(points, controls, displacements, radius=radius, implementation="jax"), jnp.float64)


def test_empty_inputs_on_warp():
    points, controls, displacements, _ = _case((10, 3), (4, 3), jnp.float32, seed=13)
    empty = jnp.zeros((0, 3), jnp.float32)
    np.testing.assert_array_equal(morph_points(points, empty, empty, radius=-1.0, implementation="warp"), points)
    assert morph_points(empty, controls, displacements, radius=0.5, implementation="warp").shape == (0, 3)
    grads = jax.grad(lambda c: morph_points(empty, c, displacements, radius=0.5, implementation="warp").sum())(controls)
    np.testing.assert_array_equal(grads, jnp.zeros_like(controls))


def test_bucket_keys_agree_between_jax_and_warp():
    wp = warp_morph.wp
    rng = np.random.default_rng(14)
    cells = rng.integers(-40, 40, (500, 3))
    cells[:4] = [[-1, -1, -1], [0, 0, 0], [2**29, -(2**29), 7], [-(2**29), 3, -4]]
    table_size = warp_morph.table_size_for(1000)

    @wp.kernel
    def keys_kernel(cells: wp.array(dtype=wp.vec3i), table_size: int, keys: wp.array(dtype=wp.int32)):
        i = wp.tid()
        c = cells[i]
        bx, rx = warp_morph._split(c[0])
        by, ry = warp_morph._split(c[1])
        bz, rz = warp_morph._split(c[2])
        # Neighbour 13 is the cell itself.
        keys[i] = warp_morph._neighbour_bucket(wp.vec3i(bx, by, bz), wp.vec3i(rx, ry, rz), 13, wp.uint32(table_size - 1))

    out = wp.zeros(len(cells), dtype=wp.int32)
    wp.launch(keys_kernel, dim=len(cells), inputs=[wp.array(cells.astype(np.int32), dtype=wp.vec3i), table_size], outputs=[out])
    expected = warp_morph._bucket_keys(jnp.asarray(cells, jnp.int32), table_size)
    np.testing.assert_array_equal(out.numpy(), np.asarray(expected))
    # The 27 neighbours of any cell fall in 27 distinct buckets.
    for c in cells[:50]:
        neighbours = c + np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
        assert len(set(np.asarray(warp_morph._bucket_keys(jnp.asarray(neighbours, jnp.int32), table_size)).tolist())) == 27
