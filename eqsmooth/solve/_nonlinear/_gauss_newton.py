"""The Gauss-Newton family: one solver, one state, one iteration; a descent
(undamped or damped) and a stopping policy (tolerances or a fixed number of
steps) make Gauss-Newton, Levenberg-Marquardt and the unrolled fixed-step
solver."""

from typing import Any

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from .._linear._default_solver import linear_solver_for
from .._linear._linear_solver import solve_unless
from .._linearization import (
    Linearization,
    linearize_graph,
    retract_values,
    Tangent,
    zeros_tangent,
)
from .._misc import finite_lin, nan_derivative_if, sq_norm, tree_where
from .._solution import RESULTS
from ._descent import AbstractDescent, check_damping, DampedDescent, UndampedDescent
from ._graph_solver import (
    AbstractGraphSolver,
    cost_record,
    graph_of,
    record_iteration,
    start,
    to_optx_result,
)
from ._stopping import (
    AbstractStopping,
    check_num_steps,
    check_tolerances,
    FixedSteps,
    Tolerances,
)


class GaussNewtonState(eqx.Module):
    """The state of every Gauss-Newton-family solver
    ([`eqsmooth.solve.GaussNewton`][], [`eqsmooth.solve.LevenbergMarquardt`][],
    [`eqsmooth.solve.FixedStepGaussNewton`][]).

    Every iteration linearises once: the first at the initial values, each
    later one at the trial point `x ⊕ δ` of the step solved at the end of the
    iteration before. So the compiled loop holds a single copy of the
    linearisation, and the initial state holds a placeholder (zeros) until
    the first iteration.

    **Fields:**

    - `lin`: the linearisation at the current values (after the first
        iteration).
    - `delta`: the step to try in the next iteration.
    - `solved`: whether `delta` came from a successful linear solve.
    - `step`: iterations run, the first (which only linearises) included.
    - `num_accepted`: steps taken.
    - `damping`: λ of the next solve (0 for an undamped descent).
    - `nu`: the factor λ grows by on the next rejection.
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
    solved: Bool[Array, ""]
    step: Int[Array, ""]
    num_accepted: Int[Array, ""]
    damping: Float[Array, ""]
    nu: Float[Array, ""]
    done: Bool[Array, ""]
    result: RESULTS
    last_step_norm: Float[Array, ""]
    initial_cost: Float[Array, ""]
    cost_history: Float[Array, " H"]


LevenbergMarquardtState = GaussNewtonState  # the name before 0.3.0


class AbstractGaussNewton(AbstractGraphSolver):
    """A Gauss-Newton-family solver on the manifold: a descent and a stopping policy.

    Each iteration linearises the trial point `x ⊕ δ` of the step solved in
    the iteration before (the initial values in the first), lets the
    `descent` judge it (take it or not, move the damping λ, stop), asks the
    `stopping` policy whether it has converged, and solves
    `(JᵀJ + λD) δ = −Jᵀr` for the next step with the lineax
    `linear_solver`. The three concrete solvers are
    [`eqsmooth.solve.GaussNewton`][] (`UndampedDescent`, `Tolerances`),
    [`eqsmooth.solve.LevenbergMarquardt`][] (`DampedDescent`, `Tolerances`)
    and [`eqsmooth.solve.FixedStepGaussNewton`][] (`UndampedDescent`,
    `FixedSteps`); a subclass with other `descent` and `stopping` (fields
    or properties) is a new member of the family with the same state.
    """

    linear_solver: eqx.AbstractVar[lx.AbstractLinearSolver | None]
    descent: eqx.AbstractVar[AbstractDescent]
    stopping: eqx.AbstractVar[AbstractStopping]

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags
        lin, done, result = start(fn, y, args, options, f_struct, type(self).__name__)
        dtype = lin.dtype
        return GaussNewtonState(
            lin=lin,
            delta=zeros_tangent(lin),
            solved=jnp.array(True),
            step=jnp.array(0),
            num_accepted=jnp.array(0),
            damping=jnp.asarray(self.descent.initial_damping_value(), dtype),
            nu=jnp.asarray(2.0, dtype),
            done=done,
            result=result,
            last_step_norm=jnp.asarray(jnp.inf, dtype),
            initial_cost=lin.cost.astype(dtype),
            cost_history=cost_record(options, dtype),
        )

    def step(self, fn, y, args, options: dict[str, Any], state, tags):
        del fn, tags  # fn was checked against the graph's residuals in init
        graph = graph_of(args, type(self).__name__)
        first = state.step == 0
        trial = tree_where(first, y, retract_values(y, state.delta))
        trial_lin = linearize_graph(graph, trial)
        finite = finite_lin(trial_lin)
        verdict = self.descent.judge(state, trial_lin, finite, first)
        converged = self.stopping.converged(
            first, verdict.accept, state.lin.cost, trial_lin, state.delta
        )
        done = verdict.stop | (finite & converged)
        take = verdict.accept | first
        values = tree_where(take, trial, y)
        # A failed step is not taken, and nothing is differentiable through it.
        values = nan_derivative_if(verdict.diverged, values, state.lin.cost)
        lin = tree_where(take, trial_lin, state.lin)
        delta, solved = solve_unless(
            done,
            linear_solver_for(self.linear_solver, lin),
            lin,
            self.descent.damping(lin, verdict.damping),
            options,
        )
        result = verdict.result
        if not self.descent.recovers_from_failed_solve():
            # A failed solve ends the solve here: no derivative through its
            # values.
            result = RESULTS.where(done | solved, result, RESULTS.linear_solve_failed)
            values = nan_derivative_if(~solved, values, lin.cost)
            done = done | ~solved
        # Diagnostic only; stopped so that sqrt at a zero step never puts a NaN
        # into masked iterations of an unrolled backward pass.
        step_norm = jnp.where(
            first, jnp.inf, lax.stop_gradient(jnp.sqrt(sq_norm(state.delta)))
        ).astype(lin.dtype)
        new_state = GaussNewtonState(
            lin=lin,
            delta=delta,
            solved=solved,
            step=state.step + 1,
            num_accepted=state.num_accepted
            + verdict.accept.astype(state.num_accepted.dtype),
            damping=verdict.damping,
            nu=verdict.nu,
            done=done,
            result=result,
            last_step_norm=step_norm,
            initial_cost=jnp.where(first, lin.cost, state.initial_cost),
            cost_history=record_iteration(
                options,
                state.step,
                state.cost_history,
                lin.cost,
                step_norm,
                verdict.damping,
            ),
        )
        return values, new_state, None

    def terminate(
        self, fn, y, args, options, state: GaussNewtonState, tags
    ) -> tuple[Bool[Array, ""], optx.RESULTS]:
        del fn, y, args, options, tags  # fn: checked in init
        done = state.done | self.stopping.out_of_steps(state.step)
        return done, to_optx_result(state.result)

    def finish(self, graph, values, state: GaussNewtonState):
        if not self.steps_after_loop():
            return values, state, state.lin.cost
        # The last step, solved in the last iteration: taken here and
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
        state = eqx.tree_at(
            lambda s: (
                s.lin,
                s.delta,
                s.step,
                s.num_accepted,
                s.done,
                s.result,
                s.last_step_norm,
            ),
            state,
            (
                tree_where(take & ok, final_lin, state.lin),
                zeros_tangent(state.lin),
                state.step + take.astype(state.step.dtype),
                state.num_accepted + (take & ok).astype(state.step.dtype),
                state.done | failed,
                RESULTS.where(failed, RESULTS.nonlinear_divergence, state.result),
                jnp.where(
                    take, lax.stop_gradient(jnp.sqrt(sq_norm(state.delta))), jnp.inf
                ).astype(state.lin.dtype),
            ),
        )
        return values, state, jnp.where(take & ok, cost, state.lin.cost)


class GaussNewton(AbstractGaussNewton):
    """Gauss-Newton on the manifold: solve `JᵀJ δ = −Jᵀr`, set `x ← x ⊕ δ`.

    An optimistix least-squares solver (`args` is the graph, see
    [`eqsmooth.solve.AbstractGraphSolver`][]) of the Gauss-Newton family:
    [`eqsmooth.solve.UndampedDescent`][] and [`eqsmooth.solve.Tolerances`][].
    Converges when the relative cost change is at most `ftol`, the largest
    gradient entry at most `gtol`, or the largest step entry at most `xtol`
    (Ceres-like tolerances). Undamped: prefer
    [`eqsmooth.solve.LevenbergMarquardt`][] far from the solution.

    **Arguments:**

    - `linear_solver`: any lineax solver of the
        [`eqsmooth.solve.NormalOperator`][]: `BlockTridiagonal()`, `PCG()`,
        `SparseLU()`, `DenseCholesky()`, or lineax's (`lx.Cholesky()`,
        `lx.CG(rtol, atol)`, ...). `None` (the default) picks one from the
        graph's structure: `BlockTridiagonal()` for chains, else
        `DenseCholesky()` (small) or `SparseLU()`.
    - `ftol`, `gtol`, `xtol`: tolerances (each `>= 0`).
    """

    linear_solver: lx.AbstractLinearSolver | None = None
    ftol: float = eqx.field(static=True, default=1e-8)
    gtol: float = eqx.field(static=True, default=1e-10)
    xtol: float = eqx.field(static=True, default=1e-10)

    def __check_init__(self):
        check_tolerances("GaussNewton", self.ftol, self.gtol, self.xtol)

    @property
    def descent(self) -> UndampedDescent:
        return UndampedDescent()

    @property
    def stopping(self) -> Tolerances:
        return Tolerances(self.ftol, self.gtol, self.xtol)


class FixedStepGaussNewton(AbstractGaussNewton):
    """Exactly `num_steps` Gauss-Newton steps (the paper's unrolled solver).

    The Gauss-Newton family with [`eqsmooth.solve.UndampedDescent`][] and
    [`eqsmooth.solve.FixedSteps`][]. Reaching `num_steps` is success; no
    tolerance stops it early, so the computation (and its gradient under
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
    - `num_steps`: K (an int `>= 1`).
    """

    linear_solver: lx.AbstractLinearSolver | None = None
    num_steps: int = eqx.field(static=True, default=3)

    def __check_init__(self):
        check_num_steps("FixedStepGaussNewton", self.num_steps)

    @property
    def descent(self) -> UndampedDescent:
        return UndampedDescent()

    @property
    def stopping(self) -> FixedSteps:
        return FixedSteps(self.num_steps)


class LevenbergMarquardt(AbstractGaussNewton):
    """Levenberg-Marquardt on the manifold, robust to singular Gauss-Newton systems.

    The Gauss-Newton family with [`eqsmooth.solve.DampedDescent`][] and
    [`eqsmooth.solve.Tolerances`][]. Solves `(JᵀJ + λ D) δ = −Jᵀr` with
    `D = clip(diag(JᵀJ), min_diagonal, max_diagonal)` (Marquardt scaling with
    a floor, so the damped system is positive definite even where `JᵀJ` is
    singular). A step is accepted when the gain ratio ρ (actual / predicted
    cost decrease) exceeds `min_gain`; λ then moves by the `damping_update`
    rule. A failed linear solve counts as a rejection. Only accepted steps
    are tested for convergence.

    **Arguments:**

    - `linear_solver`: the linear solver (`None`: chosen from the graph, see
        [`eqsmooth.solve.GaussNewton`][]).
    - `ftol`, `gtol`, `xtol`: Ceres-like tolerances (see
        [`eqsmooth.solve.GaussNewton`][]).
    - `initial_damping`: λ₀, relative to the diagonal of `JᵀJ`. The default
        `1e-8` starts close to Gauss-Newton: λ shrinks by at most a factor 3
        per accepted step, so a large λ₀ costs many steps on long pose-graph
        chains, while a rejected step raises λ quickly (factors 2, 4, 8, … in
        a row).
    - `min_diagonal`, `max_diagonal`: clipping of `D`.
    - `max_damping`: if λ exceeds this, the solve stops with
        `RESULTS.linear_solve_failed` (or success if already converged).
    - `min_gain`: acceptance threshold of the gain ratio.
    - `damping_update`: how λ moves after each trial step. `"nielsen"` (the
        default; Nielsen 1999): times `max(1/3, 1 − (2ρ − 1)³)` after an
        accepted step, so it shrinks when ρ > ½ and grows when ρ < ½, and
        times ν after a rejection, where ν starts at 2 and doubles on every
        consecutive rejection. `"fixed"`: divided by `damping_factor` after
        every accepted step and multiplied by it after every rejection,
        whatever ρ (GTSAM's default, with factor 10). On large, badly
        initialised pose graphs Nielsen's λ can settle where ρ ≈ ½ and the
        steps are small (`w20000.txt`: λ ≈ 0.2, cost 7894 after 300 steps
        against 7189 with `"fixed"`); elsewhere the fixed factor rejects
        more steps (`cubicle.g2o`: cost 20961 after 100 steps against 1199
        after 85 with Nielsen's rule). See the performance page.
    - `damping_factor`: the factor of `"fixed"` (`> 1`; default 10).
    """

    linear_solver: lx.AbstractLinearSolver | None = None
    ftol: float = eqx.field(static=True, default=1e-8)
    gtol: float = eqx.field(static=True, default=1e-10)
    xtol: float = eqx.field(static=True, default=1e-10)
    initial_damping: float = eqx.field(static=True, default=1e-8)
    min_diagonal: float = eqx.field(static=True, default=1e-6)
    max_diagonal: float = eqx.field(static=True, default=1e32)
    max_damping: float = eqx.field(static=True, default=1e16)
    min_gain: float = eqx.field(static=True, default=1e-3)
    damping_update: str = eqx.field(static=True, default="nielsen")
    damping_factor: float = eqx.field(static=True, default=10.0)

    def __check_init__(self):
        check_tolerances("LevenbergMarquardt", self.ftol, self.gtol, self.xtol)
        check_damping("LevenbergMarquardt", self)

    @property
    def descent(self) -> DampedDescent:
        return DampedDescent(
            self.initial_damping,
            self.min_diagonal,
            self.max_diagonal,
            self.max_damping,
            self.min_gain,
            self.damping_update,
            self.damping_factor,
        )

    @property
    def stopping(self) -> Tolerances:
        return Tolerances(self.ftol, self.gtol, self.xtol)
