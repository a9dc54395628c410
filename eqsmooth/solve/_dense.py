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

    Every factor stack contributes one `(n, K, K)` batch of products of its
    concatenated row Jacobian `[J_1 … J_k]` (`K = Σ d_i`); all entries of all
    stacks are added into the flat `N²` matrix by a single scatter whose
    indices are computed once, at trace time (no `M × N` Jacobian, no
    per-block scatter).
    """
    N = lin.num_tangent
    offsets = group_offsets(lin)
    dims = {g.name: g.dim for g in lin.layout}
    values, indices = [], []
    for fl in lin.factors:
        n = fl.residual.shape[0]
        if n == 0:
            continue
        cols = np.concatenate(
            [
                offsets[v.group]
                + np.asarray(v.ids)[:, None] * dims[v.group]
                + np.arange(dims[v.group])[None]
                for v in fl.variables
            ],
            axis=1,
        )  # (n, K) absolute coordinates touched by each row
        jac = jnp.concatenate(fl.jacobians, axis=2)  # (n, m, K)
        values.append(jnp.einsum("nmi,nmj->nij", jac, jac).reshape(-1))
        indices.append((cols[:, :, None] * N + cols[:, None, :]).reshape(-1))
    flat = jnp.zeros((N * N,), lin.dtype)
    if values:
        flat = flat.at[np.concatenate(indices)].add(jnp.concatenate(values))
    H = flat.reshape(N, N)
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
