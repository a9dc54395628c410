from typing import Any, ClassVar

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._linear._default_solver import linear_solver_for
from .._linear._linear_solver import solve_unless
from .._linearization import (
    gradient,
    Linearization,
    linearize_graph,
    retract_values,
    Tangent,
    zeros_tangent,
)
from .._misc import (
    converged_test,
    finite_lin,
    max_abs,
    nan_derivative_if,
    sq_norm,
    tree_where,
)
from .._solution import RESULTS
from ._graph_solver import (
    AbstractConvergingSolver,
    AbstractFixedStepSolver,
    cost_record,
    graph_of,
    record_iteration,
    start,
    to_optx_result,
)


class GaussNewtonState(eqx.Module):
    """The state of [`eqsmooth.solve.GaussNewton`][] and
    [`eqsmooth.solve.FixedStepGaussNewton`][].

    Every iteration linearises once: the first at the initial values, each
    later one at the trial point `x ⊕ δ` of the step solved at the end of the
    iteration before. So the compiled loop holds a single copy of the
    linearisation, and the initial state holds a placeholder (zeros) until
    the first iteration.

    **Fields:**

    - `lin`: the linearisation at the current values (after the first
        iteration).
    - `delta`: the step to try in the next iteration.
    - `step`: iterations run, the first (which only linearises) included.
    - `num_accepted`: steps taken.
    - `done`: converged or failed.
    - `result`: an [`eqsmooth.solve.RESULTS`][] code.
    - `last_step_norm`: `‖δ‖₂` of the last step tried (a diagnostic).
    - `initial_cost`: the cost at the initial values (after the first
        iteration).
    - `cost_history`: the cost after each iteration (its length is the
        `"cost_history_length"` option, 0 by default).
    """

    lin: Linearization
    delta: Tangent
    step: Int[Array, ""]
    num_accepted: Int[Array, ""]
    done: Bool[Array, ""]
    result: RESULTS
    last_step_norm: Float[Array, ""]
    initial_cost: Float[Array, ""]
    cost_history: Float[Array, " H"]


def _init(fn, values, args, options, f_struct, who: str) -> GaussNewtonState:
    lin, done, result, step = start(fn, values, args, options, f_struct, who)
    return GaussNewtonState(
        lin=lin,
        delta=zeros_tangent(lin),
        step=step,
        num_accepted=jnp.array(0),
        done=done,
        result=result,
        last_step_norm=jnp.asarray(jnp.inf, lin.dtype),
        initial_cost=lin.cost.astype(lin.dtype),
        cost_history=cost_record(options, lin.dtype),
    )


def _step(solver, graph, values, state: GaussNewtonState, options, check: bool):
    """One iteration: linearise the trial point, take or refuse it, solve the
    next step. `check=False` never stops on convergence."""
    first = state.step == 0
    trial = tree_where(first, values, retract_values(values, state.delta))
    new_lin = linearize_graph(graph, trial)
    finite = finite_lin(new_lin)
    result = RESULTS.where(
        finite,
        RESULTS.successful,
        RESULTS.where(first, RESULTS.nonfinite_problem, RESULTS.nonlinear_divergence),
    )
    done = ~finite
    if check:
        converged = jnp.where(
            first,
            max_abs(gradient(new_lin)) <= solver.gtol,
            converged_test(
                state.lin.cost,
                new_lin,
                state.delta,
                solver.ftol,
                solver.gtol,
                solver.xtol,
            ),
        )
        done = done | (finite & converged)
    # A failed step is not taken, and nothing is differentiable through it.
    failed = ~finite & ~first
    values = nan_derivative_if(
        failed, tree_where(finite, trial, values), state.lin.cost
    )
    lin = tree_where(finite | first, new_lin, state.lin)
    delta, solved = solve_unless(
        done, linear_solver_for(solver.linear_solver, lin), lin, None, options
    )
    result = RESULTS.where(done | solved, result, RESULTS.linear_solve_failed)
    # A failed solve ends the solve here: no derivative through its values.
    values = nan_derivative_if(~solved, values, lin.cost)
    # Diagnostic only; stopped so that sqrt at a zero step never puts a NaN
    # into masked iterations of an unrolled backward pass.
    step_norm = jnp.where(
        first, jnp.inf, lax.stop_gradient(jnp.sqrt(sq_norm(state.delta)))
    ).astype(lin.dtype)
    new_state = GaussNewtonState(
        lin=lin,
        delta=delta,
        step=state.step + 1,
        num_accepted=state.num_accepted
        + (finite & ~first).astype(state.num_accepted.dtype),
        done=done | ~solved,
        result=result,
        last_step_norm=step_norm,
        initial_cost=jnp.where(first, lin.cost, state.initial_cost),
        cost_history=record_iteration(
            options, state.step, state.cost_history, lin.cost, step_norm
        ),
    )
    return values, new_state, None


def _solver_init(self, fn, y, args, options, f_struct, aux_struct, tags):
    """`init` of both Gauss-Newton solvers (optimistix's signature)."""
    del aux_struct, tags
    return _init(fn, y, args, options, f_struct, type(self).__name__)


def _solver_step(self, fn, y, args, options: dict[str, Any], state, tags):
    """`step` of both Gauss-Newton solvers (`check_steps`: a converging one
    checks each linear solve, a fixed-step one runs its steps whatever they
    give)."""
    del tags  # fn was checked against the graph's residuals in init
    graph = graph_of(args, type(self).__name__)
    return _step(self, graph, y, state, options, check=self.check_steps)


class GaussNewton(AbstractConvergingSolver):
    """Gauss-Newton on the manifold: solve `JᵀJ δ = −Jᵀr`, set `x ← x ⊕ δ`.

    An optimistix least-squares solver (`args` is the graph, see
    [`eqsmooth.solve.AbstractGraphSolver`][]). Converges when the relative
    cost change is at most `ftol`, the largest gradient entry at most
    `gtol`, or the largest step entry at most `xtol` (Ceres-like
    tolerances). Undamped: prefer [`eqsmooth.solve.LevenbergMarquardt`][]
    far from the solution.

    **Arguments:**

    - `linear_solver`: any lineax solver of the
        [`eqsmooth.solve.NormalOperator`][]: `BlockTridiagonal()`, `PCG()`,
        `SparseLU()`, `DenseCholesky()`, or lineax's (`lx.Cholesky()`,
        `lx.CG(rtol, atol)`, ...). `None` (the default) picks one from the
        graph's structure: `BlockTridiagonal()` for chains, else
        `DenseCholesky()` (small) or `SparseLU()`.
    - `ftol`, `gtol`, `xtol`: tolerances.
    """

    linear_solver: lx.AbstractLinearSolver | None = None
    ftol: float = eqx.field(static=True, default=1e-8)
    gtol: float = eqx.field(static=True, default=1e-10)
    xtol: float = eqx.field(static=True, default=1e-10)

    check_steps: ClassVar[bool] = True
    init = _solver_init
    step = _solver_step

    def terminate(self, fn, y, args, options, state: GaussNewtonState, tags):
        del y, args, options, tags  # fn: checked in init
        return state.done, to_optx_result(state.result)

    def finish(self, graph, values, state: GaussNewtonState):
        del graph
        return values, state, state.lin.cost


class FixedStepGaussNewton(AbstractFixedStepSolver):
    """Exactly `num_steps` Gauss-Newton steps (the paper's unrolled solver).

    Reaching `num_steps` is success; no tolerance stops it early, so the
    computation (and its gradient under
    [`eqsmooth.solve.UnrolledAdjoint`][]) is the same for every input. Used
    by the surrogate loss (start at ground truth, K steps). It runs K
    iterations, each one linearisation and one solve; the K-th step is
    taken after the loop (`finish`, or optimistix's `postprocess`), where
    only the cost of the result is evaluated, not its Jacobians (so
    `state.lin` is the linearisation before the last step). A non-finite
    cost there counts as a failed step: the values before it are returned,
    with `RESULTS.nonlinear_divergence`. Through `optx.least_squares` give
    `max_steps >= num_steps`.

    **Arguments:**

    - `linear_solver`: the linear solver (`None`: chosen from the graph, see
        [`eqsmooth.solve.GaussNewton`][]).
    - `num_steps`: K.
    """

    linear_solver: lx.AbstractLinearSolver | None = None
    num_steps: int = eqx.field(static=True, default=3)
    ftol: float = eqx.field(static=True, default=0.0)
    gtol: float = eqx.field(static=True, default=-1.0)
    xtol: float = eqx.field(static=True, default=-1.0)

    def __check_init__(self):
        if self.num_steps < 1:
            raise ValueError(
                f"FixedStepGaussNewton.num_steps must be >= 1, got {self.num_steps}"
            )

    check_steps: ClassVar[bool] = False
    init = _solver_init
    step = _solver_step

    def terminate(
        self, fn, y, args, options, state: GaussNewtonState, tags
    ) -> tuple[Bool[Array, ""], optx.RESULTS]:
        del y, args, options, tags  # fn: checked in init
        done = state.done | (state.step >= self.num_steps)
        return done, to_optx_result(state.result)

    def finish(self, graph, values, state: GaussNewtonState):
        # The K-th step, solved in the last iteration: taken here and
        # linearised, so that the state keeps the linearisation at the
        # returned values (marginals). Where only the values are used (a
        # training loss), the Jacobians are dead code and compiled away.
        take = state.result == RESULTS.successful
        final = retract_values(values, state.delta)
        final_lin = linearize_graph(graph, final)
        cost = final_lin.cost.astype(state.lin.dtype)
        ok = jnp.isfinite(cost)
        failed = take & ~ok
        values = nan_derivative_if(
            failed, tree_where(take & ok, final, values), state.lin.cost
        )
        state = GaussNewtonState(
            initial_cost=state.initial_cost,
            cost_history=state.cost_history,
            lin=tree_where(take & ok, final_lin, state.lin),
            delta=zeros_tangent(state.lin),
            step=state.step + take.astype(state.step.dtype),
            num_accepted=state.num_accepted + (take & ok).astype(state.step.dtype),
            done=state.done | failed,
            result=RESULTS.where(failed, RESULTS.nonlinear_divergence, state.result),
            last_step_norm=jnp.where(
                take, lax.stop_gradient(jnp.sqrt(sq_norm(state.delta))), jnp.inf
            ).astype(state.lin.dtype),
        )
        return values, state, jnp.where(take & ok, cost, state.lin.cost)
