"""geomjax.enable_compilation_cache: programs compiled by one process are reused by the next.

Each run is a fresh interpreter (the persistent cache is only read by later processes). The
second run must load every program from the cache (no new entries), give the same values, and a
failed runtime check in a cached program must still report its own message.
"""

import json
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax, jax.numpy as jnp
    import geomjax

    geomjax.enable_compilation_cache(sys.argv[1])
    sphere = geomjax.icosphere(1)
    controls = sphere.points[:6]

    @jax.jit
    def loss(points):
        moved = geomjax.morph_points(points, controls, 0.1 * controls, radius=0.8)  # the Warp default
        return jnp.sum(moved**2)

    value, gradient = jax.value_and_grad(loss)(sphere.points)
    fit = jax.jit(lambda c: geomjax.radial_basis_function_deform_points(c, c, jnp.ones_like(c)))
    try:
        jax.block_until_ready(fit(jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])))
        message = None
    except Exception as error:
        message = str(error)
    print(json.dumps({"value": float(value), "gradient": float(jnp.sum(gradient**2)), "message": message}))
    """
)


def _run(cache_dir):
    result = subprocess.run([sys.executable, "-c", SCRIPT, str(cache_dir)], capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout.strip().splitlines()[-1])


def _entries(cache_dir):
    return sorted(p.name for p in cache_dir.rglob("*") if p.is_file())


def test_second_process_loads_every_program_from_the_cache(tmp_path):
    first = _run(tmp_path)
    written = _entries(tmp_path)
    assert written, "the first process wrote no compiled programs"
    second = _run(tmp_path)
    assert _entries(tmp_path) == written  # every program of the second run was a cache hit
    assert second == first
    assert first["message"].startswith("FAILED_PRECONDITION: radial_basis_function_deform_points: the thin-plate-spline fit system is singular")
