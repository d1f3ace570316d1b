"""Clustering remesher: integration-mass-weighted centroidal clustering of a triangle surface."""

from __future__ import annotations

import functools
import inspect
import math
import warnings
from concurrent.futures import Executor, Future, ThreadPoolExecutor
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import platform_of, select_implementation, warp_available
from .._errors import raises_documented_errors
from .._hash_grid import table_dims
from .._projection import SurfaceProjector
from .._sharding import outside_context_mesh
from .._validate import check_host_surface, check_host_vertex_field, check_integer, check_real_scalar
from ..sample.farthest import farthest_point_order
from ._flips import delaunay_flips, fold_flips
from ._patch_projection import PatchProjector
from ._quadrics import ClusterQuadrics, vertex_plane_terms
from ._surface_clusters import ClusterPatches, MeshEdges, SeedForest, VertexMoments, cluster_means, connected_clusters, mend_tears
from ._triangulation import (
    bending_density,
    boundary_vertices,
    collapse_poor_triangles,
    column_max,
    column_min,
    degenerate_vertices,
    drop_crowded_edges,
    nondegenerate,
    overturned_vertices,
    relabelled_triangles,
    relaxation_targets,
    relocate_poor_corners,
    remove_degree_three,
    row_cross,
    row_dot,
    row_norm,
    topology,
)

__all__ = ["remeshing", "remesh_with_sources", "RemeshResult", "RemeshTopologyWarning", "SurfaceProjector"]

_NAME = "remeshing"


MAX_HASH_GRID_RESOLUTION = 256
RADIUS_SCALE_CAP = 12.0  # the search radius never exceeds max(s, 12) cluster spacings
MASS_FLOOR = float(np.finfo(np.float32).tiny)
RELAXATION_ITERATIONS = 4  # surface relaxation rounds after the clustering (see remeshing)
# From this many faces the Warp kernel computes the faces' geometry faster than NumPy (icospheres:
# 20k faces 0.36 against 0.28 ms, 82k faces 1.6 against 3.1 ms).
FACE_KERNEL_MIN_FACES = 32768
# Relaxation keeps each vertex within this many cluster spacings of its cluster's point: it
# shapes the triangles, it must not drag a vertex off the feature its cluster holds (a tip).
RELAXATION_REACH = 0.5
GRAPH_LLOYD_ROUNDS = 2  # Lloyd rounds on the surface's edge graph after the Euclidean ones
TEAR_REPAIR_ROUNDS = 12  # rounds of mending fins and pinches of the cluster layout
# Below this many vertices the background thread's work runs on the calling thread: handing it
# over costs more than the overlap saves. A core that has idled since the last call takes about
# 0.1 ms to wake, and the handed-over NumPy work contends for the GIL; remeshes to 500 clusters
# after a 50 ms pause were 1.4-2 ms faster inline on the shared meshes of 500 to 4,500 vertices,
# even on lion's 8,400 and 0.5 ms slower on camelhead's 11,400.
BACKGROUND_MIN_VERTICES = 8192


class RemeshTopologyWarning(UserWarning):
    """The remeshed surface's topology (closedness, Euler characteristic) differs from the input's.

    :func:`remeshing` and :meth:`geomjax.Mesh.remesh` warn with it when the clusters are too few
    to resolve a thin part or a tunnel of the input. Turn it into an error where a topology
    change must not pass:

    Example:
        >>> import warnings
        >>> from geomjax import RemeshTopologyWarning, icosphere, remeshing
        >>> sphere = icosphere(3)
        >>> with warnings.catch_warnings():
        ...     warnings.simplefilter("error", RemeshTopologyWarning)
        ...     vertices, faces = remeshing(sphere.points, sphere.cells, 100)
        >>> print(vertices.shape[0] - 3 * faces.shape[0] // 2 + faces.shape[0])  # Euler characteristic
        2
    """


class RemeshResult(NamedTuple):
    """A remeshed surface and where each of its vertices lies on the source surface.

    Attributes:
        vertices: ``(K', 3)`` positions in the input dtype and frame, on the source surface.
        faces: ``(F', 3)`` triangle indices (int64 for int64 input indices, else int32).
        source_faces: ``(K',)`` int32 index of the source triangle holding each vertex.
        barycentric: ``(K', 3)`` weights of that triangle's corners (input dtype), so that
            ``vertices = sum_k barycentric[:, k, None] * mesh_vertices[mesh_indices[source_faces, k]]``.
    """

    vertices: jax.Array
    faces: jax.Array
    source_faces: jax.Array
    barycentric: jax.Array


@raises_documented_errors
def remeshing(
    mesh_vertices: Float[Array, "num_vertices 3"],
    mesh_indices: Int[Array, "num_faces 3"],
    n_clusters: int,
    *,
    max_iterations: int = 4,
    vertex_density: Float[Array, " num_vertices"] | None = None,
    search_radius_scale: float = 1.6,
    voxel_width_scale: float = 1.15,
    hash_grid_resolution: int = 128,
    farthest_point_threshold: int = 256,
    farthest_point_oversampling: int = 4,
    implementation: str | None = None,
) -> tuple[Float[Array, "num_output_vertices 3"], Int[Array, "num_output_faces 3"]]:
    """Remesh a triangle surface to about ``n_clusters`` vertices by centroidal clustering.

    1. Coordinates are centred on the bounding-box midpoint and scaled by the largest half
       extent. Each vertex gets an integration mass: a third of the area of its triangles,
       times ``rho = density / max(density)`` for a non-constant ``vertex_density`` (a constant
       density is uniform), floored at the float32 ``tiny`` and rescaled to the total area.
    2. ``K = n_clusters`` seeds are input vertices: for ``K <= farthest_point_threshold``,
       farthest-point sampling (:func:`geomjax.farthest_point_sampling`, first candidate
       first) of ``min(V, farthest_point_oversampling K)`` candidates drawn by mass without
       replacement; else, with a density, ``K`` vertices drawn by ``area sqrt(rho)`` (the ideal
       2-D generator density); else one vertex (the lowest index) per occupied voxel of width
       ``voxel_width_scale sqrt(A / K)``, a random subset when there are more than ``K`` and a
       mass-weighted draw from the other vertices when fewer. Draws use NumPy's generator with
       seed 0, so the result is deterministic.
    3. ``max_iterations`` Lloyd iterations: each vertex joins its nearest centroid (ties: the
       lowest centroid index), then each centroid moves to the mass-weighted mean of its
       vertices (an empty cluster keeps its position). Then (not in the reference) the
       clusters become regions of the surface: 2 more Lloyd rounds in which each vertex joins
       the cluster whose seed (the member closest to its centroid; at first, the member of the
       last assignment closest to the final centroid) is nearest along the mesh's edges
       (Dijkstra), so no cluster reaches across a thin part or a narrow gap; and up to 12
       rounds that mend the layouts whose relabelled triangles would not be a surface (a
       cluster squeezed between two others gives up its seed; two clusters meeting along two
       arcs get one of them split, the smallest other cluster giving up its seed).
    4. A point per cluster on the source surface: the reference projects the centroid onto
       the closest point of the source surface (a Warp BVH search, or brute force on the JAX
       path, then :func:`geomjax._geometry.closest_point_on_triangle`). geomjax first moves
       it to the point closest to the planes of the cluster's triangles, along the directions
       in which they bend (across a crease, onto a tip), so that features are not cut off, and
       takes the closest point of the cluster's own *patch* (the source triangles with a
       corner in the cluster; ties, distances within 64 epsilons of the coordinates'
       magnitude: the lowest triangle index, alike on both backends), which keeps it on its
       own sheet where the surface passes close to itself.
    5. Topology: every input triangle is relabelled by its vertices' clusters; triangles with a
       repeated label are dropped, duplicates (in any orientation) keep their first occurrence,
       triangles of zero area after projection are dropped (geomjax first puts their corners
       back on the projected centroids), and while an edge has more than two triangles one
       triangle per such edge is removed (the one touching the most such edges, then the
       smallest, then the lowest index).
    6. Relaxation on the surface (not in the reference, which stops at step 5): 4 rounds of one
       round of Delaunay edge flips (an interior edge whose opposite angles sum to more than pi
       is flipped, unless that would fold the pair, duplicate an edge, leave a vertex with
       fewer than three edges, or cut a crease of more than 20 degrees) followed by an
       optimal-Delaunay-triangulation step: each interior vertex moves towards the
       mass-weighted mean of the circumcentres of its triangles (the midpoint of the longest
       edge for an obtuse one), within the directions in which its cluster's triangles are
       flat (in the tangent plane, along a crease, not at a tip or corner), at most half a
       cluster spacing from its point of step 5 in all, and is projected onto its cluster's
       patch again; a move that would overturn a triangle is undone. A triangle's mass is its
       area times the mean over its corners of ``1 + (s / mean s)^2`` (times the density, if
       given), ``s`` a vertex's largest edge sagitta ``|(b - a) . (n_b - n_a)| / 8`` (``n``:
       the unit mean normals of the ends' clusters): vertices gather where the surface bends
       away from the triangles. Boundary vertices stay. A complete flip pass follows; then each interior vertex of
       degree three that lies near the plane of its neighbours is removed, and the shortest
       edge of each triangle with an angle below 12 degrees is collapsed into its endpoint on
       the stronger feature, where that keeps the topology, turns no triangle over and
       improves the triangles. Then the 16 pairs of triangles that stand farthest off the
       surface by an estimate from their clusters' normals, and whose other diagonal is
       estimated 10% closer, are measured (distances from their centroids and diagonals'
       midpoints to the patches), and flipped where the other diagonal is measured 10% closer
       and both new triangles keep angles of 20 degrees or more. The corners of the triangles
       still below 12 degrees (a needle across a strip narrower than the spacing, which no
       collapse improves) then try points 0.1, 0.25 and 0.5 of the way to each neighbour,
       within the same directions and back on their patches, and take the one that most
       raises the smallest angle of their triangles without turning one over (up to 4
       rounds); last, the checks of step 5. This raises the radius ratios and the smallest
       angles and keeps tips and creases, at a few times the cost of steps 1 to 5
       (``benchmarks/bench_sampling_remesh.py`` and ``benchmarks/bench_real_meshes.py``
       measure both, against pyacvd). Unused vertices are dropped and the result is returned
       in the input frame and dtype.

    The output is manifold in the sense that every edge has at most two triangles, and every
    vertex lies on the source surface (on its cluster's patch). A closed input stays closed and
    keeps its Euler characteristic (genus) whenever the clusters can resolve its thin parts and
    tunnels; where they cannot, a :class:`RemeshTopologyWarning` says so (use more clusters).
    Output vertices are not welded by position.

    Args:
        mesh_vertices: ``(V, 3)`` float32 or float64, finite, ``V >= 3``. Computations run in
            this dtype (the reference always uses float32).
        mesh_indices: ``(F, 3)`` indices of any integer dtype (not bool), ``F >= 1``, in
            ``[0, V)``, on the device of the vertices. The total area must be positive.
        n_clusters: target vertex count ``K``, integer with ``3 <= K <= V``. The output has
            between 3 and ``K`` vertices.
        max_iterations: Lloyd iterations, integer ``>= 0``.
        vertex_density: optional ``(V,)`` float32/float64 positive finite relative density
            (more output vertices where it is larger; scale-invariant).
        search_radius_scale: positive real ``s``; the Warp path searches centroids within
            ``min(s f, max(s, 12)) sqrt(A / K)`` first (``f = sqrt(mean / min)`` of the
            generator density ``sqrt(rho)``, 1 when uniform), scanning all centroids for a
            vertex with none that close. The result is the nearest centroid either way: the
            radius only sets the speed.
        voxel_width_scale: positive real, the stratification voxel width of step 2.
        hash_grid_resolution: integer in ``[1, 256]``, dimensions of the centroid hash table
            (clamped to the cells the surface spans, at least 3).
        farthest_point_threshold: integer ``>= 0``; 0 disables farthest-point seeding.
        farthest_point_oversampling: integer ``>= 1``.
        implementation: ``"warp"``, ``"jax"`` (also ``"torch"``) or ``None``. Warp assigns
            vertices on a hash grid of centroids and measures each point against its patch's
            triangles in a kernel (both CPU cores); the JAX path compares every vertex with
            every centroid and measures every (point, patch triangle) pair at once (a reference
            for small meshes). Both share the seeding and the topology step (host NumPy).
            ``None`` picks Warp on every platform when warp-lang is installed
            (``benchmarks/bench_sampling_remesh.py`` measures it on CPU), JAX otherwise.

    Returns:
        ``(vertices, faces)``: ``(K', 3)`` vertices in the input dtype on the input device, and
        ``(F', 3)`` faces (int64 for int64 ``mesh_indices``, else int32).

    Raises:
        TypeError: non-float vertices or density, non-integer or bool indices, non-integer
            counts, non-real scales, traced inputs (the output size depends on the data, so this
            runs eagerly: call it outside ``jit``).
        ValueError: bad shapes, ``V < 3``, ``K`` outside ``[3, V]``, indices out of range,
            non-finite vertices, coordinates beyond the square root of the dtype's range, a
            non-positive or non-finite density, out-of-range options, a zero-area surface, an
            input split across processes (a multi-host array: this runs on one host; replicated
            arrays and arrays on several local devices are read from one device, also under
            ``jax.set_mesh``).
        RuntimeError: no triangle survives the topology step.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.

    Warns:
        RemeshTopologyWarning: the result's Euler characteristic differs from the input's, or
            a closed input came out with boundary edges (too few clusters for its thin parts).

    Not differentiable. Deterministic on CPU for a given machine (the Warp path's assignment is
    exact; its centroid sums are NumPy sums in a fixed order). :meth:`geomjax.Mesh.remesh` adds
    barycentric transfer of point data, differentiable with respect to the data.

    Example:
        >>> import numpy as np
        >>> from geomjax import icosphere, remeshing
        >>> sphere = icosphere(3)
        >>> vertices, faces = remeshing(sphere.points, sphere.cells, 100, implementation="jax")
        >>> print(vertices.shape[0] <= 100, faces.shape[1])
        True 3
        >>> print(np.round(float(np.abs(np.linalg.norm(np.asarray(vertices), axis=1) - 1).max()), 2))
        0.0
    """
    result = remesh_with_sources(
        mesh_vertices, mesh_indices, n_clusters, max_iterations=max_iterations, vertex_density=vertex_density,
        search_radius_scale=search_radius_scale, voxel_width_scale=voxel_width_scale,
        hash_grid_resolution=hash_grid_resolution, farthest_point_threshold=farthest_point_threshold,
        farthest_point_oversampling=farthest_point_oversampling, implementation=implementation,
    )  # fmt: skip
    return result.vertices, result.faces


@outside_context_mesh
def remesh_with_sources(
    mesh_vertices: Float[Array, "num_vertices 3"],
    # Host indices too: Mesh.remesh passes its validated NumPy cells (no device round trip).
    mesh_indices: Int[Array, "num_faces 3"] | Int[np.ndarray, "num_faces 3"],
    n_clusters: int,
    *,
    density_exponent: float = 1.0,
    relaxation_iterations: int = RELAXATION_ITERATIONS,
    reference: bool = False,
    **options,
) -> RemeshResult:
    """:func:`remeshing`, also returning the source triangle and weights of each new vertex.

    Takes the arguments of :func:`remeshing` (its keyword options, with its defaults, passed
    through ``options``), plus ``density_exponent`` ``p`` (a positive real): the mass density is
    ``rho = (vertex_density / max)^p``. :func:`remeshing` uses ``p = 1``;
    :meth:`geomjax.Mesh.remesh` uses ``p = 4`` for a ``resolution_field`` (a linear
    resolution ``r`` is a CVT density ``r^4``); ``relaxation_iterations`` (integer ``>= 0``,
    default 4): the rounds of step 6; and ``reference`` (bool, default False): True runs the
    reference's algorithm (Euclidean clusters, projected centroids, steps 1 to 5 only). Returns a
    :class:`RemeshResult`.

    Example:
        >>> import numpy as np
        >>> from geomjax import icosphere
        >>> from geomjax.remesh.clustering import remesh_with_sources
        >>> sphere = icosphere(2)
        >>> result = remesh_with_sources(sphere.points, sphere.cells, 40, implementation="jax")
        >>> corners = np.asarray(sphere.points)[np.asarray(sphere.cells)[np.asarray(result.source_faces)]]
        >>> rebuilt = np.einsum("vk,vkd->vd", np.asarray(result.barycentric), corners)
        >>> print(np.allclose(rebuilt, np.asarray(result.vertices)))
        True
    """
    options = remesh_options(options)
    if not isinstance(reference, bool):
        raise TypeError(f"reference must be a bool, got {type(reference).__name__}")
    vertices, faces = check_host_surface(_NAME, mesh_vertices, mesh_indices, min_vertices=3)
    num_vertices = vertices.shape[0]
    n_clusters = check_integer("n_clusters", n_clusters, minimum=3)
    if n_clusters > num_vertices:
        raise ValueError(f"n_clusters must be at most the number of vertices {num_vertices}, got {n_clusters}")
    max_iterations = check_integer("max_iterations", options["max_iterations"], minimum=0)
    density = _checked_density(options["vertex_density"], vertices)
    dtype = np.dtype(vertices.dtype)
    exponent = check_real_scalar("density_exponent", density_exponent, dtype, positive=True)
    relaxation_iterations = check_integer("relaxation_iterations", relaxation_iterations, minimum=0)
    search_radius_scale = check_real_scalar("search_radius_scale", options["search_radius_scale"], dtype, positive=True)
    voxel_width_scale = check_real_scalar("voxel_width_scale", options["voxel_width_scale"], dtype, positive=True)
    resolution = check_integer("hash_grid_resolution", options["hash_grid_resolution"], minimum=1)
    if resolution > MAX_HASH_GRID_RESOLUTION:
        raise ValueError(f"hash_grid_resolution must be at most {MAX_HASH_GRID_RESOLUTION}, got {resolution}")
    farthest_point_threshold = check_integer("farthest_point_threshold", options["farthest_point_threshold"], minimum=0)
    farthest_point_oversampling = check_integer("farthest_point_oversampling", options["farthest_point_oversampling"], minimum=1)
    # Not differentiated: only the backend's name matters here.
    backend = select_implementation(_NAME, options["implementation"], platform=platform_of(vertices)).name
    device = next(iter(vertices.devices()))
    host = np.asarray(vertices)
    low, high = column_min(host), column_max(host)
    # Steps 4 to 6 measure the output in the input frame: areas and distances there square the
    # coordinates.
    largest = float(np.max(np.maximum(-low, high)))
    if largest > (limit := math.sqrt(float(np.finfo(dtype).max)) / 4):
        raise ValueError(
            f"{_NAME}: vertex coordinates must be at most {limit:.3g} in magnitude in {dtype} (their squares overflow), got {largest:.3g}: rescale the mesh"
        )
    # The reference's search tree (Warp kernels, which run outside the GIL) is built on another
    # thread while the host work of steps 1 to 3 runs (on larger meshes: see
    # BACKGROUND_MIN_VERTICES).
    helper = _background() if num_vertices >= BACKGROUND_MIN_VERTICES else _Inline()
    projector = helper.submit(SurfaceProjector, vertices, faces, backend, _NAME) if reference else None

    # 1. Normalised frame, areas and integration masses.
    centre = (low + high) / 2
    scale = float(np.max(high - low)) / 2
    if scale == 0.0:
        raise ValueError(f"{_NAME}: the surface has zero area (all vertices coincide)")
    x = ((host - centre) / scale).astype(dtype)
    first_corners, doubled_normals, face_area = _face_geometry(x, faces)
    total_area = float(face_area.sum())
    if not total_area > 0.0:
        raise ValueError(f"{_NAME}: the surface has zero area")
    vertex_area = np.bincount(faces.reshape(-1), weights=np.repeat(face_area / 3, 3), minlength=num_vertices)
    rho = None if density is None else (density / density.max()) ** exponent
    mass = vertex_area if rho is None else vertex_area * rho
    mass = np.maximum(mass, MASS_FLOOR)
    mass *= total_area / mass.sum()
    if not np.all(np.isfinite(mass)):
        raise ValueError(f"{_NAME}: the integration masses are not finite (density out of range)")
    spacing = math.sqrt(total_area / n_clusters)

    # 2. Seeds (farthest-point ones: XLA computes them while the host work submitted below runs).
    rng = np.random.default_rng(0)
    voxels = picked = None
    if n_clusters <= farthest_point_threshold:
        pool = rng.choice(num_vertices, min(num_vertices, farthest_point_oversampling * n_clusters), replace=False, p=mass / mass.sum())
        picked = farthest_point_order(x[pool], n_clusters, device)
    elif rho is not None:
        weight = np.maximum(vertex_area * np.sqrt(rho), MASS_FLOOR)
        seeds = rng.choice(num_vertices, n_clusters, replace=False, p=weight / weight.sum())
    else:
        seeds, voxels = _stratified_seeds(x, mass, n_clusters, voxel_width_scale * spacing, rng)

    # 3. Lloyd iterations.
    spread = 1.0
    if rho is not None:
        generator_density = np.sqrt(rho[vertex_area > 0])
        spread = math.sqrt(float(np.average(generator_density, weights=vertex_area[vertex_area > 0]) / generator_density.min()))
    radius = min(search_radius_scale * spread, max(search_radius_scale, RADIUS_SCALE_CAP)) * spacing
    moments = VertexMoments.of(x, mass)
    # The edge graph of the graph rounds below and the vertices' plane terms of step 4 are
    # computed on the background thread while the Lloyd iterations run (their Warp kernels
    # release the GIL between the host steps); below BACKGROUND_MIN_VERTICES, on this thread
    # while XLA computes farthest-point seeds.
    edge_graph = None if projector is not None else helper.submit(MeshEdges.of, x, faces)
    plane_terms = None if projector is not None else helper.submit(vertex_plane_terms, faces, first_corners, doubled_normals, face_area, num_vertices)
    if picked is not None:
        seeds = pool[np.asarray(picked)[0]]
    centroids = x[seeds]
    # The reference's labels are those of a last assignment to the final centroids; the graph
    # rounds below replace them, and take their seeds from the assignment that gave the final
    # centroids (a search less).
    final = projector is not None
    if backend == "warp":
        centroids, labels = _lloyd_warp(x, moments, centroids, max_iterations, radius, resolution, device, final, voxels)
    else:
        centroids, labels = _lloyd_jax(x, moments, centroids, max_iterations, device, final)
    index_dtype = jnp.int64 if np.dtype(mesh_indices.dtype) == np.int64 else jnp.int32
    if projector is not None:
        # 4. and 5. as the reference: projected centroids and their relabelled triangles.
        positions, source_faces, barycentric = projector.result()((centroids * scale + centre).astype(dtype))
        triangles = _surviving(relabelled_triangles(labels, np.ascontiguousarray(faces.T)), positions, "topology reconstruction")
        return _result(positions, triangles, source_faces, barycentric, index_dtype, device)
    assert edge_graph is not None  # submitted unless the reference returned above
    edges = edge_graph.result()
    forest = SeedForest(edges, labels, n_clusters)
    centroids = connected_clusters(forest, x, moments, centroids, GRAPH_LLOYD_ROUNDS)
    centroids, triangles = mend_tears(edges, forest, x, np.ascontiguousarray(faces.T), moments, centroids, TEAR_REPAIR_ROUNDS)
    labels = forest.labels

    # 4. A point per cluster on its patch of the source surface, in the input frame.
    # The patches and their search (whose bounding spheres come from a Warp kernel outside the
    # GIL) are set up on the background thread while the quadrics are summed here.
    setup = helper.submit(lambda: PatchProjector(vertices, faces, ClusterPatches.of(faces, labels, n_clusters), backend))
    assert plane_terms is not None  # submitted with the edge graph
    quadrics = ClusterQuadrics.of(plane_terms.result(), labels, n_clusters)
    project = setup.result()
    positions, source_faces, barycentric = project((quadrics.snap(centroids, spacing) * scale + centre).astype(dtype))

    # 5. Topology (the relabelled triangles came with the last check of the mending).
    flat = degenerate_vertices(triangles, positions, n_clusters)
    if np.any(flat):  # quadric points that make a triangle flat fall back to the centroids
        positions, source_faces, barycentric = (np.array(a) for a in (positions, source_faces, barycentric))
        positions[flat], source_faces[flat], barycentric[flat] = project((centroids[flat] * scale + centre).astype(dtype), np.flatnonzero(flat))
    triangles = _surviving(triangles, positions, "topology reconstruction")

    # 6. Relaxation on the surface. Flips and the removals below touch interior edges and
    # vertices only, so the boundary vertices stay those of step 5.
    fixed = boundary_vertices(triangles, n_clusters)
    anchors = positions.astype(np.float64)
    for _ in range(relaxation_iterations):
        # One round per step: the next steps continue the flips, the final pass completes them.
        triangles = delaunay_flips(positions, triangles, rounds=1)
        vertex_rho = bending_density(positions, triangles, quadrics.normals)
        if rho is not None:
            vertex_rho *= np.einsum("vk,vk->v", barycentric, rho[faces[source_faces]])
        targets = relaxation_targets(positions, triangles, vertex_rho, fixed)
        targets = _within_reach(anchors, positions + quadrics.free_moves(targets - positions), RELAXATION_REACH * spacing * scale)
        moved = project(targets.astype(dtype), hints=source_faces)
        # A step that would overturn a triangle is undone for that triangle's vertices.
        undo = overturned_vertices(positions, moved[0], triangles)
        positions = np.where(undo[:, None], positions, moved[0])
        source_faces = np.where(undo, source_faces, moved[1])
        barycentric = np.where(undo[:, None], barycentric, moved[2])
    if relaxation_iterations:
        # Flips stop at degree three, so the degree-three vertices go after them; the last
        # needles and caps (at creases and tips, which flips and moves keep) lose an edge.
        triangles = remove_degree_three(positions, delaunay_flips(positions, triangles), n_clusters)
        triangles = collapse_poor_triangles(positions, triangles, fixed, quadrics.crease_strength())
        triangles = fold_flips(positions, triangles, quadrics.normals, lambda points, vertices: row_norm(points - project(points.astype(dtype), vertices)[0]))

        # The needles that no collapse removes: their corners move on their patches (along
        # the crease, for a vertex on one).
        def place(vertex, start, move):
            return project((start + quadrics.free_moves(move, vertex)).astype(dtype), vertex)

        positions, source_faces, barycentric = relocate_poor_corners((positions, source_faces, barycentric), triangles, fixed, place)
        triangles = _surviving(triangles, positions, "relaxation")
    _warn_if_topology_changed(edges, triangles, n_clusters)
    return _result(positions, triangles, source_faces, barycentric, index_dtype, device)


@functools.cache
def _background() -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=1, thread_name_prefix="geomjax-remesh")


class _Inline(Executor):
    """An executor that runs each call at once, on the calling thread."""

    def submit(self, fn, /, *args, **kwargs) -> Future:
        future: Future = Future()
        try:
            future.set_result(fn(*args, **kwargs))
        except BaseException as error:  # raised by .result(), as from the thread
            future.set_exception(error)
        return future


def _within_reach(anchors: np.ndarray, points: np.ndarray, reach: float) -> np.ndarray:
    """``points`` ``(V, 3)`` pulled back to within ``reach`` of their ``anchors``."""
    offset = points - anchors
    distance = row_norm(offset)
    # reach / max(distance, reach): 1 within reach, no overflow at distance 0.
    return anchors + offset * (reach / np.maximum(distance, reach))[:, None]


def _surviving(triangles: np.ndarray, positions: np.ndarray, step: str) -> np.ndarray:
    """The triangles of non-zero area, at most two per edge; ``RuntimeError`` if none is left."""
    triangles = drop_crowded_edges(*nondegenerate(triangles, positions)) if triangles.shape[0] else triangles
    if triangles.shape[0] == 0:
        raise RuntimeError(f"{_NAME}: no triangle survived the {step} (try more clusters)")
    return triangles


def _result(positions, triangles, source_faces, barycentric, index_dtype, device) -> RemeshResult:
    """The used vertices, renumbered, on ``device``."""
    # The used vertices ascending and their new numbers (np.unique's, by counting: no sort).
    used = np.flatnonzero(np.bincount(triangles.reshape(-1), minlength=positions.shape[0]))
    renumbered = np.zeros(positions.shape[0], jax.dtypes.canonicalize_dtype(index_dtype))
    renumbered[used] = np.arange(used.size)
    faces = renumbered[triangles]
    # One transfer call for the four (a call per array costs twice as much on small outputs).
    return RemeshResult(*jax.device_put((positions[used], faces, source_faces[used].astype(np.int32), barycentric[used]), device))


# ---------------------------------------------------------------------------------------------
# Validation.


def remesh_options(options: dict, *, exclude: tuple[str, ...] = ()) -> dict:
    """:func:`remeshing`'s keyword options (but ``exclude``), completed with its defaults.

    One list of options and defaults serves the public function, ``remesh_with_sources`` and
    ``Mesh.remesh``; an unknown name is a ``TypeError``, as for a misspelt keyword argument.
    """
    keyword_only = {name: default for name, default in _remeshing_defaults().items() if name not in exclude}
    unknown = sorted(set(options) - set(keyword_only))
    if unknown:
        raise TypeError(f"{_NAME} got unexpected keyword arguments {unknown}; its options are {list(keyword_only)}")
    return {name: options.get(name, default) for name, default in keyword_only.items()}


@functools.cache
def _remeshing_defaults() -> dict:
    """:func:`remeshing`'s keyword-only options and their defaults (reading the signature costs
    0.1 ms a call)."""
    return {name: parameter.default for name, parameter in inspect.signature(remeshing).parameters.items() if parameter.kind is inspect.Parameter.KEYWORD_ONLY}


def _checked_density(vertex_density, vertices: jax.Array) -> np.ndarray | None:
    """``None`` for no or constant density, else the host density in the vertices' dtype."""
    host = check_host_vertex_field(_NAME, "vertex_density", vertex_density, vertices)
    if host is None or host.min() == host.max():
        return None
    return host.astype(vertices.dtype)


# ---------------------------------------------------------------------------------------------
# Geometry and seeding (host NumPy, shared by both backends).


def _face_geometry(x: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each face's first corner, ``(b - a) x (c - a)`` (``(F, 3)`` each) and area ``(F,)``, in
    float64: once for the masses and the quadrics. With warp-lang and at least
    ``FACE_KERNEL_MIN_FACES`` faces a kernel on the CPU cores (``warp_ffi.remesh.face_geometry``,
    the same bits: the same roundings in the same order)."""
    if faces.shape[0] >= FACE_KERNEL_MIN_FACES and warp_available():
        from warp_ffi.remesh import face_geometry

        return face_geometry(x, faces)
    # np.take gathers rows several times faster than fancy indexing.
    a, b, c = (np.take(x, faces[:, k], axis=0).astype(np.float64, copy=False) for k in range(3))
    doubled_normals = row_cross(b - a, c - a)
    return a, doubled_normals, 0.5 * np.sqrt(row_dot(doubled_normals, doubled_normals))


def _stratified_seeds(x: np.ndarray, mass: np.ndarray, count: int, width: float, rng: np.random.Generator) -> tuple[np.ndarray, Voxels]:
    """One vertex (the lowest index) per occupied voxel, subsampled or topped up to ``count``;
    and the voxels."""
    # Non-negative, so truncation is the floor.
    cells = ((x - column_min(x)) / width).astype(np.int64)
    dims = column_max(cells) + 1
    keys = cells[:, 0] + dims[0] * (cells[:, 1] + dims[1] * cells[:, 2])
    # A stable sort of 16-bit keys is a radix sort: ten times faster than of 64-bit ones.
    order = np.argsort(keys.astype(np.uint16) if np.prod(dims) <= 1 << 16 else keys, kind="stable")
    first = np.ones(order.size, bool)
    first[1:] = keys[order[1:]] != keys[order[:-1]]
    voxel = np.empty(order.size, np.int64)
    voxel[order] = np.cumsum(first) - 1
    voxels = Voxels(order[first], voxel)
    seeds = voxels.representatives
    if seeds.size > count:
        return seeds[np.sort(rng.permutation(seeds.size)[:count])], voxels
    if seeds.size < count:
        # The other vertices, ascending (np.setdiff1d sorts: 200x slower on 40k vertices).
        rest = np.flatnonzero(np.bincount(seeds, minlength=x.shape[0]) == 0)
        extra = rng.choice(rest, count - seeds.size, replace=False, p=mass[rest] / mass[rest].sum())
        seeds = np.concatenate([seeds, extra])
    return seeds, voxels


class Voxels(NamedTuple):
    """The seeding's voxels: each occupied voxel's lowest vertex index (ascending) and each
    vertex's voxel (an index into ``representatives``)."""

    representatives: np.ndarray
    voxel: np.ndarray


# ---------------------------------------------------------------------------------------------
# Lloyd iterations.


def _lloyd_warp(x, moments, centroids, iterations, radius, resolution, device, final, voxels: Voxels | None = None):
    """Lloyd's iterations on the Warp hash grid: the final centroids and the labels of the last
    assignment (to the final centroids if ``final``, else to those before the last means).
    Labels that repeat are a fixed point: the iterations stop there, with the same results.

    With the seeding's ``voxels``, the first search starts from a guess: each vertex's voxel's
    representative's nearest centroid (a search of a few points per cluster; the labels are
    the same without, the first search from scratch costs 20% more on the shared meshes).
    """
    import warp

    from warp_ffi.remesh import CentroidSearch

    warp_device = str(warp.device_from_jax(device))
    # Cells four times the first search radius (radius / 2): that search visits 1 to 8 cells.
    # Warp's cost per visited cell outweighs the extra centroids in each: on the shared meshes
    # this is 20-25% faster than cells of half the width, and wider ones are no faster.
    cell = 2 * radius
    low, high = column_min(x) - radius, column_max(x) + radius
    dims = table_dims(low, high, cell, (resolution,) * 3)
    search = CentroidSearch(x, radius, cell, dims, warp_device)
    # One core is left to the edge graph (or the reference's search tree), built meanwhile on the
    # background thread.
    nearest = functools.partial(search, spare_threads=1)
    guess = None
    if voxels is not None:
        guess = CentroidSearch(x[voxels.representatives], radius, cell, dims, warp_device)(centroids, spare_threads=1)[voxels.voxel]
    labels = None
    for _ in range(iterations):
        previous = labels
        labels = nearest(centroids, guess if previous is None else previous)
        if previous is not None and np.array_equal(labels, previous):
            # A fixed point: the means of these labels are the centroids they were assigned to
            # (an empty cluster keeps its centroid), so every later iteration repeats both.
            return centroids, labels
        centroids = cluster_means(moments, labels, centroids)
    if final or labels is None:
        labels = nearest(centroids, guess if labels is None else labels)
    return centroids, labels


def _lloyd_jax(x, moments, centroids, iterations, device, final):
    """Lloyd's iterations as :func:`_lloyd_warp`: the nearest centroids from JAX on ``device``, the
    means from :func:`cluster_means` on the host with the host ``moments``, as on the Warp
    path (the same centroids to the bit, so that the assignments agree on both backends, ties
    included)."""
    points = jax.device_put(x, device)
    labels = np.asarray(_nearest_jax(points, jax.device_put(centroids, device)))
    for iteration in range(iterations):
        centroids = cluster_means(moments, labels, centroids)
        if final or iteration < iterations - 1:
            previous, labels = labels, np.asarray(_nearest_jax(points, jax.device_put(centroids, device)))
            if np.array_equal(labels, previous):
                break  # a fixed point (see _lloyd_warp)
    return centroids, labels


@jax.jit
def _nearest_jax(x, centroids):
    """``(N,)`` int32: the nearest centroid of each point (ties: the lowest index)."""
    block = query_block_size(x.shape[0], centroids.shape[0] * x.dtype.itemsize * 8)

    def block_labels(p):
        # max(square, 0) (a no-op) keeps XLA from fusing a product into the sum (a fused
        # multiply-add, rounded once): each product is rounded, as in the Warp kernel and
        # NumPy, so exact ties between centroids (common on regular meshes) fall the same way
        # on both backends.
        squares = jnp.maximum(jnp.square(centroids[None, :, :] - p[:, None, :]), 0)
        d2 = squares[..., 0] + squares[..., 1] + squares[..., 2]
        return jnp.argmin(d2, axis=1).astype(jnp.int32)

    return map_query_blocks(block_labels, (x,), block_size=block)


def _warn_if_topology_changed(edges: MeshEdges, triangles: np.ndarray, n_clusters: int) -> None:
    """Warn when the remesh lost the input's Euler characteristic, or a closed input its closedness."""
    euler, boundary = topology(triangles)
    if euler == edges.euler and (edges.boundary.size or not boundary):
        return
    found = f"Euler characteristic {euler} and {boundary} boundary edges"
    expected = f"Euler characteristic {edges.euler}" + ("" if edges.boundary.size else ", closed")
    warnings.warn(
        f"{_NAME}: the remeshed surface's topology differs from the input's ({found}; the input: {expected}): "
        f"{n_clusters} clusters cannot resolve its thin parts or tunnels there; use more clusters",
        RemeshTopologyWarning,
        stacklevel=4,
    )
