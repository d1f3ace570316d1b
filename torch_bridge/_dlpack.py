"""Tensors to JAX arrays and back: zero-copy DLPack, NumPy views, dtypes and the local x64 context.

float64 (and int64) tensors run under a local ``jax.enable_x64(True)`` context (:func:`x64_for`): the
user never configures JAX and the global flag is never flipped.
"""

from __future__ import annotations

import contextlib
import weakref
from collections.abc import Callable

import jax
import numpy as np
import torch
import torch.utils.dlpack

_TORCH_FROM_NUMPY: dict[np.dtype, torch.dtype] = {
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


def numpy_dtype(dtype: torch.dtype) -> np.dtype:
    return _NUMPY_FROM_TORCH[dtype]


def x64_for(tensors) -> contextlib.AbstractContextManager:
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


_import_cpu, _export_cpu = _fast_cpu_converters() or (jax.dlpack.from_dlpack, lambda a: torch.utils.dlpack.from_dlpack(a.__dlpack__()))


# A small tensor goes to a jitted function as a NumPy view: jit's C++ dispatch takes a NumPy
# argument ~20 µs faster than a DLPack buffer (whose sharding is built in Python), and copying a
# few kilobytes costs nothing next to that (measured). It must be a NumPy view on every call, not
# only the first: jit keys its cache on whether an argument is committed to a device, so a NumPy
# first call followed by a kept (committed) view compiled every program twice.
SMALL_CPU_BYTES = 16 * 2**10


# What a kept view was made from: the tensor's memory, shape, strides and dtype.
_Layout = tuple[int, torch.Size, tuple[int, ...], torch.dtype]


class _CpuViews:
    """Zero-copy JAX views of CPU tensors, kept while the tensor lives.

    Inputs that are passed again — fixed points and controls, parameters updated in place — skip
    the ~15 µs of a DLPack import and release. A view shares the tensor's memory, so in-place
    updates are seen; it is reused only while the tensor keeps the same memory, shape, strides and
    dtype. Copies (unaligned memory) are never kept, and CUDA tensors are never kept: each CUDA
    import must order JAX after PyTorch's current stream.
    """

    def __init__(self) -> None:
        self._views: dict[int, tuple[weakref.ref[torch.Tensor], _Layout, jax.Array]] = {}

    def __call__(self, t: torch.Tensor) -> jax.Array:
        key = id(t)
        entry = self._views.get(key)
        signature = (t.data_ptr(), t.shape, t.stride(), t.dtype)
        if entry is not None:
            ref, kept_signature, array = entry
            if ref() is t and kept_signature == signature:
                return array
        # Import a detached alias: a capsule holding ``t`` itself would keep ``t`` alive through
        # the kept view, so the weak reference below would never fire.
        array = _import_cpu(t.detach())
        if array.unsafe_buffer_pointer() == t.data_ptr():
            views = self._views
            ref = weakref.ref(t, lambda _: views.pop(key, None))
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
    array only goes into a jitted function) gives a small CPU tensor as a NumPy view, on every
    call (see ``SMALL_CPU_BYTES``)."""
    if jit_argument and t.is_cpu and t.numel() * t.element_size() <= SMALL_CPU_BYTES:
        small = _numpy_view(t.contiguous())  # contiguous or not, like every other call
        if small is not None:
            return small
    if not t.is_contiguous():
        t = t.contiguous()
    elif keep and t.is_cpu:
        return _cpu_views(t)
    if t.requires_grad:
        t = t.detach()
    return _import_cpu(t) if t.is_cpu else jax.dlpack.from_dlpack(t)


def to_torch(a: jax.Array, device: torch.device) -> torch.Tensor:
    """Zero-copy view of a JAX array on ``device`` as a tensor. On CUDA the consumer-stream
    protocol makes PyTorch's current stream wait for JAX's result."""
    if a.size == 0:  # DLPack strides of empty buffers differ between producers; normalise them
        return torch.empty(a.shape, dtype=torch_dtype(a.dtype), device=device)
    return _export_cpu(a) if device.type == "cpu" else torch.from_dlpack(a)
