"""Test-session configuration: float64 available and strict dtype promotion (DESIGN.md)."""

import gc
import os

os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


def _has_gpu() -> bool:
    try:
        return any(d.platform == "gpu" for d in jax.devices())
    except RuntimeError:
        return False


def pytest_collection_modifyitems(config, items):
    if _has_gpu():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_executables():
    """Drop JAX's compiled executables after every test module.

    Each XLA CPU executable keeps a few anonymous memory mappings for its JIT-compiled code, and
    the suite compiles tens of thousands of programs. Kept for the whole session they approach
    Linux's per-process limit (``vm.max_map_count``, 65530 by default), where the next
    compilation crashes the interpreter (CI saw SIGSEGV/SIGABRT inside ``backend_compile``).
    """
    yield
    jax.clear_caches()
    gc.collect()
