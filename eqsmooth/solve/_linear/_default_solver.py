"""Choosing a linear solver from the graph's structure, and factorisations."""

import lineax as lx

from ...factors import GroupLayout, Var
from .._linearization import Linearization, Tangent
from ._block_tridiagonal import BlockTridiagonal, chain_violation
from ._dense import DenseCholesky
from ._linear_solver import AbstractFactorization, NormalOperator
from ._sparsax import sparsax_available, SparsaxCholesky
from ._sparse import SparseLU


DENSE_LIMIT = 1000
"""Non-chain graphs with at most this many tangent coordinates get
`DenseCholesky()` by default, larger ones `SparseLU()`."""


def default_linear_solver(
    layout: tuple[GroupLayout, ...], variables: tuple[tuple[Var, ...], ...]
) -> lx.AbstractLinearSolver:
    """The linear solver used when none is given, from the (static) structure.

    A chain (every group has one variable per time step and every factor row
    touches steps `t, t + 1` only) gets [`eqsmooth.solve.BlockTridiagonal`][];
    any other graph [`eqsmooth.solve.DenseCholesky`][] up to
    `DENSE_LIMIT` tangent coordinates and beyond that
    [`eqsmooth.solve.SparsaxCholesky`][] when the optional `sparsax` package
    is installed and JAX runs in 64-bit mode, else
    [`eqsmooth.solve.SparseLU`][]. A graph with dynamic indices
    ([`eqsmooth.factors.Var.dynamic`][], as [`eqsmooth.solve.pad_graph`][]
    builds) gets `DenseCholesky()` at any size: the structured solvers read
    the indices at trace time.
    """
    if any(v.is_dynamic for vs in variables for v in vs):
        return DenseCholesky()
    names = tuple(f"factor stack {i}" for i in range(len(variables)))
    if chain_violation(layout, variables, names) is None:
        return BlockTridiagonal()
    size = sum(g.count * g.dim for g in layout)
    if size <= DENSE_LIMIT:
        return DenseCholesky()
    return SparsaxCholesky() if sparsax_available() else SparseLU()


def linear_solver_for(
    linear_solver: lx.AbstractLinearSolver | None, lin: Linearization
) -> lx.AbstractLinearSolver:
    """`linear_solver`, or the default for the structure of `lin` if `None`."""
    if linear_solver is not None:
        return linear_solver
    return default_linear_solver(lin.layout, tuple(fl.variables for fl in lin.factors))


def factorize(
    lin: Linearization,
    solver: lx.AbstractLinearSolver | None = None,
    damping: Tangent | None = None,
) -> AbstractFactorization:
    """The factorisation of `JᵀJ + diag(damping)` that `solver` keeps in its state.

    `None` picks `BlockTridiagonal()` for chains, `SparsaxCholesky()` where it
    is the default solver (large graphs, sparsax installed), `DenseCholesky()`
    otherwise.
    A solver whose state is not an [`eqsmooth.solve.AbstractFactorization`][]
    (iterative, host or lineax solvers) falls back to `DenseCholesky()`.
    Unlike a solve, the factorisation is differentiable by ordinary autodiff.
    """
    if solver is None:
        solver = linear_solver_for(None, lin)
    operator = NormalOperator(lin, damping)
    state = solver.init(operator, {})
    if not isinstance(state, AbstractFactorization):
        state = DenseCholesky().init(operator, {})
    return state
