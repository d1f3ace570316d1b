"""Host-side entry points: NumPy in, NumPy (or a prepared structure) out, run eagerly.

Everything else in ``warp_ffi`` is a JAX function (JAX arrays in and out, traceable under
``jit`` and ``vmap``). The functions here run eagerly instead, as plain Warp launches on
``wp.array`` copies, because what they return is data dependent in size or is a structure that
JAX calls then reuse:

* Mesh preparation for the BVH searches (``warp_ffi.bvh`` re-exports these): :func:`closest_tree`
  (the oriented-box tree as JAX arrays), :func:`mesh_handle` (a ``wp.Mesh`` as JAX
  ``mesh_words``), :func:`refit_mesh`; ``warp_ffi._grid.build_mesh`` builds the ``wp.Mesh``.
* Poisson-disk sampling (``warp_ffi.poisson`` re-exports these): :func:`reject_near_accepted`,
  :func:`resolve_conflicts`, :func:`neighbour_lists` and :func:`eliminate`.
* The clustering remesher's :func:`face_geometry`, :func:`nearest_centroids` and
  :class:`CentroidSearch`, :class:`PatchSearch` with :func:`patch_closest_faces`,
  :func:`vertex_plane_terms`, :func:`largest_sagittas`, :func:`relaxation_sums` and
  :func:`overturned_vertices`, and :class:`EdgeGraph` with :func:`grow_forest` (its clusters as
  a shortest-path forest of the edge graph, updated where the seeds changed), re-exported by
  ``warp_ffi.remesh``.

Inputs arrive validated (no checks here).

Poisson-disk sampling. Candidate positions, radii and priorities, and the elimination weights,
are computed by geomjax (shared with its JAX path); Warp does the neighbour searches and the
sequential elimination.

* Neighbour searches use Warp's ``wp.HashGrid`` with cells at least as wide as the largest
  search radius (the caller picks twice as wide), so a query visits at most three cells per
  axis. The table dimensions are clamped by the caller to the cells the points span, and grids
  are cached per (dimensions, device, dtype): creating a 128^3 grid costs more than rebuilding
  it. Queries run in cell order (:func:`cell_order`) so they walk the table nearly in sequence.
  CPU launches are split over the cores with ``launch_in_chunks``; every kernel writes only its
  own items, so no output is shared.
* Conflict tests compare squared distances with the squared radius widened by a relative
  ``widening`` (float32 rounding can then never accept a pair closer than the radius).
* ``eliminate`` runs Yuksel's elimination one sample at a time with an indexed binary max-heap
  on integer weights (ties: lowest index first), in one sequential CPU kernel.

Nearest centroids. Each point looks for its nearest centroid (ties: the lowest centroid index)
among the centroids in the grid cells within ``radius / 2``, then within ``radius``. A found
centroid closer than the search radius times ``1 - 2**-12`` is the nearest of all centroids
(every centroid outside the visited cells is farther than that radius, up to float32 rounding of
the cell assignment, which the margin covers); a point with none that close even within
``radius`` scans all centroids. The answer is therefore always the global nearest centroid, and
``radius`` only sets the speed. The first, small search visits a few cells and settles nearly
every point (a centroidal cell's radius is about 0.6 cluster spacings). Given the previous
labels (Lloyd iterations), a point first measures its previous cluster's moved centroid ``c``:
when it is closer than half the distance ``g`` from ``c`` to any other centroid (times the
margin), no other centroid can be as close (``|p - c_j| >= g - |p - c|``), and the search is
skipped; that settles most points of a centroidal layout with one distance. ``g`` is the
nearest other centroid within ``radius``, or ``radius`` if none is (a lower bound either way).
With many points per centroid (``NEIGHBOUR_LIST_MIN_POINTS``) each centroid lists instead its
neighbours within ``radius`` by distance, and a point measures only those within ``2 |p - c|``
of ``c`` (any centroid as close as ``c`` is: ``|c_j - c| <= |c_j - p| + |p - c|``): that also
settles the points near a cluster's border, where the gap test fails, without a grid search.
"""

from __future__ import annotations

import functools
import threading
from typing import Any, no_type_check

import jax
import numpy as np

from ._grid import mesh_words
from ._obb_tree import TREE_ARRAYS, build_tree
from ._wrap import WARP_SCALAR, Overloads, host_values, launch_in_chunks, launch_on_host, scalars, vectors
from ._wrap import warp as wp
from .closest import triangle_distance_sq

wp.set_module_options({"enable_backward": False})

__all__ = [
    "closest_tree", "mesh_handle", "refit_mesh",
    "reject_near_accepted", "resolve_conflicts", "neighbour_lists", "eliminate",
    "nearest_centroids", "CentroidSearch", "PatchSearch", "patch_closest_faces", "face_geometry", "vertex_plane_terms", "largest_sagittas", "relaxation_sums", "overturned_vertices", "flip_rules", "corner_terms", "cluster_seeds", "fold_heights", "EdgeGraph", "grow_forest",
]  # fmt: skip


def _int32_array(values: np.ndarray, device) -> wp.array:
    """A flat int32 ``wp.array`` copy of integer ``values`` on ``device``."""
    return wp.array(np.ascontiguousarray(values, np.int32).reshape(-1), dtype=wp.int32, device=device)


def _host_view(values: np.ndarray, dtype, device: str) -> wp.array:
    """A ``wp.array`` of C-contiguous host ``values`` (of ``dtype``'s NumPy type): on the CPU
    their memory itself, not a copy (a copy costs 10 us even for a few hundred rows; the array
    holds a reference to ``values``), on another device a copy."""
    return wp.array(values, dtype=dtype, device=device, copy=not wp.get_device(device).is_cpu)


class _HostArguments:
    """Kernel arguments made from host data, for launches on ``device``: on the CPU the NumPy
    arrays themselves, as ``(values, dtype)`` pairs (launches replayed by
    ``warp_ffi._wrap.launch_in_chunks`` and ``launch_on_host``), elsewhere ``wp.array`` copies."""

    def __init__(self, device: str):
        self.device = device
        self.on_cpu = wp.get_device(device).is_cpu

    def array(self, values: np.ndarray, dtype) -> Any:
        """An argument of C-contiguous ``values`` of Warp type ``dtype`` (one row per element)."""
        return (values, dtype) if self.on_cpu else wp.array(values, dtype=dtype, device=self.device)

    def empty(self, size: int, dtype) -> Any:
        """An output of ``size`` elements of the Warp scalar ``dtype``."""
        return (np.empty(size, wp.dtype_to_numpy(dtype)), dtype) if self.on_cpu else wp.empty(size, dtype=dtype, device=self.device)

    def launch(self, kernel, dim, args: list) -> None:
        """One launch of ``kernel`` over ``dim`` with these arguments."""
        if self.on_cpu:
            launch_on_host(kernel, dim, args)
        else:
            wp.launch(kernel, dim=dim, inputs=args, device=self.device)


# ---------------------------------------------------------------------------------------------
# Mesh preparation.


def mesh_handle(mesh: wp.Mesh) -> jax.Array:
    """The JAX ``mesh_words`` of ``mesh``: uint32 ``(2,)``, zero-copy, keeping ``mesh`` alive.

    The words live in a Warp array that holds a reference to the mesh, shared with JAX without a
    copy: the mesh lives as long as that buffer, and XLA keeps an input buffer alive until every
    computation that reads it has finished, so a handle dropped while a dispatched computation
    still uses it is never freed too early.
    """
    words = mesh_words(mesh)
    # The reference that ties the mesh's lifetime to the JAX buffer: an ad-hoc attribute, which
    # Warp arrays accept at runtime but their type does not declare.
    words.geomjax_mesh = mesh  # type: ignore[attr-defined]
    handle = jax.dlpack.from_dlpack(words)
    if handle.unsafe_buffer_pointer() != words.ptr:  # pragma: no cover - JAX copied: no keep-alive
        raise RuntimeError("could not share the Warp mesh handle with JAX without a copy")
    return handle


def refit_mesh(mesh: wp.Mesh, vertices: np.ndarray) -> None:
    """Move the mesh's vertices (float32 ``(V, 3)``) and refit its BVH in place (same id)."""
    mesh.points.assign(wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=mesh.device))
    mesh.refit()


def closest_tree(vertices, faces_flat, device) -> tuple:
    """The oriented-box tree of a mesh as JAX arrays (``warp_ffi._obb_tree.TREE_ARRAYS`` order).

    ``vertices``: float32 ``(V, 3)``, ``faces_flat``: int32 ``(3 F,)`` NumPy arrays; the arrays
    are built on ``device`` and shared with JAX without a copy.
    """
    vertices = wp.array(np.ascontiguousarray(vertices, np.float32), dtype=wp.vec3, device=device)
    faces_flat = _int32_array(faces_flat, device)
    arrays = build_tree(vertices, faces_flat)
    return tuple(jax.dlpack.from_dlpack(arrays[name]) for name in TREE_ARRAYS)


# ---------------------------------------------------------------------------------------------
# Hash grids.

# Grids are reused across calls; the lock keeps two Python threads from rebuilding one grid
# while the other queries it.
GRID_LOCK = threading.RLock()


@functools.lru_cache(maxsize=8)
def _cached_grid(dims: tuple[int, int, int], device: str, dtype) -> wp.HashGrid:
    return wp.HashGrid(*dims, device=device, dtype=dtype)


def cell_order(points: np.ndarray, cell_width: float) -> np.ndarray:
    """A permutation listing the points cell by cell (cache-friendly query and storage order)."""
    cells = np.floor(points / cell_width).astype(np.int64)
    cells -= cells.min(axis=0, initial=0)
    span = cells.max(axis=0, initial=0) + 1
    return np.argsort(cells[:, 0] + span[0] * (cells[:, 1] + span[1] * cells[:, 2]))


def hash_grid(points: wp.array, cell_width: float, dims: tuple[int, int, int]) -> wp.HashGrid:
    """A cached ``wp.HashGrid`` of ``dims`` rebuilt over ``points`` (call under ``GRID_LOCK``)."""
    dtype = wp.float64 if points.dtype == wp.vec3d else wp.float32
    grid = _cached_grid(tuple(int(d) for d in dims), str(points.device), dtype)
    grid.build(points, cell_width)
    return grid


# ---------------------------------------------------------------------------------------------
# Dart throwing.


@wp.kernel
@no_type_check
def _reject_kernel(
    grid: wp.uint64, accepted: wp.array(dtype=wp.vec3), candidates: wp.array(dtype=wp.vec3), radius: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32), widening: wp.float32, offset: wp.int32, alive: wp.array(dtype=wp.int32),
):  # fmt: skip
    _, t = wp.tid()
    i = order[t + offset]
    p = candidates[i]
    r = radius[i]
    limit = r * r * widening
    query = wp.hash_grid_query(grid, p, r)
    j = int(0)
    keep = int(1)
    while wp.hash_grid_query_next(query, j):
        d = accepted[j] - p
        if wp.dot(d, d) < limit:
            keep = 0
            break
    alive[i] = keep


@wp.kernel
@no_type_check
def _conflict_kernel(
    grid: wp.uint64, candidates: wp.array(dtype=wp.vec3), radius: wp.array(dtype=wp.float32), priority: wp.array(dtype=wp.uint32),
    index: wp.array(dtype=wp.int32), widening: wp.float32, offset: wp.int32, keep: wp.array(dtype=wp.int32),
):  # fmt: skip
    _, t = wp.tid()
    i = t + offset
    keep[i] = 0
    p = candidates[i]
    r = radius[i]
    rank = priority[i]
    own = index[i]
    # A conflicting neighbour is within min(r, r_j) <= r, so querying with r finds all of them.
    query = wp.hash_grid_query(grid, p, r)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        if j == i:
            continue
        m = wp.min(r, radius[j])
        d = candidates[j] - p
        if wp.dot(d, d) < m * m * widening:
            other = priority[j]
            if other > rank or (other == rank and index[j] > own):
                return
    keep[i] = 1


def reject_near_accepted(
    accepted: np.ndarray, candidates: np.ndarray, radius: np.ndarray, cell_width: float,
    dims: tuple[int, int, int], widening: float, device: str,
) -> np.ndarray:  # fmt: skip
    """``(B,)`` bool: candidates with no accepted sample within their own radius (widened)."""
    num = candidates.shape[0]
    if accepted.shape[0] == 0:
        return np.ones(num, bool)
    accepted_wp: wp.array = wp.array(accepted, dtype=wp.vec3, device=device)
    candidates_wp: wp.array = wp.array(candidates, dtype=wp.vec3, device=device)
    radius_wp: wp.array = wp.array(radius, dtype=wp.float32, device=device)
    # Queries in cell order walk the grid's table nearly sequentially.
    order: wp.array = wp.array(cell_order(candidates, cell_width).astype(np.int32), dtype=wp.int32, device=device)
    alive = wp.empty(num, dtype=wp.int32, device=device)
    with GRID_LOCK:
        grid = hash_grid(accepted_wp, cell_width, dims)
        inputs = [grid.id, accepted_wp, candidates_wp, radius_wp, order, widening]
        launch_in_chunks(_reject_kernel, 1, num, inputs, [alive])
    return alive.numpy().astype(bool)


def resolve_conflicts(
    candidates: np.ndarray, radius: np.ndarray, priority: np.ndarray, index: np.ndarray, cell_width: float,
    dims: tuple[int, int, int], widening: float, device: str,
) -> np.ndarray:  # fmt: skip
    """``(B,)`` bool: candidates with no conflicting candidate of higher priority.

    Two candidates conflict when closer than ``min(r_i, r_j)`` (widened); of a conflicting pair
    the higher ``priority`` survives (ties: the higher ``index``), so the survivors are
    independent.
    """
    num = candidates.shape[0]
    # Candidates are processed and stored cell by cell.
    order = cell_order(candidates, cell_width)
    candidates_wp: wp.array = wp.array(candidates[order], dtype=wp.vec3, device=device)
    radius_wp: wp.array = wp.array(radius[order], dtype=wp.float32, device=device)
    priority_wp: wp.array = wp.array(priority[order], dtype=wp.uint32, device=device)
    index_wp: wp.array = wp.array(index[order].astype(np.int32), dtype=wp.int32, device=device)
    keep = wp.empty(num, dtype=wp.int32, device=device)
    with GRID_LOCK:
        grid = hash_grid(candidates_wp, cell_width, dims)
        inputs = [grid.id, candidates_wp, radius_wp, priority_wp, index_wp, widening]
        launch_in_chunks(_conflict_kernel, 1, num, inputs, [keep])
    kept = np.empty(num, bool)
    kept[order] = keep.numpy().astype(bool)
    return kept


# ---------------------------------------------------------------------------------------------
# Weighted sample elimination.


@wp.kernel
@no_type_check
def _neighbours_kernel(
    grid: wp.uint64, points: wp.array(dtype=wp.vec3), radius: wp.float32, limit: wp.float32, row_starts: wp.array(dtype=wp.int32),
    capacity: wp.int32, offset: wp.int32, counts: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
):  # fmt: skip
    """Point ``i``'s neighbours (other points with squared distance below ``limit``).

    They are counted, and the first ``capacity`` stored from ``row_starts[i]``, or from
    ``i * capacity`` when ``row_starts`` is empty (a fixed-width table).
    """
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    query = wp.hash_grid_query(grid, p, radius)
    j = int(0)
    count = int(0)
    base = i * capacity
    if row_starts.shape[0] > 0:
        base = row_starts[i]
    while wp.hash_grid_query_next(query, j):
        d = points[j] - p
        if j != i and wp.dot(d, d) < limit:
            if count < capacity:
                columns[base + count] = j
            count += 1
    counts[i] = count


def neighbour_lists(points: np.ndarray, radius: float, limit: float, capacity: int, cell_width: float, dims: tuple[int, int, int], device: str):
    """CSR lists of the other points with squared distance below ``limit`` (``limit >= r^2``).

    One pass stores up to ``capacity`` neighbours per point; only when some point has more does
    a second pass fill exact rows. Returns ``(row_offsets (P + 1,) int64, columns (nnz,)
    int32)``, each row in grid order. Points listed cell by cell (see :func:`cell_order`) run
    several times faster: queries then walk the grid's table and the point array in order.
    """
    num = points.shape[0]
    points_wp: wp.array = wp.array(points, dtype=wp.vec3, device=device)
    counts = wp.empty(num, dtype=wp.int32, device=device)
    slots = wp.empty(num * capacity, dtype=wp.int32, device=device)
    fixed_width = wp.empty(0, dtype=wp.int32, device=device)
    with GRID_LOCK:
        grid = hash_grid(points_wp, cell_width, dims)
        launch_in_chunks(_neighbours_kernel, 1, num, [grid.id, points_wp, radius, limit, fixed_width, capacity], [counts, slots])
        degree = counts.numpy()
        row_offsets = np.zeros(num + 1, np.int64)
        np.cumsum(degree, out=row_offsets[1:])
        if row_offsets[-1] >= 2**31:
            raise ValueError(f"{row_offsets[-1]} neighbour pairs are more than int32 indices allow")
        if degree.max(initial=0) <= capacity:
            table = slots.numpy().reshape(num, capacity)
            return row_offsets, table[np.arange(capacity)[None, :] < degree[:, None]]
        columns = wp.empty(int(row_offsets[-1]), dtype=wp.int32, device=device)
        starts: wp.array = wp.array(row_offsets[:-1].astype(np.int32), dtype=wp.int32, device=device)
        inputs = [grid.id, points_wp, radius, limit, starts, int(degree.max())]
        launch_in_chunks(_neighbours_kernel, 1, num, inputs, [counts, columns])
    return row_offsets, columns.numpy()


@wp.func
@no_type_check
def _ranks_above(weight_a: wp.int32, a: wp.int32, weight_b: wp.int32, b: wp.int32):
    """Heap order: the larger weight first, ties to the lower index (``argmax`` semantics)."""
    return weight_a > weight_b or (weight_a == weight_b and a < b)


@wp.func
@no_type_check
def _sift_down(
    heap: wp.array(dtype=wp.int32), position: wp.array(dtype=wp.int32), weight: wp.array(dtype=wp.int32), start: wp.int32,
    size: wp.int32,
):  # fmt: skip
    i = start
    item = heap[i]
    item_weight = weight[item]
    while 2 * i + 1 < size:
        child = 2 * i + 1
        best = heap[child]
        if child + 1 < size:
            right = heap[child + 1]
            if _ranks_above(weight[right], right, weight[best], best):
                child = child + 1
                best = right
        if not _ranks_above(weight[best], best, item_weight, item):
            break
        heap[i] = best
        position[best] = i
        i = child
    heap[i] = item
    position[item] = i


@wp.kernel
@no_type_check
def _eliminate_kernel(
    row_offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32), pair_weight: wp.array(dtype=wp.int32),
    target: wp.int32, weight: wp.array(dtype=wp.int32), heap: wp.array(dtype=wp.int32), position: wp.array(dtype=wp.int32),
):  # fmt: skip
    size = heap.shape[0]
    for k in range(size):
        heap[k] = k
        position[k] = k
    k = size // 2 - 1
    while k >= 0:
        _sift_down(heap, position, weight, k, size)
        k -= 1
    while size > target:
        top = heap[0]
        size -= 1
        position[top] = -1
        if size > 0:
            last = heap[size]
            heap[0] = last
            position[last] = 0
            _sift_down(heap, position, weight, 0, size)
        for e in range(row_offsets[top], row_offsets[top + 1]):
            j = columns[e]
            at = position[j]
            if at >= 0 and pair_weight[e] > 0:
                # A smaller weight can only move an entry down a max-heap.
                weight[j] = weight[j] - pair_weight[e]
                _sift_down(heap, position, weight, at, size)


def eliminate(row_offsets: np.ndarray, columns: np.ndarray, pair_weight: np.ndarray, weight: np.ndarray, target: int) -> np.ndarray:
    """Exact one-at-a-time elimination down to ``target`` samples: ``(P,)`` bool survivors.

    Repeatedly removes the sample of largest ``weight`` (ties: lowest index) and subtracts its
    ``pair_weight`` from each surviving neighbour. Integer weights make every update exact. Runs
    on the CPU in one thread (the algorithm is sequential; a single GPU thread is far slower).
    """
    num = weight.shape[0]
    device = "cpu"
    heap = wp.empty(num, dtype=wp.int32, device=device)
    position = wp.empty(num, dtype=wp.int32, device=device)
    inputs = [_int32_array(row_offsets, device), _int32_array(columns, device), _int32_array(pair_weight, device), int(target)]
    weight_wp = _int32_array(weight, device)
    wp.launch(_eliminate_kernel, dim=1, inputs=inputs, outputs=[weight_wp, heap, position], device=device)
    return position.numpy() >= 0


# ---------------------------------------------------------------------------------------------
# Nearest centroids.

ACCEPT_MARGIN = 1.0 - 2.0**-12
INNER_RADIUS_FRACTION = 0.5  # the first search radius, as a fraction of ``radius``
# Points per centroid from which Lloyd iterations look up neighbour lists rather than gaps:
# with fewer, building the lists costs more than they save.
NEIGHBOUR_LIST_MIN_POINTS = 10
# Absolute widening of a point's reach around its previous centroid, in dtype epsilons of the
# largest coordinates of the two: covers the rounding of the distances near coinciding points.
NEIGHBOUR_SLACK_EPSILONS = 16.0
# Centroids per chunk of the neighbour-list launches (a few dozen hash-grid neighbours each).
LIST_MIN_CHUNK = 128
_ACCEPT_MARGIN = wp.constant(ACCEPT_MARGIN)


@wp.func
@no_type_check
def _closer(d2: Any, j: int, best_d2: Any, best: int):
    return d2 < best_d2 or (d2 == best_d2 and j < best)


@wp.func
@no_type_check
def _nearer(p: Any, centroids: wp.array(dtype=Any), j: int, best: int, best_d2: Any):
    """``(best, best_d2)`` updated with centroid ``j``."""
    d = centroids[j] - p
    d2 = wp.dot(d, d)
    if _closer(d2, j, best_d2, best):
        return j, d2
    return best, best_d2


@wp.kernel
@no_type_check
def _centroid_gap_kernel(grid: wp.uint64, centroids: wp.array(dtype=Any), params: wp.array(dtype=Any), gaps: wp.array(dtype=Any)):
    k = wp.tid()
    c = centroids[k]
    # A lower bound of the distance to the nearest other centroid: the nearest found within the
    # outer radius, else that radius (params: see _nearest_centroid_kernel).
    accept = params[3]
    gap2 = accept * accept
    query = wp.hash_grid_query(grid, c, params[2])
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        if j != k:
            d = centroids[j] - c
            gap2 = wp.min(gap2, wp.dot(d, d))
    gaps[k] = wp.sqrt(gap2)


@wp.kernel
@no_type_check
def _centroid_neighbours_kernel(
    grid: wp.uint64, centroids: wp.array(dtype=Any), params: wp.array(dtype=Any), offsets: wp.array(dtype=wp.int32),
    offset: wp.int32, counts: wp.array(dtype=wp.int32), neighbours: wp.array(dtype=wp.int32), distances: wp.array(dtype=Any),
):  # fmt: skip
    # Each centroid's other centroids within the outer radius: counted, and given offsets (the
    # counts' running sums), also listed from offsets[k] by distance (ties: the lower index;
    # sorted by insertion, a few dozen each).
    _, k = wp.tid()
    k = k + offset
    c = centroids[k]
    r = params[2]
    listing = offsets.shape[0] > 0
    start = int(0)
    if listing:
        start = offsets[k]
    n = int(0)
    query = wp.hash_grid_query(grid, c, r)
    j = int(0)
    while wp.hash_grid_query_next(query, j):
        d = centroids[j] - c
        if j != k and wp.dot(d, d) < r * r:
            if listing:
                length = wp.length(d)
                at = start + n
                while at > start and (distances[at - 1] > length or (distances[at - 1] == length and neighbours[at - 1] > j)):
                    distances[at] = distances[at - 1]
                    neighbours[at] = neighbours[at - 1]
                    at -= 1
                distances[at] = length
                neighbours[at] = j
            n += 1
    counts[k] = n


@wp.kernel
@no_type_check
def _nearest_centroid_kernel(
    grid: wp.uint64, points: wp.array(dtype=Any), centroids: wp.array(dtype=Any), params: wp.array(dtype=Any), previous: wp.array(dtype=wp.int32),
    gaps: wp.array(dtype=Any), offsets: wp.array(dtype=wp.int32), neighbours: wp.array(dtype=wp.int32), distances: wp.array(dtype=Any),
    offset: wp.int32, labels: wp.array(dtype=wp.int32),
):  # fmt: skip
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    if previous.shape[0] > 0:
        own = previous[i]
        c = centroids[own]
        own_d2 = wp.dot(c - p, c - p)
        if offsets.shape[0] > 0:
            # A centroid as close as c lies within 2 |p - c| of c (see the module docstring):
            # the neighbours of c up to that reach (the margin and the slack, for the rounding
            # of the coordinates, only widen it) hold the nearest.
            magnitude = wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2])) + wp.max(wp.max(wp.abs(c[0]), wp.abs(c[1])), wp.abs(c[2]))
            reach = type(p[0])(2.0) * wp.sqrt(own_d2) / type(p[0])(_ACCEPT_MARGIN) + params[4] * magnitude
            if reach < params[3]:
                best = own
                best_d2 = own_d2
                for e in range(offsets[own], offsets[own + 1]):
                    if distances[e] > reach:
                        break
                    best, best_d2 = _nearer(p, centroids, neighbours[e], best, best_d2)
                labels[i] = best
                return
        else:
            # 2 |p - c| < g: c is strictly the nearest (see the module docstring).
            bound = gaps[own] * type(p[0])(_ACCEPT_MARGIN)
            if type(p[0])(4.0) * own_d2 < bound * bound:
                labels[i] = own
                return
    best = int(-1)
    best_d2 = params[0] * params[0]
    # Two radii (params: inner radius, its acceptance distance, outer radius, its acceptance
    # distance): most points find their centroid within the inner one and visit few cells.
    for stage in range(2):
        if best < 0:
            radius = params[2 * stage]
            accept = params[2 * stage + 1]
            best_d2 = radius * radius
            query = wp.hash_grid_query(grid, p, radius)
            j = int(0)
            while wp.hash_grid_query_next(query, j):
                d = centroids[j] - p
                d2 = wp.dot(d, d)
                if d2 < accept * accept and (best < 0 or _closer(d2, j, best_d2, best)):
                    best = j
                    best_d2 = d2
    if best < 0:
        best = int(0)
        d = centroids[0] - p
        best_d2 = wp.dot(d, d)
        for k in range(1, centroids.shape[0]):
            best, best_d2 = _nearer(p, centroids, k, best, best_d2)
    labels[i] = best


def _centroid_types(scalar) -> dict:
    return {"points": vectors(scalar), "centroids": vectors(scalar), "params": scalars(scalar), "gaps": scalars(scalar), "distances": scalars(scalar)}


_nearest_centroid = Overloads(_nearest_centroid_kernel, _centroid_types)
_centroid_gap = Overloads(_centroid_gap_kernel, _centroid_types)
_centroid_neighbours = Overloads(_centroid_neighbours_kernel, _centroid_types)


def nearest_centroids(
    points: np.ndarray,
    centroids: np.ndarray,
    radius: float,
    cell_width: float,
    dims: tuple[int, int, int],
    device: str,
    previous: np.ndarray | None = None,
    spare_threads: int = 0,
) -> np.ndarray:
    """``(N,)`` int32: index of the nearest centroid of each point (ties: lowest index).

    One search of a :class:`CentroidSearch` (see there for the arguments).
    """
    return CentroidSearch(points, radius, cell_width, dims, device)(centroids, previous, spare_threads)


class CentroidSearch:
    """Points on ``device`` for repeated nearest-centroid searches (Lloyd's iterations).

    ``points`` ``(N, 3)`` and the centroids of each call share one float dtype (float32 or
    float64); centroids are bucketed in cells of ``cell_width`` over a table of ``dims``
    (``radius`` suits: the first search then visits at most two cells per axis).
    """

    def __init__(self, points: np.ndarray, radius: float, cell_width: float, dims: tuple[int, int, int], device: str):
        self.dtype = np.dtype(points.dtype)
        scalar = WARP_SCALAR[self.dtype]
        self.vec = wp.vec3d if scalar == wp.float64 else wp.vec3f  # the types wp.HashGrid accepts
        self.device, self.cell_width, self.dims = device, cell_width, dims
        self.arguments = _HostArguments(device)
        self.num_points = points.shape[0]
        self.points = self.arguments.array(np.ascontiguousarray(points, self.dtype), self.vec)
        inner = radius * INNER_RADIUS_FRACTION
        slack = NEIGHBOUR_SLACK_EPSILONS * np.finfo(self.dtype).eps
        params = np.array([inner, inner * ACCEPT_MARGIN, radius, radius * ACCEPT_MARGIN, slack], self.dtype)
        self.params = self.arguments.array(params, scalar)
        # The last call's labels, as returned and as the kernels' argument: passed back as
        # ``previous``, they need no copy.
        self._last: tuple[np.ndarray, Any] | None = None

    def __call__(self, centroids: np.ndarray, previous: np.ndarray | None = None, spare_threads: int = 0) -> np.ndarray:
        """``(N,)`` int32: the nearest of ``centroids`` ``(K, 3)`` to each point (ties: lowest index).

        ``previous``: the points' labels before the centroids moved (``(N,)`` integers in
        ``[0, K)``), which settles most points with one distance (with at least
        ``NEIGHBOUR_LIST_MIN_POINTS`` points per centroid, a few: those of the centroids next to
        the previous one); the result is the same without. ``spare_threads``: as for
        ``launch_in_chunks``.
        """
        device, scalar, arguments = self.device, WARP_SCALAR[self.dtype], self.arguments
        num_points = self.num_points
        centroids = np.ascontiguousarray(centroids, self.dtype)
        # The hash grid is built over a wp.array (on the CPU, of the centroids' memory).
        centroids_wp: wp.array = _host_view(centroids, self.vec, device)
        centroids_arg = (centroids, self.vec) if arguments.on_cpu else centroids_wp
        labels = arguments.empty(num_points, wp.int32)
        if previous is None:
            previous_arg = arguments.empty(0, wp.int32)
        elif self._last is not None and previous is self._last[0]:
            previous_arg = self._last[1]
        else:
            previous_arg = arguments.array(np.ascontiguousarray(previous, np.int32), wp.int32)
        num = centroids.shape[0]
        with_lists = previous is not None and num_points >= NEIGHBOUR_LIST_MIN_POINTS * num
        # Unused inputs are empty arrays (the kernels read their sizes).
        num_gaps = num if previous is not None and not with_lists else 0
        gaps = arguments.array(np.zeros(num_gaps, self.dtype), scalar)
        with GRID_LOCK:
            grid = hash_grid(centroids_wp, self.cell_width, self.dims)
            if with_lists:
                counts = arguments.empty(num, wp.int32)
                unlisted = [arguments.empty(0, wp.int32), arguments.empty(0, scalar)]
                lists = functools.partial(launch_in_chunks, _centroid_neighbours(self.dtype), 1, num, min_chunk=LIST_MIN_CHUNK, spare_threads=spare_threads)
                # Count (no offsets: nothing listed), then list from the counts' running sums.
                lists([grid.id, centroids_arg, self.params, unlisted[0]], [counts, *unlisted])
                offsets = np.zeros(num + 1, np.int32)
                np.cumsum(host_values(counts), out=offsets[1:])
                offsets_arg = arguments.array(offsets, wp.int32)
                neighbours, distances = arguments.empty(int(offsets[-1]), wp.int32), arguments.empty(int(offsets[-1]), scalar)
                lists([grid.id, centroids_arg, self.params, offsets_arg], [counts, neighbours, distances])
            else:
                offsets_arg, neighbours, distances = arguments.empty(0, wp.int32), arguments.empty(0, wp.int32), arguments.empty(0, scalar)
                if num_gaps:
                    arguments.launch(_centroid_gap(self.dtype), num_gaps, [grid.id, centroids_arg, self.params, gaps])
            inputs = [grid.id, self.points, centroids_arg, self.params, previous_arg, gaps, offsets_arg, neighbours, distances]
            launch_in_chunks(_nearest_centroid(self.dtype), 1, num_points, inputs, [labels], spare_threads=spare_threads)
        result = host_values(labels)
        self._last = (result, labels)
        return result


# ---------------------------------------------------------------------------------------------
# Closest faces on cluster patches.

# Patch queries are heavy (hundreds of faces each): chunks this small still pay their launch.
PATCH_MIN_CHUNK = 64
# Candidate faces per launch chunk: a chunk of fewer costs more in the thread pool's handoff
# than the second core saves (the remesher's searches of 500-2,000 points over 50k-110k
# candidates were 1.5-8% faster whole in one launch on 2 cores than in chunks of 4,096).
PATCH_CHUNK_FACES = 65536
# Slack of the bounding-sphere pruning, in units of the working dtype's epsilon times the
# magnitudes compared: it covers the rounding of the centre distances and of the bounds.
PATCH_BOUND_SLACK = 64


@wp.kernel
@no_type_check
def _patch_closest_kernel(
    points: wp.array(dtype=Any), patches: wp.array(dtype=wp.int32), vertices: wp.array(dtype=Any), faces: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32), candidates: wp.array(dtype=wp.int32), centres: wp.array(dtype=Any), radii: wp.array(dtype=Any),
    tolerances: wp.array(dtype=Any), hints: wp.array(dtype=wp.int32), offset: wp.int32, found: wp.array(dtype=wp.int32),
):  # fmt: skip
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    # tolerances: the pruning's slack s, and the tie tolerance (relative, magnitude): faces
    # within tie = relative (magnitude + max |p_k|) of the nearest distance count as tied.
    tie = tolerances[1] * (tolerances[2] + wp.max(wp.max(wp.abs(p[0]), wp.abs(p[1])), wp.abs(p[2])))
    patch = patches[i]
    start = offsets[patch]
    stop = offsets[patch + 1]
    # The face whose bounding-sphere centre is nearest is usually the closest face: its distance
    # U bounds the patch's. Each face lies in its bounding sphere, so a face at |p - centre| - radius
    # > U cannot be closer: the test |p - centre| <= (U + radius)(1 + s) / (1 - s) (s: the slack
    # for rounding) needs no square root per face.
    # (centres and radii are stored per candidate, in patch order: read in sequence.) A hint (a
    # face of the patch near the point, e.g. its face before it moved a little) serves as well.
    nearest = int(0)
    if hints.shape[0] > 0:
        nearest = hints[i]
    else:
        nearest = candidates[start]
        nearest_d2 = wp.length_sq(p - centres[start])
        for j in range(start + 1, stop):
            d2 = wp.length_sq(p - centres[j])
            if d2 < nearest_d2:
                nearest = candidates[j]
                nearest_d2 = d2
    # (U + tie: the tied faces must pass too.)
    upper = wp.sqrt(triangle_distance_sq(p, vertices[faces[3 * nearest]], vertices[faces[3 * nearest + 1]], vertices[faces[3 * nearest + 2]])) + tie
    one = type(upper)(1.0)
    widen = (one + tolerances[0]) / (one - tolerances[0])
    best = int(-1)
    best_d2 = type(upper)(0.0)
    # Candidates ascend within a patch, so the strict comparison keeps the lowest index of a tie.
    for j in range(start, stop):
        reach = (upper + radii[j]) * widen
        if wp.length_sq(p - centres[j]) <= reach * reach:
            face = candidates[j]
            d2 = triangle_distance_sq(p, vertices[faces[3 * face]], vertices[faces[3 * face + 1]], vertices[faces[3 * face + 2]])
            if best < 0 or d2 < best_d2:
                best = face
                best_d2 = d2
    # The lowest face within the tie tolerance of the nearest (a lower one than best, if any).
    limit = wp.sqrt(best_d2) + tie
    limit2 = limit * limit
    for j in range(start, stop):
        face = candidates[j]
        if face >= best:
            break
        reach = (upper + radii[j]) * widen
        if wp.length_sq(p - centres[j]) <= reach * reach:
            if triangle_distance_sq(p, vertices[faces[3 * face]], vertices[faces[3 * face + 1]], vertices[faces[3 * face + 2]]) <= limit2:
                best = face
                break
    found[i] = best


_patch_closest = Overloads(
    _patch_closest_kernel,
    lambda s: {"points": vectors(s), "vertices": vectors(s), "centres": vectors(s), "radii": wp.array(dtype=s), "tolerances": wp.array(dtype=s)},
)


@wp.kernel
@no_type_check
def _face_sphere_kernel(
    vertices: wp.array(dtype=Any), faces: wp.array(dtype=wp.int32), candidates: wp.array(dtype=wp.int32), offset: wp.int32,
    centres: wp.array(dtype=Any), radii: wp.array(dtype=Any),
):  # fmt: skip
    _, j = wp.tid()
    j = j + offset
    face = candidates[j]
    a = vertices[faces[3 * face]]
    b = vertices[faces[3 * face + 1]]
    c = vertices[faces[3 * face + 2]]
    centre = (a + b + c) / type(a[0])(3.0)
    centres[j] = centre
    radii[j] = wp.max(wp.max(wp.length(a - centre), wp.length(b - centre)), wp.length(c - centre))


_face_sphere = Overloads(_face_sphere_kernel, lambda s: {"vertices": vectors(s), "centres": vectors(s), "radii": wp.array(dtype=s)})


class PatchSearch:
    """A triangle surface and its cluster patches on ``device``, for :func:`patch_closest_faces`.

    ``vertices`` ``(V, 3)`` float32 or float64 (the working dtype), ``faces`` ``(F, 3)``
    int32; patch ``k`` is ``candidates[offsets[k]:offsets[k + 1]]``, ascending face indices, at
    least one per patch. Each candidate also gets its face's bounding sphere (stored in candidate
    order): the face's centroid and the largest distance from there to a corner (their rounding
    is within the pruning's slack). ``tie``: ``(relative, magnitude)``, faces within
    ``relative * (magnitude + max_k |p_k|)`` of a point's nearest distance are tied.
    """

    def __init__(
        self, vertices: np.ndarray, faces: np.ndarray, offsets: np.ndarray, candidates: np.ndarray, device: str, tie: tuple[float, float]
    ):  # fmt: skip
        self.dtype = np.dtype(vertices.dtype)
        scalar = WARP_SCALAR[self.dtype]
        vec = wp.types.vector(3, scalar)
        self.device = device
        self.arguments = arguments = _HostArguments(device)
        vertices_arg = arguments.array(np.ascontiguousarray(vertices), vec)
        faces_arg = arguments.array(np.ascontiguousarray(faces, np.int32).reshape(-1), wp.int32)
        candidates_arg = arguments.array(np.ascontiguousarray(candidates, np.int32), wp.int32)
        # Spheres per candidate (a face once per patch it is in): the search reads them in order.
        spheres = [wp.empty(candidates.size, dtype=vec, device=device), wp.empty(candidates.size, dtype=scalar, device=device)]
        launch_in_chunks(_face_sphere(self.dtype), 1, candidates.size, [vertices_arg, faces_arg, candidates_arg], spheres)
        tolerances = np.array([PATCH_BOUND_SLACK * np.finfo(self.dtype).eps, *tie], self.dtype)
        offsets_arg = arguments.array(np.ascontiguousarray(offsets, np.int32), wp.int32)
        spheres_args = [arguments.array(a.numpy(), a.dtype) if arguments.on_cpu else a for a in spheres]
        self.arrays = [vertices_arg, faces_arg, offsets_arg, candidates_arg, *spheres_args, arguments.array(tolerances, scalar)]
        self.min_chunk = max(PATCH_MIN_CHUNK, round(PATCH_CHUNK_FACES * (offsets.size - 1) / max(candidates.size, 1)))


def patch_closest_faces(search: PatchSearch, points: np.ndarray, patches: np.ndarray, hints: np.ndarray | None = None) -> np.ndarray:
    """``(Q,)`` int32: the nearest face of each point ``(Q, 3)`` (the working dtype) among the
    faces of its patch ``patches`` ``(Q,)``; distances exact in the working dtype, ties (within
    the search's tie tolerance) to the lowest face index. ``hints`` ``(Q,)``: optionally a face
    of each point's patch near it (its distance bounds the search; the result is the same)."""
    vec, arguments = wp.types.vector(3, WARP_SCALAR[search.dtype]), search.arguments
    found = arguments.empty(points.shape[0], wp.int32)
    inputs = [
        arguments.array(np.ascontiguousarray(points, search.dtype), vec),
        arguments.array(np.ascontiguousarray(patches, np.int32), wp.int32),
        *search.arrays,
        arguments.array(np.ascontiguousarray(np.zeros(0) if hints is None else hints, np.int32), wp.int32),
    ]
    launch_in_chunks(_patch_closest(search.dtype), 1, points.shape[0], inputs, [found], min_chunk=search.min_chunk)
    return host_values(found)


# ---------------------------------------------------------------------------------------------
# The remesher's face geometry.


@wp.kernel
@no_type_check
def _face_geometry_kernel(
    vertices: wp.array(dtype=Any), faces: wp.array(dtype=wp.int32), offset: wp.int32,
    first: wp.array(dtype=wp.vec3d), doubled: wp.array(dtype=wp.vec3d), area: wp.array(dtype=wp.float64),
):  # fmt: skip
    # Each product, difference and sum rounded on its own, in NumPy's order (row_cross, row_dot):
    # the same bits as geomjax's NumPy twin.
    _, f = wp.tid()
    f = f + offset
    a = wp.vec3d(vertices[faces[3 * f]])
    ab = wp.vec3d(vertices[faces[3 * f + 1]]) - a
    ac = wp.vec3d(vertices[faces[3 * f + 2]]) - a
    d0 = ab[1] * ac[2]
    d0 = d0 - ab[2] * ac[1]
    d1 = ab[2] * ac[0]
    d1 = d1 - ab[0] * ac[2]
    d2 = ab[0] * ac[1]
    d2 = d2 - ab[1] * ac[0]
    first[f] = a
    doubled[f] = wp.vec3d(d0, d1, d2)
    square = d0 * d0 + d1 * d1
    area[f] = wp.float64(0.5) * wp.sqrt(square + d2 * d2)


_face_geometry = Overloads(_face_geometry_kernel, lambda s: {"vertices": vectors(s)})


def face_geometry(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per face ``(F, 3)`` of ``vertices`` ``(V, 3)`` (float32 or float64), in float64: its first
    corner ``a`` ``(F, 3)``, ``(b - a) x (c - a)`` ``(F, 3)`` and its area ``(F,)``; the same bits
    as geomjax's NumPy twin. Parallel chunks on the CPU cores."""
    device = "cpu"
    num = faces.shape[0]
    outputs = [wp.empty(num, dtype=wp.vec3d, device=device), wp.empty(num, dtype=wp.vec3d, device=device), wp.empty(num, dtype=wp.float64, device=device)]
    dtype = np.dtype(vertices.dtype)
    vertices_wp: wp.array = wp.array(vertices, dtype=wp.types.vector(3, WARP_SCALAR[dtype]), device=device)
    launch_in_chunks(_face_geometry(dtype), 1, num, [vertices_wp, _int32_array(faces, device)], outputs)
    first, doubled, area = (a.numpy() for a in outputs)
    return first, doubled, area


# ---------------------------------------------------------------------------------------------
# The remesher's plane quadric terms, summed into the vertices.


@wp.kernel
@no_type_check
def _vertex_plane_terms_kernel(
    faces: wp.array(dtype=wp.int32), first_corners: wp.array2d(dtype=wp.float64), doubled_normals: wp.array2d(dtype=wp.float64),
    face_area: wp.array(dtype=wp.float64), sums: wp.array2d(dtype=wp.float64),
):  # fmt: skip
    # One thread, faces and corners in order, each product and sum rounded as NumPy's: the sums
    # equal geomjax's NumPy twin (its face terms, np.bincount over the flattened faces) to the bit.
    term = wp.vector(dtype=wp.float64, length=12)
    for f in range(face_area.shape[0]):
        area = face_area[f]
        scale = wp.float64(1.0)
        if area > wp.float64(0.0):
            scale = wp.float64(2.0) * area
        n0 = doubled_normals[f, 0] / scale
        n1 = doubled_normals[f, 1] / scale
        n2 = doubled_normals[f, 2] / scale
        third = area / wp.float64(3.0)
        offset = n0 * first_corners[f, 0] + n1 * first_corners[f, 1]
        offset = offset + n2 * first_corners[f, 2]
        # n n^T's upper triangle (row by row), (n . p) n, n; each times a third of the area.
        term[0] = (third * n0) * n0
        term[1] = (third * n0) * n1
        term[2] = (third * n0) * n2
        term[3] = (third * n1) * n1
        term[4] = (third * n1) * n2
        term[5] = (third * n2) * n2
        term[6] = (third * offset) * n0
        term[7] = (third * offset) * n1
        term[8] = (third * offset) * n2
        term[9] = third * n0
        term[10] = third * n1
        term[11] = third * n2
        for k in range(3):
            v = faces[3 * f + k]
            for j in range(12):
                sums[j, v] = sums[j, v] + term[j]


def vertex_plane_terms(faces: np.ndarray, first_corners: np.ndarray, doubled_normals: np.ndarray, face_area: np.ndarray, num_vertices: int) -> np.ndarray:
    """``(12, V)`` float64: geomjax's remesher's plane terms (``geomjax.remesh._quadrics``) of
    each face ``(F, 3)``, summed into its corners, from the faces' first corners, doubled
    normals ``(F, 3)`` and areas ``(F,)`` (float64). One sequential CPU kernel outside the GIL
    (the remesher runs it on a second thread); the same bits as the NumPy twin."""
    sums = np.zeros((12, num_vertices))
    floats = [(np.ascontiguousarray(a, np.float64), wp.float64) for a in (first_corners, doubled_normals, face_area)]
    launch_on_host(_vertex_plane_terms_kernel, 1, [(np.ascontiguousarray(faces, np.int32).reshape(-1), wp.int32), *floats, (sums, wp.float64)])
    return sums


# ---------------------------------------------------------------------------------------------
# The remesher's relaxation rounds: the bending measure, the circumcentre sums and the check for
# overturned triangles (sequential launches: the NumPy twins' roundings in their order).


@wp.kernel
@no_type_check
def _relaxation_sums_kernel(
    x: wp.array(dtype=wp.vec3d), triangles: wp.array(dtype=wp.int32), rho: wp.array(dtype=wp.float64),
    total: wp.array(dtype=wp.float64), sums: wp.array(dtype=wp.vec3d),
):  # fmt: skip
    # One thread, triangles and corners in order, each product and sum rounded as in geomjax's
    # NumPy twin (row by row, left to right; np.bincount over the flattened triangles): the same
    # bits.
    zero = wp.float64(0.0)
    two = wp.float64(2.0)
    for t in range(triangles.shape[0] // 3):
        i = triangles[3 * t]
        j = triangles[3 * t + 1]
        k = triangles[3 * t + 2]
        a = x[i]
        b = x[j]
        c = x[k]
        ab = b - a
        ac = c - a
        bc = c - b
        n0 = ab[1] * ac[2] - ab[2] * ac[1]
        n1 = ab[2] * ac[0] - ab[0] * ac[2]
        n2 = ab[0] * ac[1] - ab[1] * ac[0]
        normal2 = (n0 * n0 + n1 * n1) + n2 * n2
        ab2 = (ab[0] * ab[0] + ab[1] * ab[1]) + ab[2] * ab[2]
        ac2 = (ac[0] * ac[0] + ac[1] * ac[1]) + ac[2] * ac[2]
        bc2 = (bc[0] * bc[0] + bc[1] * bc[1]) + bc[2] * bc[2]
        denominator = two
        if normal2 > zero:
            denominator = two * normal2
        # Circumcentre: a + ((n x ab) |ac|^2 + (ac x n) |ab|^2) / (2 |n|^2).
        centre = wp.vec3d(
            a[0] + ((n1 * ab[2] - n2 * ab[1]) * ac2 + (ac[1] * n2 - ac[2] * n1) * ab2) / denominator,
            a[1] + ((n2 * ab[0] - n0 * ab[2]) * ac2 + (ac[2] * n0 - ac[0] * n2) * ab2) / denominator,
            a[2] + ((n0 * ab[1] - n1 * ab[0]) * ac2 + (ac[0] * n1 - ac[1] * n0) * ab2) / denominator,
        )
        # Obtuse (the largest excess, the first of equals, not negative): the longest edge's midpoint.
        excess = (bc2 - ab2) - ac2
        midpoint = wp.vec3d((b[0] + c[0]) / two, (b[1] + c[1]) / two, (b[2] + c[2]) / two)
        if (ac2 - ab2) - bc2 > excess:
            excess = (ac2 - ab2) - bc2
            midpoint = wp.vec3d((a[0] + c[0]) / two, (a[1] + c[1]) / two, (a[2] + c[2]) / two)
        if (ab2 - ac2) - bc2 > excess:
            excess = (ab2 - ac2) - bc2
            midpoint = wp.vec3d((a[0] + b[0]) / two, (a[1] + b[1]) / two, (a[2] + b[2]) / two)
        if excess >= zero:
            centre = midpoint
        mass = wp.float64(0.5) * wp.sqrt(normal2)
        if rho.shape[0] > 0:
            mass = mass * (((rho[i] + rho[j]) + rho[k]) / wp.float64(3.0))
        weighted = wp.vec3d(mass * centre[0], mass * centre[1], mass * centre[2])
        for corner in range(3):
            v = triangles[3 * t + corner]
            total[v] = total[v] + mass
            sums[v] = sums[v] + weighted


@wp.kernel
@no_type_check
def _largest_sagittas_kernel(
    x: wp.array(dtype=wp.vec3d), unit: wp.array(dtype=wp.vec3d), triangles: wp.array(dtype=wp.int32),
    largest: wp.array(dtype=wp.float64), used: wp.array(dtype=wp.int32),
):  # fmt: skip
    # One launch on the CPU runs the threads in sequence: plain read-modify-writes are safe.
    t = wp.tid()
    for corner in range(3):
        tail = triangles[3 * t + corner]
        head = triangles[3 * t + (corner + 1) % 3]
        chord = x[head] - x[tail]
        turn = unit[head] - unit[tail]
        sagitta = wp.abs((chord[0] * turn[0] + chord[1] * turn[1]) + chord[2] * turn[2]) / wp.float64(8.0)
        largest[tail] = wp.max(largest[tail], sagitta)
        largest[head] = wp.max(largest[head], sagitta)
        used[tail] = 1


@wp.func
@no_type_check
def _cross(a: wp.vec3d, b: wp.vec3d):
    """``a x b``, rounded as the NumPy twins' row_cross."""
    return wp.vec3d(a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


@wp.func
@no_type_check
def _dot(a: wp.vec3d, b: wp.vec3d):
    """``a . b``, summed as the NumPy twins' row_dot."""
    return (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2]


@wp.func
@no_type_check
def _unit(a: wp.vec3d):
    """``a / |a|`` (``a`` itself if its norm is not positive), as the NumPy twins' unit_rows."""
    norm = wp.sqrt(_dot(a, a))
    if norm > wp.float64(0.0):
        return wp.vec3d(a[0] / norm, a[1] / norm, a[2] / norm)
    return a


@wp.func
@no_type_check
def _doubled_normal(x: wp.array(dtype=wp.vec3d), i: wp.int32, j: wp.int32, k: wp.int32):
    """``(x_j - x_i) x (x_k - x_i)``, rounded as the NumPy twin's row_cross."""
    return _cross(x[j] - x[i], x[k] - x[i])


@wp.kernel
@no_type_check
def _overturned_kernel(
    before: wp.array(dtype=wp.vec3d), after: wp.array(dtype=wp.vec3d), triangles: wp.array(dtype=wp.int32), turned: wp.array(dtype=wp.int32)
):
    # (Parameters are C++ names: not "new".)
    t = wp.tid()
    i = triangles[3 * t]
    j = triangles[3 * t + 1]
    k = triangles[3 * t + 2]
    a = _doubled_normal(before, i, j, k)
    b = _doubled_normal(after, i, j, k)
    if (a[0] * b[0] + a[1] * b[1]) + a[2] * b[2] <= wp.float64(0.0):
        turned[i] = 1
        turned[j] = 1
        turned[k] = 1


def overturned_vertices(old: np.ndarray, new: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(V,)`` bool: the corners of the ``triangles`` ``(T, 3)`` whose normal turns by 90 degrees
    or more from positions ``old`` to ``new`` ``(V, 3)`` (measured in float64): geomjax's
    remesher's check of a relaxation step (``geomjax.remesh._triangulation.overturned_vertices``),
    the same answer as its NumPy twin (the same roundings)."""
    turned = np.zeros(old.shape[0], np.int32)
    arrays = [(np.ascontiguousarray(old, np.float64), wp.vec3d), (np.ascontiguousarray(new, np.float64), wp.vec3d)]
    launch_on_host(_overturned_kernel, triangles.shape[0], [*arrays, (np.ascontiguousarray(triangles, np.int32).reshape(-1), wp.int32), (turned, wp.int32)])
    return turned.astype(bool)


@wp.kernel
@no_type_check
def _flip_rules_kernel(
    x: wp.array(dtype=wp.vec3d), u: wp.array(dtype=wp.int64), v: wp.array(dtype=wp.int64), p: wp.array(dtype=wp.int64), q: wp.array(dtype=wp.int64),
    edges: wp.array(dtype=wp.int64), degree: wp.array(dtype=wp.int64), stride: wp.int64, flat_factor: wp.float64, flat: wp.array(dtype=wp.int32),
    flippable: wp.array(dtype=wp.int32),
):  # fmt: skip
    i = wp.tid()
    a = u[i]
    b = v[i]
    c = p[i]
    d = q[i]
    xa = x[a]
    xb = x[b]
    xc = x[c]
    xd = x[d]
    # Flat: the new diagonal cd passes within flat_factor |cd| of the old one ab.
    across = _cross(xb - xa, xd - xc)
    length = wp.sqrt(_dot(across, across))
    if length < wp.float64(2.2250738585072014e-308):  # np.maximum(length, tiny); NaN stays NaN
        length = wp.float64(2.2250738585072014e-308)
    cd = xd - xc
    if wp.abs(_dot(xc - xa, across)) / length <= flat_factor * wp.sqrt(_dot(cd, cd)):
        flat[i] = 1
    # Flippable: cd is no edge yet (a binary search of the sorted keys), a and b keep more than
    # three edges, and both new triangles face like the old pair.
    key = wp.min(c, d) * stride + wp.max(c, d)
    low = int(0)
    high = edges.shape[0]
    while low < high:
        middle = (low + high) // 2
        if edges[middle] < key:
            low = middle + 1
        else:
            high = middle
    existing = False
    if low < edges.shape[0]:
        existing = edges[low] == key
    old_normal = _unit(_cross(xb - xa, xc - xa)) + _unit(_cross(xa - xb, xd - xb))
    unfolded = _dot(_cross(xd - xa, xc - xa), old_normal) > wp.float64(0.0) and _dot(_cross(xb - xd, xc - xd), old_normal) > wp.float64(0.0)
    if not existing and degree[a] > wp.int64(3) and degree[b] > wp.int64(3) and unfolded:
        flippable[i] = 1


def flip_rules(
    x: np.ndarray, u: np.ndarray, v: np.ndarray, p: np.ndarray, q: np.ndarray, edges: np.ndarray, degree: np.ndarray, flat_factor: float
) -> tuple[np.ndarray, np.ndarray]:
    """``(M,)`` bool twice: per pair of triangles ``(u, v, p)`` and ``(v, u, q)`` (int64
    ``(M,)`` vertex indices of ``x`` ``(V, 3)`` float64), whether it is flat (the new diagonal
    ``pq`` passes within ``flat_factor |pq|`` of ``uv``) and flippable (``pq`` is not among the
    sorted int64 edge keys ``min * V + max`` ``edges``, ``u`` and ``v`` have more than three
    edges by ``degree`` ``(V,)`` int64, and both new triangles face like the old pair):
    geomjax's remesher's flip rules (``geomjax.remesh._flips``), the same answers as their NumPy
    twin (the same roundings)."""
    flat, flippable = np.zeros(u.shape[0], np.int32), np.zeros(u.shape[0], np.int32)
    corners = [(np.ascontiguousarray(a, np.int64), wp.int64) for a in (u, v, p, q)]
    graph = [(np.ascontiguousarray(edges, np.int64), wp.int64), (np.ascontiguousarray(degree, np.int64), wp.int64), x.shape[0], float(flat_factor)]
    launch_on_host(_flip_rules_kernel, u.shape[0], [(np.ascontiguousarray(x, np.float64), wp.vec3d), *corners, *graph, (flat, wp.int32), (flippable, wp.int32)])
    return flat.astype(bool), flippable.astype(bool)


@wp.kernel
@no_type_check
def _corner_terms_kernel(
    x: wp.array(dtype=wp.vec3d), apex: wp.array(dtype=wp.int64), first: wp.array(dtype=wp.int64), second: wp.array(dtype=wp.int64),
    sines: wp.array(dtype=wp.float64), cosines: wp.array(dtype=wp.float64),
):  # fmt: skip
    i = wp.tid()
    origin = x[apex[i]]
    u = x[first[i]] - origin
    v = x[second[i]] - origin
    normal = _cross(u, v)
    sines[i] = wp.sqrt(_dot(normal, normal))
    cosines[i] = _dot(u, v)


def corner_terms(x: np.ndarray, apex: np.ndarray, first: np.ndarray, second: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(M,)`` float64 twice: per corner, ``|u x v|`` and ``u . v`` with ``u = x[first] -
    x[apex]`` and ``v = x[second] - x[apex]`` (``x`` ``(V, 3)`` float64, int64 indices
    ``(M,)``): the sine and cosine terms of the corner's angle, whose ``arctan2`` is geomjax's
    remesher's corner angle (``geomjax.remesh._triangulation.corner_angles``; the same bits as
    its NumPy twin). Separate contiguous arrays: NumPy's vectorised arctan2 (AVX-512) takes only
    those, and may round differently from its strided loop."""
    sines, cosines = np.empty(apex.shape[0]), np.empty(apex.shape[0])
    corners = [(np.ascontiguousarray(a, np.int64), wp.int64) for a in (apex, first, second)]
    launch_on_host(_corner_terms_kernel, apex.shape[0], [(np.ascontiguousarray(x, np.float64), wp.vec3d), *corners, (sines, wp.float64), (cosines, wp.float64)])
    return sines, cosines


@wp.kernel
@no_type_check
def _cluster_seeds_kernel(
    x: wp.array(dtype=wp.vec3d), centroids: wp.array(dtype=wp.vec3d), labels: wp.array(dtype=wp.int32), nearest: wp.array(dtype=wp.float64),
    seed: wp.array(dtype=wp.int64),
):  # fmt: skip
    # One thread, vertices in order: a strictly nearer vertex replaces the seed, so a tie keeps
    # the lowest index. A NaN distance poisons its cluster's minimum (as np.minimum.at's NaN
    # does in the twin), which then has no seed.
    for v in range(x.shape[0]):
        label = labels[v]
        offset = x[v] - centroids[label]
        distance2 = _dot(offset, offset)
        if distance2 != distance2:
            nearest[label] = distance2
            seed[label] = wp.int64(x.shape[0])
        elif distance2 < nearest[label] or (distance2 == nearest[label] and seed[label] == wp.int64(x.shape[0])):
            # (The second case: a first distance that is infinite.)
            nearest[label] = distance2
            seed[label] = wp.int64(v)


def cluster_seeds(x: np.ndarray, centroids: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """Per non-empty cluster (in label order), the vertex of ``x`` ``(V, 3)`` with label
    ``labels`` ``(V,)`` (int32 in ``[0, K)``) nearest to its centroid of ``centroids``
    ``(K, 3)`` (float64 distances; ties: the lowest vertex index): geomjax's remesher's cluster
    seeds (``geomjax.remesh._surface_clusters._cluster_seeds``), the same answer as its NumPy
    twin. One sequential CPU kernel."""
    nearest, seed = np.full(centroids.shape[0], np.inf), np.full(centroids.shape[0], x.shape[0], np.int64)
    arrays = [
        (np.ascontiguousarray(x, np.float64), wp.vec3d),
        (np.ascontiguousarray(centroids, np.float64), wp.vec3d),
        (np.ascontiguousarray(labels, np.int32), wp.int32),
    ]
    launch_on_host(_cluster_seeds_kernel, 1, [*arrays, (nearest, wp.float64), (seed, wp.int64)])
    return seed[seed < x.shape[0]]


@wp.func
@no_type_check
def _edge_sagitta(x: wp.array(dtype=wp.vec3d), unit: wp.array(dtype=wp.vec3d), a: wp.int64, b: wp.int64):
    """The signed sagitta ``(x_b - x_a) . (n_b - n_a) / 8`` of edge ``a -> b``, rounded as the
    NumPy twin's."""
    return _dot(x[b] - x[a], unit[b] - unit[a]) / wp.float64(8.0)


@wp.func
@no_type_check
def _fold_height(ab: wp.float64, bc: wp.float64, ca: wp.float64):
    """The largest of a triangle's edge sagittas and 4/9 of their sum, in absolute value."""
    four_ninths = wp.float64(4.0) / wp.float64(9.0)
    return wp.max(wp.max(wp.abs(ab), wp.abs(bc)), wp.max(wp.abs(ca), four_ninths * wp.abs((ab + bc) + ca)))


@wp.func
@no_type_check
def _triangle_fold_height(x: wp.array(dtype=wp.vec3d), unit: wp.array(dtype=wp.vec3d), triangles: wp.array(dtype=wp.int32), t: wp.int64):
    three = wp.int64(3)
    a = wp.int64(triangles[three * t])
    b = wp.int64(triangles[three * t + wp.int64(1)])
    c = wp.int64(triangles[three * t + wp.int64(2)])
    return _fold_height(_edge_sagitta(x, unit, a, b), _edge_sagitta(x, unit, b, c), _edge_sagitta(x, unit, c, a))


@wp.kernel
@no_type_check
def _fold_heights_kernel(
    x: wp.array(dtype=wp.vec3d), unit: wp.array(dtype=wp.vec3d), triangles: wp.array(dtype=wp.int32), first: wp.array(dtype=wp.int64),
    second: wp.array(dtype=wp.int64), u: wp.array(dtype=wp.int64), v: wp.array(dtype=wp.int64), p: wp.array(dtype=wp.int64),
    q: wp.array(dtype=wp.int64), now: wp.array(dtype=wp.float64), flipped: wp.array(dtype=wp.float64),
):  # fmt: skip
    # (Parameters are C++ names: not "new".)
    i = wp.tid()
    now[i] = wp.max(_triangle_fold_height(x, unit, triangles, first[i] // wp.int64(3)), _triangle_fold_height(x, unit, triangles, second[i] // wp.int64(3)))
    pq = _edge_sagitta(x, unit, p[i], q[i])
    first_new = _fold_height(_edge_sagitta(x, unit, u[i], q[i]), pq, _edge_sagitta(x, unit, p[i], u[i]))
    second_new = _fold_height(_edge_sagitta(x, unit, q[i], v[i]), _edge_sagitta(x, unit, v[i], p[i]), pq)
    flipped[i] = wp.max(first_new, second_new)


def fold_heights(
    x: np.ndarray, unit: np.ndarray, triangles: np.ndarray, first: np.ndarray, second: np.ndarray, u: np.ndarray, v: np.ndarray, p: np.ndarray, q: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``(M,)`` float64 twice: per pair of ``triangles`` ``(T, 3)`` (half-edges ``first``
    ``u -> v`` and ``second`` ``v -> u``, half-edge ``h`` being edge ``h % 3`` of triangle
    ``h // 3``, third corners ``p`` and ``q``; int64 ``(M,)``), the estimated height of the
    surface over its two triangles now and after a flip, from positions ``x`` and unit normals
    ``unit`` ``(V, 3)`` float64: geomjax's remesher's fold-flip estimate
    (``geomjax.remesh._flips.fold_flips``), the same bits as its NumPy twin (finite inputs)."""
    old, new = np.empty(u.shape[0]), np.empty(u.shape[0])
    rows = [(np.ascontiguousarray(x, np.float64), wp.vec3d), (np.ascontiguousarray(unit, np.float64), wp.vec3d)]
    pairs = [(np.ascontiguousarray(a, np.int64), wp.int64) for a in (first, second, u, v, p, q)]
    faces = (np.ascontiguousarray(triangles, np.int32).reshape(-1), wp.int32)
    launch_on_host(_fold_heights_kernel, u.shape[0], [*rows, faces, *pairs, (old, wp.float64), (new, wp.float64)])
    return old, new


def largest_sagittas(x: np.ndarray, unit: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(V,)`` float64 and bool: per vertex of ``x`` ``(V, 3)`` (float64), the largest sagitta
    estimate ``|(b - a) . (n_b - n_a)| / 8`` of its edges in ``triangles`` ``(T, 3)`` (``unit``
    ``(V, 3)``: unit normals), and whether a triangle uses it: geomjax's remesher's bending
    density (``geomjax.remesh._triangulation.bending_density``), the same bits as its NumPy twin."""
    largest, used = np.zeros(x.shape[0]), np.zeros(x.shape[0], np.int32)
    arrays = [
        (np.ascontiguousarray(x, np.float64), wp.vec3d),
        (np.ascontiguousarray(unit, np.float64), wp.vec3d),
        (np.ascontiguousarray(triangles, np.int32).reshape(-1), wp.int32),
    ]
    # The kernel writes into the NumPy arrays themselves.
    launch_on_host(_largest_sagittas_kernel, triangles.shape[0], [*arrays, (largest, wp.float64), (used, wp.int32)])
    return largest, used.astype(bool)


def relaxation_sums(x: np.ndarray, triangles: np.ndarray, rho: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """``(V,)`` and ``(V, 3)`` float64: per vertex of ``x`` ``(V, 3)`` (float64), the masses of
    the ``triangles`` ``(T, 3)`` around it and their mass-weighted circumcentres (for obtuse
    triangles the longest edge's midpoint), summed: geomjax's remesher's relaxation sums
    (``geomjax.remesh._triangulation.relaxation_targets``; a triangle's mass is its area, times
    the mean of ``rho`` ``(V,)`` at its corners if given). One sequential CPU kernel; the same
    bits as the NumPy twin."""
    total, sums = np.zeros(x.shape[0]), np.zeros((x.shape[0], 3))
    weights = np.zeros(0) if rho is None else np.ascontiguousarray(rho, np.float64)
    arrays = [(np.ascontiguousarray(x, np.float64), wp.vec3d), (np.ascontiguousarray(triangles, np.int32).reshape(-1), wp.int32), (weights, wp.float64)]
    # The kernel adds into the NumPy arrays themselves.
    launch_on_host(_relaxation_sums_kernel, 1, [*arrays, (total, wp.float64), (sums, wp.vec3d)])
    return total, sums


# ---------------------------------------------------------------------------------------------
# Shortest-path forests on a mesh's edge graph.


@wp.func
@no_type_check
def _shorter(distance_a: wp.float64, label_a: wp.int32, distance_b: wp.float64, label_b: wp.int32):
    """Forest order: the shorter distance first, ties to the lower label."""
    return distance_a < distance_b or (distance_a == distance_b and label_a < label_b)


@wp.func
@no_type_check
def _queue_push(
    entry_distance: wp.array(dtype=wp.float64), entry_label: wp.array(dtype=wp.int32), entry_vertex: wp.array(dtype=wp.int32),
    entry_next: wp.array(dtype=wp.int32), head: wp.array(dtype=wp.int32), tail: wp.array(dtype=wp.int32), used: wp.int32,
    distance: wp.float64, label: wp.int32, vertex: wp.int32, width: wp.float64, overflow: wp.array(dtype=wp.int32),
):  # fmt: skip
    """Appends an entry to the bucket of its distance (a ring of ``head.shape[0]`` buckets of
    ``width``); returns the entries used. A full pool drops it and raises ``overflow[0]``."""
    if used == entry_vertex.shape[0]:
        overflow[0] = 1
        return used
    entry_distance[used] = distance
    entry_label[used] = label
    entry_vertex[used] = vertex
    entry_next[used] = -1
    # (min: an index within int range however far the distance.)
    bucket = int(wp.min(distance / width, wp.float64(1.0e9))) % head.shape[0]
    if tail[bucket] < 0:
        head[bucket] = used
    else:
        entry_next[tail[bucket]] = used
    tail[bucket] = used
    return used + 1


@wp.kernel
@no_type_check
def _grow_forest_kernel(
    row_offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32), lengths: wp.array(dtype=wp.float64), width: wp.float64,
    cleared: wp.array(dtype=wp.int32), seeds: wp.array(dtype=wp.int32), seed_labels: wp.array(dtype=wp.int32),
    distance: wp.array(dtype=wp.float64), label: wp.array(dtype=wp.int32), parent: wp.array(dtype=wp.int32),
    entry_distance: wp.array(dtype=wp.float64), entry_label: wp.array(dtype=wp.int32), entry_vertex: wp.array(dtype=wp.int32),
    entry_next: wp.array(dtype=wp.int32), head: wp.array(dtype=wp.int32), tail: wp.array(dtype=wp.int32), overflow: wp.array(dtype=wp.int32),
):  # fmt: skip
    unreached = wp.float64(wp.inf)
    for b in range(head.shape[0]):
        head[b] = -1
        tail[b] = -1
    for k in range(cleared.shape[0]):
        distance[cleared[k]] = unreached
        parent[cleared[k]] = -1
    # Each cleared vertex starts from its best kept neighbour (their paths are still shortest);
    # the candidates go to the queue first and to the vertices after, so that no cleared vertex
    # reads another's candidate. (All cleared: there is none to start from.)
    used = int(0)
    kept = cleared.shape[0] < distance.shape[0]
    for k in range(cleared.shape[0] if kept else 0):
        v = cleared[k]
        best = unreached
        best_label = int(0)
        for e in range(row_offsets[v], row_offsets[v + 1]):
            u = columns[e]
            if distance[u] < unreached:
                d = distance[u] + lengths[e]
                if best == unreached or _shorter(d, label[u], best, best_label):
                    best = d
                    best_label = label[u]
                    parent[v] = u
        if best < unreached:
            used = _queue_push(entry_distance, entry_label, entry_vertex, entry_next, head, tail, used, best, best_label, v, width, overflow)
    for e in range(used):
        distance[entry_vertex[e]] = entry_distance[e]
        label[entry_vertex[e]] = entry_label[e]
    for k in range(seeds.shape[0]):
        s = seeds[k]
        if _shorter(wp.float64(0.0), seed_labels[k], distance[s], label[s]):
            distance[s] = wp.float64(0.0)
            label[s] = seed_labels[k]
            parent[s] = -1
            used = _queue_push(entry_distance, entry_label, entry_vertex, entry_next, head, tail, used, wp.float64(0.0), seed_labels[k], s, width, overflow)
    # Label-correcting shortest paths on (distance, label), the queue's buckets in turn (entries
    # within a bucket in their order; an entry whose vertex has changed since is stale): a
    # vertex takes a shorter path (or as short, from a lower label), and is expanded again when
    # it does; the fixed point is Dijkstra's, in a fraction of its time (no heap). A kept
    # vertex also follows its parent's new value when that is no longer (as short and of its
    # label): rounding can give two paths of different lengths the same sum, and a vertex must
    # keep a parent of its own label, or its cluster would fall apart. A full pool ends the run
    # (reported as an overflow: the caller starts over another way).
    popped = int(0)
    current = int(0)
    while popped < used and overflow[0] == 0:
        slot = current % head.shape[0]
        while head[slot] >= 0 and overflow[0] == 0:
            entry = head[slot]
            head[slot] = entry_next[entry]
            if head[slot] < 0:
                tail[slot] = -1
            popped += 1
            v = entry_vertex[entry]
            d = entry_distance[entry]
            own = entry_label[entry]
            if d == distance[v] and own == label[v]:
                for e in range(row_offsets[v], row_offsets[v + 1]):
                    j = columns[e]
                    reach = d + lengths[e]
                    if _shorter(reach, own, distance[j], label[j]) or (parent[j] == v and (reach != distance[j] or own != label[j])):
                        distance[j] = reach
                        label[j] = own
                        parent[j] = v
                        used = _queue_push(entry_distance, entry_label, entry_vertex, entry_next, head, tail, used, reach, own, j, width, overflow)
        current += 1


# Buckets of the forest's queue: a ring this long, each a mean edge length wide, holds the
# distances of a cluster (a few dozen edges across) without wrapping around.
FOREST_BUCKETS = 4096


class EdgeGraph:
    """A symmetric edge graph in CSR form (``row_offsets`` ``(V + 1,)``, ``columns``, positive
    float64 ``lengths``) and the queue of :func:`grow_forest`, kept on the CPU between calls."""

    def __init__(self, row_offsets: np.ndarray, columns: np.ndarray, lengths: np.ndarray):
        # Kernel arguments as (NumPy array, Warp dtype): see warp_ffi._wrap.launch_on_host.
        lengths = np.ascontiguousarray(lengths, np.float64)
        self.arrays = [(np.ascontiguousarray(row_offsets, np.int32), wp.int32), (np.ascontiguousarray(columns, np.int32), wp.int32), (lengths, wp.float64)]
        self.width = float(np.mean(lengths)) if lengths.size else 1.0
        # A push improves a vertex or moves it with its parent: about once per cleared vertex,
        # seed and edge of an expanded vertex (few vertices are expanded twice).
        capacity = 2 * (row_offsets.size - 1) + columns.size + 1
        self.entries = [(np.empty(capacity, wp.dtype_to_numpy(kind)), kind) for kind in (wp.float64, wp.int32, wp.int32, wp.int32)]
        self.buckets = [(np.empty(FOREST_BUCKETS, np.int32), wp.int32) for _ in range(2)]
        self.overflow = np.zeros(1, np.int32)


def grow_forest(
    graph: EdgeGraph, distance: np.ndarray, labels: np.ndarray, parents: np.ndarray, cleared: np.ndarray, seeds: np.ndarray, seed_labels: np.ndarray
) -> bool:  # fmt: skip
    """Updates a shortest-path forest in place after its seeds changed; False if it could not.

    ``distance`` ``(V,)`` float64, ``labels`` and ``parents`` ``(V,)`` int32 (C-contiguous,
    modified in place) are each vertex's distance from its seed along the edges, the seed's
    label and the neighbour it is reached from (negative for a seed or an unreached vertex), a
    shortest-path forest of the previous seeds. ``cleared`` (int32 vertex indices): the vertices
    whose seed is gone (all, with infinite distances, to start from nothing); ``seeds`` and
    ``seed_labels`` (int32): the current seeds. A label whose seed moved must have all its
    vertices cleared. On return each reached vertex holds its shortest distance to a seed and
    the label of a seed at that distance, reached from a neighbour of the same label (so every
    cluster is connected); a vertex whose value changed took the lowest such label. An unreached
    cleared vertex keeps its label with an infinite distance. Expands only the vertices whose
    value changes (a sequential CPU kernel, label-correcting on a queue of distance buckets).
    False (the arrays then are not a forest): the queue's pool of entries ran out (arrays that
    were not a forest of the previous seeds, which could cycle, or a graph that needed more
    expansions than it holds); start over from nothing.
    """
    graph.overflow[0] = 0
    inputs = [*graph.arrays, graph.width, *((np.ascontiguousarray(a, np.int32), wp.int32) for a in (cleared, seeds, seed_labels))]
    # The kernel writes the caller's arrays themselves.
    state = [(distance, wp.float64), (labels, wp.int32), (parents, wp.int32)]
    launch_on_host(_grow_forest_kernel, 1, [*inputs, *state, *graph.entries, *graph.buckets, (graph.overflow, wp.int32)])
    return not graph.overflow[0]
