"""One helper for turning a generic Warp kernel into per-dtype JAX callables.

Kernels are written once with ``typing.Any`` element types; ``KernelFamily`` makes the float32
and float64 overloads on first use and wraps each with ``wp.jax_kernel``. Wrappers use
``vmap_method="sequential"`` by default because our kernels gather across the point and control
axes, where Warp's default broadcast rule would be silently wrong.
"""

from __future__ import annotations

from collections.abc import Callable

import jax.numpy as jnp
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
