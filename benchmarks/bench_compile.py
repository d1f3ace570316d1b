"""Compile time against size: which ops' first call grows faster than linearly with a parameter.

Issue 14, item 3: a 1-D Bernstein lattice of 133 nodes compiled for minutes (the basis was written
out node by node). This script measures, per op and backend, the first call of a fresh shape
(tracing, lowering, XLA compile and, on the Warp path, any kernel variant that Warp builds for
it) minus a warm call of the same shape, over a range of one size parameter at a time:

* ``free_form_deform_points`` (Bernstein): nodes of a 1-D lattice (4 to 133; beyond 32 the Warp
  path runs its general kernels),
  and the resolution ``r`` of an ``r^3`` lattice (2 to 8);
* ``morph_points`` and ``radial_basis_function_deform_points``: the number of controls;
* ``displace_points``: the batch size ``B`` of ``(B, N, 3)`` points;
* ``sobolev_deform_points``: the icosphere subdivision (42 to 10,242 vertices);
* ``simplex_strain_energy``: the number of tetrahedra (``tetrahedralized_box``).

Each row gives the first-call overhead ``compile_s`` and ``growth``, the log-log slope of the
overhead between the two largest sizes (about 0 when compiling does not depend on the size, 1 when
linear; above 1 flags super-linear growth). The JAX persistent compilation cache is off and Warp's
kernel cache is a fresh temporary folder, so every first call pays in full. Sizes run from small
to large in one process: a Warp kernel that does not depend on the size is built once, at the
smallest size, which is what a user meets. Usage: ``python benchmarks/bench_compile.py [--quick]``
(``--quick``: the three smallest sizes of each case).
"""

from __future__ import annotations

import math
import os
import sys
import tempfile
import time

# A fresh Warp kernel cache before warp is imported: kernel builds count as they would for a new user.
os.environ["WARP_CACHE_PATH"] = tempfile.mkdtemp(prefix="geomjax-bench-compile-warp-")

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _harness import QUICK, block, report

jax.config.update("jax_enable_x64", True)

import geomjax as gj

RNG = np.random.default_rng(0)


def _ffd_1d(nodes: int):
    points = jnp.asarray(RNG.random((256, 1)))
    lattice = jnp.asarray(RNG.normal(size=(nodes, 1)) * 0.01)
    return lambda impl: gj.free_form_deform_points(points, lattice, origin=[0.0], extent=[1.0], implementation=impl)


def _ffd_3d(resolution: int):
    points = jnp.asarray(RNG.random((256, 3)))
    lattice = jnp.asarray(RNG.normal(size=(resolution,) * 3 + (3,)) * 0.01)
    return lambda impl: gj.free_form_deform_points(points, lattice, origin=[0.0] * 3, extent=[1.0] * 3, implementation=impl)


def _morph(controls: int):
    points, centres = jnp.asarray(RNG.random((256, 3))), jnp.asarray(RNG.random((controls, 3)))
    moves = jnp.asarray(RNG.normal(size=(controls, 3)) * 0.01)
    return lambda impl: gj.morph_points(points, centres, moves, radius=0.3, implementation=impl)


def _rbf(controls: int):
    points, centres = jnp.asarray(RNG.random((256, 3))), jnp.asarray(RNG.random((controls, 3)))
    moves = jnp.asarray(RNG.normal(size=(controls, 3)) * 0.01)
    return lambda impl: gj.radial_basis_function_deform_points(points, centres, moves, implementation=impl)


def _displace(batch: int):
    points = jnp.asarray(RNG.random((batch, 256, 3)))
    moves = jnp.asarray(RNG.normal(size=(batch, 256, 3)) * 0.01)
    return lambda impl: gj.displace_points(points, moves, implementation=impl)


def _sobolev(subdivisions: int):
    sphere = gj.icosphere(subdivisions, dtype=jnp.float64)
    moves = 0.01 * jnp.sin(3 * sphere.points)
    return lambda impl: gj.sobolev_deform_points(sphere.points, sphere.cells, moves, length_scale=0.2, implementation=impl)


def _strain(cells_per_axis: int):
    box = gj.tetrahedralized_box(cells_per_axis, cells_per_axis, cells_per_axis)
    moved = box.points + 0.01 * jnp.sin(3 * box.points)
    return lambda impl: gj.simplex_strain_energy(moved, box.points, box.cells, implementation=impl)


# (op, parameter, builder, sizes, backends); a backend given as (name, largest size) stops there.
CASES = [
    ("free_form_deform_points", "1-D Bernstein nodes", _ffd_1d, (4, 8, 16, 32, 64, 133), ("jax", "warp")),
    ("free_form_deform_points", "r of an r^3 Bernstein lattice", _ffd_3d, (2, 3, 4, 6, 8), ("jax", "warp")),
    ("morph_points", "controls", _morph, (10, 100, 1000, 10000), ("jax", "warp")),
    ("radial_basis_function_deform_points", "controls", _rbf, (10, 100, 1000), ("jax", "warp")),
    ("displace_points", "batch", _displace, (1, 8, 64), ("jax",)),  # no Warp path: one fused XLA op
    ("sobolev_deform_points", "icosphere subdivisions", _sobolev, (1, 2, 3, 4, 5), ("jax", "warp")),
    ("simplex_strain_energy", "cells per axis of a box", _strain, (2, 4, 8, 12), ("jax", "warp")),
]


def _first_call_overhead(call) -> tuple[float, float]:
    """``(first call - warm call, warm call)`` in seconds."""
    start = time.perf_counter()
    block(call())
    first = time.perf_counter() - start
    warm = min(_timed(call) for _ in range(3))
    return max(first - warm, 0.0), warm


def _timed(call) -> float:
    start = time.perf_counter()
    block(call())
    return time.perf_counter() - start


def main() -> None:
    rows = []
    for op, parameter, build, sizes, backends in CASES:
        sizes = sizes[:3] if QUICK else sizes
        for backend in backends:
            name, largest = backend if isinstance(backend, tuple) else (backend, max(sizes))
            measured = []
            for size in (s for s in sizes if s <= largest):
                jax.clear_caches()  # no traced or compiled program carries over between sizes
                seconds, warm = _first_call_overhead(lambda: build(size)(name))
                measured.append((size, seconds))
                rows.append({"op": op, "parameter": parameter, "size": size, "backend": name, "compile_s": seconds, "warm_s": warm})
                print(f"{op} [{name}] {parameter}={size}: first call +{seconds:.2f} s over warm {warm * 1e3:.1f} ms", flush=True)
            if len(measured) >= 2:
                (small, t_small), (large, t_large) = measured[-2], measured[-1]
                rows[-1]["growth"] = math.log(max(t_large, 1e-3) / max(t_small, 1e-3)) / math.log(large / small)
    report("compile", rows)


if __name__ == "__main__":
    main()
