"""Sharded-vs-unsharded cases, run on 4 host devices in one subprocess by ``tests/test_sharding.py``.

``python -m tests.sharding_cases RESULT.json`` needs ``XLA_FLAGS=--xla_force_host_platform_device_count=4``
set before JAX starts (the parent test sets it). Every case runs an op under ``jax.jit`` on
inputs sharded over a 4-device mesh and on the same inputs on one device, and compares values
(and gradients for some) and the output sharding. Meshes: ``jax.make_mesh``'s default
``Explicit`` axes (sharding in types: the ops run per shard through ``jax.shard_map``) and
``Auto`` axes (XLA's partitioner decides). ``CASES`` maps each case name to a function that
raises ``AssertionError`` on failure; it is built without touching any device, so the parent
process can import it to parametrize.

The one-op value cases take their inputs from the one case table (``tests/op_cases.py``) and
their backends from geomjax's registry; the scenarios after them (gradients through chained ops,
the energies, a 2-D device mesh, eager and replicated calls, Sobolev) build their own inputs,
whose layouts are the point of those cases.
"""

from __future__ import annotations

import contextlib
import functools
import json
import sys
import traceback

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import AxisType, NamedSharding
from jax.sharding import PartitionSpec as P

import geomjax as g
from geomjax._registry import REGISTRY

NUM_DEVICES = 4
NUM_DESIGNS = 8
TOLERANCE = {"float32": 2e-5, "float64": 1e-11}
CASES = {}


def case(name):
    def register(fn):
        CASES[name] = fn
        return fn

    return register


@functools.cache
def mesh(axis_type: str):
    return jax.make_mesh((NUM_DEVICES,), ("d",), axis_types=(getattr(AxisType, axis_type),))


def shard(x, axis_type: str, axis: int):
    spec = P(*([None] * axis), "d")
    return jax.device_put(x, NamedSharding(mesh(axis_type), spec))


def close(actual, expected, dtype):
    actual, expected = jax.tree.leaves(actual), jax.tree.leaves(expected)
    for a, e in zip(actual, expected, strict=True):
        a, e = np.asarray(a, np.float64), np.asarray(e, np.float64)
        tol = TOLERANCE[dtype]
        scale = max(1.0, float(np.nanmax(np.abs(e)))) if e.size else 1.0
        np.testing.assert_allclose(a, e, rtol=tol, atol=tol * scale)


def sharded_axis(x, axis: int) -> bool:
    """Whether ``x`` is split over the 4 devices along ``axis``."""
    spec = tuple(x.sharding.spec) + (None,) * x.ndim
    return spec[axis] == "d"


def check(fn, inputs, sharded_inputs, dtype, *, keep_axis: int | None):
    """``jit(fn)`` on sharded inputs equals it on unsharded ones; ``keep_axis`` stays split."""
    expected = jax.jit(fn)(*inputs)
    actual = jax.jit(fn)(*sharded_inputs)
    close(actual, expected, dtype)
    if keep_axis is not None:
        for leaf in jax.tree.leaves(actual):
            assert sharded_axis(leaf, keep_axis), f"output sharding {leaf.sharding} does not split axis {keep_axis}"


def rng_array(seed, shape, dtype, scale=1.0):
    return jnp.asarray(np.random.default_rng(seed).uniform(-scale, scale, shape), dtype)


def design_batch(dtype, num_points=48, num_controls=6):
    points = rng_array(0, (NUM_DESIGNS, num_points, 3), dtype)
    controls = rng_array(1, (NUM_DESIGNS, num_controls, 3), dtype)
    displacements = rng_array(2, (NUM_DESIGNS, num_controls, 3), dtype, 0.1)
    return points, controls, displacements


def lattices(dtype):
    return rng_array(3, (NUM_DESIGNS, 3, 3, 3, 3), dtype, 0.1)


def ffd(points, lattice, impl):
    return g.free_form_deform_points(points, lattice, origin=[-1.0] * 3, extent=[2.0] * 3, implementation=impl)


def morph(points, controls, displacements, impl, radius=0.8):
    return g.morph_points(points, controls, displacements, radius=radius, implementation=impl)


def rbf(points, controls, displacements, impl):
    return g.radial_basis_function_deform_points(points, controls, displacements, implementation=impl)


# Which axis of the output is expected to stay split: always under Explicit axes (the ops run
# per shard); under Auto axes only for the JAX paths, since XLA's partitioner gathers the inputs
# of Warp's FFI calls (see the op docstrings), so there only values are checked.
def kept(axis_type, impl, axis=0):
    return axis if axis_type == "Explicit" or impl == "jax" else None


# The ops whose values are compared sharded and unsharded, on the inputs of the one case table
# (tests/op_cases.py): a batch of designs split over the designs (the table's arrays stacked
# where its in_axes is 0), and the queries of one design split over the points.
SHARDED_OPS = ("displace_points", "morph_points", "radial_basis_function_deform_points", "free_form_deform_points", "signed_distance_field")
# The per-point arrays of a case (split with the queries); the others (controls, lattices, meshes)
# are replicated.
POINT_ARRAYS = frozenset({"points", "displacement", "point_weights", "input_points"})


def table_case(name: str, dtype: str):
    # Imported here: the table builds arrays, which must wait for main()'s x64 setting.
    from tests.op_cases import CASES as TABLE

    return TABLE[name](jnp.dtype(dtype))


def design_values(name, axis_type, impl, dtype):
    c = table_case(name, dtype)
    rng = np.random.default_rng(SHARDED_OPS.index(name))
    designs = tuple(
        a if axis is None else jnp.asarray(np.asarray(a, np.float64)[None] + 0.02 * rng.normal(size=(NUM_DESIGNS, *a.shape)), a.dtype)
        for a, axis in zip(c.arrays, c.in_axes)
    )  # fmt: skip
    sharded = [a if axis is None else shard(a, axis_type, 0) for a, axis in zip(designs, c.in_axes)]
    check(lambda *a: c.call(*a, implementation=impl), designs, sharded, dtype, keep_axis=kept(axis_type, impl))


def query_values(name, axis_type, impl, dtype):
    c = table_case(name, dtype)
    assert c.arrays[c.arg_names.index(next(n for n in c.arg_names if n in POINT_ARRAYS))].shape[0] % NUM_DEVICES == 0
    sharded = [shard(a, axis_type, 0) if n in POINT_ARRAYS else a for n, a in zip(c.arg_names, c.arrays)]
    check(lambda *a: c.call(*a, implementation=impl), c.arrays, sharded, dtype, keep_axis=kept(axis_type, impl))


def design_grad(axis_type, impl):
    dtype = "float64"
    points, controls, displacements = design_batch(dtype)
    lattice = lattices(dtype)

    def objective(displacements, lattice):
        moved = morph(points, controls, displacements, impl)
        moved = rbf(moved, controls, displacements, impl)
        return jnp.sum(jnp.square(ffd(moved, lattice, impl)))

    fn = jax.grad(objective, argnums=(0, 1))
    args = (displacements, lattice)
    check(fn, args, [shard(a, axis_type, 0) for a in args], dtype, keep_axis=kept(axis_type, impl))


def query_grad(axis_type, impl):
    # Split queries with replicated controls and mesh: the gradients of the replicated inputs
    # are partial sums on each device that must be added up.
    dtype = "float64"
    points = rng_array(4, (512, 3), dtype)
    _, controls, displacements = design_batch(dtype, num_controls=12)
    sphere = g.icosphere(1, dtype=dtype)

    def objective(points, controls, displacements, vertices):
        moved = rbf(points, controls, displacements, impl)
        if impl == "jax":  # compile time: the JAX morph and SDF are covered elsewhere
            return jnp.sum(jnp.square(moved))
        moved = morph(moved, controls, displacements, impl)
        sdf = g.signed_distance_field(vertices, sphere.cells, moved, implementation=impl)[0]
        return jnp.sum(jnp.square(sdf))

    fn = jax.grad(objective, argnums=(0, 1, 2, 3))
    args = (points, controls[0], displacements[0], sphere.points)
    sharded = (shard(points, axis_type, 0), *args[1:])
    check(fn, args, sharded, dtype, keep_axis=None)
    if kept(axis_type, impl) is not None:
        grads = jax.jit(fn)(*sharded)
        assert sharded_axis(grads[0], 0), f"point gradient sharding {grads[0].sharding}"


def design_energies(axis_type, impl):
    dtype = "float64"
    sphere = g.icosphere(1, dtype=dtype)
    box = g.tetrahedralized_box(2, 2, 2, dtype=dtype)
    surface = sphere.points + rng_array(6, (NUM_DESIGNS, *sphere.points.shape), dtype, 0.05)
    solid = box.points + rng_array(7, (NUM_DESIGNS, *box.points.shape), dtype, 0.05)
    # vmap over an explicitly split axis does not reach Warp's FFI calls (their sequential
    # batching is a scan, which JAX refuses over a split axis); the batched form does.
    vmapped = not (axis_type == "Explicit" and impl == "warp")

    def energies(surface, solid):
        rest_surface = jnp.broadcast_to(sphere.points, surface.shape)
        rest_solid = jnp.broadcast_to(box.points, solid.shape)
        terms = [g.closed_surface_volume_energy(surface, rest_surface, sphere.cells, target_ratio=1.1, reduction="none", implementation=impl)]
        if impl == "warp":
            # Each Warp energy has its own per-shard call; the JAX energies are plain XLA code,
            # slow to compile here, so the volume stands for them.
            terms.append(g.simplex_strain_energy(solid, rest_solid, box.cells, reduction="none", implementation=impl).sum(-1))
            terms.append(g.surface_bending_energy(surface, rest_surface, sphere.hinges, reduction="none", implementation=impl).sum(-1))
            terms.append(g.simplex_measure_energy(surface, rest_surface, sphere.cells, reduction="none", implementation=impl).sum(-1))
            terms.append(g.simplex_inversion_energy(solid, rest_solid, box.cells, reduction="none", implementation=impl).sum(-1))
        if vmapped:

            def one(s, x):
                volume = g.closed_surface_volume_energy(s, sphere.points, sphere.cells, target_ratio=1.1, implementation=impl)
                return volume + g.total_measure_energy(x, box.points, box.cells, implementation=impl)

            terms.append(jax.vmap(one)(surface, solid))
        return jnp.stack(terms, axis=-1)

    args = (surface, solid)
    sharded = [shard(a, axis_type, 0) for a in args]
    total = jax.grad(lambda s, x: jnp.sum(energies(s, x)), argnums=(0, 1))
    # Under jax.set_mesh, as explicit sharding asks of a vmap over a split axis: without it JAX
    # 0.12 cannot type the gradient of any gather there (not only ours).
    with jax.set_mesh(mesh(axis_type)) if axis_type == "Explicit" and vmapped else contextlib.nullcontext():
        check(energies, args, sharded, dtype, keep_axis=kept(axis_type, impl))
        check(total, args, sharded, dtype, keep_axis=kept(axis_type, impl))


# Compilation dominates the run time: float32 (a separate Warp kernel variant) runs for the Warp
# paths under Explicit axes, and Auto axes (where the ops run unchanged) only get float64.
VALUE_CONFIGS = [
    ("Explicit", "jax", "float64"),
    ("Explicit", "warp", "float32"),
    ("Explicit", "warp", "float64"),
    ("Auto", "jax", "float64"),
    ("Auto", "warp", "float64"),
]
GRADIENT_CONFIGS = [
    ("Explicit", "jax", (design_grad, query_grad, design_energies)),
    ("Explicit", "warp", (design_grad, query_grad, design_energies)),
    ("Auto", "warp", (design_grad, design_energies)),
]

for _axis_type, _impl, _dtype in VALUE_CONFIGS:
    for _name in SHARDED_OPS:
        if _impl not in REGISTRY[_name].backends:
            continue
        if (_axis_type, _impl, _name) == ("Auto", "jax", "signed_distance_field"):
            continue  # under Auto axes the JAX SDF is ordinary XLA partitioning of slow-to-compile code
        for _values in (design_values, query_values):
            _label = _values.__name__.split("_")[0]
            case(f"{_label}-{_name}-{_axis_type}-{_impl}-{_dtype}")(functools.partial(_values, _name, _axis_type, _impl, _dtype))
for _axis_type, _impl, _fns in GRADIENT_CONFIGS:
    for _fn in _fns:
        case(f"{_fn.__name__.replace('_', '-')}-{_axis_type}-{_impl}")(functools.partial(_fn, _axis_type, _impl))


def sobolev_design_batch(implementation: str):
    """``(smooth, (points, displacement))``: a batch of sphere designs and their Sobolev smoothing."""
    sphere = g.icosphere(1, dtype="float64")
    points = jnp.broadcast_to(sphere.points, (NUM_DESIGNS, *sphere.points.shape))
    displacement = rng_array(10, points.shape, "float64", 0.01)

    def smooth(p, d):
        return g.sobolev_deform_points(p, sphere.cells, d, length_scale=0.3, implementation=implementation)

    return smooth, (points, displacement)


@case("design-sobolev-Explicit-warp")
def _():
    # Values only (its gradient compiles slowly; checked by hand when this was written).
    deform, args = sobolev_design_batch("warp")
    check(deform, args, [shard(a, "Explicit", 0) for a in args], "float64", keep_axis=0)


@case("design-sobolev-Explicit-jax")
def _():
    # The JAX path solves shard by shard, like the Warp path: values and gradients, and the
    # compiled forward moves no design between devices (no all-gather, which placing the solve
    # on Auto axes did: every device then solved the whole batch).
    smooth, (points, displacement) = sobolev_design_batch("jax")

    def objective(p, d):
        return jnp.sum(jnp.sin(smooth(p, d)))

    fn = jax.value_and_grad(objective, argnums=(0, 1))
    split = [shard(a, "Explicit", 0) for a in (points, displacement)]
    expected = jax.jit(fn)(points, displacement)
    actual = jax.jit(fn)(*split)
    close(actual, expected, "float64")
    assert sharded_axis(actual[1][0], 0) and sharded_axis(actual[1][1], 0), actual[1][0].sharding.spec
    forward = jax.jit(smooth).lower(*split).compile().as_text()
    assert "all-gather" not in forward and "all-to-all" not in forward, "the forward solve moves designs between devices"


@case("query-rays-and-shrinkwrap-Explicit")
def _():
    # Split rays and points against a replicated mesh, both backends; every output keeps the split
    # (the miss encoding's inf distances compare equal in place).
    sphere = g.icosphere(2, dtype="float64")
    origins = rng_array(11, (32, 3), "float64", 1.2)
    directions = -origins / jnp.linalg.norm(origins, axis=1, keepdims=True)
    for impl in ("jax", "warp"):

        def rays(o, d, impl=impl):
            return g.ray_mesh_intersect(sphere.points, sphere.cells, o, d, implementation=impl)

        def wrap(p, impl=impl):
            return g.shrinkwrap_points(p, sphere.points, sphere.cells, implementation=impl)

        check(rays, (origins, directions), [shard(a, "Explicit", 0) for a in (origins, directions)], "float64", keep_axis=0)
        check(wrap, (origins,), [shard(origins, "Explicit", 0)], "float64", keep_axis=0)


@case("design-and-query-morph-Explicit")
def _():
    # A 2 x 2 mesh splitting designs and points at once; the controls (split over designs only)
    # get per-device partial gradients that are summed over the point axis.
    grid = jax.make_mesh((2, 2), ("designs", "points"))
    points, controls, displacements = design_batch("float64")
    split_points = jax.device_put(points, NamedSharding(grid, P("designs", "points")))
    split_controls = [jax.device_put(a, NamedSharding(grid, P("designs"))) for a in (controls, displacements)]
    for impl in ("jax", "warp"):

        def objective(p, c, d, impl=impl):
            return jnp.sum(jnp.square(morph(p, c, d, impl)))

        fn = jax.value_and_grad(objective, argnums=(0, 1, 2))
        expected = jax.jit(fn)(points, controls, displacements)
        actual = jax.jit(fn)(split_points, *split_controls)
        close(actual, expected, "float64")
        spec = tuple(actual[1][0].sharding.spec)
        assert spec[:2] == ("designs", "points"), f"point gradient sharding {spec}"


@case("query-eager-Explicit")
def _():
    # Outside jit, on concrete sharded arrays (shard_map on a concrete mesh).
    points = rng_array(4, (256, 3), "float64")
    _, controls, displacements = design_batch("float64")
    sharded = shard(points, "Explicit", 0)
    for impl in ("jax", "warp"):
        out = morph(sharded, controls[0], displacements[0], impl)
        close(out, morph(points, controls[0], displacements[0], impl), "float64")
        assert sharded_axis(out, 0), f"eager output sharding {out.sharding}"


@case("query-replicated-Explicit")
def _():
    # Replicated inputs on an Explicit mesh: nothing to split, the ops run as without a mesh.
    points = rng_array(4, (1024, 3), "float64")
    _, controls, displacements = design_batch("float64")
    replicated = jax.device_put(points, NamedSharding(mesh("Explicit"), P()))
    fn = functools.partial(morph, controls=controls[0], displacements=displacements[0], impl="warp")
    check(fn, (points,), (replicated,), "float64", keep_axis=None)


@case("design-fps-and-voxels-Explicit")
def _():
    # A split batch of clouds and of meshes: farthest-point sampling (its own batch axis, jitted
    # and eager; indices exactly equal) and the JAX voxel fractions under vmap (whose run-time
    # checks, a cond on the batch, must keep the split).
    sphere = g.icosphere(1, dtype="float64")
    designs = sphere.points + rng_array(12, (NUM_DESIGNS, *sphere.points.shape), "float64", 0.05)
    split = shard(designs, "Explicit", 0)
    expected = g.farthest_point_sampling(designs, 12)
    for call in (jax.jit(lambda x: g.farthest_point_sampling(x, 12)), lambda x: g.farthest_point_sampling(x, 12)):
        np.testing.assert_array_equal(call(split), expected)

    def voxels(x):
        return g.mesh_to_voxel_fraction(x, sphere.cells, [-1.2] * 3, 0.3, (8, 8, 8), n_samples=8, implementation="jax")

    # Under jax.set_mesh, as JAX's explicit sharding asks of a vmap over a split axis (JAX 0.12
    # refuses it without: its platform_dependent batching looks the axis up in an empty mesh).
    with jax.set_mesh(mesh("Explicit")):
        check(jax.vmap(voxels), (designs,), (split,), "float64", keep_axis=0)


@case("host-ops-under-set_mesh")
def _():
    # Remeshing and sampling run on one device; under jax.set_mesh (as the README's multi-host
    # code runs) and on arrays replicated over the 4 devices they give the plain call's result.
    # The Warp backend only: the JAX one's programs take half a minute to compile, and the
    # wrapper that leaves the context mesh and the reading of replicated inputs are shared.
    sphere = g.icosphere(2, dtype="float64")
    replicated = [jax.device_put(a, NamedSharding(mesh("Explicit"), P())) for a in (sphere.points, sphere.cells)]
    expected = (
        g.remeshing(sphere.points, sphere.cells, 60, implementation="warp"),
        g.mesh_poisson_disk_sample(sphere.points, sphere.cells, 0.3, implementation="warp"),
    )
    with jax.set_mesh(mesh("Explicit")):
        actual = (g.remeshing(*replicated, 60, implementation="warp"), g.mesh_poisson_disk_sample(*replicated, 0.3, implementation="warp"))
    for a, e in zip(jax.tree.leaves(actual), jax.tree.leaves(expected), strict=True):
        np.testing.assert_array_equal(a, e)


def main(path: str) -> None:
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_dtype_promotion", "strict")
    assert jax.device_count() == NUM_DEVICES, f"expected {NUM_DEVICES} host devices, got {jax.devices()}"
    results = {}
    for name, fn in CASES.items():
        try:
            fn()
            results[name] = {"ok": True}
        except Exception:  # noqa: BLE001 - every failure is reported as that case's result
            results[name] = {"ok": False, "error": traceback.format_exc(limit=6)}
    with open(path, "w") as f:
        json.dump(results, f)


if __name__ == "__main__":
    main(sys.argv[1])
