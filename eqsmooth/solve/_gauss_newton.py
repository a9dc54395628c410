from typing import Any

import equinox as eqx
import jax.lax as lax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float, Int

from ._default_solver import linear_solver_for
from ._least_squares import (
    AbstractFixedStepSolver,
    AbstractGraphSolver,
    graph_of,
    start,
    to_optx_result,
)
from ._linear_solver import solve_normal
from ._linearization import Linearization, linearize, retract_values
from ._misc import converged_test, finite_lin, nan_derivative_if, sq_norm, tree_where
from ._solution import RESULTS


class GaussNewtonState(eqx.Module):
    """The state of [`eqsmooth.solve.GaussNewton`][] and
    [`eqsmooth.solve.FixedStepGaussNewton`][].

    **Fields:**

    - `lin`: the linearisation at the current values.
    - `step`, `num_accepted`: iterations taken and accepted.
    - `done`: converged or failed.
    - `result`: an [`eqsmooth.solve.RESULTS`][] code.
    - `last_step_norm`: `‖δ‖₂` of the last step (a diagnostic).
    """

    lin: Linearization
    step: Int[Array, ""]
    num_accepted: Int[Array, ""]
    done: Bool[Array, ""]
    result: RESULTS
    last_step_norm: Float[Array, ""]


def _init(graph, values, gtol: float) -> GaussNewtonState:
    lin, done, result = start(graph, values, gtol)
    return GaussNewtonState(
        lin=lin,
        step=jnp.array(0),
        num_accepted=jnp.array(0),
        done=done,
        result=result,
        last_step_norm=jnp.asarray(jnp.inf, lin.dtype),
    )


def _step(solver, graph, values, state: GaussNewtonState, options, check: bool):
    """One Gauss-Newton step; `check=False` never stops on convergence."""
    lin = state.lin
    linear_solver = linear_solver_for(solver.linear_solver, lin)
    delta, lres = solve_normal(
        linear_solver, lin, None, options=options.get("linear_options")
    )
    solved = lres == RESULTS.successful
    new_values = retract_values(values, delta)
    new_lin = linearize(graph, new_values)
    finite = finite_lin(new_lin)
    ok = solved & finite
    result = RESULTS.where(
        solved,
        RESULTS.where(finite, RESULTS.successful, RESULTS.nonlinear_divergence),
        RESULTS.linear_solve_failed,
    )
    done = ~ok
    if check:
        converged = converged_test(
            lin.cost, new_lin, delta, solver.ftol, solver.gtol, solver.xtol
        )
        done = done | (ok & converged)
    # A failed step is not taken, and nothing is differentiable through it.
    values = nan_derivative_if(~ok, tree_where(ok, new_values, values), lin.cost)
    new_state = GaussNewtonState(
        lin=tree_where(ok, new_lin, lin),
        step=state.step + 1,
        num_accepted=state.num_accepted + ok.astype(state.num_accepted.dtype),
        done=done,
        result=result,
        # Diagnostic only; stopped so that sqrt at a zero step never puts a
        # NaN into masked iterations of an unrolled backward pass.
        last_step_norm=lax.stop_gradient(jnp.sqrt(sq_norm(delta)).astype(lin.dtype)),
    )
    return values, new_state, None


class GaussNewton(AbstractGraphSolver):
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

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, options, f_struct, aux_struct, tags
        return _init(graph_of(args, "GaussNewton"), y, self.gtol)

    def step(self, fn, y, args, options: dict[str, Any], state, tags):
        del fn, tags
        graph = graph_of(args, "GaussNewton")
        return _step(self, graph, y, state, options, check=True)

    def terminate(self, fn, y, args, options, state: GaussNewtonState, tags):
        del fn, y, args, options, tags
        return state.done, to_optx_result(state.result)


class FixedStepGaussNewton(AbstractFixedStepSolver):
    """Exactly `num_steps` Gauss-Newton steps (the paper's unrolled solver).

    Reaching `num_steps` is success; no tolerance stops it early, so the
    computation (and its gradient under
    [`eqsmooth.solve.UnrolledAdjoint`][]) is the same for every input. Used
    by the surrogate loss (start at ground truth, K steps). Through
    `optx.least_squares` give `max_steps >= num_steps`.

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

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del fn, options, f_struct, aux_struct, tags
        return _init(graph_of(args, "FixedStepGaussNewton"), y, -1.0)

    def step(self, fn, y, args, options: dict[str, Any], state, tags):
        del fn, tags
        graph = graph_of(args, "FixedStepGaussNewton")
        return _step(self, graph, y, state, options, check=False)

    def terminate(
        self, fn, y, args, options, state: GaussNewtonState, tags
    ) -> tuple[Bool[Array, ""], optx.RESULTS]:
        del fn, y, args, options, tags
        return state.done | (state.step >= self.num_steps), to_optx_result(state.result)
