"""Compact Wendland-C2 Shepard morphing: the Warp hash-grid backend against the JAX path.

Points and controls uniform in [-1, 1]^3, 1,000,000 points (``--quick``: 100,000), float32 by
default (``--dtype float64``). Cases and targets (2-core CPU):

* 1,000 controls, radius 0.5: forward + backward (gradient of ``sum(out**2)`` with respect to
  the points, controls and displacements) < 2 s;
* 100,000 controls, radius 0.1 (~50 controls in range per point): forward + backward < 3 s;
* dense worst case, 1,000 controls, radius 4 (every control in range of every point):
  forward < 10 s.

Every case is timed for ``implementation="warp"`` and ``implementation="jax"`` in this process
(jitted, compile excluded) and the ratio JAX / Warp is printed. The JAX path evaluates every
point/control pair, so with 100,000 controls it is timed on 10,000 points and scaled linearly
(marked "extrapolated"; ``--quick``: on 100 points). The Warp rows are also timed with one CPU thread to show the speed-up
of the split launches. Finally the peak resident memory of one forward AND backward pass at
1,000,000 points x 1,000 controls is measured for both backends, each in a fresh subprocess
(target < 4 GB).

Usage: ``python benchmarks/bench_morph.py [--quick] [--dtype float64] [--no-memory]``
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
from _harness import best_time, block, peak_rss_bytes_of, report  # noqa: E402

jax.config.update("jax_enable_x64", True)

from geomjax import morph_points  # noqa: E402

MEMORY_TARGET_BYTES = 4 * 10**9
THREADS_ENV = "GEOMJAX_WARP_CPU_THREADS"

# (name, controls, radius, with backward, target seconds)
CASES = [
    ("C=1000 r=0.5 fwd+bwd", 1_000, 0.5, True, 2.0),
    ("C=100000 r=0.1 fwd+bwd", 100_000, 0.1, True, 3.0),
    ("dense C=1000 r=4 fwd", 1_000, 4.0, False, 10.0),
    ("C=1000 r=0.5 fwd", 1_000, 0.5, False, None),
    ("C=100000 r=0.1 fwd", 100_000, 0.1, False, None),
]

MEMORY_SCRIPT = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from geomjax import morph_points
rng = np.random.default_rng(0)
dtype = jnp.{dtype}
points = jnp.asarray(rng.uniform(-1, 1, ({points}, 3)), dtype)
controls = jnp.asarray(rng.uniform(-1, 1, ({controls}, 3)), dtype)
displacements = jnp.asarray(0.05 * rng.normal(size=({controls}, 3)), dtype)
loss = lambda p, c, d: jnp.sum(morph_points(p, c, d, radius=0.5, implementation="{implementation}") ** 2)
value, grads = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))(points, controls, displacements)
jax.block_until_ready(grads)
assert all(bool(jnp.isfinite(g).all()) for g in grads)
"""


def make_function(implementation: str, radius: float, backward: bool):
    def field(p, c, d):
        return morph_points(p, c, d, radius=radius, implementation=implementation)

    if not backward:
        return jax.jit(field)
    return jax.jit(jax.grad(lambda p, c, d: jnp.sum(field(p, c, d) ** 2), argnums=(0, 1, 2)))


def data(num_points: int, num_controls: int, dtype, seed: int = 0):
    rng = np.random.default_rng(seed)
    points = jnp.asarray(rng.uniform(-1, 1, (num_points, 3)), dtype)
    controls = jnp.asarray(rng.uniform(-1, 1, (num_controls, 3)), dtype)
    displacements = jnp.asarray(0.05 * rng.normal(size=(num_controls, 3)), dtype)
    return points, controls, displacements


def timed(fn, args, repeat: int, warmup: int = 1) -> float:
    return best_time(lambda: fn(*args), repeat=repeat, warmup=warmup)


def set_threads(value: str | None) -> None:
    """Warp CPU worker threads for the next calls (``None``: the default, one per CPU)."""
    if value is None:
        os.environ.pop(THREADS_ENV, None)
    else:
        os.environ[THREADS_ENV] = value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="100,000 points instead of 1,000,000")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--no-memory", action="store_true", help="skip the peak-memory subprocesses")
    parser.add_argument("--repeat", type=int, default=3, help="best of this many Warp runs")
    args = parser.parse_args()
    dtype = jnp.dtype(args.dtype)
    num_points = 100_000 if args.quick else 1_000_000
    threads = os.environ.get(THREADS_ENV)

    rows = []
    for name, num_controls, radius, backward, target in CASES:
        points, controls, displacements = data(num_points, num_controls, dtype)
        warp_fn = make_function("warp", radius, backward)
        set_threads(threads)
        warp_s = timed(warp_fn, (points, controls, displacements), args.repeat)
        set_threads("1")
        warp_1t_s = timed(warp_fn, (points, controls, displacements), 1, warmup=0)
        set_threads(threads)

        # The JAX path is O(N C): time it on fewer points where that would take minutes (10,000 of
        # 1,000,000; 100 of a --quick run's 100,000, which has a minute for all its cases).
        jax_points = num_points if num_controls <= 1_000 else num_points // (1_000 if args.quick else 100)
        jax_fn = make_function("jax", radius, backward)
        sub = (points[:jax_points], controls, displacements)
        start = time.perf_counter()
        block(jax_fn(*sub))  # compile (and a first run: the slow side gets no more repeats)
        jax_s = timed(jax_fn, sub, 1, warmup=0) if time.perf_counter() - start < 300 else time.perf_counter() - start
        jax_s *= num_points / jax_points

        # Agreement of the two backends on the first 10,000 points (no more than the JAX path was
        # timed on: with 100,000 controls, 10,000 of its points take minutes in a --quick run).
        check = (points[: min(10_000, jax_points)], controls, displacements)
        pairs = zip(jax.tree.leaves(warp_fn(*check)), jax.tree.leaves(jax_fn(*check)), strict=True)
        diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in pairs)
        rows.append(
            {
                "case": f"{name} N={num_points} {args.dtype}",
                "warp_s": warp_s,
                "warp_1thread_s": warp_1t_s,
                "jax_s": jax_s,
                "jax_note": "measured" if jax_points == num_points else f"extrapolated from {jax_points} points",
                "ratio_jax_over_warp": jax_s / warp_s,
                "thread_speedup": warp_1t_s / warp_s,
                "target_s": target,
                "met": None if target is None or args.quick else warp_s < target,
                "max_abs_diff_warp_vs_jax": diff,
            }
        )
        print(rows[-1], flush=True)

    if not args.no_memory:
        for implementation in ("jax", "warp"):
            code = MEMORY_SCRIPT.format(points=num_points, controls=1_000, implementation=implementation, dtype=args.dtype)
            peak = peak_rss_bytes_of(code)
            rows.append(
                {
                    "case": f"peak RSS fwd+bwd C=1000 r=0.5 N={num_points} {args.dtype} [{implementation}]",
                    "peak_rss_gb": peak / 1e9,
                    "target_gb": MEMORY_TARGET_BYTES / 1e9,
                    "met": peak < MEMORY_TARGET_BYTES,
                }
            )
            print(rows[-1], flush=True)

    report("morph_quick" if args.quick else "morph", rows)


if __name__ == "__main__":
    main()
