"""A fast first-order backend whose every other transform is served by the JAX reference.

Warp kernels are wrapped with ``jax.custom_vjp``: fast values and a fast hand-written adjoint,
but no forward mode and no second derivatives. ``fast_with_reference(fast, reference, args)``
evaluates ``fast(*args)`` and differentiates it as follows:

- first-order reverse mode (``grad``, ``vjp``, ``jacrev``): the fast adjoint;
- forward mode (``jvp``, ``jacfwd``, ``linearize`` evaluated forward): the reference's JVP;
- derivatives of either (``hessian``, reverse over reverse, torch double backward): the
  reference's second derivatives.

How: the result is a ``jax.custom_jvp`` function whose tangent is one primitive,
``fast_path_tangent``, linear in the tangents. Its rule runs the fast forward pass once, under
``jax.vjp``, and passes the saved residuals to the primitive as operands. Evaluated forward the
primitive runs the reference's JVP. Transposed (reverse mode) it calls the adjoint function on
those residuals (so a gradient costs one fast forward pass and one fast backward pass), itself a
``custom_jvp`` whose value is the fast VJP and whose derivatives are the reference's. A primitive
is needed because JAX can only transpose primitives (a ``custom_vjp`` inside a tangent
computation has no transpose rule); its batching rule vmaps both functions, so ``grad`` of a
``vmap`` still uses the fast adjoint.

With ``explicit=True`` (the user named the fast backend) forward mode and higher order raise
``NotImplementedError`` naming the transform and the backend that can do it, instead of
silently switching.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir

from ._validate import as_jax_array

__all__ = ["fast_with_reference"]


def _differentiable(x) -> bool:
    return jnp.issubdtype(jnp.result_type(x), jnp.inexact)


def _filled(base, selected, values) -> list:
    """``base`` with its ``selected`` positions replaced, in order, by ``values``."""
    it = iter(values)
    return [next(it) if chosen else b for b, chosen in zip(base, selected)]


def _unsupported(op_name: str, backend: str, transform: str) -> NotImplementedError:
    return NotImplementedError(
        f"{op_name}: implementation={backend!r} supports values and first-order reverse mode only; "
        f"{transform} needs implementation='jax' (or implementation=None, which uses the JAX path "
        "for the transforms the fast backend lacks)"
    )


def fast_with_reference(
    fast: Callable[..., Any], reference: Callable[..., Any], args: Sequence[Any], *, op_name: str, backend: str = "warp", explicit: bool = False
):
    """``fast(*args)``, differentiated by ``fast``'s VJP at first order and by ``reference`` otherwise.

    Args:
        fast: a JAX function of arrays with a reverse-mode rule (typically a Warp ``custom_vjp``).
        reference: the same mathematical function in plain JAX, differentiable to any order.
        args: the arrays (``None`` for an absent optional one); integer and bool arrays are not
            differentiated.
        op_name: named in error messages.
        backend: the fast backend's name, for error messages.
        explicit: the user asked for ``backend`` by name: forward mode and higher order raise
            ``NotImplementedError`` rather than running ``reference``.

    Returns:
        ``fast(*args)``, with the output structure of ``fast``.
    """
    if any(a is None for a in args):
        # Absent optional arrays are not operands: bind them into both functions.
        present = tuple(a is not None for a in args)
        absent = [None] * len(args)

        def with_absent(fn):
            return lambda *arrays: fn(*_filled(absent, present, arrays))

        fast, reference, args = with_absent(fast), with_absent(reference), [a for a in args if a is not None]
    args = tuple(as_jax_array(a) for a in args)
    mask = tuple(_differentiable(a) for a in args)

    def reference_diff(primals, *diff_args):
        """``reference`` as a function of the differentiable arguments, returning its float
        outputs (``fast`` and ``reference`` return the same dtypes, so both keep the same outputs)."""
        leaves = jax.tree.leaves(reference(*_filled(primals, mask, diff_args)))
        return tuple(leaf for leaf in leaves if _differentiable(leaf))

    def diff_part(primals):
        return tuple(p for p, m in zip(primals, mask) if m)

    def tangent_fn(primals, tangents):
        if explicit:
            raise _unsupported(op_name, backend, "forward-mode differentiation (jax.jvp, jax.jacfwd, jax.hessian)")
        return jax.jvp(lambda *d: reference_diff(primals, *d), diff_part(primals), tuple(tangents))[1]

    def adjoint_from(pullback_tree):
        """The fast VJP from the residuals the forward pass saved, differentiated by the reference."""

        @jax.custom_jvp
        def adjoint(primals, residuals, cotangents):
            return jax.tree.unflatten(pullback_tree, residuals)(tuple(cotangents))

        @adjoint.defjvp
        def _adjoint_jvp(primal_pair, tangent_pair):
            if explicit:
                raise _unsupported(op_name, backend, "differentiating its gradient (second-order derivatives, double backward)")
            # The residuals are functions of the primals, so the reference's derivative in the
            # primals and cotangents is the whole derivative; their own tangents are ignored.
            primals, _, cotangents = primal_pair
            primal_dots, _, cotangent_dots = tangent_pair

            def reference_adjoint(diff_primals, cts):
                _, pullback = jax.vjp(lambda *d: reference_diff(primals, *d), *diff_primals)
                return pullback(cts)

            return jax.jvp(reference_adjoint, (diff_part(primals), tuple(cotangents)), (diff_part(primal_dots), tuple(cotangent_dots)))

        return adjoint

    @jax.custom_jvp
    def function(*primals):
        return fast(*primals)

    @jax.custom_jvp
    def replay(primals, value):
        """``value`` (computed as ``function(*primals)``), differentiated as ``function``."""
        return value

    @replay.defjvp
    def _replay_jvp(primal_pair, tangent_pair):
        return _function_jvp(primal_pair[0], tangent_pair[0])

    @function.defjvp
    def _function_jvp(primals, tangents):
        # One fast forward pass gives the value and the residuals of its VJP; the adjoint reuses
        # them instead of running the forward pass again. The primals are frozen so that an
        # enclosing differentiation never traces into the fast pass (it has no forward mode);
        # ``replay`` hands such a differentiation the value with ``function``'s rule instead.
        frozen = tuple(jax.lax.stop_gradient(p) for p in primals)

        def split_outputs(*diff_args):
            out = fast(*_filled(frozen, mask, diff_args))
            return tuple(leaf for leaf in jax.tree.leaves(out) if _differentiable(leaf)), out

        _, pullback, out = jax.vjp(split_outputs, *diff_part(frozen), has_aux=True)
        residuals, pullback_tree = jax.tree.flatten(pullback)
        out = replay(primals, out)
        out_leaves, out_tree = jax.tree.flatten(out)
        out_mask = tuple(_differentiable(o) for o in out_leaves)
        # Tangent types from the traced outputs themselves: under shard_map they carry the
        # varying manual axes, which an abstract evaluation of ``fast`` would not know.
        out_avals = tuple(jax.typeof(o).to_tangent_aval() for o, m in zip(out_leaves, out_mask) if m)
        tangent_leaves = iter(
            _tangent_p.bind(
                *primals, *residuals, *diff_part(tangents),
                tangent_fn=tangent_fn, adjoint_fn=adjoint_from(pullback_tree), out_avals=out_avals, num_primals=len(primals), num_residuals=len(residuals),
            )
        )  # fmt: skip
        tangent_out = [next(tangent_leaves) if m else np.zeros(o.shape, jax.dtypes.float0) for o, m in zip(out_leaves, out_mask)]
        return out, jax.tree.unflatten(out_tree, tangent_out)

    return function(*args)


# ---------------------------------------------------------------------------------------------
# The tangent primitive: operands are the primals (all of them), the residuals of the fast VJP,
# then the tangents of the differentiable primals; it is linear in the tangents.

_tangent_p = Primitive("fast_path_tangent")
_tangent_p.multiple_results = True


def _split(operands, num_primals, num_residuals):
    return operands[:num_primals], operands[num_primals : num_primals + num_residuals], operands[num_primals + num_residuals :]


def _tangent_impl(*operands, tangent_fn, adjoint_fn, out_avals, num_primals, num_residuals):
    del adjoint_fn, out_avals
    primals, _, tangents = _split(operands, num_primals, num_residuals)
    return list(tangent_fn(primals, tangents))


def _tangent_abstract_eval(*operands, tangent_fn, adjoint_fn, out_avals, num_primals, num_residuals):
    del operands, tangent_fn, adjoint_fn, num_primals, num_residuals
    return list(out_avals)


def _tangent_transpose(cotangents, *operands, tangent_fn, adjoint_fn, out_avals, num_primals, num_residuals):
    del tangent_fn
    primals, residuals, tangents = _split(operands, num_primals, num_residuals)
    if any(ad.is_undefined_primal(p) for p in (*primals, *residuals)):
        raise NotImplementedError("fast_path_tangent is linear in its tangents only")
    cotangents = tuple(ad.zeros_like_aval(a) if type(ct) is ad.Zero else ct for ct, a in zip(cotangents, out_avals))
    tangent_cts = adjoint_fn(tuple(primals), tuple(residuals), cotangents)
    return [None] * (num_primals + num_residuals) + [ct if ad.is_undefined_primal(t) else None for ct, t in zip(tangent_cts, tangents)]


def _tangent_jvp(primals_in, tangents_in, *, tangent_fn, adjoint_fn, out_avals, num_primals, num_residuals):
    # Differentiating the tangent map itself (jacrev of jacfwd, jacfwd of jacfwd): plain JAX
    # derivatives of tangent_fn, which is the reference's JVP (the residuals play no part).
    del adjoint_fn, out_avals
    primals, _, tangents = _split(primals_in, num_primals, num_residuals)
    primal_dots, _, tangent_dots = _split(tangents_in, num_primals, num_residuals)
    mask = tuple(_differentiable(p) for p in primals)

    def tangent_of(diff_primals, tangents):
        return tuple(tangent_fn(tuple(_filled(primals, mask, diff_primals)), tangents))

    primal_dots = tuple(ad.instantiate_zeros(t) for t, m in zip(primal_dots, mask) if m)
    tangent_dots = tuple(ad.instantiate_zeros(t) for t in tangent_dots)
    diff_primals = tuple(p for p, m in zip(primals, mask) if m)
    out, out_dot = jax.jvp(tangent_of, (diff_primals, tuple(tangents)), (primal_dots, tangent_dots))
    return list(out), list(out_dot)


def _tangent_batch(operands, dims, *, tangent_fn, adjoint_fn, out_avals, num_primals, num_residuals):
    size = next(x.shape[d] for x, d in zip(operands, dims) if d is not None)
    primal_dims, residual_dims, tangent_dims = (tuple(d) for d in _split(dims, num_primals, num_residuals))

    def batched_tangent_fn(primals, tangents):
        return jax.vmap(tangent_fn, in_axes=(primal_dims, tangent_dims))(tuple(primals), tuple(tangents))

    def batched_adjoint_fn(primals, residuals, cotangents):
        # The cotangent of an unbatched tangent operand sums over the batch.
        cts = jax.vmap(adjoint_fn, in_axes=(primal_dims, residual_dims, 0))(tuple(primals), tuple(residuals), tuple(cotangents))
        return tuple(jnp.sum(ct, axis=0) if d is None else jnp.moveaxis(ct, 0, d) for ct, d in zip(cts, tangent_dims))

    batched_avals = tuple(a.update(shape=(size, *a.shape)) for a in out_avals)
    out = _tangent_p.bind(
        *operands, tangent_fn=batched_tangent_fn, adjoint_fn=batched_adjoint_fn, out_avals=batched_avals, num_primals=num_primals, num_residuals=num_residuals
    )
    return out, [0] * len(out)


_tangent_p.def_impl(_tangent_impl)
_tangent_p.def_abstract_eval(_tangent_abstract_eval)
ad.primitive_jvps[_tangent_p] = _tangent_jvp
ad.primitive_transposes[_tangent_p] = _tangent_transpose
batching.primitive_batchers[_tangent_p] = _tangent_batch
mlir.register_lowering(_tangent_p, mlir.lower_fun(_tangent_impl, multiple_results=True))
