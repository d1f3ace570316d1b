"""``torch.compile(dynamic=True)`` with real options passed as Python floats.

Under ``dynamic=True`` a Python float is symbolic. Every real option of every op (a radius, a
smoothing, a length scale, a Lamé parameter, a distance bound) must then give one graph for all
its valid values, values equal to eager calls, and for invalid values the exception that eager
calls raise, when the compiled function runs (``torch_bridge._lift``: real options reach the custom
op as 0-d tensors). Dynamo's counters count the graphs it compiles.
"""

from __future__ import annotations

import math

import pytest
import torch

import torch_bridge

from ..op_cases import CASES, torch_inputs


def _real_options(name) -> list[str]:
    """The op's real options (``float``, ``float[]``, optional or not), as the bridge's table
    reads them."""
    op = getattr(torch_bridge, name).bridged_op
    return [p.name for p in op.parameters if p.static_type is not None and p.static_type.rstrip("?") in ("float", "float[]")]


CASES_WITH_OPTIONS = [(name, option) for name in CASES for option in _real_options(name)]


def _valid_values(value) -> tuple:
    """Two valid values of an option whose case value (or default) is ``value``: it and a
    quarter more (options that are zero, absent or infinite by default take small finite ones;
    a sequence, entry by entry)."""
    if isinstance(value, (list, tuple)):
        first, second = zip(*(_valid_values(v) for v in value))
        return list(first), list(second)
    if isinstance(value, torch.Tensor):  # e.g. a radius per control point: their mean
        value = float(value.mean())
    if value is None or not math.isfinite(value):
        return 10.0, 12.5
    if value == 0.0:
        return 0.0, 0.125
    return float(value), 1.25 * float(value)


def _invalid_values(valid) -> list:
    """Values out of range for most options: NaN and -1 (each entry of a sequence), and for a
    sequence one entry too few."""
    if isinstance(valid, list):
        return [[math.nan] * len(valid), [-1.0] * len(valid), valid[:-1]]
    return [math.nan, -1.0]


def _outcome(function):
    """``("value", outputs)`` or ``("error", type, message)`` of ``function()``."""
    try:
        out = function()
    except Exception as error:  # noqa: BLE001 - the outcome is compared, whatever it is
        return ("error", type(error), str(error))
    return ("value", out if isinstance(out, tuple) else (out,))


def _assert_same(compiled, eager, context):
    assert compiled[0] == eager[0], f"{context}: compiled {compiled[:3]}, eager {eager[:3]}"
    if eager[0] == "error":
        assert compiled[1:] == eager[1:], context
        return
    for a, b in zip(compiled[1], eager[1], strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True, msg=context)


@pytest.mark.parametrize(("name", "option"), CASES_WITH_OPTIONS)
def test_real_options_are_symbolic_under_dynamic_compile(name, option):
    fn = getattr(torch_bridge, name)
    inputs = torch_inputs(name, torch.float32)
    default = next(p.default for p in fn.bridged_op.parameters if p.name == option)
    first, second = _valid_values(inputs.get(option, default))

    def run(value):
        return fn(**{**inputs, option: value})

    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    # Through AOT autograd, as every real backend: its "tensorify" pass is where a symbolic
    # float is either turned into a tensor or specialised (a guard on its value).
    compiled = torch.compile(run, fullgraph=True, dynamic=True, backend="aot_eager")
    for value in (first, second):
        eager = _outcome(lambda: run(value))
        assert eager[0] == "value", f"{name}({option}={value}) is not valid: {eager}"
        _assert_same(_outcome(lambda: compiled(value)), eager, f"{name}({option}={value})")
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    assert graphs == 1, f"{name}: {graphs} graphs for two values of {option}"
    # Out-of-range values: the eager call's outcome (its exception, type and message), raised
    # when the compiled function runs.
    for value in _invalid_values(first):
        _assert_same(_outcome(lambda: compiled(value)), _outcome(lambda: run(value)), f"{name}({option}={value})")


def test_compiled_backward_with_a_symbolic_option():
    """The autograd formula passes the option on to the VJP op as the same tensor: gradients
    for two values of a symbolic smoothing equal eager autograd's, from one forward graph."""
    fn = torch_bridge.radial_basis_function_deform_points
    inputs = torch_inputs("radial_basis_function_deform_points", torch.float64)

    def run(displacements, smoothing):
        return fn(**{**inputs, "control_displacements": displacements, "smoothing": smoothing}).square().sum()

    torch._dynamo.reset()
    torch._dynamo.utils.counters.clear()
    compiled = torch.compile(run, fullgraph=True, dynamic=True, backend="aot_eager")
    for smoothing in (0.0, 0.25):
        eager_displacements = inputs["control_displacements"].clone().requires_grad_()
        compiled_displacements = inputs["control_displacements"].clone().requires_grad_()
        run(eager_displacements, smoothing).backward()
        compiled(compiled_displacements, smoothing).backward()
        # The compiled backward runs the VJP op, eager autograd the saved linearisation: one
        # XLA program against another, equal to a few roundings of the gradient's scale.
        eps = torch.finfo(torch.float64).eps
        scale = float(eager_displacements.grad.abs().max())
        torch.testing.assert_close(compiled_displacements.grad, eager_displacements.grad, rtol=0, atol=64 * eps * scale)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1
