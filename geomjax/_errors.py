"""Data-dependent checks that reach callers as the documented exception type.

A check on values that are only known when a compiled program runs (an index range, finiteness,
a singular fit, a solve that did not converge) is an ``equinox.error_if``: the outputs depend on
it, so it can never be skipped. When it fails, JAX reports a ``JaxRuntimeError: INTERNAL:
CpuCallback error ...`` (or, from its C++ dispatch path, a ``ValueError`` with the same text)
with the message buried in a traceback, ``equinox.filter_jit`` reports an
``EquinoxRuntimeError`` with a long banner, and JAX logs the failed callback to stderr.

This module is the one place that turns those back into the documented exception:

* :func:`runtime_check` / :func:`runtime_branched_check` replace ``eqx.error_if`` /
  ``eqx.branched_error_if``: concrete predicates raise the documented type at once; traced ones
  become an ``equinox.error_if`` whose message is recorded with its exception type.
* :func:`checked_pure_callback` is ``jax.pure_callback`` for host functions that may raise: the
  exception's type and message are recorded the same way.
* :func:`raises_documented_errors` (a decorator for public ops) and :func:`documented_errors` (a
  context manager, used by ``torch_bridge`` around its jitted programs) run the call and turn a
  runtime error that carries a recorded message into ``error(message)`` (``from None``: the first
  line is the op's message). Other exceptions pass through unchanged. While such a call runs,
  JAX's "jax.pure_callback failed" log records of these checks are dropped, so nothing reaches
  stderr.

Under a user's own ``jax.jit`` the op is only traced by the decorated call; the check fails
later, when the user's program runs, and reaches the user as JAX's (or equinox's) runtime error,
whose text contains the message.
"""

from __future__ import annotations

import functools
import logging
import threading
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import numpy as np

__all__ = ["checked_pure_callback", "documented_errors", "raises_documented_errors", "runtime_branched_check", "runtime_check", "translate_runtime_error"]

# message -> documented exception type, for every runtime check traced so far.
_REGISTERED: dict[str, type[Exception]] = {}
_LOCK = threading.Lock()
# Markers that identify a failed runtime check in the text JAX reports.
_EQUINOX_MARKER = "_EquinoxRuntimeError: "
_CALLBACK_MARKER = "_HostCheckError: "


def _register(message: str, error: type[Exception]) -> None:
    if _REGISTERED.get(message) is not error:
        with _LOCK:
            _REGISTERED[message] = error


def _is_concrete(value) -> bool:
    return not isinstance(value, jax.core.Tracer)


def runtime_check(x, failed, message: str, error: type[Exception] = ValueError):
    """``x`` after checking that ``failed`` (a bool or bool array, any element) is false.

    A concrete ``failed`` raises ``error(message)`` at once. A traced one becomes an
    ``equinox.error_if`` on ``x`` (use the returned value: the check is attached to it) and
    ``message`` is recorded so :func:`documented_errors` raises ``error(message)`` when the
    compiled check fails.
    """
    if _is_concrete(failed):
        if bool(np.any(np.asarray(failed))):
            raise error(message)
        return x
    _register(message, error)
    return eqx.error_if(x, failed, message)


def runtime_branched_check(x, failed, index, messages: Sequence[str], error: type[Exception] = RuntimeError):
    """As :func:`runtime_check` with one of several ``messages`` chosen by ``index``
    (``equinox.branched_error_if``)."""
    if _is_concrete(failed) and _is_concrete(index):
        if bool(np.any(np.asarray(failed))):
            raise error(messages[int(np.max(np.asarray(index)))])
        return x
    for message in messages:
        if message:
            _register(message, error)
    return eqx.branched_error_if(x, failed, index, tuple(messages))


class _HostCheckError(RuntimeError):
    """Raised from a host callback in place of the callback's own exception (recorded first)."""


def checked_pure_callback(callback: Callable, result_shape_dtypes, *args, **kwargs):
    """``jax.pure_callback(callback, result_shape_dtypes, *args, **kwargs)`` where an exception
    raised by ``callback`` reaches the caller as that exception's type and message (through
    :func:`documented_errors`)."""

    @functools.wraps(callback)
    def run(*call_args, **call_kwargs):
        try:
            return callback(*call_args, **call_kwargs)
        except Exception as exception:
            message = str(exception)
            _register(message, type(exception))
            raise _HostCheckError(message) from exception

    return jax.pure_callback(run, result_shape_dtypes, *args, **kwargs)


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
    """Context manager: a failed runtime check in the body raises its documented type (see the
    module docstring); other exceptions pass through unchanged."""

    __slots__ = ("_thread",)

    def __enter__(self) -> None:
        self._thread = _enter()

    def __exit__(self, kind, exception, traceback) -> bool:
        _leave(self._thread)
        if exception is not None and isinstance(exception, _TRANSLATED_TYPES):
            translated = translate_runtime_error(exception)
            if translated is not None:
                raise translated from None
        return False


def raises_documented_errors(function: Callable) -> Callable:
    """Decorator for public ops: a failed runtime check raises its documented type (see the
    module docstring). ``functools.wraps`` keeps the name, docstring and signature."""

    @functools.wraps(function)
    def wrapper(*args, **kwargs):
        thread = _enter()
        try:
            return function(*args, **kwargs)
        except _TRANSLATED_TYPES as exception:
            translated = translate_runtime_error(exception)
            if translated is None:
                raise
            raise translated from None
        finally:
            _leave(thread)

    return wrapper
