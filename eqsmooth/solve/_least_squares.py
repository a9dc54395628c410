"""The nonlinear least-squares entry point and the base of its solvers.

eqsmooth's solvers ([`eqsmooth.solve.GaussNewton`][],
[`eqsmooth.solve.LevenbergMarquardt`][],
[`eqsmooth.solve.FixedStepGaussNewton`][]) are optimistix least-squares
solvers whose `args` is the [`eqsmooth.factors.FactorGraph`][] and whose `y`
is the values dict; they update the values on the manifold (`x ⊕ δ`).
They run through `optx.least_squares(eqs.solve.graph_residuals, solver,
values, args=graph)` and through [`eqsmooth.solve.least_squares`][], which
adds eqsmooth's adjoints (unrolled, truncated, implicit in tangent
coordinates) and cost statistics.
"""

import abc
import functools as ft
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float, PyTree

from ..factors import FactorGraph
from ._adjoint import AbstractAdjoint, ImplicitAdjoint
from ._default_solver import default_linear_solver
from ._solution import raise_unless_successful, RESULTS, Solution


Values = dict[str, PyTree]


def graph_residuals(
    values: Values, graph: FactorGraph
) -> tuple[Float[Array, "_n _m"], ...]:
    """Residuals of every factor stack whose half squared norm is the graph's cost.

    The residual function to pass to `optx.least_squares` together with
    `args=graph`: `½ Σ‖r‖² = graph.cost(values)`. Gaussian factors give their
    whitened residuals; a robust noise model scales row `i` by
    `√(ρ(sᵢ)/sᵢ)` (`sᵢ` its squared whitened norm; `√ρ'(0)` at `sᵢ = 0`).

    **Arguments:**

    - `values`: the values dict `{group: stacked states}`.
    - `graph`: the [`eqsmooth.factors.FactorGraph`][].

    **Returns:** a tuple of `(n, m)` arrays, one per factor stack.
    """
    if not isinstance(graph, FactorGraph):
        raise TypeError(
            f"graph_residuals(values, graph): graph must be a FactorGraph, got "
            f"{type(graph).__name__}"
        )
    out = []
    for f, rw in zip(graph.factors, graph.whitened_residuals(values)):
        s = jnp.sum(rw * rw, axis=1)
        positive = s > 0
        safe = jnp.where(positive, s, 1.0)
        rho, _ = f.noise.rho(safe)
        _, drho0 = f.noise.rho(jnp.zeros_like(s))
        scale = jnp.where(positive, jnp.sqrt(rho / safe), jnp.sqrt(drho0))
        out.append(rw * scale[:, None])
    return tuple(out)


def graph_of(args: Any, who: str) -> FactorGraph:
    """The factor graph passed as optimistix's `args`."""
    if not isinstance(args, FactorGraph):
        raise TypeError(
            f"{who} solves an eqsmooth factor graph: call optx.least_squares("
            "eqsmooth.solve.graph_residuals, solver, values, args=graph), or "
            f"eqsmooth.least_squares(graph, values, solver); got args of type "
            f"{type(args).__name__}"
        )
    return args


def to_optx_result(result: RESULTS) -> optx.RESULTS:
    """An eqsmooth result code as the nearest `optimistix.RESULTS` code."""
    out = optx.RESULTS.successful
    for item in optx.RESULTS._name_to_item.values():  # pyright: ignore
        out = optx.RESULTS.where(result == RESULTS.promote(item), item, out)
    out = optx.RESULTS.where(
        result == RESULTS.linear_solve_failed, optx.RESULTS.singular, out
    )
    return optx.RESULTS.where(
        result == RESULTS.nonfinite_problem, optx.RESULTS.nonfinite, out
    )


class AbstractGraphSolver(optx.AbstractLeastSquaresSolver):
    """Base of eqsmooth's nonlinear solvers: optimistix least-squares solvers on graphs.

    Subclasses implement optimistix's `init`, `step` and `terminate` with
    `args` the [`eqsmooth.factors.FactorGraph`][] and `y` the values dict.
    They linearise every factor stack with forward-mode autodiff, hand a
    [`eqsmooth.solve.NormalOperator`][] to their lineax `linear_solver` and
    update the values on the manifold (`x ⊕ δ`). Their states keep `lin`,
    the linearisation at the current values (the adjoints of
    [`eqsmooth.solve.least_squares`][] rely on it), `step`, `num_accepted`,
    `done` and `result` (an [`eqsmooth.solve.RESULTS`][] code).

    `options` (optimistix's per-call knobs): `"linear_options"` is passed to
    `lineax.linear_solve` at every step.
    """

    linear_solver: eqx.AbstractVar[lx.AbstractLinearSolver | None]
    ftol: eqx.AbstractVar[float]
    gtol: eqx.AbstractVar[float]
    xtol: eqx.AbstractVar[float]

    # optimistix's names for the tolerances and the norm of its solvers.
    @property
    def rtol(self) -> float:
        return self.ftol

    @property
    def atol(self) -> float:
        return self.xtol

    @property
    def norm(self):
        return optx.max_norm

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, options, tags, result
        y, state, cost = self.finish(graph_of(args, type(self).__name__), y, state)
        return y, aux, {"num_accepted": state.num_accepted, "final_cost": cost}

    @abc.abstractmethod
    def finish(self, graph: FactorGraph, values: Values, state) -> tuple:
        """After the last iteration: `(values, state, final_cost)` of the
        solution. [`eqsmooth.solve.GaussNewton`][] and
        [`eqsmooth.solve.LevenbergMarquardt`][] return the values and the
        cost of their last linearisation; [`eqsmooth.solve.FixedStepGaussNewton`][]
        takes its last step here (see
        [`eqsmooth.solve.AbstractGraphSolver.steps_after_loop`][])."""

    def iteration_limit(self, max_steps: int) -> int:
        """The static iteration limit of a solve called with `max_steps`.

        One iteration more than steps, since the first iteration only
        linearises the initial values (and solves for the first step):
        `max_steps + 1`. An [`eqsmooth.solve.AbstractFixedStepSolver`][]
        always runs its `num_steps` iterations (and takes its last step in
        `finish`). [`eqsmooth.solve.UnrolledAdjoint`][] scans this many
        iterations.
        """
        if isinstance(self, AbstractFixedStepSolver):
            return self.num_steps
        return max_steps + 1

    def steps_after_loop(self) -> int:
        """How many steps `finish` takes after the last iteration: 1 for an
        [`eqsmooth.solve.AbstractFixedStepSolver`][] (its last step), else 0.
        [`eqsmooth.solve.TruncatedAdjoint`][] replays that many iterations
        fewer."""
        return 1 if isinstance(self, AbstractFixedStepSolver) else 0

    def at_max_steps(self) -> RESULTS:
        """The result when the iteration limit is reached before convergence
        (success for an [`eqsmooth.solve.AbstractFixedStepSolver`][])."""
        if isinstance(self, AbstractFixedStepSolver):
            return RESULTS.successful
        return RESULTS.nonlinear_max_steps_reached


class AbstractFixedStepSolver(AbstractGraphSolver):
    """A solver that always runs exactly `num_steps` iterations.

    [`eqsmooth.solve.least_squares`][] ignores its `max_steps` argument for
    these solvers (see
    [`eqsmooth.solve.AbstractGraphSolver.iteration_limit`][]); reaching
    `num_steps` is success.
    """

    num_steps: eqx.AbstractVar[int]


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
    steps_cap = (
        solver.num_steps if isinstance(solver, AbstractFixedStepSolver) else max_steps
    )
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

    values, state, history = adjoint.run(
        init, body, cond, graph, values, linear_solver, limit, solver.steps_after_loop()
    )
    values, state, final_cost = solver.finish(graph, values, state)
    steps = jnp.maximum(state.step - 1, 0)
    history = history.at[steps].set(final_cost)
    history = jnp.where(jnp.arange(steps_cap + 1) <= steps, history, final_cost)
    result = state.result
    stats = {
        "num_steps": steps,
        "num_accepted": state.num_accepted,
        "initial_cost": history[0],
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


def _is_none(x) -> bool:
    return x is None
