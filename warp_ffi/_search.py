"""What the float32 mesh searches (closest points, rays) share: padded radii and their inputs.

Warp's meshes and our oriented-box tree are float32, while queries and answers are in the
working dtype. Every float32 search radius is therefore widened by ``PAD`` of the coordinate
magnitudes (far above float32 rounding, so no face is lost at the gate) and the caller re-gates
exactly in the working dtype.
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp
import numpy as np

from ._grid import FLOAT32_MAX
from ._wrap import warp as wp

__all__ = ["PAD", "max_abs", "padded_radius", "unit_scaled", "face_corners", "search_params", "mesh_inputs"]

PAD = wp.constant(2.0**-16)  # relative margin of every float32 search radius


@wp.func
@no_type_check
def max_abs(v: Any):
    """The largest magnitude of a 3-vector's components."""
    return wp.max(wp.max(wp.abs(v[0]), wp.abs(v[1])), wp.abs(v[2]))


@wp.func
@no_type_check
def padded_radius(radius: Any, magnitude: Any):
    """``radius`` widened by the pad and rounded to a float32 that cannot be too small."""
    widened = radius + type(radius)(PAD) * (magnitude + radius)
    if not wp.isfinite(widened) or widened > type(radius)(FLOAT32_MAX):
        return float(FLOAT32_MAX)
    return float(widened)


@wp.func
@no_type_check
def unit_scaled(v: Any):
    """``v / |v|`` computed on ``v / max |v_i|`` (no underflow); zero for a zero vector."""
    size = max_abs(v)
    if size > type(size)(0.0):
        w = v / size
        return w / wp.length(w)
    return v - v


@wp.func
@no_type_check
def face_corners(faces: wp.array(dtype=wp.vec3i), vertices: wp.array(dtype=Any), face: int):
    """The three corners of ``face``."""
    tri = faces[face]
    return vertices[tri[0]], vertices[tri[1]], vertices[tri[2]]


def search_params(dtype, *values) -> tuple[jax.Array, jax.Array]:
    """0-d ``values`` as one parameter array in ``dtype`` and its float32 copy (clamped to range)."""
    params = jnp.stack(values).astype(dtype)
    return params, jnp.minimum(params, jnp.asarray(np.finfo(np.float32).max, dtype)).astype(jnp.float32)


def mesh_inputs(mesh) -> tuple:
    """A search's mesh arguments: a prepared handle (one array, or a tuple of tree arrays), or
    ``(vertices32, faces_flat)`` to build the structure in the call."""
    return mesh if isinstance(mesh, tuple) else (mesh,)
