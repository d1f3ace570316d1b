"""The quick tier, ``pytest -m quick``: every registered op once, in about two minutes.

For each op of ``geomjax._registry.REGISTRY`` the tier runs four existing tests (nothing here is
a test of its own, so the full suite pays nothing extra):

- ``value``: a hand-checked or peer-library value of the op (its own test file), on the CPU
  default backend where that test is parametrised by backend;
- ``gradient``: the default path's VJP against central finite differences (differentiable ops);
- ``torch_bridge``: the torch_bridge call (gradcheck for differentiable ops, of the JAX path for
  the ops of torch_bridge's op table; equality with geomjax for the others);
- ``bad_input``: a wrong shape raises the documented ``ValueError``.

``tests/conftest.py`` marks the collected tests named here with ``quick(op=..., kind=...)``;
``tests/test_quick_tier.py`` checks that every registry key has each kind it needs, so an op
added without quick-tier tests fails the tier itself. Names are pytest node ids; ``{op}`` stands
for the registry key.
"""

from __future__ import annotations

from geomjax._registry import REGISTRY
from torch_bridge._ops import OPS

TORCH_TABLE = {op.name for op in OPS}

TRANSFORMATIONS = "tests/test_transformations.py"

# kind -> node-id template, for every op that has that kind.
BY_TEMPLATE = {
    "gradient": f"{TRANSFORMATIONS}::test_grad_matches_finite_differences[{{op}}-default]",
    "torch_bridge": f"{TRANSFORMATIONS}::test_torch_gradcheck[{{op}}]",
    "bad_input": f"{TRANSFORMATIONS}::test_wrong_shape_is_a_value_error[{{op}}-default]",
}
# The torch_bridge entry of the ops of torch_bridge's op table: gradcheck of the JAX path, which
# every op has.
TORCH_TABLE_GRADCHECK = "tests/torch_bridge/test_ops.py::test_gradcheck[{op}-jax]"

VALUE = {
    "displace_points": "tests/deform/test_displace.py::test_reference_example_values",
    "morph_points": "tests/deform/test_morph.py::test_reference_example_values_hand_checked",
    "radial_basis_function_deform_points": "tests/deform/test_rbf.py::test_matches_scipy_rbf_interpolator",
    "free_form_deform_points": "tests/deform/test_ffd.py::test_bspline_origin_corner_value",
    "sobolev_deform_points": "tests/deform/test_sobolev.py::test_hand_checked_chain",
    "shrinkwrap_points": "tests/deform/test_shrinkwrap.py::test_square_by_hand[float64-warp]",
    "simplex_strain_energy": "tests/energy/test_energies.py::test_segment_values",
    "simplex_measure_energy": "tests/energy/test_energies.py::test_segment_values",
    "simplex_inversion_energy": "tests/energy/test_energies.py::test_segment_values",
    "total_measure_energy": "tests/energy/test_energies.py::test_total_measure_allows_redistribution",
    "surface_bending_energy": "tests/energy/test_energies.py::test_bending_values_and_branch_cut",
    "closed_surface_volume_energy": "tests/energy/test_energies.py::test_volume_values",
    "signed_distance_field": "tests/query/test_sdf.py::test_hand_checked_values[True-warp]",
    "ray_mesh_intersect": "tests/query/test_ray.py::test_reference_conventions[warp]",
    "mesh_to_voxel_fraction": "tests/query/test_voxel.py::test_windows_deep_inside_and_far_outside[warp]",
    "mesh_poisson_disk_sample": "tests/sample/test_poisson.py::test_dart_throwing_minimum_distance_is_exact[warp]",
    "remeshing": "tests/remesh/test_clustering.py::test_sphere_remesh_is_closed_manifold_on_surface[float64-warp]",
    "farthest_point_sampling": "tests/sample/test_farthest.py::test_hand_checked",
}

# The torch_bridge call of the ops without gradients (gradcheck does not apply).
MESH_OPS = "tests/torch_bridge/test_mesh_ops.py"
TORCH_BRIDGE = {
    "mesh_to_voxel_fraction": f"{MESH_OPS}::test_voxel_fraction_equals_geomjax_with_tensor_or_sequence_options",
    "mesh_poisson_disk_sample": f"{MESH_OPS}::test_poisson_sample_equals_geomjax[int]",
    "remeshing": f"{MESH_OPS}::test_remeshing_equals_geomjax_and_keeps_dtypes",
    "farthest_point_sampling": f"{MESH_OPS}::test_farthest_point_sampling_equals_geomjax",
}


def required_kinds(op: str) -> tuple[str, ...]:
    """The kinds an op must have in the quick tier (no gradient for a non-differentiable op)."""
    if REGISTRY[op].differentiable:
        return ("value", "gradient", "torch_bridge", "bad_input")
    return ("value", "torch_bridge", "bad_input")


def quick_tests() -> dict[str, list[tuple[str, str]]]:
    """Node id -> ``[(op, kind), ...]`` of every test in the quick tier."""
    table: dict[str, list[tuple[str, str]]] = {}
    for op in REGISTRY:
        kinds = required_kinds(op)
        for kind in kinds:
            if kind == "value":
                node = VALUE.get(op)
            elif kind == "torch_bridge" and op in TORCH_BRIDGE:
                node = TORCH_BRIDGE[op]
            elif kind == "torch_bridge" and op in TORCH_TABLE:
                node = TORCH_TABLE_GRADCHECK.format(op=op)
            else:
                node = BY_TEMPLATE[kind].format(op=op)
            if node is not None:
                table.setdefault(node, []).append((op, kind))
    return table
