"""The multilevel preconditioner (``geomjax.linalg._multilevel``): Galerkin coarse operators, a
symmetric positive definite V-cycle that beats Jacobi, and Sobolev solves on a real scanned mesh
that Jacobi-PCG could not finish within the default budget."""

import functools
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from geomjax import sobolev_deform_points
from geomjax.linalg import MultilevelPreconditioner, RowStiffness, aggregation_hierarchy, row_pattern, simplex_stiffness, uniform_lumped_mass
from geomjax.linalg._multilevel import jacobi_iteration_bound

from .meshes import MESHES, dense_sobolev, dense_stiffness

LENGTH = 0.3


@functools.cache
def _problem():
    """The Sobolev system of a jittered grid with obtuse cells and three fixed rows: the dense
    matrix (independent assembly), the preconditioner, the hierarchy and the uniform mass m̄.
    Built once per module, in one compiled program."""
    points, cells = MESHES["triangles-fine"]()
    free = np.ones(points.shape[0], bool)
    free[[0, 17, 100]] = False
    pattern = row_pattern(cells, points.shape[0])
    hierarchy = aggregation_hierarchy(pattern)

    @jax.jit
    def build(points, cells, free):
        local, measures, _ = simplex_stiffness(points, cells)
        mass = uniform_lumped_mass(measures, jnp.sum(pattern.referenced, dtype=jnp.int32))
        rows = RowStiffness.assemble(local, pattern)
        return MultilevelPreconditioner.for_helmholtz(rows, mass, jnp.asarray(LENGTH**2), free, hierarchy), mass

    preconditioner, mass = build(points, cells, free)
    stiffness, _ = dense_stiffness(points, cells)
    matrix = float(mass) * np.eye(points.shape[0]) + LENGTH**2 * np.asarray(stiffness)
    # Fixed rows are identity rows, their columns removed.
    matrix[~free, :] = 0
    matrix[:, ~free] = 0
    matrix[~free, ~free] = 1
    return matrix, preconditioner, hierarchy, float(mass)


def _dense(mass, couplings, neighbours):
    """The matrix of ``(A x)_i = mass_i x_i + sum_k c_ik (x[n_ik] - x_i)``, entry by entry."""
    mass, couplings, neighbours = (np.asarray(a) for a in (mass, couplings, neighbours))
    matrix = np.diag(mass)
    for i, row in enumerate(neighbours):
        for k, j in enumerate(row):
            matrix[i, j] += couplings[i, k]
            matrix[i, i] -= couplings[i, k]
    return matrix


def test_the_fixture_coarsens_twice():
    _, preconditioner, hierarchy, _ = _problem()
    sizes = [level.mass.shape[0] for level in preconditioner.levels]
    assert len(hierarchy) >= 1 and sizes[0] == 224 and sizes[-1] <= 150, sizes
    assert aggregation_hierarchy(row_pattern(MESHES["triangles-fine"]()[1], 224)) is hierarchy  # cached per topology


def test_every_level_is_the_galerkin_product_of_the_one_above():
    matrix, preconditioner, hierarchy, _ = _problem()
    finest = preconditioner.levels[0]
    np.testing.assert_allclose(_dense(finest.mass, finest.couplings, finest.neighbours), matrix, rtol=1e-12, atol=1e-15)
    for step, coarse in zip(hierarchy, preconditioner.levels[1:]):
        prolongation = np.zeros((matrix.shape[0], coarse.mass.shape[0]))
        prolongation[np.arange(matrix.shape[0]), np.asarray(step.aggregate)] = 1
        matrix = prolongation.T @ matrix @ prolongation
        np.testing.assert_allclose(_dense(coarse.mass, coarse.couplings, coarse.neighbours), matrix, rtol=1e-12, atol=1e-15)


def test_the_v_cycle_is_symmetric_positive_definite_and_beats_jacobi():
    matrix, preconditioner, _, _ = _problem()
    # M^-1 column by column: the cycle acts on (N, D) blocks, here D = N.
    inverse = np.asarray(jax.jit(lambda p, r: p(r))(preconditioner, jnp.eye(matrix.shape[0])))
    np.testing.assert_allclose(inverse, inverse.T, rtol=0, atol=1e-12 * np.abs(inverse).max())
    assert np.linalg.eigvalsh((inverse + inverse.T) / 2).min() > 0

    def condition(preconditioned):
        values = np.linalg.eigvals(preconditioned).real  # similar to a symmetric matrix: real
        return values.max() / values.min()

    jacobi = condition(matrix / np.diag(matrix)[:, None])
    multilevel = condition(inverse @ matrix)
    assert multilevel < jacobi / 4, (multilevel, jacobi)


def test_the_jacobi_iteration_bound_bounds_the_condition_number():
    matrix, preconditioner, _, mass = _problem()
    finest = preconditioner.levels[0]
    tolerance = 1e-10
    smallest = min(mass, 1.0)  # A >= m̄ I on the free rows (m̄ I + a block of K); fixed rows are identity rows
    bound = float(jax.jit(jacobi_iteration_bound)(finest.mass, finest.couplings, smallest, tolerance))
    values = np.linalg.eigvals(matrix / np.diag(matrix)[:, None]).real
    exact = 0.5 * np.sqrt(values.max() / values.min()) * np.log(2 / tolerance)
    assert exact <= bound < 10 * exact, (exact, bound)


@pytest.mark.parametrize("implementation", ["jax", "warp"])
def test_torch_bridge_calls_get_the_v_cycle_that_concrete_cells_get(implementation):
    # torch_bridge's programs take cells traced, where geomjax alone could only use Jacobi; the
    # bridge builds the topology from the cells tensor and passes it in, eager and compiled.
    torch = pytest.importorskip("torch")
    import torch_bridge

    points, cells = MESHES["triangles-fine"]()
    displacement = 0.1 * np.sin(3 * np.asarray(points)[:, ::-1])
    options = dict(length_scale=LENGTH, max_iterations=30, implementation=implementation)
    if implementation == "jax":  # Jacobi-PCG needs more than 60 iterations here, the V-cycle fewer than 30
        with pytest.raises(RuntimeError, match="did not converge within 30 iterations"):
            jax.block_until_ready(jax.jit(lambda c: sobolev_deform_points(points, c, displacement, **options))(cells))
    expected = np.asarray(dense_sobolev(points, cells, displacement, LENGTH))

    tracked = torch.tensor(np.asarray(points)).requires_grad_()
    torch_cells, torch_displacement = torch.tensor(np.asarray(cells)), torch.tensor(displacement)
    moved = torch_bridge.sobolev_deform_points(tracked, torch_cells, torch_displacement, **options)
    # The solver's tolerance (1e-10 of the residual) times the system's conditioning (below 1e3).
    np.testing.assert_allclose(moved.detach().numpy(), expected, rtol=0, atol=1e-7 * np.abs(expected - np.asarray(points)).max())
    if implementation == "warp":
        return  # the Warp adjoint reuses the forward's preconditioner (tests/deform/test_sobolev_warp.py)
    (gradient,) = torch.autograd.grad(moved.square().sum(), tracked)
    expected_gradient = jax.grad(lambda p: jnp.sum(sobolev_deform_points(p, cells, displacement, **options) ** 2))(points)
    np.testing.assert_allclose(gradient.numpy(), expected_gradient, rtol=1e-8, atol=1e-12)
    # Compiled: the custom op's kernel prepares the topology as the eager call does.
    compiled = torch.compile(lambda p: torch_bridge.sobolev_deform_points(p, torch_cells, torch_displacement, **options), fullgraph=True)
    torch.testing.assert_close(compiled(tracked.detach()), moved.detach(), rtol=0, atol=0)


# ---------------------------------------------------------------------------------------------
# A real scanned mesh (the shared libigl meshes, when present next to the checkout).

MESH = Path(__file__).resolve().parents[3] / "shared" / "meshes" / "camelhead.off"


@pytest.mark.skipif(not MESH.is_file(), reason="the shared meshes are not next to the checkout")
@pytest.mark.parametrize(("dtype", "implementation"), [("float64", "jax"), ("float64", "warp"), ("float32", "jax")])
def test_sobolev_converges_on_a_scanned_open_mesh_within_the_default_budget(dtype, implementation):
    # Jacobi-PCG needs 309 iterations here in float64 (184 in float32), over the default 128.
    meshio = pytest.importorskip("meshio")
    sp = pytest.importorskip("scipy.sparse")
    pytest.importorskip("scipy.sparse.linalg")
    mesh = meshio.read(MESH)
    cells = np.concatenate([block.data for block in mesh.cells if block.type == "triangle"]).astype(np.int32)
    points = mesh.points - mesh.points.min(axis=0)
    points = points / points.max()
    displacement = 0.01 * np.sin(3 * points[:, [1, 2, 0]])
    moved = sobolev_deform_points(
        jnp.asarray(points, dtype), jnp.asarray(cells), jnp.asarray(displacement, dtype), length_scale=0.05, implementation=implementation
    )
    # The system assembled independently in SciPy (cotangent-form P1 stiffness), in float64 from
    # the points as the solver saw them.
    points = np.asarray(jnp.asarray(points, dtype), np.float64)
    corners = points[cells]
    edges = [corners[:, (k + 2) % 3] - corners[:, (k + 1) % 3] for k in range(3)]  # opposite vertex k
    area = 0.5 * np.linalg.norm(np.cross(edges[0], edges[1]), axis=1)
    rows, columns, values = [], [], []
    for k in range(3):
        i, j = (k + 1) % 3, (k + 2) % 3
        # Edges i and j meet at vertex k, as -u and v (u, v from k): their product is -cot(k) 2|c|.
        weight = np.einsum("cd,cd->c", edges[i], edges[j]) / (4 * area)  # K_ij = -cot(angle at k) / 2
        for a, b in ((i, j), (j, i)):
            rows += [cells[:, a], cells[:, a]]
            columns += [cells[:, b], cells[:, a]]
            values += [weight, -weight]
    stiffness = sp.csr_matrix((np.concatenate(values), (np.concatenate(rows), np.concatenate(columns))), shape=(len(points),) * 2)
    referenced = np.bincount(cells.ravel(), minlength=len(points)) > 0
    mass = area.sum() / referenced.sum()
    system = mass * sp.identity(len(points)) + 0.05**2 * stiffness
    rhs = mass * np.asarray(jnp.asarray(displacement, dtype), np.float64)
    if dtype == "float64":
        # The solver's contract: relative residual 1e-10 (plus the two assemblies' rounding).
        field = np.asarray(moved) - points
        residual = np.linalg.norm(rhs - system @ field) / np.linalg.norm(rhs)
        assert residual < 2e-10, residual
    else:
        # float32 returns x + u, rounded to eps |x| (1e-5 of |u| here), so u cannot be recovered
        # to the residual tolerance: compare with SciPy's direct solve instead, to the float32
        # tolerance 1e-6 times the system's conditioning (below 1e3 of max |u|).
        exact = points + sp.linalg.spsolve(system.tocsc(), rhs)
        error = np.abs(np.asarray(moved, np.float64) - exact).max() / np.abs(exact - points).max()
        assert error < 1e-3, error
