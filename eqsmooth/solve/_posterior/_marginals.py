"""Marginal covariances of the Gauss-Newton (Laplace) approximation."""

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from .._linear._default_solver import factorize
from .._linearization import Linearization
from .._solution import Solution
from ._posterior import (
    as_linearization,
    raise_unless_ok,
    real_counts,
    singular_message,
    take_real,
)


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

    A dict `{group: (N_g, d_g, d_g)}` of covariance blocks. A normal matrix
    that cannot be factorised (singular, or too ill-conditioned in float32)
    raises an `EquinoxRuntimeError` that says which.
    """
    names = [g.name for g in as_linearization(lin, "marginal_covariances").layout]
    if groups is None:
        groups = names
    unknown = [g for g in groups if g not in names]
    if unknown:
        raise ValueError(
            f"marginal_covariances: unknown groups {unknown}; the graph has {names}"
        )
    counts = real_counts(lin)
    lin = as_linearization(lin, "marginal_covariances")
    cov, ok = _marginal_covariances(lin, solver, tuple(groups))
    cov = raise_unless_ok(ok, cov, singular_message("marginal_covariances", lin.dtype))
    return take_real(cov, counts)


@eqx.filter_jit
def _marginal_covariances(lin, solver, groups):
    factor = factorize(lin, solver)
    cov = factor.inverse_block_diagonal()
    finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(v)) for v in cov.values()]))
    return {k: v for k, v in cov.items() if k in groups}, factor.ok & finite
