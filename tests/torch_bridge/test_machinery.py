"""torch_bridge's generic machinery: signatures from the table, tuple and integer outputs, any-order
gradients, DLPack, float64 without JAX configuration, the eager fast path vs the dispatcher."""

from __future__ import annotations

import ast
import inspect
import re
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from torch.overrides import TorchFunctionMode

import geomjax
import torch_bridge
from torch_bridge import _dlpack, _lift
from torch_bridge._signature import BridgedOp, make_public_function

REPO = Path(__file__).resolve().parents[2]
REFERENCE_API = REPO.parent / "shared" / "spec" / "reference-api.txt"


def _toy(points, *, scale=2.0, powers=(3,)):
    """A test-only op with a tuple output: a float field, integer indices and a scalar."""
    field = sum(points**p for p in powers) * scale
    return field, jnp.argmax(points, axis=-1).astype(jnp.int32), jnp.sum(points**2)


TOY = BridgedOp(
    "bridge_test_toy(points: Tensor, *, scale: float = 2.0, powers: Sequence[int] = (3,)) -> tuple[Tensor, Tensor, Tensor]",
    _toy,
)
toy = make_public_function(TOY)


def _points(dtype=torch.float64, shape=(4, 3), seed=0):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64).to(dtype)


# ---------------------------------------------------------------------------------------------
# signatures
# ---------------------------------------------------------------------------------------------


def test_generated_signature_follows_the_table_entry():
    signature = inspect.signature(toy)
    assert str(signature) == "(points, *, scale=2.0, powers=(3,))"
    assert toy.__name__ == "bridge_test_toy" and toy.__module__ == "torch_bridge"
    assert str(TOY.lifted.op._schema) == (
        "geomjax::bridge_test_toy(Tensor points, Tensor scale, int[] powers, bool[] requires_grad) -> (Tensor, Tensor, Tensor)"
    )


def _reference_signatures() -> dict:
    """Each function's signature in the reference API text: ``{name: [(parameter, keyword_only,
    default), ...]}``, read from the blocks ``physicsnemo.nn.functional.<name>(`` ... ``) <returns>#``."""
    text = REFERENCE_API.read_text()
    signatures = {}
    for match in re.finditer(r"^physicsnemo\.nn\.functional\.(\w+)\(\n(.*?)^\) ", text, re.MULTILINE | re.DOTALL):
        tree = ast.parse(f"def {match[1]}({match[2]}): pass").body[0]
        positional, keyword_only = tree.args.args, tree.args.kwonlyargs
        defaults = [None] * (len(positional) - len(tree.args.defaults)) + list(tree.args.defaults)
        defaults += list(tree.args.kw_defaults)
        signatures[match[1]] = [
            (arg.arg, i >= len(positional), inspect.Parameter.empty if d is None else ast.literal_eval(d))
            for i, (arg, d) in enumerate(zip([*positional, *keyword_only], defaults))
        ]
    return signatures


@pytest.mark.skipif(not REFERENCE_API.exists(), reason="the reference API text is in the shared folder")
def test_generated_signatures_equal_the_reference_api():
    """Names, order, keyword-only marker and defaults of every public function (derived from
    geomjax) are the reference's documented ones."""
    reference = _reference_signatures()
    assert set(reference) <= set(torch_bridge.__all__)  # farthest_point_sampling is ours alone
    for name in reference:
        ours = [
            (p.name, p.kind == p.KEYWORD_ONLY, p.default)
            for p in inspect.signature(getattr(torch_bridge, name)).parameters.values()
        ]
        assert ours == reference[name], name
        assert all(type(a[2]) is type(b[2]) for a, b in zip(ours, reference[name])), name  # 1 vs 1.0


def test_signatures_are_derived_from_geomjax_with_table_overrides():
    op = torch_bridge.mesh_to_voxel_fraction.bridged_op
    assert op.function is geomjax.mesh_to_voxel_fraction
    assert "int[] grid_dims" in str(op.lifted.op._schema)  # the table's Sequence[int], not geomjax's tensor form
    assert [p.name for p in torch_bridge.shrinkwrap_points.bridged_op.parameters][-1] == "implementation"  # no bvh
    handle = torch_bridge.ray_mesh_intersect.bridged_op
    assert [p.name for p in handle.parameters][4:6] == ["max_distance", "warp_mesh_handle"]
    assert handle.parameters[4].default == inspect.signature(geomjax.ray_mesh_intersect).parameters["max_distance"].default


def test_union_annotations_split_into_tensor_and_static_slots():
    op = torch_bridge.morph_points.bridged_op
    schema = str(op.lifted.op._schema)
    assert "Tensor? radius" in schema and "Tensor? radius_value" in schema  # a real option travels as a 0-d tensor
    ffd_schema = str(torch_bridge.free_form_deform_points.bridged_op.lifted.op._schema)
    assert "Tensor? origin" in ffd_schema and "Tensor? origin_value" in ffd_schema


def test_bad_table_entries_are_rejected():
    with pytest.raises(ValueError, match="annotation"):
        BridgedOp("bridge_test_bad(points: Tensor, mesh: Mesh) -> Tensor", _toy)
    with pytest.raises(ValueError, match="nondifferentiable"):
        BridgedOp("bridge_test_bad2(points: Tensor) -> Tensor", _toy, nondifferentiable=("origin",))


# ---------------------------------------------------------------------------------------------
# tuple and integer outputs, gradients of any order
# ---------------------------------------------------------------------------------------------


def test_tuple_outputs_values_and_dtypes():
    points = _points()
    field, index, total = toy(points, scale=0.5, powers=[1, 2])
    expected = _toy(jnp.asarray(points.numpy()), scale=0.5, powers=(1, 2))
    assert field.dtype == torch.float64 and index.dtype == torch.int32 and total.shape == ()
    np.testing.assert_array_equal(index.numpy(), np.asarray(expected[1]))
    for ours, theirs in ((field, expected[0]), (total, expected[2])):  # jit vs eager rounding
        np.testing.assert_allclose(ours.numpy(), np.asarray(theirs), rtol=1e-15, atol=1e-15)


def test_tuple_outputs_gradcheck_and_gradgradcheck():
    points = _points().requires_grad_()

    def float_outputs(p):  # gradcheck's numerical Jacobian cannot skip the integer output
        field, _, total = toy(p, powers=[2, 3])
        return field, total

    assert torch.autograd.gradcheck(float_outputs, (points,))
    assert torch.autograd.gradgradcheck(float_outputs, (points,))


def test_unused_outputs_and_integer_outputs_get_no_cotangent():
    points = _points().requires_grad_()
    field, index, total = toy(points)
    assert not index.requires_grad
    (grad,) = torch.autograd.grad(total, points)  # field's cotangent is absent (None)
    torch.testing.assert_close(grad, 2 * points.detach(), rtol=0, atol=0)


def test_third_order_gradients_recurse_through_lifted_vjps():
    points = _points().requires_grad_()
    field = toy(points, scale=1.5)[0]  # 1.5 p^3
    (first,) = torch.autograd.grad(field.sum(), points, create_graph=True)
    (second,) = torch.autograd.grad(first.sum(), points, create_graph=True)
    (third,) = torch.autograd.grad(second.sum(), points)
    torch.testing.assert_close(first, 4.5 * points.detach() ** 2, rtol=1e-15, atol=0)
    torch.testing.assert_close(second, 9.0 * points.detach(), rtol=1e-15, atol=0)
    torch.testing.assert_close(third, torch.full_like(points, 9.0), rtol=0, atol=0)
    assert "bridge_test_toy_vjp_vjp" in str(TOY.lifted.vjp.vjp.op._schema)


def test_scalar_or_sequence_annotations_get_two_static_slots():
    op = torch_bridge.mesh_poisson_disk_sample.bridged_op
    schema = str(op.lifted.op._schema)
    assert "int? hash_grid_resolution," in schema and "int[]? hash_grid_resolution_sequence" in schema
    defaults = [torch.zeros(3, 3), torch.zeros(1, 3, dtype=torch.int64)] + [p.default for p in op.parameters[2:]]
    for value, expected in ((16, 16), ((8, 16, 32), (8, 16, 32)), (torch.tensor([8, 16, 32]), (8, 16, 32))):
        values = list(defaults)
        values[[p.name for p in op.parameters].index("hash_grid_resolution")] = value
        slots, statics = op.bind(values)
        assert op._geomjax_kwargs(slots, statics)["hash_grid_resolution"] == expected


def test_backward_ops_are_registered_before_first_use():
    # A compiled backward looks its ops up by name while tracing: they must already exist then.
    fresh = BridgedOp("bridge_test_registration(points: Tensor) -> Tensor", lambda points: points**2)
    assert hasattr(torch.ops.geomjax, "bridge_test_registration_vjp")
    assert hasattr(torch.ops.geomjax, "bridge_test_registration_vjp_vjp")
    assert fresh.lifted.vjp.vjp.op is torch.ops.geomjax.bridge_test_registration_vjp_vjp.default


def test_toy_opcheck_and_compile():
    points = _points().requires_grad_()
    torch.library.opcheck(TOY.lifted.op, TOY.lifted.op_arguments((points,), (2.0, (3,)), [True]))
    cotangents = [torch.ones_like(points).requires_grad_(), torch.ones((), dtype=points.dtype)]
    torch.library.opcheck(TOY.lifted.vjp.op, TOY.lifted.vjp.op_arguments((points, cotangents), (2.0, (3,), (True, False, True), (True,)), [True, True, False]))
    torch._dynamo.reset()
    compiled = torch.compile(lambda p: toy(p, powers=[1, 3]), fullgraph=True, backend="aot_eager")
    for ours, theirs in zip(compiled(points), toy(points, powers=[1, 3])):
        torch.testing.assert_close(ours, theirs, rtol=0, atol=0)


def test_compile_with_dynamic_shapes():
    torch._dynamo.reset()
    compiled = torch.compile(lambda p, d: torch_bridge.displace_points(p, d), fullgraph=True, dynamic=True)
    for n in (3, 5, 8):
        p, d = _points(shape=(n, 2)), _points(shape=(n, 2), seed=1)
        torch.testing.assert_close(compiled(p, d), p + d, rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# DLPack and dtypes
# ---------------------------------------------------------------------------------------------


def test_dlpack_is_zero_copy_both_ways():
    t = _points(torch.float32, (64, 3))
    a = _dlpack.to_jax(t)
    assert a.unsafe_buffer_pointer() == t.data_ptr()
    b = jnp.sin(a)
    back = _dlpack.to_torch(b, t.device)
    assert back.data_ptr() == b.unsafe_buffer_pointer()
    torch.testing.assert_close(back, torch.sin(t))


def test_cpu_views_are_reused_and_follow_the_tensor():
    views = _dlpack._cpu_views
    p, d = _points(torch.float32, (16, 3)), _points(torch.float32, (16, 3), seed=1)
    first = torch_bridge.displace_points(p, d)
    assert _dlpack.to_jax(p) is _dlpack.to_jax(p)  # a kept view: no DLPack import per call
    with torch.no_grad():
        p.mul_(2.0)  # in place: same memory, the kept view sees it
    torch.testing.assert_close(torch_bridge.displace_points(p, d), 2 * (first - d) + d)
    p.set_(torch.ones(4, 3))  # new memory and shape: a new view
    torch.testing.assert_close(torch_bridge.displace_points(p, torch.ones(4, 3)), torch.full((4, 3), 2.0))
    key = id(p)
    assert key in views._views
    del p
    assert key not in views._views  # released with the tensor
    strided = _points(torch.float32, (3, 16)).T
    before = len(views._views)
    _dlpack.to_jax(strided)  # a contiguous copy is a snapshot: never kept
    assert len(views._views) == before


# Programs lowered so far in this process (each jit cache miss lowers, then compiles or loads).
_LOWERINGS = [0]
jax.monitoring.register_event_duration_secs_listener(
    lambda event, duration, **_: _LOWERINGS.__setitem__(0, _LOWERINGS[0] + (event == "/jax/core/compile/jaxpr_to_mlir_module_duration"))
)


@pytest.mark.parametrize("rows", [16, _dlpack.SMALL_CPU_BYTES // 12 + 1], ids=["small", "large"])
def test_repeated_calls_compile_once(rows):
    """The same tensors again, the same tensors updated in place, and new tensors of the same
    shapes all reach the first call's program: jit keys its cache on whether an argument is
    committed, and a NumPy first call followed by a kept view compiled every program twice.
    Small tensors go as NumPy views on every call, large ones as kept DLPack views."""
    p, d = _points(torch.float32, (rows, 3)), _points(torch.float32, (rows, 3), seed=1)
    torch.testing.assert_close(torch_bridge.displace_points(p, d), p + d, rtol=0, atol=0)
    first = _LOWERINGS[0]
    with torch.no_grad():
        p.add_(1.0)  # in place: seen through the NumPy view and the kept view alike
    torch.testing.assert_close(torch_bridge.displace_points(p, d), p + d, rtol=0, atol=0)
    q = p.clone()
    torch.testing.assert_close(torch_bridge.displace_points(q, d), q + d, rtol=0, atol=0)
    assert _LOWERINGS[0] == first, "a repeated call compiled its program again"
    kept = id(p) in _dlpack._cpu_views._views
    assert kept == (rows * 3 * 4 > _dlpack.SMALL_CPU_BYTES)


def test_low_precision_tensors_without_a_numpy_dtype_convert():
    half = torch.full((4, 3), 1.5, dtype=torch.bfloat16)  # no NumPy dtype: DLPack from the first call
    array = _dlpack.to_jax(half, jit_argument=True)
    assert isinstance(array, jax.Array) and array.dtype == jnp.bfloat16
    np.testing.assert_array_equal(np.asarray(array, np.float32), np.full((4, 3), 1.5, np.float32))


def test_empty_arrays_convert():
    out = _dlpack.to_torch(jnp.zeros((0, 3), jnp.float32), torch.device("cpu"))
    assert out.shape == (0, 3) and out.dtype == torch.float32


def test_non_contiguous_inputs():
    p, d = _points(shape=(3, 6)).T, _points(shape=(3, 6), seed=1).T
    assert not p.is_contiguous()
    torch.testing.assert_close(torch_bridge.displace_points(p, d), p + d, rtol=0, atol=0)


def test_parameters_are_plain_tensors():
    p = torch.nn.Parameter(_points())
    d = _points(seed=1)
    torch_bridge.displace_points(p, d).sum().backward()
    torch.testing.assert_close(p.grad, torch.ones_like(p))


def test_float64_round_trips_exactly_without_jax_x64():
    """conftest enables x64 and strict promotion for the session, which hides float64 bugs: run
    with JAX's defaults (x64 off, standard promotion), as a user's process has them."""
    from tests.op_cases import assert_trees_close, torch_inputs
    from tests.torch_bridge.test_ops import NAMES, as_jax, size

    with jax.enable_x64(False), jax.numpy_dtype_promotion("standard"):
        rng = np.random.default_rng(0)
        p, d = rng.normal(size=(7, 3)), rng.normal(size=(7, 3))
        # Powers of two: w * d is exact, so any rounding of the sum is numpy's.
        w = np.array([0.5, -2.0, 1.0, 0.25, -4.0, 8.0, -0.125])
        points, displacement, weights = (torch.tensor(a, requires_grad=True) for a in (p, d, w))
        out = torch_bridge.displace_points(points, displacement, point_weights=weights)
        assert out.dtype == torch.float64
        assert np.array_equal(out.detach().numpy(), p + w[:, None] * d), "float64 values lost precision"
        out.backward(torch.ones_like(out))
        assert np.array_equal(displacement.grad.numpy(), np.repeat(w[:, None], 3, axis=1))
        assert np.allclose(weights.grad.numpy(), d.sum(axis=1), rtol=1e-15, atol=1e-15)
        assert np.array_equal(points.grad.numpy(), np.ones((7, 3)))
        # Ops that build constants inside would return float32 (or raise) if the bridge did not
        # run them in float64: compare with geomjax under an explicit x64 context, to float64
        # rounding (float32 would be off by 1e-7).
        for name in NAMES:
            with jax.enable_x64(True):  # the case table builds float64 arrays with JAX
                inputs = {**torch_inputs(name, torch.float64), "implementation": "jax"}
            out = getattr(torch_bridge, name)(**inputs)
            with jax.enable_x64(True):
                arrays = {k: v for k, v in as_jax(inputs).items() if isinstance(v, jax.Array)}
                options = {k: v for k, v in inputs.items() if k not in arrays}
                expected = jax.jit(lambda a, name=name, options=options: getattr(geomjax, name)(**a, **options))(arrays)
            assert out.dtype == torch.float64, name
            assert_trees_close(out.numpy(), np.asarray(expected), jnp.float64, size(name), name)
        assert not jax.config.jax_enable_x64, "the x64 flag was flipped"


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_dtype_is_preserved(dtype):
    p = _points(dtype)
    assert torch_bridge.displace_points(p, p).dtype == dtype


# ---------------------------------------------------------------------------------------------
# eager fast path vs the dispatcher
# ---------------------------------------------------------------------------------------------


class _PassThrough(TorchFunctionMode):
    def __torch_function__(self, func, types, args=(), kwargs=None):
        return func(*args, **(kwargs or {}))


def test_dispatcher_path_equals_eager_fast_path():
    def run():
        p = _points().requires_grad_()
        c = _points(shape=(2, 3), seed=1).requires_grad_()
        d = (0.1 * _points(shape=(2, 3), seed=2)).requires_grad_()
        out = torch_bridge.morph_points(p, c, d, radius=1.5, implementation="jax")
        grads = torch.autograd.grad(out, (p, c, d), torch.ones_like(out))
        return out.detach(), grads

    assert _lift._plain_eager([_points()])
    fast = run()
    with _PassThrough():
        assert not _lift._plain_eager([_points()])
        dispatched = run()
    torch.testing.assert_close(dispatched[0], fast[0], rtol=0, atol=0)
    for a, b in zip(dispatched[1], fast[1]):
        torch.testing.assert_close(a, b, rtol=0, atol=0)


def test_gradcheck_through_the_dispatcher():
    p = _points().requires_grad_()
    w = _points(shape=(4,), seed=3).requires_grad_()
    with _PassThrough():
        assert torch.autograd.gradcheck(lambda p, w: torch_bridge.displace_points(p, p, point_weights=w), (p, w))
        assert torch.autograd.gradgradcheck(lambda p, w: torch_bridge.displace_points(p, p, point_weights=w), (p, w))


def test_jax_arrays_are_not_kept_alive():
    import gc
    import weakref

    p = _points(torch.float32, (32, 3))
    out = torch_bridge.displace_points(p, p)
    ref = weakref.ref(out)
    del out
    gc.collect()
    assert ref() is None
    assert jax.config.jax_enable_x64  # conftest's setting is left alone


def test_package_docstring_example_runs():
    import doctest

    result = doctest.testmod(torch_bridge, optionflags=doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE)
    assert result.attempted > 0 and result.failed == 0
