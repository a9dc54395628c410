"""The nonlinear least-squares entry point, [`eqsmooth.solve.least_squares`][].

It runs an eqsmooth [`eqsmooth.solve.AbstractGraphSolver`][] (also usable
through `optx.least_squares(eqs.solve.graph_residuals, solver, values,
args=graph)`) with one of eqsmooth's adjoints (unrolled, truncated, implicit
in tangent coordinates) and adds cost statistics.
"""

import functools as ft
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import PyTree

from ..factors import FactorGraph
from ..factors._graph import graph_cost
from ._adjoint import AbstractAdjoint, ImplicitAdjoint
from ._default_solver import default_linear_solver
from ._derivatives import checked_derivative, recomputed
from ._graph_solver import AbstractGraphSolver, graph_residuals
from ._misc import stationary
from ._solution import raise_unless_successful, RESULTS, Solution


Values = dict[str, PyTree]


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

    **Returns:** a [`eqsmooth.solve.Solution`][].
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
    if not options and _all_arrays((graph, values, solver, adjoint)):
        sol = _least_squares_of_arrays(
            graph, values, solver, adjoint, max_steps=max_steps, verbose=verbose
        )
    else:
        sol = _least_squares(
            graph, values, solver, max_steps, adjoint, verbose, options or {}
        )
    if throw:
        sol = raise_unless_successful(sol)
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


def _all_arrays(tree) -> bool:
    return all(isinstance(x, jax.Array) for x in jax.tree_util.tree_leaves(tree))


def _solve(graph, values, solver, max_steps, adjoint, verbose, options):
    limit = solver.iteration_limit(max_steps)
    steps_cap = limit - 1 + solver.steps_after_loop()
    at_max = solver.at_max_steps()
    linear_solver = solver.linear_solver
    if linear_solver is None:
        linear_solver = default_linear_solver(
            graph.validate(values), tuple(f.variables for f in graph.factors)
        )
        solver = eqx.tree_at(
            lambda s: s.linear_solver, solver, linear_solver, is_leaf=_is_none
        )
    tags = frozenset()

    def init(graph, values):
        state = solver.init(graph_residuals, values, graph, options, None, None, tags)
        # Filled by the iterations: entry i is the cost after step i (entry 0
        # at the initial values, from the first iteration).
        history = jnp.zeros((steps_cap + 1,), state.lin.cost.dtype)
        return values, state, history

    def body(graph, carry):
        values, state, history = carry
        new_values, new_state, _ = solver.step(
            graph_residuals, values, graph, options, state, tags
        )
        # Out of steps without converging: stop with the solver's at-max code.
        out = (new_state.step >= limit) & ~new_state.done
        result = RESULTS.where(
            out & (new_state.result == RESULTS.successful), at_max, new_state.result
        )
        new_state = eqx.tree_at(
            lambda s: (s.done, s.result), new_state, (new_state.done | out, result)
        )
        if verbose:
            jax.debug.print(
                "step {step:4d}  cost {cost:.6e}  damping {lam:.2e}  |δ| {dx:.2e}",
                step=new_state.step - 1,
                cost=new_state.lin.cost,
                lam=getattr(new_state, "damping", jnp.zeros(())),
                dx=new_state.last_step_norm,
            )
        history = history.at[new_state.step - 1].set(new_state.lin.cost)
        return new_values, new_state, history

    def cond(carry):
        _, state, _ = carry
        return ~state.done & (state.step < limit)

    values0 = values
    values, state, history = adjoint.run(
        init, body, cond, graph, values, linear_solver, limit, solver.steps_after_loop()
    )
    if isinstance(adjoint, ImplicitAdjoint) and not solver.reaches_minimum():
        values = checked_derivative(
            values, state.lin, _not_stationary, _implicit_refusal(solver)
        )
    values, state, final_cost = solver.finish(graph, values, state)
    steps = jnp.maximum(state.step - 1, 0)
    history = history.at[steps].set(final_cost)
    history = jnp.where(jnp.arange(steps_cap + 1) <= steps, history, final_cost)
    result = state.result
    # The initial cost with its own derivative (the loop's copy may have been
    # computed with gradients stopped, under the implicit adjoint).
    initial_cost = recomputed((graph, values0), history[0], graph_cost)
    stats = {
        "num_steps": steps,
        "num_accepted": state.num_accepted,
        "initial_cost": initial_cost,
        "final_cost": final_cost,
        "cost_history": history,
    }
    return Solution(value=values, result=result, stats=stats, state=state)


# Two entry points to one program. When every leaf of the graph, the values,
# the solver and the adjoint is a JAX array (the usual case), `jax.jit`
# dispatches in C++ (flattening, cache lookup), which takes about half a
# millisecond less per call than `eqx.filter_jit`'s partition of the
# arguments into arrays and the rest (`benchmarks/small_graph.py`). Anything
# else (numpy arrays, Python scalars as leaves, per-call options) goes through
# `eqx.filter_jit`, which treats non-array leaves as static.
_least_squares = eqx.filter_jit(_solve)


@ft.partial(jax.jit, static_argnames=("max_steps", "verbose"))
def _least_squares_of_arrays(graph, values, solver, adjoint, *, max_steps, verbose):
    return _solve(graph, values, solver, max_steps, adjoint, verbose, {})


def _not_stationary(lin):
    return ~stationary(lin)


def _implicit_refusal(solver) -> str:
    return (
        "ImplicitAdjoint (least_squares's default adjoint) differentiates the "
        f"optimality condition at a minimum, but this {type(solver).__name__} "
        "solve stopped after its fixed number of steps short of a stationary "
        "point, so an implicit gradient would be wrong: pass "
        "adjoint=eqsmooth.UnrolledAdjoint() (the paper's K unrolled steps) or "
        "TruncatedAdjoint(k), or use a converging solver "
        "(GaussNewton, LevenbergMarquardt)"
    )


def _is_none(x) -> bool:
    return x is None
