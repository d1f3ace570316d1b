"""The one case table: one small case per registered op, for every table-driven test.

``CASES[name](dtype)`` returns an :class:`OpCase`: the op's float arrays (the inputs that are
differentiated, for a differentiable op), its fixed inputs (topology, options), which outputs are
differentiated, and batched / empty / zero-control / wrong-shape variants of the arrays, and an
option value the op rejects. Every op of ``geomjax._registry.REGISTRY`` needs a builder here
(``test_every_registered_op_has_a_case``). The JAX tests (``test_transformations.py``) call the
cases directly; torch_bridge's tests take the same inputs as tensors (:func:`torch_inputs`), so
both fronts are checked on the same shapes. Backends always come from the registry.

Inputs are small and share a few shapes (one icosphere, one tetrahedral box, 12 query points)
because compilation dominates the runtime on a small CPU machine: each distinct shape is another
set of compiled programs that every run pays for.
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
        no_controls: ``arrays`` with zero control points (the identity deformation), or ``None``
            for an op without control points.
        bad_option: keyword options that the op rejects with ``ValueError``, or ``None`` when it
            has no such option.
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
    no_controls: tuple[jax.Array, ...] | None = None
    bad_option: Mapping[str, Any] | None = None

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


def _deformation_case(name, dtype, arg_names, arrays, fixed, *, seed, empty=None, bad_shape=None, in_axes=None, **variants):
    in_axes = (0,) * len(arrays) if in_axes is None else in_axes
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
        **variants,
    )


def _point_weights(rng, n=NUM_QUERIES):
    """Per-point weights in [-0.25, 1.25] (negative and above one, as the reference allows), at
    least 0.01 away from zero: a test divides the displacement by them."""
    weights = rng.uniform(0.05, 1.25, n)
    return np.where(rng.random(n) < 0.25, -0.2 * weights, weights)


# ---------------------------------------------------------------------------------------------
# deformations (the ones with per-point weights take them as a differentiated array)
# ---------------------------------------------------------------------------------------------


def displace_points(dtype):
    rng = _rng(1)
    arrays = _cast(dtype, rng.normal(size=(NUM_QUERIES, 3)), 0.1 * rng.normal(size=(NUM_QUERIES, 3)), _point_weights(rng))
    empty = _cast(dtype, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0,)))
    return _deformation_case(
        "displace_points", dtype, ("points", "displacement", "point_weights"), arrays, {}, seed=101, empty=empty
    )


def morph_points(dtype):
    # Per-control radii (differentiated): the points lie partly outside the supports.
    rng = _rng(2)
    points, weights = _query_points(2, 0.0, 1.0), _point_weights(rng)
    controls, displacements, radii = rng.uniform(0.2, 0.8, (4, 3)), 0.2 * rng.normal(size=(4, 3)), rng.uniform(0.8, 1.0, 4)
    arrays = _cast(dtype, points, controls, displacements, radii, weights)
    return _deformation_case(
        "morph_points",
        dtype,
        ("points", "control_points", "control_displacements", "radius", "point_weights"),
        arrays,
        {},
        seed=102,
        empty=_cast(dtype, np.zeros((0, 3)), controls, displacements, radii, np.zeros((0,))),
        no_controls=_cast(dtype, points, np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0,)), weights),
        bad_option={"radius": -1.0},
    )


def radial_basis_function_deform_points(dtype):
    rng = _rng(3)
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1.0]])
    points, weights = _query_points(3, 0.1, 0.9), _point_weights(rng)
    controls, displacements = corners + 0.05 * rng.uniform(size=corners.shape), 0.2 * rng.normal(size=(5, 3))
    return _deformation_case(
        "radial_basis_function_deform_points",
        dtype,
        ("points", "control_points", "control_displacements", "point_weights"),
        _cast(dtype, points, controls, displacements, weights),
        {"smoothing": 0.01},
        seed=103,
        empty=_cast(dtype, np.zeros((0, 3)), controls, displacements, np.zeros((0,))),
        no_controls=_cast(dtype, points, np.zeros((0, 3)), np.zeros((0, 3)), weights),
        bad_option={"smoothing": -1.0},
    )


def free_form_deform_points(dtype):
    # A local basis, so that implementation=None picks Warp on CPU (registry "cpu" entry) and the
    # default's forward mode and second order come from the JAX path.
    rng = _rng(4)
    lattice, weights = 0.2 * rng.normal(size=(2, 3, 2, 3)), _point_weights(rng)
    arrays = _cast(dtype, _query_points(4, 0.05, 0.95), lattice, weights)
    fixed = {"origin": [0.0, 0.0, 0.0], "extent": [1.0, 1.0, 1.0], "basis": "cubic_hermite"}
    return _deformation_case(
        "free_form_deform_points",
        dtype,
        ("points", "control_displacements", "point_weights"),
        arrays,
        fixed,
        seed=104,
        empty=_cast(dtype, np.zeros((0, 3)), lattice, np.zeros((0,))),
        bad_option={"extent": [1.0, 0.0, 1.0]},
    )


def sobolev_deform_points(dtype):
    rng = _rng(5)
    points = SPHERE_POINTS + 0.02 * rng.normal(size=SPHERE_POINTS.shape)
    arrays = _cast(dtype, points, 0.1 * rng.normal(size=SPHERE_POINTS.shape))
    # A tight tolerance (the default is 1e-10 in float64) so the solvers of the two backends
    # agree to rounding rather than to the stopping rule.
    tolerance = float(jnp.finfo(dtype).eps) * 100
    fixed = {"cells": jnp.asarray(SPHERE_FACES), "length_scale": 0.3, "tolerance": tolerance, "max_iterations": 512}
    return _deformation_case(
        "sobolev_deform_points", dtype, ("points", "displacement"), arrays, fixed, seed=105, bad_option={"length_scale": -1.0}
    )


def shrinkwrap_points(dtype):
    # One target (and one offset) shared by the batch; the offset is differentiated.
    rng = _rng(6)
    points, weights = _face_points(6, -0.1, 0.3), _point_weights(rng)
    arrays = _cast(dtype, points, SPHERE_POINTS, 0.05, weights)
    in_axes = (0, None, None, 0)
    return OpCase(
        name="shrinkwrap_points",
        arg_names=("points", "target_points", "offset", "point_weights"),
        arrays=arrays,
        fixed={"target_faces": jnp.asarray(SPHERE_FACES)},
        differentiated=(0,),
        batched=_stack_perturbed(arrays, in_axes, 106, scale=0.005),
        in_axes=in_axes,
        empty=_cast(dtype, np.zeros((0, 3)), SPHERE_POINTS, 0.05, np.zeros((0,))),
        bad_shape=_drop_coordinate(arrays),
        bad_option={"max_distance": -1.0},
    )


# ---------------------------------------------------------------------------------------------
# energies: (points, reference_points) of a small random deformation of a fixed mesh
# ---------------------------------------------------------------------------------------------


def _energy_case(name, topology_name, reference, topology, seed, bad_option, **options):
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
            bad_option=bad_option,
        )

    build.__name__ = name
    return build


simplex_strain_energy = _energy_case(
    "simplex_strain_energy", "cells", BOX_POINTS, BOX_TETS, 7, {"shear_modulus": -1.0}, lame_lambda=0.5
)
simplex_measure_energy = _energy_case(
    "simplex_measure_energy", "cells", BOX_POINTS, BOX_TETS, 8, {"target_ratio": 0.0}, target_ratio=1.1
)
total_measure_energy = _energy_case("total_measure_energy", "cells", BOX_POINTS, BOX_TETS, 9, {"target_ratio": -1.0})
# minimum_jacobian 1.2 makes every term active (the default 0.1 is inactive for small deformations).
simplex_inversion_energy = _energy_case(
    "simplex_inversion_energy", "cells", BOX_POINTS, BOX_TETS, 10, {"minimum_jacobian": -0.5}, minimum_jacobian=1.2
)
surface_bending_energy = _energy_case(
    "surface_bending_energy", "hinges", SPHERE_POINTS, SPHERE_HINGES, 11, {"reduction": "max"}
)
closed_surface_volume_energy = _energy_case(
    "closed_surface_volume_energy", "triangles", SPHERE_POINTS, SPHERE_FACES, 12, {"reduction": "max"}, target_ratio=0.9
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
        bad_option={"max_dist": -1.0},
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
        bad_option={"max_distance": -1.0},
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
        bad_option={"voxel_size": -1.0},
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
        bad_option={"min_distance": -1.0},
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
        bad_option={"n_clusters": 0},
    )


def farthest_point_sampling(dtype):
    # Not differentiable (integer indices); JAX only ("warp" is a ValueError, no kernel).
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
        bad_option={"num_samples": NUM_QUERIES + 1},  # more samples than points
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


# ---------------------------------------------------------------------------------------------
# the same cases as torch tensors, and the comparison tolerance
# ---------------------------------------------------------------------------------------------

VARIANTS = ("arrays", "batched", "empty", "no_controls")


def torch_inputs(name: str, dtype, variant: str = "arrays") -> dict[str, Any]:
    """The case's keyword inputs for torch_bridge: arrays (of ``variant``) as ``dtype`` tensors,
    integer arrays (topology) as int64 tensors (torch's index dtype), other options unchanged.

    ``dtype`` is ``torch.float32`` or ``torch.float64``. Build float64 cases with JAX's x64 mode on
    (the arrays are made by JAX first).
    """
    import torch

    case = CASES[name]({torch.float32: jnp.float32, torch.float64: jnp.float64}[dtype])
    arrays = getattr(case, variant)
    assert variant in VARIANTS and arrays is not None, f"{name} has no {variant!r} variant"

    def to_torch(x):
        if not isinstance(x, (jax.Array, np.ndarray)):
            return x
        x = np.asarray(x)
        return torch.from_numpy(x.astype(np.int64) if np.issubdtype(x.dtype, np.integer) else x.copy())

    return {**{k: to_torch(v) for k, v in case.fixed.items()}, **{k: to_torch(a) for k, a in zip(case.arg_names, arrays)}}


def tolerance(dtype, size: int) -> float:
    """``100 n eps``: the rounding two evaluation orders of an ``n``-input computation may differ by."""
    return 100 * size * float(jnp.finfo(dtype).eps)


def assert_trees_close(actual, expected, dtype, size, err_msg=""):
    """Floats within ``100 n eps`` (relative to the largest entry), integers and bools exactly."""
    actual_leaves, expected_leaves = jax.tree.leaves(actual), jax.tree.leaves(expected)
    assert len(actual_leaves) == len(expected_leaves), err_msg
    rtol = tolerance(dtype, size)
    for i, (a, e) in enumerate(zip(actual_leaves, expected_leaves)):
        a, e = np.asarray(a), np.asarray(e)
        msg = f"{err_msg} (leaf {i})"
        assert a.shape == e.shape and a.dtype == e.dtype, (msg, a.shape, a.dtype, e.shape, e.dtype)
        if np.issubdtype(e.dtype, np.inexact):
            finite = np.isfinite(e)
            scale = float(np.max(np.abs(e[finite]), initial=1.0))
            np.testing.assert_allclose(a, e, rtol=rtol, atol=rtol * scale, err_msg=msg)
        else:
            np.testing.assert_array_equal(a, e, err_msg=msg)
