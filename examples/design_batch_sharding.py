"""Evaluate a batch of 64 FFD designs with ``jax.vmap`` and shard the batch over devices with ``jax.sharding``.

What it shows: 64 random free-form-deformation lattices (the designs: a random stretch along x
plus noise) deform the unit icosphere of
``_shape_problem.py``. One design's objective is the shape-matching loss of that problem (mean
squared signed distance to the peanut target, strain, inversion and volume energies, all geomjax
ops); ``jax.vmap`` evaluates all designs in one call. The design axis is then split over a 1-D
device mesh (``jax.sharding.Mesh``, ``NamedSharding``, ``PartitionSpec("design")``): each device
runs the vmapped evaluation on its own slice through ``jax.shard_map`` (the Warp kernels are
custom calls that XLA's automatic partitioner cannot split, so the per-device program is stated
explicitly). The script checks that the sharded objectives equal the unsharded ones and prints
both timings.

Devices: on a CPU-only machine the script sets ``XLA_FLAGS=--xla_force_host_platform_device_count=4``
before importing JAX, so the host appears as 4 devices and the sharding is real (the 4 devices
share the host's cores, so expect no speed-up beyond the core count). It does so only when
``XLA_FLAGS`` is not already set: set it yourself to choose another count (``--devices`` too),
or run on a machine with several GPUs, where the same code shards across them.

Outputs (PNG, in ``examples/output/`` or ``--output-dir``): ``design_batch_sharding.png``
(the objectives of all designs, sorted, split into their terms) and
``design_batch_sharding_designs.png`` (renders of the best and the worst designs).

Run:
    python examples/design_batch_sharding.py           # about a minute on a 2-core CPU
    python examples/design_batch_sharding.py --full    # finer sphere and lattice
    python examples/design_batch_sharding.py --smoke   # seconds; used by tests/test_examples.py
"""

from __future__ import annotations

import os

# Must happen before JAX initialises its CPU backend; a user's own XLA_FLAGS wins.
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=4")

import argparse
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from _render import figure_of_surfaces, plt, save
from _shape_problem import make_problem, objective_terms
from jax.sharding import NamedSharding, PartitionSpec

import geomjax

SIZES = {
    "smoke": {"subdivisions": 2, "lattice_shape": (4, 3, 3), "designs": 8},
    "default": {"subdivisions": 4, "lattice_shape": (6, 4, 4), "designs": 64},
    "full": {"subdivisions": 5, "lattice_shape": (8, 6, 6), "designs": 64},
}
NOISE_SCALE = 0.06  # standard deviation of the random part of the lattice displacements
MAX_STRETCH = 0.5  # the designs stretch the sphere along x by a random fraction up to this


def best_time(fn, repeats: int = 3) -> float:
    """Best wall time of ``repeats`` calls (after a warm-up call that compiles)."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    geomjax.enable_compilation_cache()  # later runs load the compiled programs instead of compiling them
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    size = parser.add_mutually_exclusive_group()
    size.add_argument("--full", action="store_true", help="full size: subdivision-5 sphere, 8x6x6 lattices")
    size.add_argument("--smoke", action="store_true", help="tiny size for the tests (8 designs, a few seconds)")
    parser.add_argument("--designs", type=int, help="override the number of designs (a multiple of the device count)")
    parser.add_argument("--devices", type=int, help="devices to shard over (default: all)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output-dir", type=Path, default=Path(__file__).parent / "output")
    args = parser.parse_args()
    config = SIZES["full" if args.full else "smoke" if args.smoke else "default"]
    num_designs = args.designs or config["designs"]
    devices = jax.devices()[: args.devices] if args.devices else jax.devices()
    if num_designs % len(devices):
        parser.error(f"--designs ({num_designs}) must be a multiple of the device count ({len(devices)})")

    problem = make_problem(config["subdivisions"], config["lattice_shape"])
    arrays = {
        name: jnp.asarray(getattr(problem, name))
        for name in ("source_points", "triangles", "target_points", "target_triangles", "probe_points", "probe_tets")
    }
    lattices = random_designs(jax.random.key(args.seed), num_designs, problem)
    print(f"{num_designs} designs: {problem.lattice_shape} lattices on a {problem.source_points.shape[0]}-vertex sphere; "
          f"{len(devices)} {devices[0].platform} devices")

    # The meshes are arguments, not captured constants: XLA would fold constant arrays of this size
    # at compile time (slowly, with "slow operation" alarms) and embed them in every program.
    def evaluate(lattice, arrays):
        terms = objective_terms(geomjax, lattice, **arrays, problem=problem)
        return {"total": sum(terms.values()), **terms}

    evaluate_batch = jax.vmap(evaluate, in_axes=(0, None))
    unsharded = jax.jit(evaluate_batch)

    mesh = jax.sharding.Mesh(np.array(devices), ("design",))
    by_design = NamedSharding(mesh, PartitionSpec("design"))
    sharded = jax.jit(jax.shard_map(evaluate_batch, mesh=mesh, in_specs=(PartitionSpec("design"), PartitionSpec()),
                                    out_specs=PartitionSpec("design")))
    sharded_lattices = jax.device_put(lattices, by_design)

    start = time.perf_counter()
    reference = jax.block_until_ready(unsharded(lattices, arrays))
    print(f"unsharded vmap: first call (with compilation) {time.perf_counter() - start:.2f} s")
    start = time.perf_counter()
    result = jax.block_until_ready(sharded(sharded_lattices, arrays))
    print(f"sharded vmap:   first call (with compilation) {time.perf_counter() - start:.2f} s")
    print(f"result sharding: {result['total'].sharding.spec}, "
          f"{len(result['total'].sharding.device_set)} devices, per-device shard shape "
          f"{result['total'].addressable_shards[0].data.shape}")

    worst_gap = max(float(jnp.max(jnp.abs(result[name] - reference[name]) / jnp.maximum(jnp.abs(reference[name]), 1e-12)))
                    for name in reference)
    print(f"sharded vs unsharded: max relative difference {worst_gap:.2e}")
    if worst_gap > 1e-5:
        raise SystemExit("the sharded objectives differ from the unsharded ones")

    unsharded_time = best_time(lambda: unsharded(lattices, arrays))
    sharded_time = best_time(lambda: sharded(sharded_lattices, arrays))
    print(f"timings (best of 3): unsharded {unsharded_time * 1e3:.1f} ms, sharded over {len(devices)} devices "
          f"{sharded_time * 1e3:.1f} ms (ratio {unsharded_time / sharded_time:.2f}x)")

    totals = np.asarray(reference["total"])
    order = np.argsort(totals)
    print(f"objective: best design {order[0]} {totals[order[0]]:.4e}, worst {order[-1]} {totals[order[-1]]:.4e}, "
          f"median {np.median(totals):.4e}")
    plot_objectives(args.output_dir / "design_batch_sharding.png", {name: np.asarray(v)[order] for name, v in reference.items()})

    shown = list(order[:3]) + list(order[-3:])
    surfaces = np.asarray(jax.vmap(lambda lattice: geomjax.free_form_deform_points(
        arrays["source_points"], lattice, origin=problem.origin, extent=problem.extent, basis="bernstein"))(lattices[np.array(shown)]))
    figure_of_surfaces(
        args.output_dir / "design_batch_sharding_designs.png",
        [{"points": surface, "triangles": problem.triangles, "colour": "tab:green" if rank < 3 else "tab:red",
          "title": f"{'best' if rank < 3 else 'worst'}: design {index}\nobjective {totals[index]:.3g}"}
         for rank, (index, surface) in enumerate(zip(shown, surfaces))],
        columns=3, panel_size=3.5,
    )


def random_designs(key, num_designs: int, problem) -> jax.Array:
    """Lattices ``(num_designs, *lattice_shape, 3)``: a random stretch along x (narrowing y and z) plus noise."""
    stretch_key, noise_key = jax.random.split(key)
    axes = [jnp.linspace(o, o + e, n, dtype=jnp.float32) for o, e, n in zip(problem.origin, problem.extent, problem.lattice_shape)]
    nodes = jnp.stack(jnp.meshgrid(*axes, indexing="ij"), axis=-1)
    stretch = jax.random.uniform(stretch_key, (num_designs, 1, 1, 1, 1), jnp.float32, 0.0, MAX_STRETCH)
    affine = stretch * nodes * jnp.array([1.0, -0.4, -0.4], jnp.float32)
    return affine + NOISE_SCALE * jax.random.normal(noise_key, affine.shape, jnp.float32)


def plot_objectives(path: Path, sorted_terms: dict[str, np.ndarray]) -> None:
    """Stacked bars of each design's weighted terms, designs sorted by their total."""
    fig, ax = plt.subplots(figsize=(10, 4))
    positions = np.arange(sorted_terms["total"].shape[0])
    bottom = np.zeros_like(sorted_terms["total"])
    for name, values in sorted_terms.items():
        if name == "total":
            continue
        ax.bar(positions, values, bottom=bottom, label=name, width=0.85)
        bottom = bottom + values
    ax.set_xlabel("design (sorted by objective)")
    ax.set_ylabel("objective")
    ax.set_title(f"{positions.size} FFD designs evaluated with vmap + sharding")
    ax.legend()
    fig.tight_layout()
    save(fig, path)


if __name__ == "__main__":
    main()
