"""A banded Cholesky solve of the fixed-lag window's normal equations.

With loop closures (or a prior spanning several slots) the window is not a
chain, and the default linear solver would be a dense Cholesky of the whole
window, `O((lag · d)³)` per iteration. But every factor of the window links
states at most `S` slots apart (the prior spans the first `S` slots, a
closure reaches at most `S = max_back` steps back), so the normal matrix of
the slot-major tangent vector is banded: an entry `(i, j)` is zero when
`|i − j| ≥ (S + 1) · d`. Cut into blocks of `B = (S + 1) · d` coordinates it
is block tridiagonal, and its block Cholesky factorisation costs
`O(lag · d · B²)` (Golub & Van Loan, *Matrix Computations*, 4th ed., §4.5).
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from ..factors import GroupLayout
from ..solve import AbstractFactorization, AbstractNormalSolver, NormalOperator
from ..solve._linear._linear_solver import diagonal_blocks, pivot_tolerance
from ..solve._linearization import flatten_layout, unflatten_layout


def _solve_lower(L, b):
    return jax.scipy.linalg.solve_triangular(L, b, lower=True)


def _solve_upper(L, b):
    return jax.scipy.linalg.solve_triangular(L, b, lower=True, trans="T")


class BandedFactorization(AbstractFactorization):
    """`H = L Lᵀ` with `L` block lower bidiagonal in blocks of `B`
    coordinates: diagonal blocks `diag[i]` (lower triangular) and
    sub-diagonal blocks `sub[i]` (row block `i + 1`, column block `i`). The
    matrix is padded with an identity to a whole number of blocks."""

    diag: Float[Array, "nb B B"]
    sub: Float[Array, "nb1 B B"]
    ok: Bool[Array, ""]
    size: int = eqx.field(static=True)
    layout: tuple[GroupLayout, ...] = eqx.field(static=True)

    def log_det(self) -> Float[Array, ""]:
        pivots = jnp.diagonal(self.diag, axis1=1, axis2=2).reshape(-1)[: self.size]
        return 2.0 * jnp.sum(jnp.log(pivots))

    def solve(self, b: Float[Array, "N ..."]) -> Float[Array, "N ..."]:
        nb, B = self.diag.shape[:2]
        tail = b.shape[1:]
        pad = jnp.zeros((nb * B - self.size, *tail), b.dtype)
        b = jnp.concatenate([b, pad]).reshape(nb, B, -1)

        def forward(y_prev, inputs):
            L, C, bi = inputs
            y = _solve_lower(L, bi - C @ y_prev)
            return y, y

        zero = jnp.zeros_like(b[0])
        subs = jnp.concatenate([jnp.zeros_like(self.sub[:1]), self.sub])
        _, y = jax.lax.scan(forward, zero, (self.diag, subs, b))

        def backward(x_next, inputs):
            L, C, yi = inputs
            x = _solve_upper(L, yi - C.T @ x_next)
            return x, x

        later = jnp.concatenate([self.sub, jnp.zeros_like(self.sub[:1])])
        _, x = jax.lax.scan(backward, zero, (self.diag, later, y), reverse=True)
        return x.reshape(nb * B, *tail)[: self.size]

    def inverse_block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        inv = self.solve(jnp.eye(self.size, dtype=self.diag.dtype))
        return diagonal_blocks(inv, self.layout)


class BandedCholesky(AbstractNormalSolver):
    """Cholesky factorisation of a [`eqsmooth.solve.NormalOperator`][] whose
    entries vanish at `|i − j| ≥ block` (coordinates of the flat, group-major
    tangent vector), as block tridiagonal in blocks of `block` coordinates.
    The caller vouches for the band (the fixed-lag window does); a matrix
    that is singular or not positive definite to working precision gives
    `RESULTS.singular` and a zero solution, as `DenseCholesky`."""

    block: int = eqx.field(static=True)

    def init(
        self, operator: lx.AbstractLinearOperator, options: dict[str, Any]
    ) -> BandedFactorization:
        del options
        if not isinstance(operator, NormalOperator):
            raise TypeError(
                "BandedCholesky solves the normal equations of a linearisation "
                f"(an eqsmooth.solve.NormalOperator), got {type(operator).__name__}"
            )
        H = operator.as_matrix()
        N, B = H.shape[0], self.block
        nb = -(-N // B)
        P = nb * B
        Hp = jnp.zeros((P, P), H.dtype).at[:N, :N].set(0.5 * (H + H.T))
        Hp = Hp + jnp.diag(jnp.where(jnp.arange(P) >= N, 1.0, 0.0).astype(H.dtype))
        blocks = Hp.reshape(nb, B, nb, B)
        i = np.arange(nb)
        D = blocks[i, :, i, :]  # (nb, B, B)
        E = blocks[i[1:], :, i[:-1], :]  # (nb - 1, B, B): row block i + 1

        def step(L_prev, inputs):
            Di, Ei = inputs
            C = _solve_lower(L_prev, Ei.T).T  # E L_prevᵀ⁻¹
            L = jnp.linalg.cholesky(Di - C @ C.T)
            return L, (L, C)

        L0 = jnp.linalg.cholesky(D[0])
        _, (Ls, Cs) = jax.lax.scan(step, L0, (D[1:], E))
        diag = jnp.concatenate([L0[None], Ls])
        pivots = jnp.diagonal(diag, axis1=1, axis2=2).reshape(-1)[:N]
        tol = pivot_tolerance(H.dtype, N, jnp.asarray(1.0, H.dtype))
        ok = (
            jnp.all(jnp.isfinite(diag))
            & jnp.all(jnp.isfinite(Cs))
            & jnp.all(pivots * pivots > tol * jnp.diagonal(H))
        )
        return BandedFactorization(diag, Cs, ok, N, operator.lin.layout)

    def compute(self, state: BandedFactorization, vector, options: dict[str, Any]):
        del options
        b = flatten_layout(state.layout, vector)
        x = state.solve(b.astype(state.diag.dtype))
        x = jnp.where(state.ok, x, jnp.zeros_like(x))
        result = lx.RESULTS.where(state.ok, lx.RESULTS.successful, lx.RESULTS.singular)
        return unflatten_layout(state.layout, x), result, {}
