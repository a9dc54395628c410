"""Log-determinant of the Gauss-Newton normal matrix `JᵀJ` (Laplace evidence)."""

import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ._block_tridiagonal import assemble_chain, BlockTridiagonal, chain_plan
from ._dense import dense_normal_matrix
from ._linear_solver import AbstractLinearSolver
from ._linearization import Linearization, Tangent


def _chol_log_det(chol: Float[Array, "*b D D"]) -> Float[Array, "*b"]:
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)


def block_tridiagonal_log_det(
    diagonal: Float[Array, "T D D"], upper: Float[Array, "T-1 D D"]
) -> Float[Array, ""]:
    """`log det` of a symmetric positive definite block-tridiagonal matrix.

    A sequential block Cholesky (block LDLᵀ) recursion run by `lax.scan`: with
    `S_0 = A_0` and `S_t = A_t − B_{t−1}ᵀ S_{t−1}⁻¹ B_{t−1}` (the Schur
    complements, `B` the super-diagonal blocks), `log det = Σ_t log det S_t`,
    each term from the Cholesky factor of `S_t`. `O(T D³)` work, differentiable
    by ordinary reverse- or forward-mode autodiff (Cholesky and triangular
    solves).

    **Arguments:**

    - `diagonal`: the `(T, D, D)` diagonal blocks.
    - `upper`: the `(T − 1, D, D)` super-diagonal blocks.

    **Returns:**

    The scalar log-determinant; NaN when the matrix is not positive definite
    (a non-positive Schur complement pivot).
    """
    if diagonal.ndim != 3 or diagonal.shape[1] != diagonal.shape[2]:
        raise ValueError(
            f"block_tridiagonal_log_det: diagonal must be (T, D, D), got "
            f"{diagonal.shape}"
        )
    T, D, _ = diagonal.shape
    if upper.shape != (T - 1, D, D):
        raise ValueError(
            f"block_tridiagonal_log_det: upper must be ({T - 1}, {D}, {D}), got "
            f"{upper.shape}"
        )
    chol0 = jnp.linalg.cholesky(diagonal[0])
    if T == 1:
        return _chol_log_det(chol0)

    def body(chol_prev, blocks):
        a, b = blocks
        # W = L_{t-1}⁻¹ B_{t-1}, so that B_{t-1}ᵀ S_{t-1}⁻¹ B_{t-1} = WᵀW.
        w = jax.scipy.linalg.solve_triangular(chol_prev, b, lower=True)
        s = a - w.T @ w
        s = 0.5 * (s + s.T)
        chol = jnp.linalg.cholesky(s)
        return chol, _chol_log_det(chol)

    _, terms = lax.scan(body, chol0, (diagonal[1:], upper))
    return _chol_log_det(chol0) + jnp.sum(terms)


def normal_log_det(
    lin: Linearization,
    solver: AbstractLinearSolver | None = None,
    damping: Tangent | None = None,
) -> Float[Array, ""]:
    """`log det (JᵀJ + diag(damping))` of a linearisation.

    With the noise whitening included in `J`, this is the log-determinant of
    the Laplace (Gauss-Newton) posterior precision, the term that turns a MAP
    cost into an approximate log marginal likelihood
    (see [`eqsmooth.discover.laplace_log_marginal`][]).

    Chains (see [`eqsmooth.solve.BlockTridiagonal`][]) use
    [`eqsmooth.solve.block_tridiagonal_log_det`][], `O(T D³)`; other graphs
    use a dense Cholesky of the `N × N` normal matrix, `O(N³)`.

    **Arguments:**

    - `lin`: the linearisation.
    - `solver`: `BlockTridiagonal()` forces the chain method (a `ValueError` if
        the graph is not a chain); any other solver selects the dense method;
        `None` picks the chain method whenever the graph is a chain.
    - `damping`: optional tangent dict added to the diagonal.

    **Returns:**

    The scalar log-determinant; NaN when the matrix is singular or not positive
    definite.
    """
    plan = None
    if isinstance(solver, BlockTridiagonal):
        plan = chain_plan(lin)
    elif solver is None:
        try:
            plan = chain_plan(lin)
        except ValueError:
            plan = None
    if plan is not None:
        diag, upper, _ = assemble_chain(lin, plan, damping)
        return block_tridiagonal_log_det(diag, upper)
    H = dense_normal_matrix(lin, damping)
    return _chol_log_det(jnp.linalg.cholesky(0.5 * (H + H.T)))
