"""Bad input never crashes the process: every op, every backend, random malformed arguments.

Each case either runs (and returns finite-or-NaN arrays of the promised shape) or raises one of the
documented exception types. A segfault or an out-of-bounds kernel read would kill the test process.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import geomjax

DOCUMENTED = (TypeError, ValueError, KeyError, RuntimeError)

dtypes = st.sampled_from([jnp.float32, jnp.float64, jnp.float16, jnp.int32, jnp.bool_])
small_shape = st.lists(st.integers(0, 4), min_size=0, max_size=4).map(tuple)
values = st.sampled_from([0.0, 1.0, -1.0, np.nan, np.inf, 1e30, 1e-30])


def _array(shape, dtype, fill):
    data = np.random.default_rng(len(shape)).normal(size=shape)
    if data.size:
        data.flat[0] = fill
    with np.errstate(all="ignore"):  # NaN, inf and 1e30 cast to integers and float16
        # Converted by NumPy and transferred by device_put: no compiled program per shape and
        # dtype (jnp.asarray of a NumPy array compiles one).
        return jax.device_put(data.astype(dtype))


def _call(fn, *args, **kwargs):
    try:
        out = fn(*args, **kwargs)
    except DOCUMENTED:
        return
    assert out.shape == args[0].shape


BACKENDS = ["jax", "warp"]


@pytest.mark.parametrize("implementation", BACKENDS)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p_shape=small_shape, c_shape=small_shape, p_dtype=dtypes, c_dtype=dtypes, fill=values,
       radius=st.one_of(values, st.just(True), st.just("a")))
def test_morph_survives_bad_input(implementation, p_shape, c_shape, p_dtype, c_dtype, fill, radius):
    points, controls = _array(p_shape, p_dtype, fill), _array(c_shape, c_dtype, fill)
    _call(geomjax.morph_points, points, controls, controls, radius=radius, implementation=implementation)


@pytest.mark.parametrize("implementation", BACKENDS)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p_shape=small_shape, c_shape=small_shape, p_dtype=dtypes, c_dtype=dtypes, fill=values,
       smoothing=st.one_of(values, st.just(False)), polynomial=st.sampled_from([True, False, 1]))
def test_rbf_survives_bad_input(implementation, p_shape, c_shape, p_dtype, c_dtype, fill, smoothing, polynomial):
    points, controls = _array(p_shape, p_dtype, fill), _array(c_shape, c_dtype, fill)
    _call(geomjax.radial_basis_function_deform_points, points, controls, controls,
          smoothing=smoothing, polynomial=polynomial, implementation=implementation)


@pytest.mark.parametrize("implementation", BACKENDS)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(p_shape=small_shape, lattice_shape=st.lists(st.integers(0, 5), min_size=0, max_size=5).map(tuple),
       p_dtype=dtypes, fill=values, basis=st.sampled_from(["bernstein", "bspline", "linear", "quintic_hermite", "nurbs"]),
       extent=st.sampled_from([(1.0, 1.0, 1.0), (1.0, 0.0, 1.0), (1.0, 1.0), (np.nan, 1.0, 1.0), "abc"]))
def test_ffd_survives_bad_input(implementation, p_shape, lattice_shape, p_dtype, fill, basis, extent):
    points, lattice = _array(p_shape, p_dtype, fill), _array(lattice_shape, p_dtype, fill)
    _call(geomjax.free_form_deform_points, points, lattice, origin=(0.0, 0.0, 0.0), extent=extent,
          basis=basis, implementation=implementation)
