"""One small case per registered op, for the table-driven tests of ``test_transformations.py``.

``CASES[name](dtype)`` returns an :class:`OpCase`: the op's float arrays (the inputs that are
differentiated, for a differentiable op), its fixed inputs (topology, options), which outputs are
differentiated, and batched / empty / wrong-shape variants of the arrays. Every op of
``geomjax._registry.REGISTRY`` needs a builder here (``test_every_registered_op_has_a_case``).

Inputs are small and share a few shapes (one icosphere, one tetrahedral box, 12 query points)
because compilation dominates the runtime on a small CPU machine.
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Callable, Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

import geomjax

SPHERE = geomjax.icosphere(1)  # 42 vertices, 80 triangles, 120 hinges
BOX = geomjax.tetrahedralized_box(2, 2, 2)  # 27 vertices, 48 tetrahedra
NUM_QUERIES = 12
BATCH = 2

SPHERE_POINTS = np.asarray(SPHERE.points, np.float64)
SPHERE_FACES = np.asarray(SPHERE.cells, np.int32)
SPHERE_HINGES = np.asarray(SPHERE.hinges, np.int32)
BOX_POINTS = np.asarray(BOX.points, np.float64)
BOX_TETS = np.asarray(BOX.cells, np.int32)


@dataclasses.dataclass(frozen=True)
class OpCase:
    """A small call of one op.

    Attributes:
        name: the registry key and the public function's name (``geomjax.<name>``).
        arg_names: keyword names of ``arrays``.
        arrays: the op's float input arrays, in ``arg_names`` order (all differentiated for a
            differentiable op).
        fixed: the other inputs (topology, options), passed by keyword.
        differentiated: indices of the differentiated outputs in the op's output tuple; ``()``
            for an op that is not differentiable.
        batched: ``arrays`` with a leading batch axis of size ``BATCH`` where ``in_axes`` is 0
            (unchanged where it is ``None``), or ``None`` when the op cannot be ``vmap``-ed.
        in_axes: the ``vmap`` axes of ``arrays``.
        empty: ``arrays`` with zero points / queries, or ``None`` when the op rejects them.
        bad_shape: ``arrays`` with one of wrong shape (the op raises ``ValueError``).
        output_dtype: the float outputs' dtype when it is not the inputs' (e.g. always float32).
    """

    name: str
    arg_names: tuple[str, ...]
    arrays: tuple[jax.Array, ...]
    fixed: Mapping[str, Any]
    differentiated: tuple[int, ...]
    batched: tuple[jax.Array, ...] | None
    in_axes: tuple[int | None, ...]
    empty: tuple[jax.Array, ...] | None
    bad_shape: tuple[jax.Array, ...]
    output_dtype: Any = None

    @property
    def function(self) -> Callable:
        return getattr(geomjax, self.name)

    @property
    def takes_implementation(self) -> bool:
        return "implementation" in inspect.signature(self.function).parameters

    @property
    def size(self) -> int:
        """The number of input scalars (scales the comparison tolerances)."""
        return max(1, sum(int(np.prod(a.shape)) for a in self.arrays))

    def call(self, *arrays, implementation=None, fn=None, fixed=None):
        """The op's outputs as a tuple (``fn``/``fixed``: another front, e.g. torch_bridge)."""
        fn = self.function if fn is None else fn
        kwargs = {**(self.fixed if fixed is None else fixed), **dict(zip(self.arg_names, arrays, strict=True))}
        if self.takes_implementation:
            kwargs["implementation"] = implementation
        out = fn(**kwargs)
        return tuple(out) if isinstance(out, (tuple, list)) else (out,)

    def differentiable_function(self, implementation=None) -> Callable:
        """``f(*arrays) -> tuple`` of the differentiated outputs."""

        def f(*arrays):
            out = self.call(*arrays, implementation=implementation)
            return tuple(out[i] for i in self.differentiated)

        return f

    def loss(self, implementation=None) -> Callable:
        """A smooth scalar of the differentiated outputs (sum of squares), for Hessians."""
        f = self.differentiable_function(implementation)

        def loss(*arrays):
            return sum(jnp.sum(jnp.square(y)) for y in f(*arrays))

        return loss


def _rng(seed):
    return np.random.default_rng(seed)


def _cast(dtype, *arrays):
    return tuple(jnp.asarray(a, dtype) for a in arrays)


def _drop_coordinate(arrays, index=0):
    """``arrays`` with the last axis of ``arrays[index]`` cut to 2 entries (a shape mismatch)."""
    return tuple(a[..., :2] if i == index else a for i, a in enumerate(arrays))


def _query_points(seed, low, high, n=NUM_QUERIES):
    return _rng(seed).uniform(low, high, size=(n, 3))


def _face_points(seed, low, high, n=NUM_QUERIES):
    """Points off the interior of ``n`` distinct sphere faces, along their normals by ``[low, high]``.

    Their closest point lies inside one face (never on a shared edge or vertex), so the nearest
    face is unique and the queries are smooth functions of the inputs.
    """
    rng = _rng(seed)
    faces = SPHERE_FACES[rng.choice(len(SPHERE_FACES), n, replace=False)]
    a, b, c = (SPHERE_POINTS[faces[:, i]] for i in range(3))
    weights = 0.2 + 0.6 * rng.dirichlet(np.ones(3), n)  # every barycentric weight in [0.2, 0.8]
    weights /= weights.sum(-1, keepdims=True)
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return weights[:, :1] * a + weights[:, 1:2] * b + weights[:, 2:] * c + rng.uniform(low, high, (n, 1)) * normal


def _stack_perturbed(arrays, in_axes, seed, scale=0.02):
    """A batch of ``BATCH`` perturbed copies of the arrays mapped over (axis 0)."""
    rng = _rng(seed)
    out = []
    for a, axis in zip(arrays, in_axes):
        if axis is None:
            out.append(a)
            continue
        noise = rng.normal(size=(BATCH, *a.shape)) * scale
        out.append(jnp.asarray(np.asarray(a, np.float64)[None] + noise, a.dtype))
    return tuple(out)


def _deformation_case(name, dtype, arg_names, arrays, fixed, *, seed, empty=None, bad_shape=None):
    in_axes = (0,) * len(arrays)
    return OpCase(
        name=name,
        arg_names=arg_names,
        arrays=arrays,
        fixed=fixed,
        differentiated=(0,),
        batched=_stack_perturbed(arrays, in_axes, seed),
        in_axes=in_axes,
        empty=empty,
        bad_shape=_drop_coordinate(arrays) if bad_shape is None else bad_shape,
    )


# ---------------------------------------------------------------------------------------------
# deformations
# ---------------------------------------------------------------------------------------------


def displace_points(dtype):
    rng = _rng(1)
    arrays = _cast(dtype, rng.normal(size=(NUM_QUERIES, 3)), 0.1 * rng.normal(size=(NUM_QUERIES, 3)), rng.uniform(0.2, 1.0, NUM_QUERIES))
    empty = _cast(dtype, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0,)))
    return _deformation_case(
        "displace_points", dtype, ("points", "displacement", "point_weights"), arrays, {}, seed=101, empty=empty
    )


def morph_points(dtype):
    rng = _rng(2)
    arrays = _cast(dtype, _query_points(2, 0.0, 1.0), rng.uniform(0.2, 0.8, (4, 3)), 0.2 * rng.normal(size=(4, 3)))
    empty = (jnp.zeros((0, 3), dtype), *arrays[1:])
    return _deformation_case(
        "morph_points",
        dtype,
        ("points", "control_points", "control_displacements"),
        arrays,
        {"radius": 0.9},
        seed=102,
        empty=empty,
    )


def radial_basis_function_deform_points(dtype):
    rng = _rng(3)
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    arrays = _cast(dtype, _query_points(3, 0.1, 0.9), corners + 0.05 * rng.uniform(size=corners.shape), 0.2 * rng.normal(size=(5, 3)))
    empty = (jnp.zeros((0, 3), dtype), *arrays[1:])
    return _deformation_case(
        "radial_basis_function_deform_points",
        dtype,
        ("points", "control_points", "control_displacements"),
        arrays,
        {"smoothing": 0.01},
        seed=103,
        empty=empty,
    )


def free_form_deform_points(dtype):
    # A local basis, so that implementation=None picks Warp on CPU (registry "cpu" entry) and the
    # default's forward mode and second order come from the JAX path.
    rng = _rng(4)
    arrays = _cast(dtype, _query_points(4, 0.05, 0.95), 0.2 * rng.normal(size=(2, 3, 2, 3)))
    empty = (jnp.zeros((0, 3), dtype), arrays[1])
    fixed = {"origin": [0.0, 0.0, 0.0], "extent": [1.0, 1.0, 1.0], "basis": "cubic_hermite"}
    return _deformation_case(
        "free_form_deform_points", dtype, ("points", "control_displacements"), arrays, fixed, seed=104, empty=empty
    )


def sobolev_deform_points(dtype):
    rng = _rng(5)
    points = SPHERE_POINTS + 0.02 * rng.normal(size=SPHERE_POINTS.shape)
    arrays = _cast(dtype, points, 0.1 * rng.normal(size=SPHERE_POINTS.shape))
    # A tight tolerance (the default is 1e-10 in float64) so the solvers of the two backends
    # agree to rounding rather than to the stopping rule.
    tolerance = float(jnp.finfo(dtype).eps) * 100
    fixed = {"cells": jnp.asarray(SPHERE_FACES), "length_scale": 0.3, "tolerance": tolerance, "max_iterations": 512}
    return _deformation_case("sobolev_deform_points", dtype, ("points", "displacement"), arrays, fixed, seed=105)


def shrinkwrap_points(dtype):
    arrays = _cast(dtype, _face_points(6, -0.1, 0.3), SPHERE_POINTS)
    fixed = {"target_faces": jnp.asarray(SPHERE_FACES), "offset": 0.05}
    in_axes = (0, None)  # one target shared by the batch
    return OpCase(
        name="shrinkwrap_points",
        arg_names=("points", "target_points"),
        arrays=arrays,
        fixed=fixed,
        differentiated=(0,),
        batched=_stack_perturbed(arrays, in_axes, 106, scale=0.005),
        in_axes=in_axes,
        empty=(jnp.zeros((0, 3), dtype), arrays[1]),
        bad_shape=_drop_coordinate(arrays),
    )


# ---------------------------------------------------------------------------------------------
# energies: (points, reference_points) of a small random deformation of a fixed mesh
# ---------------------------------------------------------------------------------------------


def _energy_case(name, topology_name, reference, topology, seed, **options):
    def build(dtype):
        points = reference + 0.05 * _rng(seed).normal(size=reference.shape)
        arrays = _cast(dtype, points, reference)
        return OpCase(
            name=name,
            arg_names=("points", "reference_points"),
            arrays=arrays,
            fixed={topology_name: jnp.asarray(topology), **options},
            differentiated=(0,),
            batched=_stack_perturbed(arrays, (0, 0), seed + 100),
            in_axes=(0, 0),
            empty=None,  # the mesh is fixed: zero points with its cells are out of range
            bad_shape=_drop_coordinate(arrays),
        )

    build.__name__ = name
    return build


simplex_strain_energy = _energy_case("simplex_strain_energy", "cells", BOX_POINTS, BOX_TETS, 7, lame_lambda=0.5)
simplex_measure_energy = _energy_case("simplex_measure_energy", "cells", BOX_POINTS, BOX_TETS, 8, target_ratio=1.1)
total_measure_energy = _energy_case("total_measure_energy", "cells", BOX_POINTS, BOX_TETS, 9)
# minimum_jacobian 1.2 makes every term active (the default 0.1 is inactive for small deformations).
simplex_inversion_energy = _energy_case("simplex_inversion_energy", "cells", BOX_POINTS, BOX_TETS, 10, minimum_jacobian=1.2)
surface_bending_energy = _energy_case("surface_bending_energy", "hinges", SPHERE_POINTS, SPHERE_HINGES, 11)
closed_surface_volume_energy = _energy_case(
    "closed_surface_volume_energy", "triangles", SPHERE_POINTS, SPHERE_FACES, 12, target_ratio=0.9
)


# ---------------------------------------------------------------------------------------------
# queries
# ---------------------------------------------------------------------------------------------


def signed_distance_field(dtype):
    # outputs (sdf, closest point, face id): the distance and the closest point are differentiated.
    arrays = _cast(dtype, SPHERE_POINTS, _face_points(13, -0.1, 0.3))
    in_axes = (None, 0)
    return OpCase(
        name="signed_distance_field",
        arg_names=("mesh_vertices", "input_points"),
        arrays=arrays,
        fixed={"mesh_indices": jnp.asarray(SPHERE_FACES)},
        differentiated=(0, 1),
        batched=_stack_perturbed(arrays, in_axes, 113, scale=0.005),
        in_axes=in_axes,
        empty=(arrays[0], jnp.zeros((0, 3), dtype)),
        bad_shape=_drop_coordinate(arrays, 1),
    )


def ray_mesh_intersect(dtype):
    # outputs (hit, distance, point, face id, normal): origins inside the sphere, so every ray
    # hits and distance, point and normal are differentiated.
    rng = _rng(14)
    arrays = _cast(dtype, SPHERE_POINTS, 0.2 * rng.uniform(-1, 1, (NUM_QUERIES, 3)), rng.normal(size=(NUM_QUERIES, 3)))
    in_axes = (None, 0, 0)
    return OpCase(
        name="ray_mesh_intersect",
        arg_names=("mesh_vertices", "ray_origins", "ray_directions"),
        arrays=arrays,
        fixed={"mesh_indices": jnp.asarray(SPHERE_FACES)},
        differentiated=(1, 2, 4),
        batched=_stack_perturbed(arrays, in_axes, 114),
        in_axes=in_axes,
        empty=(arrays[0], jnp.zeros((0, 3), dtype), jnp.zeros((0, 3), dtype)),
        bad_shape=_drop_coordinate(arrays, 1),
    )


def mesh_to_voxel_fraction(dtype):
    # Not differentiable (piecewise-constant fractions).
    arrays = _cast(dtype, SPHERE_POINTS)
    fixed = {
        "mesh_indices": jnp.asarray(SPHERE_FACES),
        "origin": [-0.9, -0.9, -0.9],
        "voxel_size": 0.6,
        "grid_dims": (3, 3, 3),
        "n_samples": 8,
    }
    return OpCase(
        name="mesh_to_voxel_fraction",
        arg_names=("mesh_vertices",),
        arrays=arrays,
        fixed=fixed,
        differentiated=(),
        batched=(jnp.stack([arrays[0], 0.8 * arrays[0]]),),
        in_axes=(0,),
        empty=None,  # an empty mesh is a ValueError
        bad_shape=_drop_coordinate(arrays),
        output_dtype=jnp.float32,
    )


# ---------------------------------------------------------------------------------------------
# sampling and remeshing
# ---------------------------------------------------------------------------------------------


def mesh_poisson_disk_sample(dtype):
    # Not differentiable, eager only (data-dependent output size); samples are float32.
    arrays = _cast(dtype, SPHERE_POINTS)
    fixed = {"mesh_indices": jnp.asarray(SPHERE_FACES), "min_distance": 0.4, "batch_size": 256, "max_iterations": 8}
    return OpCase(
        name="mesh_poisson_disk_sample",
        arg_names=("mesh_vertices",),
        arrays=arrays,
        fixed=fixed,
        differentiated=(),
        batched=None,
        in_axes=(0,),
        empty=None,
        bad_shape=_drop_coordinate(arrays),
        output_dtype=jnp.float32,
    )


def remeshing(dtype):
    # Not differentiable, eager only; vertices in the input dtype. The sphere is jittered: on the
    # symmetric icosphere many vertices are equidistant from two centroids, ties that the two
    # backends' roundings break differently.
    arrays = _cast(dtype, SPHERE_POINTS + 0.01 * _rng(16).normal(size=SPHERE_POINTS.shape))
    return OpCase(
        name="remeshing",
        arg_names=("mesh_vertices",),
        arrays=arrays,
        fixed={"mesh_indices": jnp.asarray(SPHERE_FACES), "n_clusters": 16},
        differentiated=(),
        batched=None,
        in_axes=(0,),
        empty=None,
        bad_shape=_drop_coordinate(arrays),
    )


def farthest_point_sampling(dtype):
    # Not differentiable (integer indices); JAX only, no implementation argument.
    arrays = _cast(dtype, _query_points(15, -1.0, 1.0))
    return OpCase(
        name="farthest_point_sampling",
        arg_names=("points",),
        arrays=arrays,
        fixed={"num_samples": 4},
        differentiated=(),
        batched=_stack_perturbed(arrays, (0,), 115, scale=0.5),
        in_axes=(0,),
        empty=None,  # num_samples=4 needs at least 4 points
        output_dtype=jnp.int32,
        bad_shape=(arrays[0][None, None],),  # (N, D) and (B, N, D) only
    )


CASES: Mapping[str, Callable[[Any], OpCase]] = {
    f.__name__: f
    for f in (
        displace_points,
        morph_points,
        radial_basis_function_deform_points,
        free_form_deform_points,
        sobolev_deform_points,
        shrinkwrap_points,
        simplex_strain_energy,
        simplex_measure_energy,
        total_measure_energy,
        simplex_inversion_energy,
        surface_bending_energy,
        closed_surface_volume_energy,
        signed_distance_field,
        ray_mesh_intersect,
        mesh_to_voxel_fraction,
        mesh_poisson_disk_sample,
        remeshing,
        farthest_point_sampling,
    )
}
