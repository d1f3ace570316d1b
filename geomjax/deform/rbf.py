"""Thin-plate-spline radial-basis deformation, with a reusable fit.

The displacement field is ``u(x) = sum_j phi(|x - c_j|) w_j + a_0 + A x`` with the thin-plate
kernel ``phi(r) = r^2 log r`` (``phi(0) = 0``), fitted from the augmented interpolation system
``[[K + lambda I, P], [P^T, 0]] [W; a] = [Delta; 0]`` (Bookstein 1989).

Two things go beyond the reference API:

* :class:`ThinPlateSplineFit` holds the fitted coefficients, so one fit is evaluated on many query
  sets; :func:`radial_basis_function_deform_points` is ``fit`` followed by one evaluation.
* The fit centres and scales the control coordinates internally. With the affine tail this gives
  exactly the same function as the unscaled fit (derivation in :meth:`ThinPlateSplineFit.fit`), so
  the conditioning no longer depends on the user's units.
"""

from __future__ import annotations

import decimal
import functools
import struct

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from .._blocking import map_query_blocks, query_block_size
from .._dispatch import Implementation, platform_of, select_implementation
from .._errors import raises_documented_errors, runtime_check
from .._points import add_batch_axis, apply_point_weights, remove_batch_axis
from .._sharding import map_local_shards
from .._validate import check_bool, check_choice, check_companion, check_coordinates, check_point_weights, check_real_scalar, check_same_shape

__all__ = ["ThinPlateSplineFit", "radial_basis_function_deform_points"]

_NAME = "radial_basis_function_deform_points"
KERNELS = ("thin_plate_spline",)
# Pairwise temporaries per query block (bytes per live N_block x C array). Small blocks stay in
# cache on CPU (measured fastest around 2-8 MiB); GPUs want large launches.
_BLOCK_BYTES = {"cpu": 4 * 2**20}
_DEFAULT_BLOCK_BYTES = 64 * 2**20
# A pivot below this many ulps of the largest one marks the fit system as singular. Exactly
# singular layouts leave pivots of about one ulp (or zero); well-posed layouts of 1,000 random
# controls keep ratios above 1e-5, and even a 1e-6-thin slab stays near 1e-9 in float64.
_PIVOT_ULPS = 16.0


@raises_documented_errors
def radial_basis_function_deform_points(
    points: Float[Array, "*batch num_points num_dims"],
    control_points: Float[Array, "*batch num_controls num_dims"],
    control_displacements: Float[Array, "*batch num_controls num_dims"],
    *,
    kernel: str = "thin_plate_spline",
    polynomial: bool = True,
    smoothing: float = 0.0,
    point_weights: Bool[Array, "*batch num_points"] | Float[Array, "*batch num_points"] | None = None,
    implementation: str | None = None,
) -> Float[Array, "*batch num_points num_dims"]:
    r"""Deform points with a global thin-plate-spline RBF field fitted to control displacements.

    ``u(x) = sum_j phi(|x - c_j|) w_j + a_0 + A x`` with ``phi(r) = r^2 log r`` (natural log, the same
    kernel in every dimension). The coefficients solve the dense augmented system
    ``[[K + smoothing I, P], [P^T, 0]] [W; a] = [Delta; 0]`` with ``K_ij = phi(|c_i - c_j|)`` and
    ``P = [1, c]``; all ``D`` displacement components are one multi-right-hand-side solve. With
    ``smoothing=0`` the field interpolates the control displacements; affine displacement fields
    are reproduced exactly. Returns ``x + w * u(x)``.

    This is :meth:`ThinPlateSplineFit.fit` followed by one evaluation; build the fit yourself to
    evaluate it on several query sets.

    Args:
        points: ``(N, D)`` or aligned batched ``(B, N, D)``, float32 or float64, any ``D >= 1``.
        control_points: ``(C, D)`` / ``(B, C, D)`` control locations, same dtype, same batching.
        control_displacements: exactly the shape and dtype of ``control_points`` (displacements,
            not destinations).
        kernel: ``"thin_plate_spline"`` (the only kernel; other names raise ``ValueError``).
        polynomial: include the affine tail and its side conditions ``P^T W = 0`` (needs at least
            ``D + 1`` controls). ``False`` solves ``(K + smoothing I) W = Delta`` alone. A real
            ``bool`` (``1`` is a ``TypeError``).
        smoothing: finite real ``>= 0`` added to the diagonal of ``K``; ``0`` interpolates.
        point_weights: optional ``(N,)`` / ``(B, N)`` bool mask or float multipliers of the field
            (float weights must match the points dtype; signed and amplifying values are used as
            given).
        implementation: field-evaluation backend: ``"jax"`` (also ``"torch"``), ``"warp"`` or
            ``None``. The fit is always the JAX solve. ``None`` picks ``"jax"`` on CPU (where the Warp
            evaluator's kernels run on one thread; ``benchmarks/bench_rbf.py``) and ``"warp"`` on GPU
            when Warp is installed (the reference's rule, not yet measured on a GPU), otherwise ``"jax"``.

    Returns:
        Deformed points with the shape and dtype of ``points``. Zero controls give the identity.

    Raises:
        TypeError: non-float arrays, mixed dtypes, integer weights, non-bool ``polynomial``,
            non-real ``smoothing``.
        ValueError: bad shapes or batching, unknown ``kernel``, negative or non-finite
            ``smoothing``, ``polynomial=True`` with ``0 < C < D + 1``.
        KeyError: unknown ``implementation``.
        ImportError: ``implementation="warp"`` without warp-lang.
        RuntimeError: the fit system is singular (duplicate controls, controls that do not
            affinely span ``R^D``, a single control without tail and smoothing). Raised eagerly
            and under ``jax.jit`` (through ``equinox.error_if``); a singular layout never returns
            a field.

    Differentiability: ``points``, ``control_points``, ``control_displacements`` and float
    ``point_weights``, through the solve, with the transforms of the README's "Backends and
    transforms" (the Warp field has hand-written adjoint kernels; the fit is always JAX).

    Sharding: see the README's "Sharding"; designs are fitted and evaluated shard by shard; a
    query split alone repeats the small fit on every device.

    Example:
        >>> import jax.numpy as jnp
        >>> import numpy as np
        >>> from geomjax import radial_basis_function_deform_points
        >>> points = jnp.array([[0.25, 0.25], [0.75, 0.25], [0.75, 0.75], [0.25, 0.75]])
        >>> controls = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
        >>> control_displacements = jnp.array([[0.0, 0.0], [0.0, 0.0], [0.15, 0.25], [0.0, 0.0]])
        >>> moved = radial_basis_function_deform_points(points, controls, control_displacements)
        >>> print(np.round(np.asarray(moved - points), 4) + 0.0)
        [[0.0124 0.0207]
         [0.0251 0.0418]
         [0.0874 0.1457]
         [0.0251 0.0418]]
    """
    points, batched = check_coordinates("points", points)
    control_points = check_companion("points", points, "control_points", control_points)
    control_displacements = check_same_shape("control_points", control_points, "control_displacements", control_displacements)
    point_weights = check_point_weights(point_weights, points)
    backend = select_implementation(_NAME, implementation, platform=platform_of(points))
    fit = ThinPlateSplineFit.fit(control_points, control_displacements, kernel=kernel, polynomial=polynomial, smoothing=smoothing)
    return fit._deformed(points, point_weights, backend)


class ThinPlateSplineFit(eqx.Module):
    """A fitted thin-plate-spline displacement field, reusable across query sets.

    Build it with :meth:`fit`, then call it on points (``fit(points)`` returns deformed points;
    :meth:`displacement` returns the field itself). It is an ``equinox.Module``: pass it through
    ``jax.jit``, ``jax.vmap`` (a batch of fits) and ``jax.grad`` like any pytree; gradients of a
    loss on the evaluated points reach the control points and displacements through the solve.

    The coefficients live in normalised coordinates ``x_hat = (x - centre) / scale`` (the controls
    too, as ``normalised_controls``): ``weights`` are the radial coefficients, ``constant`` and
    ``linear`` the affine part ``u = constant + x_hat @ linear``. ``centre`` and ``scale`` are
    constants for autodiff (the field does not depend on them; see :meth:`fit`). Leaves carry a
    leading batch axis when the fit was made from ``(B, C, D)`` controls (``batched=True``).

    Example:
        >>> import jax
        >>> import jax.numpy as jnp
        >>> import numpy as np
        >>> from geomjax import ThinPlateSplineFit
        >>> controls = jnp.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.5, 0.5]])
        >>> shift = jnp.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.1]])
        >>> fit = ThinPlateSplineFit.fit(controls, shift)
        >>> print(np.round(np.asarray(fit.displacement(controls)), 6)[:, 1] + 0.0)
        [0.  0.  0.  0.  0.1]
        >>> moved = jax.jit(lambda f, x: f(x))(fit, jnp.array([[0.5, 0.25]]))
        >>> print(np.round(np.asarray(moved), 4) + 0.0)
        [[0.5    0.3256]]
    """

    centre: Float[Array, "*batch num_dims"]
    scale: Float[Array, "*batch"]
    normalised_controls: Float[Array, "*batch num_controls num_dims"]
    weights: Float[Array, "*batch num_controls num_dims"]
    constant: Float[Array, "*batch num_dims"]
    linear: Float[Array, "*batch num_dims num_dims"]
    polynomial: bool = eqx.field(static=True)
    batched: bool = eqx.field(static=True)

    @classmethod
    @raises_documented_errors
    def fit(
        cls,
        control_points: Float[Array, "*batch num_controls num_dims"],
        control_displacements: Float[Array, "*batch num_controls num_dims"],
        *,
        kernel: str = "thin_plate_spline",
        polynomial: bool = True,
        smoothing: float = 0.0,
    ) -> ThinPlateSplineFit:
        r"""Fit the thin-plate spline to control displacements (one dense solve per batch item).

        Args:
            control_points: ``(C, D)`` or ``(B, C, D)``, float32 or float64.
            control_displacements: exactly the shape and dtype of ``control_points``.
            kernel, polynomial, smoothing: as in :func:`radial_basis_function_deform_points`.

        Returns:
            The fit; it expects points batched like ``control_points``.

        Raises:
            TypeError, ValueError: as in :func:`radial_basis_function_deform_points`.
            RuntimeError: singular system (eagerly, and under ``jit`` through
                ``equinox.error_if``; the check sits on the LU factors, so it also survives a
                ``grad`` that never uses the forward field).

        Normalisation. With the affine tail the controls are centred on their mean ``m`` and
        divided by ``s``, the power of two nearest above their largest absolute coordinate
        (power of two: dividing by it is exact). Writing ``x_hat = (x - m) / s``, the kernel
        becomes ``phi(r / s) = phi(r) / s^2 - (log s / s^2) r^2``. Under the side conditions
        ``sum_j w_j = 0`` and ``sum_j c_j w_j^T = 0`` (the same conditions in either coordinate
        system, because ``[1, x_hat]`` is an invertible affine map of ``[1, x]``),
        ``sum_j r_j^2 w_j = sum_j |c_j|^2 w_j`` is constant in ``x`` and is absorbed by ``a_0``.
        So the normalised fit is a thin-plate spline in ``x`` with ``W = W_hat / s^2``, and the
        interpolation rows ``u(c_i) + lambda W_i = Delta_i`` match when the normalised smoothing
        is ``lambda_hat = lambda / s^2``. Uniqueness of the fit then makes the two fields the same
        function. Without the tail the ``r^2`` term is not absorbed, so ``polynomial=False``
        only centres (``K`` depends on differences only, so translation is exact) and keeps
        ``s = 1``.
        """
        control_points, batched = check_coordinates("control_points", control_points)
        control_displacements = check_same_shape("control_points", control_points, "control_displacements", control_displacements)
        check_choice("kernel", kernel, KERNELS)
        polynomial = check_bool("polynomial", polynomial)
        smoothing = check_real_scalar("smoothing", smoothing, control_points.dtype, nonnegative=True)
        num_controls, num_dims = control_points.shape[-2:]
        if polynomial and 0 < num_controls < num_dims + 1:
            raise ValueError(f"polynomial=True needs at least D + 1 = {num_dims + 1} control points in {num_dims}-D (or none), got {num_controls}")
        controls = add_batch_axis(control_points, batched)
        displacements = add_batch_axis(control_displacements, batched)
        leaves: tuple[jax.Array, ...]
        if num_controls == 0:
            batch, dtype = controls.shape[0], controls.dtype
            leaves = (
                jnp.zeros((batch, num_dims), dtype),
                jnp.ones((batch,), dtype),
                controls,
                displacements,
                jnp.zeros((batch, num_dims), dtype),
                jnp.zeros((batch, num_dims, num_dims), dtype),
            )
        else:
            smoothing_array = jnp.asarray(smoothing, controls.dtype)
            # The fit's singularity check (equinox.error_if) needs check_vma off; both inputs are
            # sharded along the design axis, so nothing is replicated.
            leaves = map_local_shards(
                lambda c, d: _fit_batch(c, d, smoothing_array, polynomial), (controls, displacements), (1, 1), out_axes=1, check_vma=False
            )
        centre, scale, normalised_controls, weights, constant, linear = (remove_batch_axis(leaf, batched) for leaf in leaves)
        return cls(centre, scale, normalised_controls, weights, constant, linear, polynomial=polynomial, batched=batched)

    def displacement(
        self, points: Float[Array, "*batch num_points num_dims"], *, implementation: str | None = None
    ) -> Float[Array, "*batch num_points num_dims"]:
        """The fitted field ``u(points)`` (not added to the points), shape and dtype of ``points``."""
        points = self._check_points(points)
        backend = self._implementation(points, implementation)
        return _displacement(points, self._leaves, batched=self.batched, backend=backend, budget=_block_budget(points))

    def __call__(
        self,
        points: Float[Array, "*batch num_points num_dims"],
        *,
        point_weights: Bool[Array, "*batch num_points"] | Float[Array, "*batch num_points"] | None = None,
        implementation: str | None = None,
    ) -> Float[Array, "*batch num_points num_dims"]:
        """Deformed points ``x + w * u(x)``; arguments as in :func:`radial_basis_function_deform_points`."""
        return self._deformed(points, point_weights, implementation)

    # -- internals ---------------------------------------------------------------------------

    def _deformed(self, points, point_weights, implementation: str | Implementation | None) -> jax.Array:
        # Also takes a resolved backend: radial_basis_function_deform_points selects it before the
        # fit, so that an unknown or unavailable one is reported first.
        points = self._check_points(points)
        point_weights = check_point_weights(point_weights, points)
        backend = self._implementation(points, implementation)
        return _deformed_points(points, point_weights, self._leaves, batched=self.batched, backend=backend, budget=_block_budget(points))

    def _check_points(self, points) -> jax.Array:
        points, batched = check_coordinates("points", points)
        # Same rank (batched or not), batch size, D and dtype as the fitted controls.
        check_companion("points", points, "the fit's control_points", self.normalised_controls)
        return points

    def _implementation(self, points, implementation: str | Implementation | None) -> Implementation:
        return select_implementation(_NAME, implementation, platform=platform_of(points))

    @property
    def _leaves(self) -> tuple[jax.Array, ...]:
        return (self.centre, self.scale, self.normalised_controls, self.weights, self.constant, self.linear)


# -- evaluation --------------------------------------------------------------------------------


def _block_budget(points: jax.Array) -> int:
    """Bytes per block of point/control pairs on the platform of ``points`` (read outside any
    trace: inside one, the platform of a tracer is unknown)."""
    return _BLOCK_BYTES.get(platform_of(points), _DEFAULT_BLOCK_BYTES)


def _field(points: jax.Array, leaves: tuple[jax.Array, ...], implementation: Implementation, budget: int) -> jax.Array:
    """``u`` on ``(B, N, D)`` points from batched fit leaves."""
    if points.shape[0] == 0 or points.shape[1] == 0:
        return jnp.zeros(points.shape, points.dtype)
    return map_local_shards(functools.partial(_evaluate, implementation, budget), (points, *leaves), (2, 1, 1, 1, 1, 1, 1), out_axes=2)


# An eager evaluation is one compiled program per shape (batch axes, field and weights together)
# rather than a program for each of those steps.
@functools.partial(jax.jit, static_argnames=("batched", "backend", "budget"))
def _displacement(points, leaves, *, batched: bool, backend: Implementation, budget: int) -> jax.Array:
    batched_leaves = tuple(add_batch_axis(leaf, batched) for leaf in leaves)
    return remove_batch_axis(_field(add_batch_axis(points, batched), batched_leaves, backend, budget), batched)


@functools.partial(jax.jit, static_argnames=("batched", "backend", "budget"))
def _deformed_points(points, point_weights, leaves, *, batched: bool, backend: Implementation, budget: int) -> jax.Array:
    field = _displacement(points, leaves, batched=batched, backend=backend, budget=budget)
    return apply_point_weights(points, field, point_weights)


@eqx.filter_jit
def _evaluate(implementation: Implementation, budget: int, points, centre, scale, controls, weights, constant, linear):
    """The field on ``(B, N, D)`` points from batched fit leaves (one compiled program per shape)."""
    normalised = (points - centre[:, None, :]) / scale[:, None, None]
    if implementation.is_warp:
        from warp_ffi.rbf import thin_plate_spline_field

        jax_field = functools.partial(_jax_field, budget=budget)
        return implementation.run(thin_plate_spline_field, jax_field, normalised, controls, weights, constant, linear)
    return _jax_field(normalised, controls, weights, constant, linear, budget=budget)


def _jax_field(normalised, controls, weights, constant, linear, *, budget: int) -> jax.Array:
    """The JAX field on normalised ``(B, N, D)`` points."""
    batch, num_points, _ = normalised.shape
    block = query_block_size(num_points, batch * controls.shape[1] * normalised.dtype.itemsize, budget_bytes=budget)
    # Controls as contiguous coordinate rows (D, C): a strided column read inside the pairwise
    # loop costs 25% on CPU; the barrier keeps XLA from folding the transpose back into it.
    controls_t = jax.lax.optimization_barrier(jnp.swapaxes(controls, 1, 2))

    def one(x, c_t, w, a, lin):
        return map_query_blocks(lambda xb: _block_field(xb, c_t, w, a, lin), (x,), block_size=block)

    if batch == 1:
        # A flat loop: XLA:CPU spreads its fused pairwise work over all cores, which it does not
        # do inside a vmapped (batched) loop (measured 2x on 2 cores).
        return one(normalised[0], controls_t[0], weights[0], constant[0], linear[0])[None]
    return jax.vmap(one)(normalised, controls_t, weights, constant, linear)


# -- fit ---------------------------------------------------------------------------------------


@eqx.filter_jit
def _fit_batch(controls, displacements, smoothing, polynomial: bool):
    """Fit leaves for ``(B, C, D)`` controls (one compiled program per shape and ``polynomial``)."""
    return jax.vmap(lambda c, d: _fit_one(c, d, smoothing, polynomial))(controls, displacements)


def _fit_one(controls, displacements, smoothing, polynomial: bool):
    """Normalise and solve one ``(C, D)`` control set; returns the fit leaves."""
    num_controls, num_dims = controls.shape
    dtype = controls.dtype
    # The fitted field does not depend on the centre and scale (see ThinPlateSplineFit.fit), so
    # they are constants for autodiff.
    centre = jax.lax.stop_gradient(jnp.mean(controls, axis=0))
    if polynomial:
        scale, exponent = _power_of_two_above(jax.lax.stop_gradient(jnp.max(jnp.abs(controls - centre))))
    else:
        scale, exponent = jnp.ones((), dtype), jnp.zeros((), jnp.int32)
    normalised = (controls - centre) / scale
    matrix = _tps_kernel(_squared_distances(normalised, normalised.T))
    # lambda / scale^2 as an exact exponent shift: scale^2 itself can flush to zero or overflow
    # (scale ~ 1e-20 in float32), and XLA may rewrite (a / s) / s as a / (s * s).
    matrix = matrix + jnp.ldexp(smoothing, -2 * exponent) * jnp.eye(num_controls, dtype=dtype)
    rhs = displacements
    if polynomial:
        # Symmetric equilibration: the tail columns and rows are scaled to the size of the kernel
        # block, so a large smoothing does not shrink the tail's pivots towards the singularity
        # threshold (solution unchanged: the affine coefficients are scaled back below).
        balance, _ = _power_of_two_above(jax.lax.stop_gradient(jnp.max(jnp.abs(matrix))))
        tail = balance * jnp.concatenate([jnp.ones((num_controls, 1), dtype), normalised], axis=1)
        matrix = jnp.block([[matrix, tail], [tail.T, jnp.zeros((num_dims + 1, num_dims + 1), dtype)]])
        rhs = jnp.concatenate([displacements, jnp.zeros((num_dims + 1, num_dims), dtype)], axis=0)
    solution = _checked_symmetric_solve(matrix, rhs)
    weights = solution[:num_controls]
    if polynomial:
        constant, linear = balance * solution[num_controls], balance * solution[num_controls + 1 :]
    else:
        constant, linear = jnp.zeros((num_dims,), dtype), jnp.zeros((num_dims, num_dims), dtype)
    return centre, scale, normalised, weights, constant, linear


def _power_of_two_above(spread):
    """``(2**e, e)`` with ``spread / 2**e`` in ``[0.5, 1)``; ``(1, 0)`` for zero or non-finite spreads."""
    _, exponent = jnp.frexp(spread)
    usable = jnp.isfinite(spread) & (spread > 0) & jnp.isfinite(jnp.ldexp(jnp.ones_like(spread), exponent))
    exponent = jnp.where(usable, exponent, jnp.zeros_like(exponent))
    return jnp.ldexp(jnp.ones_like(spread), exponent), exponent


def _checked_symmetric_solve(matrix, rhs):
    """Solve ``matrix @ x = rhs`` (symmetric, possibly indefinite) with one LU factorisation.

    The factorisation is reused by the tangent and adjoint solves (``custom_linear_solve``), so
    gradients and higher derivatives cost triangular solves only. The singularity check is
    attached to the LU factors, which every forward and backward solve reads.
    """
    lu, pivots, _ = jax.lax.linalg.lu(jax.lax.stop_gradient(matrix))
    magnitudes = jnp.abs(jnp.diagonal(lu))
    tolerance = _PIVOT_ULPS * jnp.finfo(matrix.dtype).eps
    # Strict, so that an all-zero matrix and NaN (a non-finite control layout) count as singular.
    regular = jnp.min(magnitudes) > tolerance * jnp.max(magnitudes)
    lu = runtime_check(
        lu,
        jnp.logical_not(regular),
        "radial_basis_function_deform_points: the thin-plate-spline fit system is singular or not "
        "finite (duplicate control points, controls that do not affinely span R^D, or a single "
        "control without the affine tail and without smoothing)",
        RuntimeError,
    )

    def solve(_, b):
        return jax.scipy.linalg.lu_solve((lu, pivots), b)

    return jax.lax.custom_linear_solve(lambda x: jnp.matmul(matrix, x, precision=jax.lax.Precision.HIGHEST), rhs, solve, symmetric=True)


# -- field -------------------------------------------------------------------------------------


def _block_field(points, controls_t, weights, constant, linear):
    """``u`` for one block of normalised ``(n, D)`` points; ``controls_t`` is ``(D, C)``."""
    highest = jax.lax.Precision.HIGHEST
    radial = jnp.matmul(_tps_kernel(_squared_distances(points, controls_t)), weights, precision=highest)
    return radial + (constant + jnp.matmul(points, linear, precision=highest))


def _squared_distances(x, controls_t):
    """``|x_i - c_j|^2`` for ``(n, D)`` points and ``(D, C)`` controls, from coordinate
    differences: exactly zero at coincidence, no cancellation (unlike |x|^2 - 2 x.c + |c|^2)."""
    total = jnp.zeros((x.shape[0], controls_t.shape[1]), x.dtype)
    for k in range(x.shape[-1]):
        diff = x[:, k, None] - controls_t[k][None, :]
        total = diff * diff if k == 0 else total + diff * diff
    return total


def _tps_kernel(squared):
    """``phi = r^2 log r = 0.5 s log s`` from ``s = r^2``.

    At ``s = 0`` the log argument is replaced by one, which gives the value zero and a zero
    derivative of every order there; ``log(0)`` never enters the graph, so no NaN reaches any
    gradient.
    """
    safe = jnp.where(squared > 0, squared, jnp.ones((), squared.dtype))
    # The factor 0.5 goes on the log, not on ``squared``: XLA:CPU fuses ``s * (0.5 * log s)``
    # into one loop but splits ``(0.5 * s) * log s`` around the float64 log's word split, which
    # made the whole pairwise evaluation 2.5x slower (measured).
    return squared * (0.5 * _log(safe))


@jax.custom_jvp
def _log(x):
    """Natural log; float64 uses a branch-free polynomial that XLA vectorises (see ``_log64``)."""
    if x.dtype == jnp.float64:
        return _log64(x)
    return jnp.log(x)


_log.defjvps(lambda tangent, _, x: tangent / x)


def _split_ln2():
    ln2 = decimal.Context(prec=40).ln(decimal.Decimal(2))
    bits = struct.unpack("<q", struct.pack("<d", float(ln2)))[0] & ~0xFFFFFFF  # 28 zero low bits
    high = struct.unpack("<d", struct.pack("<q", bits))[0]
    return high, float(ln2 - decimal.Decimal(high))


_LN2_HIGH, _LN2_LOW = _split_ln2()  # k * _LN2_HIGH is exact for every float64 exponent k
# The high 32-bit word of sqrt(1/2) (sign, 11 exponent bits, top 20 mantissa bits).
_SQRT_HALF_HIGH_WORD = int(np.float64(np.sqrt(0.5)).view(np.int64)) >> 32
_HIGH_MANTISSA_MASK = (1 << 20) - 1
# log(m) = 2 atanh(z) = 2z + z w P(w), z = (m - 1) / (m + 1), w = z^2. For m in
# [sqrt(1/2), sqrt(2)), w <= (3 - 2 sqrt 2)^2 = 0.02944. P is the degree-6 Chebyshev fit of
# (2 atanh(z) - 2z) / (z w) on that interval (fitted in 50-digit arithmetic; max error 3.1e-16
# of P, i.e. below 5e-18 relative to log m). The Taylor series would need ten terms.
_ATANH_REMAINDER = (
    0.14616449685043406,
    0.15331721600556042,
    0.18182889125261723,
    0.2222221113479508,
    0.28571428625975487,
    0.39999999999899505,
    0.666666666666667,
)


def _log64(x):
    """``log(x)`` for positive float64 ``x`` within 2 ulp (measured; subnormals less accurate).

    XLA's CPU ``log`` is several times slower than arithmetic when its result is materialised
    for a matrix product, and it dominates the pairwise evaluation; this version uses only
    integer and floating arithmetic (one division) and vectorises. Split ``x = 2^k m`` with
    ``m`` in ``[sqrt(1/2), sqrt(2))``, then ``log x = k ln 2 + 2 atanh z``.

    The split works on the high 32-bit word only (exponent and top mantissa bits): 32-bit
    integer lanes are twice as wide as 64-bit ones on CPUs without AVX2 integer vectors, and
    the low word passes through unchanged (measured 20% faster than 64-bit integer arithmetic
    for the whole pairwise RBF evaluation). The word order of the split is little-endian, as on
    every platform JAX runs on; the powers-of-two cases of the accuracy test would catch others.
    """
    words = jax.lax.bitcast_convert_type(x, jnp.int32)  # (..., 2): [low, high]
    high = words[..., 1] - jnp.int32(_SQRT_HALF_HIGH_WORD)
    exponent = jax.lax.shift_right_arithmetic(high, jnp.int32(20))
    mantissa_high = (high & jnp.int32(_HIGH_MANTISSA_MASK)) + jnp.int32(_SQRT_HALF_HIGH_WORD)
    mantissa = jax.lax.bitcast_convert_type(jnp.stack([words[..., 0], mantissa_high], axis=-1), jnp.float64)
    f = mantissa - 1.0
    z = f / (f + 2.0)
    w = z * z
    remainder = jnp.full_like(w, _ATANH_REMAINDER[0])
    for coefficient in _ATANH_REMAINDER[1:]:
        remainder = remainder * w + coefficient
    k = exponent.astype(jnp.float64)
    return k * _LN2_HIGH + (2.0 * z + (z * w * remainder + k * _LN2_LOW))
