"""Generic machinery that turns a table of geomjax ops into PyTorch functions.

A table entry is the reference signature of an op (``_ops.py``). From it this module builds:

* the public function, with the reference's name, parameters, defaults and keyword-only marker
  (:func:`make_public_function`);
* a ``torch.library.custom_op`` ``geomjax::<name>`` whose schema holds the tensor arguments
  (``Tensor`` / ``Tensor?``) and the static options (``float``, ``bool``, ``str``, lists, ...).
  Python argument forms a schema cannot hold (``radius: float | Tensor``,
  ``origin: Tensor | Sequence[float]``) are split into a ``Tensor?`` slot and a static slot.

Every custom op here is a :class:`LiftedFunction`: a pure JAX function ``fn(slots, statics)``
lifted to PyTorch. Its kernel converts tensors to JAX arrays with DLPack (zero copy), runs a cached
``jax.jit`` of ``fn`` (static options are static arguments) and converts the outputs back. Its
autograd formula (``register_autograd``) calls the forward op of another ``LiftedFunction`` whose
``fn`` is the VJP of this one, lifted the same way, so gradients of any order the JAX path supports
work (``gradgradcheck``), and ``torch.compile`` sees custom ops whose outputs are exactly the
public outputs.

Plain eager calls (the common case) skip the dispatcher's per-call Python layers: they run the same
kernels through a ``torch.autograd.Function`` that keeps the residuals of ``jax.vjp`` from the
forward pass, so a first-order backward applies the saved linearisation instead of recomputing the
forward (the pure-JAX cost of ``jax.vjp``). Residuals never appear in op schemas: their number and
shapes are geomjax internals, and compiled graphs cached on disk by ``torch.compile`` must not
depend on them.

Fake (meta) kernels obtain output shapes from geomjax itself with ``jax.eval_shape``. When geomjax
rejects the inputs, the fake returns placeholders instead of raising, so under ``torch.compile``
the real kernel raises geomjax's exception — with its original type — when the graph runs.

float64 (and int64) tensors run under a local ``jax.enable_x64(True)`` context: the user never
configures JAX and the global flag is never flipped.
"""

from __future__ import annotations

import ast
import contextlib
import inspect
import numbers
import weakref
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import jax
import numpy as np
import torch
import torch.utils.dlpack

NAMESPACE = "geomjax"

# ---------------------------------------------------------------------------------------------
# dtypes and DLPack
# ---------------------------------------------------------------------------------------------

_TORCH_FROM_NUMPY = {
    np.dtype(np.float16): torch.float16,
    np.dtype(np.float32): torch.float32,
    np.dtype(np.float64): torch.float64,
    np.dtype(np.int8): torch.int8,
    np.dtype(np.int16): torch.int16,
    np.dtype(np.int32): torch.int32,
    np.dtype(np.int64): torch.int64,
    np.dtype(np.uint8): torch.uint8,
    np.dtype(np.bool_): torch.bool,
    np.dtype(np.complex64): torch.complex64,
    np.dtype(np.complex128): torch.complex128,
}
_TORCH_FROM_NUMPY[np.dtype(jax.numpy.bfloat16)] = torch.bfloat16
_NUMPY_FROM_TORCH = {v: k for k, v in _TORCH_FROM_NUMPY.items()}
_WIDE_DTYPES = frozenset({torch.float64, torch.int64, torch.complex128})


def torch_dtype(dtype) -> torch.dtype:
    return _TORCH_FROM_NUMPY[np.dtype(dtype)]


def _x64_for(tensors) -> contextlib.AbstractContextManager:
    """A local x64 context when any tensor is 64-bit, so float64 round-trips exactly."""
    for t in tensors:
        if t is not None and t.dtype in _WIDE_DTYPES:
            return jax.enable_x64(True)
    return contextlib.nullcontext()


def _fast_cpu_converters() -> tuple[Callable, Callable] | None:
    """Zero-copy CPU DLPack converters that skip the Python layers of the public APIs.

    ``jax.dlpack.from_dlpack`` and ``jax.Array.__dlpack__`` spend ~80 µs and ~15 µs per CPU array
    in jax 0.10 on Python-level device lookups and checks that are no-ops for a CPU tensor; these
    call the same jaxlib entry points directly. They are verified once (values, zero copy, both
    directions) and replaced by the public APIs if the private entry points are missing or behave
    differently. CUDA always uses the public, stream-aware protocol.
    """
    try:
        from jax._src.lib import _jax, jaxlib_extension_version

        cpu = jax.devices("cpu")[0]
        to_capsule, from_capsule = torch.utils.dlpack.to_dlpack, torch.utils.dlpack.from_dlpack
        if jaxlib_extension_version >= 467:

            def import_cpu(t):
                return _jax.dlpack_managed_tensor_to_buffer(to_capsule(t), cpu, None, None, 1)
        else:  # pragma: no cover - older jaxlib

            def import_cpu(t):
                return _jax.dlpack_managed_tensor_to_buffer(to_capsule(t), cpu, None, None)

        def export_cpu(a):
            return from_capsule(_jax.buffer_to_dlpack_managed_tensor(a))

        probe = torch.arange(12, dtype=torch.float32).reshape(4, 3)
        array = import_cpu(probe)
        result = jax.jit(lambda x: x * 2.0)(array)
        back = export_cpu(result)
        ok = (
            isinstance(array, jax.Array)
            and array.unsafe_buffer_pointer() == probe.data_ptr()
            and back.data_ptr() == result.unsafe_buffer_pointer()
            and torch.equal(back, probe * 2)
        )
        return (import_cpu, export_cpu) if ok else None
    except Exception:  # pragma: no cover - depends on the jaxlib build
        return None


_import_cpu, _export_cpu = _fast_cpu_converters() or (
    jax.dlpack.from_dlpack,
    lambda a: torch.utils.dlpack.from_dlpack(a.__dlpack__()),
)


# A small tensor seen for the first time goes to the jitted function as a NumPy view: jit's C++
# dispatch takes a NumPy argument ~20 µs faster than a freshly imported DLPack buffer (whose
# sharding is built in Python), and copying a few kilobytes costs nothing next to that
# (measured). A kept DLPack view pays off only for tensors that come back.
SMALL_CPU_BYTES = 16 * 2**10
_FIRST_SIGHTINGS = 1024  # bound on the remembered first sightings (cleared when full)


class _CpuViews:
    """Zero-copy JAX views of CPU tensors, kept while the tensor lives.

    Inputs that are passed again — fixed points and controls, parameters updated in place — skip
    the ~15 µs of a DLPack import and release. A view shares the tensor's memory, so in-place
    updates are seen; it is reused only while the tensor keeps the same memory, shape, strides and
    dtype. Copies (unaligned memory) are never kept, and CUDA tensors are never kept: each CUDA
    import must order JAX after PyTorch's current stream. With ``numpy_first`` (arguments of a
    jitted function) a small tensor gets a kept view on its second call only and its first call
    returns a NumPy view (see ``SMALL_CPU_BYTES``), so tensors made anew for every call never pay
    for a view and its weak reference.
    """

    def __init__(self):
        self._views = {}
        self._seen = {}  # id -> signature of small tensors passed once (a hint, not a reference)

    def __call__(self, t: torch.Tensor, *, numpy_first: bool = False):
        key = id(t)
        entry = self._views.get(key)
        if entry is not None:
            ref, signature, array = entry
            if ref() is t and signature == (t.data_ptr(), t.shape, t.stride(), t.dtype):
                return array
        signature = (t.data_ptr(), t.shape, t.stride(), t.dtype)
        if numpy_first and t.numel() * t.element_size() <= SMALL_CPU_BYTES and self._seen.get(key) != signature:
            small = _numpy_view(t)
            if small is not None:
                if len(self._seen) >= _FIRST_SIGHTINGS:
                    self._seen.clear()
                self._seen[key] = signature
                return small
        # Import a detached alias: a capsule holding ``t`` itself would keep ``t`` alive through
        # the kept view, so the weak reference below would never fire.
        array = _import_cpu(t.detach())
        if array.unsafe_buffer_pointer() == t.data_ptr():
            views = self._views
            ref = weakref.ref(t, lambda _, key=key: views.pop(key, None))
            views[key] = (ref, signature, array)
        return array


def _numpy_view(t: torch.Tensor) -> np.ndarray | None:
    """``t`` as a NumPy array sharing its memory, or ``None`` where NumPy cannot hold it (bfloat16,
    tensors with a lazy negation or conjugation bit)."""
    try:
        return t.detach().numpy()
    except (TypeError, RuntimeError):
        return None


_cpu_views = _CpuViews()


def to_jax(t: torch.Tensor, *, keep: bool = True, jit_argument: bool = False) -> jax.Array | np.ndarray:
    """Zero-copy view of a tensor as a JAX array (made contiguous first). CUDA tensors go through
    the stream-aware DLPack protocol, so JAX waits for PyTorch's current stream. ``keep=False``
    is for transient tensors (saved outputs and residuals, which autograd re-wraps on every
    unpack, and cotangents): their views are not kept for reuse. ``jit_argument=True`` (the
    array only goes into a jitted function) lets a small CPU tensor's first call pass a NumPy
    view instead (see ``_CpuViews``)."""
    if not t.is_contiguous():
        t = t.contiguous()
    elif keep and t.is_cpu:
        return _cpu_views(t, numpy_first=jit_argument)
    if t.requires_grad:
        t = t.detach()
    return _import_cpu(t) if t.is_cpu else jax.dlpack.from_dlpack(t)


def to_torch(a: jax.Array, device: torch.device) -> torch.Tensor:
    """Zero-copy view of a JAX array on ``device`` as a tensor. On CUDA the consumer-stream
    protocol makes PyTorch's current stream wait for JAX's result."""
    if a.size == 0:  # DLPack strides of empty buffers differ between producers; normalise them
        return torch.empty(a.shape, dtype=torch_dtype(a.dtype), device=device)
    return _export_cpu(a) if device.type == "cpu" else torch.from_dlpack(a)


# ---------------------------------------------------------------------------------------------
# slots: the tensor arguments of a lifted function
# ---------------------------------------------------------------------------------------------

TENSOR, OPTIONAL_TENSOR, TENSOR_LIST = "Tensor", "Tensor?", "Tensor[]"


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
    diff_indices = tuple(
        i for i, (w, x) in enumerate(zip(wrt, leaves)) if w and x is not None and _is_float_dtype(x.dtype)
    )

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
    sources, residuals = [], []
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
    pb_leaves = [
        leaves[i] if kind == "input" else saved_outputs[i] if kind == "output" else saved_residuals[i]
        for kind, i in lin.sources
    ]
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

    The op ``geomjax::<name>`` takes the slots, the statics and ``bool[] requires_grad`` (which
    leaves require grad: the kernel rejects non-differentiable ones, so the reference's
    ``ValueError`` is raised in compiled graphs too) and returns the outputs.
    """

    def __init__(
        self, name, fn, slots, statics, num_outputs, *, nondifferentiable=(), eager_vjp_levels=0, dynamic_outputs=None
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
        self._has_lists = TENSOR_LIST in self.kinds
        self._shape_cache = {}
        self._vjp = None
        self.dynamic_outputs = dynamic_outputs

        self._forward_jit = jax.jit(
            lambda slots, statics, wrt: _forward_with_residuals(fn, self.kinds, slots, statics, wrt),
            static_argnums=(1, 2),
        )
        self._pullback_jit = jax.jit(
            lambda slots, outputs, residuals, cotangents, statics, present, wrt: _apply_saved_pullback(
                fn, self.kinds, slots, outputs, residuals, cotangents, statics, present, wrt
            ),
            static_argnums=(4, 5, 6),
        )
        if dynamic_outputs is not None:
            self._forward_jit = lambda slots, statics, wrt: (_distinct_outputs(tuple(fn(slots, statics)), slots), ())

        arguments = [f"{kind} {n}" for n, kind in slots] + [f"{t} {n}" for n, t in statics] + ["bool[] requires_grad"]
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
        if not _plain_eager(leaves):
            result = self.op(*slots, *statics, requires_grad)
            if self.num_outputs is None:
                return list(result)
            return (result,) if self.num_outputs == 1 else tuple(result)
        self._check_inputs(slots, leaves, requires_grad)
        wrt = tuple(requires_grad) if torch.is_grad_enabled() else (False,) * len(leaves)
        if any(wrt):
            num_outputs = []  # filled by forward: list outputs have no fixed count
            result = _EagerAutograd.apply(self, slots, statics, wrt, num_outputs, *leaves)
            outputs = result[: num_outputs[0]]
        else:
            outputs, _ = self._run_forward(slots, leaves, statics, wrt)
        return list(outputs) if self.num_outputs is None else tuple(outputs)

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
                raise ValueError(
                    f"{self.name}: {names[i]} must be on the same device as {names[first]} ({device}), "
                    f"got {x.device}"
                )
        for i in self.nondifferentiable:
            if requires_grad[i]:
                raise ValueError(
                    f"{self.name}: {self.leaf_names(slots)[i]} is a non-differentiable parameter and must "
                    "not require grad"
                )

    def _as_arrays(self, slots, leaves):
        # Eager (dynamic-output) ops take JAX arrays; the others only feed jitted functions.
        jitted = self.dynamic_outputs is None
        arrays = [None if x is None else to_jax(x, jit_argument=jitted) for x in leaves]
        return _unflatten(arrays, slots, self.kinds) if self._has_lists else tuple(arrays)

    def _device_of(self, leaves) -> torch.device:
        return next(x.device for x in leaves if x is not None)

    def _run_forward(self, slots, leaves, statics, wrt):
        """Outputs and (when ``wrt`` selects leaves) the residuals of their linearisation."""
        device = self._device_of(leaves)
        with _x64_for(leaves):
            outputs, residuals = self._forward_jit(self._as_arrays(slots, leaves), statics, wrt)
        return [to_torch(o, device) for o in outputs], [to_torch(r, device) for r in residuals]

    def _run_pullback(self, slots, leaves, outputs, residuals, cotangents, statics, present, wrt):
        device = self._device_of(leaves)
        with _x64_for([*leaves, *residuals]):
            grads = self._pullback_jit(
                self._as_arrays(slots, leaves),
                tuple(to_jax(x, keep=False) for x in outputs),
                tuple(to_jax(x, keep=False) for x in residuals),
                tuple(to_jax(x, keep=False) for x in cotangents),
                statics,
                present,
                wrt,
            )
        return [to_torch(g, device) for g in grads]

    def _split(self, args):
        slots = args[: self._num_slots]
        statics = tuple(_hashable(v) for v in args[self._num_slots : self._num_slots + self._num_statics])
        return slots, statics

    def _kernel(self, *args):
        slots, statics = self._split(args)
        leaves = _flatten(slots, self.kinds) if self._has_lists else slots
        self._check_inputs(slots, leaves, args[-1])
        outputs, _ = self._run_forward(slots, leaves, statics, (False,) * len(leaves))
        if self.num_outputs is None:
            return outputs
        return outputs[0] if self.num_outputs == 1 else tuple(outputs)

    def leaf_names(self, slots) -> list:
        names = []
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
        statics = _concrete(statics)
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
        shapes = tuple(None if x is None else (tuple(int(d) for d in x.shape), x.dtype) for x in leaves)
        key = (shapes, self._list_lengths(slots), statics, jax.config.jax_enable_x64)
        if key in self._shape_cache:
            return self._shape_cache[key]
        structs = [None if s is None else jax.ShapeDtypeStruct(s[0], _NUMPY_FROM_TORCH[s[1]]) for s in shapes]
        try:
            with _x64_for(leaves):
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
            _group(leaves, ctx.list_lengths),
            leaves,
            ctx.statics,
            list(grads[0]) if self.num_outputs is None else grads,
            self._effective_wrt(leaves, needs),
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
    def vjp(self) -> LiftedFunction:
        """The VJP of this function, lifted the same way (created on first use beyond ``eager_vjp_levels``)."""
        if self._vjp is None:
            depth = self.name.count("_vjp") + 1
            self._vjp = LiftedFunction(
                f"{self.name}_vjp",
                _vjp_function(self.fn, self.kinds),
                [*zip(self.slot_names, self.kinds), (f"cotangents_{depth}", TENSOR_LIST)],
                [*zip(self.static_names, self.static_types), (f"present_{depth}", "bool[]"), (f"wrt_{depth}", "bool[]")],
                None,
            )
        return self._vjp


# ---------------------------------------------------------------------------------------------
# Table entries: reference signature -> public function
# ---------------------------------------------------------------------------------------------

_REQUIRED = object()
_BAD = object()


def _static_normalizer(schema_type: str) -> Callable:
    """Map a Python option to the value a schema slot holds, or ``_BAD`` if it cannot hold it."""
    optional = schema_type.endswith("?")
    base = schema_type.rstrip("?")

    def real(v):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Real, torch.SymFloat, torch.SymInt)):
            return _BAD
        return float(v) if isinstance(v, numbers.Real) else v

    def integer(v):
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (numbers.Integral, torch.SymInt)):
            return _BAD
        return int(v) if isinstance(v, numbers.Integral) else v

    def boolean(v):
        return bool(v) if isinstance(v, (bool, np.bool_)) else _BAD

    def string(v):
        return v if isinstance(v, str) else _BAD

    def sequence_of(element):
        def normalize(v):
            if isinstance(v, torch.Tensor) and element is integer and v.ndim == 1 and not v.is_floating_point():
                # e.g. grid_dims given as a tensor: its values are shapes, read on the host.
                v = v.tolist()
            if isinstance(v, (str, bytes)) or not isinstance(v, Sequence):
                return _BAD
            out = tuple(element(x) for x in v)
            return _BAD if any(x is _BAD for x in out) else out

        return normalize

    normalizers = {"float": real, "int": integer, "bool": boolean, "str": string}
    if base.endswith("[]"):
        inner = sequence_of(normalizers[base[:-2]])
    else:
        inner = normalizers[base]
    if optional:
        return lambda v: None if v is None else inner(v)
    return inner


_OPTION_WORDS = {
    "float": "a real number",
    "int": "an integer",
    "bool": "a bool",
    "str": "a string",
    "float[]": "a sequence of real numbers",
    "int[]": "a sequence of integers",
}

_ANNOTATION_TYPES = {
    "float": "float",
    "int": "int",
    "bool": "bool",
    "str": "str",
    "Sequence[float]": "float[]",
    "Sequence[int]": "int[]",
}


@dataclass(frozen=True)
class Parameter:
    """One parameter of a public function, read from the reference signature."""

    name: str
    keyword_only: bool
    default: object
    tensor_slot: int | None  # index of its Tensor/Tensor? slot
    static_slot: int | None  # index of its static slot
    static_type: str | None
    optional: bool
    sequence_slot: int | None = None  # index of its sequence static slot (``int | Sequence[int]``)


def _parse_annotation(name: str, annotation: str) -> tuple[bool, str | None, bool, str | None]:
    """``(has_tensor, static_schema_type, optional, sequence_schema_type)`` from an annotation like
    ``float | Tensor``; ``int | Sequence[int]`` gives ``("int", "int[]")`` as the two static forms."""
    has_tensor, optional, statics = False, False, []
    for member in (m.strip() for m in annotation.split("|")):
        if member == "Tensor":
            has_tensor = True
        elif member == "None":
            optional = True
        elif member.startswith("Literal["):
            statics.append("str")
        elif member in _ANNOTATION_TYPES:
            statics.append(_ANNOTATION_TYPES[member])
        else:
            raise ValueError(f"parameter {name}: unsupported annotation member {member!r}")
    forms = sorted(set(statics), key=len)
    if len(forms) == 2 and forms[1] == forms[0] + "[]":
        return has_tensor, forms[0], optional, forms[1]
    if len(forms) > 1:
        raise ValueError(f"parameter {name}: more than one static form in {annotation!r}")
    return has_tensor, (forms[0] if forms else None), optional, None


class BridgedOp:
    """One table entry: a geomjax function exposed to PyTorch under its reference signature.

    Args:
        signature: the reference signature, e.g.
            ``"displace_points(points: Tensor, displacement: Tensor, *, point_weights: Tensor | None
            = None, implementation: str | None = None) -> Tensor"``. Annotations use ``Tensor``,
            ``None``, ``float``, ``int``, ``bool``, ``str``, ``Literal[...]`` and
            ``Sequence[float | int]``, joined with ``|``; the return is ``Tensor`` or
            ``tuple[Tensor, ...]``.
        function: the geomjax function with the same parameter names.
        nondifferentiable: tensor parameters that must not require grad (``ValueError``).
        dynamic_outputs: for a non-differentiable op with data-dependent output sizes,
            ``f(arguments) -> [(trailing_shape, torch_dtype), ...]`` given the bound arguments by
            name (tensors may be fake); see :class:`LiftedFunction`.
    """

    def __init__(
        self,
        signature: str,
        function: Callable,
        *,
        nondifferentiable: Sequence[str] = (),
        dynamic_outputs: Callable[[dict], list] | None = None,
    ):
        tree = ast.parse(f"def {signature}: pass").body[0]
        self.name = tree.name
        self.function = function
        returns = ast.unparse(tree.returns)
        if returns == "Tensor":
            self.num_outputs, self.single_output = 1, True
        elif returns.startswith("tuple["):
            self.num_outputs, self.single_output = len(tree.returns.slice.elts), False
        else:
            raise ValueError(f"{self.name}: unsupported return annotation {returns!r}")

        positional, keyword_only = tree.args.args, tree.args.kwonlyargs
        defaults = [_REQUIRED] * (len(positional) - len(tree.args.defaults)) + list(tree.args.defaults)
        defaults += [_REQUIRED if d is None else d for d in tree.args.kw_defaults]
        slots, statics, params = [], [], []
        for i, (arg, default) in enumerate(zip([*positional, *keyword_only], defaults)):
            has_tensor, static_type, optional, sequence_type = _parse_annotation(arg.arg, ast.unparse(arg.annotation))
            tensor_slot = static_slot = sequence_slot = None
            if has_tensor:
                tensor_slot = len(slots)
                slots.append((arg.arg, OPTIONAL_TENSOR if (optional or static_type) else TENSOR))
            if static_type:
                static_slot = len(statics)
                schema_type = static_type + ("?" if (optional or has_tensor or sequence_type) else "")
                statics.append((f"{arg.arg}_value" if has_tensor else arg.arg, schema_type))
            if sequence_type:
                sequence_slot = len(statics)
                statics.append((f"{arg.arg}_sequence", sequence_type + "?"))
            params.append(
                Parameter(
                    name=arg.arg,
                    keyword_only=i >= len(positional),
                    default=_REQUIRED if default is _REQUIRED else ast.literal_eval(default),
                    tensor_slot=tensor_slot,
                    static_slot=static_slot,
                    static_type=statics[static_slot][1] if static_type else None,
                    optional=optional,
                    sequence_slot=sequence_slot,
                )
            )
        self.parameters = tuple(params)
        unknown = set(nondifferentiable) - {p.name for p in params if p.tensor_slot is not None}
        if unknown:
            raise ValueError(f"{self.name}: nondifferentiable names unknown tensor parameters {sorted(unknown)}")
        self._num_slots, self._num_statics = len(slots), len(statics)
        self._normalizers = tuple(
            _static_normalizer(p.static_type) if p.static_slot is not None else None for p in params
        )
        self._sequence_normalizers = tuple(
            _static_normalizer(statics[p.sequence_slot][1]) if p.sequence_slot is not None else None for p in params
        )
        self.lifted = LiftedFunction(
            self.name,
            self._call_geomjax,
            slots,
            statics,
            self.num_outputs,
            nondifferentiable=[p.tensor_slot for p in params if p.name in nondifferentiable],
            # first and second derivatives, under torch.compile too
            eager_vjp_levels=0 if dynamic_outputs is not None else 2,
            dynamic_outputs=None
            if dynamic_outputs is None
            else lambda slots, statics: dynamic_outputs(self._geomjax_kwargs(slots, statics)),
        )

    def _geomjax_kwargs(self, slots, statics) -> dict:
        kwargs = {}
        for p in self.parameters:
            value = None
            if p.tensor_slot is not None:
                value = slots[p.tensor_slot]
            if value is None and p.static_slot is not None:
                value = statics[p.static_slot]
            if value is None and p.sequence_slot is not None:
                value = statics[p.sequence_slot]
            kwargs[p.name] = value
        return kwargs

    def _call_geomjax(self, slots, statics):
        result = self.function(**self._geomjax_kwargs(slots, statics))
        return (result,) if self.single_output else tuple(result)

    def bind(self, values):
        """Split Python arguments (in signature order) into tensor slots and static options."""
        slots = [None] * self._num_slots
        statics = [None] * self._num_statics
        for p, normalize, normalize_sequence, value in zip(
            self.parameters, self._normalizers, self._sequence_normalizers, values
        ):
            if p.tensor_slot is not None and isinstance(value, torch.Tensor):
                slots[p.tensor_slot] = value
            elif normalize is not None:
                normalized, slot = normalize(value), p.static_slot
                if normalized is _BAD and normalize_sequence is not None:
                    normalized, slot = normalize_sequence(value), p.sequence_slot
                if normalized is _BAD:
                    self._raise_for_option(p, values)
                statics[slot] = normalized
            elif value is not None or not p.optional:
                raise TypeError(
                    f"{self.name}: {p.name} must be a torch.Tensor{' or None' if p.optional else ''}, "
                    f"got {type(value).__name__}"
                )
        return tuple(slots), tuple(statics)

    def _raise_for_option(self, parameter: Parameter, values):
        """An option the schema cannot hold: raise geomjax's own error for it, if it has one.

        Under ``torch.compile`` geomjax cannot run at trace time; the bridge's ``TypeError`` is
        raised instead (with ``fullgraph=True`` Dynamo reports it as an ``Unsupported`` error that
        quotes this message).
        """
        value = values[self.parameters.index(parameter)]
        base = parameter.static_type.rstrip("?")
        expected = _OPTION_WORDS.get(base, base)
        if parameter.sequence_slot is not None:
            expected += " or " + _OPTION_WORDS[base + "[]"]
        if parameter.tensor_slot is not None:
            expected += " or a torch.Tensor"
        elif parameter.optional:
            expected += " or None"
        error = TypeError(f"{self.name}: {parameter.name} must be {expected}, got {type(value).__name__}")
        if torch.compiler.is_compiling() or self.lifted.dynamic_outputs is not None:
            raise error  # geomjax cannot be traced here (under compile, or an eager-only op)
        tensors = {
            p.name: v for p, v in zip(self.parameters, values) if p.tensor_slot is not None and isinstance(v, torch.Tensor)
        }
        others = {p.name: v for p, v in zip(self.parameters, values) if p.name not in tensors}
        structs = {n: jax.ShapeDtypeStruct(tuple(t.shape), _NUMPY_FROM_TORCH[t.dtype]) for n, t in tensors.items()}
        with _x64_for(tensors.values()):
            jax.eval_shape(lambda arrays: self.function(**arrays, **others), structs)
        raise error

    def __call__(self, *values):
        slots, statics = self.bind(values)
        outputs = self.lifted.apply(slots, statics)
        return outputs[0] if self.single_output else tuple(outputs)


def make_public_function(op: BridgedOp) -> Callable:
    """The user-facing function: the reference's name, parameters, defaults and ``*`` marker."""
    parts, names, namespace = [], [], {"_call": op.__call__}
    star_written = False
    for p in op.parameters:
        if p.keyword_only and not star_written:
            parts.append("*")
            star_written = True
        if p.default is _REQUIRED:
            parts.append(p.name)
        else:
            namespace[f"_default_{p.name}"] = p.default
            parts.append(f"{p.name}=_default_{p.name}")
        names.append(p.name)
    source = f"def {op.name}({', '.join(parts)}):\n    return _call({', '.join(names)})\n"
    exec(compile(source, f"<torch_bridge.{op.name}>", "exec"), namespace)
    function = namespace[op.name]
    function.__module__ = "torch_bridge"
    function.__qualname__ = op.name
    function.__doc__ = _docstring(op)
    function.bridged_op = op
    return function


def _docstring(op: BridgedOp) -> str:
    # geomjax's doc without its JAX example (the torch_bridge package docstring has a torch one).
    geomjax_doc = inspect.cleandoc(op.function.__doc__ or "").split("\nExample")[0].rstrip()
    summary = geomjax_doc.splitlines()[0] if geomjax_doc else op.name
    return (
        f"{summary}\n\n"
        f"PyTorch front of :func:`geomjax.{op.name}`: same parameters, defaults, values, errors and "
        "gradients, with ``torch.Tensor`` inputs and outputs (zero-copy through DLPack). It is the "
        f"custom op ``torch.ops.{NAMESPACE}.{op.name}`` with autograd (any order the JAX path supports), "
        "a fake kernel for ``torch.compile(fullgraph=True)``, and ``torch.library.opcheck`` coverage. "
        '``implementation="torch"`` selects the portable JAX path.\n\n'
        f"geomjax documentation:\n\n{geomjax_doc}"
    )
