"""Read and write :class:`geomjax.Mesh` files through meshio (optional extra ``geomjax[io]``).

Any format meshio knows (VTU, VTK, OBJ, STL, PLY, Gmsh, XDMF, ...) is chosen by file extension.
Point data is kept where the format stores it (VTU and VTK do; OBJ and STL do not).
"""

from __future__ import annotations

import os

import numpy as np

from .mesh import Mesh
from .primitives import _float_dtype, _points

__all__ = ["read_mesh", "write_mesh"]

# meshio's cell type for each simplex a Mesh holds, by vertices per cell, and back.
_MESHIO_TYPES = {2: "line", 3: "triangle", 4: "tetra"}
_VERTICES_OF = {name: count for count, name in _MESHIO_TYPES.items()}
# meshio cell types of each manifold dimension that are not simplices (cannot be held by a Mesh).
_NON_SIMPLEX_DIMS = {"quad": 2, "polygon": 2, "hexahedron": 3, "wedge": 3, "pyramid": 3}


def _meshio(op_name: str):
    try:
        import meshio
    except ImportError as error:
        raise ImportError(f'{op_name} needs meshio, which is optional: install it with pip install "geomjax[io]" (or pip install "meshio>=5")') from error
    return meshio


def read_mesh(path: str | os.PathLike, *, dtype=None) -> Mesh:
    """Read a simplicial mesh file into a :class:`geomjax.Mesh`.

    The cells are the blocks of the highest-dimensional simplex type in the file (``tetra``,
    else ``triangle``, else ``line``), concatenated in file order; lower-dimensional blocks
    (boundary facets, vertices) are skipped. Point data is kept; cell data is kept for the
    selected blocks. Points keep meshio's shape (many formats store 3-D points even for planar
    meshes).

    Args:
        path: file name; the format follows from the extension.
        dtype: float32 or float64 for the points (default: float64 with ``jax_enable_x64``,
            else float32). Data arrays keep their own dtypes (as JAX canonicalises them).

    Returns:
        A validated :class:`geomjax.Mesh`.

    Raises:
        ImportError: meshio is not installed (optional extra ``geomjax[io]``).
        ValueError: no simplex cells, or non-simplex cells (quads, hexahedra, ...) of the same
            or a higher dimension than the simplices, or invalid connectivity (see ``Mesh``).
        TypeError: a non-float ``dtype``.

    Example:
        >>> import os, tempfile
        >>> from geomjax import icosphere, read_mesh, write_mesh
        >>> path = os.path.join(tempfile.mkdtemp(), "sphere.vtu")
        >>> write_mesh(path, icosphere(1))
        >>> sphere = read_mesh(path)
        >>> sphere.n_points, sphere.n_cells
        (42, 80)
    """
    meshio = _meshio("read_mesh")
    dtype = _float_dtype(dtype)
    source = meshio.read(os.fspath(path))
    simplex_blocks = [i for i, block in enumerate(source.cells) if block.type in _VERTICES_OF]
    if not simplex_blocks:
        found = sorted({block.type for block in source.cells})
        raise ValueError(f"read_mesh: {os.fspath(path)!r} holds no line, triangle or tetra cells (found {found})")
    num_vertices = max(_VERTICES_OF[source.cells[i].type] for i in simplex_blocks)
    blocking = sorted({block.type for block in source.cells if _NON_SIMPLEX_DIMS.get(block.type, 0) >= num_vertices - 1})
    if blocking:
        raise ValueError(
            f"read_mesh: {os.fspath(path)!r} mixes {_MESHIO_TYPES[num_vertices]} cells with non-simplex cells {blocking}; a Mesh holds one simplex type"
        )
    chosen = [i for i in simplex_blocks if _VERTICES_OF[source.cells[i].type] == num_vertices]
    cells = np.concatenate([source.cells[i].data for i in chosen]).astype(np.int64)
    cell_data = {name: _native(np.concatenate([arrays[i] for i in chosen])) for name, arrays in source.cell_data.items()}
    return Mesh(
        _points(np.asarray(source.points, np.float64), dtype),
        cells,
        point_data={name: _native(values) for name, values in source.point_data.items()},
        cell_data=cell_data,
    )


def _native(values) -> np.ndarray:
    # Legacy VTK stores big-endian data, which JAX cannot take.
    values = np.asarray(values)
    return values.astype(values.dtype.newbyteorder("="), copy=False)


def write_mesh(path: str | os.PathLike, mesh: Mesh, *, file_format: str | None = None) -> None:
    """Write a :class:`geomjax.Mesh` (points, cells, flat point and cell data) with meshio.

    Args:
        path: file name; the format follows from the extension unless ``file_format`` is given.
        mesh: an unbatched mesh. Its ``point_data`` and ``cell_data`` must be flat (name ->
            array); formats without data fields (OBJ, STL) drop them.
        file_format: optional meshio format name (e.g. ``"vtu"``).

    Raises:
        ImportError: meshio is not installed (optional extra ``geomjax[io]``).
        TypeError: ``mesh`` is not a :class:`geomjax.Mesh`.
        ValueError: batched points or nested data.

    Example:
        >>> import os, tempfile
        >>> import numpy as np
        >>> from geomjax import read_mesh, rectangle, write_mesh
        >>> plate = rectangle(2, 2, dtype=np.float64)
        >>> path = os.path.join(tempfile.mkdtemp(), "plate.vtk")
        >>> write_mesh(path, plate)
        >>> read_mesh(path).cells.shape
        (8, 3)
    """
    meshio = _meshio("write_mesh")
    if not isinstance(mesh, Mesh):
        raise TypeError(f"write_mesh needs a geomjax.Mesh, got {type(mesh).__name__}")
    if mesh.points.ndim != 2:
        raise ValueError(f"write_mesh needs unbatched (N, D) points, got {tuple(mesh.points.shape)}")
    for name, data in (("point_data", mesh.point_data), ("cell_data", mesh.cell_data)):
        nested = [key for key, value in data.items() if isinstance(value, dict)]
        if nested:
            raise ValueError(f"write_mesh stores flat {name} only; nested entries: {nested}")
    meshio.write(
        os.fspath(path),
        meshio.Mesh(
            np.asarray(mesh.points),
            [(_MESHIO_TYPES[mesh.n_manifold_dims + 1], mesh.topology.cells_host)],
            point_data={name: np.asarray(values) for name, values in mesh.point_data.items()},
            cell_data={name: [np.asarray(values)] for name, values in mesh.cell_data.items()},
        ),
        file_format=file_format,
    )
