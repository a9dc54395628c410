"""The base of eqsmooth's nonlinear solvers and the residual function they solve.

eqsmooth's solvers ([`eqsmooth.solve.GaussNewton`][],
[`eqsmooth.solve.LevenbergMarquardt`][],
[`eqsmooth.solve.FixedStepGaussNewton`][]) are optimistix least-squares
solvers whose `args` is the [`eqsmooth.factors.FactorGraph`][], whose `y` is
the values dict and whose `fn` is [`eqsmooth.solve.graph_residuals`][]; they
update the values on the manifold (`x ⊕ δ`).
"""

import abc
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float

from ...factors import FactorGraph
from ...factors._graph import Values
from .._linearization import Linearization, placeholder_linearization
from .._solution import RESULTS
from ._fn_check import fn_mismatch
from ._stopping import AbstractStopping


# Per-call options eqsmooth's driver sets (optimistix's `options` dict):
# the length of the per-iteration cost record and whether to print each
# iteration.
HISTORY = "cost_history_length"
VERBOSE = "verbose"


def cost_record(options, dtype) -> Float[Array, " H"]:
    """The empty per-iteration cost record of a solver state."""
    return jnp.zeros((int(options.get(HISTORY, 0)),), dtype)


def record_iteration(options, state_step, history, cost, step_norm, damping=None):
    """The cost after iteration `state_step` written into `history` (and
    printed when `options["verbose"]`)."""
    if options.get(VERBOSE, False):
        jax.debug.print(
            "step {step:4d}  cost {cost:.6e}  damping {lam:.2e}  |δ| {dx:.2e}",
            step=state_step,
            cost=cost,
            lam=jnp.zeros(()) if damping is None else damping,
            dx=step_norm,
        )
    if history.shape[0] == 0:
        return history
    return history.at[state_step].set(cost.astype(history.dtype), mode="drop")


def graph_of(args, who: str) -> FactorGraph:
    """The factor graph passed as optimistix's `args`."""
    if not isinstance(args, FactorGraph):
        raise TypeError(
            f"{who} solves an eqsmooth factor graph: call optx.least_squares("
            "eqsmooth.solve.graph_residuals, solver, values, args=graph), or "
            f"eqsmooth.least_squares(graph, values, solver); got args of type "
            f"{type(args).__name__}"
        )
    return args


def initial_status(values: Values) -> tuple[Bool[Array, ""], RESULTS]:
    """`(done, result)` of a solver's initial state.

    Initial values that are not finite end the solve before its first
    iteration with `RESULTS.nonfinite_problem` (optimistix's loop does not
    start on them either). Both are computed from the values, so they are
    traced under `jit`: optimistix calls `terminate` on the initial state,
    and on constants (`RESULTS.successful` is one) its operations would run
    eagerly, one small XLA compilation each in a fresh process.
    """
    finite = jnp.array(True)
    for leaf in jax.tree_util.tree_leaves(values):
        finite = finite & jnp.all(jnp.isfinite(leaf))
    return ~finite, RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_problem)


class Start(NamedTuple):
    """What every eqsmooth solver's initial state starts from."""

    lin: Linearization  # placeholder zeros; cost NaN where `done`
    done: Bool[Array, ""]
    result: RESULTS


def start(fn, values, args, options, f_struct, who: str) -> Start:
    """The shared beginning of the solvers' `init`: the graph passed as
    `args` (and `fn` checked against it), a placeholder linearisation shaped
    from optimistix's `f_struct` (no trace of the linearisation for shapes),
    and the initial `done`/`result` (`initial_status`)."""
    del options
    graph = graph_of(args, who)
    lin = placeholder_linearization(graph, values, f_struct)
    mismatch = fn_mismatch(fn, values, graph, lin, who)
    done, result = initial_status(values)
    if mismatch is not None:
        # A result code, not an error callback: the compiled solve holds no
        # host callback, and `throw` raises with the code's message.
        result = RESULTS.where(mismatch, RESULTS.fn_not_graph_residuals, result)
        done = done | mismatch
    # No cost before the first linearisation: NaN where the solve ends
    # before it (non-finite initial values, another fn).
    no_cost = jnp.where(done, jnp.nan, 0.0).astype(lin.cost.dtype)
    lin = eqx.tree_at(lambda x: x.cost, lin, no_cost)
    return Start(lin, done, result)


_OPTX_CODES = (
    "successful",
    "nonlinear_max_steps_reached",
    "nonlinear_divergence",
    "singular",
    "nonfinite",
)


def to_optx_result(result: RESULTS) -> optx.RESULTS:
    """An eqsmooth result code as the nearest `optimistix.RESULTS` code."""
    # Compared with eqsmooth's own item of the same name: `RESULTS.promote`
    # of a constant would be evaluated eagerly at trace time (several tiny
    # compilations in every fresh process).
    out = optx.RESULTS.nonlinear_divergence
    for name in _OPTX_CODES:
        out = optx.RESULTS.where(
            result == getattr(RESULTS, name), getattr(optx.RESULTS, name), out
        )
    out = optx.RESULTS.where(
        result == RESULTS.linear_solve_failed, optx.RESULTS.singular, out
    )
    # Another fn: the solve did not start. optimistix has no code for it;
    # the state's eqsmooth code (`Solution.state.result`) names it.
    out = optx.RESULTS.where(
        result == RESULTS.fn_not_graph_residuals, optx.RESULTS.nonlinear_divergence, out
    )
    return optx.RESULTS.where(
        result == RESULTS.nonfinite_problem, optx.RESULTS.nonfinite, out
    )


class AbstractGraphSolver(optx.AbstractLeastSquaresSolver):
    """Base of eqsmooth's nonlinear solvers: optimistix least-squares solvers on graphs.

    Subclasses implement optimistix's `init`, `step` and `terminate` with
    `fn` [`eqsmooth.solve.graph_residuals`][] (any other `fn` raises: the
    solvers linearise the graph itself), `args` the
    [`eqsmooth.factors.FactorGraph`][] and `y` the values dict, plus `finish`
    (what happens after the last iteration) and a `stopping` policy
    ([`eqsmooth.solve.AbstractStopping`][]). They linearise every factor
    stack with forward-mode autodiff, hand a
    [`eqsmooth.solve.NormalOperator`][] to their lineax `linear_solver` and
    update the values on the manifold (`x ⊕ δ`). Their states keep `lin`,
    the linearisation at the current values, `step`, `num_accepted`, `done`,
    `result` (an [`eqsmooth.solve.RESULTS`][] code), `initial_cost` and
    `cost_history`.

    `options` (optimistix's per-call knobs): `"linear_options"` is passed to
    `lineax.linear_solve` at every step; `"cost_history_length"` (an int)
    sizes the per-iteration cost record of `stats["cost_history"]`;
    `"verbose"` prints every iteration. `postprocess` returns the stats
    `num_steps`, `num_accepted`, `initial_cost`, `final_cost`,
    `cost_history` and `linearization` (the linearisation at the returned
    values, differentiable under every eqsmooth adjoint).
    """

    linear_solver: eqx.AbstractVar[lx.AbstractLinearSolver | None]
    stopping: eqx.AbstractVar[AbstractStopping]

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, options, tags, result  # fn: checked in init
        y, state, cost = self.finish(graph_of(args, type(self).__name__), y, state)
        return y, aux, solve_stats(state, cost)

    @abc.abstractmethod
    def finish(self, graph: FactorGraph, values: Values, state) -> tuple:
        """After the last iteration: `(values, state, final_cost)` of the
        solution, with `state.lin` the linearisation at the returned values.
        A converging solver returns the values and the cost of its last
        linearisation; [`eqsmooth.solve.FixedStepGaussNewton`][] takes its
        last step here (see [`eqsmooth.solve.AbstractStopping`][])."""

    # optimistix's names for the tolerances and the norm of its solvers.
    @property
    def rtol(self) -> float:
        return self.stopping.relative_tolerance()

    @property
    def atol(self) -> float:
        return self.stopping.absolute_tolerance()

    @property
    def norm(self):
        return optx.max_norm

    def iteration_limit(self, max_steps: int) -> int:
        """The static iteration limit of a solve called with `max_steps`."""
        return self.stopping.iteration_limit(max_steps)

    def steps_after_loop(self) -> int:
        """How many steps `finish` takes after the last iteration."""
        return self.stopping.steps_after_loop()

    def at_max_steps(self) -> RESULTS:
        """The result when the iteration limit is reached before convergence."""
        return self.stopping.at_max_steps()

    def reaches_minimum(self) -> bool:
        """Whether the solve runs to a stationary point of the cost (which the
        implicit adjoint differentiates)."""
        return self.stopping.reaches_minimum()


def solve_stats(state, cost) -> dict:
    """The stats `postprocess` returns for the solution's `state` and cost."""
    steps = jnp.maximum(state.step - 1, 0)
    # The cost record: entry i is the cost after step i (0: the initial
    # values), padded with the final cost.
    history = state.cost_history
    if history.shape[0]:
        history = history.at[steps].set(cost, mode="drop")
        history = jnp.where(jnp.arange(history.shape[0]) <= steps, history, cost)
    return {
        "num_steps": steps,
        "num_accepted": state.num_accepted,
        "initial_cost": state.initial_cost,
        "final_cost": cost,
        "cost_history": history,
        # optimistix returns the state of the last iteration; a fixed-step
        # solver takes its last step in `finish`, after it.
        "linearization": state.lin,
    }
