"""Shared input checks for every public op.

All checks here run at trace time: they look at shapes, dtypes and Python scalars only, never at
array values, so they cost nothing inside ``jit`` and never force a device sync. Messages name the
argument, what was expected and what was received. Exception types follow the reference API:
``TypeError`` for wrong types and dtypes, ``ValueError`` for shapes and values.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

FLOAT_DTYPES = (jnp.dtype(jnp.float32), jnp.dtype(jnp.float64))
INDEX_DTYPES = (jnp.dtype(jnp.int32), jnp.dtype(jnp.int64))


def is_array(x) -> bool:
    """Whether ``x`` is an array (JAX, NumPy or array-like with shape and dtype), not a scalar."""
    return isinstance(x, (jax.Array, np.ndarray)) or (
        hasattr(x, "shape") and hasattr(x, "dtype") and not isinstance(x, (numbers.Number, np.generic))
    )


def as_float_array(name: str, x) -> jax.Array:
    """Return ``x`` as a JAX array after checking it is a float32/float64 array.

    Raises:
        TypeError: ``x`` is not an array, or its dtype is not float32 or float64.
    """
    if not is_array(x):
        raise TypeError(f"{name} must be a float32 or float64 array, got {type(x).__name__}")
    dtype = jnp.dtype(x.dtype)
    if dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name} must have dtype float32 or float64, got {dtype}")
    return jnp.asarray(x)


def as_index_array(name: str, x) -> jax.Array:
    """Return ``x`` as a JAX integer array after checking it is int32/int64."""
    if not is_array(x):
        raise TypeError(f"{name} must be an int32 or int64 array, got {type(x).__name__}")
    dtype = jnp.dtype(x.dtype)
    if dtype not in INDEX_DTYPES:
        raise TypeError(f"{name} must have dtype int32 or int64, got {dtype}")
    return jnp.asarray(x)


def check_same_dtype(reference_name: str, reference: jax.Array, name: str, x: jax.Array) -> None:
    """Floating inputs of one call share a dtype: there is no implicit promotion."""
    if jnp.dtype(x.dtype) != jnp.dtype(reference.dtype):
        raise TypeError(
            f"{name} must have the same dtype as {reference_name} ({jnp.dtype(reference.dtype)}), "
            f"got {jnp.dtype(x.dtype)}"
        )


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


def check_companion(
    points_name: str, points: jax.Array, name: str, x, *, same_count: bool = False
) -> jax.Array:
    """Check a per-batch companion of ``points`` (controls, displacements) for alignment.

    Companions have the same rank as ``points`` (both unbatched or both batched, never broadcast),
    the same leading batch size, the same coordinate count ``D`` and the same dtype and device.
    With ``same_count`` the number of rows must match too.
    """
    x = as_float_array(name, x)
    check_same_dtype(points_name, points, name, x)
    check_same_device(points_name, points, name, x)
    if x.ndim != points.ndim:
        raise ValueError(
            f"{points_name} and {name} must both be unbatched or both be batched: got shapes "
            f"{tuple(points.shape)} and {tuple(x.shape)}"
        )
    if points.ndim == 3 and x.shape[0] != points.shape[0]:
        raise ValueError(
            f"{name} batch size {x.shape[0]} does not match {points_name} batch size {points.shape[0]} "
            "(batches are aligned, not broadcast)"
        )
    if x.shape[-1] != points.shape[-1]:
        raise ValueError(
            f"{name} must have {points.shape[-1]} coordinates per row like {points_name}, got shape {tuple(x.shape)}"
        )
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
    point_weights = jnp.asarray(point_weights)
    check_same_device("points", points, "point_weights", point_weights)
    expected = tuple(points.shape[:-1])
    if tuple(point_weights.shape) != expected:
        raise ValueError(f"point_weights must have shape {expected} (one weight per point, no broadcasting), got {tuple(point_weights.shape)}")
    return point_weights


def check_real_scalar(
    name: str,
    value,
    dtype,
    *,
    positive: bool = False,
    nonnegative: bool = False,
) -> float:
    """Validate a Python real scalar option against the working ``dtype``.

    ``bool`` and non-real values are a ``TypeError``; NaN, infinity, values outside the dtype's
    range, and (for positive quantities) values that underflow in the dtype are a ``ValueError``.
    """
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {type(value).__name__}")
    value = float(value)
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
    """Validate a Python sequence of ``length`` real scalars (used for box origins and extents)."""
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        raise TypeError(f"{name} must be an array or a sequence of {length} real numbers, got {type(value).__name__}")
    if len(value) != length:
        raise ValueError(f"{name} must have {length} entries (one per coordinate), got {len(value)}")
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


def check_integer(name: str, value, *, minimum: int) -> int:
    """A count option must be a Python/NumPy integer (``bool`` is a ``TypeError``) ``>= minimum``."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {type(value).__name__}")
    value = int(value)
    if value < minimum:
        raise ValueError(f"{name} must be at least {minimum}, got {value}")
    return value


# ---------------------------------------------------------------------------------------------
# Eager host-side checks, for the ops whose output size depends on the data (sampling, remeshing).
# Unlike everything above, these look at values: those ops run outside jit anyway.


def check_host_surface(
    op_name: str, mesh_vertices, mesh_indices, *, min_vertices: int = 1, flat_indices: bool = False
) -> tuple[jax.Array, np.ndarray]:
    """Finite ``(V, 3)`` vertices and in-range int64 host faces ``(F, 3)``, checked eagerly.

    ``flat_indices`` also accepts a flat ``(3 F,)`` index list (the reference's sampling layout).
    Tracers are a ``TypeError``: these ops cannot run under ``jit``.
    """
    vertices = as_float_array("mesh_vertices", mesh_vertices)
    if isinstance(vertices, jax.core.Tracer) or isinstance(mesh_indices, jax.core.Tracer):
        raise TypeError(f"{op_name} runs eagerly (its output size depends on the data): call it outside jax.jit")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] < min_vertices:
        raise ValueError(
            f"mesh_vertices must have shape (V, 3) with V >= {min_vertices}, got {tuple(vertices.shape)}"
        )
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
    if faces.min() < 0 or faces.max() >= num_vertices:
        raise ValueError(f"mesh_indices must lie in [0, {num_vertices}), got values in [{faces.min()}, {faces.max()}]")
    if not bool(jnp.all(jnp.isfinite(vertices))):
        raise ValueError("mesh_vertices must be finite")
    return vertices, faces


def check_host_vertex_field(op_name: str, name: str, value, vertices: jax.Array) -> np.ndarray | None:
    """``None`` stays ``None``; otherwise a finite, positive ``(V,)`` field as a float64 host array."""
    if value is None:
        return None
    field = as_float_array(name, value)
    if isinstance(field, jax.core.Tracer):
        raise TypeError(f"{op_name} runs eagerly: {name} must be concrete")
    check_same_device("mesh_vertices", vertices, name, field)
    if field.shape != (vertices.shape[0],):
        raise ValueError(f"{name} must have shape ({vertices.shape[0]},), got {tuple(field.shape)}")
    host = np.asarray(field, np.float64)
    if not np.all(np.isfinite(host) & (host > 0)):
        raise ValueError(f"{name} must be finite and positive")
    return host
