"""torch.func transforms through bridged ops: grad, vjp, jvp, jacrev, jacfwd, hessian and vmap of
every differentiable op (default implementation), each against plain autograd or a Python loop.

Inputs are the small float64 cases of the case table (``tests/op_cases.py``); the transforms are taken with respect to
``points``, the argument every op shares. Compile time dominates, so each op is seen at one shape.
"""

from __future__ import annotations

import warnings

import pytest
import torch

import torch_bridge
from torch_bridge._ops import OPS

from ..op_cases import BATCH, torch_inputs

NAMES = [op.name for op in OPS]
TOLERANCE = {"rtol": 1e-9, "atol": 1e-12}
# Forward- and reverse-mode PCG solves stop at different iterates (same tolerance, other residual).
SOLVER_TOLERANCE = {"sobolev_deform_points": {"rtol": 1e-7, "atol": 1e-10}}


def _inputs(name):
    return torch_inputs(name, torch.float64)


def _function_of_points(name, inputs):
    fn = getattr(torch_bridge, name)
    return lambda points: fn(**{**inputs, "points": points})


def _scalar(output):
    return output if output.ndim == 0 else output.square().sum()


def _autograd_jacobian(f, points):
    return torch.autograd.functional.jacobian(f, points)


@pytest.mark.parametrize("name", NAMES)
def test_grad_and_vjp_equal_autograd(name):
    inputs = _inputs(name)
    f = _function_of_points(name, inputs)
    points = inputs["points"]
    tracked = points.clone().requires_grad_()
    output = f(tracked)
    cotangent = torch.randn(output.shape, generator=torch.Generator().manual_seed(0), dtype=output.dtype)
    (expected_grad,) = torch.autograd.grad(_scalar(f(tracked)), tracked)
    (expected_vjp,) = torch.autograd.grad(output, tracked, cotangent)

    torch.testing.assert_close(torch.func.grad(lambda p: _scalar(f(p)))(points), expected_grad, **TOLERANCE)
    value, pullback = torch.func.vjp(f, points)
    # torch.func runs the forward of another program than autograd's (with residuals): rounding.
    torch.testing.assert_close(value, output.detach(), **TOLERANCE)
    torch.testing.assert_close(pullback(cotangent)[0], expected_vjp, **TOLERANCE)


@pytest.mark.parametrize("name", NAMES)
def test_jvp_jacrev_and_jacfwd_equal_the_autograd_jacobian(name):
    inputs = _inputs(name)
    f = _function_of_points(name, inputs)
    points = inputs["points"]
    jacobian = _autograd_jacobian(f, points)
    tangent = torch.randn(points.shape, generator=torch.Generator().manual_seed(1), dtype=points.dtype)

    value, output_tangent = torch.func.jvp(f, (points,), (tangent,))
    torch.testing.assert_close(value, f(points), rtol=0, atol=0)
    expected_tangent = (jacobian.reshape(-1, points.numel()) @ tangent.reshape(-1)).reshape(value.shape)
    torch.testing.assert_close(output_tangent, expected_tangent, **SOLVER_TOLERANCE.get(name, TOLERANCE))
    torch.testing.assert_close(torch.func.jacrev(f)(points), jacobian, **TOLERANCE)
    torch.testing.assert_close(torch.func.jacfwd(f)(points), jacobian, **SOLVER_TOLERANCE.get(name, TOLERANCE))


@pytest.mark.parametrize("name", NAMES)
def test_hessian_equals_double_backward(name):
    inputs = _inputs(name)
    f = _function_of_points(name, inputs)
    points = inputs["points"]
    expected = torch.autograd.functional.hessian(lambda p: _scalar(f(p)), points)
    hessian = torch.func.hessian(lambda p: _scalar(f(p)))(points)
    torch.testing.assert_close(hessian, expected, **SOLVER_TOLERANCE.get(name, TOLERANCE))


def _batched_points(points):
    shift = 0.01 * torch.randn((BATCH, *points.shape), generator=torch.Generator().manual_seed(2), dtype=points.dtype)
    return points + shift


@pytest.mark.parametrize("name", NAMES)
def test_vmap_and_vmap_of_grad_equal_a_loop(name):
    inputs = _inputs(name)
    f = _function_of_points(name, inputs)
    batch = _batched_points(inputs["points"])
    expected = torch.stack([f(p) for p in batch])
    # batch dimension last on the way in, to exercise in_dims other than 0
    # jax.vmap may batch a solve or a reduction differently from one example: rounding only
    torch.testing.assert_close(torch.func.vmap(f, in_dims=-1)(batch.movedim(0, -1)), expected, **TOLERANCE)
    expected_grads = torch.stack([torch.func.grad(lambda p: _scalar(f(p)))(p) for p in batch])
    grads = torch.func.vmap(torch.func.grad(lambda p: _scalar(f(p))))(batch)
    torch.testing.assert_close(grads, expected_grads, **TOLERANCE)


def test_vmap_has_no_fallback_warning():
    inputs = _inputs("morph_points")
    f = _function_of_points("morph_points", inputs)
    batch = _batched_points(inputs["points"])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        torch.func.vmap(f)(batch)
        torch.func.vmap(torch.func.grad(lambda p: f(p).sum()))(batch)
    assert not [w for w in caught if "batching rule" in str(w.message)], [str(w.message) for w in caught]


def test_vmap_over_a_batched_companion_and_tuple_outputs():
    # Several batched leaves (points and displacement) and a shared optional one (weights).
    inputs = _inputs("displace_points")
    points, displacement = _batched_points(inputs["points"]), _batched_points(inputs["displacement"])

    def f(p, d):
        return torch_bridge.displace_points(p, d, point_weights=inputs["point_weights"])

    expected = torch.stack([f(p, d) for p, d in zip(points, displacement)])
    torch.testing.assert_close(torch.func.vmap(f)(points, displacement), expected, rtol=0, atol=0)


def test_tuple_and_integer_outputs_under_transforms():
    # The toy op of test_machinery: a float field, integer indices (non-differentiable) and a scalar.
    from .test_machinery import toy

    points = torch.randn((4, 3), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    tangent = torch.ones_like(points)
    field, index, total = torch.func.vmap(toy)(_batched_points(points))
    for i, p in enumerate(_batched_points(points)):
        for ours, theirs in zip((field[i], index[i], total[i]), toy(p)):
            torch.testing.assert_close(ours, theirs, rtol=0, atol=0)
    (_, _, total), (field_tangent, _, total_tangent) = torch.func.jvp(toy, (points,), (tangent,))
    torch.testing.assert_close(field_tangent, 6.0 * points**2 * tangent, **TOLERANCE)  # 2 p^3
    torch.testing.assert_close(total_tangent, (2 * points * tangent).sum(), **TOLERANCE)
    torch.testing.assert_close(torch.func.grad(lambda p: toy(p)[2])(points), 2 * points, **TOLERANCE)
    torch.testing.assert_close(torch.func.hessian(lambda p: toy(p)[2])(points).reshape(12, 12), 2 * torch.eye(12, dtype=points.dtype), **TOLERANCE)
