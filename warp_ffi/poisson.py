"""Poisson-disk sampling on Warp: hash-grid conflict tests and exact sample elimination.

Inputs arrive validated (no checks here) as NumPy arrays; results come back as NumPy arrays.
The sampler runs eagerly (its output size depends on the data), so these are plain launches on
``wp.array`` copies rather than XLA FFI calls. Candidate positions, radii and priorities, and
the elimination weights, are computed by geomjax (shared with its JAX path); this module only
does the neighbour searches and the sequential elimination.

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
"""

from __future__ import annotations

import functools
import threading

import numpy as np

from ._kernels import launch_in_chunks
from ._kernels import warp as wp

wp.set_module_options({"enable_backward": False})

__all__ = ["hash_grid", "reject_near_accepted", "resolve_conflicts", "neighbour_lists", "eliminate"]

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
def _reject_kernel(
    grid: wp.uint64,
    accepted: wp.array(dtype=wp.vec3),
    candidates: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    order: wp.array(dtype=wp.int32),
    widening: wp.float32,
    offset: wp.int32,
    alive: wp.array(dtype=wp.int32),
):
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
def _conflict_kernel(
    grid: wp.uint64,
    candidates: wp.array(dtype=wp.vec3),
    radius: wp.array(dtype=wp.float32),
    priority: wp.array(dtype=wp.uint32),
    index: wp.array(dtype=wp.int32),
    widening: wp.float32,
    offset: wp.int32,
    keep: wp.array(dtype=wp.int32),
):
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
    accepted_wp = wp.array(accepted, dtype=wp.vec3, device=device)
    candidates_wp = wp.array(candidates, dtype=wp.vec3, device=device)
    radius_wp = wp.array(radius, dtype=wp.float32, device=device)
    # Queries in cell order walk the grid's table nearly sequentially.
    order = wp.array(cell_order(candidates, cell_width).astype(np.int32), dtype=wp.int32, device=device)
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
    candidates_wp = wp.array(candidates[order], dtype=wp.vec3, device=device)
    radius_wp = wp.array(radius[order], dtype=wp.float32, device=device)
    priority_wp = wp.array(priority[order], dtype=wp.uint32, device=device)
    index_wp = wp.array(index[order].astype(np.int32), dtype=wp.int32, device=device)
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
def _gather_kernel(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    radius: wp.float32,
    limit: wp.float32,
    capacity: wp.int32,
    offset: wp.int32,
    counts: wp.array(dtype=wp.int32),
    slots: wp.array(dtype=wp.int32),
):
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    query = wp.hash_grid_query(grid, p, radius)
    j = int(0)
    count = int(0)
    base = i * capacity
    while wp.hash_grid_query_next(query, j):
        d = points[j] - p
        if j != i and wp.dot(d, d) < limit:
            if count < capacity:
                slots[base + count] = j
            count += 1
    counts[i] = count


@wp.kernel
def _fill_kernel(
    grid: wp.uint64,
    points: wp.array(dtype=wp.vec3),
    radius: wp.float32,
    limit: wp.float32,
    row_offsets: wp.array(dtype=wp.int32),
    offset: wp.int32,
    columns: wp.array(dtype=wp.int32),
):
    _, t = wp.tid()
    i = t + offset
    p = points[i]
    query = wp.hash_grid_query(grid, p, radius)
    j = int(0)
    k = row_offsets[i]
    while wp.hash_grid_query_next(query, j):
        d = points[j] - p
        if j != i and wp.dot(d, d) < limit:
            columns[k] = j
            k += 1


def neighbour_lists(
    points: np.ndarray, radius: float, limit: float, capacity: int, cell_width: float, dims: tuple[int, int, int], device: str
):
    """CSR lists of the other points with squared distance below ``limit`` (``limit >= r^2``).

    One pass stores up to ``capacity`` neighbours per point; only when some point has more does
    a second pass fill exact rows. Returns ``(row_offsets (P + 1,) int64, columns (nnz,)
    int32)``, each row in grid order. Points listed cell by cell (see :func:`cell_order`) run
    several times faster: queries then walk the grid's table and the point array in order.
    """
    num = points.shape[0]
    points_wp = wp.array(points, dtype=wp.vec3, device=device)
    counts = wp.empty(num, dtype=wp.int32, device=device)
    slots = wp.empty(num * capacity, dtype=wp.int32, device=device)
    with GRID_LOCK:
        grid = hash_grid(points_wp, cell_width, dims)
        launch_in_chunks(_gather_kernel, 1, num, [grid.id, points_wp, radius, limit, capacity], [counts, slots])
        degree = counts.numpy()
        row_offsets = np.zeros(num + 1, np.int64)
        np.cumsum(degree, out=row_offsets[1:])
        if row_offsets[-1] >= 2**31:
            raise ValueError(f"{row_offsets[-1]} neighbour pairs are more than int32 indices allow")
        if degree.max(initial=0) <= capacity:
            table = slots.numpy().reshape(num, capacity)
            return row_offsets, table[np.arange(capacity)[None, :] < degree[:, None]]
        columns = wp.empty(int(row_offsets[-1]), dtype=wp.int32, device=device)
        offsets_wp = wp.array(row_offsets[:-1].astype(np.int32), dtype=wp.int32, device=device)
        launch_in_chunks(_fill_kernel, 1, num, [grid.id, points_wp, radius, limit, offsets_wp], [columns])
    return row_offsets, columns.numpy()


@wp.func
def _ranks_above(weight_a: wp.int32, a: wp.int32, weight_b: wp.int32, b: wp.int32):
    """Heap order: the larger weight first, ties to the lower index (``argmax`` semantics)."""
    return weight_a > weight_b or (weight_a == weight_b and a < b)


@wp.func
def _sift_down(
    heap: wp.array(dtype=wp.int32),
    position: wp.array(dtype=wp.int32),
    weight: wp.array(dtype=wp.int32),
    start: wp.int32,
    size: wp.int32,
):
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
def _eliminate_kernel(
    row_offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    pair_weight: wp.array(dtype=wp.int32),
    target: wp.int32,
    weight: wp.array(dtype=wp.int32),
    heap: wp.array(dtype=wp.int32),
    position: wp.array(dtype=wp.int32),
):
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
    inputs = [
        wp.array(row_offsets.astype(np.int32), dtype=wp.int32, device=device),
        wp.array(columns.astype(np.int32), dtype=wp.int32, device=device),
        wp.array(pair_weight.astype(np.int32), dtype=wp.int32, device=device),
        int(target),
    ]
    weight_wp = wp.array(weight.astype(np.int32), dtype=wp.int32, device=device)
    wp.launch(_eliminate_kernel, dim=1, inputs=inputs, outputs=[weight_wp, heap, position], device=device)
    return position.numpy() >= 0
