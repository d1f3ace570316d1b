"""Warp kernels exposed as JAX functions (``jit``/``vmap``/``grad`` through ``custom_vjp``).

This package knows nothing of geomjax: inputs arrive validated and normalised to ``(B, N, D)``.
Importing it raises ``ImportError`` when warp-lang is missing, which geomjax's dispatcher reports.
Every op module takes and returns JAX arrays, except :mod:`warp_ffi.host` (NumPy, run eagerly).
"""

from ._wrap import warp as warp  # noqa: F401  (import check: fails fast without warp-lang)
