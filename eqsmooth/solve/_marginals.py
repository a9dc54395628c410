"""Marginal covariances of the Gauss-Newton (Laplace) approximation."""

from collections.abc import Sequence

import equinox as eqx
import lineax as lx
from jaxtyping import Array, Float

from ._default_solver import factorize
from ._joint_marginals import as_linearization
from ._linearization import Linearization
from ._solution import Solution


_SINGULAR = (
    "marginal_covariances: the normal matrix JᵀJ is singular, so some marginal "
    "covariance is infinite (is every gauge freedom fixed by a prior?)"
)


@eqx.filter_jit
def marginal_covariances(
    lin: Linearization | Solution,
    solver: lx.AbstractLinearSolver | None = None,
    groups: Sequence[str] | None = None,
) -> dict[str, Float[Array, "_N _d _d"]]:
    """Marginal covariance of every variable: the diagonal blocks of `(JᵀJ)⁻¹`.

    At a (local) optimum this is the Laplace approximation of the posterior, in
    the tangent coordinates of the linearisation point (right perturbations,
    `x ⊕ δ` with `δ ~ N(0, Σ)`).

    The blocks come from the linear solver's factorisation (its state, an
    [`eqsmooth.solve.AbstractFactorization`][]): `BlockTridiagonal()` gives
    them by selected inversion of the block cyclic reduction, `O(T D³)`;
    `DenseCholesky()` by a dense inverse, `O(N³)`, so keep those graphs
    small. Solvers without a factorisation in their state fall back to
    `DenseCholesky()`.

    **Arguments:**

    - `lin`: the [`eqsmooth.solve.Solution`][] of a solve (its final state
        keeps the linearisation at the solution: `eqs.marginal_covariances(sol)`
        costs no new linearisation), or any
        [`eqsmooth.solve.Linearization`][], e.g.
        `eqs.linearize(graph, values)`.
    - `solver`: the linear solver (`BlockTridiagonal()` on a graph that is
        not a chain raises a `ValueError`); `None` picks `BlockTridiagonal()`
        for chains and `DenseCholesky()` otherwise.
    - `groups`: the variable groups to return (default: all).

    **Returns:**

    A dict `{group: (N_g, d_g, d_g)}` of covariance blocks. A singular normal
    matrix raises an `EquinoxRuntimeError` (`eqx.error_if`).
    """
    lin = as_linearization(lin, "marginal_covariances")
    names = [g.name for g in lin.layout]
    if groups is None:
        groups = names
    unknown = [g for g in groups if g not in names]
    if unknown:
        raise ValueError(
            f"marginal_covariances: unknown groups {unknown}; the graph has {names}"
        )
    factor = factorize(lin, solver)
    cov = factor.inverse_block_diagonal()
    cov = eqx.error_if(cov, ~factor.ok, _SINGULAR)
    return {k: v for k, v in cov.items() if k in groups}
