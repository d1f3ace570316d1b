"""Device helpers shared by several ops: counting sort, Morton order, mesh ids, meshes built in a call.

* :func:`counting_sort` (JAX): the stable sort of small integer keys behind the morph hash grid
  and the Sobolev vertex incidence.
* :func:`morton_order` / :func:`query_order` (inside an FFI call): the Morton order of points,
  for the oriented-box tree's faces and the closest-point queries.
* Mesh ids: a ``wp.Mesh`` is addressed by a 64-bit id, which enters JAX as ``mesh_words``, two
  uint32 words (so no 64-bit JAX types are needed): :func:`mesh_words` packs them and the Warp
  function :func:`mesh_id` unpacks them in a kernel.
* :func:`mesh_in_call`: a ``wp.Mesh`` built inside an FFI call from (traced) buffers and freed
  at its end, once the launches that read it are done.
"""

from __future__ import annotations

import contextlib
import weakref
from typing import no_type_check

import jax
import jax.numpy as jnp
import numpy as np

from ._wrap import KernelFamily, launch_in_chunks
from ._wrap import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["build_mesh", "counting_sort", "mesh_id", "mesh_in_call", "mesh_words", "morton_order", "query_order"]

FLOAT32_MAX = wp.constant(3.4028234663852886e38)


# ---------------------------------------------------------------------------------------------
# Counting sort.


@wp.kernel
@no_type_check
def _counting_sort_kernel(
    keys: wp.array(dtype=wp.int32), num_items: wp.int32, num_keys: wp.int32, offsets: wp.array(dtype=wp.int32),
    order: wp.array(dtype=wp.int32), cursor: wp.array(dtype=wp.int32),
):  # fmt: skip
    """One thread per row: stable counting sort of the row's keys, values in ``[0, num_keys)``."""
    b = wp.tid()
    first_item = b * num_items
    first_offset = b * (num_keys + 1)
    first_cursor = b * num_keys
    for k in range(num_keys + 1):
        offsets[first_offset + k] = 0
    for i in range(num_items):
        offsets[first_offset + keys[first_item + i] + 1] += 1
    for k in range(num_keys):
        offsets[first_offset + k + 1] += offsets[first_offset + k]
        cursor[first_cursor + k] = offsets[first_offset + k]
    for i in range(num_items):
        slot = first_cursor + keys[first_item + i]
        order[first_item + cursor[slot]] = i
        cursor[slot] += 1


_counting_sort = KernelFamily(_counting_sort_kernel, outputs=("offsets", "order", "cursor"))


def counting_sort(keys: jax.Array, num_keys: int) -> tuple[jax.Array, jax.Array]:
    """Stable sort of each row of int32 ``keys`` ``(B, N)``, values in ``[0, num_keys)``.

    Returns ``(offsets (B, num_keys + 1), order (B, N))``, int32: row ``b``'s items with key
    ``k`` are ``order[b, offsets[b, k]:offsets[b, k + 1]]``, in increasing order. On CPU a serial
    counting sort in Warp is ~20x faster than XLA's comparison sort for a million items;
    elsewhere ``argsort``. Not differentiable.
    """
    num_rows, num_items = keys.shape
    if jax.default_backend() != "cpu":
        order = jnp.argsort(keys, axis=1, stable=True).astype(jnp.int32)
        bounds = jnp.arange(num_keys + 1, dtype=jnp.int32)
        offsets = jax.vmap(lambda row: jnp.searchsorted(row, bounds))(jnp.take_along_axis(keys, order, axis=1))
        return offsets.astype(jnp.int32), order
    shapes = {"offsets": (num_rows * (num_keys + 1),), "order": (num_rows * num_items,), "cursor": (max(num_rows * num_keys, 1),)}
    offsets, order, _ = _counting_sort(jnp.int32)(keys.reshape(-1), num_items, num_keys, launch=(num_rows,), shapes=shapes)
    return offsets.reshape(num_rows, -1), order.reshape(num_rows, num_items)


# ---------------------------------------------------------------------------------------------
# Morton order.


@wp.func
@no_type_check
def _spread_bits(x: wp.int32):
    """The 10 low bits of ``x`` moved to every third bit (for a 30-bit Morton code)."""
    v = wp.uint32(x) & wp.uint32(0x3FF)
    v = (v | (v << wp.uint32(16))) & wp.uint32(0x030000FF)
    v = (v | (v << wp.uint32(8))) & wp.uint32(0x0300F00F)
    v = (v | (v << wp.uint32(4))) & wp.uint32(0x030C30C3)
    v = (v | (v << wp.uint32(2))) & wp.uint32(0x09249249)
    return v


@wp.func
@no_type_check
def _cell(x: float, low: float, scale: float):
    return wp.int32(wp.clamp((x - low) * scale, 0.0, 1023.0))


@wp.kernel
@no_type_check
def _morton_kernel(
    points: wp.array(dtype=wp.vec3), box: wp.array(dtype=wp.float32), offset: wp.int32, keys_out: wp.array(dtype=wp.int32),
    order_out: wp.array(dtype=wp.int32),
):  # fmt: skip
    """Morton code of each point on a 1024^3 grid over ``box`` = (low corner, 1023 / size) (non-finite: 0)."""
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    code = wp.uint32(0)
    if wp.isfinite(p):
        code = _spread_bits(_cell(p[0], box[0], box[3]))
        code = code | (_spread_bits(_cell(p[1], box[1], box[3])) << wp.uint32(1))
        code = code | (_spread_bits(_cell(p[2], box[2], box[3])) << wp.uint32(2))
    keys_out[i] = wp.int32(code)
    order_out[i] = i


@wp.kernel
@no_type_check
def _box_kernel(points: wp.array(dtype=wp.vec3), box: wp.array(dtype=wp.float32)):
    """One thread: the Morton box (low corner, 1023 / largest side) of finite ``points``."""
    low = wp.vec3(FLOAT32_MAX, FLOAT32_MAX, FLOAT32_MAX)
    high = -low
    for i in range(points.shape[0]):
        p = points[i]
        if wp.isfinite(p):
            low = wp.min(low, p)
            high = wp.max(high, p)
    size = wp.max(wp.max(high[0] - low[0], high[1] - low[1]), high[2] - low[2])
    if not (size > 0.0):
        low = wp.vec3(0.0, 0.0, 0.0)
        size = 1.0
    box[0] = low[0]
    box[1] = low[1]
    box[2] = low[2]
    box[3] = 1023.0 / size


@wp.kernel
@no_type_check
def _identity_kernel(offset: wp.int32, order_out: wp.array(dtype=wp.int32)):
    _, t = wp.tid()
    order_out[t + offset] = t + offset


def morton_order(points, keys, order) -> None:
    """Fill ``order`` with the permutation that sorts ``points`` along the Morton curve of their box.

    ``points``: ``(N,)`` vec3; ``keys``/``order``: int32 scratch of length ``2 N`` (Warp's radix
    sort needs it). Non-finite points come first (code 0).
    """
    num = points.shape[0]
    box = wp.empty(4, dtype=wp.float32, device=points.device)
    wp.launch(_box_kernel, dim=1, inputs=[points], outputs=[box], device=points.device)
    launch_in_chunks(_morton_kernel, 1, num, [points, box], [keys, order])
    wp.utils.radix_sort_pairs(keys, order, num)


def query_order(points32, keys, order) -> None:
    """Fill ``order`` with a permutation of the points that visits them in Morton order on CPU.

    Neighbouring queries then walk the same tree nodes while they are in cache (1.5-3x faster on
    CPU for a million points) and the search's warm start is close. On CUDA the order is the
    identity (the sort is not measured there yet). ``keys``/``order`` as in :func:`morton_order`.
    """
    if points32.device.is_cpu:
        morton_order(points32, keys, order)
    else:
        launch_in_chunks(_identity_kernel, 1, points32.shape[0], [], [order])


# ---------------------------------------------------------------------------------------------
# Meshes.


@wp.func
@no_type_check
def mesh_id(words: wp.array(dtype=wp.uint32)):
    """The ``uint64`` mesh id stored as (low, high) uint32 words (the JAX handle format)."""
    return wp.uint64(words[0]) | (wp.uint64(words[1]) << wp.uint64(32))


def mesh_words(mesh: wp.Mesh) -> wp.array:
    """``mesh``'s id as (low, high) uint32 words, a ``(2,)`` Warp array on the mesh's device."""
    words = np.array([mesh.id & 0xFFFFFFFF, mesh.id >> 32], dtype=np.uint32)
    return wp.array(words, dtype=wp.uint32, device=mesh.device)


def build_mesh(vertices, faces_flat, *, winding_number: bool, device) -> wp.Mesh:
    """A ``wp.Mesh`` on ``device`` from float32 ``(V, 3)`` vertices and flat int32 indices.

    ``vertices``/``faces_flat`` may be NumPy arrays (copied to ``device``) or Warp arrays (used
    in place; they must outlive the mesh). The mesh's id is live (:func:`is_live_mesh`) until
    it is freed.
    """
    if not isinstance(vertices, wp.array):
        vertices = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    if not isinstance(faces_flat, wp.array):
        faces_flat = wp.array(np.ascontiguousarray(faces_flat, np.int32), dtype=wp.int32, device=device)
    mesh = wp.Mesh(points=vertices, indices=faces_flat, support_winding_number=winding_number)
    _LIVE_MESH_IDS.add(mesh.id)
    # Runs when the mesh is collected, before Warp frees it, so a new mesh at the same address
    # is registered after the old one left.
    weakref.finalize(mesh, _LIVE_MESH_IDS.discard, mesh.id)
    return mesh


# The ids of the meshes build_mesh made that are not freed yet. A mesh handle is ordinary data
# (``mesh_words``, a pytree leaf): ``jax.tree.map`` over a MeshBVH, or one rebuilt from its fields,
# forges one, and Warp dereferences whatever id it is given.
_LIVE_MESH_IDS: set[int] = set()


def is_live_mesh(words: wp.array) -> bool | None:
    """Whether the ``(2,)`` uint32 ``words`` of a handle name a mesh that is alive.

    ``None`` where they cannot be read from here: on a CUDA device while a graph is captured
    (the check would have to synchronise; the searches that take a handle are never captured,
    see ``runs_on_host`` in ``warp_ffi._wrap.CallableFamily``). Elsewhere the words are read on the host (a copy of
    8 bytes on CUDA).
    """
    device = words.device
    if device is not None and not device.is_cpu and device.is_capturing:
        return None
    low, high = (int(word) for word in words.numpy())
    return (low | high << 32) in _LIVE_MESH_IDS


# The face id a search of a handle that is not live reports for every query (a miss is -1).
DEAD_MESH_FACE = -2


def fill_outputs(outputs, values) -> None:
    """Fill each Warp output array with its value (what a search reports for a dead handle)."""
    for array, value in zip(outputs, values):
        array.fill_(value)


@contextlib.contextmanager
def mesh_in_call(vertices32: wp.array, faces_flat: wp.array, *, winding_number: bool):
    """A ``wp.Mesh`` built from an FFI call's buffers, with its words: ``with ... as (mesh, words)``.

    The mesh is freed when the call returns; on CUDA the stream is synchronised first, so no
    launch that reads the mesh is still running.
    """
    device = vertices32.device
    assert device is not None  # only annotation arrays (no data) have no device
    mesh = build_mesh(vertices32, faces_flat, winding_number=winding_number, device=device)
    try:
        yield mesh, mesh_words(mesh)
    finally:
        if not device.is_cpu:
            wp.synchronize_stream(wp.get_stream(device))
