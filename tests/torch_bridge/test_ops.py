"""torch_bridge, op by op: every test is parametrised over the op table.

Inputs come from the one case table, ``tests/op_cases.py`` (the cases of the JAX tests, as
tensors: :func:`tests.op_cases.torch_inputs`), and backends from geomjax's registry; an op added to
``torch_bridge._ops.OPS`` is then tested here automatically (values against geomjax, gradcheck,
gradgradcheck, opcheck, torch.compile, errors).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

import geomjax
import torch_bridge
from geomjax._registry import REGISTRY
from torch_bridge._ops import OPS

from ..op_cases import CASES, assert_trees_close, torch_inputs

OP_BY_NAME = {op.name: op for op in OPS}
NAMES = [op.name for op in OPS]
TORCH_DTYPES = {torch.float32: jnp.float32, torch.float64: jnp.float64}


@functools.cache
def case(name):
    """The op's float64 case (its shapes, names and options; tensors come from ``torch_inputs``)."""
    return CASES[name](jnp.float64)


# Ops with per-point weights: the deformations x' = x + w u (the weight and empty-input tests).
WEIGHTED = [name for name in NAMES if "point_weights" in case(name).arg_names]
# Ops with control points (the zero-control test).
WITH_CONTROLS = [name for name in NAMES if case(name).no_controls is not None]
# Backends geomjax registers for each op (the bridge adds "torch" -> "jax").
IMPLEMENTATION_PARAMS = [(name, impl) for name in NAMES for impl in REGISTRY[name].backends]


def size(name):
    return case(name).size


def public(name):
    return getattr(torch_bridge, name)


def differentiable(name, inputs):
    """The case's arrays that are float tensors in ``inputs`` (a bool mask of weights is not)."""
    return [k for k in case(name).arg_names if isinstance(inputs.get(k), torch.Tensor) and inputs[k].is_floating_point()]


def as_jax(inputs):
    # device_put compiles nothing (jnp.asarray of a NumPy array compiles a program per shape).
    return {k: jax.device_put(v.detach().numpy()) if isinstance(v, torch.Tensor) else v for k, v in inputs.items()}


def geomjax_reference(name, inputs):
    """geomjax's own result on the same inputs (jitted: one compile instead of many eager ones)."""
    arrays = {k: v for k, v in as_jax(inputs).items() if isinstance(v, jax.Array)}
    options = {k: v for k, v in inputs.items() if k not in arrays}
    return jax.jit(lambda a: getattr(geomjax, name)(**a, **options))(arrays)


def function_of(name, inputs, wrt):
    """``f(*tensors)`` calling the public function with ``wrt`` replaced (for gradcheck)."""
    fn = public(name)

    def f(*tensors):
        return fn(**{**inputs, **dict(zip(wrt, tensors))})

    return f


def with_grad(inputs, names):
    return {k: (v.detach().clone().requires_grad_() if k in names else v) for k, v in inputs.items()}


def op_arguments(name, inputs):
    """Custom-op arguments ``(slots, statics, requires_grad)`` for the public inputs."""
    op = OP_BY_NAME[name]
    values = [inputs.get(p.name, p.default) for p in op.parameters]
    slots, statics = op.bind(values)
    return slots, statics, [x is not None and x.requires_grad for x in slots]


# ---------------------------------------------------------------------------------------------
# table and signatures
# ---------------------------------------------------------------------------------------------


def test_every_op_has_a_case():
    assert set(NAMES) <= set(CASES)  # the case table covers the registry (test_transformations.py)
    assert set(NAMES) <= set(torch_bridge.__all__)  # the mesh ops are tested in test_mesh_ops.py


@pytest.mark.parametrize("name", NAMES)
def test_custom_op_is_registered(name):
    op = getattr(torch.ops.geomjax, name).default
    schema = str(op._schema)
    assert schema.startswith(f"geomjax::{name}(") and schema.endswith("bool[] requires_grad) -> Tensor")
    assert op is OP_BY_NAME[name].lifted.op


# ---------------------------------------------------------------------------------------------
# values and gradients against geomjax
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
@pytest.mark.parametrize(("name", "implementation"), IMPLEMENTATION_PARAMS)
def test_values_and_gradients_equal_geomjax(name, implementation, dtype):
    base = {**torch_inputs(name, dtype), "implementation": implementation}
    names = differentiable(name, base)
    plain = public(name)(**base)  # no input requires grad: the forward without residuals
    inputs = with_grad(base, names)
    out = public(name)(**inputs)
    cotangent = torch.linspace(-1.0, 1.0, out.numel(), dtype=dtype).reshape(out.shape)
    grads = torch.autograd.grad(out, [inputs[k] for k in names], cotangent)

    arrays = as_jax(base)
    options = {k: v for k, v in arrays.items() if k not in names}
    fn = getattr(geomjax, name)

    @jax.jit
    def reference(xs, ct):
        # Value and VJP in one program: one compile per case, not one for each.
        value, pullback = jax.vjp(lambda *xs: fn(**dict(zip(names, xs)), **options), *xs)
        return value, pullback(ct)

    expected_value, expected_grads = reference(tuple(arrays[k] for k in names), jnp.asarray(cotangent.numpy()))
    expected_value = np.asarray(expected_value)
    # XLA may fuse the bridge's programs and this one differently: equal to rounding.
    for label, value in (("without grad", plain), ("with grad", out.detach())):
        assert_trees_close(value.numpy(), expected_value, TORCH_DTYPES[dtype], size(name), label)
    for k, g, e in zip(names, grads, expected_grads):
        assert_trees_close(g.numpy(), np.asarray(e), TORCH_DTYPES[dtype], size(name), k)


@pytest.mark.parametrize(("name", "implementation"), IMPLEMENTATION_PARAMS)
def test_batched_values_equal_geomjax(name, implementation):
    inputs = {**torch_inputs(name, torch.float64, "batched"), "implementation": implementation}
    out = public(name)(**inputs)
    expected = np.asarray(geomjax_reference(name, inputs))
    assert_trees_close(out.numpy(), expected, jnp.float64, size(name))


@pytest.mark.parametrize(("name", "implementation"), IMPLEMENTATION_PARAMS)
def test_gradcheck(name, implementation):
    inputs = {**torch_inputs(name, torch.float64), "implementation": implementation}
    names = differentiable(name, inputs)
    tensors = [inputs[k].detach().clone().requires_grad_() for k in names]
    assert torch.autograd.gradcheck(function_of(name, inputs, names), tensors)


@pytest.mark.parametrize("name", NAMES)
def test_gradgradcheck_default(name):
    # The default implementation: double backward is what a user's default call must support,
    # whichever backend serves the first order (a Warp default's second order is the JAX path's).
    inputs = torch_inputs(name, torch.float64)
    # Every differentiable input, as test_opcheck_backward_op's call of the VJP op: the two tests
    # then share their second-order programs (compiling those is nearly all of their cost).
    names = differentiable(name, inputs)
    tensors = [inputs[k].detach().clone().requires_grad_() for k in names]
    assert torch.autograd.gradgradcheck(function_of(name, inputs, names), tensors, fast_mode=True)


def test_unrepresentable_strain_bulk_term_is_a_value_error():
    # Segments (m = 1): lame_lambda / 2 + shear_modulus = 4.5e38 overflows float32, as in geomjax.
    points = torch.linspace(0.0, 1.0, 12, dtype=torch.float32).reshape(4, 3)
    cells = torch.tensor([[0, 1], [1, 2], [2, 3]])
    with pytest.raises(ValueError, match=r"lame_lambda / 2 \+ shear_modulus / simplex_dimension must be finite in float32"):
        torch_bridge.simplex_strain_energy(points + 0.01, points, cells, lame_lambda=3e38, shear_modulus=3e38)


@pytest.mark.parametrize("name", NAMES)
def test_implementation_torch_means_jax(name):
    inputs = torch_inputs(name, torch.float64)
    torch.testing.assert_close(
        public(name)(**inputs, implementation="torch"), public(name)(**inputs, implementation="jax"), rtol=0, atol=0
    )


@pytest.mark.parametrize("name", NAMES)
def test_only_requested_gradients_are_returned(name):
    base = torch_inputs(name, torch.float64)
    names = differentiable(name, base)
    inputs = with_grad(base, names[-1:])  # only the last differentiable input requires grad
    out = public(name)(**inputs)
    out.sum().backward()
    assert inputs[names[-1]].grad is not None
    for k in names[:-1]:
        assert not inputs[k].requires_grad


# ---------------------------------------------------------------------------------------------
# point weights, empty inputs
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", WEIGHTED)
def test_bool_weights_are_a_non_differentiable_mask(name):
    base = torch_inputs(name, torch.float64)
    mask = torch.zeros(base["points"].shape[:-1], dtype=torch.bool)
    mask[::2] = True
    base = {**base, "point_weights": mask}
    names = differentiable(name, base)
    assert "point_weights" not in names
    inputs = with_grad(base, names)
    out = public(name)(**inputs)
    assert_trees_close(out.detach().numpy(), np.asarray(geomjax_reference(name, base)), jnp.float64, size(name))
    torch.testing.assert_close(out[~mask], base["points"][~mask], rtol=0, atol=0)
    grads = torch.autograd.grad(out.sum(), [inputs[k] for k in names])
    assert all(g is not None for g in grads)


@pytest.mark.parametrize("name", WEIGHTED)
def test_float_weights_get_gradients(name):
    base = torch_inputs(name, torch.float64)
    inputs = with_grad(base, ["point_weights"])
    out = public(name)(**inputs)
    (grad,) = torch.autograd.grad(out.sum(), inputs["point_weights"])
    # x' = x + w u  =>  d sum(x') / d w = sum over coordinates of u = (x' - x) / w
    field = (out.detach() - base["points"]) / base["point_weights"][..., None]
    torch.testing.assert_close(grad, field.sum(-1), rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("name", WEIGHTED)
def test_empty_points(name):
    base = torch_inputs(name, torch.float64, "empty")
    names = differentiable(name, base)
    inputs = with_grad(base, names)
    out = public(name)(**inputs)
    assert tuple(out.shape) == tuple(base["points"].shape)
    grads = torch.autograd.grad(out.sum(), [inputs[k] for k in names])
    for k, g in zip(names, grads):
        assert g is not None and g.shape == inputs[k].shape and not g.abs().sum(), k


@pytest.mark.parametrize("name", WITH_CONTROLS)
def test_zero_controls_is_identity_with_defined_gradients(name):
    base = torch_inputs(name, torch.float64, "no_controls")
    names = differentiable(name, base)
    inputs = with_grad(base, names)
    out = public(name)(**inputs)
    torch.testing.assert_close(out, base["points"], rtol=0, atol=0)
    grads = torch.autograd.grad(out.sum(), [inputs[k] for k in names])
    for k, g in zip(names, grads):
        assert g is not None and g.shape == inputs[k].shape, k


# ---------------------------------------------------------------------------------------------
# errors (same exception types as the reference)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_error_types(name):
    fn, inputs = public(name), torch_inputs(name, torch.float32)
    second = next(k for k in differentiable(name, inputs) if k != "points")
    with pytest.raises(TypeError):
        fn(**{**inputs, "points": inputs["points"].half()})
    with pytest.raises(TypeError):
        fn(**{**inputs, "points": inputs["points"].to(torch.int32)})
    with pytest.raises(TypeError):
        fn(**{**inputs, second: inputs[second].double()})
    with pytest.raises(TypeError):
        fn(**{**inputs, "points": inputs["points"].numpy()})
    with pytest.raises(ValueError):
        fn(**{**inputs, "points": inputs["points"][..., :2]})
    if name in WEIGHTED:
        with pytest.raises(TypeError):
            fn(**{**inputs, "point_weights": inputs["point_weights"].double()})
        with pytest.raises(TypeError):
            fn(**{**inputs, "point_weights": inputs["point_weights"].to(torch.int64)})
        with pytest.raises(ValueError):
            fn(**{**inputs, "point_weights": inputs["point_weights"][:-1]})
    topology = next((k for k in ("cells", "hinges", "triangles") if k in inputs), None)
    if topology is not None:
        with pytest.raises(TypeError):
            fn(**{**inputs, topology: inputs[topology].to(torch.int16)})
    if all(axis == 0 for axis in case(name).in_axes):  # no array is shared by a batch
        with pytest.raises(ValueError):
            fn(**{**inputs, "points": inputs["points"][None]})  # batched points, unbatched companions
    with pytest.raises(KeyError):
        fn(**inputs, implementation="cuda")
    with pytest.raises(KeyError):
        fn(**inputs, implementation=3)
    if "warp" not in REGISTRY[name].backends:
        with pytest.raises(KeyError):
            fn(**inputs, implementation="warp")
    if case(name).bad_option is not None:
        with pytest.raises(ValueError):
            fn(**{**inputs, **case(name).bad_option})


@pytest.mark.parametrize("name", NAMES)
def test_python_option_types_raise_geomjax_errors(name):
    fn, inputs = public(name), torch_inputs(name, torch.float32)
    op = OP_BY_NAME[name]
    for p in op.parameters:
        if p.static_type is None or p.name == "implementation":
            continue
        base = p.static_type.rstrip("?")
        bad = {"float": True, "int": 1.5, "bool": 1, "str": 3, "float[]": [1.0, True, 1.0]}[base]
        expected = ValueError if base == "str" else TypeError  # unknown names are ValueError
        with pytest.raises(expected):
            fn(**{**inputs, p.name: bad})


@pytest.mark.parametrize("name", [n for n in NAMES if any((p.static_type or "").startswith("float") for p in OP_BY_NAME[n].parameters)])
def test_python_integers_beyond_every_float_are_a_value_error(name):
    # 10**400 for a real option: geomjax's ValueError, not float()'s (or torch's) OverflowError.
    fn, inputs = public(name), torch_inputs(name, torch.float32)
    for p in OP_BY_NAME[name].parameters:
        if not (p.static_type or "").startswith("float"):
            continue
        huge = [10**400, 1.0, 1.0] if p.static_type.startswith("float[]") else 10**400
        with pytest.raises(ValueError, match=f"{p.name}.*must be finite"):
            fn(**{**inputs, p.name: huge})


@pytest.mark.parametrize("name", NAMES)
def test_mismatched_devices_raise_value_error(name):
    fn, inputs = public(name), torch_inputs(name, torch.float32)
    second = next(k for k in differentiable(name, inputs) if k != "points")
    with pytest.raises(ValueError, match="device"):
        fn(**{**inputs, second: inputs[second].to("meta")})


def test_ffd_box_requiring_grad_is_a_value_error():
    inputs = torch_inputs("free_form_deform_points", torch.float64)
    box = {"origin": torch.tensor(inputs["origin"], dtype=torch.float64), "extent": torch.tensor(inputs["extent"], dtype=torch.float64)}
    expected = torch_bridge.free_form_deform_points(**{**inputs, **box})
    torch.testing.assert_close(expected, torch_bridge.free_form_deform_points(**inputs), rtol=0, atol=0)
    for key in box:
        bad = {**inputs, **box, key: box[key].clone().requires_grad_()}
        with pytest.raises(ValueError, match=key):
            torch_bridge.free_form_deform_points(**bad)
        with torch.no_grad(), pytest.raises(ValueError, match=key):
            torch_bridge.free_form_deform_points(**bad)


# ---------------------------------------------------------------------------------------------
# custom ops: opcheck
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_opcheck_forward(name):
    base = {**torch_inputs(name, torch.float64), "implementation": "jax"}
    lifted = OP_BY_NAME[name].lifted
    for grad in (False, True):
        inputs = with_grad(base, differentiable(name, base) if grad else [])
        slots, statics, requires_grad = op_arguments(name, inputs)
        torch.library.opcheck(lifted.op, lifted.op_arguments(slots, statics, requires_grad))


@pytest.mark.parametrize("name", NAMES)
def test_opcheck_backward_op(name):
    """The autograd formula's op: the lifted VJP (its own autograd is its lifted VJP), on the
    default implementation as test_gradgradcheck_default."""
    base = torch_inputs(name, torch.float64)
    inputs = with_grad(base, differentiable(name, base))
    slots, statics, requires_grad = op_arguments(name, inputs)
    output = public(name)(**inputs)
    cotangent = torch.linspace(-1.0, 1.0, output.numel(), dtype=torch.float64).reshape(output.shape).requires_grad_()
    vjp = OP_BY_NAME[name].lifted.vjp
    arguments = vjp.op_arguments((*slots, [cotangent]), (*statics, [True], requires_grad), [*requires_grad, True])
    torch.library.opcheck(vjp.op, arguments)
    grads = vjp.op(*arguments)
    expected = torch.autograd.grad(output, [x for x in slots if x is not None and x.requires_grad], cotangent)
    assert len(grads) == len(expected)
    for g, e in zip(grads, expected):
        assert_trees_close(g.detach().numpy(), e.detach().numpy(), jnp.float64, size(name))


# ---------------------------------------------------------------------------------------------
# torch.compile
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_compile_fullgraph_equals_eager(name):
    base = torch_inputs(name, torch.float32)
    names = differentiable(name, base)
    fn = public(name)

    def run(*tensors):
        return fn(**{**base, **dict(zip(names, tensors))})

    eager_inputs = [base[k].clone().requires_grad_() for k in names]
    compiled_inputs = [base[k].clone().requires_grad_() for k in names]
    torch._dynamo.reset()
    compiled = torch.compile(run, fullgraph=True)
    out = compiled(*compiled_inputs)
    expected = run(*eager_inputs)
    torch.testing.assert_close(out, expected, rtol=0, atol=0)
    cotangent = torch.linspace(-1.0, 1.0, out.numel()).reshape(out.shape)
    out.backward(cotangent)
    expected.backward(cotangent)
    # The compiled backward runs the VJP op (linearise + pull back in one XLA program); eager
    # autograd applies the forward's saved residuals. XLA may fuse the two differently, so they
    # agree to a few roundings of the gradient's scale (float32 here), not bitwise.
    eps = torch.finfo(torch.float32).eps
    for k, a, b in zip(names, compiled_inputs, eager_inputs):
        torch.testing.assert_close(a.grad, b.grad, rtol=0, atol=16 * eps * float(b.grad.abs().max()), msg=k)


def test_compile_has_no_graph_breaks():
    inputs = with_grad(torch_inputs("morph_points", torch.float32), ["control_displacements"])
    explanation = torch._dynamo.explain(lambda: torch_bridge.morph_points(**inputs).sum())()
    assert explanation.graph_break_count == 0 and explanation.graph_count == 1


@pytest.mark.parametrize("name", NAMES)
def test_errors_keep_their_type_under_compile(name):
    fn, inputs = public(name), torch_inputs(name, torch.float32)
    second = next(k for k in differentiable(name, inputs) if k != "points")
    torch._dynamo.reset()

    def run(points, other):
        return fn(**{**inputs, "points": points, second: other})

    compiled = torch.compile(run, fullgraph=True, backend="aot_eager")
    with pytest.raises(TypeError):
        compiled(inputs["points"], inputs[second].double())
    with pytest.raises(ValueError):
        compiled(inputs["points"][..., :2].contiguous(), inputs[second])


def test_compiled_ffd_rejects_a_box_requiring_grad():
    inputs = torch_inputs("free_form_deform_points", torch.float32)
    torch._dynamo.reset()
    compiled = torch.compile(
        lambda points, origin: torch_bridge.free_form_deform_points(**{**inputs, "points": points, "origin": origin}),
        fullgraph=True,
        backend="aot_eager",
    )
    compiled(inputs["points"], torch.zeros(3))
    with pytest.raises(ValueError, match="origin"):
        compiled(inputs["points"], torch.zeros(3, requires_grad=True))


def test_compiled_unknown_implementation_is_a_key_error():
    inputs = torch_inputs("morph_points", torch.float32)
    torch._dynamo.reset()
    compiled = torch.compile(lambda p: torch_bridge.morph_points(**{**inputs, "points": p}, implementation="nope"), fullgraph=True, backend="aot_eager")
    with pytest.raises(KeyError):
        compiled(inputs["points"])


# ---------------------------------------------------------------------------------------------
# CUDA (run on the device machine)
# ---------------------------------------------------------------------------------------------


def _cuda_available():
    return torch.cuda.is_available() and any(d.platform == "gpu" for d in jax.devices())


@pytest.mark.gpu
@pytest.mark.skipif(not _cuda_available(), reason="needs CUDA in both torch and JAX")
@pytest.mark.parametrize(("name", "implementation"), IMPLEMENTATION_PARAMS)
def test_cuda_values_gradients_and_devices(name, implementation):
    base = {**torch_inputs(name, torch.float32), "implementation": implementation}
    cuda = {k: v.cuda() if isinstance(v, torch.Tensor) else v for k, v in base.items()}
    names = differentiable(name, base)
    inputs = with_grad(cuda, names)
    out = public(name)(**inputs)
    assert out.device.type == "cuda"
    cpu = public(name)(**base)
    torch.testing.assert_close(out.cpu(), cpu, rtol=1e-5, atol=1e-6)
    grads = torch.autograd.grad(out.square().sum(), [inputs[k] for k in names])
    assert all(g.device.type == "cuda" for g in grads)
    second = next(k for k in names if k != "points")
    with pytest.raises(ValueError, match="device"):
        public(name)(**{**cuda, second: base[second]})
