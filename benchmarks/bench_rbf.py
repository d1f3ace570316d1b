"""Thin-plate-spline RBF deformation: fit + evaluation against scipy's RBFInterpolator.

Case: 1,000 controls uniform in [-1, 1]^3 with random displacements, evaluated at 1,000,000 query
points in float64 (``--quick``: 100,000 points). Times, in one process and on the same data:

* geomjax ``radial_basis_function_deform_points`` (fit + evaluation, jitted, compile excluded),
  with ``implementation="jax"`` and ``implementation="warp"``;
* ``scipy.interpolate.RBFInterpolator(kernel="thin_plate_spline", degree=1)``, fit + call.

Prints ratios (best scipy time / best time of ours; target >= 10x) and the largest difference
from scipy's field.
Then measures the peak resident memory of one forward AND backward pass (gradients to the points,
controls and displacements) at 1,000,000 points (``--quick``: 100,000) x 1,000 controls for both backends, each in a
fresh subprocess (target < 4 GB).

Usage: ``python benchmarks/bench_rbf.py [--quick] [--no-memory]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import best_time, peak_rss_bytes_of, report  # noqa: E402

jax.config.update("jax_enable_x64", True)

from geomjax import radial_basis_function_deform_points  # noqa: E402

NUM_CONTROLS = 1_000
TARGET_RATIO = 10.0
MEMORY_TARGET_BYTES = 4 * 10**9

MEMORY_SCRIPT = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from geomjax import radial_basis_function_deform_points as rbf
rng = np.random.default_rng(0)
controls = jnp.asarray(rng.uniform(-1, 1, ({controls}, 3)))
displacements = jnp.asarray(0.05 * rng.normal(size=({controls}, 3)))
points = jnp.asarray(rng.uniform(-1, 1, ({points}, 3)))
loss = lambda p, c, d: jnp.sum(rbf(p, c, d, implementation="{implementation}") ** 2)
value, grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))(points, controls, displacements)
jax.block_until_ready(grads)
assert all(bool(jnp.isfinite(g).all()) for g in grads)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100,000 query points instead of 1,000,000")
    parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many runs of the JAX path")
    parser.add_argument("--scipy-repeat", type=int, default=2, help="best of this many scipy runs")
    args = parser.parse_args()
    num_points = 100_000 if args.quick else 1_000_000

    rng = np.random.default_rng(0)
    controls = rng.uniform(-1.0, 1.0, (NUM_CONTROLS, 3))
    displacements = 0.05 * rng.normal(size=(NUM_CONTROLS, 3))
    points = rng.uniform(-1.0, 1.0, (num_points, 3))
    controls_j, displacements_j, points_j = (jnp.asarray(a) for a in (controls, displacements, points))

    from scipy.interpolate import RBFInterpolator

    def scipy_fit_and_call():
        return RBFInterpolator(controls, displacements, kernel="thin_plate_spline", degree=1)(points)

    scipy_field = scipy_fit_and_call()
    scipy_s = best_time(scipy_fit_and_call, repeat=args.scipy_repeat, warmup=0)  # the slow side

    rows = []
    for implementation in ("jax", "warp"):
        function = jax.jit(lambda p, c, d, impl=implementation: radial_basis_function_deform_points(p, c, d, implementation=impl))
        deformed = np.asarray(function(points_j, controls_j, displacements_j))  # compile + check
        error = float(np.abs(deformed - points - scipy_field).max())
        repeat = args.repeat if implementation == "jax" else 1
        ours_s = best_time(lambda: function(points_j, controls_j, displacements_j), repeat=repeat, warmup=0)
        ratio = scipy_s / ours_s
        rows.append(
            {
                "case": f"tps fit+eval C={NUM_CONTROLS} N={num_points} f64 [{implementation}]",
                "ours_s": ours_s,
                "scipy_s": scipy_s,
                "ratio": ratio,
                "target": TARGET_RATIO,
                "met": None if args.quick else ratio >= TARGET_RATIO,  # the target is for 1,000,000 points
                "max_abs_diff_vs_scipy": error,
            }
        )
        print(f"{implementation}: {ours_s:.3f} s, scipy {scipy_s:.3f} s, ratio {ratio:.2f}x, max |diff| {error:.2e}", flush=True)

    if not args.no_memory:
        for implementation in ("jax", "warp"):
            code = MEMORY_SCRIPT.format(controls=NUM_CONTROLS, points=num_points, implementation=implementation)
            start = time.perf_counter()
            peak = peak_rss_bytes_of(code)
            elapsed = time.perf_counter() - start
            rows.append(
                {
                    "case": f"peak RSS fwd+bwd C={NUM_CONTROLS} N={num_points} f64 [{implementation}]",
                    "peak_rss_gb": peak / 1e9,
                    "target": MEMORY_TARGET_BYTES / 1e9,
                    "met": peak < MEMORY_TARGET_BYTES,
                    "wall_s": elapsed,
                }
            )
            print(f"{implementation}: peak RSS {peak / 1e9:.2f} GB (fwd+bwd, {elapsed:.1f} s incl. start-up)", flush=True)

    report("rbf", rows)


if __name__ == "__main__":
    main()
