"""Backend selection shared by every op: ``implementation`` is ``"jax"``, ``"warp"`` or ``None``.

Rules (DESIGN.md): an unknown name is a ``KeyError``; an explicit ``"warp"`` without Warp installed
is an ``ImportError``; ``None`` picks the op's documented default for the platform of its inputs,
falling back to JAX when Warp is missing. ``"torch"`` is the reference's name for the portable
path and means ``"jax"`` here, so code written for the reference runs unchanged.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping

import jax

PORTABLE_ALIASES = {"torch": "jax"}


@functools.cache
def warp_available() -> bool:
    """Whether ``warp_ffi`` can be imported (Warp installed and initialised)."""
    try:
        import warp_ffi  # noqa: F401
    except ImportError:
        return False
    return True


def platform_of(*arrays) -> str:
    """The JAX platform (``"cpu"``, ``"gpu"``) the inputs live on, or the default backend."""
    for x in arrays:
        if isinstance(x, jax.Array) and not isinstance(x, jax.core.Tracer):
            try:
                return next(iter(x.devices())).platform
            except Exception:  # pragma: no cover
                break
    return jax.default_backend()


def select_implementation(
    op_name: str,
    implementation: str | None,
    *,
    backends: tuple[str, ...],
    default: Mapping[str, str],
    platform: str,
) -> str:
    """Resolve ``implementation`` for ``op_name``.

    Args:
        backends: the backends the op registers, e.g. ``("jax", "warp")``.
        default: the faster backend per platform (``{"cpu": "warp", "gpu": "warp"}``), as measured
            by the op's benchmark; platforms not listed use ``"jax"``.
        platform: where the inputs live (see :func:`platform_of`).
    """
    if implementation is None:
        choice = default.get(platform, "jax")
        if choice == "warp" and not warp_available():
            return "jax"
        return choice
    if not isinstance(implementation, str):
        raise KeyError(f"{op_name}: implementation must be one of {backends + tuple(PORTABLE_ALIASES)} or None, got {implementation!r}")
    name = PORTABLE_ALIASES.get(implementation, implementation)
    if name not in backends:
        raise KeyError(
            f"{op_name}: unknown implementation {implementation!r}; registered backends are "
            f"{backends + tuple(k for k, v in PORTABLE_ALIASES.items() if v in backends)}"
        )
    if name == "warp" and not warp_available():
        raise ImportError(f"{op_name}: implementation='warp' was requested but warp-lang is not installed")
    return name
