"""The screened-Poisson (Helmholtz) operator ``m̄ I + l^2 K`` with zero-Dirichlet rows."""

from __future__ import annotations

from typing import Protocol

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int

__all__ = ["HelmholtzOperator", "uniform_lumped_mass"]


def uniform_lumped_mass(measures: Float[Array, " C"], num_referenced: Int[Array, ""]) -> Float[Array, ""]:
    """Mean lumped P1 vertex mass over the vertices with positive mass (1 when there are none).

    The lumped masses (``|c| / V`` from every cell to each of its vertices) sum to ``sum |c|``,
    so for nondegenerate cells the mean over the referenced vertices is ``sum |c| / count``.
    Differentiable in ``measures``.
    """
    one = jnp.ones((), measures.dtype)
    count = num_referenced.astype(measures.dtype)
    return jnp.where(num_referenced > 0, jnp.sum(measures) / jnp.maximum(count, one), one)


class StiffnessOperator(Protocol):
    """What :class:`HelmholtzOperator` needs of ``K``: the product on ``(N, D)`` blocks and the diagonal."""

    def __call__(self, x: Float[Array, "N D"]) -> Float[Array, "N D"]: ...

    def diagonal(self) -> Float[Array, " N"]: ...


class HelmholtzOperator(eqx.Module):
    """``A x = m̄ x + l^2 K x`` on free rows, ``A x = x`` on fixed rows, fixed columns removed.

    Symmetric positive definite whenever ``m̄ > 0`` and ``K`` is a stiffness matrix (positive
    semidefinite), because the Dirichlet rows and columns decouple. Acts on ``(N, D)`` blocks
    column by column, as :func:`~geomjax.linalg.jacobi_pcg` requires.

    Attributes:
        stiffness: ``x -> K x`` on ``(N, D)`` blocks, with a ``diagonal()`` method (e.g.
            :class:`~geomjax.linalg.RowStiffness`, :class:`~geomjax.linalg.CellStiffness`).
        mass: the uniform mass ``m̄`` (a scalar).
        length_scale_squared: ``l^2`` (a scalar).
        free: ``(N,)`` bool, false at Dirichlet (fixed) rows; ``None`` when no row is fixed.
    """

    stiffness: StiffnessOperator
    mass: Float[Array, ""]
    length_scale_squared: Float[Array, ""]
    free: Bool[Array, " N"] | None

    def mv(self, x: Float[Array, "N D"]) -> Float[Array, "N D"]:
        if self.free is None:
            return self.mass * x + self.length_scale_squared * self.stiffness(x)
        free = self.free[:, None]
        smoothed = self.mass * x + self.length_scale_squared * self.stiffness(jnp.where(free, x, 0))
        return jnp.where(free, smoothed, x)

    def inverse_diagonal(self) -> Float[Array, " N"]:
        """``1 / diag(A)``, clamped to stay finite (the Jacobi preconditioner)."""
        diagonal = self.mass + self.length_scale_squared * self.stiffness.diagonal()
        if self.free is not None:
            diagonal = jnp.where(self.free, diagonal, 1)
        return 1 / jnp.maximum(diagonal, jnp.finfo(diagonal.dtype).tiny)

    def as_linear_operator(self, structure: jax.ShapeDtypeStruct) -> lx.FunctionLinearOperator:
        """The operator for ``lineax.linear_solve``, tagged symmetric positive semidefinite.

        ``self.mv`` is a bound method of this module, a pytree of its arrays already, so lineax
        need not closure-convert it; its conversion would also compare every vector's type with
        ``structure``'s, which fails inside ``shard_map`` (the solve's own output, fed back in its
        derivative, is typed without the per-shard mesh).
        """
        return lx.FunctionLinearOperator(self.mv, structure, tags=(lx.symmetric_tag, lx.positive_semidefinite_tag), closure_convert=False)
