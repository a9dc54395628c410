"""Dense Cholesky: the reference solver for small graphs."""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from ._linear_solver import AbstractLinearSolver, pivot_tolerance
from ._linearization import (
    flatten_tangent,
    gradient,
    group_offsets,
    Linearization,
    Tangent,
    unflatten_tangent,
)
from ._solution import RESULTS


def dense_normal_matrix(
    lin: Linearization, damping: Tangent | None = None
) -> Float[Array, "N N"]:
    """`JᵀJ + diag(damping)` as a dense group-major matrix.

    Accumulated from the per-row `d_k × d_l` products (no `M × N` Jacobian).
    """
    N = lin.num_tangent
    offsets = group_offsets(lin)
    dims = {g.name: g.dim for g in lin.layout}
    H = jnp.zeros((N, N), lin.dtype)
    for fl in lin.factors:
        idx = [
            offsets[v.group] + v.ids[:, None] * dims[v.group] + np.arange(dims[v.group])
            for v in fl.variables
        ]
        for a, ja in enumerate(fl.jacobians):
            for b, jb in enumerate(fl.jacobians):
                p = jnp.einsum("nmd,nme->nde", ja, jb)
                H = H.at[idx[a][:, :, None], idx[b][:, None, :]].add(p)
    if damping is not None:
        d = flatten_tangent(lin, {k: v.astype(lin.dtype) for k, v in damping.items()})
        H = H + jnp.diag(d)
    return H


def dense_cholesky_ok(
    H: Float[Array, "N N"], upper_factor: Float[Array, "N N"]
) -> Bool[Array, ""]:
    """Whether a Cholesky factor of `H` has finite pivots above rounding level."""
    piv = jnp.diagonal(upper_factor)
    tol = pivot_tolerance(H.dtype, H.shape[0], jnp.asarray(1.0, H.dtype))
    return jnp.all(jnp.isfinite(upper_factor)) & jnp.all(
        piv * piv > tol * jnp.diagonal(H)
    )


class DenseCholesky(AbstractLinearSolver):
    """Dense Cholesky factorisation of the normal matrix.

    Materialises `JᵀJ + diag(damping)` (`N × N` for `N` tangent coordinates)
    and solves it with `lineax.Cholesky`: `O(N³)`. The reference solver, for
    small graphs and tests; it accepts any graph structure.
    """

    def solve(
        self,
        lin: Linearization,
        damping: Tangent | None,
        rhs: Tangent | None = None,
    ) -> tuple[Tangent, RESULTS]:
        H = dense_normal_matrix(lin, damping)
        if rhs is None:
            b = -flatten_tangent(lin, gradient(lin))
        else:
            b = flatten_tangent(lin, {k: v.astype(lin.dtype) for k, v in rhs.items()})
        operator = lx.MatrixLinearOperator(H, lx.positive_semidefinite_tag)
        solver = lx.Cholesky()
        stopped = lx.MatrixLinearOperator(
            jax.lax.stop_gradient(H), lx.positive_semidefinite_tag
        )
        state = solver.init(stopped, {})
        # lineax's Cholesky state is (upper factor, static flag); its pivots tell
        # a singular system apart from a merely ill-conditioned one.
        ok = dense_cholesky_ok(jax.lax.stop_gradient(H), state[0])
        sol = lx.linear_solve(operator, b, solver, state=state, throw=False)
        x = jnp.where(ok, sol.value, jnp.zeros_like(sol.value))
        result = lx.RESULTS.where(ok, sol.result, lx.RESULTS.singular)
        return unflatten_tangent(lin, x), RESULTS.promote(result)
