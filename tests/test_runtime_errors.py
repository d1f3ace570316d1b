"""Runtime checks (equinox.error_if, host callbacks) reach callers as the documented exception.

Every data-dependent check that can only fail while a compiled program runs must reach an eager
geomjax caller, and every torch_bridge caller (forward and backward, eager path and custom-op
kernel), as its documented type with the op's message as the whole message, and print nothing to
stderr (DESIGN.md, "Validation and errors"). Inside a user's own ``jax.jit`` it stays JAX's
runtime error, whose text on CPU is the XLA status followed by the op's message.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

import geomjax
import torch_bridge
from geomjax._errors import checked_pure_callback, documented_errors, raises_documented_errors, runtime_check
from tests.linalg.meshes import MESHES

TETRA = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
TETRA_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
BAD_FACES = TETRA_FACES.copy()
BAD_FACES[3, 2] = 9  # out of range for 4 vertices
POINTS = np.array([[0.2, 0.2, 2.0], [2.0, 0.1, -1.0]])


def _t(a, dtype=torch.float64):
    return torch.tensor(np.asarray(a), dtype=dtype if np.asarray(a).dtype.kind == "f" else torch.int64)


def _expect(capfd, error, match, function, *args, **kwargs):
    """``function(*args, **kwargs)`` raises exactly ``error`` (a readable message), stderr stays empty."""
    capfd.readouterr()
    with pytest.raises(error, match=match) as info:
        function(*args, **kwargs)
    assert type(info.value) is error, repr(info.value)
    text = str(info.value)
    assert "JaxRuntimeError" not in text and "CpuCallback" not in text and "EquinoxRuntimeError" not in text
    assert info.value.__suppress_context__ or info.value.__context__ is None
    _, err = capfd.readouterr()
    assert err == "", err
    return info.value


# ---------------------------------------------------------------------------------------------
# The helpers themselves


def test_runtime_check_concrete_and_traced(capfd):
    assert runtime_check(1.0, False, "never") == 1.0
    _expect(capfd, RuntimeError, "^toy: concrete$", runtime_check, 1.0, np.array([False, True]), "toy: concrete", RuntimeError)

    checked = jax.jit(lambda x: runtime_check(x, jnp.any(x < 0), "toy: x must be >= 0", ValueError) * 2)
    op = raises_documented_errors(lambda x: checked(x))
    np.testing.assert_array_equal(op(jnp.ones(2)), 2 * jnp.ones(2))
    for _ in range(2):  # a first run (JaxRuntimeError) and a cached one (C++ dispatch)
        _expect(capfd, ValueError, "^toy: x must be >= 0$", op, -jnp.ones(2))


def test_check_codes_are_the_same_in_every_process():
    # A compiled program embeds its checks' codes; JAX's persistent compilation cache can hand it
    # to another process, which must map them to the same messages.
    import subprocess
    import sys

    from geomjax._check_target import code_for

    messages = ["toy: x must be >= 0", "sobolev_deform_points: did not converge"]
    script = f"from geomjax._check_target import code_for; print([code_for(m, ValueError) for m in {messages!r}])"
    other = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True).stdout.strip()
    assert other == str([code_for(m, ValueError) for m in messages])
    assert code_for(messages[0], RuntimeError) == code_for(messages[0], ValueError) + 1


def test_host_callback_errors_translate(capfd):
    def host(x):
        if np.min(x) < 0:
            raise ValueError("toy: host values must be >= 0")
        return x

    run = jax.jit(lambda x: checked_pure_callback(host, jax.ShapeDtypeStruct(x.shape, x.dtype), x))

    def call(x):
        with documented_errors():
            return run(x)

    _expect(capfd, ValueError, "^toy: host values must be >= 0$", call, -jnp.ones(2))


def test_unregistered_errors_pass_through():
    def host(x):
        raise KeyError("toy: not one of ours")

    run = jax.jit(lambda x: jax.pure_callback(host, jax.ShapeDtypeStruct(x.shape, x.dtype), x))
    with pytest.raises((jax.errors.JaxRuntimeError, ValueError), match="not one of ours"):
        with documented_errors():
            run(jnp.ones(2))
    with pytest.raises(TypeError, match="plain"):
        raises_documented_errors(lambda: (_ for _ in ()).throw(TypeError("plain")))()


def test_decorator_keeps_signature_and_docstring():
    import inspect

    for function in (geomjax.shrinkwrap_points, geomjax.sobolev_deform_points, geomjax.radial_basis_function_deform_points):
        assert function.__wrapped__.__doc__ == function.__doc__
        assert inspect.signature(function) == inspect.signature(function.__wrapped__)
        assert "points" in inspect.signature(function).parameters


# ---------------------------------------------------------------------------------------------
# radial_basis_function_deform_points: singular fit -> RuntimeError


RBF_CONTROLS = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 0.0], [0.0, 1.0]])  # a duplicate control


def test_rbf_singular_fit(capfd):
    controls = jnp.asarray(RBF_CONTROLS)
    displacements = jnp.ones_like(controls)
    points = jnp.asarray(np.random.default_rng(0).random((4, 2)))
    _expect(capfd, RuntimeError, "fit system is singular", geomjax.radial_basis_function_deform_points, points, controls, displacements)
    _expect(capfd, RuntimeError, "fit system is singular", geomjax.ThinPlateSplineFit.fit, controls, displacements)
    _expect(
        capfd, RuntimeError, "fit system is singular", torch_bridge.radial_basis_function_deform_points,
        _t(points), _t(controls), _t(displacements),
    )  # fmt: skip
    # With gradients (the forward that keeps the linearisation) and through the custom op.
    _expect(
        capfd, RuntimeError, "fit system is singular", torch_bridge.radial_basis_function_deform_points,
        _t(points), _t(controls), _t(displacements).requires_grad_(),
    )  # fmt: skip
    _expect(capfd, RuntimeError, "fit system is singular", _custom_op, "radial_basis_function_deform_points", _t(points), _t(controls), _t(displacements))


def _custom_op(name, *values, **options):
    """Call ``torch.ops.geomjax.<name>`` (the dispatcher's kernel, not the eager fast path)."""
    import inspect

    function = getattr(torch_bridge, name)
    op = function.bridged_op
    bound = inspect.signature(function).bind(*values, **options)
    bound.apply_defaults()
    slots, statics = op.bind(tuple(bound.arguments.values()))
    return op.lifted.op(*op.lifted.op_arguments(slots, statics, [x is not None and x.requires_grad for x in slots]))


# ---------------------------------------------------------------------------------------------
# sobolev_deform_points: non-convergence and breakdown -> RuntimeError; indices, degenerate cells
# -> ValueError (forward, adjoint, torch eager and custom op)


def _sobolev_mesh(name="triangles-2d"):
    """A small mesh; ``"triangles-fine"`` where the solve must need several iterations (the
    multilevel preconditioner solves a mesh this small directly)."""
    points, cells = MESHES[name]()
    return np.asarray(points, np.float64), np.asarray(cells)


def _rough(shape, seed):
    return np.random.default_rng(seed).normal(size=shape)


SOBOLEV = {"length_scale": 0.3, "implementation": "jax"}


def test_sobolev_non_convergence_and_breakdown(capfd):
    points, cells = _sobolev_mesh("triangles-fine")
    displacement = _rough(points.shape, 1)
    message = "did not converge within 1 iterations"
    _expect(capfd, RuntimeError, message, geomjax.sobolev_deform_points, jnp.asarray(points), jnp.asarray(cells),
            jnp.asarray(displacement), max_iterations=1, **SOBOLEV)  # fmt: skip
    # Twice: the second call runs the cached executable.
    for _ in range(2):
        _expect(capfd, RuntimeError, message, torch_bridge.sobolev_deform_points, _t(points), _t(cells), _t(displacement),
                max_iterations=1, **SOBOLEV)  # fmt: skip
    _expect(capfd, RuntimeError, message, torch_bridge.sobolev_deform_points, _t(points).requires_grad_(), _t(cells),
            _t(displacement), max_iterations=1, **SOBOLEV)  # fmt: skip
    broken = displacement.copy()
    broken[3, 0] = np.nan
    _expect(capfd, RuntimeError, "breakdown", geomjax.sobolev_deform_points, jnp.asarray(points), jnp.asarray(cells),
            jnp.asarray(broken), **SOBOLEV)  # fmt: skip
    _expect(capfd, RuntimeError, "breakdown", torch_bridge.sobolev_deform_points, _t(points), _t(cells), _t(broken), **SOBOLEV)


@pytest.mark.parametrize("implementation", ["jax", "warp", None])
def test_sobolev_non_convergence_reads_the_same_on_every_backend(capfd, implementation):
    # An eager Warp solve on a mesh of this size fails while XLA dispatches the program, which XLA
    # reports as "INTERNAL: Error dispatching computation: <message>"; it must still arrive as the
    # documented RuntimeError, eager and through torch_bridge.
    sphere = geomjax.icosphere(3)
    points, cells = np.asarray(sphere.points, np.float64), np.asarray(sphere.cells)
    displacement = 0.1 * _rough(points.shape, 3)
    options = {"length_scale": 0.5, "max_iterations": 2, "implementation": implementation}
    message = "^sobolev_deform_points: the {} solve did not converge within 2 iterations"
    # Concrete cells: the JAX path chooses Jacobi or the multilevel V-cycle per solve ("PCG"),
    # the Warp path always cycles.
    chosen = "multilevel-PCG" if implementation == "warp" else "PCG"
    _expect(capfd, RuntimeError, message.format(chosen), geomjax.sobolev_deform_points, jnp.asarray(points),
            jnp.asarray(cells), jnp.asarray(displacement), **options)  # fmt: skip
    # torch_bridge builds the same topology from the cells tensor: the same choice.
    _expect(capfd, RuntimeError, message.format(chosen), torch_bridge.sobolev_deform_points, _t(points), _t(cells), _t(displacement), **options)


def test_sobolev_adjoint_non_convergence_in_backward(capfd):
    # A constant displacement is solved by the initial guess; the adjoint solve for a rough
    # cotangent is not, and must raise in backward rather than return an inexact gradient.
    points, cells = _sobolev_mesh("triangles-fine")
    x = _t(points).requires_grad_()
    moved = torch_bridge.sobolev_deform_points(x, _t(cells), torch.ones(points.shape, dtype=torch.float64), max_iterations=1, **SOBOLEV)
    loss = (_t(_rough(points.shape, 2)) * moved).sum()
    _expect(capfd, RuntimeError, "did not converge within 1 iterations", loss.backward, retain_graph=True)
    # create_graph=True goes through the lifted VJP op (a forward of the VJP function).
    _expect(capfd, RuntimeError, "did not converge within 1 iterations", torch.autograd.grad, loss, x, create_graph=True)


def test_sobolev_indices_and_degenerate_cells(capfd):
    points, cells = _sobolev_mesh()
    displacement = _rough(points.shape, 3)
    bad_cells = cells.copy()
    bad_cells[2, 1] = points.shape[0]
    message = rf"cells indices must be in \[0, {points.shape[0]}\)"
    _expect(capfd, ValueError, message, geomjax.sobolev_deform_points, jnp.asarray(points), jnp.asarray(bad_cells),
            jnp.asarray(displacement), **SOBOLEV)  # fmt: skip
    _expect(capfd, ValueError, message, torch_bridge.sobolev_deform_points, _t(points), _t(bad_cells), _t(displacement), **SOBOLEV)
    collapsed = points.copy()
    collapsed[5] = collapsed[0]  # cell (0, 4, 5) gets a repeated point
    degenerate = "cells must be finite, nondegenerate simplices"
    _expect(capfd, ValueError, degenerate, geomjax.sobolev_deform_points, jnp.asarray(collapsed), jnp.asarray(cells),
            jnp.asarray(displacement), **SOBOLEV)  # fmt: skip
    error = _expect(capfd, ValueError, degenerate, torch_bridge.sobolev_deform_points, _t(collapsed), _t(cells), _t(displacement), **SOBOLEV)
    assert str(error).startswith("sobolev_deform_points: cells must be finite")
    _expect(capfd, ValueError, degenerate, _custom_op, "sobolev_deform_points", _t(collapsed), _t(cells), _t(displacement), **SOBOLEV)


# ---------------------------------------------------------------------------------------------
# shrinkwrap_points: indices, non-finite points or offset, no valid triangle -> ValueError


def _shrinkwrap_cases():
    flat = TETRA.copy()
    flat[:, 2] = 0.0
    flat[3] = flat[0]  # every face degenerate
    inf_points = POINTS.copy()
    inf_points[1, 0] = np.inf
    return [
        ("target_faces indices must be in", POINTS, TETRA, BAD_FACES, 0.0),
        ("points must be finite", inf_points, TETRA, TETRA_FACES, 0.0),
        ("offset must be finite", POINTS, TETRA, TETRA_FACES, np.array(np.nan)),
        ("no valid triangle", POINTS, np.zeros((4, 3)), TETRA_FACES, 0.0),
    ]


@pytest.mark.parametrize("case", range(4))
def test_shrinkwrap_runtime_checks(capfd, case):
    match, points, target, faces, offset = _shrinkwrap_cases()[case]
    jax_offset = jnp.asarray(offset) if isinstance(offset, np.ndarray) else offset
    torch_offset = _t(offset) if isinstance(offset, np.ndarray) else offset
    options = {"implementation": "jax"}
    _expect(capfd, ValueError, match, geomjax.shrinkwrap_points, jnp.asarray(points), jnp.asarray(target),
            jnp.asarray(faces), offset=jax_offset, **options)  # fmt: skip
    # Under vmap the checks are traced and run eagerly: the runtime path of the eager op.
    batched = jax.vmap(lambda p: geomjax.shrinkwrap_points(p, jnp.asarray(target), jnp.asarray(faces), offset=jax_offset, **options))
    _expect(capfd, ValueError, match, batched, jnp.asarray(points)[None])
    _expect(capfd, ValueError, match, torch_bridge.shrinkwrap_points, _t(points), _t(target), _t(faces), offset=torch_offset,
            implementation="torch")  # fmt: skip
    _expect(capfd, ValueError, match, torch_bridge.shrinkwrap_points, _t(points).requires_grad_(), _t(target), _t(faces),
            offset=torch_offset, implementation="torch")  # fmt: skip
    _expect(capfd, ValueError, match, _custom_op, "shrinkwrap_points", _t(points), _t(target), _t(faces), offset=torch_offset,
            implementation="torch")  # fmt: skip


def _user_jit_cases():
    """(expected documented type, message fragment, a function of no arguments that runs the op
    inside a user's own ``jax.jit``) for checks of each kind (index range, finiteness, singular
    fit, non-convergence, host callback)."""
    sobolev_points, sobolev_cells = _sobolev_mesh("triangles-fine")
    rbf = jax.jit(lambda c: geomjax.radial_basis_function_deform_points(c, c, jnp.ones_like(c)))
    shrinkwrap = jax.jit(lambda p: geomjax.shrinkwrap_points(p, jnp.asarray(TETRA), jnp.asarray(TETRA_FACES), implementation="jax"))
    sdf = jax.jit(lambda f: geomjax.signed_distance_field(jnp.asarray(TETRA), f, jnp.asarray(POINTS), implementation="jax"))
    sobolev = jax.jit(lambda d: geomjax.sobolev_deform_points(jnp.asarray(sobolev_points), jnp.asarray(sobolev_cells), d, max_iterations=1, **SOBOLEV))

    def host(x):
        if np.min(x) < 0:
            raise ValueError("toy: host values must be >= 0")
        return x

    callback = jax.jit(lambda x: checked_pure_callback(host, jax.ShapeDtypeStruct(x.shape, x.dtype), x) * 2)
    return {
        "rbf singular": (RuntimeError, "radial_basis_function_deform_points: the thin-plate-spline fit system is singular", lambda: rbf(jnp.asarray(RBF_CONTROLS))),
        "shrinkwrap finite": (ValueError, "shrinkwrap_points: points must be finite", lambda: shrinkwrap(jnp.full((2, 3), jnp.inf))),
        "sdf indices": (ValueError, r"signed_distance_field: mesh_indices must lie in \[0, 4\)", lambda: sdf(jnp.asarray(BAD_FACES))),
        "sobolev convergence": (RuntimeError, "sobolev_deform_points: .*did not converge within 1 iterations", lambda: sobolev(jnp.asarray(_rough(sobolev_points.shape, 1)))),
        "host callback": (ValueError, "toy: host values must be >= 0", lambda: callback(-jnp.ones(2))),
    }


@pytest.mark.parametrize("case", sorted(_user_jit_cases()))
def test_user_jit_error_starts_with_the_message(capfd, case):
    # Inside a user's own jax.jit no geomjax code runs when the check fails, so the error stays
    # JAX's; on CPU its text is the XLA status and then the op's message, with nothing printed.
    error, match, run = _user_jit_cases()[case]
    capfd.readouterr()
    for _ in range(2):  # a first run (JaxRuntimeError) and a cached one (C++ dispatch: ValueError)
        with pytest.raises((jax.errors.JaxRuntimeError, ValueError)) as info:
            jax.block_until_ready(run())
        status = "INVALID_ARGUMENT" if error is ValueError else "FAILED_PRECONDITION"
        assert re.match(f"{status}: {match}", str(info.value)), str(info.value)
        assert "Traceback" not in str(info.value) and "equinox" not in str(info.value)
    assert capfd.readouterr().err == ""
    # geomjax.documented_errors() around the user's call gives the documented type.
    _expect(capfd, error, f"^{match}", geomjax.documented_errors()(lambda: jax.block_until_ready(run())))


def test_checks_under_user_jit_keep_the_values_and_gradients():
    run = jax.jit(lambda p: geomjax.shrinkwrap_points(p, jnp.asarray(TETRA), jnp.asarray(TETRA_FACES), implementation="jax"))
    reference = geomjax.shrinkwrap_points(jnp.asarray(POINTS), jnp.asarray(TETRA), jnp.asarray(TETRA_FACES), implementation="jax")
    np.testing.assert_array_equal(run(jnp.asarray(POINTS)), reference)
    loss = lambda p: jnp.sum(geomjax.shrinkwrap_points(p, jnp.asarray(TETRA), jnp.asarray(TETRA_FACES), implementation="jax") ** 2)
    np.testing.assert_allclose(jax.jit(jax.grad(loss))(jnp.asarray(POINTS)), jax.grad(loss)(jnp.asarray(POINTS)), rtol=0, atol=0)
    # The check fails the program when only the gradient is used, too.
    with pytest.raises((jax.errors.JaxRuntimeError, ValueError), match="^INVALID_ARGUMENT: shrinkwrap_points: points must be finite"):
        jax.block_until_ready(jax.jit(jax.grad(loss))(jnp.full((2, 3), jnp.inf)))


# ---------------------------------------------------------------------------------------------
# Mesh queries: index range and finite vertices -> ValueError


def test_signed_distance_field_indices(capfd):
    match = r"signed_distance_field: mesh_indices must lie in \[0, 4\)"
    _expect(capfd, ValueError, match, geomjax.signed_distance_field, jnp.asarray(TETRA), jnp.asarray(BAD_FACES),
            jnp.asarray(POINTS), implementation="jax")  # fmt: skip
    batched = jax.vmap(lambda f: geomjax.signed_distance_field(jnp.asarray(TETRA), f, jnp.asarray(POINTS), implementation="jax"))
    _expect(capfd, ValueError, match, batched, jnp.asarray(BAD_FACES)[None])
    _expect(capfd, ValueError, match, torch_bridge.signed_distance_field, _t(TETRA), _t(BAD_FACES), _t(POINTS), implementation="torch")
    _expect(capfd, ValueError, match, torch_bridge.signed_distance_field, _t(TETRA), _t(BAD_FACES), _t(POINTS),
            use_sign_winding_number=True, implementation="torch")  # fmt: skip


def test_ray_mesh_intersect_indices(capfd):
    match = r"ray_mesh_intersect: mesh_indices must lie in \[0, 4\)"
    directions = np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])
    _expect(capfd, ValueError, match, geomjax.ray_mesh_intersect, jnp.asarray(TETRA), jnp.asarray(BAD_FACES),
            jnp.asarray(POINTS), jnp.asarray(directions), implementation="jax")  # fmt: skip
    _expect(capfd, ValueError, match, torch_bridge.ray_mesh_intersect, _t(TETRA), _t(BAD_FACES), _t(POINTS), _t(directions),
            implementation="torch")  # fmt: skip


def test_mesh_to_voxel_fraction_indices_and_finite_vertices(capfd):
    options = {"origin": [-0.5, -0.5, -0.5], "voxel_size": 0.5, "grid_dims": (2, 2, 2), "n_samples": 8, "implementation": "jax"}
    torch_options = {**options, "implementation": "torch"}
    match = r"mesh_to_voxel_fraction: mesh_indices must lie in \[0, 4\)"
    _expect(capfd, ValueError, match, geomjax.mesh_to_voxel_fraction, jnp.asarray(TETRA), jnp.asarray(BAD_FACES), **options)
    _expect(capfd, ValueError, match, torch_bridge.mesh_to_voxel_fraction, _t(TETRA), _t(BAD_FACES), **torch_options)
    nan_vertices = TETRA.copy()
    nan_vertices[2, 1] = np.nan
    match = "mesh_to_voxel_fraction: mesh_vertices must be finite"
    _expect(capfd, ValueError, match, geomjax.mesh_to_voxel_fraction, jnp.asarray(nan_vertices), jnp.asarray(TETRA_FACES), **options)
    _expect(capfd, ValueError, match, torch_bridge.mesh_to_voxel_fraction, _t(nan_vertices), _t(TETRA_FACES), **torch_options)


def test_build_bvh_indices(capfd):
    pytest.importorskip("warp")
    _expect(capfd, ValueError, r"build_bvh: mesh_indices must lie in \[0, 4\)", geomjax.build_bvh, jnp.asarray(TETRA), jnp.asarray(BAD_FACES))


def test_mesh_free_form_deform_flat_box(capfd):
    flat = geomjax.polyline(5)  # all y = 0
    lattice = jnp.zeros((2, 2, 2), flat.points.dtype)
    _expect(capfd, ValueError, "finite and positive on every axis", flat.free_form_deform, lattice)
    # Under vmap the derived box is traced and the check runs eagerly at run time.
    batched = jax.vmap(lambda p: flat.with_points(p).free_form_deform(lattice, implementation="jax").points)
    _expect(capfd, ValueError, "finite and positive on every axis", batched, flat.points[None])
