"""Marginal covariances of the Gauss-Newton (Laplace) approximation."""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ._block_tridiagonal import (
    assemble_chain,
    BlockTridiagonal,
    chain_plan,
    cyclic_reduction_factor,
    cyclic_reduction_inverse_blocks,
)
from ._dense import dense_cholesky_ok, dense_normal_matrix
from ._linear_solver import AbstractLinearSolver
from ._linearization import group_offsets, Linearization


_SINGULAR = (
    "marginal_covariances: the normal matrix JᵀJ is singular, so some marginal "
    "covariance is infinite (is every gauge freedom fixed by a prior?)"
)


@eqx.filter_jit
def marginal_covariances(
    lin: Linearization,
    solver: AbstractLinearSolver | None = None,
    groups: Sequence[str] | None = None,
) -> dict[str, Float[Array, "_N _d _d"]]:
    """Marginal covariance of every variable: the diagonal blocks of `(JᵀJ)⁻¹`.

    At a (local) optimum this is the Laplace approximation of the posterior, in
    the tangent coordinates of the linearisation point (right perturbations,
    `x ⊕ δ` with `δ ~ N(0, Σ)`).

    Chains (see [`eqsmooth.solve.BlockTridiagonal`][]) use the selected
    inversion of the block cyclic reduction, `O(T D³)`; other graphs use a
    dense inverse, `O(N³)`, so keep them small.

    **Arguments:**

    - `lin`: the linearisation, e.g. the final state's `lin` of a solve.
    - `solver`: `BlockTridiagonal()` forces the chain method (a `ValueError` if
        the graph is not a chain); any other solver selects the dense method;
        `None` picks the chain method whenever the graph is a chain.
    - `groups`: the variable groups to return (default: all).

    **Returns:**

    A dict `{group: (N_g, d_g, d_g)}` of covariance blocks. A singular normal
    matrix raises an `EquinoxRuntimeError` (`eqx.error_if`).
    """
    names = [g.name for g in lin.layout]
    if groups is None:
        groups = names
    unknown = [g for g in groups if g not in names]
    if unknown:
        raise ValueError(
            f"marginal_covariances: unknown groups {unknown}; the graph has {names}"
        )
    plan = None
    if isinstance(solver, BlockTridiagonal):
        plan = chain_plan(lin)
    elif solver is None:
        try:
            plan = chain_plan(lin)
        except ValueError:
            plan = None
    if plan is not None:
        return _chain_marginals(lin, plan, groups)
    return _dense_marginals(lin, groups)


def _chain_marginals(lin, plan, groups):
    diag, upper, _ = assemble_chain(lin, plan, None)
    state = cyclic_reduction_factor(diag, upper)
    cov, _ = cyclic_reduction_inverse_blocks(state, plan.length)
    cov = eqx.error_if(cov, ~state.ok, _SINGULAR)
    out = {}
    for g, off in zip(lin.layout, plan.offsets):
        if g.name in groups:
            out[g.name] = cov[:, off : off + g.dim, off : off + g.dim]
    return out


def _dense_marginals(lin, groups):
    H = dense_normal_matrix(lin)
    chol = jnp.linalg.cholesky(H)
    ok = dense_cholesky_ok(H, chol.T)
    eye = jnp.eye(H.shape[0], dtype=H.dtype)
    inv = jax.scipy.linalg.cho_solve((chol, True), eye)
    inv = eqx.error_if(inv, ~ok, _SINGULAR)
    offsets = group_offsets(lin)
    out = {}
    for g in lin.layout:
        if g.name in groups:
            start = offsets[g.name]
            block = inv[
                start : start + g.count * g.dim, start : start + g.count * g.dim
            ]
            block = block.reshape(g.count, g.dim, g.count, g.dim)
            i = np.arange(g.count)
            out[g.name] = block[i, :, i, :]
    return out
