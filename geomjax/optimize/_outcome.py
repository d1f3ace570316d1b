"""How the fits report an optimistix solve that did not succeed: one rule for all of them.

``optimistix``'s own ``throw=True`` raises ``EquinoxRuntimeError`` from a host callback, its
message after a stack dump. The fits instead always solve with ``throw=False`` and check the
solution's ``result`` themselves: a ``RuntimeError`` whose first line is the fit's message (at
once when called eagerly, at run time under ``jit`` through :func:`geomjax._errors.runtime_check`),
or, on request, the whole ``optimistix.Solution`` so the caller reads ``result`` itself.
"""

from __future__ import annotations

import jax.numpy as jnp
import optimistix as optx

from .._errors import runtime_check


def fitted(solution: optx.Solution, *, op_name: str, max_steps: int, throw: bool, return_solution: bool):
    """``solution.value`` (``solution`` itself with ``return_solution``), checked with ``throw``."""
    if return_solution:
        return solution
    if not throw:
        return solution.value
    # optimistix can stop "successfully" on non-finite residuals (NaN never exceeds a tolerance).
    failed = (solution.result != optx.RESULTS.successful) | ~jnp.all(jnp.isfinite(solution.value))
    message = (
        f"{op_name}: the least-squares solve did not succeed within max_steps={max_steps} (not converged, or a "
        "non-finite residual). Raise max_steps, add regularization, or pass return_solution=True to read "
        "optimistix's result"
    )
    return runtime_check(solution.value, failed, message, RuntimeError)
