"""A pure JAX function lifted to PyTorch: custom op, fake kernel and every autograd route.

A :class:`LiftedFunction` is a JAX function ``fn(slots, statics)`` (tensor slots, hashable static
options) exposed as a ``torch.library.custom_op`` ``geomjax::<name>``. Its kernel converts tensors to
JAX arrays with DLPack (zero copy), runs a cached ``jax.jit`` of ``fn`` (static options are static
arguments) and converts the outputs back. Its derivatives are lifted functions too — :attr:`~LiftedFunction.vjp`
(``jax.vjp``), :attr:`~LiftedFunction.jvp` (``jax.jvp``) and :attr:`~LiftedFunction.batched`
(``jax.vmap``) — so every transform composes with every other, to any order the JAX path supports.

A call takes one of three routes (:meth:`LiftedFunction.apply`):

* the custom op, whose ``register_autograd`` formula calls the lifted VJP: ``torch.compile``
  (graphs hold exactly the public outputs), ``make_fx``, fake tensors, dispatch modes, subclasses;
* under ``torch.func`` transforms, :class:`_FunctorchAutograd`, a ``setup_context``-style
  autograd.Function with ``backward``, ``jvp`` and ``vmap`` rules (the function that
  ``register_autograd`` generates is not functorch-compatible, pytorch/pytorch#168393);
* plain eager calls (the common case) skip the dispatcher's per-call Python layers:
  :class:`_EagerAutograd` keeps the residuals of ``jax.vjp`` from the forward pass, so a
  first-order backward applies the saved linearisation instead of recomputing the forward.
  Residuals never appear in op schemas: their number and shapes are geomjax internals, and
  compiled graphs cached on disk by ``torch.compile`` must not depend on them.

Fake (meta) kernels obtain output shapes from geomjax itself with ``jax.eval_shape``. When geomjax
rejects the inputs, the fake returns placeholders instead of raising, so under ``torch.compile``
the real kernel raises geomjax's exception — with its original type — when the graph runs.

Real options (``float`` / ``float[]`` statics: a radius, a smoothing, a length scale, a lattice
origin) reach the custom op as float64 tensors (0-d, or 1-d for a sequence), not as ``float``
schema arguments: under
``torch.compile(dynamic=True)`` a Python float is symbolic, and a ``float`` argument of a custom op
would specialise the graph on its value (a recompilation per value). A tensor is traced instead,
so one graph serves every value; the kernel reads it back as Python numbers before geomjax runs, so
geomjax checks the value (and raises its documented exception) when the graph runs. The fake
kernel cannot read it: it takes the option's default for the output shapes, which no real
option changes. Eager calls never build these tensors.
"""

from __future__ import annotations

import contextvars
from collections.abc import Callable
from dataclasses import dataclass

import jax
import numpy as np
import torch

from geomjax._errors import documented_errors

from ._dlpack import numpy_dtype, to_jax, to_torch, torch_dtype, x64_for

NAMESPACE = "geomjax"

# ---------------------------------------------------------------------------------------------
# slots: the tensor arguments of a lifted function
# ---------------------------------------------------------------------------------------------

TENSOR, OPTIONAL_TENSOR, TENSOR_LIST = "Tensor", "Tensor?", "Tensor[]"

# Static options carried into the custom op as float64 tensors (see the module docstring).
REAL_OPTION_TYPES = {"float": TENSOR, "float?": OPTIONAL_TENSOR, "float[]": TENSOR, "float[]?": OPTIONAL_TENSOR}


def _option_tensor(value):
    """A real option as the custom op takes it: a 0-d float64 tensor, or a 1-d one for a
    sequence of reals (``None`` stays ``None``).

    Written as a tensor plus the number: under ``torch.compile`` a symbolic float is kept
    symbolic only where it feeds arithmetic that AOT autograd's "tensorify" pass rewrites into
    tensor arithmetic (add, mul, ...). It specialises the graph on the value where it feeds
    anything else, ``torch.scalar_tensor`` and ``torch.tensor`` included. float64 holds every
    Python float exactly, and -0.0 is the identity of addition for every float (-0.0 too)."""
    if value is None or isinstance(value, torch.Tensor):
        return value
    if isinstance(value, (tuple, list)):
        return torch.stack([_option_tensor(v) for v in value]) if value else torch.zeros(0, dtype=torch.float64)
    return torch.full((), -0.0, dtype=torch.float64) + value


def _read_option(tensor) -> float | tuple:
    """A real option back from its tensor: a float, or a tuple of floats."""
    return float(tensor.item()) if tensor.ndim == 0 else tuple(float(v) for v in tensor.tolist())


def _flatten(slots, kinds) -> list:
    """Tensor leaves of ``slots`` in order; ``None`` slots stay as ``None`` so indices line up."""
    leaves = []
    for value, kind in zip(slots, kinds):
        if kind == TENSOR_LIST:
            leaves.extend(value)
        else:
            leaves.append(value)
    return leaves


def _unflatten(leaves, slots, kinds) -> tuple:
    """Inverse of :func:`_flatten`, list lengths taken from ``slots``."""
    out, i = [], 0
    for value, kind in zip(slots, kinds):
        if kind == TENSOR_LIST:
            out.append(tuple(leaves[i : i + len(value)]))
            i += len(value)
        else:
            out.append(leaves[i])
            i += 1
    return tuple(out)


def _is_float_dtype(dtype) -> bool:
    return jax.numpy.issubdtype(dtype, jax.numpy.inexact)


# ---------------------------------------------------------------------------------------------
# host-prepared arguments: what a function builds from its concrete tensors before tracing
# ---------------------------------------------------------------------------------------------

_PREPARED: contextvars.ContextVar = contextvars.ContextVar("torch_bridge_prepared", default=None)


def prepared():
    """While a lifted function is traced: what its ``prepare`` built on the host from the call's
    concrete tensors (JAX arrays, traced like the slots), or ``None`` (no ``prepare``, or traced
    for shapes only)."""
    return _PREPARED.get()


def _with_prepared(value, function, *args):
    """``function(*args)`` with :func:`prepared` returning ``value`` meanwhile."""
    token = _PREPARED.set(value)
    try:
        return function(*args)
    finally:
        _PREPARED.reset(token)


# ---------------------------------------------------------------------------------------------
# JAX side: forward with residuals, pullback, VJP
# ---------------------------------------------------------------------------------------------


def _zero_cotangent(aval):
    if _is_float_dtype(aval.dtype):
        return jax.numpy.zeros(aval.shape, aval.dtype)
    return np.zeros(aval.shape, dtype=jax.dtypes.float0)


def _fill_cotangents(outputs, cotangents, present) -> tuple:
    """Cotangents for every output: the given ones where ``present``, zeros elsewhere."""
    given = iter(cotangents)
    return tuple(next(given) if p else _zero_cotangent(o) for o, p in zip(outputs, present))


@dataclass(frozen=True)
class _Linearization:
    outputs: tuple
    pullback: Callable
    # Where each leaf of the pullback's pytree comes from: ("input", i), ("output", i) or
    # ("residual", k). Inputs and outputs are not returned again as residuals: that would copy
    # them and make torch outputs alias torch inputs.
    sources: tuple
    residuals: tuple
    treedef: object


def _linearize(fn, slots, kinds, statics, wrt) -> _Linearization:
    leaves = _flatten(slots, kinds)
    diff_indices = tuple(i for i, (w, x) in enumerate(zip(wrt, leaves)) if w and x is not None and _is_float_dtype(x.dtype))

    def restricted(*diff):
        full = list(leaves)
        for i, x in zip(diff_indices, diff):
            full[i] = x
        return tuple(fn(_unflatten(full, slots, kinds), statics))

    outputs, pullback = jax.vjp(restricted, *(leaves[i] for i in diff_indices))
    pb_leaves, treedef = jax.tree_util.tree_flatten(pullback)
    known = {id(x): ("input", i) for i, x in enumerate(leaves) if x is not None}
    for i, x in enumerate(outputs):
        known.setdefault(id(x), ("output", i))
    sources: list[tuple[str, int]] = []
    residuals: list[jax.Array] = []
    for leaf in pb_leaves:
        source = known.get(id(leaf))
        if source is None:
            source = ("residual", len(residuals))
            residuals.append(jax.numpy.asarray(leaf))
            known[id(leaf)] = source
        sources.append(source)
    return _Linearization(outputs, pullback, tuple(sources), tuple(residuals), treedef)


def _distinct_outputs(outputs, leaves) -> tuple:
    """Copy outputs that are inputs (or repeat another output) so no torch output aliases."""
    seen = {id(x) for x in leaves if x is not None}
    out = []
    for x in outputs:
        if id(x) in seen:
            x = jax.numpy.copy(x)
        seen.add(id(x))
        out.append(x)
    return tuple(out)


def _forward_with_residuals(fn, kinds, slots, statics, wrt):
    leaves = _flatten(slots, kinds)
    if not any(wrt):
        return _distinct_outputs(tuple(fn(slots, statics)), leaves), ()
    lin = _linearize(fn, slots, kinds, statics, wrt)
    return _distinct_outputs(lin.outputs, leaves), lin.residuals


def _apply_saved_pullback(fn, kinds, slots, saved_outputs, saved_residuals, cotangents, statics, present, wrt):
    # Re-tracing the linearisation only recovers its structure; the recomputed forward is dead code
    # that XLA removes, and the saved residuals are used instead.
    lin = _linearize(fn, slots, kinds, statics, wrt)
    if [(r.shape, r.dtype) for r in lin.residuals] != [(r.shape, r.dtype) for r in saved_residuals]:
        raise RuntimeError(
            "torch_bridge: the linearisation traced for the backward pass does not match the one saved "
            "by the forward pass (was JAX's configuration changed in between?)"
        )
    leaves = _flatten(slots, kinds)
    pb_leaves = [leaves[i] if kind == "input" else saved_outputs[i] if kind == "output" else saved_residuals[i] for kind, i in lin.sources]
    pullback = jax.tree_util.tree_unflatten(lin.treedef, pb_leaves)
    return tuple(pullback(_fill_cotangents(lin.outputs, cotangents, present)))


def _vjp_function(fn, kinds):
    """``fn``'s VJP as a liftable function: slots gain a cotangent list, statics gain
    ``(present, wrt)``; it returns the gradients of the ``wrt`` leaves."""

    def vjp(slots, statics):
        *base_slots, cotangents = slots
        *base_statics, present, wrt = statics
        lin = _linearize(fn, tuple(base_slots), kinds, tuple(base_statics), wrt)
        return tuple(lin.pullback(_fill_cotangents(lin.outputs, cotangents, present)))

    return vjp


def _jvp_function(fn, kinds):
    """``fn``'s JVP as a liftable function: slots gain a tangent list, statics gain
    ``has_tangent`` (which leaves the tangents belong to); it returns the tangents of the
    floating-point outputs."""

    def jvp(slots, statics):
        *base_slots, tangents = slots
        *base_statics, has_tangent = statics
        base_slots, base_statics = tuple(base_slots), tuple(base_statics)
        leaves = _flatten(base_slots, kinds)
        indices = [i for i, h in enumerate(has_tangent) if h]

        def restricted(*diff):
            full = list(leaves)
            for i, x in zip(indices, diff):
                full[i] = x
            return tuple(fn(_unflatten(full, base_slots, kinds), base_statics))

        outputs, output_tangents = jax.jvp(restricted, tuple(leaves[i] for i in indices), tuple(tangents))
        return tuple(t for o, t in zip(outputs, output_tangents) if _is_float_dtype(o.dtype))

    return jvp


def _vmap_function(fn, kinds):
    """``fn`` mapped over a leading axis: statics gain ``batched`` (which leaves carry it)."""

    def batched(slots, statics):
        *base_statics, mask = statics
        base_statics = tuple(base_statics)

        def one(*leaves):
            return tuple(fn(_unflatten(leaves, slots, kinds), base_statics))

        return jax.vmap(one, in_axes=tuple(0 if m else None for m in mask))(*_flatten(slots, kinds))

    return batched


# ---------------------------------------------------------------------------------------------
# Torch side: a JAX function lifted to custom ops
# ---------------------------------------------------------------------------------------------


def _hashable(value):
    return tuple(value) if isinstance(value, list) else value


def _concrete(value):
    """Static values as plain Python (fake kernels may see symbolic numbers)."""
    if isinstance(value, (list, tuple)):
        return tuple(_concrete(v) for v in value)
    if isinstance(value, torch.SymInt):
        return int(value)
    if isinstance(value, torch.SymFloat):
        return float(value)
    if isinstance(value, torch.SymBool):
        return bool(value)
    return value


_PLAIN_TENSOR_TYPES = (torch.Tensor, torch.nn.Parameter)
_CUDAGRAPH_UNSAFE = (torch.Tag.cudagraph_unsafe,) if hasattr(torch.Tag, "cudagraph_unsafe") else ()


def _plain_eager(leaves) -> bool:
    """Whether a call can skip the dispatcher: eager mode, plain tensors, no dispatch or function
    modes, no functorch transform. Anything else (``torch.compile``, ``make_fx``, fake tensors,
    ``torch.func``, subclasses) goes through the custom op, which computes the same values."""
    if (
        torch.compiler.is_compiling()
        or torch._C._len_torch_dispatch_stack()
        or torch._C._is_torch_function_mode_enabled()
        or torch._C._functorch.peek_interpreter_stack() is not None
    ):
        return False
    return all(x is None or type(x) in _PLAIN_TENSOR_TYPES for x in leaves)


def _under_functorch() -> bool:
    """Whether a ``torch.func`` transform is active (outside ``torch.compile``, which keeps the
    custom op)."""
    return torch._C._are_functorch_transforms_active() and not torch.compiler.is_compiling()


def _detached(x):
    if isinstance(x, (list, tuple)):
        return type(x)(_detached(v) for v in x)
    return x.detach() if isinstance(x, torch.Tensor) else x


def _group(flat, list_lengths) -> list:
    """Regroup per-leaf values into slots (a list per list slot)."""
    grouped, i = [], 0
    for n in list_lengths:
        if n >= 0:
            grouped.append(flat[i : i + n])
            i += n
        else:
            grouped.append(flat[i])
            i += 1
    return grouped


class _EagerAutograd(torch.autograd.Function):
    """Autograd for plain eager calls: the forward keeps ``jax.vjp``'s residuals (as tensors,
    zero copy) and a first-order backward applies them; ``create_graph=True`` goes through the
    lifted VJP like the custom op's own formula."""

    @staticmethod
    def forward(ctx, lifted, slots, statics, wrt, num_outputs, *leaves):
        outputs, residuals = lifted._run_forward(slots, leaves, statics, wrt)
        num_outputs.append(len(outputs))
        ctx.set_materialize_grads(False)
        ctx.mark_non_differentiable(*residuals)
        ctx.save_for_backward(*leaves, *outputs, *residuals)
        ctx.lifted, ctx.statics, ctx.wrt = lifted, statics, lifted._effective_wrt(leaves, wrt)
        ctx.layout = (lifted._list_lengths(slots), len(leaves), len(outputs))
        return (*outputs, *residuals)

    @staticmethod
    def backward(ctx, *grads):
        list_lengths, num_leaves, num_outputs = ctx.layout
        saved = ctx.saved_tensors
        leaves = saved[:num_leaves]
        linearization = (saved[num_leaves : num_leaves + num_outputs], saved[num_leaves + num_outputs :], ctx.wrt)
        grads = ctx.lifted._leaf_gradients(
            _group(list(leaves), list_lengths),
            leaves,
            ctx.statics,
            grads[:num_outputs],
            ctx.lifted._effective_wrt(leaves, ctx.needs_input_grad[5:]),
            linearization,
        )
        return (None,) * 5 + tuple(grads)


class _FunctorchAutograd(torch.autograd.Function):
    """The route under ``torch.func`` transforms (``grad``, ``vjp``, ``jvp``, ``vmap`` and their
    compositions). The autograd.Function that ``register_autograd`` generates cannot run under
    functorch (pytorch/pytorch#168393), so this one states every rule itself, each through
    another lifted function so that transforms compose: ``backward`` calls :attr:`LiftedFunction.vjp`,
    ``jvp`` calls :attr:`LiftedFunction.jvp` (``jax.jvp``) and ``vmap`` calls
    :attr:`LiftedFunction.batched` (``jax.vmap``, so PyTorch's slow per-example fallback never
    runs). Functorch runs ``forward`` with the tensors of the innermost level unwrapped."""

    generate_vmap_rule = False

    @staticmethod
    def forward(lifted, statics, list_lengths, *leaves):
        slots = _group(list(leaves), list_lengths)
        if not _plain_eager(leaves):  # e.g. the fake tensors of make_fx under the transforms
            return tuple(lifted._call_op(slots, statics, [False] * len(leaves)))
        outputs, _ = lifted._run_forward(slots, leaves, statics, (False,) * len(leaves))
        return tuple(outputs)

    @staticmethod
    def setup_context(ctx, inputs, output):
        lifted, statics, list_lengths, *leaves = inputs
        ctx.set_materialize_grads(False)
        ctx.mark_non_differentiable(*(o for o in output if not o.is_floating_point()))
        ctx.save_for_backward(*leaves)
        ctx.save_for_forward(*leaves)
        ctx.lifted, ctx.statics, ctx.list_lengths = lifted, statics, list_lengths
        ctx.float_outputs = tuple(o.is_floating_point() for o in output)

    @staticmethod
    def backward(ctx, *grads):
        leaves = ctx.saved_tensors
        wanted = ctx.lifted._effective_wrt(leaves, ctx.needs_input_grad[3:])
        slots = _group(list(leaves), ctx.list_lengths)
        return (None, None, None, *ctx.lifted._leaf_gradients(slots, leaves, ctx.statics, grads, wanted))

    @staticmethod
    def jvp(ctx, lifted_tangent, statics_tangent, list_lengths_tangent, *tangents):
        leaves = ctx.saved_tensors
        has_tangent = ctx.lifted._effective_wrt(leaves, [t is not None for t in tangents])
        if not any(has_tangent):
            return tuple(None for _ in ctx.float_outputs)
        slots = _group(list(leaves), ctx.list_lengths)
        given = [t for t, h in zip(tangents, has_tangent) if h]
        output_tangents = iter(ctx.lifted.jvp.apply((*slots, given), (*ctx.statics, has_tangent)))
        return tuple(next(output_tangents) if is_float else None for is_float in ctx.float_outputs)

    @staticmethod
    def vmap(info, in_dims, lifted, statics, list_lengths, *leaves):
        leaf_dims = in_dims[3:]
        moved = [x if d is None else x.movedim(d, 0) for x, d in zip(leaves, leaf_dims)]
        batched = tuple(d is not None for d in leaf_dims)
        outputs = lifted.batched.apply(_group(moved, list_lengths), (*statics, batched))
        return tuple(outputs), (0,) * len(outputs)


class LiftedFunction:
    """A pure JAX function ``fn(slots, statics) -> tuple of arrays`` as a PyTorch custom op.

    Args:
        name: op name in the ``geomjax`` namespace.
        fn: the JAX function. ``slots`` holds one entry per tensor slot (an array, ``None`` for an
            absent optional tensor, or a tuple of arrays for a list slot); ``statics`` holds the
            hashable static options.
        slots: ``(name, kind)`` per tensor slot, kind ``"Tensor"``, ``"Tensor?"`` or ``"Tensor[]"``.
        statics: ``(name, schema_type)`` per static option, e.g. ``("kernel", "str")``.
        num_outputs: fixed number of outputs, or ``None`` when the outputs are a list.
        nondifferentiable: leaf indices that must not require grad (``ValueError``).
        eager_vjp_levels: how many levels of :attr:`vjp` ops to register right away.
        dynamic_outputs: for ops whose output sizes depend on the data (sampling, remeshing):
            ``f(slots, statics) -> [(trailing_shape, torch_dtype), ...]``, one per output, whose
            leading dimension is data-dependent. Such a function runs eagerly (geomjax cannot
            trace it), is not differentiable (no autograd formula; inputs are detached), and its
            fake kernel gives each output an unbacked leading size for ``torch.compile``.
        prepare: ``f(slots, statics) -> pytree of JAX arrays``, built on the host from a call's
            concrete tensors; see :func:`prepared`.
        real_placeholders: per static option, the value the fake kernel uses for a real option
            (``float``, ``float[]``: for each entry), whose tensor it cannot read (default 1.0;
            ignored for the other options).

    The op ``geomjax::<name>`` takes the slots, the statics (real options as 0-d float64 tensors,
    see :meth:`op_arguments`) and ``bool[] requires_grad`` (which leaves require grad: the kernel
    rejects non-differentiable ones, so the reference's ``ValueError`` is raised in compiled graphs
    too) and returns the outputs.
    """

    def __init__(
        self, name, fn, slots, statics, num_outputs, *, nondifferentiable=(), eager_vjp_levels=0, dynamic_outputs=None, prepare=None, real_placeholders=None
    ):
        self.name = name
        self.fn = fn
        self.slot_names = tuple(n for n, _ in slots)
        self.kinds = tuple(k for _, k in slots)
        self.static_names = tuple(n for n, _ in statics)
        self.static_types = tuple(t for _, t in statics)
        self.num_outputs = num_outputs
        self.nondifferentiable = frozenset(nondifferentiable)
        self._num_slots = len(slots)
        self._num_statics = len(statics)
        self._real_statics = tuple(t in REAL_OPTION_TYPES for t in self.static_types)
        placeholders = real_placeholders if real_placeholders is not None else [1.0] * len(statics)
        self._real_placeholders = tuple(p if real else None for p, real in zip(placeholders, self._real_statics))
        self._has_lists = TENSOR_LIST in self.kinds
        self._shape_cache = {}
        self._vjp = self._jvp = self._batched = None
        self.dynamic_outputs = dynamic_outputs
        self.prepare = prepare

        # Every program takes what ``prepare`` built as an argument (a pytree of arrays, or None),
        # and ``fn`` reads it through prepared() while it is traced.
        self._forward_jit = jax.jit(
            lambda slots, statics, wrt, extra: _with_prepared(extra, _forward_with_residuals, fn, self.kinds, slots, statics, wrt), static_argnums=(1, 2)
        )
        self._pullback_jit = jax.jit(
            lambda slots, outputs, residuals, cotangents, statics, present, wrt, extra: _with_prepared(
                extra, _apply_saved_pullback, fn, self.kinds, slots, outputs, residuals, cotangents, statics, present, wrt
            ),
            static_argnums=(4, 5, 6),
        )
        if dynamic_outputs is not None:
            self._forward_jit = lambda slots, statics, wrt, extra: (_distinct_outputs(tuple(_with_prepared(extra, fn, slots, statics)), slots), ())

        arguments = [f"{kind} {n}" for n, kind in slots] + [f"{REAL_OPTION_TYPES.get(t, t)} {n}" for n, t in statics] + ["bool[] requires_grad"]
        if num_outputs is None:
            returns = "Tensor[]"
        elif num_outputs == 1:
            returns = "Tensor"
        else:
            returns = f"({', '.join(['Tensor'] * num_outputs)})"
        op = torch.library.custom_op(
            f"{NAMESPACE}::{name}",
            self._kernel,
            mutates_args=(),
            schema=f"({', '.join(arguments)}) -> {returns}",
            # JAX launches work on its own CUDA stream: keep the op out of captured CUDA graphs.
            tags=_CUDAGRAPH_UNSAFE,
        )
        op.register_fake(self._fake)
        if dynamic_outputs is None:
            op.register_autograd(self._backward, setup_context=self._setup_context)
        self.op = op._opoverload
        # torch.compile looks the backward ops up as ``torch.ops.geomjax.<name>_vjp`` while it
        # builds the backward graph: registering them then is too late (AttributeError), so the
        # levels a compiled backward can reach are registered now.
        level = self
        for _ in range(eager_vjp_levels):
            level = level.vjp

    # -- calling --------------------------------------------------------------------------------

    def apply(self, slots, statics):
        """Run the function on tensors; returns its outputs (a tuple, or a list for list outputs)."""
        if self.dynamic_outputs is not None:  # not differentiable: outputs never require grad
            slots = tuple(_detached(x) for x in slots)
        leaves = _flatten(slots, self.kinds) if self._has_lists else slots
        requires_grad = [x is not None and x.requires_grad for x in leaves]
        if _under_functorch() and self.dynamic_outputs is None:
            statics = self._read_real_options(statics)
            self._check_inputs(slots, leaves, requires_grad)
            outputs = _FunctorchAutograd.apply(self, statics, self._list_lengths(slots), *leaves)
            return list(outputs) if self.num_outputs is None else tuple(outputs)
        if not _plain_eager(leaves):
            return self._call_op(slots, statics, requires_grad)
        # The op's own backward (run eagerly) passes its real options on as tensors; JAX takes
        # them as numbers.
        statics = self._read_real_options(statics)
        self._check_inputs(slots, leaves, requires_grad)
        wrt = tuple(requires_grad) if torch.is_grad_enabled() else (False,) * len(leaves)
        if any(wrt):
            num_outputs = []  # filled by forward: list outputs have no fixed count
            result = _EagerAutograd.apply(self, slots, statics, wrt, num_outputs, *leaves)
            outputs = result[: num_outputs[0]]
        else:
            outputs, _ = self._run_forward(slots, leaves, statics, wrt)
        return list(outputs) if self.num_outputs is None else tuple(outputs)

    def op_arguments(self, slots, statics, requires_grad) -> tuple:
        """The custom op's arguments for a call: the slots, the statics (real options as 0-d
        float64 tensors) and ``requires_grad``."""
        options = (_option_tensor(v) if real else v for v, real in zip(statics, self._real_statics))
        return (*slots, *options, list(requires_grad))

    def _read_real_options(self, statics) -> tuple:
        """``statics`` with real options given as tensors read back as Python floats."""
        return tuple(_read_option(v) if real and isinstance(v, torch.Tensor) else v for v, real in zip(statics, self._real_statics))

    def _call_op(self, slots, statics, requires_grad):
        result = self.op(*self.op_arguments(slots, statics, requires_grad))
        if self.num_outputs is None:
            return list(result)
        return (result,) if self.num_outputs == 1 else tuple(result)

    # -- kernels --------------------------------------------------------------------------------

    def _check_inputs(self, slots, leaves, requires_grad) -> None:
        """Mismatched devices and non-differentiable leaves that require grad are a
        ``ValueError``, as in the reference."""
        device = None
        for i, x in enumerate(leaves):
            if x is None:
                continue
            if device is None:
                device, first = x.device, i
            elif x.device != device:
                names = self.leaf_names(slots)
                raise ValueError(f"{self.name}: {names[i]} must be on the same device as {names[first]} ({device}), got {x.device}")
        for i in self.nondifferentiable:
            if requires_grad[i]:
                raise ValueError(f"{self.name}: {self.leaf_names(slots)[i]} is a non-differentiable parameter and must not require grad")

    def _as_arrays(self, slots, leaves):
        # Eager (dynamic-output) ops take JAX arrays; the others only feed jitted functions.
        jitted = self.dynamic_outputs is None
        arrays = [None if x is None else to_jax(x, jit_argument=jitted) for x in leaves]
        return _unflatten(arrays, slots, self.kinds) if self._has_lists else tuple(arrays)

    def _prepared(self, slots, statics):
        """``prepare``'s result for these concrete tensors (``None`` without a ``prepare``)."""
        return None if self.prepare is None else self.prepare(slots, statics)

    def _device_of(self, leaves) -> torch.device:
        return next(x.device for x in leaves if x is not None)

    def _run_forward(self, slots, leaves, statics, wrt, keep_residuals=True):
        """Outputs and (when ``wrt`` selects leaves and ``keep_residuals``) the residuals of
        their linearisation."""
        device = self._device_of(leaves)
        # A failed runtime check of geomjax (equinox.error_if, host callback) raises the op's
        # documented exception type with its message, as the eager geomjax call does.
        with documented_errors():
            with x64_for(leaves):
                outputs, residuals = self._forward_jit(self._as_arrays(slots, leaves), statics, wrt, self._prepared(slots, statics))
            return [to_torch(o, device) for o in outputs], [to_torch(r, device) for r in residuals] if keep_residuals else []

    def _run_pullback(self, slots, leaves, outputs, residuals, cotangents, statics, present, wrt):
        device = self._device_of(leaves)
        with documented_errors():  # see _run_forward
            with x64_for([*leaves, *residuals]):
                grads = self._pullback_jit(
                    self._as_arrays(slots, leaves),
                    tuple(to_jax(x, keep=False) for x in outputs),
                    tuple(to_jax(x, keep=False) for x in residuals),
                    tuple(to_jax(x, keep=False) for x in cotangents),
                    statics,
                    present,
                    wrt,
                    self._prepared(slots, statics),
                )
            return [to_torch(g, device) for g in grads]

    def _split(self, args):
        """The op's arguments as ``(slots, statics)``; real options stay tensors."""
        slots = args[: self._num_slots]
        statics = tuple(_hashable(v) for v in args[self._num_slots : self._num_slots + self._num_statics])
        return slots, statics

    def _shape_statics(self, statics) -> tuple:
        """``statics`` for computing output shapes: real options given as (possibly fake) tensors
        take their placeholders (a sequence: one per entry). No real option changes an output's
        shape or dtype."""

        def placeholder(value, real, stand_in):
            if not (real and isinstance(value, torch.Tensor)):
                return value
            return stand_in if value.ndim == 0 else (stand_in,) * int(value.shape[0])

        return tuple(placeholder(*entry) for entry in zip(statics, self._real_statics, self._real_placeholders))

    def _kernel(self, *args):
        slots, statics = self._split(args)
        statics = self._read_real_options(statics)
        leaves = _flatten(slots, self.kinds) if self._has_lists else slots
        self._check_inputs(slots, leaves, args[-1])
        # The same XLA program as an eager call with the same leaves requiring grad (whose forward
        # keeps the linearisation's residuals; here they are dropped): XLA fuses a forward alone
        # differently, and compiled and eager values should agree bitwise, not to rounding.
        # (The kernel runs below autograd, with grad mode off: ``requires_grad`` says what the
        # caller's leaves require.)
        # A VJP op (a compiled backward, double backward) computes just its gradients: linearising
        # it would build the next derivative's residuals (compiled and run, then dropped) for a
        # bitwise match that its eager counterpart, the saved pullback, does not share anyway.
        wrt = (False,) * len(leaves) if self._is_derivative else self._effective_wrt(leaves, args[-1])
        outputs, _ = self._run_forward(slots, leaves, statics, wrt, keep_residuals=False)
        if self.num_outputs is None:
            return outputs
        return outputs[0] if self.num_outputs == 1 else tuple(outputs)

    def leaf_names(self, slots) -> list:
        names: list[str] = []
        for name, value, kind in zip(self.slot_names, slots, self.kinds):
            if kind == TENSOR_LIST:
                names.extend(f"{name}[{i}]" for i in range(len(value)))
            else:
                names.append(name)
        return names

    def _list_lengths(self, slots) -> tuple:
        return tuple(len(s) if k == TENSOR_LIST else -1 for s, k in zip(slots, self.kinds))

    # -- fake kernel ----------------------------------------------------------------------------

    def _fake(self, *args):
        slots, statics = self._split(args)
        statics = _concrete(self._shape_statics(statics))
        leaves = _flatten(slots, self.kinds)
        device = self._device_of(leaves)
        if self.dynamic_outputs is not None:
            context = torch.library.get_ctx()
            specs = [((context.new_dynamic_size(), *trailing), dtype) for trailing, dtype in self.dynamic_outputs(slots, statics)]
        else:
            specs = self._output_specs(slots, leaves, statics)
        if specs is None:
            # geomjax rejects these inputs: return placeholders and let the real kernel raise the
            # same exception (with its own type) when the compiled graph runs.
            first = next(x for x in leaves if x is not None)
            specs = [(first.shape, first.dtype)] * (self.num_outputs or 0)
        outputs = [torch.empty(shape, dtype=dtype, device=device) for shape, dtype in specs]
        if self.num_outputs is None:
            return outputs
        return outputs[0] if self.num_outputs == 1 else tuple(outputs)

    def _output_specs(self, slots, leaves, statics):
        statics = self._shape_statics(statics)
        shapes = tuple(None if x is None else (tuple(int(d) for d in x.shape), x.dtype) for x in leaves)
        key = (shapes, self._list_lengths(slots), statics, jax.config.jax_enable_x64)
        if key in self._shape_cache:
            return self._shape_cache[key]
        structs = [None if s is None else jax.ShapeDtypeStruct(s[0], numpy_dtype(s[1])) for s in shapes]
        try:
            with x64_for(leaves):
                outputs = jax.eval_shape(lambda arrays: tuple(self.fn(arrays, statics)), _unflatten(structs, slots, self.kinds))
        except Exception:
            return None
        specs = [(o.shape, torch_dtype(o.dtype)) for o in outputs]
        self._shape_cache[key] = specs
        return specs

    # -- autograd (the op's formula) ------------------------------------------------------------

    @staticmethod
    def _effective_wrt(leaves, wrt) -> tuple:
        return tuple(bool(w) and x is not None and x.is_floating_point() for w, x in zip(wrt, leaves))

    def _setup_context(self, ctx, inputs, output):
        ctx.set_materialize_grads(False)
        slots, statics = self._split(inputs)
        ctx.save_for_backward(*_flatten(slots, self.kinds))
        ctx.statics, ctx.list_lengths = statics, self._list_lengths(slots)

    def _backward(self, ctx, *grads):
        leaves = list(ctx.saved_tensors)
        needs = []
        for need, n in zip(ctx.needs_input_grad[: self._num_slots], ctx.list_lengths):
            needs.extend((need if isinstance(need, (list, tuple)) else [need] * n) if n >= 0 else [need])
        grads = self._leaf_gradients(
            _group(leaves, ctx.list_lengths), leaves, ctx.statics, list(grads[0]) if self.num_outputs is None else grads, self._effective_wrt(leaves, needs)
        )
        return (*_group(grads, ctx.list_lengths), *([None] * (self._num_statics + 1)))

    def _leaf_gradients(self, slots, leaves, statics, grad_outputs, wanted, linearization=None) -> list:
        """Gradients of the ``wanted`` leaves (``None`` elsewhere) for the output cotangents
        ``grad_outputs`` (``None``: zero).

        ``linearization`` is ``(outputs, residuals, wrt)`` saved by an eager forward; a first-order
        backward applies it. Otherwise — ``create_graph=True``, or the custom op's own formula —
        the lifted VJP recomputes the forward and is itself differentiable.
        """
        present = tuple(g is not None for g in grad_outputs)
        result = [None] * len(leaves)
        if not (any(wanted) and any(present)):
            return result
        if self._is_derivative and not all(present):
            grad_outputs, present = self._with_zero_cotangents(slots, leaves, statics, grad_outputs)
        cotangents = [g for g in grad_outputs if g is not None]
        if (
            linearization is not None
            and not torch.is_grad_enabled()
            and all(saved or not w for saved, w in zip(linearization[2], wanted))
            and _plain_eager(cotangents)
        ):
            outputs, residuals, wrt = linearization
            grads = self._run_pullback(slots, leaves, outputs, residuals, cotangents, statics, present, wrt)
            positions = [i for i, w in enumerate(wrt) if w]
        else:
            grads = self.vjp.apply((*slots, cotangents), (*statics, present, wanted))
            positions = [i for i, w in enumerate(wanted) if w]
        for i, g in zip(positions, grads):
            if wanted[i]:
                result[i] = g
        return result

    @property
    def _is_derivative(self) -> bool:
        """Whether this function is a VJP (so its own pullback is a second or higher derivative)."""
        return "_vjp" in self.name

    def _with_zero_cotangents(self, slots, leaves, statics, grad_outputs):
        """``grad_outputs`` with an explicit zero for every absent floating-point cotangent.

        Each pattern of present cotangents is another compiled program, and at second order each
        costs seconds to compile: double backward (``gradgradcheck``, Hessian-vector products)
        asks for one output's gradient at a time, one program per output (11 for morph_points).
        With zeros filled in, every pattern shares the all-present program; the result is the same
        (the pullback is linear in the cotangents), for a little more arithmetic.
        """
        specs = self._output_specs(slots, leaves, statics)
        if specs is None:  # cannot happen after a successful forward; keep the given pattern
            return grad_outputs, tuple(g is not None for g in grad_outputs)
        device = self._device_of(leaves)
        filled = [
            torch.zeros(shape, dtype=dtype, device=device) if g is None and dtype.is_floating_point else g for g, (shape, dtype) in zip(grad_outputs, specs)
        ]
        return filled, tuple(g is not None for g in filled)

    def _derived(self, suffix: str, fn, extra_slots, extra_statics, num_outputs, **options) -> LiftedFunction:
        """A function derived from this one (its VJP, JVP or vmap), lifted the same way. The extra
        slots and (``bool[]``) statics are numbered by nesting depth, so nested levels stay distinct.
        It prepares what this one does, from this one's slots and statics (its own come first)."""
        depth = self.name.count(suffix) + 1
        prepare = None
        if self.prepare is not None:
            base_prepare, num_slots, num_statics = self.prepare, self._num_slots, self._num_statics

            def prepare(slots, statics):
                return base_prepare(slots[:num_slots], statics[:num_statics])

        return LiftedFunction(
            f"{self.name}{suffix}",
            fn,
            [*zip(self.slot_names, self.kinds), *((f"{name}_{depth}", kind) for name, kind in extra_slots)],
            [*zip(self.static_names, self.static_types), *((f"{name}_{depth}", "bool[]") for name in extra_statics)],
            num_outputs,
            prepare=prepare,
            real_placeholders=[*self._real_placeholders, *([None] * len(extra_statics))],
            **options,
        )

    @property
    def vjp(self) -> LiftedFunction:
        """The VJP of this function, lifted the same way (created on first use beyond ``eager_vjp_levels``)."""
        if self._vjp is None:
            vjp = _vjp_function(self.fn, self.kinds)
            self._vjp = self._derived("_vjp", vjp, [("cotangents", TENSOR_LIST)], ["present", "wrt"], None)
        return self._vjp

    @property
    def jvp(self) -> LiftedFunction:
        """The JVP of this function (floating-point outputs only), lifted the same way."""
        if self._jvp is None:
            jvp = _jvp_function(self.fn, self.kinds)
            self._jvp = self._derived("_jvp", jvp, [("tangents", TENSOR_LIST)], ["has_tangent"], None)
        return self._jvp

    @property
    def batched(self) -> LiftedFunction:
        """This function mapped over the leading axis of the leaves selected by a static mask."""
        if self._batched is None:
            mapped = _vmap_function(self.fn, self.kinds)
            self._batched = self._derived("_vmap", mapped, [], ["batched"], self.num_outputs, nondifferentiable=self.nondifferentiable)
        return self._batched
