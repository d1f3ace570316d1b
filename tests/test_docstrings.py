"""Every public function's docstring example runs and prints what it claims (doctest)."""

import doctest
import importlib
import pkgutil

import pytest

import geomjax
import torch_bridge

# The packages themselves and every module and subpackage below them (``walk_packages`` lists only
# what is below, so the package ``__init__`` docstrings are added explicitly).
MODULES = sorted(
    {package.__name__ for package in (geomjax, torch_bridge)}
    | {
        name
        for package in (geomjax, torch_bridge)
        for _, name, _ in pkgutil.walk_packages(package.__path__, package.__name__ + ".")
    }
)


@pytest.fixture
def _jax_cache_config_restored():
    """``enable_compilation_cache``'s example sets JAX's global cache directory to a temporary one;
    without this the rest of the worker's session would compile into it."""
    import jax

    saved = {name: getattr(jax.config, name) for name in ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs")}
    yield
    for name, value in saved.items():
        jax.config.update(name, value)


@pytest.mark.parametrize("module_name", MODULES)
@pytest.mark.usefixtures("_jax_cache_config_restored")
def test_docstring_examples(module_name):
    module = importlib.import_module(module_name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{result.failed} doctest example(s) failed in {module_name}"


def test_every_public_function_has_an_example():
    missing = [name for name in dir(geomjax) if not name.startswith("_") and callable(getattr(geomjax, name))
               and ">>>" not in (getattr(geomjax, name).__doc__ or "")]
    assert not missing, f"public functions without a docstring example: {missing}"
