"""Data-dependent checks that reach callers as the documented exception type.

A check on values that are only known when a compiled program runs (an index range, finiteness,
a singular fit, a solve that did not converge) must fail that program: its outputs depend on the
check, so it can never be skipped. How a failure reads depends on the mechanism:

* an ``equinox.error_if`` raises from a host callback, which JAX reports as ``JaxRuntimeError:
  INTERNAL: CpuCallback error ...`` with the whole Python stack before the message (and an
  equinox banner after it), and logs the failed callback to stderr;
* the XLA FFI target of :mod:`._check_target` (CPU) fails the program with the message as the
  error text, ``INVALID_ARGUMENT: <message>`` (``FAILED_PRECONDITION`` for ``RuntimeError``
  checks), and prints nothing.

This module is the one place that makes the checks and turns their failures back into the
documented exception:

* :func:`runtime_check` / :func:`runtime_branched_check` replace ``eqx.error_if`` /
  ``eqx.branched_error_if``: concrete predicates raise the documented type at once; traced ones
  become the FFI check on CPU and ``equinox``'s elsewhere (``lax.platform_dependent`` picks at
  lowering), with the message recorded with its exception type.
* :func:`checked_pure_callback` is ``jax.pure_callback`` for host functions that may raise: on
  CPU the host function reports the exception to the FFI check instead of raising it.
* :func:`raises_documented_errors` (a decorator for public ops) and :func:`documented_errors` (a
  context manager and decorator, used by ``torch_bridge`` around its jitted programs and public
  as ``geomjax.documented_errors`` for a user's own) run the call and turn a runtime error that
  carries a recorded message into ``error(message)`` (``from None``: the first line is the op's
  message). Other exceptions pass through unchanged. While such a call runs, JAX's "jax.pure_callback
  failed" log records of these checks are dropped, so nothing reaches stderr.

Under a user's own ``jax.jit`` the op is only traced by the decorated call; the check fails
later, when the user's program runs, and reaches the user as JAX's runtime error: on CPU its text
is the status and the op's message (nothing before it, nothing printed); on GPU it is equinox's.
"""

from __future__ import annotations

import functools
import logging
import threading
from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import _check_target

__all__ = ["checked_pure_callback", "documented_errors", "raises_documented_errors", "runtime_branched_check", "runtime_check", "translate_runtime_error"]

# message -> documented exception type, for every runtime check traced so far.
_REGISTERED: dict[str, type[Exception]] = {}
_LOCK = threading.Lock()
# Markers that identify a failed runtime check in the text JAX reports.
_EQUINOX_MARKER = "_EquinoxRuntimeError: "
_CALLBACK_MARKER = "_HostCheckError: "
# XLA's CPU client reports a check that fails while it dispatches a program (an eager call whose
# program is mostly Warp FFI calls, e.g. the Warp Sobolev solve) as ``INTERNAL: Error dispatching
# computation: <message>``: the status is lost, the message is intact.
_DISPATCH_PREFIX = "Error dispatching computation: "


def _register(message: str, error: type[Exception]) -> None:
    if _REGISTERED.get(message) is not error:
        with _LOCK:
            _REGISTERED[message] = error


def _is_concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def runtime_check(x, failed, message: str, error: type[Exception] = ValueError):
    """``x`` after checking that ``failed`` (a bool or bool array, any element) is false.

    A concrete ``failed`` raises ``error(message)`` at once. A traced one becomes a check on
    ``x`` (use the returned value: the check is attached to it) that fails the compiled program
    with ``message`` (see :func:`_traced_check`), and ``message`` is recorded so
    :func:`documented_errors` raises ``error(message)``.
    """
    if _is_concrete(failed):
        if bool(np.any(np.asarray(failed))):
            raise error(message)
        return x
    return _traced_check(x, failed, jnp.zeros((), jnp.int32), (message,), error)


def runtime_branched_check(x, failed, index, messages: Sequence[str], error: type[Exception] = RuntimeError):
    """As :func:`runtime_check` with one of several ``messages`` chosen by ``index``
    (an int array broadcastable with ``failed``; ``messages[index]`` must be non-empty where
    ``failed``)."""
    if _is_concrete(failed) and _is_concrete(index):
        if bool(np.any(np.asarray(failed))):
            raise error(messages[int(np.max(np.asarray(index)))])
        return x
    return _traced_check(x, failed, index, tuple(messages), error)


def _traced_check(x, failed, index, messages: tuple[str, ...], error: type[Exception]):
    """The compiled check: on CPU the FFI target of :mod:`._check_target`, whose error text is
    the message itself (also under a user's own ``jax.jit``); elsewhere ``equinox``'s
    ``branched_error_if`` (a host callback, its message after JAX's traceback)."""
    for message in messages:
        if message:
            _register(message, error)
    codes = jnp.asarray([_check_target.code_for(m, error) if m else -1 for m in messages], jnp.int32)
    failed_codes = jnp.where(failed, codes[index], jnp.int32(-1))
    leaves, tree = jax.tree.flatten(x)

    def on_cpu(failed_codes, *leaves):
        return jax.tree.unflatten(tree, _check_target.checked(leaves, failed_codes))

    def elsewhere(failed_codes, *leaves):
        return eqx.branched_error_if(jax.tree.unflatten(tree, leaves), failed, index, messages)

    return jax.lax.platform_dependent(failed_codes, *leaves, cpu=on_cpu, default=elsewhere)


class _HostCheckError(RuntimeError):
    """Raised from a host callback in place of the callback's own exception (recorded first)."""


def checked_pure_callback(callback: Callable, result_shape_dtypes, *args, **kwargs):
    """``jax.pure_callback(callback, result_shape_dtypes, *args, **kwargs)`` where an exception
    raised by ``callback`` reaches the caller as that exception's type and message (through
    :func:`documented_errors`).

    On CPU the callback reports the failure instead of raising it (its outputs are then
    placeholders) and the FFI check of :mod:`._check_target` fails the program with the message;
    elsewhere the callback raises. ``vmap_method`` may only be ``"sequential"`` (or absent): the
    placeholders have the shapes of ``result_shape_dtypes``.
    """
    if kwargs.get("vmap_method") not in (None, "sequential"):
        raise ValueError(f"checked_pure_callback: vmap_method must be 'sequential', not {kwargs['vmap_method']!r}")

    def reporting(*call_args, **call_kwargs):
        try:
            return callback(*call_args, **call_kwargs), np.int32(-1)
        except Exception as exception:
            message = str(exception)
            _register(message, type(exception))
            placeholders = jax.tree.map(lambda s: np.zeros(s.shape, s.dtype), result_shape_dtypes)
            return placeholders, np.int32(_check_target.code_for(message, type(exception)))

    @functools.wraps(callback)
    def raising(*call_args, **call_kwargs):
        try:
            return callback(*call_args, **call_kwargs)
        except Exception as exception:
            message = str(exception)
            _register(message, type(exception))
            raise _HostCheckError(message) from exception

    def on_cpu(*args):
        out, code = jax.pure_callback(reporting, (result_shape_dtypes, jax.ShapeDtypeStruct((), jnp.int32)), *args, **kwargs)
        leaves, tree = jax.tree.flatten(out)
        return jax.tree.unflatten(tree, _check_target.checked(leaves, code))

    def elsewhere(*args):
        return jax.pure_callback(raising, result_shape_dtypes, *args, **kwargs)

    return jax.lax.platform_dependent(*args, cpu=on_cpu, default=elsewhere)


# ---------------------------------------------------------------------------------------------
# Translation


def _equinox_runtime_error() -> type[Exception]:
    try:
        return eqx.EquinoxRuntimeError
    except AttributeError:  # pragma: no cover - older equinox
        from equinox._jit import EquinoxRuntimeError

        return EquinoxRuntimeError


_TRANSLATED_TYPES = (jax.errors.JaxRuntimeError, _equinox_runtime_error(), ValueError)


def _recorded_message(text: str) -> str | None:
    """The recorded message a runtime-error text carries (``None``: not one of our checks)."""
    for prefix in (*_check_target.status_prefixes(), _DISPATCH_PREFIX):  # the FFI check: the text is the message
        message = text.partition(prefix)[2]
        if message in _REGISTERED:
            return message
    if _EQUINOX_MARKER not in text and _CALLBACK_MARKER not in text and "EquinoxRuntimeError: " not in text:
        return None
    try:  # equinox keeps the message of the check that failed last
        from equinox import _jit

        last = _jit.last_error_info
    except (ImportError, AttributeError):  # pragma: no cover - equinox internals moved
        last = None
    if last is not None and last[0] in _REGISTERED and last[0] in text:
        return last[0]
    with _LOCK:
        candidates = [m for m in _REGISTERED if m and m in text]
    return max(candidates, key=len) if candidates else None


def translate_runtime_error(exception: BaseException) -> BaseException | None:
    """``error(message)`` for a runtime error that carries a recorded check, else ``None``."""
    if not isinstance(exception, _TRANSLATED_TYPES):
        return None
    message = _recorded_message(str(exception))
    if message is None:
        return None
    return _REGISTERED[message](message)


# -- quiet callbacks ------------------------------------------------------------------------------

# Calls in progress, per thread id (each thread writes only its own entry, so no lock is needed).
# Checks fail inside a host callback, which XLA may run on one of its own threads (GPU), not the
# caller's: the filter drops our checks' records while any thread has a call in progress.
_DEPTH: dict[int, int] = {}


def _is_our_check(record: logging.LogRecord) -> bool:
    exception = record.exc_info[1] if record.exc_info else None
    if exception is None:
        return False
    if isinstance(exception, _HostCheckError):
        return True
    text = f"{type(exception).__name__}: {exception}"
    return type(exception).__name__ == "_EquinoxRuntimeError" and _recorded_message(text) is not None


class _QuietChecks(logging.Filter):
    """Drops JAX's "callback failed" records of our checks while a translating call runs."""

    def filter(self, record: logging.LogRecord) -> bool:
        if not any(tuple(_DEPTH.values())):  # a snapshot: other threads may add entries
            return True
        return not _is_our_check(record)


_CALLBACK_LOGGER = logging.getLogger("jax._src.callback")
if not any(isinstance(f, _QuietChecks) for f in _CALLBACK_LOGGER.filters):
    _CALLBACK_LOGGER.addFilter(_QuietChecks())


def _enter() -> int:
    thread = threading.get_ident()
    _DEPTH[thread] = _DEPTH.get(thread, 0) + 1
    return thread


def _leave(thread: int) -> None:
    _DEPTH[thread] -= 1


class documented_errors:  # noqa: N801 - used like a function: ``with documented_errors():``
    """Context manager (or decorator): a failed runtime check of a geomjax op in the body raises
    its documented type with the op's message (see the module docstring); other exceptions pass
    through unchanged.

    geomjax's own entry points and torch_bridge do this already; wrap a call of your own jitted
    function to get the same, instead of JAX's runtime error. Block on the results inside the
    body (XLA may finish a CPU program after the call returns); as a decorator it blocks for you.

    Example:
        >>> import jax, jax.numpy as jnp, geomjax
        >>> controls = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # a duplicate
        >>> step = jax.jit(lambda c: geomjax.radial_basis_function_deform_points(c, c, jnp.ones_like(c)))
        >>> with geomjax.documented_errors():
        ...     jax.block_until_ready(step(controls))
        Traceback (most recent call last):
        RuntimeError: radial_basis_function_deform_points: the thin-plate-spline fit system is singular ...
    """

    __slots__ = ("_thread",)

    def __call__(self, function: Callable) -> Callable:
        @functools.wraps(function)
        def wrapper(*args, **kwargs):
            with documented_errors():
                return _ready(function(*args, **kwargs))

        return wrapper

    def __enter__(self) -> None:
        self._thread = _enter()

    def __exit__(self, kind, exception, traceback) -> Literal[False]:
        _leave(self._thread)
        if exception is not None and isinstance(exception, _TRANSLATED_TYPES):
            translated = translate_runtime_error(exception)
            if translated is not None:
                raise translated from None
        return False


def _ready(result):
    """``result`` once computed: XLA runs larger CPU programs asynchronously, and a check that
    fails after the call returned would reach the caller untranslated, at first use. Tracers
    (the call was traced by an enclosing transform) pass through."""
    return jax.block_until_ready(result)


def raises_documented_errors(function: Callable) -> Callable:
    """Decorator for public ops: a failed runtime check raises its documented type (see the
    module docstring). ``functools.wraps`` keeps the name, docstring and signature."""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        thread = _enter()
        try:
            return _ready(function(*args, **kwargs))
        except _TRANSLATED_TYPES as exception:
            translated = translate_runtime_error(exception)
            if translated is None:
                raise
            raise translated from None
        finally:
            _leave(thread)

    return wrapper
