"""farthest_point_sampling: hand-checked values, a NumPy reference, batching, jit/vmap, errors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax import farthest_point_sampling, icosphere


def _reference(points, count, start):
    """Greedy farthest-point order by an explicit loop (ties: lowest index)."""
    points = np.asarray(points, np.float64)
    chosen = [start]
    nearest = np.full(points.shape[0], np.inf)
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
