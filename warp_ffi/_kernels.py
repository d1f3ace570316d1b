"""Shared Warp plumbing: per-dtype JAX wrappers of generic kernels, and threaded CPU launches.

Kernels are written once with ``typing.Any`` element types; ``KernelFamily`` makes the float32
and float64 overloads on first use and wraps each with ``wp.jax_kernel``. Wrappers use
``vmap_method="sequential"`` by default because our kernels gather across the point and control
axes, where Warp's default broadcast rule would be silently wrong.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import jax.numpy as jnp
import numpy as np
import warp

# Warp 1.19 ignores ``config.quiet``: the log level keeps the init banner and module-load
# messages off stdout (they would break doctests and pollute benchmark output).
warp.config.quiet = True
warp.config.log_level = max(warp.config.log_level, warp.LOG_WARNING)
warp.init()

WARP_SCALAR = {jnp.dtype(jnp.float32): warp.float32, jnp.dtype(jnp.float64): warp.float64}


class KernelFamily:
    """Per-dtype JAX wrappers of one generic Warp kernel.

    Args:
        kernel: a ``@warp.kernel`` whose float arguments are typed ``Any``.
        signature: maps a Warp scalar type (``warp.float32``/``warp.float64``) to the concrete
            argument types of the kernel, as ``warp.overload`` expects.
        **jax_kernel_kwargs: forwarded to ``warp.jax_kernel`` (``num_outputs``,
            ``in_out_argnames``, ...).
    """

    def __init__(self, kernel, signature: Callable[[type], dict], **jax_kernel_kwargs):
        self._kernel = kernel
        self._signature = signature
        self._kwargs = {"vmap_method": "sequential", **jax_kernel_kwargs}
        self._wrapped = {}

    def __call__(self, dtype):
        """The JAX callable for arrays of ``dtype`` (float32 or float64)."""
        dtype = jnp.dtype(dtype)
        if dtype not in self._wrapped:
            overload = warp.overload(self._kernel, self._signature(WARP_SCALAR[dtype]))
            self._wrapped[dtype] = warp.jax_kernel(overload, **self._kwargs)
        return self._wrapped[dtype]


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


@functools.cache
def _pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="geomjax-warp")


def launch_in_chunks(kernel, num_batch: int, num_items: int, inputs: list, outputs: list, accumulated=(), *, min_chunk: int = MIN_CHUNK):
    """Launch ``kernel`` over ``(num_batch, num_items)``, in parallel chunks of items on CPU.

    Meant for the body of a ``warp.jax_callable``. The kernel's last input is an ``offset`` added
    to its item index; ``inputs`` end just before it. ``accumulated`` lists the positions in
    ``outputs`` that the kernel adds into: they are zeroed first and, on CPU, each worker gets a
    private copy that is summed at the end (Warp's CPU atomics are not thread-safe). On CUDA it is
    one launch over all items.
    """
    for k in accumulated:
        outputs[k].zero_()
    device = outputs[0].device
    workers = cpu_threads() if device.is_cpu else 1
    num_chunks = min(4 * workers, max(1, num_items // min_chunk))
    if workers == 1 or num_chunks == 1:
        warp.launch(kernel, dim=(num_batch, num_items), inputs=[*inputs, 0], outputs=outputs, device=device)
        return
    workers = min(workers, num_chunks)
    bounds = [round(c * num_items / num_chunks) for c in range(num_chunks + 1)]
    private = [outputs]
    for _ in range(1, workers):
        copy = list(outputs)
        for k in accumulated:
            copy[k] = warp.zeros_like(outputs[k])
        private.append(copy)

    def work(w):
        # Contiguous chunks (rather than interleaved items) keep each worker's data in its cache.
        for c in range(w, num_chunks, workers):
            start, stop = bounds[c], bounds[c + 1]
            warp.launch(kernel, dim=(num_batch, stop - start), inputs=[*inputs, start], outputs=private[w], device=device)

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
        total = outputs[k].numpy()
        for copy in private[1:]:
            np.add(total, copy[k].numpy(), out=total)
