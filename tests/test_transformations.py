"""Every op, every transformation: table-driven tests over the op registry (lineax-style).

Each op of ``geomjax._registry.REGISTRY`` has a case in ``tests/op_cases.py``; the tests below are
parametrised over the registry and each op's backends, and compare every result with an
independent computation: the eager call, a Python loop, central finite differences, the JAX path
(the specification) or the float64 result.

Runtime: compilation dominates. Each (op, dtype, backend) compiles one program that computes the
outputs and every transform at once (``program``), at XLA's cheap optimisation level (set for the
whole session in ``tests/conftest.py``); its results are cached and
shared by the tests that compare against them. Transforms beyond values run in float64 only.
"""

from __future__ import annotations

import functools
import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from jax.test_util import check_jvp, check_vjp

import geomjax
import torch_bridge
from geomjax._dispatch import PORTABLE_ALIASES, select_implementation
from geomjax._registry import JAX_DIFFERENTIABLE, REGISTRY, declaration
from torch_bridge._ops import OPS as TORCH_TABLE

from .op_cases import CASES, OpCase, assert_trees_close, torch_inputs

NAMES = list(REGISTRY)
DIFFERENTIABLE = [n for n in NAMES if REGISTRY[n].differentiable]
WARP_OPS = [n for n in NAMES if "warp" in REGISTRY[n].backends]
DTYPES = {"f32": jnp.float32, "f64": jnp.float64}
DEVICES = ["cpu", pytest.param("gpu", marks=pytest.mark.gpu)]


# Confirmed library bugs, xfail(strict=True) with the reason: a fix turns them into failures to
# remove. None at present.
XFAIL: dict[str, str] = {}


def param(*values, id):
    """``pytest.param`` marked ``xfail(strict=True)`` when ``id`` is a confirmed bug of ``XFAIL``."""
    marks = [pytest.mark.xfail(strict=True, reason=XFAIL[id])] if id in XFAIL else []
    if id.endswith("-gpu"):
        marks.append(pytest.mark.gpu)
    return pytest.param(*values, id=id, marks=marks)


def _label(implementation):
    return "default" if implementation is None else implementation


def _backend_params(names, *, default=False, transforms=("",)):
    """``(name, implementation[, transform])`` for every backend of each op, ids ``op-backend-transform``."""
    params = []
    for name in names:
        implementations = ([None] if default else []) + list(REGISTRY[name].backends)
        for implementation in implementations:
            for transform in transforms:
                values = (name, implementation, transform) if transform else (name, implementation)
                ident = "-".join(filter(None, (name, _label(implementation), transform)))
                params.append(param(*values, id=ident))
    return params


def capabilities(name, implementation):
    """The registry capabilities of the backend that ``implementation`` runs for the op's case."""
    if implementation is None:
        variant = CASES[name](jnp.float64).fixed.get("basis")
        implementation = select_implementation(name, None, platform=jax.default_backend(), variant=variant).name
    return declaration(name).capabilities(implementation)


def assert_bitwise_equal(actual, expected):
    for a, e in zip(jax.tree.leaves(actual), jax.tree.leaves(expected), strict=True):
        a, e = np.asarray(a), np.asarray(e)
        assert a.dtype == e.dtype and a.shape == e.shape
        np.testing.assert_array_equal(a.reshape(-1).view(np.uint8), e.reshape(-1).view(np.uint8))


# ---------------------------------------------------------------------------------------------
# cached cases and results
# ---------------------------------------------------------------------------------------------


def cached(fn):
    """``functools.cache`` keyed on every argument with its default filled in (``f(a)`` and
    ``f(a, "cpu")`` are one entry: a second entry would compile the same program again)."""
    signature = inspect.signature(fn)
    memo = functools.cache(fn)

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()
        return memo(*bound.args)

    return wrapper


@cached
def case(name, dtype="f64", device="cpu") -> OpCase:
    built = CASES[name](DTYPES[dtype])
    if device == "cpu":
        return built
    target = jax.devices(device)[0]

    def put(x):
        return jax.device_put(x, target) if isinstance(x, jax.Array) else x

    return OpCase(
        **{
            **{f: getattr(built, f) for f in OpCase.__dataclass_fields__},
            "arrays": tuple(put(a) for a in built.arrays),
            "fixed": {k: put(v) for k, v in built.fixed.items()},
        }
    )


@cached
def compiled(name, dtype, implementation, device="cpu"):
    """The op's full outputs as a jitted function of its arrays (default XLA options)."""
    c = case(name, dtype, device)
    return jax.jit(lambda *arrays: c.call(*arrays, implementation=implementation))


def _normal_like(tree, seed):
    rng = np.random.default_rng(seed)
    return jax.tree.map(lambda x: jnp.asarray(rng.normal(size=x.shape), x.dtype), tree)


def _uses_fast_path(name):
    """The CPU default is a backend that lacks forward mode or second order (served by JAX)."""
    caps = capabilities(name, None)
    return not (caps.forward and caps.higher_order)


def _with_jacrev2(name):
    """Reverse over reverse (torch's double backward) is compared where something other than
    plain JAX autodiff serves it: a first-order default, or a Warp backend declaring second order."""
    backends = declaration(name).backends
    return _uses_fast_path(name) or ("warp" in backends and backends["warp"].higher_order)


def transforms_of(name, dtype, implementation):
    """What the combined program computes for this backend: float64 runs every transform the
    backend supports (the default: all of the JAX path's), float32 the first order only."""
    if not REGISTRY[name].differentiable:
        return ()
    if dtype != "f64":
        return ()  # float32: values only
    caps = JAX_DIFFERENTIABLE if implementation is None else declaration(name).capabilities(implementation)
    found = ["vjp"]
    if caps.forward:
        found += ["jvp", "jacfwd"]
    if caps.higher_order:
        # Reverse over reverse where it is compared (with the JAX path's Hessian, the same matrix).
        found += ["hessian"] + (["jacrev2"] if implementation != "jax" and _with_jacrev2(name) else [])
    return tuple(found)


@cached
def program(name, dtype, implementation, device="cpu"):
    """One jitted program per (op, dtype, backend, device) computing the outputs and every
    transform of ``transforms_of``: one compile instead of one per transform (compilation
    dominates).

    Called as ``program(arrays, cotangents, tangents)``; returns a dict: ``"full"`` (every
    output), ``"out"`` (the differentiated outputs), and one entry per transform.
    """
    c = case(name, dtype, device)
    f, loss = c.differentiable_function(implementation), c.loss(implementation)
    argnums = tuple(range(len(c.arrays)))
    transforms = transforms_of(name, dtype, implementation)

    def run(arrays, cotangents, tangents):
        results = {"full": c.call(*arrays, implementation=implementation)}
        if not transforms:
            return results
        results["out"] = tuple(results["full"][i] for i in c.differentiated)
        results["vjp"] = jax.vjp(f, *arrays)[1](cotangents)
        if "jvp" in transforms:
            results["jvp"] = jax.jvp(f, arrays, tangents)
            results["jacfwd"] = jax.jacfwd(f, argnums=argnums)(*arrays)
        if "hessian" in transforms:
            # With respect to the first array: the whole block Hessian costs 2.5x the compile time
            # and exercises the same rules.
            results["hessian"] = jax.hessian(loss)(*arrays)
        if "jacrev2" in transforms:
            results["jacrev2"] = jax.jacrev(jax.jacrev(loss))(*arrays)
        return results

    return jax.jit(run)


@cached
def vjp_program(name, dtype, implementation, device="cpu"):
    """``(arrays, cotangents) -> (outputs, vjp)``: the value and the first-order reverse
    derivative alone, for the finite-difference check (a fraction of ``program``'s compile time,
    so that the quick tier, which runs that check for every op, stays quick)."""
    c = case(name, dtype, device)
    f = c.differentiable_function(implementation)

    def run(arrays, cotangents):
        out, pullback = jax.vjp(f, *arrays)
        return out, pullback(cotangents)

    return jax.jit(run)


def probes(name, dtype, device="cpu"):
    """Fixed random ``(cotangents, tangents)`` for the case's differentiated outputs and arrays."""
    c = case(name, dtype, device)
    if not REGISTRY[name].differentiable:
        return (), ()
    out = jax.eval_shape(c.differentiable_function("jax"), *c.arrays)
    return _normal_like(out, 1), _normal_like(c.arrays, 2)


@cached
def results(name, dtype, implementation, device="cpu"):
    c = case(name, dtype, device)
    if capabilities(name, implementation).eager_only:
        return {"full": c.call(*c.arrays, implementation=implementation)}
    return program(name, dtype, implementation, device)(c.arrays, *probes(name, dtype, device))


def reference(name, transform):
    """The JAX path's float64 ``transform`` (reverse over reverse: its Hessian, the same matrix)."""
    return result(name, "jax", "hessian" if transform == "jacrev2" else transform)


def result(name, implementation, transform, dtype="f64", device="cpu"):
    found = results(name, dtype, implementation, device)
    assert transform in found, f"{name} ({_label(implementation)}) does not compute {transform}"
    return found[transform]


@cached
def eager(name, dtype, implementation):
    c = case(name, dtype)
    return c.call(*c.arrays, implementation=implementation)


# ---------------------------------------------------------------------------------------------
# the registry
# ---------------------------------------------------------------------------------------------


def test_every_registered_op_has_a_case():
    assert set(CASES) == set(REGISTRY)


@pytest.mark.parametrize("name", NAMES)
def test_declaration_matches_the_public_function(name):
    op = declaration(name)
    function = getattr(geomjax, name)
    assert op.name == name and inspect.unwrap(function).__module__ == op.module
    assert op.backends["jax"] == JAX_DIFFERENTIABLE or not op.differentiable
    for key, backend in op.defaults.items():
        platform, _, _variant = key.partition("/")
        assert platform in ("cpu", "gpu") and backend in op.backends, (key, backend)
    if op.mesh_method is not None:
        assert callable(getattr(geomjax.Mesh, op.mesh_method))
    # Every backend of a differentiable op differentiates at least to first order in reverse mode.
    assert all(caps.reverse for caps in op.backends.values()) == op.differentiable


# One op per family, with its variant, on a case where Warp and JAX differ bitwise in float64 (so a
# bitwise comparison tells the backends apart). mesh_poisson_disk_sample is left out: its two
# backends share the candidates and give identical samples by design.
FAMILY_DEFAULTS = [
    ("morph_points", None),
    ("radial_basis_function_deform_points", None),
    ("free_form_deform_points", "cubic_hermite"),
    ("simplex_strain_energy", None),
    ("signed_distance_field", None),
    ("mesh_to_voxel_fraction", None),
    ("remeshing", None),
]


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize(("name", "variant"), FAMILY_DEFAULTS, ids=[n for n, _ in FAMILY_DEFAULTS])
def test_default_runs_the_declared_backend(name, variant, device):
    declared = declaration(name).default_backend(device, variant)
    assert select_implementation(name, None, platform=device, variant=variant).name == declared
    c = case(name, "f64", device)
    assert_bitwise_equal(c.call(*c.arrays, implementation=None), c.call(*c.arrays, implementation=declared))


@pytest.mark.parametrize(("name", "variant"), FAMILY_DEFAULTS, ids=[n for n, _ in FAMILY_DEFAULTS])
def test_implementation_torch_means_jax(name, variant):
    assert PORTABLE_ALIASES == {"torch": "jax"}
    c = case(name, "f64")
    assert_bitwise_equal(c.call(*c.arrays, implementation="torch"), eager(name, "f64", "jax"))


# ---------------------------------------------------------------------------------------------
# jit and vmap
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "implementation"), _backend_params(NAMES))
def test_jit_equals_eager(name, implementation):
    c = case(name, "f64")
    if capabilities(name, implementation).eager_only:
        with pytest.raises(TypeError):
            compiled(name, "f64", implementation)(*c.arrays)
        return
    jitted = result(name, implementation, "full")  # the outputs of the jitted program
    assert_trees_close(jitted, eager(name, "f64", implementation), jnp.float64, c.size)


@pytest.mark.parametrize(("name", "implementation"), _backend_params(NAMES))
def test_vmap_equals_loop(name, implementation):
    c = case(name, "f64")
    if not capabilities(name, implementation).vmap or c.batched is None:
        # Skipped for what the registry declares (an eager-only op, whose output size depends on
        # the data): the case table agrees, and vmap raises the documented TypeError.
        assert c.batched is None and not capabilities(name, implementation).vmap, "case table and registry disagree"
        stacked = jnp.stack([c.arrays[0]] * 2)
        with pytest.raises(TypeError, match="runs eagerly"):
            jax.vmap(lambda first: c.call(first, *c.arrays[1:], implementation=implementation))(stacked)
        pytest.skip(f"{name} ({implementation}) is not vmappable (registry capabilities)")
    f = compiled(name, "f64", implementation)
    batched = jax.vmap(f, in_axes=c.in_axes)(*c.batched)
    loop = [f(*(a if axis is None else a[b] for a, axis in zip(c.batched, c.in_axes))) for b in range(c.batched[c.in_axes.index(0)].shape[0])]
    expected = jax.tree.map(lambda *xs: jnp.stack(xs), *loop)
    assert_trees_close(batched, expected, jnp.float64, c.size)


# ---------------------------------------------------------------------------------------------
# first-order gradients against finite differences (float64)
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "implementation"), _backend_params(DIFFERENTIABLE, default=True))
def test_grad_matches_finite_differences(name, implementation):
    # check_grads(f, arrays, order=1, modes=["rev"]) is check_vjp(f, partial(jax.vjp, f), arrays);
    # here f and its VJP come from one compiled value-and-VJP program.
    c = case(name, "f64")
    run = vjp_program(name, "f64", implementation)
    cotangents, _ = probes(name, "f64")

    def f(*arrays):
        return run(arrays, cotangents)[0]

    def f_vjp(*arrays):
        return f(*arrays), lambda ct: run(arrays, ct)[1]

    check_vjp(f, f_vjp, c.arrays)


# ---------------------------------------------------------------------------------------------
# implementation=None keeps every transform of the JAX path
# ---------------------------------------------------------------------------------------------

DEFAULT_TRANSFORMS = [
    param(name, transform, id=f"{name}-default-{transform}")
    for name in DIFFERENTIABLE
    for transform in ("jvp", "jacfwd", "hessian")
] + [
    # Reverse over reverse where the default is not plain JAX autodiff (see _with_jacrev2).
    param(name, "jacrev2", id=f"{name}-default-jacrev2")
    for name in DIFFERENTIABLE
    if _with_jacrev2(name)
]


def _contract(derivative, directions):
    """``sum_a <derivative[a], directions[a]>`` over the trailing (input) axes of each block."""
    return sum(jnp.tensordot(block, d, axes=d.ndim) for block, d in zip(derivative, directions))


@pytest.mark.parametrize(("name", "transform"), DEFAULT_TRANSFORMS)
def test_default_supports_the_jax_transforms(name, transform):
    c = case(name, "f64")
    assert_trees_close(result(name, None, transform), reference(name, transform), jnp.float64, c.size)
    # ...and equals central finite differences along a random direction: an independent check,
    # which the comparison above is not where the default already is the JAX path. The program
    # is evaluated at perturbed inputs of the same shapes: nothing new is compiled.
    run = program(name, "f64", None)
    cotangents, tangents = probes(name, "f64")

    def out(*arrays):
        return run(arrays, cotangents, tangents)["out"]

    if transform == "jvp":
        check_jvp(out, lambda arrays, directions: run(arrays, cotangents, directions)["jvp"], c.arrays)
    elif transform == "jacfwd":
        # jacfwd[output][argument], contracted with the direction: the directional derivative.
        def jacobian_times(arrays, directions):
            jacobian = run(arrays, cotangents, tangents)["jacfwd"]
            return out(*arrays), tuple(_contract(per_argument, directions) for per_argument in jacobian)

        check_jvp(out, jacobian_times, c.arrays)
    else:  # hessian / jacrev2: of the sum-of-squares loss, with respect to the first array

        def gradient(first):
            arrays = (first, *c.arrays[1:])
            return run(arrays, tuple(2 * y for y in out(*arrays)), tangents)["vjp"][0]

        def hessian_times(firsts, directions):
            arrays = (firsts[0], *c.arrays[1:])
            hessian = run(arrays, cotangents, tangents)[transform]
            return gradient(firsts[0]), _contract((hessian,), directions)

        check_jvp(gradient, hessian_times, (c.arrays[0],))


FIRST_ORDER_WARP = [n for n in WARP_OPS if REGISTRY[n].differentiable]


@pytest.mark.parametrize(
    ("name", "transform"),
    [
        param(n, t, id=f"{n}-warp-{t}")
        for n in FIRST_ORDER_WARP
        for t in ("jacfwd", "hessian", "jacrev2", "grad")
    ],
)
def test_explicit_warp_names_the_transforms_it_lacks(name, transform):
    caps = declaration(name).capabilities("warp")
    c = case(name, "f64")
    if transform == "grad":
        # First-order reverse mode: the hand-written adjoint, equal to JAX's gradient.
        assert_trees_close(result(name, "warp", "vjp"), result(name, "jax", "vjp"), jnp.float64, c.size)
        return
    supported = caps.forward if transform == "jacfwd" else caps.higher_order
    if supported:
        assert_trees_close(result(name, "warp", transform), reference(name, transform), jnp.float64, c.size)
        return
    f, loss = c.differentiable_function("warp"), c.loss("warp")
    traced = {"jacfwd": jax.jacfwd(f), "hessian": jax.hessian(loss), "jacrev2": jax.jacrev(jax.jacrev(loss))}[transform]
    fragment = "forward-mode" if transform == "jacfwd" else "second-order"
    with pytest.raises(NotImplementedError, match=rf"{fragment}.*implementation='jax'"):
        jax.jit(traced).lower(*c.arrays)  # raised while lowering: nothing is compiled


# ---------------------------------------------------------------------------------------------
# dtypes and empty inputs
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", list(DTYPES))
@pytest.mark.parametrize("name", NAMES)
def test_dtypes_are_kept(name, dtype):
    c = case(name, dtype)
    out = result(name, None, "full", dtype)
    expected = c.output_dtype or DTYPES[dtype]
    # The float outputs (the integer indices, for an op without any).
    checked = [o for o in out if jnp.issubdtype(o.dtype, jnp.floating)] or out
    assert all(o.dtype == expected for o in checked), [o.dtype for o in out]
    if dtype == "f32" and REGISTRY[name].differentiable:
        # float32 agrees with float64 to float32 precision.
        reference = [o.astype(jnp.float32) if jnp.issubdtype(o.dtype, jnp.floating) else o for o in result(name, None, "full")]
        assert_trees_close(out, reference, jnp.float32, c.size)


@pytest.mark.parametrize(("name", "implementation"), _backend_params([n for n in NAMES if CASES[n](jnp.float64).empty is not None]))
def test_empty_inputs(name, implementation):
    c = case(name, "f64")
    full = c.call(*c.arrays, implementation=implementation)
    out = c.call(*c.empty, implementation=implementation)
    assert [o.shape[1:] for o in out] == [o.shape[1:] for o in full] and all(o.shape[0] == 0 for o in out)
    assert [o.dtype for o in out] == [o.dtype for o in full]
    if REGISTRY[name].differentiable:
        f = c.differentiable_function(implementation)
        primal, pullback = jax.vjp(f, *c.empty)
        grads = pullback(jax.tree.map(jnp.ones_like, primal))
        for g, a in zip(grads, c.empty):
            assert g.shape == a.shape and g.dtype == a.dtype and not np.any(np.asarray(g))


# ---------------------------------------------------------------------------------------------
# Warp equals JAX
# ---------------------------------------------------------------------------------------------


def _canonical(name, out):
    """Outputs whose order carries no meaning, sorted (the Poisson samples)."""
    if name == "mesh_poisson_disk_sample":
        (samples,) = out
        return (samples[np.lexsort(np.asarray(samples).T[::-1])],)
    return out


@pytest.mark.parametrize(
    ("name", "dtype", "device"),
    [param(n, d, device, id=f"{n}-warp-{d}-{device}") for n in WARP_OPS for d in DTYPES for device in ("cpu", "gpu")],
)
def test_warp_equals_jax(name, dtype, device):
    c = case(name, dtype, device)
    assert_trees_close(
        _canonical(name, result(name, "warp", "full", dtype, device)),
        _canonical(name, result(name, "jax", "full", dtype, device)),
        DTYPES[dtype],
        c.size,
    )
    if REGISTRY[name].differentiable and dtype == "f64":
        # First-order gradients in float64 (float32 programs compute values only, to save compiles).
        assert_trees_close(result(name, "warp", "vjp", dtype, device), result(name, "jax", "vjp", dtype, device), DTYPES[dtype], c.size)


# ---------------------------------------------------------------------------------------------
# bad input raises the documented type
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_unknown_implementation_is_a_key_error(name):
    c = case(name, "f32")
    if not c.takes_implementation:
        pytest.skip(f"{name} takes no implementation argument (JAX only)")
    with pytest.raises(KeyError, match="implementation"):
        c.call(*c.arrays, implementation="cuda")


# Every backend and the default: validation runs before the op's program is traced, so these rows
# cost a few small programs (of the checks) at most.
BAD_INPUT_PARAMS = _backend_params(NAMES, default=True)


@pytest.mark.parametrize(("name", "implementation"), BAD_INPUT_PARAMS)
def test_non_float_array_is_a_type_error(name, implementation):
    c = case(name, "f32")
    with pytest.raises(TypeError, match="float"):
        c.call(c.arrays[0].astype(jnp.int32), *c.arrays[1:], implementation=implementation)


@pytest.mark.parametrize(("name", "implementation"), BAD_INPUT_PARAMS)
def test_wrong_shape_is_a_value_error(name, implementation):
    c = case(name, "f32")
    with pytest.raises(ValueError, match="shape|dimension|rank|\\(N, 3\\)"):
        c.call(*c.bad_shape, implementation=implementation)


@pytest.mark.parametrize(("name", "implementation"), BAD_INPUT_PARAMS)
def test_bad_option_is_a_value_error(name, implementation):
    c = case(name, "f32")
    if c.bad_option is None:
        assert name == "displace_points", "every op with options lists one it rejects (op_cases.bad_option)"
        pytest.skip(f"{name} has no option to reject")
    option = next(iter(c.bad_option))
    fixed = {k: v for k, v in c.fixed.items() if k not in c.bad_option}
    arrays = {k: a for k, a in zip(c.arg_names, c.arrays) if k not in c.bad_option}
    kwargs = {**fixed, **arrays, **c.bad_option}
    if c.takes_implementation:
        kwargs["implementation"] = implementation
    with pytest.raises(ValueError, match=option):
        c.function(**kwargs)


def _real_options(name):
    """The case's real options: Python floats and lists of floats (box origins, extents)."""
    fixed = case(name, "f32").fixed
    return [k for k, v in fixed.items() if isinstance(v, float) or (isinstance(v, list) and all(isinstance(e, float) for e in v))]


def _integer_options(name):
    fixed = case(name, "f32").fixed
    return [k for k, v in fixed.items() if isinstance(v, int) and not isinstance(v, bool)]


@pytest.mark.parametrize("name", [n for n in NAMES if _integer_options(n)])
def test_integers_beyond_int64_are_a_value_error(name):
    # Counts, sizes and seeds: a Python int beyond int64 raises ValueError before anything runs
    # (remeshing looped without end on max_iterations=10**400).
    c = case(name, "f32")
    for key in _integer_options(name):
        with pytest.raises(ValueError, match=f"{key} must be at most"):
            c.call(*c.arrays, fixed={**c.fixed, key: 10**400})


@pytest.mark.parametrize("name", [n for n in NAMES if _real_options(n)])
def test_python_integers_beyond_every_float_are_a_value_error(name):
    # A Python int too large for any float (10**400) given for a real option: the documented
    # ValueError, never float()'s OverflowError. Every real option of the case (scalars and
    # the entries of box sequences).
    c = case(name, "f32")
    for key in _real_options(name):
        huge = 10**400 if isinstance(c.fixed[key], float) else [10**400, *c.fixed[key][1:]]
        with pytest.raises(ValueError, match=f"{key}.*must be finite"):
            c.call(*c.arrays, fixed={**c.fixed, key: huge})


# ---------------------------------------------------------------------------------------------
# torch_bridge: gradcheck and gradgradcheck with default arguments
# ---------------------------------------------------------------------------------------------

# The differentiable ops that torch_bridge exposes outside its op table (the mesh queries of
# _ops.MESH_OPS and _ray.py). The ops of the table (_ops.OPS) are gradchecked on every backend,
# and gradgradchecked on the default, by tests/torch_bridge/test_ops.py: running them here too
# would repeat those checks at other shapes, each a second set of compiled programs.
TORCH_OPS = [n for n in DIFFERENTIABLE if hasattr(torch_bridge, n) and n not in {op.name for op in TORCH_TABLE}]


def _torch_function(name, num_differentiated=None):
    """``f(*tensors)`` of the case's first ``num_differentiated`` arrays (all by default), the
    others fixed, returning the differentiated outputs; and those tensors, requiring grad."""
    c = case(name, "f64")
    inputs = torch_inputs(name, torch.float64)
    tensors = [inputs[k] for k in c.arg_names]
    fixed = {k: v for k, v in inputs.items() if k not in c.arg_names}
    count = len(tensors) if num_differentiated is None else num_differentiated
    fn = getattr(torch_bridge, name)

    def f(*differentiated):
        out = c.call(*differentiated, *tensors[count:], fn=fn, fixed=fixed)
        return tuple(out[i] for i in c.differentiated)

    return f, tuple(t.requires_grad_() for t in tensors[:count])


@pytest.mark.parametrize("name", TORCH_OPS)
def test_torch_gradcheck(name):
    f, inputs = _torch_function(name)
    assert torch.autograd.gradcheck(f, inputs, fast_mode=True)


@pytest.mark.parametrize("name", TORCH_OPS)
def test_torch_gradgradcheck(name):
    # Double backward with respect to the first array (points, or the mesh's vertices): XLA's
    # compile time of the second-order programs grows with the number of differentiated inputs.
    f, inputs = _torch_function(name, num_differentiated=1)
    assert torch.autograd.gradgradcheck(f, inputs, fast_mode=True)
