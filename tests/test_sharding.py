"""Ops under ``jax.jit`` with inputs sharded over 4 devices equal the unsharded results.

The cases live in ``tests/sharding_cases.py`` and need 4 host devices, which must be configured
before JAX starts; this process has already started JAX with one device. So the whole set runs
once, in one subprocess (start-up paid once), and each case is reported as its own test here.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("warp")

from tests.sharding_cases import CASES, NUM_DEVICES

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def results(tmp_path_factory):
    path = tmp_path_factory.mktemp("sharding") / "results.json"
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={NUM_DEVICES}".strip()
    env["JAX_PLATFORMS"] = "cpu"
    # XLA's cheap optimisation level, as in the test session (tests/conftest.py): compiling the
    # sharded programs is this subprocess's whole cost.
    env["JAX_DISABLE_MOST_OPTIMIZATIONS"] = "1"
    run = subprocess.run(
        [sys.executable, "-m", "tests.sharding_cases", str(path)],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert run.returncode == 0, f"sharding subprocess failed ({run.returncode}):\n{run.stdout[-4000:]}\n{run.stderr[-4000:]}"
    return json.loads(path.read_text())


@pytest.mark.parametrize("name", sorted(CASES))
def test_sharded_equals_unsharded(results, name):
    assert name in results, f"case {name} did not run"
    result = results[name]
    assert result["ok"], result["error"]
