"""The one way to expose Warp kernels to JAX: kernel families, CPU launches, adjoint pairing.

* :class:`Overloads`: the float32 and float64 overloads of one generic kernel (element types
  ``typing.Any``), registered when the family is declared. Each overload registered after a
  Warp module is built changes the module's hash and recompiles it (seconds), so every overload
  a family will use is registered up front.
* :class:`KernelFamily`: one kernel as JAX functions, declared once with its named outputs and
  made per dtype on first use. A *single* family is ``warp.jax_kernel`` (one launch over the
  launch dims); a *chunked* family is ``warp.jax_callable`` whose CPU launch is split over the
  cores (:func:`launch_in_chunks`). :class:`CallableFamily` is the same for a Python body that
  launches several kernels or builds a structure in the call.
* :func:`with_adjoint`: a forward call and its adjoint kernels as one ``jax.custom_vjp``.

Every family uses ``vmap_method="sequential"`` unless told otherwise: our kernels gather across
points and controls, where Warp's default broadcast rule would be silently wrong. Outputs that
a kernel adds into (adjoint scatters) are passed as in/out buffers that the call fills with
``jnp.zeros``: FFI output buffers are not zeroed.
"""

from __future__ import annotations

import atexit
import ctypes
import functools
import os
import re
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import warp


def _cuda_driver_loads() -> bool:
    """Whether the NVIDIA driver library that ``warp.init`` looks for can be loaded."""
    names = ("nvcuda.dll",) if sys.platform == "win32" else ("libcuda.so", "libcuda.so.1")
    for name in names:
        try:
            ctypes.CDLL(name)
            return True
        except OSError:
            continue
    return False


_NO_DRIVER_WARNING = re.compile(r"Warp CUDA warning: Could not find or load the NVIDIA CUDA driver\.[^\n]*\n?")


def _init_warp() -> None:
    """``warp.init()``, without the warning Warp's C library writes to stderr on every import on
    a machine that has no CUDA driver (where that is expected, not news). Anything else it
    writes is passed on."""
    if _cuda_driver_loads():
        warp.init()
        return
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as captured:
        os.dup2(captured.fileno(), 2)
        try:
            warp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        rest = _NO_DRIVER_WARNING.sub("", captured.read().decode(errors="replace"))
    if rest:
        sys.stderr.write(rest)


# Warp 1.19 has no ``config.quiet``: the log level keeps the init banner and module-load
# messages off stdout (they would break doctests and pollute benchmark output).
warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)
_init_warp()

WARP_SCALAR = {jnp.dtype(jnp.float32): warp.float32, jnp.dtype(jnp.float64): warp.float64}


def vectors(scalar, length: int = 3, ndim: int = 1):
    """The Warp type of an array of ``length``-vectors of ``scalar``."""
    return warp.array(dtype=warp.types.vector(length, scalar), ndim=ndim)


def scalars(scalar, ndim: int = 1):
    """The Warp type of an array of ``scalar``."""
    return warp.array(dtype=scalar, ndim=ndim)


# ---------------------------------------------------------------------------------------------
# Threaded CPU launches. Warp runs a CPU launch on one thread; kernels that take an ``offset``
# argument can be launched over disjoint chunks of their item axis from a thread pool instead.

MIN_CHUNK = 4096  # items per CPU launch chunk: smaller chunks cost more in launch overhead


def cpu_threads() -> int:
    """Worker threads for CPU launches (``GEOMJAX_WARP_CPU_THREADS`` overrides the CPU count)."""
    env = os.environ.get("GEOMJAX_WARP_CPU_THREADS")
    if env:
        return max(1, int(env))
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def _finish_pending_calls() -> None:
    """Wait, at interpreter exit, for computations still running (``atexit``).

    JAX dispatches asynchronously: a script may end while a program with Warp calls still runs on
    XLA's threads (under ``shard_map`` they always run there). Each Warp call needs the GIL, which
    the interpreter stops handing out once it finalises, while finalising waits for those threads
    to end: the process hung at exit. Waiting here, before finalisation, lets them finish. A
    failure of such a computation has nobody left to report to, so it is not raised.
    """
    try:
        jax.block_until_ready(jax.live_arrays())
    except Exception:  # noqa: BLE001 - see the docstring
        pass


@functools.cache
def _finish_pending_calls_at_exit() -> None:
    """Registers :func:`_finish_pending_calls` once, when the first Warp call is made: a process
    that never calls one does not start JAX's backend at exit."""
    atexit.register(_finish_pending_calls)


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="geomjax-warp")


def launch_in_chunks(
    kernel, num_batch: int, num_items: int, inputs: list, outputs: list, accumulated=(), *, min_chunk: int = MIN_CHUNK, spare_threads: int = 0
):  # fmt: skip
    """Launch ``kernel`` over ``(num_batch, num_items)``, in parallel chunks of items on CPU.

    The kernel's last input is an ``offset`` added to its item index; ``inputs`` end just before
    it. ``accumulated`` lists the positions in ``outputs`` that the kernel adds into (they hold
    zeros, or whatever is to be added to): on CPU each further worker adds into a private zeroed
    copy, summed in at the end, because Warp's CPU atomics are not thread-safe. On CUDA it is one
    launch over all items. ``spare_threads``: CPU threads to leave free (a caller that keeps
    them busy meanwhile); at least one thread launches. Arguments are ``warp.array`` s, scalars,
    or on the CPU NumPy arrays as ``(array, warp_dtype)`` (see :func:`launch_on_host`).
    """
    on_cpu = isinstance(outputs[0], tuple) or outputs[0].device.is_cpu
    workers = max(1, cpu_threads() - spare_threads) if on_cpu else 1
    num_chunks = min(4 * workers, max(1, num_items // min_chunk))
    if on_cpu and (workers == 1 or num_chunks == 1):
        launch_on_host(kernel, (num_batch, num_items), [*inputs, 0, *outputs])
        return
    if not on_cpu:
        device = outputs[0].device
        warp.launch(kernel, dim=(num_batch, num_items), inputs=[*inputs, 0], outputs=outputs, device=device)
        return
    workers = min(workers, num_chunks)
    bounds = [round(c * num_items / num_chunks) for c in range(num_chunks + 1)]
    private = [outputs]
    for _ in range(1, workers):
        copy = list(outputs)
        for k in accumulated:
            copy[k] = (np.zeros_like(outputs[k][0]), outputs[k][1]) if isinstance(outputs[k], tuple) else warp.zeros_like(outputs[k])
        private.append(copy)

    def work(w):
        # Contiguous chunks (rather than interleaved items) keep each worker's data in its cache;
        # each worker thread replays its own recorded launch.
        for c in range(w, num_chunks, workers):
            start, stop = bounds[c], bounds[c + 1]
            launch_on_host(kernel, (num_batch, stop - start), [*inputs, start, *private[w]])

    futures = []
    for w in range(workers):
        try:
            futures.append(_pool(workers).submit(work, w))
        except RuntimeError:
            # The interpreter is exiting (the pool takes no more work) while JAX still runs a
            # pending computation, e.g. a script that ends without blocking on a result.
            work(w)
    for future in futures:
        future.result()
    for k in accumulated:
        total = host_values(outputs[k])
        for copy in private[1:]:
            np.add(total, host_values(copy[k]), out=total)


def host_values(argument) -> np.ndarray:
    """The host values of a kernel argument: a ``(array, warp_dtype)`` pair's array, or a
    ``warp.array``'s (a view on the CPU, a copy from another device)."""
    return argument[0] if isinstance(argument, tuple) else argument.numpy()


# ---------------------------------------------------------------------------------------------
# Replayed CPU launches. ``warp.launch`` checks and packs every argument on each call (about
# 10 us, and 4 us more per NumPy array wrapped as a ``warp.array``): several times the run of a
# kernel on a few hundred rows, which the remesher launches two dozen times a call. A launch
# recorded once per kernel and argument layout (``record_cmd=True``: Warp checks the types
# then) and replayed with the new arrays' addresses and sizes written into its parameters costs
# about 3 us.


# Per thread (XLA's threads run FFI calls side by side): a recorded launch's parameters are
# rewritten on each call.
_REPLAYS = threading.local()
_RECORDING = threading.Lock()


def _layout(value) -> tuple:
    """What a recorded launch fixes of an argument: its kind, dtypes and dimensions (not its
    sizes: one recording serves every size)."""
    if isinstance(value, tuple):
        array, dtype = value
        return (dtype, array.dtype, array.ndim)
    if isinstance(value, warp.array):
        return (warp.array, value.dtype, value.ndim)
    return (type(value),)


def _host_array(value):
    """A ``(array, warp_dtype)`` argument as a ``warp.array`` of the NumPy array's memory."""
    return warp.array(value[0], dtype=value[1], device="cpu", copy=False) if isinstance(value, tuple) else value


def launch_on_host(kernel, dim, args: Sequence) -> None:
    """Launch ``kernel`` on the CPU over ``dim`` with ``args``, replaying a recorded launch.

    ``args`` are the kernel's parameters in order: a NumPy array as ``(array, warp_dtype)``
    (C-contiguous, of the NumPy type of ``warp_dtype``, one row per element: ``(N, 3)`` for
    ``warp.vec3d``), passed as its memory itself (what the kernel writes lands in it); or what
    ``warp.launch`` takes (a CPU ``warp.array``, a scalar, a Warp struct). The first call on a
    thread with a layout of arguments (their kinds, dtypes and trailing shapes) records the
    launch through ``warp.launch``, which checks them against the kernel's parameters; later
    calls with that layout write the new addresses, sizes and scalars into the recorded
    parameters and launch.
    """
    key = (kernel, *map(_layout, args))
    replays = _REPLAYS.__dict__.setdefault("table", {})
    replay = replays.get(key)
    if replay is None:
        wrapped = [_host_array(a) for a in args]
        for index, (value, array) in enumerate(zip(args, wrapped)):
            # Warp copies an array it cannot view as the dtype; the replays need a view.
            if isinstance(value, tuple) and array.ptr != value[0].ctypes.data:
                raise TypeError(f"{kernel.key}: argument {index} ({value[0].dtype}, {value[0].shape}) is no array of {value[1].__name__}")
        # One recording at a time: two threads recording a launch of a kernel whose module is
        # not loaded yet crashed one of them in the kernel (in about one run in five).
        with _RECORDING:
            launch = warp.launch(kernel, dim=dim, inputs=wrapped, device="cpu", record_cmd=True)
        # The recorded arguments would keep the first call's arrays alive.
        launch.fwd_args = None
        # Per argument: a NumPy array's Warp dimensions and the shape of an element (its trailing
        # dimensions: (3,) for a vec3d), None for anything else.
        layouts = tuple((w.ndim, a[0].shape[w.ndim :]) if isinstance(a, tuple) else None for a, w in zip(args, wrapped))
        replay = replays[key] = (launch, layouts)
    launch, layouts = replay
    params = launch.params
    for index, (value, layout) in enumerate(zip(args, layouts)):
        if layout is not None:
            array, (ndim, element) = value[0], layout
            if array.shape[ndim:] != element or not array.flags.c_contiguous:
                raise ValueError(f"{kernel.key}: argument {index} must be C-contiguous with elements of shape {element}, got {array.shape}")
            # The recorded launch's own descriptor of the array (params[0] holds the bounds).
            descriptor = params[index + 1]
            descriptor.data = array.ctypes.data
            for axis in range(ndim):
                descriptor.shape[axis] = array.shape[axis]
                descriptor.strides[axis] = array.strides[axis]
        elif isinstance(value, int | float):
            launch.set_param_at_index_from_ctype(index, value)
        else:  # a warp.array, a Warp struct: packed by Warp
            launch.set_param_at_index(index, value)
    launch.set_dim(dim)
    launch.launch()


# ---------------------------------------------------------------------------------------------
# Families.


class _PerVariant:
    """Made once per variant, a dtype (float32 or float64) and static parameters: ``self(dtype, *params)``."""

    def __init__(self):
        self._made = {}

    def __call__(self, dtype, *params):
        key = (jnp.dtype(dtype), *params)
        if key not in self._made:
            _finish_pending_calls_at_exit()
            self._made[key] = self._make(*key)
        return self._made[key]

    def _make(self, dtype, *params):  # pragma: no cover - every subclass defines it
        raise NotImplementedError


class Overloads(_PerVariant):
    """The per-dtype overloads of one Warp kernel.

    Args:
        kernel: a ``@warp.kernel``; a generic one (float element types ``Any``) is overloaded,
            a concrete one is used for every dtype.
        types: ``types(scalar, *params)`` maps the Warp scalar (``warp.float32`` or
            ``warp.float64``) and the family's static parameters to the concrete types of the
            kernel's generic arguments, by name; the kernel's own annotations give the rest.
            Names the kernel does not have are ignored, so one vocabulary can serve a module.
        variants: the parameter tuples whose overloads are registered now, for both dtypes.
    """

    def __init__(self, kernel, types: Callable[..., dict] | None = None, *, variants: Sequence[tuple] = ((),)):
        super().__init__()
        self.kernel = kernel
        self._types = types
        for params in variants:
            for dtype in WARP_SCALAR:
                self(dtype, *params)

    def _make(self, dtype, *params):
        if not self.kernel.is_generic:
            return self.kernel
        types = self._types(WARP_SCALAR[dtype], *params)
        return warp.overload(self.kernel, {name: t for name, t in types.items() if name in self.kernel.arg_indices})


def _ffi_function(name: str, arg_types: dict, body: Callable, module: str) -> Callable:
    """A Python function ``name(<arg_types' names>)`` annotated with ``arg_types`` that calls ``body``.

    ``warp.jax_callable`` reads the FFI arguments (names, Warp types, which ones are static
    scalars) from its function's signature and annotations. Ours depend on the dtype, so no
    ``def`` in the source can carry them; generating the ``def`` here gives an ordinary function
    that ``inspect`` reads like a hand-written one (rather than a ``*args`` function with its
    ``__signature__`` and ``__annotations__`` patched, as Warp's own ``jax_kernel`` does).
    ``module`` becomes its ``__module__``: Warp loads that module's kernels before the call
    (graph capture cannot load a module mid-call).
    """
    name = re.sub(r"\W", "_", name)
    parameters = ", ".join(f"{arg}: _types[{arg!r}]" for arg in arg_types)
    source = f"def {name}({parameters}) -> None:\n    _body({', '.join(arg_types)})\n"
    namespace: dict[str, Any] = {"__name__": module, "_types": dict(arg_types), "_body": body}
    exec(compile(source, f"<warp_ffi FFI function {name}>", "exec", dont_inherit=True), namespace)  # noqa: S102
    return namespace[name]


def _jax_dtype(arg_type):
    element = arg_type.dtype
    return warp.dtype_to_jax(getattr(element, "_wp_scalar_type_", element))


def _full_shape(arg_type, shape) -> tuple:
    """The JAX shape of a Warp array argument of ``arg_type`` with Warp shape ``shape``."""
    return (*shape, *getattr(arg_type.dtype, "_shape_", ()))


class _Call:
    """One wrapped variant of a family: ``call(*inputs, launch=..., shapes=...)``."""

    def __init__(self, wrapped, arg_types: dict, outputs: tuple, accumulate: tuple, launch_style: str):
        self._wrapped = wrapped
        self._arg_types = arg_types
        self._outputs = outputs
        self._accumulate = accumulate
        self._style = launch_style

    def __call__(self, *inputs, launch=None, shapes: dict):
        """The outputs (a tuple, in declared order) for ``inputs``.

        Args:
            inputs: the family's input arguments in order (arrays and static scalars).
            launch: the launch dims: any shape for a single family, ``(num_batch, num_items)``
                for a chunked one, unused by a callable family.
            shapes: the Warp shape of every output by name (for vector arrays, without the
                vector length).
        """
        zeros = [jnp.zeros(_full_shape(self._arg_types[n], shapes[n]), _jax_dtype(self._arg_types[n])) for n in self._accumulate]
        output_dims = {name: shapes[name] for name in self._outputs if name not in self._accumulate}
        if self._style == "single":
            results = self._wrapped(*inputs, *zeros, launch_dims=launch, output_dims=output_dims)
        elif self._style == "chunked":
            results = self._wrapped(*launch, *inputs, *zeros, output_dims=output_dims)
        else:
            results = self._wrapped(*inputs, *zeros, output_dims=output_dims)
        # The FFI returns the in/out buffers first.
        by_name = dict(zip([*self._accumulate, *output_dims], results, strict=True))
        return tuple(by_name[name] for name in self._outputs)


def _ordered_for_ffi(arg_types: dict, outputs: tuple, accumulate: tuple) -> dict:
    """``arg_types`` with the accumulated outputs first among the outputs (FFI in/out arguments
    must precede pure outputs)."""
    inputs = {name: t for name, t in arg_types.items() if name not in outputs}
    ordered = [*accumulate, *(name for name in outputs if name not in accumulate)]
    return {**inputs, **{name: arg_types[name] for name in ordered}}


class KernelFamily(_PerVariant):
    """One Warp kernel as JAX functions for float32 and float64, made per dtype on first use.

    Args:
        kernel, types, variants: as for :class:`Overloads`.
        outputs: the names of the kernel's trailing output arguments.
        accumulate: outputs the kernel adds into (atomics): in/out buffers zero-filled by the call.
        chunked: launch through ``warp.jax_callable`` with the CPU launch split over the cores
            (:func:`launch_in_chunks`). The kernel's ``offset`` argument, just before its
            outputs, is supplied by the launcher; a call passes ``launch=(num_batch,
            num_items)``. Otherwise ``warp.jax_kernel`` launches once over ``launch``.
        balanced: for a chunked family whose items all cost about the same: one chunk per
            thread (more chunks buy no balance and each launch costs tens of microseconds).
        min_chunk: the fewest items per chunk of a chunked family that is not balanced.
        vmap_method: as for ``warp.jax_kernel``.

    Calling the family with a dtype (and static parameters) gives the JAX function:
    ``family(dtype, *params)(*inputs, launch=..., shapes=...)`` returns the outputs as a tuple.
    """

    def __init__(
        self,
        kernel,
        types: Callable[..., dict] | None = None,
        *,
        outputs: Sequence[str],
        accumulate: Sequence[str] = (),
        chunked: bool = False,
        balanced: bool = False,
        min_chunk: int = MIN_CHUNK,
        variants: Sequence[tuple] = ((),),
        vmap_method: str = "sequential",
    ):
        super().__init__()
        self.overloads = Overloads(kernel, types, variants=variants)
        self.outputs = tuple(outputs)
        self._accumulate = tuple(name for name in self.outputs if name in accumulate)
        self._chunked = chunked
        self._balanced = balanced
        self._min_chunk = min_chunk
        self._vmap_method = vmap_method

    def _make(self, dtype, *params) -> _Call:
        kernel = self.overloads(dtype, *params)
        arg_types = dict(kernel.adj.arg_types)
        num_outputs = len(self.outputs)
        if not self._chunked:
            wrapped = warp.jax_kernel(kernel, num_outputs=num_outputs, in_out_argnames=list(self._accumulate) or None, vmap_method=self._vmap_method)
            return _Call(wrapped, arg_types, self.outputs, self._accumulate, "single")
        del arg_types["offset"]
        ffi_types = _ordered_for_ffi(arg_types, self.outputs, self._accumulate)
        names = list(ffi_types)
        num_inputs = len(names) - num_outputs
        # The kernel's outputs in its own order, taken from the FFI arguments, and which it adds into.
        output_positions = [names.index(name) for name in self.outputs]
        accumulated = [self.outputs.index(name) for name in self._accumulate]

        def body(launch_batch, launch_items, *args):
            min_chunk = max(MIN_CHUNK, launch_items // cpu_threads()) if self._balanced else self._min_chunk
            outputs = [args[k] for k in output_positions]
            launch_in_chunks(kernel, launch_batch, launch_items, list(args[:num_inputs]), outputs, accumulated, min_chunk=min_chunk)

        function = _ffi_function(kernel.key, {"launch_batch": int, "launch_items": int, **ffi_types}, body, kernel.func.__module__)
        wrapped = warp.jax_callable(function, num_outputs=num_outputs, in_out_argnames=list(self._accumulate) or None, vmap_method=self._vmap_method)
        return _Call(wrapped, ffi_types, self.outputs, self._accumulate, "chunked")


class CallableFamily(_PerVariant):
    """A Python body that launches Warp kernels, as JAX functions made per dtype on first use.

    Args:
        make_body: ``make_body(dtype, *params)`` returns the body, a function of the Warp arrays
            (and static scalars) named by ``types``.
        types: ``types(scalar, *params)``: every argument's name and Warp type, in order,
            outputs last.
        outputs: the names of the trailing output arguments, or ``outputs(*params)``.
        module: the ``__module__`` whose Warp kernels are loaded before the call.
        runs_on_host: the body must run its Python code on every call, so the call is never
            captured in a CUDA graph (whose replays skip it): it allocates (builds a structure
            in the call), or it checks data on the host first (a mesh handle's liveness, which a
            replay with a freed or forged handle would otherwise skip); or
            ``runs_on_host(*params)``.
        vmap_method: as for ``warp.jax_callable``.

    ``family(dtype, *params)(*inputs, shapes=...)`` returns the outputs as a tuple.
    """

    def __init__(
        self,
        make_body: Callable,
        types: Callable[..., dict],
        *,
        outputs: Sequence[str] | Callable[..., Sequence[str]],
        module: str,
        runs_on_host: bool | Callable[..., bool] = False,
        vmap_method: str = "sequential",
    ):
        super().__init__()
        self._make_body = make_body
        self._types = types
        self._outputs = outputs if callable(outputs) else lambda *params: outputs
        self._runs_on_host = runs_on_host if callable(runs_on_host) else lambda *params: runs_on_host
        self._module = module
        self._vmap_method = vmap_method

    def _make(self, dtype, *params) -> _Call:
        arg_types = self._types(WARP_SCALAR[dtype], *params)
        outputs = tuple(self._outputs(*params))
        function = _ffi_function(self._make_body.__name__, arg_types, self._make_body(dtype, *params), self._module)
        graph_mode = warp.JaxCallableGraphMode.NONE if self._runs_on_host(*params) else warp.JaxCallableGraphMode.JAX
        wrapped = warp.jax_callable(function, num_outputs=len(outputs), graph_mode=graph_mode, vmap_method=self._vmap_method)
        return _Call(wrapped, arg_types, outputs, (), "callable")


# ---------------------------------------------------------------------------------------------
# Adjoints.


def _zero_cotangent(value):
    """Zero cotangents for a (pytree of) non-differentiated array(s): float0 for integers."""

    def zero(leaf):
        if jnp.issubdtype(leaf.dtype, jnp.inexact):
            return jnp.zeros_like(leaf)
        return np.zeros(leaf.shape, jax.dtypes.float0)

    return jax.tree.map(zero, value)


def with_adjoint(
    forward: Callable, adjoint: Callable, *, primal: Callable | None = None, static_argnums: Sequence[int] = (), constant_argnums: Sequence[int] = ()
) -> Callable:
    """``forward`` as a ``jax.custom_vjp`` function whose reverse pass is ``adjoint``.

    Args:
        forward: ``forward(*args) -> (outputs, saved)``: the results, and what the reverse pass
            needs besides the arguments (``()`` for nothing).
        adjoint: ``adjoint(args, saved, cotangents)``: the cotangents of the differentiated
            arguments (neither static nor constant), in argument order.
        primal: ``primal(*args) -> outputs`` when the results alone cost less than ``forward``
            (default: ``forward``'s results).
        static_argnums: Python values (sizes, names), passed as they are.
        constant_argnums: arrays that are not differentiated (topology, configuration): they
            get zero cotangents, float0 for integer arrays.

    The residuals are the arguments and ``saved``.
    """
    static_argnums = tuple(static_argnums)
    constant_argnums = tuple(constant_argnums)

    @functools.partial(jax.custom_vjp, nondiff_argnums=static_argnums)
    def function(*args):
        if primal is not None:
            return primal(*args)
        return forward(*args)[0]

    def function_fwd(*args):
        outputs, saved = forward(*args)
        return outputs, ([a for k, a in enumerate(args) if k not in static_argnums], saved)

    def function_bwd(*static_residuals_cotangents):
        *static, (dynamic, saved), cotangents = static_residuals_cotangents
        count = len(static) + len(dynamic)
        static, dynamic = iter(static), iter(dynamic)
        args = [next(static) if k in static_argnums else next(dynamic) for k in range(count)]
        gradients = iter(adjoint(args, saved, cotangents))
        return tuple(_zero_cotangent(args[k]) if k in constant_argnums else next(gradients) for k in range(count) if k not in static_argnums)

    function.defvjp(function_fwd, function_bwd)
    return function
