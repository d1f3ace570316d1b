"""The example scripts run end to end at their ``--smoke`` size and do what they claim.

All the scripts start together in one module fixture (separate processes, so they overlap their
JAX/Warp/torch start-up and compilation on the available cores); each test then checks one
script's exit status, its PNG files and the figures it prints.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXAMPLES = {
    "shape_optimization_jax": ["shape_optimization_jax.png", "shape_optimization_jax_loss.png"],
    "shape_optimization_torch": ["shape_optimization_torch.png", "shape_optimization_torch_loss.png"],
    "sobolev_smoothing": ["sobolev_smoothing.png", "sobolev_smoothing_loss.png"],
    "design_batch_sharding": ["design_batch_sharding.png", "design_batch_sharding_designs.png"],
    "register_template": ["register_template.png"],
}
TIMEOUT_S = 300


@pytest.fixture(scope="module")
def smoke_runs(tmp_path_factory):
    """``{name: (returncode, stdout + stderr, output_dir, stderr)}`` of every example run with ``--smoke``."""
    pytest.importorskip("matplotlib")
    pytest.importorskip("tqdm")
    names = [name for name in EXAMPLES if name != "shape_optimization_torch" or importlib.util.find_spec("torch")]
    # XLA's cheap optimisation level and the session's XLA_FLAGS (tests/conftest.py): the scripts
    # are checked for what they do, and compiling is most of their time; the README demo and the
    # wheel check (.ci/run) compile at the default level.
    env = {**os.environ, "JAX_DISABLE_MOST_OPTIMIZATIONS": "1"}
    # Progress bars are tqdm's only use of stderr; without them stderr must be empty.
    env["TQDM_DISABLE"] = "1"
    # Without the caller's XLA_FLAGS the sharding example creates its 4 host devices itself.
    sharding_env = {key: value for key, value in env.items() if key != "XLA_FLAGS"}
    processes = {}
    for name in names:
        output_dir = tmp_path_factory.mktemp(name)
        command = [sys.executable, str(REPO / "examples" / f"{name}.py"), "--smoke", "--output-dir", str(output_dir)]
        own_env = sharding_env if name == "design_batch_sharding" else env
        processes[name] = (subprocess.Popen(command, cwd=REPO, env=own_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                            text=True), output_dir)
    runs = {}
    try:
        for name, (process, output_dir) in processes.items():
            output, errors = process.communicate(timeout=TIMEOUT_S)
            runs[name] = (process.returncode, output + errors, output_dir, errors)
    finally:
        for process, _ in processes.values():
            if process.poll() is None:
                process.kill()
                process.wait()
    return runs


def _checked_run(smoke_runs, name: str) -> str:
    if name not in smoke_runs:
        pytest.skip(f"{name}.py needs torch")
    returncode, output, output_dir, _ = smoke_runs[name]
    assert returncode == 0, f"{name}.py --smoke exited with {returncode}:\n{output[-4000:]}"
    for png in EXAMPLES[name]:
        path = output_dir / png
        assert path.is_file(), f"{name}.py did not write {png}:\n{output[-2000:]}"
        assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", f"{png} is not a PNG file"
    return output


def _losses(output: str) -> tuple[float, float]:
    match = re.search(r"^loss: initial (\S+) final (\S+)$", output, re.MULTILINE)
    assert match, f"no 'loss: initial ... final ...' line in:\n{output[-2000:]}"
    return float(match.group(1)), float(match.group(2))


@pytest.mark.parametrize("name", ["shape_optimization_jax", "shape_optimization_torch"])
def test_shape_optimization_loss_falls(smoke_runs, name):
    output = _checked_run(smoke_runs, name)
    initial, final = _losses(output)
    assert final < 0.1 * initial, f"loss fell only from {initial} to {final}"
    mean_before, mean_after = map(float, re.search(r"distance to target: mean (\S+) -> (\S+),", output).groups())
    assert mean_after < 0.5 * mean_before


def test_jax_and_torch_examples_optimise_the_same_function(smoke_runs):
    jax_losses = _losses(_checked_run(smoke_runs, "shape_optimization_jax"))
    torch_losses = _losses(_checked_run(smoke_runs, "shape_optimization_torch"))
    # The same objective at the same start, through geomjax and through torch_bridge ...
    assert jax_losses[0] == pytest.approx(torch_losses[0], rel=1e-5)
    # ... minimised by optimistix's L-BFGS and by torch's Adam in the same number of steps: the
    # quasi-Newton method ends lower (about 20x at the smoke size).
    assert jax_losses[1] < torch_losses[1]


def test_sobolev_descent_is_smooth_and_converges(smoke_runs):
    output = _checked_run(smoke_runs, "sobolev_smoothing")
    initial, final = _losses(output)
    assert final < 0.1 * initial
    bending = {name: float(value) for name, value in re.findall(r"(raw|Sobolev) gradient: .*bending energy (\S+),", output)}
    assert bending["Sobolev"] < bending["raw"], output[-2000:]


def test_design_batch_sharding_matches_unsharded(smoke_runs):
    output = _checked_run(smoke_runs, "design_batch_sharding")
    assert "4 cpu devices" in output or "gpu devices" in output
    gap = float(re.search(r"max relative difference (\S+)", output).group(1))
    assert gap <= 1e-5


def test_registration_lands_on_the_target(smoke_runs):
    output = _checked_run(smoke_runs, "register_template")
    mean_before, mean_after = map(float, re.search(r"distance to target: mean (\S+) -> (\S+),", output).groups())
    assert mean_after < 0.1 * mean_before, output[-2000:]


@pytest.mark.parametrize("name", sorted(EXAMPLES))
def test_examples_print_nothing_to_stderr(smoke_runs, name):
    # No Warp CUDA-driver warning, no XLA slow-operation alarm, no PyTorch fallback warning.
    _checked_run(smoke_runs, name)
    errors = smoke_runs[name][3]
    assert errors == "", errors[-4000:]
