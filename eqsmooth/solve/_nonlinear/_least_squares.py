"""The nonlinear least-squares entry point, [`eqsmooth.solve.least_squares`][].

It runs an eqsmooth [`eqsmooth.solve.AbstractGraphSolver`][] (also usable
through `optx.least_squares(eqs.solve.graph_residuals, solver, values,
args=graph)`) with one of eqsmooth's adjoints (unrolled, truncated, implicit
in tangent coordinates) and adds cost statistics.
"""

import functools as ft
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ...factors import FactorGraph
from ...factors._graph import graph_cost, Values
from ...factors._padding import pad_concrete, PaddedGraph, power_of_two
from .._derivatives import recomputed, refuse_derivative
from .._linear._default_solver import default_linear_solver
from .._linear._dense import DenseCholesky
from .._misc import all_arrays
from .._solution import raise_unless_successful, RESULTS, Solution
from ._adjoint import AbstractAdjoint, ImplicitAdjoint
from ._diagnose import failure_detail
from ._graph_solver import AbstractGraphSolver, HISTORY, VERBOSE
from ._residuals import graph_residuals


def least_squares(
    graph: FactorGraph,
    values: Values,
    solver: optx.AbstractLeastSquaresSolver,
    *,
    max_steps: int = 100,
    adjoint: AbstractAdjoint = ImplicitAdjoint(),
    throw: bool = True,
    verbose: bool = False,
    options: dict[str, Any] | None = None,
    pad_to: Callable[[int], int] | None = power_of_two,
) -> Solution:
    """Minimise the cost of `graph` starting from `values`.

    **Arguments:**

    - `graph`: the [`eqsmooth.factors.FactorGraph`][].
    - `values`: initial values, a dict `{group: stacked states}`.
    - `solver`: an eqsmooth [`eqsmooth.solve.AbstractGraphSolver`][], e.g.
        `GaussNewton()`, `GaussNewton(BlockTridiagonal())` or
        `LevenbergMarquardt(PCG())`. (For optimistix's own solvers, which
        update additively, see [`eqsmooth.solve.tangent_least_squares`][].)
    - `max_steps`: iteration limit (ignored by `FixedStepGaussNewton`, which
        always runs its `num_steps`).
    - `adjoint`: how reverse-mode autodiff differentiates the solve:
        [`eqsmooth.solve.ImplicitAdjoint`][] (the default; implicit function
        theorem at the solution), [`eqsmooth.solve.UnrolledAdjoint`][]
        (through every iteration; the paper's K unrolled steps with
        `FixedStepGaussNewton`) or [`eqsmooth.solve.TruncatedAdjoint`][]
        (through the last few iterations). The forward result is the same.
    - `throw`: raise an `EquinoxRuntimeError` if the solve did not succeed;
        with `throw=False` read `Solution.result`.
    - `verbose`: print cost, damping and step norm at every iteration.
    - `options`: the solver's per-call options (see
        [`eqsmooth.solve.AbstractGraphSolver`][]).
    - `pad_to`: the capacity buckets of graphs solved with dense Cholesky
        (see below): the padded size for a real size, by default
        [`eqsmooth.solve.power_of_two`][]; `None` solves every graph as
        built.

    **Returns:** a [`eqsmooth.solve.Solution`][].

    **Graphs of other sizes compile nothing new.** A graph whose linear
    solve is dense Cholesky (the default for a graph that is not a chain, up
    to `DENSE_LIMIT` tangent coordinates, or `DenseCholesky()` given), called
    with concrete arrays (not under `jit`, `grad` or `vmap`), is solved as
    [`eqsmooth.solve.pad_graph`][]`(graph, values, pad_to)` pads it: each
    factor stack and variable group padded to its bucket on the host, so
    every graph with the same factor and noise types whose sizes fall in
    the same buckets runs one compiled program. The answer is the unpadded
    graph's (the padding adds decoupled identity blocks), `value` holds the
    real variables only, and `state.lin` is the padded graph's linearisation
    (real variables first in each group), which
    [`eqsmooth.solve.marginal_covariances`][] and
    [`eqsmooth.solve.joint_marginal_covariance`][] read through the
    `Solution` for the real variables. Chains, large graphs, other linear
    solvers and traced calls are solved as built.
    """
    if not isinstance(solver, AbstractGraphSolver):
        hint = (
            " (optimistix solvers: use eqsmooth.solve.tangent_least_squares)"
            if isinstance(solver, optx.AbstractLeastSquaresSolver)
            else ""
        )
        raise TypeError(
            f"solver must be an eqsmooth AbstractGraphSolver, got "
            f"{type(solver).__name__}{hint}"
        )
    if not isinstance(adjoint, AbstractAdjoint):
        raise TypeError(
            f"adjoint must be an AbstractAdjoint, got {type(adjoint).__name__}"
        )
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"graph must be a FactorGraph, got {type(graph).__name__}")
    _check_arguments(values, max_steps)
    padded = _padded(graph, values, solver, pad_to)
    if padded is None:
        sol = _dispatch(graph, values, solver, max_steps, adjoint, verbose, options)
    else:
        sol = _dispatch(
            padded.graph, padded.values, solver, max_steps, adjoint, verbose, options
        )
        sol = Solution(
            value=padded.unpad(sol.value),
            result=sol.result,
            stats=sol.stats,
            state=sol.state,
            padding=padded.counts,
        )
    if throw:
        sol = raise_unless_successful(
            sol, lambda result: failure_detail(graph, values, result)
        )
    return sol


_SOLVER_DTYPES = (jnp.float32, jnp.float64)


def _check_arguments(values: Values, max_steps: int) -> None:
    """Trace-time checks of `least_squares`'s arguments, with messages naming
    the argument (instead of an IndexError or a finfo error deep inside)."""
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)):
        raise TypeError(
            f"least_squares: max_steps must be a Python int, got {max_steps!r} "
            f"({type(max_steps).__name__})"
        )
    if max_steps < 1:
        raise ValueError(f"least_squares: max_steps must be >= 1, got {max_steps}")
    if not isinstance(values, dict):
        return  # graph.validate names the problem
    for name, group in values.items():
        for leaf in jax.tree_util.tree_leaves(group):
            dtype = jnp.result_type(leaf)
            if jnp.issubdtype(dtype, jnp.floating) and dtype not in _SOLVER_DTYPES:
                raise TypeError(
                    f"least_squares: values[{name!r}] has dtype {dtype}; the solvers "
                    "work in float32 or float64 (cast with .astype(jnp.float32))"
                )


def _dispatch(graph, values, solver, max_steps, adjoint, verbose, options):
    if not options and all_arrays((graph, values, solver, adjoint)):
        return _least_squares_of_arrays(
            graph, values, solver, adjoint, max_steps=max_steps, verbose=verbose
        )
    return _least_squares(
        graph, values, solver, max_steps, adjoint, verbose, options or {}
    )


def _padded(graph, values, solver, pad_to) -> PaddedGraph | None:
    """The graph padded to `pad_to`'s buckets when that keeps the solve's
    linear solver (dense Cholesky) and needs no traced operation; else
    `None` (solve the graph as built)."""
    if pad_to is None:
        return None
    linear_solver = solver.linear_solver
    if linear_solver is not None and type(linear_solver) is not DenseCholesky:
        return None
    return pad_concrete(graph, values, pad_to, transfer=False, accept=_dense_graph)


def _dense_graph(graph: FactorGraph, values: Values) -> bool:
    """Whether padding keeps `graph`'s default linear solver: dense Cholesky
    (not a chain, not large), static indices and rows in every stack."""
    variables = tuple(f.variables for f in graph.factors)
    if any(v.is_dynamic for vs in variables for v in vs):
        return False  # padded already, or the user's own dynamic indices
    if any(f.num_rows == 0 for f in graph.factors):
        return False
    try:
        layout = graph.validate(values)
    except (TypeError, ValueError):
        return False  # the solve as built reports it
    return type(default_linear_solver(layout, variables)) is DenseCholesky


def _solve(graph, values, solver, max_steps, adjoint, verbose, options):
    """One solve, driven by `optx.least_squares` (the one loop driver: the
    adjoint's `apply` runs it), with eqsmooth's result codes and stats."""
    limit = solver.iteration_limit(max_steps)
    steps_cap = limit - 1 + solver.steps_after_loop()
    linear_solver = solver.linear_solver
    if linear_solver is None:
        linear_solver = default_linear_solver(
            graph.validate(values), tuple(f.variables for f in graph.factors)
        )
        solver = eqx.tree_at(
            lambda s: s.linear_solver, solver, linear_solver, is_leaf=_is_none
        )
    options = {**options, HISTORY: steps_cap + 1, VERBOSE: verbose}
    sol = optx.least_squares(
        graph_residuals,
        solver,
        values,
        args=graph,
        options=options,
        max_steps=limit,
        adjoint=adjoint,
        throw=False,
    )
    stats = sol.stats
    # The state at the returned values (a fixed-step solver takes its last
    # step in postprocess, after the state optimistix returns).
    state = eqx.tree_at(lambda s: s.lin, sol.state, stats["linearization"])
    # Out of iterations without converging: the solver's at-max code.
    result = RESULTS.where(
        ~state.done & (state.result == RESULTS.successful),
        solver.at_max_steps(),
        state.result,
    )
    history = stats["cost_history"]
    if not adjoint.differentiates_iterates():
        # Intermediate iterates have no implicit derivative.
        history = refuse_derivative(state.lin.cost, history, _HISTORY)
    stats = {
        "num_steps": stats["num_steps"],
        "num_accepted": stats["num_accepted"],
        # The initial cost with its own derivative (the loop may have run
        # with gradients stopped, under the implicit adjoint).
        "initial_cost": recomputed((graph, values), stats["initial_cost"], graph_cost),
        # = the cost of the linearisation at the returned values, which
        # carries its derivative under every adjoint.
        "final_cost": state.lin.cost,
        "cost_history": history,
    }
    return Solution(value=sol.value, result=result, stats=stats, state=state)


_HISTORY = (
    "Solution.stats['cost_history'] holds the costs of intermediate iterates, "
    "which have no derivative under ImplicitAdjoint (it differentiates the "
    "solution only): differentiate stats['final_cost'] or stats['initial_cost'], "
    "or solve with UnrolledAdjoint to differentiate every iterate"
)


# Two entry points to one program. When every leaf of the graph, the values,
# the solver and the adjoint is a JAX array (the usual case), `jax.jit`
# dispatches in C++ (flattening, cache lookup), which costs less per call
# than `eqx.filter_jit`'s partition of the arguments into arrays and the rest
# (the performance page measures both). Anything
# else (numpy arrays, Python scalars as leaves, per-call options) goes through
# `eqx.filter_jit`, which treats non-array leaves as static.
_least_squares = eqx.filter_jit(_solve)


@ft.partial(jax.jit, static_argnames=("max_steps", "verbose"))
def _least_squares_of_arrays(graph, values, solver, adjoint, *, max_steps, verbose):
    return _solve(graph, values, solver, max_steps, adjoint, verbose, {})


def _is_none(x) -> bool:
    return x is None
