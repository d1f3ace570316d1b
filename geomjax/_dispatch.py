"""Backend selection shared by every op, read from the registry (``_registry.py``).

Rules (DESIGN.md): ``implementation`` is ``"jax"``, ``"warp"`` or ``None``; an unknown name is a
``KeyError``; an explicit ``"warp"`` without Warp installed is an ``ImportError``; ``None`` picks
the op's declared default for the platform of its inputs, falling back to JAX when Warp is
missing or cannot handle the input. ``"torch"`` is the reference's name for the portable path
and means ``"jax"`` here, so code written for the reference runs unchanged.

The chosen backend comes back as an :class:`Implementation`, whose ``run`` keeps the default's
promise: a default-dispatched Warp path is differentiated like the JAX path beyond first-order
reverse mode, and an explicit one says which transform it lacks.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import jax

from ._fast_path import fast_with_reference
from ._registry import declaration

__all__ = ["Implementation", "platform_of", "select_implementation", "warp_available"]

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


@dataclasses.dataclass(frozen=True)
class Implementation:
    """The backend that runs one call of op ``op``.

    Attributes:
        op: the op's name (its registry key).
        name: ``"jax"`` or ``"warp"``.
        explicit: the caller named the backend (rather than ``implementation=None``).
    """

    op: str
    name: str
    explicit: bool

    @property
    def is_warp(self) -> bool:
        return self.name == "warp"

    def run(self, warp_fn: Callable, jax_fn: Callable, *args):
        """``warp_fn(*args)`` or ``jax_fn(*args)`` (the same function of the same arrays).

        A Warp path that lacks forward mode or second order (its registry capabilities) gets them
        from ``jax_fn`` when it was chosen by default; chosen explicitly, those transforms raise
        ``NotImplementedError`` naming the transform and ``implementation='jax'``.
        """
        if self.name == "jax":
            return jax_fn(*args)
        capabilities = declaration(self.op).capabilities(self.name)
        if capabilities.forward and capabilities.higher_order:
            return warp_fn(*args)
        return fast_with_reference(warp_fn, jax_fn, args, op_name=self.op, backend=self.name, explicit=self.explicit)


def select_implementation(
    op_name: str, implementation: str | Implementation | None, *, platform: str, variant: str | None = None, warp_unsupported: str | None = None
) -> Implementation:
    """Resolve ``implementation`` for op ``op_name`` from its registry declaration.

    Args:
        implementation: the caller's argument.
        platform: where the inputs live (see :func:`platform_of`).
        variant: an option that selects among the op's per-platform defaults (FFD's basis).
        warp_unsupported: why the Warp kernels cannot handle this input (``None`` when they
            can): ``None`` then runs JAX, an explicit ``"warp"`` raises ``ValueError`` with it.
    """
    if isinstance(implementation, Implementation):
        return implementation  # already resolved by a caller (a fit evaluated by its op)
    op = declaration(op_name)
    if implementation is None:
        choice = op.default_backend(platform, variant)
        if choice == "warp" and (warp_unsupported is not None or not warp_available()):
            choice = "jax"
        return Implementation(op_name, choice, explicit=False)
    names = tuple(op.backends) + tuple(k for k, v in PORTABLE_ALIASES.items() if v in op.backends)
    if not isinstance(implementation, str):
        raise KeyError(f"{op_name}: implementation must be one of {names} or None, got {implementation!r}")
    name = PORTABLE_ALIASES.get(implementation, implementation)
    if name not in op.backends:
        raise KeyError(f"{op_name}: unknown implementation {implementation!r}; registered backends are {names}")
    if name == "warp" and not warp_available():
        raise ImportError(f"{op_name}: implementation='warp' was requested but warp-lang is not installed")
    if name == "warp" and warp_unsupported is not None:
        raise ValueError(f"{op_name}: implementation='warp' {warp_unsupported}; use implementation='jax'")
    return Implementation(op_name, name, explicit=True)
