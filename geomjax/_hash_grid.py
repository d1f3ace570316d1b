"""Uniform spatial grids shared by the sampler, the remesher and the quality measures.

Two users, one set of rules:

* The Warp paths bucket points in Warp's ``wp.HashGrid``, whose table wraps cell coordinates
  modulo its dimensions. :func:`grid_resolution` validates the user's ``hash_grid_resolution``
  and :func:`table_dims` clamps it to the cells the points actually span (a smaller table is
  cheaper to clear and rebuild, and no two occupied cells then share a bucket), never below 3
  per axis so that a query of radius at most one cell, which visits three cells per axis, never
  visits one bucket twice.
* :func:`cell_order` sorts points cell by cell, the storage order that makes grid queries
  cache-friendly.
* :func:`nearest_distances` answers exact nearest-point queries in NumPy for the quality
  measures (sorted cell keys, a 27-cell scan, brute force for the rare query whose nearest point
  may lie beyond the scanned cells).
"""

from __future__ import annotations

import math
import numbers

import numpy as np

from ._validate import is_array

__all__ = ["grid_resolution", "table_dims", "check_cell_range", "cell_order", "nearest_distances"]

MAX_CELL_COORDINATE = 2**30  # |coordinate / cell width| bound: Warp's cell indices are int32


def grid_resolution(name: str, value) -> tuple[int, int, int]:
    """Validate a grid resolution: one positive integer, or three (a sequence or a concrete array).

    Raises:
        TypeError: a ``bool``, a non-integer, or a traced or non-integer array.
        ValueError: not one or three values, or a value below 1.
    """
    if is_array(value):
        import jax

        if isinstance(value, jax.core.Tracer):
            raise TypeError(f"{name} must be concrete (it sizes a table), got a traced array")
        host = np.asarray(value)
        if host.dtype == np.bool_ or host.dtype.kind not in "iu":
            raise TypeError(f"{name} must hold integers, got dtype {host.dtype}")
        if host.shape not in ((), (1,), (3,)):
            raise ValueError(f"{name} must be one integer or three, got shape {host.shape}")
        values = [int(v) for v in np.broadcast_to(host.reshape(-1), (3,))]
    elif isinstance(value, (bool, np.bool_)):
        raise TypeError(f"{name} must be an integer or three integers, got bool")
    elif isinstance(value, numbers.Integral):
        values = [int(value)] * 3
    elif isinstance(value, (list, tuple)):
        if len(value) != 3:
            raise ValueError(f"{name} must be one integer or three, got {len(value)} values")
        for v in value:
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Integral):
                raise TypeError(f"{name} entries must be integers, got {type(v).__name__}")
        values = [int(v) for v in value]
    else:
        raise TypeError(f"{name} must be an integer or three integers, got {type(value).__name__}")
    if min(values) < 1:
        raise ValueError(f"{name} must be positive, got {tuple(values)}")
    nx, ny, nz = values
    return nx, ny, nz


def table_dims(low: np.ndarray, high: np.ndarray, cell_width: float, resolution: tuple[int, int, int]) -> tuple[int, int, int]:
    """Hash-table dimensions: ``resolution`` clamped to the cells spanned by ``[low, high]``, >= 3."""
    spans = np.floor(np.asarray(high, np.float64) / cell_width) - np.floor(np.asarray(low, np.float64) / cell_width) + 1
    nx, ny, nz = (int(max(3, min(r, s))) for r, s in zip(resolution, spans, strict=True))
    return nx, ny, nz


def check_cell_range(name: str, largest_coordinate: float, cell_width: float) -> None:
    """Cell indices must fit int32: ``ValueError`` when coordinates are too many cells from 0."""
    if largest_coordinate / cell_width >= MAX_CELL_COORDINATE:
        raise ValueError(f"{name}={cell_width:g} is too small for coordinates up to {largest_coordinate:g}: the grid would need more than 2**30 cells per axis")


def cell_order(points: np.ndarray, cell_width: float) -> np.ndarray:
    """A stable permutation listing the points cell by cell (z, then y, then x cell index).

    Neighbour queries over points stored in this order read the grid and the points nearly
    sequentially, several times faster than in random order.
    """
    cells = np.floor(np.asarray(points, np.float64) / cell_width).astype(np.int64)
    return np.lexsort((cells[:, 0], cells[:, 1], cells[:, 2]))


def nearest_distances(queries: np.ndarray, points: np.ndarray, *, exclude_self: bool = False) -> np.ndarray:
    """Exact Euclidean distance from each query to its nearest point, float64 ``(Q,)``.

    With ``exclude_self`` the queries are the points themselves and a point is not its own
    neighbour (a lone point gets ``inf``). Cells are sized for points on a surface (about two
    points per cell); any spatial distribution gives exact results, only slower.
    """
    queries = np.asarray(queries, np.float64).reshape(-1, 3)
    points = np.asarray(points, np.float64).reshape(-1, 3)
    best = np.full(queries.shape[0], np.inf)
    if points.shape[0] == 0 or queries.shape[0] == 0:
        return best
    low = points.min(axis=0)
    diagonal = float(np.linalg.norm(points.max(axis=0) - low))
    if diagonal == 0.0:
        cell = 1.0
    else:
        cell = max(diagonal * math.sqrt(2.0 / points.shape[0]), diagonal * 2.0**-20)
    dims = np.floor((points.max(axis=0) - low) / cell).astype(np.int64) + 3
    point_cells = np.floor((points - low) / cell).astype(np.int64) + 1
    keys = point_cells[:, 0] + dims[0] * (point_cells[:, 1] + dims[1] * point_cells[:, 2])
    order = np.argsort(keys, kind="stable")
    sorted_keys = keys[order]
    sorted_points = points[order]
    query_cells = np.floor((queries - low) / cell).astype(np.int64) + 1
    inside = np.all((query_cells >= 1) & (query_cells <= dims - 2), axis=1)
    scanned = np.flatnonzero(inside)
    for offset in np.ndindex(3, 3, 3):
        cells = query_cells[scanned] + np.asarray(offset) - 1
        neighbour_keys = cells[:, 0] + dims[0] * (cells[:, 1] + dims[1] * cells[:, 2])
        start = np.searchsorted(sorted_keys, neighbour_keys, side="left")
        counts = np.searchsorted(sorted_keys, neighbour_keys, side="right") - start
        total = int(counts.sum())
        if total == 0:
            continue
        owner = np.repeat(np.arange(scanned.size), counts)
        first = np.repeat(np.cumsum(counts) - counts, counts)
        candidate = np.repeat(start, counts) + (np.arange(total) - first)
        d2 = np.sum(np.square(sorted_points[candidate] - queries[scanned[owner]]), axis=1)
        if exclude_self:
            d2 = np.where(order[candidate] == scanned[owner], np.inf, d2)
        np.minimum.at(best, scanned[owner], d2)
    # A scan covers every point closer than one cell; beyond that, brute force.
    unresolved = np.flatnonzero(~(best <= cell * cell))
    for chunk in np.array_split(unresolved, max(1, -(-unresolved.size * points.shape[0] // 2**21))):
        if chunk.size == 0:
            continue
        d2 = np.sum(np.square(queries[chunk, None, :] - points[None, :, :]), axis=-1)
        if exclude_self:
            d2[np.arange(chunk.size), chunk] = np.inf
        best[chunk] = d2.min(axis=1)
    return np.sqrt(best)
