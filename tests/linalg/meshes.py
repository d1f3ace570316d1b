"""Small simplicial meshes and an independent dense Sobolev reference, shared by the Sobolev tests.

The reference computes local stiffness from barycentric gradients through a pseudo-inverse of the
edge matrix (not the Gram inverse the library uses), assembles dense matrices and solves with
``jnp.linalg.solve``; it is written in ``jax.numpy`` so that its autodiff gradients can serve as an
independent check of the implicit adjoint.
"""

import functools
import itertools
import math

import jax
import jax.numpy as jnp
import numpy as np


def polyline(num_points, dim, seed=0):
    """A jittered open curve in ``dim`` dimensions with segments ``(i, i + 1)``."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, num_points)
    points = np.zeros((num_points, dim))
    points[:, 0] = t + rng.uniform(-0.2, 0.2, num_points) / num_points
    for k in range(1, dim):
        points[:, k] = 0.2 * np.sin((k + 1) * np.pi * t)
    cells = np.stack([np.arange(num_points - 1), np.arange(1, num_points)], axis=1)
    return points, cells


def grid_triangles(nx, ny, *, embed=False, seed=0):
    """A jittered ``nx x ny`` vertex grid in the unit square, two triangles per quad.

    With ``embed`` the surface is lifted to 3D as ``z = 0.3 sin(2x) cos(2y)``.
    """
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny), indexing="ij")
    points = np.stack([x.ravel(), y.ravel()], axis=1)
    points += rng.uniform(-0.15, 0.15, points.shape) / max(nx, ny)
    index = np.arange(nx * ny).reshape(nx, ny)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    cells = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    if embed:
        points = np.concatenate([points, 0.3 * (np.sin(2 * points[:, :1]) * np.cos(2 * points[:, 1:]))], axis=1)
    return points, cells


def kuhn_simplices(n, dim, seed=0):
    """Kuhn (Freudenthal) triangulation of an ``n^dim`` grid of unit cubes into ``dim``-simplices.

    Each cube is split into ``dim!`` simplices, one per axis permutation; vertices are jittered.
    """
    rng = np.random.default_rng(seed)
    shape = (n + 1,) * dim
    grid = np.stack(np.meshgrid(*[np.arange(n + 1)] * dim, indexing="ij"), -1).reshape(-1, dim).astype(float)
    points = grid / n + rng.uniform(-0.1, 0.1, grid.shape) / n
    cells = []
    for corner in itertools.product(range(n), repeat=dim):
        for permutation in itertools.permutations(range(dim)):
            vertex = np.array(corner)
            simplex = [np.ravel_multi_index(vertex, shape)]
            for axis in permutation:
                vertex = vertex.copy()
                vertex[axis] += 1
                simplex.append(np.ravel_multi_index(vertex, shape))
            cells.append(simplex)
    return points, np.array(cells)


MESHES = {
    "segments-1d": lambda: polyline(9, 1),
    "segments-2d": lambda: polyline(9, 2),
    "segments-3d": lambda: polyline(9, 3),
    "triangles-2d": lambda: grid_triangles(5, 4),
    "triangles-3d": lambda: grid_triangles(5, 4, embed=True),
    # More vertices than the multilevel preconditioner solves directly (COARSEST_SIZE): a V-cycle
    # with one coarsening step, so a solve needs several iterations.
    "triangles-fine": lambda: grid_triangles(16, 14),
    "tetrahedra": lambda: kuhn_simplices(2, 3),
    "4-simplices": lambda: kuhn_simplices(1, 4),
}


def local_stiffness(corners):
    """Local P1 stiffness and measure of one simplex ``(V, D)`` from barycentric gradients."""
    edges = corners[1:] - corners[0]
    m = edges.shape[0]
    measure = jnp.sqrt(jnp.linalg.det(edges @ edges.T)) / math.factorial(m)
    pseudo_inverse = jnp.linalg.pinv(edges)  # (D, m): gradients of barycentric coordinates 1..m
    gradients = jnp.concatenate([-jnp.sum(pseudo_inverse, axis=1)[None], pseudo_inverse.T])  # (V, D)
    return measure * gradients @ gradients.T, measure


@jax.jit
def dense_stiffness(points, cells):
    """Dense ``K`` ``(N, N)`` and lumped vertex masses ``(N,)`` of one mesh."""
    num_points, num_cell_points = points.shape[0], cells.shape[1]
    local, measures = jax.vmap(local_stiffness)(points[cells])
    rows = jnp.repeat(cells, num_cell_points, axis=1).reshape(-1)
    columns = jnp.tile(cells, (1, num_cell_points)).reshape(-1)
    stiffness = jnp.zeros((num_points, num_points), points.dtype).at[rows, columns].add(local.reshape(-1))
    lumped = jnp.zeros((num_points,), points.dtype).at[cells.reshape(-1)].add(jnp.repeat(measures / num_cell_points, num_cell_points))
    return stiffness, lumped


def dense_sobolev(points, cells, displacement, length_scale, fixed=None):
    """``x + u`` with ``(m̄ I + l^2 K) u = m̄ d`` on the free rows and ``u = 0`` at fixed points."""
    free = np.ones(points.shape[0], bool) if fixed is None else ~np.asarray(fixed)
    return _dense_sobolev_on(points, cells, displacement, np.nonzero(free)[0], length_scale=length_scale)


# One program per case (called eagerly, the solve's dozen steps would each compile on their own).
@functools.partial(jax.jit, static_argnames="length_scale")
def _dense_sobolev_on(points, cells, displacement, index, *, length_scale):
    stiffness, lumped = dense_stiffness(points, cells)
    positive = lumped > 0
    count = jnp.sum(positive).astype(points.dtype)
    one = jnp.ones((), points.dtype)
    mass = jnp.where(count > 0, jnp.sum(jnp.where(positive, lumped, 0)) / jnp.maximum(count, one), one)
    matrix = mass * jnp.eye(index.shape[0], dtype=points.dtype) + length_scale**2 * stiffness[index[:, None], index[None, :]]
    solution = jnp.linalg.solve(matrix, mass * displacement[index])
    return points + jnp.zeros_like(points).at[index].set(solution)
