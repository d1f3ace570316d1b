"""Deformation energies: forward plus backward, Warp path against the JAX path.

Cases (float64, one process, same data for both backends):

* a tetrahedralised box, 32 x 32 x 32 cubes split into six tetrahedra each (196,608 tets,
  35,937 points; ``--quick``: 16^3, 24,576 tets), with current points = rest points + noise of
  a fifth of the grid spacing: ``simplex_strain_energy``, ``simplex_measure_energy``,
  ``total_measure_energy``, ``simplex_inversion_energy`` (``minimum_jacobian=0.9`` so that
  part of the cells is penalised);
* an icosphere with 6 subdivisions (81,920 triangles, 122,880 interior hinges; ``--quick``: 4
  subdivisions), noise of a fifth of the edge length: ``surface_bending_energy`` and
  ``closed_surface_volume_energy``.

Each timing is ``jax.jit(jax.value_and_grad(energy, argnums=(0, 1)))`` (gradients with respect
to the current and the rest points), compile excluded, best of ``--repeat`` runs of each
backend, alternating between them. Prints the Warp/JAX speed ratio per energy and the largest
relative difference between the two backends' values and gradients. Target: Warp at least 3x
faster than JAX on the tetrahedra.

Usage: ``python benchmarks/bench_energy.py [--quick] [--repeat R]``
"""

from __future__ import annotations

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import best_time, report  # noqa: E402

jax.config.update("jax_enable_x64", True)

import geomjax  # noqa: E402

TARGET_RATIO = 3.0
TET_ENERGIES = {
    "simplex_strain_energy": {},
    "simplex_measure_energy": {},
    "total_measure_energy": {},
    "simplex_inversion_energy": {"minimum_jacobian": 0.9},
}
SURFACE_ENERGIES = ("surface_bending_energy", "closed_surface_volume_energy")


def max_relative_difference(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), np.finfo(b.dtype).tiny))


def time_energy(name, points, reference, topology, kwargs, repeat):
    """``(jax_s, warp_s, max relative difference)`` of value and both gradients.

    The two backends are timed alternately (best of ``repeat`` each), so a burst of load on a
    shared machine does not land on one backend only.
    """
    energy = getattr(geomjax, name)
    functions, results = {}, {}
    for implementation in ("jax", "warp"):
        functions[implementation] = jax.jit(
            jax.value_and_grad(lambda p, r, impl=implementation: energy(p, r, topology, implementation=impl, **kwargs), argnums=(0, 1))
        )
        results[implementation] = jax.block_until_ready(functions[implementation](points, reference))  # compile
    times = {implementation: [] for implementation in functions}
    for _ in range(repeat):
        for implementation, function in functions.items():
            times[implementation].append(best_time(lambda f=function: f(points, reference), repeat=1, warmup=0))
    times = {implementation: min(values) for implementation, values in times.items()}
    (value_w, grads_w), (value_j, grads_j) = results["warp"], results["jax"]
    difference = max(max_relative_difference(value_w, value_j), *(max_relative_difference(a, b) for a, b in zip(grads_w, grads_j)))
    return times["jax"], times["warp"], difference


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="16^3 box and a 4-subdivision sphere")
    parser.add_argument("--repeat", type=int, default=10, help="best of this many runs per backend")
    args = parser.parse_args()
    rng = np.random.default_rng(0)

    cubes = 16 if args.quick else 32
    box = geomjax.tetrahedralized_box(cubes, cubes, cubes, dtype=jnp.float64)
    rest = box.points
    current = rest + jnp.asarray(0.2 / cubes * rng.normal(size=rest.shape))
    cases = [(name, current, rest, box.cells, kwargs, True) for name, kwargs in TET_ENERGIES.items()]

    sphere = geomjax.icosphere(4 if args.quick else 6, dtype=jnp.float64)
    edge_length = float(jnp.linalg.norm(sphere.points[sphere.cells[0, 1]] - sphere.points[sphere.cells[0, 0]]))
    sphere_current = sphere.points + jnp.asarray(0.2 * edge_length * rng.normal(size=sphere.points.shape))
    topology = {"surface_bending_energy": sphere.hinges, "closed_surface_volume_energy": sphere.cells}
    cases += [(name, sphere_current, sphere.points, topology[name], {}, False) for name in SURFACE_ENERGIES]

    rows = []
    for name, points, reference, topology, kwargs, targeted in cases:
        jax_s, warp_s, difference = time_energy(name, points, reference, topology, kwargs, args.repeat)
        ratio = jax_s / warp_s
        primitives = f"{topology.shape[0]} {'tets' if targeted else ('hinges' if topology.shape[1] == 4 else 'triangles')}"
        rows.append(
            {
                "case": f"{name} fwd+bwd {primitives} f64",
                "jax_s": jax_s,
                "warp_s": warp_s,
                "ratio": ratio,
                "target": TARGET_RATIO if targeted else None,
                "met": (ratio >= TARGET_RATIO) if targeted else None,
                "max_rel_diff": difference,
            }
        )
        print(f"{name}: jax {jax_s * 1e3:.1f} ms, warp {warp_s * 1e3:.1f} ms, warp {ratio:.2f}x faster, max rel diff {difference:.1e}", flush=True)

    report("energy_quick" if args.quick else "energy", rows)


if __name__ == "__main__":
    main()
