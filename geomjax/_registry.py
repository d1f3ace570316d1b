"""One declaration per op: its backends, what each supports, and the default per platform.

This table is the one place that says which backend ``implementation=None`` runs and why (the
benchmark that measured it), and what each backend can do. ``select_implementation`` reads it;
the Mesh methods, torch_bridge and the table-driven tests (``tests/test_transformations.py``)
read it too. Adding an op means one op file plus one entry here.

Defaults never lose a capability: where the default backend lacks a transform that the JAX path
has (forward mode, second order), the JAX path serves that transform (``_fast_path.py``), so
``Capabilities`` below describes what a backend does *itself*, and the default always offers
the union of its backend's and the JAX path's capabilities.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from types import MappingProxyType

__all__ = ["REGISTRY", "Capabilities", "MeshArguments", "OpDeclaration", "declaration"]


@dataclasses.dataclass(frozen=True)
class Capabilities:
    """What one backend of one op supports by itself.

    Attributes:
        reverse: first-order reverse mode (``grad``, ``vjp``, torch ``backward``).
        forward: forward mode (``jvp``, ``jacfwd``).
        higher_order: derivatives of derivatives (``hessian``, torch double backward).
        float64: float64 inputs computed in float64.
        vmap: ``jax.vmap`` over the op.
        eager_only: runs on concrete arrays only (data-dependent output sizes); no ``jit``.
    """

    reverse: bool = True
    forward: bool = True
    higher_order: bool = True
    float64: bool = True
    vmap: bool = True
    eager_only: bool = False


# The pure-JAX path of a differentiable op: every transform.
JAX_DIFFERENTIABLE = Capabilities()
# A Warp path with a hand-written adjoint (``jax.custom_vjp``): values and first-order reverse mode.
WARP_FIRST_ORDER = Capabilities(forward=False, higher_order=False)
# Outputs that are not differentiated (queries' hit ids, samplers): no transform beyond values.
NOT_DIFFERENTIABLE = Capabilities(reverse=False, forward=False, higher_order=False)
# Data-dependent output sizes: eager only, never differentiated.
EAGER_ONLY = Capabilities(reverse=False, forward=False, higher_order=False, vmap=False, eager_only=True)


@dataclasses.dataclass(frozen=True)
class MeshArguments:
    """How a ``geomjax.Mesh`` method fills an op's arguments from the mesh (the method is generated).

    The method takes the op's arguments minus those in ``bound``, with the same defaults.

    Attributes:
        bound: op argument -> what the mesh supplies: ``"points"`` (``mesh.points``), ``"cells"``,
            ``"hinges"`` or ``"closed_surface_triangles"`` (cached topology, see ``Mesh``).
        current_points: the op argument holding the current coordinates, for ops that measure a
            configuration against the mesh (the energies): checked against ``mesh.points`` and
            the op's result returned. ``None``: the op moves ``mesh.points`` and the method
            returns a new ``Mesh`` with its result as points (the deformations).
        point_data_fields: op arguments that may also be given as ``point_data`` keys.
        requires: a check on the mesh first: ``"triangles_in_3d"`` or ``"full_dimensional"``.
    """

    bound: Mapping[str, str]
    current_points: str | None = None
    point_data_fields: tuple[str, ...] = ()
    requires: str | None = None


@dataclasses.dataclass(frozen=True)
class OpDeclaration:
    """One op of the public API.

    Attributes:
        name: the public function's name (``geomjax.<name>``).
        module: where the function lives.
        backends: each backend's name and capabilities; ``"jax"`` is always present.
        defaults: the backend ``implementation=None`` picks, keyed by platform (``"cpu"``,
            ``"gpu"``) or by ``"<platform>/<variant>"`` for ops whose faster backend depends on
            an option (FFD's basis); platforms not listed use ``"jax"``.
        benchmark: the script whose figures justify ``defaults`` (``benchmarks/...``).
        differentiable: the op's floating outputs are differentiable (on the JAX path).
        mesh_method: the name of the ``geomjax.Mesh`` method that forwards to it, if any.
        mesh_arguments: how that method binds the mesh's data, when it is generated from this
            declaration (``None``: written by hand in ``mesh.py``, or no method).
    """

    name: str
    module: str
    backends: Mapping[str, Capabilities]
    defaults: Mapping[str, str] = dataclasses.field(default_factory=dict)
    benchmark: str | None = None
    differentiable: bool = True
    mesh_method: str | None = None
    mesh_arguments: MeshArguments | None = None

    def __post_init__(self):
        if "jax" not in self.backends:
            raise ValueError(f"{self.name}: every op has a 'jax' backend (the specification)")
        for key, backend in self.defaults.items():
            if backend not in self.backends:
                raise ValueError(f"{self.name}: default {key!r} -> {backend!r} is not a registered backend")

    def default_backend(self, platform: str, variant: str | None = None) -> str:
        """The backend ``implementation=None`` runs on ``platform`` (before Warp availability)."""
        if variant is not None and f"{platform}/{variant}" in self.defaults:
            return self.defaults[f"{platform}/{variant}"]
        return self.defaults.get(platform, "jax")

    def capabilities(self, backend: str) -> Capabilities:
        return self.backends[backend]


def _declare(*declarations: OpDeclaration) -> Mapping[str, OpDeclaration]:
    table = {}
    for d in declarations:
        if d.name in table:
            raise ValueError(f"op {d.name!r} is declared twice")
        table[d.name] = d
    return MappingProxyType(table)


_JAX_ONLY = MappingProxyType({"jax": JAX_DIFFERENTIABLE})
_JAX_AND_WARP = MappingProxyType({"jax": JAX_DIFFERENTIABLE, "warp": WARP_FIRST_ORDER})
_WARP_ON_CPU = MappingProxyType({"cpu": "warp"})
_WARP_EVERYWHERE = MappingProxyType({"cpu": "warp", "gpu": "warp"})


def _deformation(
    name: str,
    module: str,
    method: str,
    fields: tuple[str, ...],
    *,
    backends=_JAX_AND_WARP,
    defaults=None,
    benchmark: str | None = None,
    bound: Mapping[str, str] = MappingProxyType({"points": "points"}),
) -> OpDeclaration:
    # A Mesh method moves mesh.points and returns a new Mesh; per-point fields may be point_data keys.
    arguments = MeshArguments(bound, point_data_fields=fields)
    return OpDeclaration(name, f"geomjax.deform.{module}", backends, defaults or {}, benchmark, mesh_method=method, mesh_arguments=arguments)


def _energy(
    name: str, module: str, topology: str = "cells", *, argument: str = "cells", requires: str | None = None, defaults: Mapping[str, str] = _WARP_ON_CPU
) -> OpDeclaration:
    # benchmarks/bench_energy.py: the Warp kernels beat XLA's gathers and scatter transposes on CPU.
    arguments = MeshArguments(MappingProxyType({"reference_points": "points", argument: topology}), current_points="points", requires=requires)
    return OpDeclaration(name, f"geomjax.energy.{module}", _JAX_AND_WARP, defaults, "benchmarks/bench_energy.py", mesh_method=name, mesh_arguments=arguments)


def _same_on_both_backends(name: str, module: str, capabilities: Capabilities, benchmark: str, **options) -> OpDeclaration:
    # The queries pick the nearest or hit face without gradient (Warp or JAX) and replay its
    # geometry in JAX, and the samplers are not differentiated, so both backends can do the same
    # transforms; Warp's search structures make it the default everywhere.
    backends = MappingProxyType({"jax": capabilities, "warp": capabilities})
    return OpDeclaration(name, module, backends, _WARP_EVERYWHERE, benchmark, **options)


REGISTRY: Mapping[str, OpDeclaration] = _declare(
    _deformation("displace_points", "displace", "displace", ("displacement", "point_weights"), backends=_JAX_ONLY),
    # bench_morph.py: on CPU the Warp hash grid visits only nearby controls (4x with every control
    # in range, up to 1000x for 100,000 controls); the JAX path evaluates every pair.
    _deformation("morph_points", "morph", "morph", ("point_weights",), defaults=_WARP_ON_CPU, benchmark="benchmarks/bench_morph.py"),
    # bench_rbf.py (1e6 points x 1,000 controls, float64, 2-core CPU): XLA uses every core, Warp's
    # CPU launch one thread, so CPU -> JAX. The GPU entry follows the reference (unmeasured here).
    _deformation(
        "radial_basis_function_deform_points",
        "rbf",
        "radial_basis_function_deform",
        ("point_weights",),
        defaults={"cpu": "jax", "gpu": "warp"},
        benchmark="benchmarks/bench_rbf.py",
    ),  # fmt: skip
    # bench_ffd.py: on CPU the fused Bernstein sum (value) and GEMM (derivatives) beat Warp's
    # per-thread loops; for the local bases Warp's per-point loops beat XLA's gathers. GPU follows
    # the reference (unmeasured here). Mesh.free_form_deform is written by hand: it derives the
    # lattice box from the points when none is given.
    OpDeclaration(
        "free_form_deform_points",
        "geomjax.deform.ffd",
        _JAX_AND_WARP,
        {"cpu": "warp", "cpu/bernstein": "jax", "gpu": "warp", "cpu/general": "jax", "gpu/general": "jax"},
        "benchmarks/bench_ffd.py",
        mesh_method="free_form_deform",
    ),
    # bench_sobolev.py: the JAX PCG (lineax: implicit adjoint, forward mode) is faster on CPU. The
    # Warp path's solve is a custom_vjp: first order only.
    _deformation(
        "sobolev_deform_points",
        "sobolev",
        "sobolev_deform",
        ("displacement", "fixed_points"),
        defaults={"cpu": "jax"},
        benchmark="benchmarks/bench_sobolev.py",
        bound=MappingProxyType({"points": "points", "cells": "cells"}),
    ),  # fmt: skip
    # bench_shrinkwrap_voxel.py: Warp's BVH search against the JAX path's all-pairs search. The
    # nearest face is chosen without gradient and its projection replayed in JAX, as for the queries.
    _same_on_both_backends("shrinkwrap_points", "geomjax.deform.shrinkwrap", JAX_DIFFERENTIABLE, "benchmarks/bench_shrinkwrap_voxel.py"),
    _energy("simplex_strain_energy", "strain"),
    _energy("simplex_measure_energy", "measure"),
    _energy("total_measure_energy", "total_measure"),
    _energy("simplex_inversion_energy", "inversion", requires="full_dimensional"),
    _energy("surface_bending_energy", "bending", "hinges", argument="hinges", requires="triangles_in_3d"),
    # Except the volume: one signed tetrahedron per triangle is too little work per element for the
    # Warp launch to pay off (0.87x and 0.88x of the JAX path in two runs of bench_energy.py).
    _energy(
        "closed_surface_volume_energy", "volume", "closed_surface_triangles", argument="triangles", requires="triangles_in_3d", defaults=MappingProxyType({})
    ),
    _same_on_both_backends("signed_distance_field", "geomjax.query.sdf", JAX_DIFFERENTIABLE, "benchmarks/bench_ray_sdf.py"),
    _same_on_both_backends("ray_mesh_intersect", "geomjax.query.ray", JAX_DIFFERENTIABLE, "benchmarks/bench_ray_sdf.py"),
    _same_on_both_backends("mesh_to_voxel_fraction", "geomjax.query.voxel", NOT_DIFFERENTIABLE, "benchmarks/bench_shrinkwrap_voxel.py", differentiable=False),
    _same_on_both_backends("mesh_poisson_disk_sample", "geomjax.sample.poisson", EAGER_ONLY, "benchmarks/bench_sampling_remesh.py", differentiable=False),
    # Mesh.remesh is written by hand: it transfers point data onto the new vertices.
    _same_on_both_backends(
        "remeshing", "geomjax.remesh.clustering", EAGER_ONLY, "benchmarks/bench_sampling_remesh.py", differentiable=False, mesh_method="remesh"
    ),
    OpDeclaration("farthest_point_sampling", "geomjax.sample.farthest", MappingProxyType({"jax": NOT_DIFFERENTIABLE}), differentiable=False),
)


def declaration(name: str) -> OpDeclaration:
    """The declaration of op ``name`` (``KeyError`` for an unknown op)."""
    return REGISTRY[name]
