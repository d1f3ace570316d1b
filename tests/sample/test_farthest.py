"""farthest_point_sampling: hand-checked values, a NumPy reference, batching, jit/vmap, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax import farthest_point_sampling, icosphere


def _reference(points, count, start):
    """Greedy farthest-point order by an explicit loop in float32, the reference's arithmetic
    (ties: lowest index)."""
    points = np.asarray(points, np.float32)
    chosen = [start]
    nearest = np.full(points.shape[0], np.inf, np.float32)
    for _ in range(1, count):
        nearest = np.minimum(nearest, np.sum((points - points[chosen[-1]]) ** 2, axis=1))
        nearest[chosen] = -1
        chosen.append(int(np.argmax(nearest)))
    return np.array(chosen)


def test_hand_checked():
    points = jnp.array([[0.0, 0.0], [0.1, 0.0], [1.0, 0.0], [1.0, 1.0], [0.5, 0.5]])
    np.testing.assert_array_equal(farthest_point_sampling(points, 5), [0, 3, 2, 4, 1])
    np.testing.assert_array_equal(farthest_point_sampling(points, 2, start_index=3), [3, 0])
    np.testing.assert_array_equal(farthest_point_sampling(points, 1, start_index=4), [4])


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("dims", [1, 3, 5])
def test_matches_reference(dtype, dims):
    points = jnp.asarray(np.random.default_rng(dims).normal(size=(300, dims)), dtype)
    out = farthest_point_sampling(points, 40, start_index=7)
    assert out.dtype == jnp.int32 and out.shape == (40,)
    np.testing.assert_array_equal(out, _reference(points, 40, 7))


def test_covering_radius_is_a_two_approximation():
    """Gonzalez: the covering radius of the first K is at most twice that of any K centres."""
    points = np.asarray(icosphere(3).points)
    chosen = np.asarray(farthest_point_sampling(jnp.asarray(points), 30))
    d = np.linalg.norm(points[:, None] - points[chosen][None], axis=-1).min(axis=1)
    # The K+1-th pick is at distance max(d) from all K, so K+1 points are pairwise >= max(d):
    # any K centres leave two of them in one cluster, whose radius is then >= max(d) / 2.
    pairwise = np.linalg.norm(points[chosen][:, None] - points[chosen][None], axis=-1)
    assert pairwise[~np.eye(30, dtype=bool)].min() >= d.max() - 1e-12
    assert len(set(chosen.tolist())) == 30


def test_near_ties_fall_as_numpy_rounds():
    """Regular points tie in exact arithmetic and differ in their last bits in float32: the
    order is the NumPy reference's only if every square is rounded as there. Compiled at XLA's
    default optimisation level (the suite's cheap level fuses no multiply-adds; the default one
    fused them into the sum and changed the third pick here)."""
    points = np.asarray(icosphere(3).points) * 3.1
    optimised = {"xla_backend_optimization_level": 3, "xla_llvm_disable_expensive_passes": False}
    sample = jax.jit(lambda p: farthest_point_sampling(p, 30, start_index=5), compiler_options=optimised)
    np.testing.assert_array_equal(sample(jnp.asarray(points)), _reference(points, 30, 5))


def test_duplicates_all_points_and_empty():
    points = jnp.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0], [1.0, 0.0]])
    out = np.asarray(farthest_point_sampling(points, 4))
    assert sorted(out.tolist()) == [0, 1, 2, 3]
    np.testing.assert_array_equal(out[:2], [0, 2])
    assert farthest_point_sampling(points, 0).shape == (0,)
    assert farthest_point_sampling(jnp.zeros((0, 3)), 0).shape == (0,)


def test_batched_jit_and_vmap():
    points = jnp.asarray(np.random.default_rng(0).normal(size=(3, 50, 3)))
    batched = farthest_point_sampling(points, 10, start_index=2)
    assert batched.shape == (3, 10)
    loop = jnp.stack([farthest_point_sampling(p, 10, start_index=2) for p in points])
    np.testing.assert_array_equal(batched, loop)
    np.testing.assert_array_equal(jax.vmap(lambda p: farthest_point_sampling(p, 10, start_index=2))(points), loop)
    np.testing.assert_array_equal(jax.jit(lambda p: farthest_point_sampling(p, 10, start_index=2))(points), loop)
    assert farthest_point_sampling(points, 0).shape == (3, 0)


def test_errors():
    points = jnp.zeros((5, 3))
    with pytest.raises(TypeError, match="points"):
        farthest_point_sampling(jnp.zeros((5, 3), jnp.int32), 2)
    with pytest.raises(ValueError, match="points"):
        farthest_point_sampling(jnp.zeros(5), 2)
    with pytest.raises(ValueError, match="num_samples"):
        farthest_point_sampling(points, 6)
    with pytest.raises(ValueError, match="num_samples"):
        farthest_point_sampling(points, -1)
    with pytest.raises(TypeError, match="num_samples"):
        farthest_point_sampling(points, True)
    with pytest.raises(ValueError, match="start_index"):
        farthest_point_sampling(points, 2, start_index=5)
    with pytest.raises(TypeError, match="start_index"):
        farthest_point_sampling(points, 2, start_index=1.0)


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_low_precision_points_are_compared_in_float32(dtype):
    # As the reference: any floating dtype, distances in float32 (exact for these inputs).
    from tests.op_cases import CASES

    fps = CASES["farthest_point_sampling"](jnp.float32)  # the case table's points and count
    points, count = fps.arrays[0].astype(dtype), fps.fixed["num_samples"]
    out = farthest_point_sampling(points, count, start_index=5)
    np.testing.assert_array_equal(out, _reference(np.asarray(points.astype(jnp.float32)), count, 5))


def test_float64_points_are_compared_in_float32():
    # 1 + 1e-9 lies farther from 0 than -1 in float64, but both are 1 away in float32: the tie
    # goes to the lower index, as in the reference.
    points = jnp.array([[0.0], [-1.0], [1.0 + 1e-9]], jnp.float64)
    np.testing.assert_array_equal(farthest_point_sampling(points, 2), [0, 1])


def test_random_start_draws_one_start_per_cloud_from_the_key():
    points = jnp.asarray(np.random.default_rng(4).normal(size=(3, 40, 2)), jnp.float32)
    key = jax.random.key(7)
    out = np.asarray(farthest_point_sampling(points, 6, random_start=key))
    np.testing.assert_array_equal(out, [_reference(p, 6, s) for p, s in zip(np.asarray(points), out[:, 0])])
    assert len(set(out[:, 0].tolist())) > 1  # one draw per cloud (equal starts: 1 in 40 per pair)
    np.testing.assert_array_equal(farthest_point_sampling(points, 6, random_start=jax.random.PRNGKey(7)), out)  # raw keys too
    drawn = {int(farthest_point_sampling(points[0], 1, random_start=jax.random.key(seed))[0]) for seed in range(20)}
    assert len(drawn) > 5  # uniform over 40 indices: 20 draws repeat a few at most


def test_start_index_arrays_per_cloud_also_traced():
    points = jnp.asarray(np.random.default_rng(5).normal(size=(3, 40, 2)), jnp.float32)
    starts = jnp.array([3, 0, 39])
    expected = [_reference(p, 6, int(s)) for p, s in zip(np.asarray(points), starts)]
    np.testing.assert_array_equal(farthest_point_sampling(points, 6, start_index=starts), expected)
    np.testing.assert_array_equal(jax.jit(lambda p, s: farthest_point_sampling(p, 6, start_index=s))(points, starts), expected)
    with pytest.raises(ValueError, match=r"start_index must lie in \[0, 40\)"):
        farthest_point_sampling(points, 6, start_index=jnp.array([3, 0, 40]))
    with pytest.raises(Exception, match=r"start_index must lie in \[0, 40\)"):  # under the caller's jit: JAX's runtime error
        jax.block_until_ready(jax.jit(lambda p, s: farthest_point_sampling(p, 6, start_index=s))(points, jnp.array([-1, 0, 0])))
    with pytest.raises(ValueError, match=r"start_index must be an integer array of shape \(\) or \(B,\)"):
        farthest_point_sampling(points, 6, start_index=jnp.array([1, 2]))


def test_random_start_and_implementation_errors():
    points = jnp.zeros((5, 3))
    with pytest.raises(ValueError, match="random_start=True needs a generator"):
        farthest_point_sampling(points, 2, random_start=True)
    with pytest.raises(ValueError, match="not both"):
        farthest_point_sampling(points, 2, random_start=jax.random.key(0), start_index=1)
    with pytest.raises(TypeError, match="random_start must be a bool or a jax.random key"):
        farthest_point_sampling(points, 2, random_start=1)
    with pytest.raises(ValueError, match="implementation='warp' has no kernel"):
        farthest_point_sampling(points, 2, implementation="warp")
    with pytest.raises(KeyError, match="unknown implementation 'cuda'"):
        farthest_point_sampling(points, 2, implementation="cuda")
    for name in ("jax", "torch", None):
        np.testing.assert_array_equal(farthest_point_sampling(points, 2, implementation=name), [0, 1])
