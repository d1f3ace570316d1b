"""Matrix-free linear algebra for implicit geometry filters (used by ``sobolev_deform_points``).

* :func:`simplex_stiffness`: local P1 stiffness matrices, measures and Gram determinants.
* :class:`RowStiffness` / :class:`CellStiffness`: matrix-free stiffness products (padded rows from
  a host-side :func:`row_pattern`, or per-cell scatters for traced topology).
* :class:`HelmholtzOperator`: ``m̄ I + l^2 K`` with Dirichlet rows, as a lineax operator.
* :func:`jacobi_pcg` / :class:`JacobiPCG`: block PCG (Jacobi unless a preconditioner is given) with a
  2-norm stopping rule on the true residual, as a function and as a ``lineax`` solver (implicit
  differentiation, ``jvp``, ``vmap``).
* :func:`aggregation_hierarchy` / :class:`MultilevelPreconditioner`: an aggregation V-cycle for
  the Helmholtz systems, its coarsening built once per topology on the host.
"""

from ._helmholtz import HelmholtzOperator as HelmholtzOperator
from ._helmholtz import uniform_lumped_mass as uniform_lumped_mass
from ._multilevel import MultilevelPreconditioner as MultilevelPreconditioner
from ._multilevel import aggregation_hierarchy as aggregation_hierarchy
from ._pcg import JacobiPCG as JacobiPCG
from ._pcg import PCGResult as PCGResult
from ._pcg import jacobi_pcg as jacobi_pcg
from ._pcg import solution_or_error as solution_or_error
from ._stiffness import CellStiffness as CellStiffness
from ._stiffness import RowPattern as RowPattern
from ._stiffness import RowStiffness as RowStiffness
from ._stiffness import off_diagonal_entries as off_diagonal_entries
from ._stiffness import off_diagonal_pairs as off_diagonal_pairs
from ._stiffness import referenced_vertices as referenced_vertices
from ._stiffness import row_pattern as row_pattern
from ._stiffness import simplex_stiffness as simplex_stiffness
