"""Mesh: points with validated, cached simplicial connectivity, energies and deformations.

A :class:`Mesh` is an ``equinox.Module`` whose only array leaves are ``points`` and the arrays in
``point_data`` / ``cell_data``. The connectivity lives in a static :class:`Topology` object that
is validated once, eagerly and with NumPy, when a mesh is built from raw cells. Everything
derived from it (the device copy of the cells, the edges, the bending hinges, the closed-surface
check) is computed on first use and cached on that object. Meshes derived from one another
(``displace``, ``morph``, ``with_points``, outputs of ``jit``/``vmap``) share the same object, so
an optimisation loop never re-validates, never rebuilds hinges and, because ``jit`` compares
static fields by identity, never retraces.
"""

from __future__ import annotations

import importlib
import inspect
import itertools
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, cast

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._errors import raises_documented_errors, runtime_check
from ._registry import REGISTRY, MeshArguments, OpDeclaration
from ._validate import as_float_array, as_jax_array, check_real_sequence, check_same_device, check_same_dtype, check_same_shape, is_array

__all__ = ["Mesh", "Topology"]

# meshio's names for the simplices a Mesh can hold, by vertices per cell.
SIMPLEX_NAMES = {2: "segments", 3: "triangles", 4: "tetrahedra"}


class Topology:
    """Validated simplicial connectivity and the arrays derived from it, built once and cached.

    Held by :class:`Mesh` as a static field: ``jit`` hashes and compares it by identity, so every
    mesh derived from one construction hits the same compiled function. Build a ``Mesh`` rather
    than a ``Topology``; this class is public so that its cache can be inspected.

    Attributes:
        cells_host: the validated cells as a read-only ``(M, K)`` int64 NumPy array.
        num_points: the number of points ``N`` the indices refer to.
        cells: the cells as an ``(M, K)`` int32 JAX array (the conversion is cached here).
    """

    def __init__(self, cells_host: np.ndarray, num_points: int):
        cells_host.setflags(write=False)
        self.cells_host = cells_host
        self.num_points = num_points
        self.cells = _device_indices(cells_host)
        self._derived: dict[str, jax.Array] = {}

    def __repr__(self) -> str:
        return f"Topology(cells={self.cells_host.shape}, num_points={self.num_points})"

    def _cached(self, key: str, build: Callable[[], np.ndarray]) -> jax.Array:
        # Only successful builds are cached: invalid topology raises again on the next call.
        if key not in self._derived:
            self._derived[key] = _device_indices(build())
        return self._derived[key]

    def edges(self) -> Int[Array, "num_edges 2"]:
        """Unique undirected edges ``(E, 2)`` int32, ``u < v``, sorted lexicographically."""
        return self._cached("edges", lambda: _unique_edges(self.cells_host, self.num_points))

    def hinges(self) -> Int[Array, "num_hinges 4"]:
        """Interior hinges ``(H, 4)`` int32 of a triangle topology (see :attr:`Mesh.hinges`)."""
        return self._cached("hinges", lambda: _build_hinges(self.cells_host))

    def closed_surface_triangles(self) -> Int[Array, "num_triangles 3"]:
        """The triangles, after checking (once) the closed-surface contract of volume energies."""
        return self._cached("closed_surface", lambda: _check_closed_surface(self.cells_host))


class Mesh(eqx.Module):
    """A simplicial mesh: points ``(N, D)`` and cells ``(M, K)`` with cached, validated topology.

    Cells are segments (``K = 2``), triangles (``K = 3``) or tetrahedra (``K = 4``) embedded in
    ``D >= K - 1`` dimensions. Construction validates the connectivity once, with NumPy, on the
    concrete cell values; derived meshes reuse it.

    Args:
        points: ``(N, D)`` float32 or float64 (may be traced: only its shape is used here).
        cells: concrete ``(M, K)`` array of any non-bool integer dtype (NumPy or JAX), indices in
            ``[0, N)``, ``K`` distinct vertices per cell. ``M = 0`` is allowed.
        point_data: optional mapping from names to arrays with ``N`` rows (or nested mappings of
            such arrays). Treated as Lagrangian: deformations carry it unchanged.
        cell_data: optional mapping from names to arrays with ``M`` rows (or nested mappings).

    Attributes:
        points: the coordinates, the differentiable leaf.
        cells: ``(M, K)`` int32 JAX array (converted once and cached).
        edges, hinges: derived connectivity, built on first use and cached.
        n_points, n_cells, n_spatial_dims, n_manifold_dims: sizes.

    Raises:
        TypeError: non-float points, non-integer or bool cells, traced cells, non-array data.
        ValueError: points not ``(N, D)``, cells not ``(M, K)`` with ``2 <= K <= 4`` and
            ``K - 1 <= D``, an index outside ``[0, N)``, a cell with a repeated vertex, data with
            the wrong number of rows.

    Transformations: ``points`` and the arrays in ``point_data``/``cell_data`` are the pytree
    leaves; the topology is static. Pass a mesh through ``jax.jit`` as an argument or close over
    it: meshes sharing a topology object share the compiled function (a mesh built separately
    from equal cells traces once more). Differentiate with respect to points, e.g.
    ``jax.grad(lambda x: mesh.simplex_strain_energy(x))(x)``, or use ``equinox.filter_grad`` on a
    whole mesh (integer data leaves are not differentiable). ``jax.vmap`` over a function of
    points, or of a mesh whose leaves all carry a leading batch axis: ``jax.vmap(lambda d:
    mesh.displace(d))(displacements)`` returns one ``Mesh`` with ``(B, N, D)`` points and the
    shared topology, whose methods run inside a further ``vmap``. Methods take unbatched points.

    Example:
        >>> import jax.numpy as jnp
        >>> import numpy as np
        >>> from geomjax import Mesh
        >>> square = jnp.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]], dtype=jnp.float32)
        >>> mesh = Mesh(square, np.array([[0, 1, 2], [1, 3, 2]]))
        >>> mesh.n_points, mesh.n_cells, mesh.n_spatial_dims, mesh.n_manifold_dims
        (4, 2, 2, 2)
        >>> print(np.asarray(mesh.edges).tolist(), np.asarray(mesh.hinges).tolist())
        [[0, 1], [0, 2], [1, 2], [1, 3], [2, 3]] [[1, 2, 0, 3]]
        >>> moved = mesh.displace(jnp.ones((4, 2), dtype=jnp.float32))
        >>> print(np.asarray(moved.points[3]), moved.cells is mesh.cells)
        [2. 2.] True
    """

    points: Float[Array, "num_points num_dims"]
    point_data: dict
    cell_data: dict
    topology: Topology = eqx.field(static=True)

    def __init__(self, points, cells, *, point_data: Mapping | None = None, cell_data: Mapping | None = None):
        points = as_float_array("points", points)
        if points.ndim != 2 or points.shape[1] < 1:
            raise ValueError(f"points must have shape (N, D) with D >= 1, got {tuple(points.shape)}")
        num_points, num_dims = points.shape
        cells_host = _validate_cells(cells, num_points, num_dims)
        self.points = points
        self.topology = Topology(cells_host, num_points)
        self.point_data = _check_data("point_data", point_data, num_points, "N")
        self.cell_data = _check_data("cell_data", cell_data, cells_host.shape[0], "M")

    # ----------------------------------------------------------------------------------------
    # Sizes and connectivity

    @property
    def cells(self) -> Int[Array, "num_cells num_cell_points"]:
        """Validated cells ``(M, K)`` as an int32 JAX array (converted once, shared)."""
        return self.topology.cells

    @property
    def n_points(self) -> int:
        return self.points.shape[-2]

    @property
    def n_cells(self) -> int:
        return self.topology.cells_host.shape[0]

    @property
    def n_spatial_dims(self) -> int:
        return self.points.shape[-1]

    @property
    def n_manifold_dims(self) -> int:
        return self.topology.cells_host.shape[1] - 1

    @property
    def edges(self) -> Int[Array, "num_edges 2"]:
        """Unique undirected edges ``(E, 2)`` int32 with ``u < v``, sorted lexicographically."""
        return self.topology.edges()

    @property
    def hinges(self) -> Int[Array, "num_hinges 4"]:
        """Interior hinges ``(H, 4)`` int32 of a triangle mesh, for bending energies.

        Row ``(u, v, k, l)`` is an edge ``u < v`` shared by exactly two triangles; ``k`` is the
        opposite vertex of the one that comes first in cell order and ``l`` that of the other, so
        the faces read ``(u, v, k)`` and ``(v, u, l)`` whatever the input winding. Boundary edges
        are dropped; rows are sorted by ``(u, v)``. Built on first use and cached.

        Raises:
            ValueError: the cells are not triangles, two cells are the same triangle, or an edge
                has more than two incident triangles.
        """
        if self.n_manifold_dims != 2:
            raise ValueError(f"hinges need a triangle mesh, got {SIMPLEX_NAMES[self.n_manifold_dims + 1]}")
        return self.topology.hinges()

    def with_points(self, points: Float[Array, "num_points num_dims"]) -> Mesh:
        """A mesh with new ``points`` (same shape, float) and this mesh's topology and data."""
        points = as_float_array("points", points)
        if points.shape != self.points.shape:
            raise ValueError(f"points must have the shape of mesh.points {tuple(self.points.shape)}, got {tuple(points.shape)}")
        return eqx.tree_at(lambda mesh: mesh.points, self, points)

    # ----------------------------------------------------------------------------------------
    # The energies (this mesh is the reference configuration) and the deformations (a new Mesh
    # with moved points, the same topology object and the same data) are generated below the
    # class from their registry declarations (``OpDeclaration.mesh_arguments``). Written by hand:
    # the deformation whose lattice box is derived from the points, and remeshing.

    @raises_documented_errors
    def free_form_deform(
        self,
        control_displacements: Float[Array, "*lattice_resolution num_dims"],
        *,
        origin: Float[Array, " num_dims"] | Sequence[float] | None = None,
        extent: Float[Array, " num_dims"] | Sequence[float] | None = None,
        basis: str = "bernstein",
        point_weights: Bool[Array, " num_points"] | Float[Array, " num_points"] | str | tuple[str, ...] | None = None,
        implementation: str | None = None,
    ) -> Mesh:
        """Lattice free-form deformation of the points (:func:`geomjax.free_form_deform_points`).

        A missing ``origin`` is the minimum corner of the points' bounding box and a missing
        ``extent`` is ``max corner - origin``, both without gradient (the box is configuration).
        An empty mesh defaults to origin 0 and extent 1. ``point_weights`` may be an array or a
        ``point_data`` key.

        Raises:
            ValueError: a derived extent that is not finite and positive on every axis (flat or
                embedded geometry: pass ``extent``). Checked eagerly on concrete points; under
                ``jit`` it is an ``equinox.error_if`` check raising at run time.
        """
        from .deform.ffd import free_form_deform_points

        points = self.points
        if origin is None or extent is None:
            num_dims = self.n_spatial_dims
            if self.n_points == 0:
                origin = jnp.zeros((num_dims,), points.dtype) if origin is None else origin
                extent = jnp.ones((num_dims,), points.dtype) if extent is None else extent
            else:
                box_points = jax.lax.stop_gradient(points)
                if origin is None:
                    origin = jnp.min(box_points, axis=0)
                if extent is None:
                    extent = _checked_box_extent(jnp.max(box_points, axis=0) - self._box_vector("origin", origin))
        points = free_form_deform_points(
            points,
            control_displacements,
            origin=origin,
            extent=extent,
            basis=basis,
            point_weights=self._field("point_weights", point_weights),
            implementation=implementation,
        )
        return self.with_points(points)

    # ----------------------------------------------------------------------------------------
    # Helpers

    def _current_points(self, points) -> jax.Array:
        if self.points.ndim != 2:
            raise ValueError(f"mesh.points are batched {tuple(self.points.shape)}; call the energy inside jax.vmap over the mesh")
        return check_same_shape("mesh.points", self.points, "points", points)

    def _field(self, name: str, value):
        """Resolve a field argument given as an array or as a ``point_data`` key / tuple path."""
        if not isinstance(value, (str, tuple)):
            return value
        path = (value,) if isinstance(value, str) else value
        node: object = self.point_data
        for key in path:
            if not isinstance(node, Mapping) or key not in node:
                node = None
                break
            node = node[key]
        if node is None or isinstance(node, Mapping):
            available = ", ".join(repr(p[0] if len(p) == 1 else p) for p in _leaf_paths(self.point_data)) or "none"
            raise KeyError(f"{name}={value!r} is not a point_data key; available keys: {available}")
        return node

    def _box_vector(self, name: str, value) -> jax.Array:
        if is_array(value):
            value = as_float_array(name, value)
            check_same_dtype("points", self.points, name, value)
            check_same_device("points", self.points, name, value)
            if value.shape != (self.n_spatial_dims,):
                raise ValueError(f"{name} must have shape ({self.n_spatial_dims},) for a mesh, got {tuple(value.shape)}")
            return value
        return jnp.asarray(check_real_sequence(name, value, self.n_spatial_dims, self.points.dtype), self.points.dtype)

    # ----------------------------------------------------------------------------------------
    # Remeshing

    @raises_documented_errors
    def remesh(
        self,
        n_clusters: int,
        *,
        point_data_keys: Sequence[str | tuple[str, ...]] = (),
        vertex_density: Float[Array, " num_points"] | str | tuple[str, ...] | None = None,
        resolution_field: Float[Array, " num_points"] | str | tuple[str, ...] | None = None,
        **remeshing_options,
    ) -> Mesh:
        """A new mesh of about ``n_clusters`` vertices by centroidal clustering (:func:`geomjax.remeshing`).

        Every new vertex lies on a triangle of this mesh; the ``point_data`` fields named in
        ``point_data_keys`` (names or tuple paths) are carried over by barycentric interpolation
        on that triangle, differentiably with respect to the field values (not to the points:
        the clustering is discrete). Other point data and all cell data are dropped.

        Args:
            n_clusters: target vertex count, ``3 <= n_clusters <= n_points``.
            point_data_keys: floating ``point_data`` fields to transfer.
            vertex_density: relative integration density (array or ``point_data`` key), as in
                :func:`geomjax.remeshing` (mass density ``vertex_density / max``).
            resolution_field: alternatively, a linear resolution ``r`` (array or key): more
                vertices where it is larger, with mass density ``(r / max r)^4`` (a CVT density
                ``r^4`` gives a vertex spacing proportional to ``1 / r``).
            max_iterations, search_radius_scale, voxel_width_scale, hash_grid_resolution,
            farthest_point_threshold, farthest_point_oversampling, implementation: as in
                :func:`geomjax.remeshing`.

        Raises:
            NotImplementedError: not a triangle surface in 3-D.
            KeyError: a key that is not in ``point_data``.
            TypeError: a transferred field that is not floating, a key that is not a str or tuple.
            ValueError: both ``vertex_density`` and ``resolution_field``, batched points, and the
                errors of :func:`geomjax.remeshing` (``RuntimeError`` included).

        Example:
            >>> import numpy as np
            >>> from geomjax import icosphere
            >>> sphere = icosphere(2)
            >>> sphere = type(sphere)(sphere.points, np.asarray(sphere.cells), point_data={"z": sphere.points[:, 2]})
            >>> coarse = sphere.remesh(40, point_data_keys=["z"], implementation="jax")
            >>> print(coarse.n_points <= 40, float(np.abs(coarse.point_data["z"] - coarse.points[:, 2]).max()) < 0.1)
            True True
        """
        from .remesh.clustering import remesh_options, remesh_with_sources

        remeshing_options = remesh_options(remeshing_options, exclude=("vertex_density",))

        if self.n_manifold_dims != 2 or self.n_spatial_dims != 3:
            raise NotImplementedError(f"remesh needs a triangle surface in 3-D, got {SIMPLEX_NAMES[self.n_manifold_dims + 1]} in {self.n_spatial_dims}-D")
        if self.points.ndim != 2:
            raise ValueError(f"remesh needs unbatched points, got shape {tuple(self.points.shape)}")
        if vertex_density is not None and resolution_field is not None:
            raise ValueError("pass at most one of vertex_density and resolution_field")
        density, exponent = self._field("vertex_density", vertex_density), 1.0
        if resolution_field is not None:
            density, exponent = self._field("resolution_field", resolution_field), 4.0
        fields = []
        for key in point_data_keys:
            if not isinstance(key, (str, tuple)):
                raise TypeError(f"point_data_keys entries must be str or tuple paths, got {type(key).__name__}")
            values = self._field("point_data_keys", key)
            if not jnp.issubdtype(values.dtype, jnp.floating):
                raise TypeError(f"point_data[{key!r}] must be floating to be interpolated, got {values.dtype}")
            fields.append(((key,) if isinstance(key, str) else key, values))
        result = remesh_with_sources(self.points, self.topology.cells_host, n_clusters, vertex_density=density, density_exponent=exponent, **remeshing_options)
        corners = self.cells[result.source_faces]
        point_data: dict = {}
        for path, values in fields:
            weights = result.barycentric.astype(values.dtype)
            transferred = jnp.einsum("vk,vk...->v...", weights, values[corners])
            node = point_data
            for part in path[:-1]:
                node = node.setdefault(part, {})
            node[path[-1]] = transferred
        return Mesh(result.vertices, np.asarray(result.faces), point_data=point_data)


# --------------------------------------------------------------------------------------------
# Methods generated from the registry: one per op declared with ``mesh_arguments``.

_FROM_MESH: dict[str, Callable[[Mesh], jax.Array]] = {
    "points": lambda mesh: mesh.points,
    "cells": lambda mesh: mesh.cells,
    "hinges": lambda mesh: mesh.hinges,
    "closed_surface_triangles": lambda mesh: mesh.topology.closed_surface_triangles(),
}

_PRECONDITIONS: dict[str, tuple[Callable[[Mesh], bool], str]] = {
    "triangles_in_3d": (lambda mesh: mesh.n_manifold_dims == 2 and mesh.n_spatial_dims == 3, "a triangle surface in 3-D"),
    "full_dimensional": (lambda mesh: mesh.n_manifold_dims == mesh.n_spatial_dims, "full-dimensional cells (n_manifold_dims == n_spatial_dims)"),
}

_SOURCE_DESCRIPTIONS = {
    "points": "``self.points``",
    "cells": "the cached cells",
    "hinges": "the interior hinges (:attr:`Mesh.hinges`, built once)",
    "closed_surface_triangles": (
        "the triangles, after checking once (and caching) the closed-surface contract the op assumes: at least one "
        "triangle, no duplicate, every edge in exactly two oppositely directed triangles, one edge-connected component"
    ),
}

_KEY_NOTE = "may also be given as ``point_data`` keys (a name or a tuple path into nested data; a missing key is a ``KeyError`` listing the available ones)"


class _SignedFunction(Protocol):
    """A function given an explicit ``__signature__``, which ``inspect.signature`` reports."""

    __signature__: inspect.Signature

    def __call__(self, *args: Any, **kwargs: Any) -> Any: ...


def _with_signature(function: Callable[..., Any], signature: inspect.Signature) -> _SignedFunction:
    # Function objects take new attributes at run time; typeshed's function type has no
    # ``__signature__``, so the function is viewed through the Protocol that declares it.
    signed = cast(_SignedFunction, function)
    signed.__signature__ = signature
    return signed


def _generated_method(declaration: OpDeclaration, binding: MeshArguments, method_name: str) -> Callable:
    """The ``Mesh`` method ``method_name`` of ``declaration``: the op's signature minus the arguments ``binding`` binds."""
    op = getattr(importlib.import_module(declaration.module), declaration.name)
    op_signature = inspect.signature(op)
    parameters = [inspect.Parameter("self", inspect.Parameter.POSITIONAL_OR_KEYWORD)]
    for name, parameter in op_signature.parameters.items():
        if name in binding.bound:
            continue
        if name in binding.point_data_fields:
            parameter = parameter.replace(annotation=f"{parameter.annotation} | str | tuple[str, ...]")
        parameters.append(parameter)
    returns = op_signature.return_annotation if binding.current_points else "Mesh"
    signature = inspect.Signature(parameters, return_annotation=returns)

    def method(self: Mesh, *args, **kwargs):
        arguments = signature.bind(self, *args, **kwargs)
        arguments.apply_defaults()
        del arguments.arguments["self"]
        call = dict(arguments.arguments)
        if binding.requires is not None:
            holds, need = _PRECONDITIONS[binding.requires]
            if not holds(self):
                raise ValueError(f"{declaration.name} needs {need}, got {SIMPLEX_NAMES[self.n_manifold_dims + 1]} in {self.n_spatial_dims}-D")
        for name, source in binding.bound.items():
            call[name] = _FROM_MESH[source](self)
        for name in binding.point_data_fields:
            call[name] = self._field(name, call[name])
        if binding.current_points is not None:
            call[binding.current_points] = self._current_points(call[binding.current_points])
            return op(**call)
        return self.with_points(op(**call))

    method.__name__ = method_name
    method.__qualname__ = f"Mesh.{method_name}"
    method.__doc__ = _generated_docstring(declaration, binding, op)
    return _with_signature(method, signature)


def _generated_docstring(declaration: OpDeclaration, binding: MeshArguments, op: Callable) -> str:
    doc = inspect.getdoc(op)
    if doc is None:
        raise AssertionError(f"geomjax.{declaration.name} has no docstring to summarise in Mesh.{declaration.mesh_method}")
    header = doc.split("\n", 1)[0]
    bound = ", ".join(f"``{name}`` = {_SOURCE_DESCRIPTIONS[source]}" for name, source in binding.bound.items())
    lines = [header, "", f"Calls :func:`geomjax.{declaration.name}` with {bound}."]
    if binding.current_points is not None:
        lines.append(
            f"``{binding.current_points}`` must be unbatched ``(N, D)`` with the shape and dtype of ``self.points`` "
            "(``ValueError`` / ``TypeError`` otherwise); ``vmap`` this method for a batch."
        )
    else:
        lines.append("Returns a new ``Mesh`` with the moved points, this mesh's topology object and its data.")
    if binding.point_data_fields:
        names = " and ".join(f"``{name}``" for name in binding.point_data_fields)
        lines.append(f"{names} {_KEY_NOTE}.")
    if binding.requires is not None:
        lines += ["", "Raises:", f"    ValueError: unless the mesh has {_PRECONDITIONS[binding.requires][1]}."]
    lines += ["", f"See geomjax.{declaration.name} for the arguments, errors and backends."]
    return "\n".join(lines)


def _remesh_signature() -> inspect.Signature:
    """``Mesh.remesh``'s signature: its own arguments, then :func:`geomjax.remeshing`'s other options."""
    from .remesh.clustering import remeshing

    own = list(inspect.signature(Mesh.remesh).parameters.values())[:-1]  # without **remeshing_options
    taken = {parameter.name for parameter in own}
    options = [p for p in inspect.signature(remeshing).parameters.values() if p.kind is p.KEYWORD_ONLY and p.name not in taken]
    return inspect.signature(Mesh.remesh).replace(parameters=own + options)


_with_signature(Mesh.remesh, _remesh_signature())

for _declaration in REGISTRY.values():
    if _declaration.mesh_arguments is not None:
        if _declaration.mesh_method is None:
            raise AssertionError(f"{_declaration.name} declares mesh_arguments without a mesh_method to generate")
        setattr(Mesh, _declaration.mesh_method, _generated_method(_declaration, _declaration.mesh_arguments, _declaration.mesh_method))
    elif _declaration.mesh_method is not None and not hasattr(Mesh, _declaration.mesh_method):
        raise AssertionError(f"Mesh.{_declaration.mesh_method} (for {_declaration.name}) is neither generated nor written")


def _checked_box_extent(extent: jax.Array) -> jax.Array:
    valid = jnp.all(jnp.isfinite(extent) & (extent > jnp.zeros((), extent.dtype)))
    message = (
        "free_form_deform: the extent derived from the point bounding box must be finite and positive on every "
        "axis (flat or embedded geometry needs an explicit extent)"
    )
    if isinstance(extent, jax.core.Tracer):
        return runtime_check(extent, jnp.logical_not(valid), message, ValueError)
    if not bool(valid):
        raise ValueError(f"{message}, got {np.asarray(extent).tolist()}")
    return extent


# --------------------------------------------------------------------------------------------
# Eager validation and derived connectivity (NumPy, on concrete cells)


def _device_indices(indices: np.ndarray) -> jax.Array:
    # A concrete constant even when first requested inside a trace, so caching it leaks no tracer.
    with jax.ensure_compile_time_eval():
        return as_jax_array(indices.astype(np.int32))


def _validate_cells(cells, num_points: int, num_dims: int) -> np.ndarray:
    """Check raw cells and return them as an int64 NumPy array (see :class:`Mesh` for the rules)."""
    if isinstance(cells, jax.core.Tracer):
        raise TypeError(
            "cells must be a concrete integer array (topology is validated eagerly), got a traced value: build the Mesh outside jit or close over the cells"
        )
    if not is_array(cells):
        raise TypeError(f"cells must be an integer array, got {type(cells).__name__}")
    dtype = np.dtype(cells.dtype)
    if dtype == np.bool_ or dtype.kind not in "iu":
        raise TypeError(f"cells must have a non-bool integer dtype, got {dtype}")
    host = np.asarray(cells)
    if host.ndim != 2 or not 2 <= host.shape[1] <= 4:
        raise ValueError(f"cells must have shape (M, K) with K = 2, 3 or 4 vertices per cell (segments, triangles, tetrahedra), got {tuple(host.shape)}")
    if host.shape[1] - 1 > num_dims:
        raise ValueError(f"cells of manifold dimension {host.shape[1] - 1} cannot live in {num_dims}-D points (need K - 1 <= D)")
    if num_points >= 2**31:
        raise ValueError(f"a Mesh holds at most 2**31 - 1 points (int32 indices), got {num_points}")
    if host.size == 0:
        return np.zeros(host.shape, np.int64)
    if host.min() < 0 or host.max() >= num_points:
        bad = np.flatnonzero(np.any((host < 0) | (host >= num_points), axis=1))[0]
        raise ValueError(f"cells index range is [0, {num_points}); cell {bad} is {host[bad].tolist()}")
    host = host.astype(np.int64)
    ordered = np.sort(host, axis=1)
    repeated = np.flatnonzero(np.any(ordered[:, 1:] == ordered[:, :-1], axis=1))
    if repeated.size:
        bad = repeated[0]
        raise ValueError(f"every cell needs distinct vertices; cell {bad} is {host[bad].tolist()}")
    return host


def _check_data(name: str, data, num_rows: int, row_name: str) -> dict:
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise TypeError(f"{name} must be a mapping from names to arrays, got {type(data).__name__}")
    checked: dict[Any, jax.Array | dict] = {}
    for key, value in data.items():
        if isinstance(value, Mapping):
            checked[key] = _check_data(f"{name}[{key!r}]", value, num_rows, row_name)
            continue
        if not is_array(value):
            raise TypeError(f"{name}[{key!r}] must be an array, got {type(value).__name__}")
        value = value if isinstance(value, jax.Array) else jnp.asarray(value)
        if value.ndim == 0 or value.shape[0] != num_rows:
            raise ValueError(f"{name}[{key!r}] must have {row_name} = {num_rows} rows, got shape {tuple(value.shape)}")
        checked[key] = value
    return checked


def _leaf_paths(data: Mapping, prefix: tuple = ()) -> list[tuple]:
    paths = []
    for key, value in data.items():
        if isinstance(value, Mapping):
            paths.extend(_leaf_paths(value, prefix + (key,)))
        else:
            paths.append(prefix + (key,))
    return paths


def _unique_edges(cells: np.ndarray, num_points: int) -> np.ndarray:
    pairs = list(itertools.combinations(range(cells.shape[1]), 2))
    edges = np.sort(cells[:, pairs].reshape(-1, 2), axis=1)
    keys = np.unique(edges[:, 0] * num_points + edges[:, 1])
    return np.stack([keys // max(num_points, 1), keys % max(num_points, 1)], axis=1)


def _check_unique_triangles(triangles: np.ndarray, purpose: str) -> None:
    ordered = np.sort(triangles, axis=1)
    order = np.lexsort(ordered.T[::-1])
    ordered = ordered[order]
    same = np.flatnonzero(np.all(ordered[1:] == ordered[:-1], axis=1))
    if same.size:
        first, second = sorted(order[same[0] : same[0] + 2].tolist())
        raise ValueError(f"{purpose} needs unique triangles: cells {first} and {second} are the same face {triangles[first].tolist()}")


def _edge_incidence(triangles: np.ndarray):
    """Every triangle's three half-edges grouped by undirected edge.

    Returns per half-edge ``(u, v, face, opposite, forward)`` sorted by ``(u, v, face)``, where
    ``u < v`` is the undirected edge and ``forward`` says the face traverses it from ``u`` to
    ``v``, plus the start index and length of each run of one undirected edge.
    """
    tails = triangles.reshape(-1)
    heads = np.roll(triangles, -1, axis=1).reshape(-1)
    opposite = np.roll(triangles, -2, axis=1).reshape(-1)
    face = np.repeat(np.arange(triangles.shape[0]), 3)
    u, v = np.minimum(tails, heads), np.maximum(tails, heads)
    order = np.lexsort((face, v, u))
    u, v, face, opposite, forward = u[order], v[order], face[order], opposite[order], (tails < heads)[order]
    new_edge = np.ones(u.shape, bool)
    new_edge[1:] = (u[1:] != u[:-1]) | (v[1:] != v[:-1])
    starts = np.flatnonzero(new_edge)
    counts = np.diff(np.append(starts, u.shape[0]))
    return u, v, face, opposite, forward, starts, counts


def _build_hinges(triangles: np.ndarray) -> np.ndarray:
    """Interior hinges ``(u, v, k, l)`` of a triangle topology (see :attr:`Mesh.hinges`)."""
    if triangles.shape[0] == 0:
        return np.zeros((0, 4), np.int64)
    _check_unique_triangles(triangles, "surface bending hinges")
    u, v, _, opposite, _, starts, counts = _edge_incidence(triangles)
    crowded = np.flatnonzero(counts > 2)
    if crowded.size:
        edge = starts[crowded[0]]
        raise ValueError(
            f"surface bending hinges need at most two triangles per edge; edge ({u[edge]}, {v[edge]}) "
            f"belongs to {counts[crowded[0]]} triangles (non-manifold edge)"
        )
    interior = starts[counts == 2]
    return np.stack([u[interior], v[interior], opposite[interior], opposite[interior + 1]], axis=1)


def _check_closed_surface(triangles: np.ndarray) -> np.ndarray:
    """Check the closed-surface contract of volume energies and return the triangles."""
    if triangles.shape[0] == 0:
        raise ValueError("closed_surface_volume_energy needs a closed surface with at least one triangle, got none")
    _check_unique_triangles(triangles, "closed_surface_volume_energy")
    u, v, face, _, forward, starts, counts = _edge_incidence(triangles)
    wrong = np.flatnonzero(counts != 2)
    if wrong.size:
        edge, count = starts[wrong[0]], counts[wrong[0]]
        rule = "the surface is open (boundary edge)" if count == 1 else "the edge is non-manifold"
        raise ValueError(f"closed_surface_volume_energy needs every edge in exactly two triangles: edge ({u[edge]}, {v[edge]}) belongs to {count}, so {rule}")
    same_direction = np.flatnonzero(forward[starts] == forward[starts + 1])
    if same_direction.size:
        edge = starts[same_direction[0]]
        raise ValueError(
            "closed_surface_volume_energy needs consistently oriented triangles: cells "
            f"{face[edge]} and {face[edge + 1]} traverse edge ({u[edge]}, {v[edge]}) in the same direction"
        )
    components = _count_components(triangles.shape[0], face[starts], face[starts + 1])
    if components != 1:
        raise ValueError(f"closed_surface_volume_energy needs one edge-connected surface, got {components} components")
    return triangles


def _count_components(num_nodes: int, first: np.ndarray, second: np.ndarray) -> int:
    """Connected components of an undirected graph by vectorised hooking and pointer jumping."""
    labels = np.arange(num_nodes)
    while True:
        first_root, second_root = labels[first], labels[second]
        if np.array_equal(first_root, second_root):
            return int(np.unique(labels).size)
        # Hook the larger root under the smaller one: labels only decrease, so no cycles form.
        np.minimum.at(labels, np.maximum(first_root, second_root), np.minimum(first_root, second_root))
        while True:
            jumped = labels[labels]
            if np.array_equal(jumped, labels):
                break
            labels = jumped
