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
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int, PyTree

from ...factors import FactorGraph
from ...lie import AbstractLieGroup
from .._derivatives import stop_arrays
from .._linearization import Linearization, placeholder_linearization
from .._solution import RESULTS


Values = dict[str, PyTree]


def _residuals(values: Values, graph: FactorGraph) -> tuple[Array, ...]:
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


_AMBIENT = (
    "eqsmooth.solve.graph_residuals was differentiated with respect to Lie-group "
    "values in their ambient coordinates (the stored parameters). That derivative "
    "is not the derivative on the manifold, and an optimality condition written "
    "with it gives wrong gradients. This happens under optimistix's default "
    "adjoint: call optx.least_squares(eqsmooth.solve.graph_residuals, solver, "
    "values, args=graph, adjoint=eqsmooth.ImplicitAdjoint()) (or UnrolledAdjoint / "
    "TruncatedAdjoint), or eqsmooth.least_squares(graph, values, solver); with "
    "optimistix's own solvers use eqsmooth.solve.tangent_least_squares. To "
    "differentiate residuals on the manifold use eqsmooth.linearize or "
    "eqsmooth.solve.TangentResiduals."
)


@eqx.filter_custom_jvp
def _residuals_on_groups(values, graph):
    return _residuals(values, graph)


@_residuals_on_groups.def_jvp
def _residuals_on_groups_jvp(primals, tangents):
    values, graph = primals
    t_values, t_graph = tangents
    if jax.tree_util.tree_leaves(t_values):
        raise ValueError(_AMBIENT)
    return eqx.filter_jvp(lambda g: _residuals(values, g), (graph,), (t_graph,))


def _has_groups(values) -> bool:
    is_group = lambda x: isinstance(x, AbstractLieGroup)
    leaves = jax.tree_util.tree_leaves(values, is_leaf=is_group)
    return any(is_group(x) for x in leaves)


def graph_residuals(
    values: Values, graph: FactorGraph
) -> tuple[Float[Array, "_n _m"], ...]:
    """Residuals of every factor stack whose half squared norm is the graph's cost.

    The residual function to pass to `optx.least_squares` together with
    `args=graph` and an eqsmooth solver: `½ Σ‖r‖² = graph.cost(values)`.
    Gaussian factors give their whitened residuals; a robust noise model
    scales row `i` by `√(ρ(sᵢ)/sᵢ)` (`sᵢ` its squared whitened norm; `√ρ'(0)`
    at `sᵢ = 0`).

    Differentiable with respect to the graph. With respect to `values` it is
    differentiable only where they are Euclidean (arrays): for Lie-group
    values, a derivative in the ambient coordinates of the stored parameters
    is not a derivative on the manifold (optimistix's default
    `optx.ImplicitAdjoint` would build a wrong optimality condition from
    it), so asking for one raises a `ValueError` that says what to use
    instead ([`eqsmooth.solve.linearize`][], [`eqsmooth.solve.TangentResiduals`][],
    or an eqsmooth adjoint).

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
    if _has_groups(values):
        return _residuals_on_groups(values, graph)
    return _residuals(values, graph)


def manifold_residuals(values: Values, graph: FactorGraph) -> tuple[Array, ...]:
    """`graph_residuals` without the ambient-derivative guard, for callers whose
    values are already on the manifold's chart (e.g. `x̄ ⊕ δ`)."""
    return _residuals(values, graph)


# Per-call options eqsmooth's driver sets (optimistix's `options` dict):
# the length of the per-iteration cost record, whether to print each
# iteration, and that `fn` is `graph_residuals` itself (optimistix hands the
# solvers a wrapped copy, so they cannot see it).
HISTORY = "cost_history_length"
VERBOSE = "verbose"
FN_IS_GRAPH_RESIDUALS = "fn_is_graph_residuals"


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


def _fn_mismatch(fn, y, graph: FactorGraph, who: str) -> Bool[Array, ""] | None:
    """Whether `fn(y, graph)` differs from the graph's residuals (None when `fn` is
    `graph_residuals` itself). The solvers linearise the graph, not `fn`, so a
    different `fn` would be silently ignored: its shapes are checked here at
    trace time and its values at run time, at the initial values."""
    if fn is graph_residuals or fn is manifold_residuals:
        return None
    y, graph = stop_arrays((y, graph))
    out = fn(y, graph)
    want = _residuals(y, graph)
    # optimistix wraps `fn` so that it returns `(residuals, aux)`.
    wrapped = isinstance(out, tuple) and len(out) == 2
    if wrapped and jax.tree_util.tree_structure(out) != jax.tree_util.tree_structure(
        want
    ):
        out = out[0]
    got = out
    got_leaves = jax.tree_util.tree_leaves(got)
    hint = (
        f"{who} solves the factor graph passed as args, so its fn must be "
        "eqsmooth.solve.graph_residuals (the graph's own residuals); for another "
        "residual function use optimistix's solvers, or "
        "eqsmooth.solve.tangent_least_squares for Lie-group values"
    )
    if len(got_leaves) != len(want) or any(
        jnp.shape(a) != jnp.shape(b) for a, b in zip(got_leaves, want)
    ):
        raise ValueError(
            f"{hint}; fn returned shapes {[jnp.shape(a) for a in got_leaves]}, the "
            f"graph's residuals have shapes {[jnp.shape(b) for b in want]}"
        )
    dtype = jnp.result_type(*want)
    tol = float(np.sqrt(np.finfo(dtype).eps))
    bad = jnp.array(False)
    for a, b in zip(got_leaves, want):
        scale = 1.0 + jnp.max(jnp.abs(b), initial=0.0)
        bad = bad | ~(jnp.max(jnp.abs(a - b), initial=0.0) <= tol * scale)
    return bad


def checked_graph(
    fn, y, args, who: str, options=None
) -> tuple[FactorGraph, Bool[Array, ""] | None]:
    """`args` as the factor graph, and whether `fn` is not its residual function
    (for an `eqx.error_if` on the solver's initial state)."""
    graph = graph_of(args, who)
    if options is not None and options.get(FN_IS_GRAPH_RESIDUALS, False):
        return graph, None
    return graph, _fn_mismatch(fn, y, graph, who)


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
    step: Int[Array, ""]  # 0, with the check of `fn` attached


def start(fn, values, args, options, f_struct, who: str) -> Start:
    """The shared beginning of the solvers' `init`: the graph passed as
    `args` (and `fn` checked against it), a placeholder linearisation shaped
    from optimistix's `f_struct` (no trace of the linearisation for shapes),
    and the initial `done`/`result` (`initial_status`)."""
    graph, mismatch = checked_graph(fn, values, args, who, options)
    lin = placeholder_linearization(graph, values, f_struct)
    done, result = initial_status(values)
    # No cost before the first linearisation: NaN where the solve ends
    # before it (non-finite initial values).
    no_cost = jnp.where(done, jnp.nan, 0.0).astype(lin.cost.dtype)
    lin = eqx.tree_at(lambda x: x.cost, lin, no_cost)
    return Start(lin, done, result, fn_error_if(jnp.array(0), mismatch, who))


def fn_error_if(x, mismatch: Bool[Array, ""] | None, who: str):
    """`x`, raising at run time where `fn` was not the graph's residual function."""
    if mismatch is None:
        return x
    return eqx.error_if(
        x,
        mismatch,
        f"{who} solves the factor graph passed as args: its fn must be "
        "eqsmooth.solve.graph_residuals, and the fn given returned other residuals "
        "at the initial values (use optimistix's solvers for another residual "
        "function)",
    )


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
    return optx.RESULTS.where(
        result == RESULTS.nonfinite_problem, optx.RESULTS.nonfinite, out
    )


class AbstractGraphSolver(optx.AbstractLeastSquaresSolver):
    """Base of eqsmooth's nonlinear solvers: optimistix least-squares solvers on graphs.

    Subclasses implement optimistix's `init`, `step` and `terminate` with
    `fn` [`eqsmooth.solve.graph_residuals`][] (any other `fn` raises: the
    solvers linearise the graph itself), `args` the
    [`eqsmooth.factors.FactorGraph`][] and `y` the values dict. They
    linearise every factor stack with forward-mode autodiff, hand a
    [`eqsmooth.solve.NormalOperator`][] to their lineax `linear_solver` and
    update the values on the manifold (`x ⊕ δ`). Their states keep `lin`,
    the linearisation at the current values (the adjoints of
    [`eqsmooth.solve.least_squares`][] rely on it), `step`, `num_accepted`,
    `done` and `result` (an [`eqsmooth.solve.RESULTS`][] code).

    `options` (optimistix's per-call knobs): `"linear_options"` is passed to
    `lineax.linear_solve` at every step; `"cost_history_length"` (an int)
    sizes the per-iteration cost record of `stats["cost_history"]`;
    `"verbose"` prints every iteration. `postprocess` returns the stats
    `num_steps`, `num_accepted`, `initial_cost`, `final_cost`,
    `cost_history` and `linearization` (the linearisation at the returned
    values).
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
        del tags, result  # fn: checked in init
        y, state, cost = self.finish(graph_of(args, type(self).__name__), y, state)
        steps = jnp.maximum(state.step - 1, 0)
        # The cost record: entry i is the cost after step i (0: the initial
        # values), padded with the final cost.
        history = state.cost_history
        if history.shape[0]:
            history = history.at[steps].set(cost, mode="drop")
            history = jnp.where(jnp.arange(history.shape[0]) <= steps, history, cost)
        stats = {
            "num_steps": steps,
            "num_accepted": state.num_accepted,
            "initial_cost": state.initial_cost,
            "final_cost": cost,
            "cost_history": history,
            # optimistix returns the state of the last iteration; a
            # fixed-step solver takes its last step here, after it.
            "linearization": state.lin,
        }
        return y, aux, stats

    @abc.abstractmethod
    def finish(self, graph: FactorGraph, values: Values, state) -> tuple:
        """After the last iteration: `(values, state, final_cost)` of the
        solution, with `state.lin` the linearisation at the returned values.
        [`eqsmooth.solve.GaussNewton`][] and
        [`eqsmooth.solve.LevenbergMarquardt`][] return the values and the
        cost of their last linearisation; [`eqsmooth.solve.FixedStepGaussNewton`][]
        takes its last step here (see
        [`eqsmooth.solve.AbstractGraphSolver.steps_after_loop`][])."""

    @abc.abstractmethod
    def iteration_limit(self, max_steps: int) -> int:
        """The static iteration limit of a solve called with `max_steps`."""

    @abc.abstractmethod
    def steps_after_loop(self) -> int:
        """How many steps `finish` takes after the last iteration."""

    @abc.abstractmethod
    def at_max_steps(self) -> RESULTS:
        """The result when the iteration limit is reached before convergence."""

    @abc.abstractmethod
    def reaches_minimum(self) -> bool:
        """Whether the solve runs to a stationary point of the cost (which the
        implicit adjoint differentiates)."""


class AbstractConvergingSolver(AbstractGraphSolver):
    """A solver that iterates until its tolerances are met (or `max_steps`).

    One iteration more than steps: the first iteration only linearises the
    initial values (and solves for the first step), so the iteration limit
    is `max_steps + 1`; reaching it before convergence gives
    `RESULTS.nonlinear_max_steps_reached`. No step is taken after the loop.
    """

    def iteration_limit(self, max_steps: int) -> int:
        return max_steps + 1

    def steps_after_loop(self) -> int:
        return 0

    def at_max_steps(self) -> RESULTS:
        return RESULTS.nonlinear_max_steps_reached

    def reaches_minimum(self) -> bool:
        return True


class AbstractFixedStepSolver(AbstractGraphSolver):
    """A solver that always runs exactly `num_steps` iterations.

    [`eqsmooth.solve.least_squares`][] ignores its `max_steps` argument for
    these solvers; reaching `num_steps` is success. The last step is taken
    after the loop, in `finish`. The result is not a minimiser, so
    [`eqsmooth.solve.ImplicitAdjoint`][] refuses these solvers.
    """

    num_steps: eqx.AbstractVar[int]

    def iteration_limit(self, max_steps: int) -> int:
        del max_steps
        return self.num_steps

    def steps_after_loop(self) -> int:
        return 1

    def at_max_steps(self) -> RESULTS:
        return RESULTS.successful

    def reaches_minimum(self) -> bool:
        return False
