"""A script that ends while a Warp op still runs on an explicitly sharded array exits (issue 17).

JAX dispatches asynchronously, and under ``shard_map`` XLA runs the Warp calls on its own threads.
A script that ended without waiting for such a result (printing only its sharding, as the
README's sharding example does) hung at exit: the Warp call waited for the GIL while the
finalising interpreter waited for XLA's threads. ``warp_ffi`` now waits for pending computations
at exit. Each script runs in a fresh process with one host device (where they hung every time).
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("warp")

SETUP = """
import jax
from jax.sharding import NamedSharding, PartitionSpec as P
import geomjax
mesh = jax.make_mesh((jax.device_count(),), ("points",))
sphere = geomjax.icosphere(2)
cloud = jax.device_put(jax.random.uniform(jax.random.key(0), (1000, 3)), NamedSharding(mesh, P("points")))
"""
CALLS = {
    "morph": "jax.jit(lambda q: geomjax.morph_points(q, sphere.points[::20], 0.01 * sphere.points[::20], radius=0.5, implementation='warp'))(cloud)",
    "sdf": "jax.jit(lambda q: geomjax.signed_distance_field(sphere.points, sphere.cells, q, implementation='warp')[0])(cloud)",
}


@pytest.mark.parametrize("op", sorted(CALLS))
def test_script_ending_during_a_sharded_warp_op_exits(op):
    # The result is not waited for: only its sharding (known at once) is printed.
    script = f"{SETUP}out = {CALLS[op]}\nprint(out.sharding.spec)\n"
    env = {**os.environ, "XLA_FLAGS": ""}  # one device: the case that hung
    try:
        done = subprocess.run([sys.executable, "-c", script], cwd=Path(__file__).resolve().parents[1], env=env,
                              capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired as error:
        pytest.fail(f"the script did not exit within 60 s; it printed {error.stdout!r}")
    assert done.returncode == 0, done.stderr[-3000:]
    assert "P('points'" in done.stdout, done.stdout
