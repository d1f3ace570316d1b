"""torch_bridge's mesh queries, sampling and remeshing: several and integer outputs, the reusable
BVH of ray_mesh_intersect, and the eager ops whose output sizes depend on the data.

Values and gradients are compared with geomjax called directly on the same inputs (the JAX
functions are the specification); torch.compile(fullgraph=True) must give the eager results.
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

SPHERE = geomjax.icosphere(1)
VERTICES = torch.tensor(np.asarray(SPHERE.points), dtype=torch.float64)
FACES = torch.tensor(np.asarray(SPHERE.cells), dtype=torch.int64)


def _query_points(n=7, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return (torch.rand((n, 3), generator=gen, dtype=torch.float64) - 0.5) * 3.0


def _rays(n=6, seed=1):
    gen = torch.Generator().manual_seed(seed)
    origins = 0.2 * torch.rand((n, 3), generator=gen, dtype=torch.float64)
    directions = torch.randn((n, 3), generator=gen, dtype=torch.float64)
    directions[-1] = 0.0  # a degenerate ray misses
    return origins, directions


def _jax(t):
    return jnp.asarray(t.detach().numpy())


def _assert_outputs_equal(ours, theirs, tol):
    assert len(ours) == len(theirs)
    for a, b in zip(ours, theirs):
        b = np.asarray(b)
        assert tuple(a.shape) == b.shape and a.numpy().dtype == b.dtype
        np.testing.assert_allclose(a.numpy(), b, rtol=tol, atol=tol)


def test_every_mesh_op_is_exported_with_geomjax_signature():
    names = [op.name for op in MESH_OPS] + ["ray_mesh_intersect"]
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
    vertices, points = VERTICES.to(dtype), _query_points().to(dtype)
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
    points = _query_points(4).requires_grad_()
    vertices = VERTICES.clone().requires_grad_()
    assert torch.autograd.gradcheck(
        lambda v, p: torch_bridge.signed_distance_field(v, FACES, p, implementation="jax")[0], (vertices, points)
    )


def test_sdf_compiled_equals_eager_and_opcheck():
    points = _query_points()
    eager_points, compiled_points = points.clone().requires_grad_(), points.clone().requires_grad_()

    def loss(p):
        distance, closest, _ = torch_bridge.signed_distance_field(VERTICES, FACES, p)
        return (distance**2).sum() + closest.sum()

    torch._dynamo.reset()
    compiled = torch.compile(loss, fullgraph=True)(compiled_points)
    eager = loss(eager_points)
    torch.testing.assert_close(compiled, eager, rtol=1e-12, atol=0)
    compiled.backward()
    eager.backward()
    torch.testing.assert_close(compiled_points.grad, eager_points.grad, rtol=1e-12, atol=1e-14)
    op = torch_bridge.signed_distance_field.bridged_op
    slots, statics = op.bind([VERTICES, FACES, points.requires_grad_(), 1e8, False, "jax"])
    torch.library.opcheck(op.lifted.op, (*slots, *statics, [False, False, True]))


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
    assert result[0].tolist()[:-1] == [True] * 5 and not result[0][-1]  # all from inside hit, except the zero ray
    (grad,) = torch.autograd.grad(result[1][:-1].sum(), origins_in)
    _, pullback = jax.vjp(
        lambda o: geomjax.ray_mesh_intersect(_jax(VERTICES), _jax(FACES), o, _jax(directions), implementation=implementation)[1][:-1],
        _jax(origins),
    )
    np.testing.assert_allclose(grad.numpy(), np.asarray(pullback(jnp.ones(5))[0]), rtol=1e-12, atol=1e-12)


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
        return torch_bridge.ray_mesh_intersect(VERTICES, FACES, o, d)[1][:-1]

    torch._dynamo.reset()
    torch.testing.assert_close(torch.compile(distances, fullgraph=True)(origins, directions), distances(origins, directions), rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# voxel fractions
# ---------------------------------------------------------------------------------------------


def test_voxel_fraction_equals_geomjax_with_tensor_or_sequence_options():
    options = dict(voxel_size=0.5, n_samples=8, seed=3)
    expected = geomjax.mesh_to_voxel_fraction(_jax(VERTICES), _jax(FACES), [-1.0, -1.0, -1.0], grid_dims=[4, 4, 4], **options)
    by_sequence = torch_bridge.mesh_to_voxel_fraction(VERTICES, FACES, [-1.0, -1.0, -1.0], grid_dims=[4, 4, 4], **options)
    by_tensor = torch_bridge.mesh_to_voxel_fraction(
        VERTICES, FACES, torch.full((3,), -1.0, dtype=torch.float64), grid_dims=torch.tensor([4, 4, 4]), **options
    )
    for out in (by_sequence, by_tensor):
        np.testing.assert_allclose(out.numpy(), np.asarray(expected), rtol=0, atol=1e-12)
    assert by_sequence.shape == (4, 4, 4) and 0.0 < float(by_sequence.mean()) < 1.0
    with pytest.raises(TypeError, match="grid_dims"):
        torch_bridge.mesh_to_voxel_fraction(VERTICES, FACES, [-1.0, -1.0, -1.0], 0.5, torch.tensor([4.0, 4.0, 4.0]))


def test_voxel_fraction_compiles():
    def occupied(v):
        return torch_bridge.mesh_to_voxel_fraction(v, FACES, [-1.0, -1.0, -1.0], 0.5, [4, 4, 4], n_samples=8).sum()

    torch._dynamo.reset()
    torch.testing.assert_close(torch.compile(occupied, fullgraph=True)(VERTICES), occupied(VERTICES), rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# eager ops with data-dependent output sizes
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("resolution", [32, (32, 16, 32), torch.tensor([32, 16, 32])], ids=["int", "tuple", "tensor"])
def test_poisson_sample_equals_geomjax(resolution):
    vertices = VERTICES.float().requires_grad_()  # not differentiable: the samples do not require grad
    samples = torch_bridge.mesh_poisson_disk_sample(vertices, FACES, 0.25, hash_grid_resolution=resolution)
    jax_resolution = tuple(resolution.tolist()) if isinstance(resolution, torch.Tensor) else resolution
    expected = geomjax.mesh_poisson_disk_sample(_jax(VERTICES.float()), _jax(FACES), 0.25, hash_grid_resolution=jax_resolution)
    assert samples.dtype == torch.float32 and not samples.requires_grad
    np.testing.assert_array_equal(samples.numpy(), np.asarray(expected))
    assert samples.shape[0] > 20


def test_poisson_option_errors_name_both_forms():
    with pytest.raises(TypeError, match="an integer or a sequence of integers"):
        torch_bridge.mesh_poisson_disk_sample(VERTICES, FACES, 0.25, hash_grid_resolution="fine")
    with pytest.raises(ValueError):
        torch_bridge.mesh_poisson_disk_sample(VERTICES, FACES, -0.25)


def test_remeshing_equals_geomjax_and_keeps_dtypes():
    vertices, faces = torch_bridge.remeshing(VERTICES, FACES.int(), 30)
    expected = geomjax.remeshing(_jax(VERTICES), _jax(FACES.int()), 30)
    _assert_outputs_equal((vertices, faces), expected, 0.0)
    assert vertices.dtype == torch.float64 and faces.dtype == torch.int32 and vertices.shape[0] <= 30


def test_data_dependent_ops_compile_with_unbacked_sizes():
    def sample_mean(v):
        return torch_bridge.mesh_poisson_disk_sample(v, FACES, 0.25).mean(dim=0)

    def remeshed(v):
        new_vertices, new_faces = torch_bridge.remeshing(v, FACES, 30)
        return new_vertices.sum(dim=0), new_faces.shape[0]

    torch._dynamo.reset()
    vertices = VERTICES.float()
    torch.testing.assert_close(torch.compile(sample_mean, fullgraph=True)(vertices), sample_mean(vertices), rtol=1e-6, atol=1e-7)
    (total, count), (expected_total, expected_count) = torch.compile(remeshed, fullgraph=True)(VERTICES), remeshed(VERTICES)
    assert count == expected_count
    torch.testing.assert_close(total, expected_total, rtol=1e-12, atol=1e-12)


def test_farthest_point_sampling_equals_geomjax():
    indices = torch_bridge.farthest_point_sampling(VERTICES, 6, start_index=2)
    expected = geomjax.farthest_point_sampling(_jax(VERTICES), 6, start_index=2)
    np.testing.assert_array_equal(indices.numpy(), np.asarray(expected))
    assert indices[0] == 2 and len(set(indices.tolist())) == 6
