"""Several JAX processes on one machine: ops on arrays split across processes agree with one process.

Each case starts ``num_processes`` Python processes of ``tests/multiprocess_worker.py`` with
``devices`` host devices each, coordinated by ``jax.distributed`` on 127.0.0.1 only (a free
port; Gloo collectives on CPU). Every process builds its rows of the global inputs with
``jax.make_array_from_process_local_data``, runs the op jitted on the global arrays and compares
its rows with the same computation unsharded (issue 17): SDF on split query points, and FFD and
RBF on split points with the gradient of their replicated lattice or control displacements (a
cross-process sum), each on both backends; the six energies per design and cell over a split
batch of designs, and morphing of it, on both backends; displacement, farthest-point sampling and
vmapped voxel fractions of it on the JAX backend; Sobolev smoothing of a split batch of designs, eager and
jitted, on both backends. ``examples/multiprocess_design_batch.py`` (the README's multi-host
code, checked to be the same text) runs as 2 x 2 and 4 x 1 processes. Every op on split arrays
runs jitted and eagerly (an eager op must not read another process's rows); remeshing and
Poisson sampling run on each process's own mesh, and on one mesh replicated over every process,
and are compared with the same calls here. Processes are bounded in time and always cleaned up.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("warp")

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 180  # per case a set of processes runs
# float64 values: the split computation and the unsharded one differ by rounding at most.
TOLERANCE = 1e-10


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def run_processes(cases: str, num_processes: int, devices: int) -> list[dict]:
    """Every process's JSON results for ``cases`` (comma-separated: one result per case and
    process); raises with the processes' output on failure."""
    port = _free_port()
    command = [sys.executable, "-m", "tests.multiprocess_worker", cases]
    processes = [
        subprocess.Popen([*command, str(i), str(num_processes), str(port), str(devices)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        for i in range(num_processes)
    ]
    outputs = []
    try:
        for process in processes:
            out, err = process.communicate(timeout=TIMEOUT_S * len(cases.split(",")))
            outputs.append((process.returncode, out, err))
    finally:
        for process in processes:
            if process.poll() is None:
                process.kill()
                process.wait()
    results = []
    for code, out, err in outputs:
        assert code == 0, f"{cases}: a process exited with {code}:\n{err[-3000:]}"
        # (Warp may print its module loads among them.)
        lines = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
        assert len(lines) == len(cases.split(",")), out[-3000:]
        results += lines
    return results


# Each set of processes runs its cases one after the other (starting and joining the processes
# costs more than most cases); a case without a backend suffix runs both backends.
CASES = [
    ("sdf,ffd,rbf,batch-ops,rays,shrinkwrap,sobolev", 2, 2),
    ("sdf-jax", 4, 1),
]  # fmt: skip


@pytest.mark.multiprocess
@pytest.mark.parametrize(("cases", "num_processes", "devices"), CASES)
def test_split_arrays_agree_with_one_process(cases, num_processes, devices):
    results = run_processes(cases, num_processes, devices)
    assert sorted(r["case"] for r in results) == sorted(cases.split(",") * num_processes)
    for case in cases.split(","):
        of_case = [r for r in results if r["case"] == case]
        assert sorted(r["process"] for r in of_case) == list(range(num_processes)), case
        assert all(r["devices"] == num_processes * devices for r in of_case), case
        covered = sorted(tuple(r["rows"]) for r in of_case)
        assert covered[0][0] == 0 and all(a[1] == b[0] for a, b in zip(covered, covered[1:])), (case, covered)  # every row, once
        for r in of_case:
            assert set(r["per_backend"]) == ({case} if case.endswith("-jax") else {f"{case}-jax", f"{case}-warp"}), r
            assert r["max_relative_difference"] <= TOLERANCE, r


def test_readme_multihost_code_is_the_example_code():
    readme = (REPO / "README.md").read_text()
    block = readme.split("<!-- multihost-code -->\n```python\n", 1)[1].split("```", 1)[0]
    example = (REPO / "examples" / "multiprocess_design_batch.py").read_text()
    section = example.split("    # README multi-host (start)\n", 1)[1].split("    # README multi-host (end)\n", 1)[0]
    assert block == textwrap.dedent(section)


@pytest.mark.multiprocess
@pytest.mark.parametrize(("num_processes", "devices"), [(2, 2), (4, 1)])
def test_multiprocess_design_batch_example_agrees_with_one_process(num_processes, devices):
    # The example starts its own processes on 127.0.0.1 (a free port, bounded, cleaned up) and
    # runs the README's code in each; every process compares its rows with the whole batch.
    command = [sys.executable, str(REPO / "examples" / "multiprocess_design_batch.py"), "--processes", str(num_processes),
               "--devices", str(devices), "--timeout", str(TIMEOUT_S)]  # fmt: skip
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=TIMEOUT_S + 30, check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    assert sorted(map(int, re.findall(r"^process (\d+):", done.stdout, re.MULTILINE))) == list(range(num_processes)), done.stdout
    assert f"{num_processes * devices} devices in all" in done.stdout, done.stdout
    gap = float(re.search(r"max relative difference to one process: (\S+)", done.stdout).group(1))
    assert gap <= TOLERANCE, done.stdout


@pytest.mark.multiprocess
def test_per_process_meshes_match_one_process():
    import geomjax as gj
    from tests.multiprocess_worker import per_process_mesh_summary

    results = run_processes("per-process-meshes", 2, 2)
    for r in sorted(results, key=lambda r: r["process"]):
        expected = per_process_mesh_summary(gj, r["process"])
        assert r["summary"][:3] == expected[:3]  # vertex, triangle and sample counts
        # Sums of |coordinates| of float32 outputs: the per-thread chunks of a Warp launch may
        # round differently with another number of host devices and threads.
        np.testing.assert_allclose(r["summary"][3:], expected[3:], rtol=64 * np.finfo(np.float32).eps)


@pytest.mark.multiprocess
def test_meshes_spanning_processes_match_one_process():
    # Remeshing and sampling a mesh held as replicated arrays over every process's devices, with
    # and without the mesh in context (jax.set_mesh), as the same calls on one process's arrays;
    # and its voxel fractions on both backends, jitted and eager.
    import geomjax as gj
    from tests.multiprocess_worker import per_process_mesh_summary

    expected = per_process_mesh_summary(gj, 0)
    for r in run_processes("global-meshes", 2, 2):
        for summary in r["summaries"]:
            assert summary[:3] == expected[:3]
            np.testing.assert_allclose(summary[3:], expected[3:], rtol=64 * np.finfo(np.float32).eps)
        assert r["split_error"].startswith("remeshing: mesh_vertices is split across processes"), r["split_error"]
        assert r["max_relative_difference"] <= TOLERANCE, r  # voxel fractions of the replicated mesh
