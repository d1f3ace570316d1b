"""Benchmark free_form_deform_points against PyGeM's FFD, and JAX against Warp.

    python benchmarks/bench_ffd.py [--quick]

Cases (float64):
* Bernstein FFD, 5x5x5 lattice, 1,000,000 points (100,000 with --quick): geomjax (JAX and
  Warp) against PyGeM's ``FFD``. Both are checked to give the same deformed points (to 1e-10)
  before timing, so the comparison is like for like. Target: geomjax >= 10x faster.
* Forward + backward (grad w.r.t. points and lattice) for JAX and Warp, every basis; the other
  bases are also reported as time ratios to Bernstein.
* Peak RSS of Bernstein forward + backward, 1,000,000 points, 10x10x10 lattice, each backend in
  a fresh subprocess. Target: under 4 GB.

PyGeM: the FFD of mathLab's PyGeM (``from pygem import FFD``) is used when installed. The PyPI
package named ``pygem`` is an unrelated glacier model, so where ``pygem.FFD`` is missing the
benchmark runs ``pygem_algorithm_ffd`` below instead: PyGeM's FFD algorithm written out in NumPy
(map to the unit box through the inverse box frame, closed-form Bernstein tables per axis,
then a Python loop over the lattice nodes accumulating vectorised products, and the map back).
The report says which one ran.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from scipy import special  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks._harness import best_time, peak_rss_bytes_of, report  # noqa: E402
from geomjax import free_form_deform_points  # noqa: E402

BASES = ("bernstein", "bspline", "linear", "cubic_hermite", "quintic_hermite")


def pygem_algorithm_ffd(points, control_displacements, origin, extent):
    """PyGeM's FFD algorithm in NumPy (unrotated box); ``array_mu`` is in box-length units."""
    mu = control_displacements / extent  # PyGeM's array_mu_{x,y,z}
    frame = np.diag(extent)
    reference = (points - origin) @ np.linalg.inv(frame).T
    mask = np.all((reference >= 0.0) & (reference <= 1.0), axis=1)
    mesh = reference[mask]
    tables = []
    for d, n in enumerate(mu.shape[:3]):
        table = np.zeros((n, len(mesh)))
        for i in range(n):
            table[i] = special.binom(n - 1, i) * np.power(1 - mesh[:, d], n - 1 - i) * np.power(mesh[:, d], i)
        tables.append(table)
    bx, by, bz = tables
    aux_x = aux_y = aux_z = 0.0
    for j in range(mu.shape[1]):
        for k in range(mu.shape[2]):
            byz = by[j] * bz[k]
            for i in range(mu.shape[0]):
                aux = bx[i] * byz
                aux_x = aux_x + aux * mu[i, j, k, 0]
                aux_y = aux_y + aux * mu[i, j, k, 1]
                aux_z = aux_z + aux * mu[i, j, k, 2]
    shifted = mesh + np.stack([aux_x, aux_y, aux_z], axis=1)
    out = points.copy()
    out[mask] = shifted @ frame.T + origin
    return out


def pygem_baseline(control_displacements, origin, extent):
    """Return ``(name, fn(points))``: mathLab PyGeM's FFD if installed, else its algorithm."""
    try:
        from pygem import FFD  # mathLab PyGeM >= 2

        ffd = FFD(list(control_displacements.shape[:3]))
        ffd.box_origin = np.asarray(origin, dtype=float)
        ffd.box_length = np.asarray(extent, dtype=float)
        ffd.array_mu_x = control_displacements[..., 0] / extent[0]
        ffd.array_mu_y = control_displacements[..., 1] / extent[1]
        ffd.array_mu_z = control_displacements[..., 2] / extent[2]
        return "pygem.FFD", ffd
    except Exception:
        return "PyGeM algorithm (NumPy; pygem.FFD not installed)", lambda p: pygem_algorithm_ffd(
            p, control_displacements, origin, extent
        )


def memory_code(implementation: str, num_points: int) -> str:
    return f"""
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from geomjax import free_form_deform_points
points = jnp.asarray(np.random.default_rng(0).uniform(-0.05, 1.05, size=({num_points}, 3)))
lattice = jnp.asarray(np.random.default_rng(1).normal(size=(10, 10, 10, 3)) * 0.01)
def loss(points, lattice):
    out = free_form_deform_points(points, lattice, origin=[0.0, 0.0, 0.0], extent=[1.0, 1.0, 1.0],
                                  implementation={implementation!r})
    return jnp.sum(out ** 2)
value, grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1)))(points, lattice)
jax.block_until_ready(grads)
"""


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true", help="100,000 points and fewer repeats")
    args = parser.parse_args()
    num_points = 100_000 if args.quick else 1_000_000
    repeat = 2 if args.quick else 3
    rows = []
    # --- Memory first: a child's ru_maxrss starts from this process's RSS (Linux keeps the peak
    # across fork/exec), so it is measured before this process allocates its own large arrays.
    for implementation in ("jax", "warp"):
        peak = peak_rss_bytes_of(memory_code(implementation, 1_000_000))
        rows.append(
            {
                "case": f"peak RSS bernstein 10^3 fwd+bwd, N=1000000 ({implementation})",
                "peak_GB": peak / 1e9,
                "target": "< 4 GB",
                "met": peak < 4e9,
            }
        )

    rng = np.random.default_rng(0)
    origin = np.array([-0.1, 0.2, -0.3])
    extent = np.array([1.2, 0.8, 1.5])
    points_np = origin + extent * rng.uniform(-0.05, 1.05, size=(num_points, 3))
    lattice_np = rng.normal(size=(5, 5, 5, 3)) * 0.05
    points, lattice = jnp.asarray(points_np), jnp.asarray(lattice_np)
    box = {"origin": jnp.asarray(origin), "extent": jnp.asarray(extent)}

    def forward(basis, implementation):
        return jax.jit(lambda p, lat: free_form_deform_points(p, lat, basis=basis, implementation=implementation, **box))

    def forward_backward(basis, implementation):
        def loss(p, lat):
            return jnp.sum(free_form_deform_points(p, lat, basis=basis, implementation=implementation, **box) ** 2)

        return jax.jit(jax.grad(loss, argnums=(0, 1)))

    # --- Bernstein 5^3 against PyGeM ------------------------------------------------------
    baseline_name, baseline = pygem_baseline(lattice_np, origin, extent)
    reference = baseline(points_np)
    times = {}
    for implementation in ("jax", "warp"):
        fn = forward("bernstein", implementation)
        ours = np.asarray(fn(points, lattice))
        error = float(np.max(np.abs(ours - reference)))
        assert error < 1e-10, f"{implementation} differs from {baseline_name} by {error}"
        times[implementation] = best_time(lambda fn=fn: fn(points, lattice), repeat=2 * repeat)
    # Best of several runs for both sides: on a shared machine the minimum is the least noisy.
    times["pygem"] = best_time(lambda: baseline(points_np), repeat=2 * repeat, warmup=0)
    for implementation in ("jax", "warp"):
        rows.append(
            {
                "case": f"bernstein 5^3 fwd, N={num_points}: {implementation} vs {baseline_name}",
                "ours_s": times[implementation],
                "baseline_s": times["pygem"],
                "speedup": times["pygem"] / times[implementation],
                "target": ">= 10",
                "met": times["pygem"] / times[implementation] >= 10,
            }
        )

    # --- JAX vs Warp, every basis, forward and forward+backward ---------------------------
    basis_times = {}
    for basis in BASES:
        lat = jnp.asarray(rng.normal(size=(5, 5, 5, 3)) * 0.05)
        for mode, make in (("fwd", forward), ("fwd+bwd", forward_backward)):
            for implementation in ("jax", "warp"):
                fn = make(basis, implementation)
                basis_times[basis, mode, implementation] = best_time(lambda fn=fn: fn(points, lat), repeat=repeat)
            jax_s, warp_s = basis_times[basis, mode, "jax"], basis_times[basis, mode, "warp"]
            rows.append(
                {
                    "case": f"{basis} 5^3 {mode}, N={num_points}: warp/jax time",
                    "ours_s": jax_s,
                    "baseline_s": warp_s,
                    "speedup": warp_s / jax_s,
                    "target": "default = faster",
                }
            )
    for basis in BASES[1:]:
        for implementation in ("jax", "warp"):
            ratio = basis_times[basis, "fwd", implementation] / basis_times["bernstein", "fwd", implementation]
            rows.append({"case": f"{basis}/bernstein fwd time ({implementation})", "speedup": ratio})

    report("ffd", rows)


if __name__ == "__main__":
    main()
