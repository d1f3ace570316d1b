"""An XLA FFI target that stops a running CPU program with a failed check's own message.

``equinox.error_if`` raises from a host callback, and JAX reports an exception raised in a host
callback as ``JaxRuntimeError: INTERNAL: CpuCallback error calling callback: Traceback ...``: the
whole Python stack first, the message last, and the callback's failure logged to stderr. XLA
reports the error of an FFI handler as that error's status and message alone, so a check made
by this target reaches every caller, a user's own ``jax.jit`` included, as

    JaxRuntimeError: INVALID_ARGUMENT: <the op's message>

(``FAILED_PRECONDITION`` for checks documented as ``RuntimeError``), with nothing printed.

:func:`checked` is the one entry point: ``checked(leaves, codes, error)`` returns ``leaves``
unchanged (aliased, not copied) after failing the program if any element of the int32 array
``codes`` is a message id (non-negative; ``-1`` means passed). The outputs depend on the check, so
XLA cannot drop it while they are used, like ``equinox.error_if``.

The handler is Python called through ``ctypes`` (the FFI's C structures are declared below, only
the fields it reads). It is registered for the CPU platform only: on a GPU, ``_errors`` keeps
``equinox.error_if`` (a CUDA handler would have to copy the codes to the host and synchronise).
"""

from __future__ import annotations

import ctypes
import math
import threading
import zlib
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["checked", "code_for", "status_prefixes"]

_TARGET = "geomjax_failed_check"

# id -> message. An id is a hash of the message, not a counter: a compiled program embeds the
# ids of its checks as constants, and JAX's persistent compilation cache hands that program to
# other processes, which must read the same message for the same id (the message is recorded
# again when the program is traced there, before the cache is consulted). The handler, which may
# run on an XLA thread, only reads entries that exist.
_MESSAGES: dict[int, str] = {}
_LOCK = threading.Lock()
_ID_BITS = 30  # 2 * id + 1 stays a non-negative int32


def _message_id(message: str) -> int:
    """The id ``codes`` carry for ``message``: the same in every process."""
    identifier = zlib.crc32(message.encode("utf-8", "replace")) & ((1 << _ID_BITS) - 1)
    known = _MESSAGES.get(identifier)
    if known is None:
        with _LOCK:
            known = _MESSAGES.setdefault(identifier, message)
    if known != message:  # about one chance in 10**7 for a few hundred messages; never silent
        raise RuntimeError(f"geomjax: two check messages share the id {identifier}: {known!r} and {message!r}; reword one")
    return identifier


# ---------------------------------------------------------------------------------------------
# The C structures of the XLA FFI API (xla/ffi/api/c_api.h) that the handler reads.


class _ExtensionBase(ctypes.Structure):
    pass


_ExtensionBase._fields_ = [("struct_size", ctypes.c_size_t), ("type", ctypes.c_int), ("next", ctypes.POINTER(_ExtensionBase))]
_METADATA_EXTENSION = 1  # XLA_FFI_Extension_Metadata
_EXECUTE_STAGE = 3  # XLA_FFI_ExecutionStage_EXECUTE


class _ApiVersion(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("major_version", ctypes.c_int), ("minor_version", ctypes.c_int),
    ]  # fmt: skip


class _Metadata(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("api_version", _ApiVersion), ("traits", ctypes.c_uint32)]


class _MetadataExtension(ctypes.Structure):
    _fields_ = [("extension_base", _ExtensionBase), ("metadata", ctypes.POINTER(_Metadata))]


class _ErrorCreateArgs(ctypes.Structure):
    _fields_ = [("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("message", ctypes.c_char_p), ("errc", ctypes.c_int)]


_ErrorCreate = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_ErrorCreateArgs))


class _Api(ctypes.Structure):
    # The leading fields only: the handler calls XLA_FFI_Error_Create and nothing after it.
    _fields_ = [
        ("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("api_version", _ApiVersion),
        ("internal_api", ctypes.c_void_p), ("error_create", _ErrorCreate),
    ]  # fmt: skip


class _Arguments(ctypes.Structure):  # XLA_FFI_Args and XLA_FFI_Rets share this layout
    _fields_ = [
        ("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("size", ctypes.c_int64),
        ("types", ctypes.c_void_p), ("values", ctypes.POINTER(ctypes.c_void_p)),
    ]  # fmt: skip


class _Attributes(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("size", ctypes.c_int64),
        ("types", ctypes.c_void_p), ("names", ctypes.c_void_p), ("values", ctypes.c_void_p),
    ]  # fmt: skip


class _CallFrame(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("api", ctypes.POINTER(_Api)),
        ("ctx", ctypes.c_void_p), ("stage", ctypes.c_int), ("args", _Arguments), ("rets", _Arguments), ("attrs", _Attributes),
        ("future", ctypes.c_void_p),
    ]  # fmt: skip


class _Buffer(ctypes.Structure):
    _fields_ = [
        ("struct_size", ctypes.c_size_t), ("extension_start", ctypes.POINTER(_ExtensionBase)), ("dtype", ctypes.c_int),
        ("data", ctypes.c_void_p), ("rank", ctypes.c_int64), ("dims", ctypes.POINTER(ctypes.c_int64)),
    ]  # fmt: skip


# XLA_FFI_Error_Code values (absl status codes) per documented exception type.
_INVALID_ARGUMENT, _FAILED_PRECONDITION = 3, 9
_STATUS_NAMES = {_INVALID_ARGUMENT: "INVALID_ARGUMENT", _FAILED_PRECONDITION: "FAILED_PRECONDITION"}


def status_prefixes() -> tuple[str, ...]:
    """How XLA's error text starts for a check of this target (``"INVALID_ARGUMENT: "``, ...)."""
    return tuple(f"{name}: " for name in _STATUS_NAMES.values())


def _failed_code(frame: _CallFrame) -> int:
    """The first message id in the codes buffer (argument 0), or -1."""
    codes = ctypes.cast(frame.args.values[0], ctypes.POINTER(_Buffer)).contents
    size = math.prod(codes.dims[i] for i in range(codes.rank))
    if size == 0:
        return -1
    values = np.ctypeslib.as_array(ctypes.cast(codes.data, ctypes.POINTER(ctypes.c_int32)), shape=(size,))
    failed = np.flatnonzero(values >= 0)
    return int(values[failed[0]]) if failed.size else -1


def _handler(frame_pointer) -> int | None:
    frame = frame_pointer.contents
    extension = frame.extension_start
    if extension and extension.contents.type == _METADATA_EXTENSION:
        # XLA's registration-time query: the typed FFI API version this handler speaks.
        metadata = ctypes.cast(extension, ctypes.POINTER(_MetadataExtension)).contents.metadata.contents
        metadata.api_version.major_version, metadata.api_version.minor_version = 0, 1
        return None
    if frame.stage != _EXECUTE_STAGE:
        return None
    # The outputs alias the inputs after the codes, so passing leaves nothing to write.
    code = _failed_code(frame)
    if code < 0:
        return None
    # Every traced check records its message before its program runs; the fallback is defensive.
    message = _MESSAGES.get(code >> 1, f"geomjax: a runtime check failed (message id {code >> 1})")
    status = _FAILED_PRECONDITION if code & 1 else _INVALID_ARGUMENT
    arguments = _ErrorCreateArgs(ctypes.sizeof(_ErrorCreateArgs), None, message.encode("utf-8", "replace"), status)
    return frame.api.contents.error_create(ctypes.byref(arguments))


_HANDLER = ctypes.CFUNCTYPE(ctypes.c_void_p, ctypes.POINTER(_CallFrame))(_handler)  # kept alive for XLA
_registered = False


def _register() -> None:
    global _registered
    with _LOCK:
        if not _registered:
            capsule = jax.ffi.pycapsule(ctypes.cast(_HANDLER, ctypes.c_void_p).value)
            jax.ffi.register_ffi_target(_TARGET, capsule, platform="cpu")
            _registered = True


def code_for(message: str, error: type[Exception]) -> int:
    """The code a failed check of ``message`` (documented as ``error``) carries: the message id
    and, in the low bit, whether XLA reports it as ``FAILED_PRECONDITION`` (``RuntimeError``)."""
    return 2 * _message_id(message) + int(not issubclass(error, ValueError))


# ---------------------------------------------------------------------------------------------


def _failing_call(codes, *leaves):
    _register()
    aliases = {1 + i: i for i in range(len(leaves))}
    # The outputs are typed as the inputs (``jax.typeof``: their sharding under Explicit mesh
    # axes, and inside shard_map the axes they vary over), so that they match the unchecked
    # branch of the cond below and the specs of an enclosing shard_map.
    call = jax.ffi.ffi_call(_TARGET, [jax.typeof(x) for x in leaves], input_output_aliases=aliases, vmap_method="broadcast_all")
    return tuple(call(codes, *leaves))


@jax.custom_batching.custom_vmap
def _checked_values(codes, *leaves):
    # The handler (a Python call through ctypes, taking the GIL) runs only when a check failed.
    return jax.lax.cond(jnp.any(codes >= 0), lambda: _failing_call(codes, *leaves), lambda: leaves)


@_checked_values.def_vmap
def _checked_values_vmap(axis_size, in_batched, codes, *leaves):
    # A batch is checked as one: any failed element fails the program. Run on the whole batched
    # arrays rather than through vmap's rules, which would turn the cond into a select between
    # the FFI call's outputs, typed as replicated along the batch axis, and the leaves, which a
    # split batch types as split (a sharding mismatch under Explicit axes).
    del axis_size
    return _checked_values(codes, *leaves), tuple(in_batched[1:])


@jax.custom_jvp
def _check(codes, *leaves):
    return _checked_values(codes, *leaves)


@_check.defjvp
def _check_jvp(primals, tangents):
    # The check passes tangents through unchanged (the values they are tangent to are checked).
    return _check(*primals), tuple(tangents[1:])


def checked(leaves: Sequence[jax.Array], codes) -> tuple[jax.Array, ...]:
    """``leaves`` after failing the (CPU) program if any element of ``codes`` is a
    :func:`code_for` code rather than ``-1``."""
    codes = jnp.asarray(codes, jnp.int32)
    leaves = tuple(jnp.asarray(x) for x in leaves)
    return _check(codes, *leaves)
