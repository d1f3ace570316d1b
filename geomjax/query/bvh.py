"""A reusable BVH over a triangle mesh (Warp ``wp.Mesh``) and the nearest-face search.

Build once with :func:`build_bvh`, pass the :class:`MeshBVH` to queries (inside ``jax.jit`` too),
and :meth:`MeshBVH.refit` it when the vertices move during an optimization. The pure-JAX
brute-force references of the searches (all points against all faces, for small meshes and as
the parity reference of the Warp path) live here too, with the mesh-input checks and the
orientation repair shared by the ray, SDF and voxel queries.

Interface for Warp kernels (``warp_ffi``): a kernel receives ``bvh.mesh_words`` (a uint32
``(2,)`` array input, so ``jit`` does not recompile per mesh) and turns it into the ``uint64``
mesh id with the Warp function ``warp_ffi.bvh.mesh_id(words)``. The BVH's faces are
``bvh.faces`` in the same order (face ids index both), its vertices are ``bvh.vertices`` rounded
to float32.
"""

from __future__ import annotations

import functools
import weakref

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int, UInt32

from .._blocking import map_query_blocks, query_block_size
from .._errors import checked_pure_callback, raises_documented_errors, runtime_check
from .._geometry import closest_point_on_triangle
from .._validate import (
    as_float32,
    as_float_array,
    as_index_array,
    check_bool,
    check_index_range,
    check_real_scalar,
    check_same_device,
    check_same_dtype,
    is_array,
)

__all__ = [
    "MeshBVH",
    "build_bvh",
    "closest_faces",
    "closest_faces_brute_force",
    "checked_mesh",
    "checked_query_points",
    "consistently_oriented_faces",
    "finite_vertices",
    "queries_in_working_dtype",
    "replayed",
    "sliver_faces",
]

FLOAT32_MAX = float(np.finfo(np.float32).max)
SLIVER_RATIO = 1e-6  # Warp's rule: |AB x AC| / (|AB|^2 + |AC|^2 + |BC|^2) below this is a sliver


class _WarpMeshRef:
    """Static, non-owning reference to the ``wp.Mesh`` of a :class:`MeshBVH`.

    The mesh is owned by the ``mesh_words`` buffer (see ``warp_ffi.bvh.mesh_handle``); this weak
    reference only serves :meth:`MeshBVH.refit` and :attr:`MeshBVH.warp_mesh`. All references
    compare equal, so ``jit`` caches do not depend on which mesh a :class:`MeshBVH` holds (that
    is data: ``mesh_words``), and a cache entry does not keep a mesh alive.
    """

    def __init__(self, mesh):
        self._ref = weakref.ref(mesh)

    def __call__(self):
        return self._ref()

    def __eq__(self, other):
        return isinstance(other, _WarpMeshRef)

    def __hash__(self):
        return hash(_WarpMeshRef)


class MeshBVH(eqx.Module):
    """A triangle-mesh BVH (Warp ``wp.Mesh``) usable across calls and inside ``jax.jit``.

    Made by :func:`build_bvh`. A pytree with three array leaves and static flags:

    * ``vertices`` ``(V, 3)`` float32/float64: the geometry that queries replay in JAX, so
      results are differentiable with respect to it (and computed in its dtype);
    * ``faces`` ``(F, 3)`` int32: the triangles, in the order of the BVH's face ids;
    * ``mesh_words`` ``(2,)`` uint32: the Warp mesh id, and the owner of the Warp mesh (a
      zero-copy view of a Warp array that references it). The mesh lives as long as this buffer,
      including while a dispatched computation still reads it; ray casts use it;
    * ``winding_number`` (static): whether the BVH supports winding-number queries;
    * ``closest_tree``: a tuple of arrays, the oriented-box tree that closest-point searches use
      (tighter than Warp's axis-aligned boxes around curved surfaces; see ``warp_ffi._obb_tree``),
      or ``None`` when the MeshBVH only serves ray casts.

    A MeshBVH can be passed to a jitted function as an argument (no retrace for a new mesh of
    the same size: the mesh id is data) or closed over.

    Example:
        >>> import jax.numpy as jnp
        >>> from geomjax import build_bvh
        >>> vertices = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> faces = jnp.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=jnp.int32)
        >>> bvh = build_bvh(vertices, faces)
        >>> bvh.faces.shape, bvh.mesh_words.dtype
        ((4, 3), dtype('uint32'))
        >>> moved = bvh.refit(vertices * 2)
        >>> print(float(moved.vertices.max()))
        2.0
    """

    vertices: Float[Array, "num_vertices 3"]
    faces: Int[Array, "num_faces 3"]
    mesh_words: UInt32[Array, "2"]
    winding_number: bool = eqx.field(static=True)
    _mesh: _WarpMeshRef = eqx.field(static=True)
    closest_tree: tuple | None = None

    @property
    def warp_mesh(self):
        """The underlying ``wp.Mesh`` (float32 points, faces oriented as described in build_bvh)."""
        return self._mesh()

    @raises_documented_errors
    def refit(self, vertices: Float[Array, "num_vertices 3"]) -> MeshBVH:
        """A MeshBVH for moved ``vertices`` (same topology), refitting the Warp BVH in place.

        Eager (``vertices`` must be concrete, with the shape, dtype and device of the current
        ones, finite and within the float32 range). The Warp mesh keeps its id and memory, so a
        jitted function taking the result does not recompile. The old MeshBVH shares the refitted
        BVH: do not query it afterwards, and refit only once computations that use the old
        geometry have been consumed (in an optimization loop the new vertices depend on them, so
        this holds).

        Raises:
            TypeError: non-float or traced ``vertices``, or a dtype different from the BVH's.
            ValueError: a different shape, non-finite values or values beyond float32.
        """
        vertices = as_float_array("vertices", vertices)
        check_same_dtype("bvh.vertices", self.vertices, "vertices", vertices)
        check_same_device("bvh.vertices", self.vertices, "vertices", vertices)
        if vertices.shape != self.vertices.shape:
            raise ValueError(f"refit: vertices must have the BVH's shape {tuple(self.vertices.shape)}, got {tuple(vertices.shape)}")
        host = _concrete_vertices("MeshBVH.refit", vertices)
        from warp_ffi.bvh import closest_tree, refit_mesh

        refit_mesh(self._mesh(), host)
        tree = closest_tree(host, np.asarray(self.faces).reshape(-1), _warp_device(vertices))
        return MeshBVH(vertices, self.faces, self.mesh_words, self.winding_number, self._mesh, tree)


@raises_documented_errors
def build_bvh(vertices: Float[Array, "num_vertices 3"], faces: Int[Array, "num_faces 3"], *, winding_number: bool = False) -> MeshBVH:
    """Build a Warp BVH (``wp.Mesh``) over a triangle mesh, once, eagerly.

    The BVH lives on the device of ``vertices`` (CPU or CUDA) and is float32 (Warp's meshes are):
    searches run in float32 and the answers are re-measured in the vertices' dtype (see
    :func:`closest_faces`).

    Args:
        vertices: ``(V, 3)`` float32 or float64, ``V >= 1``, concrete (not traced), finite and
            within the float32 range.
        faces: ``(F, 3)`` (or flat ``(3 F,)``) int32/int64 indices into ``vertices``,
            ``F >= 1``, on the same device.
        winding_number: build Warp's winding-number support (``support_winding_number=True``)
            for inside/outside tests of open or imperfect meshes. The Warp mesh then uses faces
            oriented consistently (:func:`consistently_oriented_faces`: each connected piece
            takes the orientation of the majority of its faces), so a few flipped faces do not
            corrupt the winding number; ``bvh.faces`` keeps the input orientation and face ids
            are unchanged.

    Returns:
        A :class:`MeshBVH`.

    Raises:
        TypeError: non-float vertices, non-integer faces, a non-bool ``winding_number``, or
            traced arrays (build the BVH outside ``jax.jit`` and pass it in).
        ValueError: bad shapes, no vertices or faces, indices out of range, non-finite vertices
            or vertices beyond the float32 range.
        ImportError: warp-lang is not installed.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import build_bvh
        >>> from geomjax.query.bvh import closest_faces
        >>> vertices = jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
        >>> faces = jnp.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], dtype=jnp.int32)
        >>> bvh = build_bvh(vertices, faces)
        >>> print(np.asarray(closest_faces(bvh, jnp.array([[0.2, 0.2, -1.0], [1.0, 1.0, 1.0], [5.0, 5.0, 5.0]]), 3.0)))
        [ 0  3 -1]
    """
    winding_number = check_bool("winding_number", winding_number)
    vertices, faces = checked_mesh("build_bvh", vertices, faces, concrete=True)
    host_vertices = _concrete_vertices("build_bvh", vertices)
    host_faces = np.asarray(faces)
    from warp_ffi.bvh import build_mesh, closest_tree, mesh_handle

    device = _warp_device(vertices)
    # The tree takes the faces as given (orientation does not matter to a closest-point search).
    tree = closest_tree(host_vertices, host_faces.reshape(-1), device)
    if winding_number:
        host_faces = _oriented_faces_numpy(host_faces)
    mesh = build_mesh(host_vertices, host_faces.reshape(-1), winding_number=winding_number, device=device)
    return MeshBVH(vertices, faces, mesh_handle(mesh), winding_number, _WarpMeshRef(mesh), tree)


def _warp_device(array: jax.Array):
    """The Warp device of a (single-device) JAX array."""
    import warp

    return warp.device_from_jax(next(iter(array.devices())))


def closest_faces(bvh: MeshBVH, points: Float[Array, "*batch 3"], max_distance: float | None = None) -> Int[Array, "*batch"]:
    """Nearest face of each point by BVH search (no gradient): int32 ids, ``-1`` = none in range.

    The answer is the face at minimum distance among all faces (degenerate ones included),
    ties going to the lowest face index, exactly as a brute-force search in the dtype of
    ``bvh.vertices`` (:func:`closest_faces_brute_force`) would give it, for float32 and
    float64: a float32 search of the BVH's oriented-box tree gives a first face, every face
    within that distance (plus a ``2**-16`` relative pad that covers float32 rounding) is
    enumerated with conservative box bounds and measured again in the vertices' dtype, with
    :func:`closest_point_on_triangle`'s rule. Measurements are made by a Warp kernel, so a
    near-tie (distances equal to rounding) may resolve differently from the JAX brute force.

    Args:
        bvh: a :class:`MeshBVH`.
        points: ``(..., 3)`` queries with the dtype and device of ``bvh.vertices``. Non-finite
            points get ``-1``.
        max_distance: faces farther than this (measured exactly) are ignored; ``None`` = no
            limit. A finite positive real.

    Returns:
        ``(...)`` int32 face ids.

    Works under ``jit`` and ``vmap`` (queries run sequentially per batch element). Degenerate
    (sliver) faces are searched like any other.

    Raises:
        TypeError: ``bvh`` is not a MeshBVH, non-float ``points`` or a dtype other than the
            vertices', a non-real ``max_distance``.
        ValueError: ``points`` not of shape ``(..., 3)``, a non-positive or non-finite
            ``max_distance``; a ``bvh`` whose faces or search tree are not those build_bvh
            made (indices out of range, leaf ranges that are not build_bvh's, e.g. after
            ``jax.tree.map``; under ``jit`` at run time). Such arrays are never searched.

    Example:
        >>> import jax.numpy as jnp, numpy as np
        >>> from geomjax import build_bvh
        >>> from geomjax.query.bvh import closest_faces
        >>> bvh = build_bvh(jnp.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]]), jnp.array([[0, 1, 2], [1, 3, 2]]))
        >>> print(np.asarray(closest_faces(bvh, jnp.array([[0.1, 0.1, 1.0], [0.9, 0.9, -1.0], [0.5, 0.5, 0.0]]))))
        [0 1 0]
    """
    if not isinstance(bvh, MeshBVH):
        raise TypeError(f"bvh must be a MeshBVH (see build_bvh), got {type(bvh).__name__}")
    points = checked_query_points("points", points, bvh.vertices, vertices_name="mesh vertices")
    limit = _max_distance(max_distance, points.dtype)
    vertices = jax.lax.stop_gradient(bvh.vertices)
    tree, faces, corrupt = _readable_search_arrays(bvh)
    found = search_closest_faces(tree, vertices, faces, points, limit)
    message = (
        "closest_faces: the MeshBVH's faces or search tree are not those build_bvh made (they were modified, e.g. "
        "by jax.tree.map, or taken from another mesh): pass a MeshBVH made by build_bvh"
    )
    return runtime_check(found, corrupt, message, ValueError)


def _readable_search_arrays(bvh: MeshBVH) -> tuple[tuple, jax.Array, jax.Array]:
    """``(tree, faces, corrupt)``: a MeshBVH's search arrays, safe for the Warp kernels to read.

    They are pytree leaves, so ``jax.tree.map`` or a MeshBVH rebuilt from other fields can
    change them, and the kernels index memory with them. When any index is out of range or the
    tree's leaf ranges are not the consecutive, non-empty ranges that build_bvh makes,
    ``corrupt`` is true and the arrays are replaced by zeros (every leaf empty: nothing is
    found, nothing is read out of bounds), so the caller can raise instead of crashing.
    """
    faces = bvh.faces
    num_faces, num_vertices = faces.shape[0], bvh.vertices.shape[0]
    corrupt = jnp.any((faces < 0) | (faces >= num_vertices))
    if bvh.closest_tree is None:
        # A MeshBVH made for ray casts only carries no tree: one is built in the call.
        safe_faces = jnp.where(corrupt, 0, faces)
        return (bvh_vertices32(jax.lax.stop_gradient(bvh.vertices)), safe_faces.reshape(-1)), safe_faces, corrupt
    from warp_ffi.bvh import tree_shapes

    nodes, leaf_starts, sorted_faces, corners = bvh.closest_tree
    expected = tree_shapes(num_faces)
    found = {"nodes": nodes.shape[:1], "leaf_starts": leaf_starts.shape, "faces": sorted_faces.shape, "corners": corners.shape[:1]}
    if any(tuple(found[name]) != tuple(shape) for name, shape in expected.items()):
        raise ValueError(
            f"closest_faces: the MeshBVH's search tree does not fit its {num_faces} faces (arrays of shapes {found}): pass a MeshBVH made by build_bvh"
        )
    steps = jnp.diff(leaf_starts)
    corrupt = corrupt | (leaf_starts[0] != 0) | (leaf_starts[-1] != num_faces) | jnp.any(steps <= 0)
    corrupt = corrupt | jnp.any((sorted_faces < 0) | (sorted_faces >= num_faces))
    tree = (nodes, jnp.where(corrupt, 0, leaf_starts), jnp.where(corrupt, 0, sorted_faces), corners)
    return tree, jnp.where(corrupt, 0, faces), corrupt


def closest_face_tree(op_name: str, vertices: jax.Array, faces: np.ndarray) -> tuple:
    """The oriented-box tree of :func:`build_bvh` alone, for closest-face searches only (no Warp
    mesh: what the eager host algorithms need), on the device of ``vertices``.

    ``vertices`` ``(V, 3)`` concrete, ``faces`` ``(F, 3)`` validated indices. ``ValueError``
    (``op_name``'s) for vertices that are not finite or beyond the float32 range.
    """
    from warp_ffi.bvh import closest_tree

    return closest_tree(_concrete_vertices(op_name, vertices), np.asarray(faces).reshape(-1), _warp_device(vertices))


def search_closest_faces(tree: tuple, vertices: jax.Array, faces: jax.Array, points: jax.Array, limit: float = float("inf")) -> jax.Array:
    """:func:`closest_faces` on an oriented-box ``tree`` of ``(vertices, faces)``, for validated
    ``points`` of the vertices' dtype (``(..., 3)``) and a real ``limit``."""
    shape = points.shape[:-1]
    flat = jax.lax.stop_gradient(points.reshape(-1, 3))
    if flat.shape[0] == 0:
        return jnp.zeros(shape, jnp.int32)
    from warp_ffi.bvh import point_faces

    found, _ = point_faces(
        tree, flat, vertices, faces, jnp.asarray(limit, flat.dtype), _extent(vertices),
        sign_mode="none", exact=True,
    )  # fmt: skip
    return found.reshape(shape)


# ---------------------------------------------------------------------------------------------
# Pure-JAX brute force (the reference of every search).


def sliver_faces(vertices: Float[Array, "num_vertices 3"], faces: Int[Array, "num_faces 3"]) -> jax.Array:
    """Faces that Warp's closest-point queries skip: ``|AB x AC| < 1e-6 (|AB|^2 + |AC|^2 + |BC|^2)``."""
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    ab, ac, bc = b - a, c - a, c - b
    total = jnp.sum(ab * ab + ac * ac + bc * bc, axis=-1)
    area2 = jnp.linalg.norm(jnp.cross(ab, ac), axis=-1)
    return ~((area2 >= SLIVER_RATIO * total) & (total > 0))


@functools.partial(jax.jit, static_argnames=("max_distance", "skip_slivers"))
def closest_faces_brute_force(
    points: Float[Array, "num_points 3"],
    vertices: Float[Array, "num_vertices 3"],
    faces: Int[Array, "num_faces 3"],
    max_distance: float | None = None,
    *,
    skip_slivers: bool = False,
) -> tuple[Int[Array, " num_points"], Float[Array, " num_points"]]:
    """Nearest face of each point over all faces, in pure JAX: ``(face ids, squared distances)``.

    Ties go to the lowest face index; a face farther than ``max_distance`` counts as absent
    (id ``-1``, squared distance ``inf``). With ``skip_slivers`` the faces of
    :func:`sliver_faces` are ignored (Warp's signed queries do the same). Memory is bounded by
    evaluating blocks of points against all faces; O(N F) time: for small meshes and tests.
    Not differentiated (use :func:`closest_point_on_triangle` on the chosen faces).
    """
    points, vertices = jax.lax.stop_gradient(points), jax.lax.stop_gradient(vertices)
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    ignored = sliver_faces(vertices, faces) if skip_slivers else jnp.zeros(faces.shape[0], bool)
    limit = jnp.inf if max_distance is None else max_distance
    itemsize = jnp.dtype(points.dtype).itemsize
    block = query_block_size(points.shape[0], faces.shape[0] * 48 * itemsize)

    def nearest(p):
        closest, _ = closest_point_on_triangle(p[:, None, :], a[None], b[None], c[None])
        d2 = jnp.sum(jnp.square(closest - p[:, None, :]), axis=-1)
        d2 = jnp.where(ignored[None, :] | jnp.isnan(d2), jnp.inf, d2)
        best = jnp.argmin(d2, axis=1).astype(jnp.int32)
        best_d2 = jnp.take_along_axis(d2, best[:, None], axis=1)[:, 0]
        found = jnp.isfinite(best_d2) & (jnp.sqrt(best_d2) <= limit)
        return jnp.stack([jnp.where(found, best, -1).astype(best_d2.dtype), jnp.where(found, best_d2, jnp.inf)], axis=-1)

    if points.shape[0] == 0:
        return jnp.zeros((0,), jnp.int32), jnp.zeros((0,), points.dtype)
    out = map_query_blocks(nearest, (points,), block_size=block)
    return out[:, 0].astype(jnp.int32), out[:, 1]


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def replayed(replay, differentiable, auxiliary, values):
    """``values`` (computed by a kernel, without gradient) with the derivatives of ``replay``.

    ``replay(*differentiable, *auxiliary)`` must recompute ``values`` (a tuple of arrays) in JAX;
    it is only evaluated when derivatives are taken, so the forward pass pays for the kernel
    alone. ``differentiable`` are the float inputs that carry derivatives; ``auxiliary`` (face
    ids, signs) do not. Supports forward and reverse mode (``custom_jvp``).
    """
    del replay, differentiable, auxiliary
    return values


@replayed.defjvp
def _replayed_jvp(replay, primals, tangents):
    differentiable, auxiliary, values = primals
    _, out_tangents = jax.jvp(lambda *x: replay(*x, *auxiliary), differentiable, tangents[0])
    # The primal goes through replayed again, so a derivative of this derivative (a Hessian)
    # differentiates the replay too; returning ``values`` would make it a constant there.
    return replayed(replay, differentiable, auxiliary, values), out_tangents


# ---------------------------------------------------------------------------------------------
# Orientation repair (for winding numbers).


def consistently_oriented_faces(faces: Int[Array, "num_faces 3"]) -> Int[Array, "num_faces 3"]:
    """``faces`` with orientations made consistent across manifold edges (int32).

    Two faces sharing an edge used by exactly two faces are consistent when they traverse it in
    opposite directions. Each connected piece (through such edges) is given the orientation of
    the majority of its faces (ties: that of its lowest-index face); faces of the minority get
    two indices swapped. Non-manifold edges do not connect faces, and a non-orientable piece keeps
    the parity found along a spanning forest. Face ids are unchanged. Computed on the host with
    NumPy (through ``jax.pure_callback`` for traced faces).
    """
    faces = jnp.asarray(faces, jnp.int32)
    if not isinstance(faces, jax.core.Tracer):
        return jnp.asarray(_oriented_faces_numpy(np.asarray(faces)))
    return checked_pure_callback(lambda f: _oriented_faces_numpy(np.asarray(f)), jax.ShapeDtypeStruct(faces.shape, jnp.int32), faces)


def _oriented_faces_numpy(faces: np.ndarray) -> np.ndarray:
    faces = np.asarray(faces, np.int32).reshape(-1, 3)
    flip = _relative_flips(faces)
    if flip is None:
        return faces
    out = faces.copy()
    out[flip, 1], out[flip, 2] = faces[flip, 2], faces[flip, 1]
    return out


def _relative_flips(faces: np.ndarray) -> np.ndarray | None:
    """Faces to flip so each piece agrees with its majority; ``None`` when nothing flips."""
    num_faces = faces.shape[0]
    if num_faces < 2:
        return None
    start = faces.reshape(-1)
    end = np.roll(faces, -1, axis=1).reshape(-1)
    owner = np.repeat(np.arange(num_faces), 3)
    low, high = np.minimum(start, end), np.maximum(start, end)
    forward = start < end
    order = np.lexsort((high, low))
    low, high, forward, owner = low[order], high[order], forward[order], owner[order]
    same_as_next = (low[:-1] == low[1:]) & (high[:-1] == high[1:])
    group_start = np.concatenate([[True], ~same_as_next])
    group_id = np.cumsum(group_start) - 1
    group_size = np.bincount(group_id)
    # Manifold edges: exactly two uses, by two different faces.
    pair = (group_size[group_id[:-1]] == 2) & same_as_next & (owner[:-1] != owner[1:])
    first, second = owner[:-1][pair], owner[1:][pair]
    # Traversing the edge in the same direction means the two faces disagree.
    disagree = forward[:-1][pair] == forward[1:][pair]
    if first.size == 0:
        return None
    u = np.concatenate([first, second])
    v = np.concatenate([second, first])
    s = np.concatenate([disagree, disagree])

    # Minimum-label propagation with pointer jumping; parity = flips relative to the label.
    label = np.arange(num_faces)
    parity = np.zeros(num_faces, bool)
    while True:
        candidate = label[v]
        best = np.full(num_faces, num_faces)
        np.minimum.at(best, u, candidate)
        improve = best[u] == candidate
        improve &= candidate < label[u]
        changed = np.zeros(num_faces, bool)
        if np.any(improve):
            targets = u[improve]
            label[targets] = candidate[improve]
            parity[targets] = parity[v[improve]] ^ s[improve]
            changed[targets] = True
        while True:
            parent = label[label]
            if np.array_equal(parent, label):
                break
            parity = parity ^ parity[label]
            label = parent
        if not np.any(changed):
            break
    flipped = np.bincount(label, weights=parity.astype(float), minlength=num_faces)
    sizes = np.bincount(label, minlength=num_faces)
    majority_flipped = flipped > sizes - flipped
    flip = parity != majority_flipped[label]
    return flip if np.any(flip) else None


# ---------------------------------------------------------------------------------------------
# Input checks shared by the mesh queries.


def checked_query_points(
    name: str, points, vertices: jax.Array, *, op_name: str | None = None, vertices_name: str = "mesh_vertices", same_dtype: bool = True
) -> jax.Array:
    """Query points ``(..., 3)`` of a mesh query, with the device (and, if ``same_dtype``, the
    dtype) of the mesh ``vertices``."""
    points = as_float_array(name, points)
    if same_dtype:
        check_same_dtype(vertices_name, vertices, name, points)
    check_same_device(vertices_name, vertices, name, points)
    if points.ndim < 1 or points.shape[-1] != 3:
        prefix = f"{op_name}: " if op_name else ""
        raise ValueError(f"{prefix}{name} must have shape (..., 3), got {tuple(points.shape)}")
    return points


def queries_in_working_dtype(name: str, points, vertices: jax.Array, *, op_name: str) -> tuple[jax.Array, jax.Array, np.dtype]:
    """Query points ``(..., 3)`` of any real floating dtype, independent of the mesh's, as the
    reference takes them: ``(points, vertices, output dtype)``, points and vertices in the working
    dtype (float64 when both are float64, else float32, the reference's arithmetic) and the
    points' own dtype, which the float outputs are cast back to."""
    checked = checked_query_points(name, as_float32(points, narrower_only=True), vertices, op_name=op_name, same_dtype=False)
    output_dtype = jnp.dtype(points.dtype) if is_array(points) else checked.dtype
    working = jnp.float64 if checked.dtype == jnp.float64 and vertices.dtype == jnp.float64 else jnp.float32
    return checked.astype(working), vertices.astype(working), output_dtype


def finite_vertices(op_name: str, vertices: jax.Array) -> jax.Array:
    """``vertices`` after checking they are all finite (``ValueError``): a NaN vertex would
    otherwise corrupt results far from it (signs, hit records). Concrete arrays are checked now;
    traced ones with ``equinox.error_if`` when the program runs."""
    return runtime_check(vertices, jnp.logical_not(jnp.all(jnp.isfinite(vertices))), f"{op_name}: mesh_vertices must be finite", ValueError)


def checked_mesh(op_name: str, mesh_vertices, mesh_indices, *, concrete: bool = False) -> tuple[jax.Array, jax.Array]:
    """Validate a triangle mesh; return vertices ``(V, 3)`` and int32 faces ``(F, 3)``.

    Vertices: float32/float64 ``(V, 3)``, ``V >= 1``. Indices: int32/int64, ``(F, 3)`` or flat
    with a length that is a positive multiple of 3, same device, values in ``[0, V)``. The range
    is checked on the host when the indices are concrete (``ValueError``); traced indices are
    checked with ``equinox.error_if`` (a runtime error) and clamped, so no kernel ever reads out
    of bounds. With ``concrete``, traced arrays are a ``TypeError``.
    """
    vertices = as_float_array("mesh_vertices", mesh_vertices)
    indices = as_index_array("mesh_indices", mesh_indices)
    check_same_device("mesh_vertices", vertices, "mesh_indices", indices)
    if concrete and (isinstance(vertices, jax.core.Tracer) or isinstance(indices, jax.core.Tracer)):
        raise TypeError(f"{op_name} needs concrete arrays (it runs eagerly): build it outside jax.jit and pass it in")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or vertices.shape[0] == 0:
        raise ValueError(f"{op_name}: mesh_vertices must have shape (V, 3) with V >= 1, got {tuple(vertices.shape)}")
    if not ((indices.ndim == 2 and indices.shape[1] == 3) or indices.ndim == 1) or indices.size == 0 or indices.size % 3:
        raise ValueError(f"{op_name}: mesh_indices must have shape (F, 3) or (3 F,) with F >= 1, got {tuple(indices.shape)}")
    faces = indices.reshape(-1, 3)
    num_vertices = vertices.shape[0]
    return vertices, check_index_range(faces, num_vertices, f"{op_name}: mesh_indices must lie in [0, {num_vertices})")


def bvh_vertices32(vertices: jax.Array) -> jax.Array:
    """Float32 vertices for a BVH built inside a query: non-finite or out-of-range values become 0.

    A NaN or infinite coordinate would give Warp's builder non-finite boxes; zero keeps the BVH
    well formed while the JAX replay (on the real vertices) still reports NaN for those faces.
    """
    v32 = jax.lax.stop_gradient(vertices).astype(jnp.float32)
    return jnp.where(jnp.isfinite(v32), v32, 0)


def checked_live_handle(face_ids: jax.Array, op_name: str) -> jax.Array:
    """``face_ids`` of a Warp search of a MeshBVH's mesh handle, after checking the handle was live.

    The handle (``mesh_words``) is data, so a MeshBVH rebuilt from its fields or mapped with
    ``jax.tree.map`` can name a freed or never-built mesh; warp_ffi does not search such a
    handle and reports ``DEAD_MESH_FACE`` for every query, which becomes ``op_name``'s
    ``ValueError`` here (at run time under ``jit``).
    """
    from warp_ffi.bvh import DEAD_MESH_FACE

    message = (
        f"{op_name}: the MeshBVH's Warp mesh is not alive (it was freed, or the MeshBVH was rebuilt from its "
        "fields, e.g. by jax.tree.map): pass a MeshBVH made by build_bvh"
    )
    return runtime_check(face_ids, jnp.any(face_ids == DEAD_MESH_FACE), message, ValueError)


def _concrete_vertices(op_name: str, vertices: jax.Array) -> np.ndarray:
    if isinstance(vertices, jax.core.Tracer):
        raise TypeError(f"{op_name} needs concrete vertices (it runs eagerly): call it outside jax.jit")
    host = np.asarray(vertices)
    if not np.all(np.isfinite(host)) or np.max(np.abs(host), initial=0.0) > FLOAT32_MAX:
        raise ValueError(f"{op_name}: vertices must be finite and within the float32 range (the Warp BVH is float32)")
    return host.astype(np.float32)


def _max_distance(value, dtype) -> float:
    if value is None:
        return float("inf")
    return check_real_scalar("max_distance", value, dtype, positive=True)


def _extent(vertices: jax.Array) -> jax.Array:
    """Largest finite coordinate magnitude: sets the search pads (not differentiated)."""
    v = jnp.abs(jax.lax.stop_gradient(vertices))
    return jnp.max(jnp.where(jnp.isfinite(v), v, 0))
