"""Mesh primitives: icosphere, triangulated rectangle, tetrahedralized box, polyline.

Every builder assembles its connectivity with vectorised NumPy (no Python loop over elements) and
returns a validated :class:`geomjax.Mesh`. Coordinates default to float64 when JAX has 64-bit
types enabled (``jax_enable_x64``) and float32 otherwise; pass ``dtype`` to choose.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._validate import FLOAT_DTYPES, as_float_array, as_jax_array, check_bool, check_integer, check_real_scalar, check_real_sequence, is_array
from .mesh import Mesh

__all__ = ["icosphere", "rectangle", "tetrahedralized_box", "polyline"]

_GOLDEN = (1.0 + 5.0**0.5) / 2.0
_ICOSAHEDRON_VERTICES = np.array(
    [
        [-1, _GOLDEN, 0],
        [1, _GOLDEN, 0],
        [-1, -_GOLDEN, 0],
        [1, -_GOLDEN, 0],
        [0, -1, _GOLDEN],
        [0, 1, _GOLDEN],
        [0, -1, -_GOLDEN],
        [0, 1, -_GOLDEN],
        [_GOLDEN, 0, -1],
        [_GOLDEN, 0, 1],
        [-_GOLDEN, 0, -1],
        [-_GOLDEN, 0, 1],
    ]
)
# Counter-clockwise seen from outside, so every normal points outward.
_ICOSAHEDRON_FACES = np.array(
    [
        [0, 11, 5],
        [0, 5, 1],
        [0, 1, 7],
        [0, 7, 10],
        [0, 10, 11],
        [1, 5, 9],
        [5, 11, 4],
        [11, 10, 2],
        [10, 7, 6],
        [7, 1, 8],
        [3, 9, 4],
        [3, 4, 2],
        [3, 2, 6],
        [3, 6, 8],
        [3, 8, 9],
        [4, 9, 5],
        [2, 4, 11],
        [6, 2, 10],
        [8, 6, 7],
        [9, 8, 1],
    ]
)


def icosphere(subdivisions: int, radius: float = 1.0, *, dtype=None) -> Mesh:
    """Triangulated sphere centred at the origin: a subdivided icosahedron.

    Each subdivision splits every triangle into four at its edge midpoints, which are pushed out
    onto the sphere; subdivision ``s`` has ``10 * 4**s + 2`` vertices and ``20 * 4**s`` triangles
    (``s = 6``: 40,962 and 81,920), all counter-clockwise seen from outside (outward normals), so
    the mesh satisfies the closed-surface contract of volume energies.

    Args:
        subdivisions: integer ``>= 0``.
        radius: positive finite real.
        dtype: float32 or float64 (default: float64 with ``jax_enable_x64``, else float32).

    Returns:
        A :class:`geomjax.Mesh` with ``(V, 3)`` points and ``(F, 3)`` triangles.

    Raises:
        TypeError: non-integer ``subdivisions``, non-real ``radius``, a non-float ``dtype``.
        ValueError: negative ``subdivisions``, non-positive or non-finite ``radius``.

    Example:
        >>> import numpy as np
        >>> from geomjax import icosphere
        >>> sphere = icosphere(2, radius=2.0)
        >>> sphere.n_points, sphere.n_cells
        (162, 320)
        >>> print(np.round(float(np.linalg.norm(np.asarray(sphere.points), axis=1).max()), 6))
        2.0
    """
    subdivisions = check_integer("subdivisions", subdivisions, minimum=0)
    dtype = _float_dtype(dtype)
    radius = check_real_scalar("radius", radius, dtype, positive=True)
    vertices = _ICOSAHEDRON_VERTICES / np.linalg.norm(_ICOSAHEDRON_VERTICES, axis=1, keepdims=True)
    faces = _ICOSAHEDRON_FACES
    for _ in range(subdivisions):
        num_vertices = vertices.shape[0]
        edges = np.sort(faces[:, [[0, 1], [1, 2], [2, 0]]], axis=2).reshape(-1, 2)
        keys, midpoint_of = np.unique(edges[:, 0] * num_vertices + edges[:, 1], return_inverse=True)
        midpoints = vertices[keys // num_vertices] + vertices[keys % num_vertices]
        midpoints /= np.linalg.norm(midpoints, axis=1, keepdims=True)
        vertices = np.concatenate([vertices, midpoints])
        m01, m12, m20 = (num_vertices + midpoint_of.reshape(-1, 3)).T
        v0, v1, v2 = faces.T
        # The four children keep the parent's winding.
        faces = np.concatenate([np.stack(corner, axis=1) for corner in ((v0, m01, m20), (v1, m12, m01), (v2, m20, m12), (m01, m12, m20))])
    return Mesh(_points(vertices * radius, dtype), faces)


def rectangle(nx: int, ny: int, *, origin: Sequence[float] = (0.0, 0.0), extent: Sequence[float] = (1.0, 1.0), dtype=None) -> Mesh:
    """Triangulated axis-aligned rectangle in 2-D.

    An ``nx`` by ``ny`` grid of quads, each split along the same diagonal into two
    counter-clockwise triangles (positive signed area); ``(nx + 1) * (ny + 1)`` vertices numbered
    with ``x`` fastest, ``2 * nx * ny`` triangles (cell ``(i, j)`` gives rows ``2 * (i + nx * j)``
    and the next).

    Args:
        nx, ny: cells along ``x`` and ``y``, integers ``>= 1``.
        origin: minimum corner, two finite reals.
        extent: side lengths, two positive finite reals.
        dtype: float32 or float64 (default: float64 with ``jax_enable_x64``, else float32).

    Raises:
        TypeError: non-integer counts, non-real corner entries or a wrong number of them, a non-float ``dtype``.
        ValueError: counts below 1, non-finite or non-positive box entries.

    Example:
        >>> import numpy as np
        >>> from geomjax import rectangle
        >>> plate = rectangle(2, 1, extent=(2.0, 1.0))
        >>> plate.n_points, plate.n_cells
        (6, 4)
        >>> print(np.asarray(plate.cells).tolist())
        [[0, 1, 4], [0, 4, 3], [1, 2, 5], [1, 5, 4]]
    """
    counts = (check_integer("nx", nx, minimum=1), check_integer("ny", ny, minimum=1))
    return _grid(counts, origin, extent, dtype, _triangles_of_square())


def tetrahedralized_box(nx: int, ny: int, nz: int, *, origin: Sequence[float] = (0.0, 0.0, 0.0), extent: Sequence[float] = (1.0, 1.0, 1.0), dtype=None) -> Mesh:
    """Conforming tetrahedral mesh of an axis-aligned box.

    An ``nx`` by ``ny`` by ``nz`` grid of hexahedra, each split into six tetrahedra around its
    main diagonal (Kuhn/Freudenthal subdivision). Every cell is split the same way, so faces
    match across cells, and every tetrahedron has positive orientation
    (``det[x1 - x0, x2 - x0, x3 - x0] > 0``). ``(nx + 1) * (ny + 1) * (nz + 1)`` vertices numbered
    with ``x`` fastest, then ``y``; ``6 * nx * ny * nz`` tetrahedra of equal volume.

    Args:
        nx, ny, nz: cells along each axis, integers ``>= 1``.
        origin: minimum corner, three finite reals.
        extent: side lengths, three positive finite reals.
        dtype: float32 or float64 (default: float64 with ``jax_enable_x64``, else float32).

    Raises:
        TypeError: non-integer counts, non-real corner entries or a wrong number of them, a non-float ``dtype``.
        ValueError: counts below 1, non-finite or non-positive box entries.

    Example:
        >>> from geomjax import tetrahedralized_box
        >>> box = tetrahedralized_box(2, 3, 4)
        >>> box.n_points, box.n_cells, box.n_manifold_dims
        (60, 144, 3)
    """
    counts = (check_integer("nx", nx, minimum=1), check_integer("ny", ny, minimum=1), check_integer("nz", nz, minimum=1))
    return _grid(counts, origin, extent, dtype, _tetrahedra_of_cube())


def polyline(points: Float[Array, "num_points num_dims"] | int, closed: bool = False, *, dtype=None) -> Mesh:
    """Chain of segments through the given points, or a regular one with ``n`` vertices.

    Segment ``i`` joins vertices ``i`` and ``i + 1``; ``closed=True`` adds the segment from the
    last vertex back to the first.

    Args:
        points: an ``(N, D)`` float array (its dtype is kept unless ``dtype`` is given), or an
            integer ``n``: ``n`` vertices evenly spaced on the segment from ``(0, 0)`` to
            ``(1, 0)`` (open), or a regular ``n``-gon on the unit circle, counter-clockwise from
            ``(1, 0)`` (closed).
        closed: whether to close the loop. An open polyline needs at least 2 vertices, a closed
            one at least 3.
        dtype: float32 or float64 (default: the array's dtype; for an integer ``n``, float64
            with ``jax_enable_x64``, else float32).

    Raises:
        TypeError: ``points`` neither an integer nor a float array, non-bool ``closed``, a
            non-float ``dtype``.
        ValueError: too few vertices, ``points`` not ``(N, D)``.

    Example:
        >>> import numpy as np
        >>> from geomjax import polyline
        >>> square = polyline(4, closed=True)
        >>> print(np.asarray(square.cells).tolist())
        [[0, 1], [1, 2], [2, 3], [3, 0]]
        >>> print(np.round(np.asarray(square.points), 6).tolist())
        [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [-0.0, -1.0]]
    """
    closed = check_bool("closed", closed)
    minimum = 3 if closed else 2
    if is_array(points):
        points = as_float_array("points", points)
        if points.ndim != 2:
            raise ValueError(f"points must have shape (N, D), got {tuple(points.shape)}")
        if points.shape[0] < minimum:
            raise ValueError(f"a{' closed' if closed else 'n open'} polyline needs at least {minimum} points, got {points.shape[0]}")
        if dtype is not None:
            points = points.astype(_float_dtype(dtype))
        num_vertices = points.shape[0]
    else:
        num_vertices = check_integer("points", points, minimum=minimum)
        if closed:
            angles = 2.0 * np.pi * np.arange(num_vertices) / num_vertices
            coordinates = np.stack([np.cos(angles), np.sin(angles)], axis=1)
        else:
            coordinates = np.stack([np.linspace(0.0, 1.0, num_vertices), np.zeros(num_vertices)], axis=1)
        points = _points(coordinates, _float_dtype(dtype))
    starts = np.arange(num_vertices if closed else num_vertices - 1)
    return Mesh(points, np.stack([starts, (starts + 1) % num_vertices], axis=1))


# --------------------------------------------------------------------------------------------


def _float_dtype(dtype):
    if dtype is None:
        return jnp.dtype(jnp.float64 if jax.config.jax_enable_x64 else jnp.float32)
    try:
        dtype = jnp.dtype(dtype)
    except TypeError as error:
        raise TypeError(f"dtype must be float32 or float64, got {dtype!r}") from error
    if dtype not in FLOAT_DTYPES:
        raise TypeError(f"dtype must be float32 or float64, got {dtype}")
    return dtype


def _points(coordinates: np.ndarray, dtype) -> jax.Array:
    # Rounded once from float64 coordinates, so float32 meshes are as accurate as float32 allows.
    return as_jax_array(coordinates.astype(np.dtype(dtype.name)))


def _grid(counts: tuple[int, ...], origin, extent, dtype, corner_simplices: np.ndarray) -> Mesh:
    """Structured simplicial grid: every cell of the ``counts`` grid split by ``corner_simplices``.

    ``corner_simplices`` ``(S, K)`` indexes the cell's ``2**D`` corners, corner ``c`` having
    offset bit ``d`` of ``c`` along axis ``d``.
    """
    dims = len(counts)
    dtype = _float_dtype(dtype)
    origin = np.array(check_real_sequence("origin", origin, dims, dtype))
    extent = np.array(check_real_sequence("extent", extent, dims, dtype, positive=True))
    axes = [origin[d] + extent[d] * np.arange(counts[d] + 1) / counts[d] for d in range(dims)]
    # C order reversed so that x varies fastest in the vertex numbering.
    coordinates = np.stack([g.reshape(-1) for g in np.meshgrid(*axes[::-1], indexing="ij")][::-1], axis=1)
    strides = np.cumprod((1,) + tuple(n + 1 for n in counts[:-1]))
    cell_origins = sum(np.arange(counts[d]).reshape((-1,) + (1,) * d) * strides[d] for d in range(dims)).reshape(-1)
    corner_offsets = np.array([sum(((c >> d) & 1) * strides[d] for d in range(dims)) for c in range(2**dims)])
    cells = cell_origins[:, None, None] + corner_offsets[corner_simplices][None]
    return Mesh(_points(coordinates, dtype), cells.reshape(-1, corner_simplices.shape[1]))


def _triangles_of_square() -> np.ndarray:
    # Corners 0 = (0, 0), 1 = (1, 0), 2 = (0, 1), 3 = (1, 1); both triangles counter-clockwise.
    return np.array([[0, 1, 3], [0, 3, 2]])


def _tetrahedra_of_cube() -> np.ndarray:
    """Kuhn subdivision: one tetrahedron per axis order, walking corner 0 -> 7 one axis at a time."""
    tetrahedra = []
    for order in itertools.permutations(range(3)):
        corners = [0]
        for axis in order:
            corners.append(corners[-1] | (1 << axis))
        # Odd axis orders give negative determinants; swapping two vertices makes them positive.
        inversions = sum(order[i] > order[j] for i in range(3) for j in range(i + 1, 3))
        if inversions % 2:
            corners[1], corners[2] = corners[2], corners[1]
        tetrahedra.append(corners)
    return np.array(tetrahedra)
