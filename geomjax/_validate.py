"""Shared input checks for every public op.

All checks here run at trace time: they look at shapes, dtypes and Python scalars only, never at
array values, so they cost nothing inside ``jit`` and never force a device sync. Messages name the
argument, what was expected and what was received. Exception types follow the reference API:
``TypeError`` for wrong types and dtypes, ``ValueError`` for shapes and values.
"""

from __future__ import annotations

import math
import numbers
import os
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from ._errors import runtime_check
from ._sharding import on_one_device

FLOAT_DTYPES = (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64))
INDEX_DTYPES = (jnp.dtype(jnp.int32), jnp.dtype(jnp.int64))


def is_array(x) -> bool:
    """Whether ``x`` is an array (JAX, NumPy or array-like with shape and dtype), not a scalar."""
    return isinstance(x, (jax.Array, np.ndarray)) or (hasattr(x, "shape") and hasattr(x, "dtype") and not isinstance(x, (numbers.Number, np.generic)))


def as_jax_array(x) -> jax.Array:
    """``x`` as a JAX array, unchanged if it is one. Host arrays go through ``jax.device_put``:
    ``jnp.asarray`` of a NumPy array compiles a copy program for each new shape (jax 0.10), a
    cost every first call with a new input shape paid."""
    if isinstance(x, jax.Array):
        return x
    if hasattr(x, "__jax_array__"):
        return jnp.asarray(x)
    return jax.device_put(np.asarray(x))


def _as_array_of(name: str, x, dtypes: tuple, kind: str) -> jax.Array:
    article = "an" if kind[0] in "aeiou" else "a"
    if not is_array(x):
        raise TypeError(f"{name} must be {article} {kind} array, got {type(x).__name__}")
    dtype = jnp.dtype(x.dtype)
    if dtype not in dtypes:
        raise TypeError(f"{name} must have dtype {kind}, got {dtype}")
    return as_jax_array(x)


def as_float_array(name: str, x) -> jax.Array:
    """Return ``x`` as a JAX array after checking it is a float32/float64 array.

    Raises:
        TypeError: ``x`` is not an array, or its dtype is not float32 or float64.
    """
    return _as_array_of(name, x, FLOAT_DTYPES, "float32 or float64")


def as_index_array(name: str, x) -> jax.Array:
    """Return ``x`` as a JAX integer array after checking it is int32/int64."""
    return _as_array_of(name, x, INDEX_DTYPES, "int32 or int64")


def check_same_dtype(reference_name: str, reference: jax.Array, name: str, x: jax.Array) -> None:
    """Floating inputs of one call share a dtype: there is no implicit promotion."""
    if jnp.dtype(x.dtype) != jnp.dtype(reference.dtype):
        raise TypeError(f"{name} must have the same dtype as {reference_name} ({jnp.dtype(reference.dtype)}), got {jnp.dtype(x.dtype)}")


def _device_set(x):
    # Tracers have no committed devices; only concrete arrays can disagree.
    if isinstance(x, jax.core.Tracer) or not isinstance(x, jax.Array):
        return None
    try:
        return frozenset(x.devices())
    except Exception:  # pragma: no cover - deleted or abstract arrays
        return None


def check_same_device(reference_name: str, reference, name: str, x) -> None:
    """Concrete arrays committed to different devices are a ``ValueError``, as in the reference."""
    a, b = _device_set(reference), _device_set(x)
    if a is not None and b is not None and a != b and reference.committed and x.committed:
        raise ValueError(f"{name} must be on the same device as {reference_name}: {sorted(map(str, b))} vs {sorted(map(str, a))}")


def check_coordinates(name: str, x, *, min_dims: int = 1) -> tuple[jax.Array, bool]:
    """Check a coordinate array of shape ``(N, D)`` or ``(B, N, D)``.

    Returns:
        The array and whether it is batched.
    """
    x = as_float_array(name, x)
    if x.ndim not in (2, 3):
        raise ValueError(f"{name} must have shape (N, D) or (B, N, D), got {tuple(x.shape)}")
    if x.shape[-1] < min_dims:
        raise ValueError(f"{name} must have at least {min_dims} coordinate(s) per point, got shape {tuple(x.shape)}")
    return x, x.ndim == 3


def check_companion(points_name: str, points: jax.Array, name: str, x, *, same_count: bool = False) -> jax.Array:
    """Check a per-batch companion of ``points`` (controls, displacements) for alignment.

    Companions have the same rank as ``points`` (both unbatched or both batched, never broadcast),
    the same leading batch size, the same coordinate count ``D`` and the same dtype and device.
    With ``same_count`` the number of rows must match too.
    """
    x = as_float_array(name, x)
    check_same_dtype(points_name, points, name, x)
    check_same_device(points_name, points, name, x)
    if x.ndim != points.ndim:
        raise ValueError(f"{points_name} and {name} must both be unbatched or both be batched: got shapes {tuple(points.shape)} and {tuple(x.shape)}")
    if points.ndim == 3 and x.shape[0] != points.shape[0]:
        raise ValueError(f"{name} batch size {x.shape[0]} does not match {points_name} batch size {points.shape[0]} (batches are aligned, not broadcast)")
    if x.shape[-1] != points.shape[-1]:
        raise ValueError(f"{name} must have {points.shape[-1]} coordinates per row like {points_name}, got shape {tuple(x.shape)}")
    if same_count and x.shape != points.shape:
        raise ValueError(f"{name} must have exactly the shape of {points_name} {tuple(points.shape)}, got {tuple(x.shape)}")
    return x


def check_same_shape(reference_name: str, reference: jax.Array, name: str, x) -> jax.Array:
    """``x`` must have exactly the shape, dtype and device of ``reference``."""
    x = as_float_array(name, x)
    check_same_dtype(reference_name, reference, name, x)
    check_same_device(reference_name, reference, name, x)
    if x.shape != reference.shape:
        raise ValueError(f"{name} must have exactly the shape of {reference_name} {tuple(reference.shape)}, got {tuple(x.shape)}")
    return x


def check_point_weights(point_weights, points: jax.Array) -> jax.Array | None:
    """Check optional per-point weights: ``None``, bool or float of shape ``(N,)`` / ``(B, N)``.

    Float weights must match the point dtype exactly; integer weights are a ``TypeError``. The
    expected shape is ``points.shape[:-1]`` with no broadcasting over the batch.
    """
    if point_weights is None:
        return None
    if not is_array(point_weights):
        raise TypeError(f"point_weights must be None or a bool/float array, got {type(point_weights).__name__}")
    dtype = jnp.dtype(point_weights.dtype)
    if dtype == jnp.dtype(bool):
        pass
    elif dtype in FLOAT_DTYPES:
        if dtype != jnp.dtype(points.dtype):
            raise TypeError(f"floating point_weights must have the points dtype {jnp.dtype(points.dtype)}, got {dtype}")
    else:
        raise TypeError(f"point_weights must be bool or float32/float64, got {dtype}")
    return check_one_per_point("point_weights", point_weights, points, "weight")


def check_one_per_point(name: str, x, points: jax.Array, entry: str) -> jax.Array:
    """``x`` as a JAX array after checking its device and shape ``points.shape[:-1]`` (one
    ``entry`` per point; no broadcasting, so a misaligned batch is an error, not a silent copy)."""
    x = jnp.asarray(x)
    check_same_device("points", points, name, x)
    expected = tuple(points.shape[:-1])
    if tuple(x.shape) != expected:
        raise ValueError(f"{name} must have shape {expected} (one {entry} per point, no broadcasting), got {tuple(x.shape)}")
    return x


def check_real_scalar(name: str, value, dtype, *, positive: bool = False, nonnegative: bool = False) -> float:
    """Validate a Python real scalar option against the working ``dtype``.

    ``bool`` and non-real values are a ``TypeError``; NaN, infinity, values outside the dtype's
    range, and (for positive quantities) values that underflow in the dtype are a ``ValueError``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    try:
        value = float(value)
    except OverflowError:  # a Python int (or Fraction) beyond every float: out of range, not a crash
        raise ValueError(f"{name} must be finite, got a number beyond the range of every float ({str(value)[:12]}...)") from None
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value}")
    info = jnp.finfo(dtype)
    if abs(value) > float(info.max):
        raise ValueError(f"{name}={value} is outside the range of {jnp.dtype(dtype)}")
    if positive:
        if value <= 0.0:
            raise ValueError(f"{name} must be positive, got {value}")
        if value < float(info.tiny) * float(info.eps):
            raise ValueError(f"{name}={value} underflows in {jnp.dtype(dtype)}")
    if nonnegative and value < 0.0:
        raise ValueError(f"{name} must be non-negative, got {value}")
    return value


def check_real_sequence(name: str, value: Sequence, length: int, dtype, *, positive: bool = False) -> tuple[float, ...]:
    """Validate a Python sequence of ``length`` real scalars (used for box origins and extents).

    A sequence of another length is a ``TypeError``, as in the reference ("must contain exactly D
    real values"): it is not the sequence type the parameter takes."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"{name} must be an array or a sequence of {length} real numbers, got {type(value).__name__}")
    if len(value) != length:
        raise TypeError(f"{name} must contain exactly {length} real values (one per coordinate), got {len(value)}")
    return tuple(check_real_scalar(f"{name}[{i}]", v, dtype, positive=positive) for i, v in enumerate(value))


def check_bool(name: str, value) -> bool:
    """A flag must be a real Python ``bool`` (``1`` is a ``TypeError``)."""
    if not isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be a bool, got {type(value).__name__}")
    return bool(value)


def check_choice(name: str, value, choices: Sequence[str]) -> str:
    """A string option must be one of ``choices`` (``ValueError`` otherwise)."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def check_topology(name: str, x, points: jax.Array, *, vertices_per_row: Sequence[int]) -> jax.Array:
    """Check shared integer topology (cells, hinges, triangles) of shape ``(M, K)``.

    ``x`` must be an int32/int64 array (``TypeError`` otherwise, bool included) on the device of
    ``points``, two-dimensional with ``K`` in ``vertices_per_row`` (``ValueError`` otherwise).
    Index values are not inspected: that would need a device sync.
    """
    x = as_index_array(name, x)
    check_same_device("points", points, name, x)
    if x.ndim != 2 or x.shape[1] not in tuple(vertices_per_row):
        allowed = " or ".join(str(k) for k in vertices_per_row)
        raise ValueError(f"{name} must have shape (M, K) with K = {allowed} vertex indices per row, got shape {tuple(x.shape)}")
    return x


_INT64_MAX = 2**63 - 1


def check_integer(name: str, value, *, minimum: int) -> int:
    """A count option must be a Python/NumPy integer (``bool`` is a ``TypeError``) ``>= minimum``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    value = int(value)
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {value}")
    if value > _INT64_MAX:  # no count, size or seed beyond int64 can reach a kernel or an array
        raise ValueError(f"{name} must be at most 2**63 - 1, got an integer of {len(str(value))} digits")
    return value


def require(x, predicate, message: str, error: type[Exception] = ValueError):
    """``x`` after checking that ``predicate(x)`` holds (a bool or bool array, every element).

    On concrete values the check runs now; on traced ones it is an ``equinox.error_if`` attached
    to the returned value, raising ``error(message)`` when the program runs (``_errors.py``).
    """
    return runtime_check(x, jnp.logical_not(predicate(x)), message, error)


def check_index_range(indices, num_points: int, message: str) -> jax.Array:
    """``indices`` as int32 after checking that every value lies in ``[0, num_points)``.

    ``message`` says what must hold (e.g. ``"op: faces indices must be in [0, 8)"``). Concrete
    indices are checked now, and the error adds the values found. Traced ones get a run-time check
    and are clamped meanwhile: a Warp kernel must never read out of bounds, even before the check
    reports.
    """
    if not isinstance(indices, jax.core.Tracer):
        check_host_index_range(np.asarray(indices), num_points, message)
        return jnp.asarray(indices).astype(jnp.int32)
    indices = require(indices, lambda i: jnp.all((i >= 0) & (i < num_points)), message)
    return jnp.clip(indices, 0, max(num_points - 1, 0)).astype(jnp.int32)


def check_host_index_range(indices: np.ndarray, num_points: int, message: str) -> None:
    """The eager half of :func:`check_index_range`, for host (NumPy) indices."""
    if indices.size and (indices.min() < 0 or indices.max() >= num_points):
        raise ValueError(f"{message}, got values in [{indices.min()}, {indices.max()}]")


# ---------------------------------------------------------------------------------------------
# Eager host-side checks, for the ops whose output size depends on the data (sampling, remeshing).
# Unlike everything above, these look at values: those ops run outside jit anyway.


def check_host_surface(op_name: str, mesh_vertices, mesh_indices, *, min_vertices: int = 1, flat_indices: bool = False) -> tuple[jax.Array, np.ndarray]:
    """Finite ``(V, 3)`` vertices and in-range int64 host faces ``(F, 3)``, checked eagerly.

    ``flat_indices`` also accepts a flat ``(3 F,)`` index list (the reference's sampling layout).
    Tracers are a ``TypeError``: these ops cannot run under ``jit``.
    """
    vertices = as_float_array("mesh_vertices", mesh_vertices)
    if isinstance(vertices, jax.core.Tracer) or isinstance(mesh_indices, jax.core.Tracer):
        raise TypeError(f"{op_name} runs eagerly (its output size depends on the data): call it outside jax.jit")
    vertices = on_one_device(op_name, "mesh_vertices", vertices)
    mesh_indices = on_one_device(op_name, "mesh_indices", mesh_indices)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] < min_vertices:
        raise ValueError(f"mesh_vertices must have shape (V, 3) with V >= {min_vertices}, got {tuple(vertices.shape)}")
    if not is_array(mesh_indices):
        raise TypeError(f"mesh_indices must be an integer array, got {type(mesh_indices).__name__}")
    dtype = np.dtype(mesh_indices.dtype)
    if dtype == np.bool_ or dtype.kind not in "iu":
        raise TypeError(f"mesh_indices must have an integer dtype, got {dtype}")
    if isinstance(mesh_indices, jax.Array):
        check_same_device("mesh_vertices", vertices, "mesh_indices", mesh_indices)
    host = np.asarray(mesh_indices)
    flat_ok = flat_indices and host.ndim == 1 and host.size % 3 == 0
    if not (flat_ok or (host.ndim == 2 and host.shape[1] == 3)) or host.size == 0:
        layouts = "(F, 3) or (3 F,)" if flat_indices else "(F, 3)"
        raise ValueError(f"mesh_indices must have shape {layouts} with F >= 1, got {tuple(host.shape)}")
    faces = host.reshape(-1, 3).astype(np.int64)
    num_vertices = vertices.shape[0]
    check_host_index_range(faces, num_vertices, f"mesh_indices must lie in [0, {num_vertices})")
    # On the CPU NumPy reads the array in place: two JAX dispatches and a sync less (each costs
    # 0.1 ms or more when XLA's threads have been idle).
    on_cpu = next(iter(vertices.devices())).platform == "cpu"
    if not (np.isfinite(np.asarray(vertices)).all() if on_cpu else bool(jnp.all(jnp.isfinite(vertices)))):
        raise ValueError("mesh_vertices must be finite")
    return vertices, faces


def as_float32(x, *, narrower_only: bool = False):
    """A real floating array as float32 (float64 rounded; float16, bfloat16 and float8 exact, as
    every narrower float is a float32); with ``narrower_only``, float32 and float64 arrays stay as
    they are. Anything else is unchanged, for the usual checks to accept or reject."""
    if is_array(x) and jnp.issubdtype(x.dtype, jnp.floating) and not (narrower_only and jnp.dtype(x.dtype) in FLOAT_DTYPES):
        return jnp.asarray(x).astype(jnp.float32)
    return x


def check_host_vertex_field(op_name: str, name: str, value, vertices: jax.Array) -> np.ndarray | None:
    """``None`` stays ``None``; otherwise a finite, positive ``(V,)`` field as a float64 host array.

    Any real floating dtype is accepted (float16, bfloat16, the float8 types too, as the reference
    accepts any real floating-point density): the field is read on the host in float64 anyway.
    """
    if value is None:
        return None
    field = as_float_array(name, as_float32(value, narrower_only=True))
    if isinstance(field, jax.core.Tracer):
        raise TypeError(f"{op_name} runs eagerly: {name} must be concrete")
    field = on_one_device(op_name, name, field)
    check_same_device("mesh_vertices", vertices, name, field)
    if field.shape != (vertices.shape[0],):
        raise ValueError(f"{name} must have shape ({vertices.shape[0]},), got {tuple(field.shape)}")
    host = np.asarray(field, np.float64)
    if not np.all(np.isfinite(host) & (host > 0)):
        raise ValueError(f"{name} must be finite and positive")
    return host


def available_bytes(device) -> int | None:
    """Memory a new allocation on ``device`` can still get: the GPU allocator's limit minus its
    use, or the host's available memory (Linux ``MemAvailable``); ``None`` when unknown."""
    if device.platform != "cpu":
        stats = device.memory_stats() or {}
        if "bytes_limit" in stats:
            return int(stats["bytes_limit"]) - int(stats.get("bytes_in_use", 0))
        return None
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_allocatable(description: str, count: int, bytes_each: int, device, *, limit: int = 2**31 - 1) -> None:
    """``count`` items of about ``bytes_each`` bytes must fit in 32-bit indices and in the memory
    ``device`` has left (``ValueError`` naming ``description``), so an oversized request fails
    with the documented error before anything is allocated (XLA aborts the process when an
    allocation fails inside a program)."""
    if count > limit:
        raise ValueError(f"{description} needs {count} items, more than {limit}")
    available = available_bytes(device)
    needed = count * bytes_each
    if available is not None and needed > available:
        raise ValueError(f"{description} needs about {needed / 2**30:.1f} GiB, more than the {available / 2**30:.1f} GiB available on {device.platform}")
