"""Log-determinant of the Gauss-Newton normal matrix `JᵀJ` (Laplace evidence)."""

import lineax as lx
from jaxtyping import Array, Float

from .._linear._block_tridiagonal import (
    block_tridiagonal_log_det as block_tridiagonal_log_det,
)
from .._linear._default_solver import factorize
from .._linearization import Linearization, Tangent


def normal_log_det(
    lin: Linearization,
    solver: lx.AbstractLinearSolver | None = None,
    damping: Tangent | None = None,
) -> Float[Array, ""]:
    """`log det (JᵀJ + diag(damping))` of a linearisation.

    With the noise whitening included in `J`, this is the log-determinant of
    the Laplace (Gauss-Newton) posterior precision, the term that turns a MAP
    cost into an approximate log marginal likelihood
    (see [`eqsmooth.discover.laplace_log_marginal`][]).

    The factorisation comes from the linear solver's state (an
    [`eqsmooth.solve.AbstractFactorization`][]): `BlockTridiagonal()` gives
    `O(T D³)` for chains, `DenseCholesky()` `O(N³)` for any graph. A solver
    whose state is not a factorisation (iterative or host solvers, lineax's
    own) falls back to the dense one. Differentiable by ordinary autodiff.

    **Arguments:**

    - `lin`: the linearisation.
    - `solver`: the linear solver whose factorisation to use
        (`BlockTridiagonal()` on a graph that is not a chain raises a
        `ValueError`); `None` picks `BlockTridiagonal()` for chains and
        `DenseCholesky()` otherwise.
    - `damping`: optional tangent dict added to the diagonal.

    **Returns:**

    The scalar log-determinant; NaN when the matrix is singular or not positive
    definite.
    """
    return factorize(lin, solver, damping).log_det()
