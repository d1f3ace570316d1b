"""First calls: import, first value-and-gradient call with empty and with warm caches, steady state.

Issue 26, item 5. For every op of the case table (``tests/op_cases.py``, float32, the small inputs
the tests use), two fresh Python processes share one cache folder (JAX's persistent compilation
cache through :func:`geomjax.enable_compilation_cache`, and Warp's kernel cache through
``WARP_CACHE_PATH``), which starts empty:

* ``import_s``: ``import geomjax`` in the first process;
* ``first_cold_s``: the first value-and-gradient call (``jax.value_and_grad`` of the case's loss
  over its differentiated arrays; the value alone for the ops that are not differentiable:
  sampling, remeshing, voxel fractions), traced, compiled and Warp kernels built, caches empty;
* ``first_warm_s``: the same first call in the second process, with the caches the first one
  filled (what a user meets from the second run of a script on);
* ``steady_s``: the best of three later calls.

Target (issue 26): ``first_warm_s`` under 2 s for every op.

Table ``startup_scripts``: the README demo (``examples/deform_demo.py``) and every ``python``
code block of the README, each run as a whole Python process twice on one empty cache folder
(``GEOMJAX_CACHE_DIR`` and ``WARP_CACHE_PATH``; the blocks are run after
``geomjax.enable_compilation_cache()``, as the README advises): wall time with the caches empty,
then warm. Target: under 10 s warm. The multi-host block needs several processes; it is run by
``examples/multiprocess_design_batch.py`` (``tests/test_multiprocess.py``), not here.

Usage: ``python benchmarks/bench_startup.py [--quick] [--only name,name] [--scripts-only]``
(``--quick``: four ops and no scripts).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
TARGET_S = 2.0
SCRIPT_TARGET_S = 10.0
QUICK_OPS = ("morph_points", "free_form_deform_points", "signed_distance_field", "simplex_strain_energy")


def child(name: str, cache: str) -> None:
    """One process: import, first call, steady state; prints one JSON line."""
    start = time.perf_counter()
    import jax

    import geomjax

    import_s = time.perf_counter() - start
    geomjax.enable_compilation_cache(cache)
    sys.path.insert(0, str(REPO))
    import jax.numpy as jnp

    from tests.op_cases import CASES

    case = CASES[name](jnp.float32)
    arrays = case.arrays
    if case.differentiated:
        argnums = tuple(range(len(arrays)))
        call = lambda: jax.value_and_grad(case.loss(), argnums=argnums)(*arrays)  # noqa: E731
    else:
        call = lambda: case.call(*arrays)  # noqa: E731
    start = time.perf_counter()
    jax.block_until_ready(call())
    first_s = time.perf_counter() - start
    steady_s = float("inf")
    for _ in range(3):
        start = time.perf_counter()
        jax.block_until_ready(call())
        steady_s = min(steady_s, time.perf_counter() - start)
    print(json.dumps({"import_s": import_s, "first_s": first_s, "steady_s": steady_s}))


def _run_child(name: str, cache: str) -> dict:
    env = {**os.environ, "WARP_CACHE_PATH": str(Path(cache) / "warp"), "JAX_ENABLE_X64": "1"}
    done = subprocess.run([sys.executable, __file__, "--child", name, cache], env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{name}: child failed\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def readme_blocks() -> list[tuple[str, str]]:
    """``(label, code)`` of the README's ``python`` blocks, without the multi-host one."""
    chunks = (REPO / "README.md").read_text().split("```python\n")
    blocks = []
    for before, part in zip(chunks, chunks[1:]):  # each block with the text just before it
        if before.rstrip().endswith("<!-- multihost-code -->"):
            continue
        code = part.split("```", 1)[0]
        first = next(line for line in code.splitlines() if line.strip() and not line.startswith(("import", "from")))
        blocks.append((f"README block: {first.strip()[:48].rstrip()}", code))
    return blocks


def _timed_process(command: list[str], cache: str) -> float:
    env = {**os.environ, "GEOMJAX_CACHE_DIR": str(Path(cache) / "jax"), "WARP_CACHE_PATH": str(Path(cache) / "warp")}
    start = time.perf_counter()
    done = subprocess.run(command, cwd=REPO, env=env, capture_output=True, text=True, check=False)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{command[-1][:200]!r} failed\n{done.stderr[-3000:]}")
    return seconds


def script_rows() -> list[dict]:
    scripts = [("examples/deform_demo.py", [sys.executable, "examples/deform_demo.py", "--output", "%OUT%/deform_demo.png"])]
    for label, code in readme_blocks():
        scripts.append((label, [sys.executable, "-c", "import geomjax; geomjax.enable_compilation_cache()\n" + code]))
    rows = []
    for label, command in scripts:
        with tempfile.TemporaryDirectory(prefix="geomjax-startup-") as cache:
            command = [part.replace("%OUT%", cache) for part in command]
            cold, warm = _timed_process(command, cache), _timed_process(command, cache)
        rows.append({"script": label, "first_cold_s": cold, "first_warm_s": warm, "met": warm < SCRIPT_TARGET_S})
        print(f"{label}: {cold:.1f} s cold, {warm:.1f} s warm", flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", default="")
    parser.add_argument("--scripts-only", action="store_true")
    parser.add_argument("--child", nargs=2, metavar=("NAME", "CACHE"))
    args = parser.parse_args()
    if args.child:
        child(*args.child)
        return
    sys.path.insert(0, str(HERE))
    sys.path.insert(0, str(REPO))
    from _harness import report

    if not args.quick and not args.only:
        report("startup_scripts", script_rows())
    if args.scripts_only:
        return

    from tests.op_cases import CASES

    names = [n for n in CASES if (not args.only or n in args.only.split(",")) and (not args.quick or n in QUICK_OPS)]
    rows = []
    for name in names:
        with tempfile.TemporaryDirectory(prefix="geomjax-startup-") as cache:
            cold = _run_child(name, cache)
            warm = _run_child(name, cache)
        row = {
            "op": name,
            "import_s": cold["import_s"],
            "first_cold_s": cold["first_s"],
            "first_warm_s": warm["first_s"],
            "steady_s": warm["steady_s"],
            "met": warm["first_s"] < TARGET_S,
        }
        rows.append(row)
        print(
            f"{name}: import {row['import_s']:.2f} s, first call {row['first_cold_s']:.2f} s cold / {row['first_warm_s']:.2f} s warm, "
            f"steady {row['steady_s'] * 1e3:.1f} ms",
            flush=True,
        )
    report("startup_quick" if args.quick else "startup", rows)


if __name__ == "__main__":
    main()
