"""torch_bridge's mesh queries, sampling and remeshing: several and integer outputs, the reusable
BVH of ray_mesh_intersect, and the eager ops whose output sizes depend on the data.

Values and gradients are compared with geomjax called directly on the same inputs (the JAX
functions are the specification); torch.compile(fullgraph=True) must give the eager results.
Inputs are the case table's (``tests/op_cases.py``), at the shapes of the JAX tests.
"""

from __future__ import annotations

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

import geomjax
import torch_bridge
from torch_bridge._ops import MESH_OPS

from ..op_cases import torch_inputs

SDF = torch_inputs("signed_distance_field", torch.float64)
VERTICES, FACES = SDF["mesh_vertices"], SDF["mesh_indices"]  # the table's sphere (icosphere(1))


def _query_points(dtype=torch.float64):
    return torch_inputs("signed_distance_field", dtype)["input_points"]


def _rays():
    """The table's rays from inside the sphere, the last one made degenerate (it misses)."""
    rays = torch_inputs("ray_mesh_intersect", torch.float64)
    origins, directions = rays["ray_origins"], rays["ray_directions"]
    directions[-1] = 0.0
    return origins, directions


def _jax(t):
    return jnp.asarray(t.detach().numpy())


def _assert_outputs_equal(ours, theirs, tol):
    """Equal outputs; geomjax's integer outputs (index outputs) are int64 tensors here."""
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs):
        b = np.asarray(b)
        expected_dtype = np.dtype(np.int64) if np.issubdtype(b.dtype, np.signedinteger) else b.dtype
        assert tuple(a.shape) == b.shape and a.numpy().dtype == expected_dtype
        np.testing.assert_allclose(a.numpy(), b, rtol=tol, atol=tol)


def test_every_mesh_op_is_exported_with_geomjax_signature():
    names = [op.name for op in MESH_OPS] + ["ray_mesh_intersect", "farthest_point_sampling"]
    assert set(names) <= set(torch_bridge.__all__)
    for name in names:
        ours = inspect.signature(getattr(torch_bridge, name)).parameters
        theirs = inspect.signature(getattr(geomjax, name)).parameters
        assert list(ours) == list(theirs), name
        for key in ours:
            assert ours[key].kind == theirs[key].kind and ours[key].default == theirs[key].default, (name, key)


# ---------------------------------------------------------------------------------------------
# signed distance
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("implementation", ["jax", "warp"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64], ids=["f32", "f64"])
def test_sdf_values_and_gradients_equal_geomjax(implementation, dtype):
    vertices, points = VERTICES.to(dtype), _query_points(dtype)
    vertices_in, points_in = vertices.clone().requires_grad_(), points.clone().requires_grad_()
    distance, closest, face = torch_bridge.signed_distance_field(vertices_in, FACES, points_in, implementation=implementation)

    def reference(v, p):
        return geomjax.signed_distance_field(v, _jax(FACES), p, implementation=implementation)

    expected, pullback = jax.vjp(lambda v, p: reference(v, p)[0], _jax(vertices), _jax(points))
    tol = 2e-6 if dtype == torch.float32 else 1e-12
    _assert_outputs_equal((distance.detach(), closest.detach(), face), reference(_jax(vertices), _jax(points)), tol)
    cotangent = torch.linspace(-1.0, 1.0, distance.numel(), dtype=dtype)
    grads = torch.autograd.grad(distance, [vertices_in, points_in], cotangent)
    for g, e in zip(grads, pullback(_jax(cotangent))):
        np.testing.assert_allclose(g.numpy(), np.asarray(e), rtol=tol, atol=tol)
    assert torch.all(distance.detach().abs() > 0) and face.dtype == torch.int64


def test_sdf_gradcheck():
    points = _query_points().requires_grad_()
    vertices = VERTICES.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda v, p: torch_bridge.signed_distance_field(v, FACES, p, implementation="jax")[0], (vertices, points)
    )


def test_sdf_compiled_equals_eager_and_opcheck():
    points = _query_points()
    eager_points, compiled_points = points.clone().requires_grad_(), points.clone().requires_grad_()

    def sdf(p):
        return torch_bridge.signed_distance_field(VERTICES, FACES, p)[:2]

    def loss(distance, closest):
        return (distance**2).sum() + closest.sum()

    # The compiled graph holds the op alone (forward and, through autograd, its VJP op): the loss's
    # own arithmetic would only add Inductor C++ kernels, seconds of g++ each, that test PyTorch.
    torch._dynamo.reset()
    compiled = loss(*torch.compile(sdf, fullgraph=True)(compiled_points))
    eager = loss(*sdf(eager_points))
    torch.testing.assert_close(compiled, eager, rtol=1e-12, atol=0)
    compiled.backward()
    eager.backward()
    torch.testing.assert_close(compiled_points.grad, eager_points.grad, rtol=1e-12, atol=1e-14)
    op = torch_bridge.signed_distance_field.bridged_op
    slots, statics = op.bind([VERTICES, FACES, points.requires_grad_(), 1e8, False, "jax"])
    torch.library.opcheck(op.lifted.op, op.lifted.op_arguments(slots, statics, [False, False, True]))


# ---------------------------------------------------------------------------------------------
# rays, with the reusable BVH
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_ray_values_and_gradients_equal_geomjax(implementation):
    origins, directions = _rays()
    origins_in = origins.clone().requires_grad_()
    result = torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins_in, directions, implementation=implementation)
    expected = geomjax.ray_mesh_intersect(_jax(VERTICES), _jax(FACES), _jax(origins), _jax(directions), implementation=implementation)
    _assert_outputs_equal([r.detach() for r in result], expected, 1e-12)
    count = len(origins) - 1
    assert result[0].tolist()[:-1] == [True] * count and not result[0][-1]  # all from inside hit, except the zero ray
    (grad,) = torch.autograd.grad(result[1][:-1].sum(), origins_in)
    _, pullback = jax.vjp(
        lambda o: geomjax.ray_mesh_intersect(_jax(VERTICES), _jax(FACES), o, _jax(directions), implementation=implementation)[1][:-1],
        _jax(origins),
    )
    np.testing.assert_allclose(grad.numpy(), np.asarray(pullback(jnp.ones(count))[0]), rtol=1e-12, atol=1e-12)


def test_ray_returns_and_reuses_the_bvh():
    origins, directions = _rays()
    *first, bvh = torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins, directions, return_warp_mesh=True)
    assert isinstance(bvh, geomjax.MeshBVH)
    again = torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins, directions, warp_mesh=bvh)
    for a, b in zip(first, again):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    # The BVH is only searched: hits are measured on the vertices passed with it (here, scaled
    # by 1.5 after refitting the BVH to them), as in geomjax.
    scaled = VERTICES * 1.5
    refitted = bvh.refit(_jax(scaled))
    distance = torch_bridge.ray_mesh_intersect(scaled, FACES, origins, directions, warp_mesh=refitted)[1]
    fresh = torch_bridge.ray_mesh_intersect(scaled, FACES, origins, directions)[1]
    torch.testing.assert_close(distance, fresh, rtol=1e-12, atol=0)
    *_, same = torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins, directions, warp_mesh=bvh, return_warp_mesh=True)
    assert same is bvh


def test_ray_rejects_a_bad_bvh():
    origins, directions = _rays()
    with pytest.raises(TypeError, match="MeshBVH"):
        torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins, directions, warp_mesh="mesh")
    with pytest.raises(TypeError, match="return_warp_mesh"):
        torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins, directions, return_warp_mesh=1)
    small = geomjax.icosphere(0)
    other = geomjax.build_bvh(small.points, jnp.asarray(np.asarray(small.cells)))
    with pytest.raises(ValueError, match="warp_mesh was built for"):
        torch_bridge.ray_mesh_intersect(VERTICES, FACES, origins, directions, warp_mesh=other)


def test_ray_compiled_equals_eager():
    origins, directions = _rays()

    def distances(o, d):
        return torch_bridge.ray_mesh_intersect(VERTICES, FACES, o, d)[1]

    torch._dynamo.reset()
    compiled = torch.compile(distances, fullgraph=True)(origins, directions)
    torch.testing.assert_close(compiled[:-1], distances(origins, directions)[:-1], rtol=0, atol=0)
    assert compiled[-1] == torch.inf  # the zero ray misses


# ---------------------------------------------------------------------------------------------
# voxel fractions
# ---------------------------------------------------------------------------------------------


VOXEL = torch_inputs("mesh_to_voxel_fraction", torch.float64)
VOXEL_OPTIONS = {k: v for k, v in VOXEL.items() if k not in ("mesh_vertices", "mesh_indices", "origin", "grid_dims")}


def test_voxel_fraction_equals_geomjax_with_tensor_or_sequence_options():
    origin, dims = VOXEL["origin"], list(VOXEL["grid_dims"])
    expected = geomjax.mesh_to_voxel_fraction(_jax(VERTICES), _jax(FACES), origin, grid_dims=dims, **VOXEL_OPTIONS)
    by_sequence = torch_bridge.mesh_to_voxel_fraction(VERTICES, FACES, origin, grid_dims=dims, **VOXEL_OPTIONS)
    by_tensor = torch_bridge.mesh_to_voxel_fraction(
        VERTICES, FACES, torch.tensor(origin, dtype=torch.float64), grid_dims=torch.tensor(dims), **VOXEL_OPTIONS
    )
    for out in (by_sequence, by_tensor):
        np.testing.assert_allclose(out.numpy(), np.asarray(expected), rtol=0, atol=1e-12)
    assert tuple(by_sequence.shape) == tuple(dims[::-1]) and 0.0 < float(by_sequence.mean()) < 1.0
    with pytest.raises(TypeError, match="grid_dims"):
        torch_bridge.mesh_to_voxel_fraction(VERTICES, FACES, origin, VOXEL["voxel_size"], torch.tensor(dims, dtype=torch.float64))


def test_voxel_fraction_compiles():
    grid = {k: value for k, value in VOXEL.items() if k not in ("mesh_vertices", "mesh_indices")}

    def occupied(v):
        return torch_bridge.mesh_to_voxel_fraction(v, FACES, **grid)

    torch._dynamo.reset()
    torch.testing.assert_close(torch.compile(occupied, fullgraph=True)(VERTICES), occupied(VERTICES), rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# eager ops with data-dependent output sizes
# ---------------------------------------------------------------------------------------------

POISSON = torch_inputs("mesh_poisson_disk_sample", torch.float32)
POISSON_OPTIONS = {k: v for k, v in POISSON.items() if k not in ("mesh_vertices", "mesh_indices")}
REMESH = torch_inputs("remeshing", torch.float64)  # a jittered sphere: no equidistant ties
CLUSTERS = REMESH["n_clusters"]


@pytest.mark.parametrize("resolution", [32, (32, 16, 32), torch.tensor([32, 16, 32])], ids=["int", "tuple", "tensor"])
def test_poisson_sample_equals_geomjax(resolution):
    vertices = VERTICES.float().requires_grad_()  # not differentiable: the samples do not require grad
    samples = torch_bridge.mesh_poisson_disk_sample(vertices, FACES, **POISSON_OPTIONS, hash_grid_resolution=resolution)
    jax_resolution = tuple(resolution.tolist()) if isinstance(resolution, torch.Tensor) else resolution
    expected = geomjax.mesh_poisson_disk_sample(_jax(VERTICES.float()), _jax(FACES), **POISSON_OPTIONS, hash_grid_resolution=jax_resolution)
    assert samples.dtype == torch.float32 and not samples.requires_grad
    np.testing.assert_array_equal(samples.numpy(), np.asarray(expected))
    assert samples.shape[0] > 20


def test_poisson_option_errors_name_both_forms():
    with pytest.raises(TypeError, match="an integer or a sequence of integers"):
        torch_bridge.mesh_poisson_disk_sample(VERTICES, FACES, **POISSON_OPTIONS, hash_grid_resolution="fine")
    with pytest.raises(ValueError, match="min_distance"):
        torch_bridge.mesh_poisson_disk_sample(VERTICES, FACES, **{**POISSON_OPTIONS, "min_distance": -0.25})


def test_remeshing_equals_geomjax_and_keeps_dtypes():
    vertices, faces = torch_bridge.remeshing(REMESH["mesh_vertices"], FACES.int(), CLUSTERS)
    expected = geomjax.remeshing(_jax(REMESH["mesh_vertices"]), _jax(FACES.int()), CLUSTERS)
    _assert_outputs_equal((vertices, faces), expected, 0.0)
    assert vertices.dtype == torch.float64 and faces.dtype == torch.int64 and vertices.shape[0] <= CLUSTERS


def test_data_dependent_ops_compile_with_unbacked_sizes():
    def sample_mean(v):
        return torch_bridge.mesh_poisson_disk_sample(v, FACES, **POISSON_OPTIONS).mean(dim=0)

    def remeshed(v):
        new_vertices, new_faces = torch_bridge.remeshing(v, FACES, CLUSTERS)
        return new_vertices.sum(dim=0), new_faces.shape[0]

    torch._dynamo.reset()
    vertices = VERTICES.float()
    torch.testing.assert_close(torch.compile(sample_mean, fullgraph=True)(vertices), sample_mean(vertices), rtol=1e-6, atol=1e-7)
    jittered = REMESH["mesh_vertices"]
    (total, count), (expected_total, expected_count) = torch.compile(remeshed, fullgraph=True)(jittered), remeshed(jittered)
    assert count == expected_count
    torch.testing.assert_close(total, expected_total, rtol=1e-12, atol=1e-12)


def test_farthest_point_sampling_equals_geomjax():
    fps = torch_inputs("farthest_point_sampling", torch.float64)
    count = fps["num_samples"]
    indices = torch_bridge.farthest_point_sampling(fps["points"], count, start_index=2)
    expected = geomjax.farthest_point_sampling(_jax(fps["points"]), count, start_index=2)
    np.testing.assert_array_equal(indices.numpy(), np.asarray(expected))
    assert indices[0] == 2 and len(set(indices.tolist())) == count


def test_farthest_point_sampling_random_start_uses_torch_global_generator():
    from ..sample.test_farthest import _reference

    fps = torch_inputs("farthest_point_sampling", torch.float32)
    points, count = torch.stack([fps["points"], fps["points"].flip(0)]), fps["num_samples"]
    torch.manual_seed(11)
    starts = torch.randint(points.shape[1], (2,))  # what the reference draws: one start per cloud
    torch.manual_seed(11)
    indices = torch_bridge.farthest_point_sampling(points, count, random_start=True)
    assert indices.dtype == torch.int64
    np.testing.assert_array_equal(indices.numpy(), [_reference(p, count, int(s)) for p, s in zip(points.numpy(), starts)])
    torch.manual_seed(11)
    compiled = torch.compile(lambda p: torch_bridge.farthest_point_sampling(p, count, True), fullgraph=True)(points)
    assert compiled.shape == (2, count) and bool(((compiled >= 0) & (compiled < points.shape[1])).all())
    with pytest.raises(ValueError, match="not both"):
        torch_bridge.farthest_point_sampling(points, count, random_start=True, start_index=1)
    with pytest.raises(TypeError, match="random_start must be a bool"):
        torch_bridge.farthest_point_sampling(points, count, random_start=torch.tensor(1))
    with pytest.raises(ValueError, match="implementation='warp' has no kernel"):
        torch_bridge.farthest_point_sampling(points, count, implementation="warp")
    with pytest.raises(KeyError, match="unknown implementation 'cuda'"):
        torch_bridge.farthest_point_sampling(points, count, implementation="cuda")


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_farthest_point_sampling_accepts_low_precision_points(dtype):
    # Any floating dtype, compared in float32 (the reference's contract): the greedy order of the
    # same values in float32, by an explicit NumPy loop.
    from ..sample.test_farthest import _reference

    fps = torch_inputs("farthest_point_sampling", torch.float32)  # the case table's points and count
    points, count = fps["points"].to(dtype), fps["num_samples"]
    indices = torch_bridge.farthest_point_sampling(points, count)
    assert indices.dtype == torch.int64
    np.testing.assert_array_equal(indices.numpy(), _reference(points.float().numpy(), count, 0))


def test_remeshing_accepts_low_precision_density():
    # Any real floating dtype (the reference's contract), read exactly: as the same values in float32.
    density = 0.5 + REMESH["mesh_vertices"][:, 0].abs()
    for dtype in (torch.float16, torch.bfloat16):
        narrow = torch_bridge.remeshing(REMESH["mesh_vertices"], FACES, CLUSTERS, vertex_density=density.to(dtype))
        wide = torch_bridge.remeshing(REMESH["mesh_vertices"], FACES, CLUSTERS, vertex_density=density.to(dtype).float())
        for a, b in zip(narrow, wide):
            torch.testing.assert_close(a, b, rtol=0, atol=0)


@pytest.mark.parametrize("index_dtype", [torch.int32, torch.int64])
def test_index_outputs_are_int64_whatever_the_index_dtype(index_dtype):
    # The reference returns face ids, triangles and sample indices as int64. geomjax returns int32
    # unless JAX runs in 64-bit mode, which float32 vertices with int32 indices do not ask for.
    vertices, faces, points = VERTICES.float(), FACES.to(index_dtype), _query_points(torch.float32)
    origins, directions = (r.float() for r in _rays())
    outputs = {
        "signed_distance_field": (torch_bridge.signed_distance_field(vertices, faces, points)[2],
                                  geomjax.signed_distance_field(_jax(vertices), _jax(faces), _jax(points))[2]),
        "ray_mesh_intersect": (torch_bridge.ray_mesh_intersect(vertices, faces, origins, directions)[3],
                               geomjax.ray_mesh_intersect(_jax(vertices), _jax(faces), _jax(origins), _jax(directions))[3]),
        "remeshing": (torch_bridge.remeshing(REMESH["mesh_vertices"].float(), faces, CLUSTERS)[1],
                      geomjax.remeshing(_jax(REMESH["mesh_vertices"].float()), _jax(faces), CLUSTERS)[1]),
        "farthest_point_sampling": (torch_bridge.farthest_point_sampling(points, 5),
                                    geomjax.farthest_point_sampling(_jax(points), 5)),
    }  # fmt: skip
    for name, (ours, theirs) in outputs.items():
        assert ours.dtype == torch.int64, name
        np.testing.assert_array_equal(ours.numpy(), np.asarray(theirs), err_msg=name)
    # Compiled graphs (fake tensors) report the same dtype.
    torch._dynamo.reset()
    compiled = torch.compile(lambda p: torch_bridge.signed_distance_field(vertices, faces, p)[2], fullgraph=True, backend="aot_eager")
    assert compiled(points).dtype == torch.int64


def test_query_dtypes_are_independent_of_the_mesh_dtype():
    # The reference's contract: float16 rays against a float32 mesh, float64 queries against a
    # float32 mesh; float outputs in the queries' dtype, ids int64, in eager and compiled calls.
    vertices = VERTICES.float()
    origins, directions = (r.half() for r in _rays())
    hit, distance, points, faces, normals = torch_bridge.ray_mesh_intersect(vertices, FACES, origins, directions)
    assert distance.dtype == points.dtype == normals.dtype == torch.float16 and faces.dtype == torch.int64
    expected = geomjax.ray_mesh_intersect(_jax(vertices), _jax(FACES), _jax(origins), _jax(directions))
    np.testing.assert_array_equal(hit.numpy(), np.asarray(expected[0]))
    np.testing.assert_array_equal(distance.numpy(), np.asarray(expected[1]))
    queries = _query_points(torch.float64)
    sdf, closest, ids = torch_bridge.signed_distance_field(vertices, FACES, queries)
    assert sdf.dtype == closest.dtype == torch.float64 and ids.dtype == torch.int64
    np.testing.assert_array_equal(sdf.numpy(), np.asarray(geomjax.signed_distance_field(_jax(vertices), _jax(FACES), _jax(queries))[0]))
    torch._dynamo.reset()
    compiled = torch.compile(lambda q: torch_bridge.signed_distance_field(vertices, FACES, q)[0], fullgraph=True, backend="aot_eager")
    assert compiled(queries).dtype == torch.float64
