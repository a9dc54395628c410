"""Dense Cholesky: the reference solver for small graphs."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from ...factors import GroupLayout
from .._linearization import (
    flatten_layout,
    unflatten_layout,
)
from ._linear_solver import (
    AbstractFactorization,
    AbstractNormalSolver,
    normal_operator_of,
    pivot_tolerance,
)


def dense_cholesky_ok(
    H: Float[Array, "N N"], upper_factor: Float[Array, "N N"]
) -> Bool[Array, ""]:
    """Whether a Cholesky factor of `H` has finite pivots above rounding level."""
    piv = jnp.diagonal(upper_factor)
    tol = pivot_tolerance(H.dtype, H.shape[0], jnp.asarray(1.0, H.dtype))
    return jnp.all(jnp.isfinite(upper_factor)) & jnp.all(
        piv * piv > tol * jnp.diagonal(H)
    )


class DenseFactorization(AbstractFactorization):
    """The state of [`eqsmooth.solve.DenseCholesky`][]: a dense Cholesky factor."""

    lower: Float[Array, "N N"]
    ok: Bool[Array, ""]
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)

    def log_det(self) -> Float[Array, ""]:
        return 2.0 * jnp.sum(jnp.log(jnp.diagonal(self.lower)))

    def solve(self, b: Float[Array, "N ..."]) -> Float[Array, "N ..."]:
        return jax.scipy.linalg.cho_solve((self.lower, True), b)

    def inverse_block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        eye = jnp.eye(self.lower.shape[0], dtype=self.lower.dtype)
        inv = self.solve(eye)
        out, start = {}, 0
        for g in self.layout:
            size = g.count * g.dim
            block = inv[start : start + size, start : start + size]
            block = block.reshape(g.count, g.dim, g.count, g.dim)
            i = np.arange(g.count)
            out[g.name] = block[i, :, i, :]
            start += size
        return out


class DenseCholesky(AbstractNormalSolver):
    """Dense Cholesky factorisation of the normal matrix.

    Materialises `JᵀJ + diag(damping)` (`N × N` for `N` tangent coordinates)
    and factorises it: `O(N³)`. The reference solver, for small graphs and
    tests; it accepts any graph structure. Its state is a
    [`eqsmooth.solve.DenseFactorization`][] (log-determinant, marginals).
    """

    def init(
        self, operator: lx.AbstractLinearOperator, options: dict[str, Any]
    ) -> DenseFactorization:
        del options
        op = normal_operator_of(operator, "DenseCholesky")
        H = op.as_matrix()
        lower = jnp.linalg.cholesky(0.5 * (H + H.T))
        ok = dense_cholesky_ok(H, lower.T)
        return DenseFactorization(lower, ok, op.lin.layout)

    def compute(self, state: DenseFactorization, vector, options: dict[str, Any]):
        del options
        b = flatten_layout(state.layout, vector)
        x = state.solve(b)
        x = jnp.where(state.ok, x, jnp.zeros_like(x))
        result = lx.RESULTS.where(state.ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return unflatten_layout(state.layout, x), result, {}
