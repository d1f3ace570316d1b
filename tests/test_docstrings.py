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


@pytest.mark.parametrize("module_name", MODULES)
def test_docstring_examples(module_name):
    module = importlib.import_module(module_name)
    result = doctest.testmod(module, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE, verbose=False)
    assert result.failed == 0, f"{result.failed} doctest example(s) failed in {module_name}"


def test_every_public_function_has_an_example():
    missing = [name for name in dir(geomjax) if not name.startswith("_") and callable(getattr(geomjax, name))
               and ">>>" not in (getattr(geomjax, name).__doc__ or "")]
    assert not missing, f"public functions without a docstring example: {missing}"
