import math
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, Int

from .._linear._default_solver import linear_solver_for
from .._linear._linear_solver import solve_unless
from .._linearization import (
    apply_jacobian,
    block_diagonal,
    gradient,
    Linearization,
    linearize_graph,
    retract_values,
    Tangent,
    zeros_tangent,
)
from .._misc import converged_test, finite_lin, max_abs, sq_norm, tree_where
from .._solution import RESULTS
from ._graph_solver import (
    AbstractConvergingSolver,
    cost_record,
    graph_of,
    record_iteration,
    start,
    to_optx_result,
)


class LevenbergMarquardtState(eqx.Module):
    """The state of [`eqsmooth.solve.LevenbergMarquardt`][].

    **Fields:** those of [`eqsmooth.solve.GaussNewtonState`][] (one
    linearisation per iteration, of the trial point), plus `solved` (whether
    `delta` came from a successful linear solve), `damping` (λ) and `nu` (the
    factor λ grows by on the next rejection).
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


def marquardt_damping(lin: Linearization, lam, min_diag: float, max_diag: float):
    blocks = block_diagonal(lin)
    return {
        name: lam * jnp.clip(jnp.diagonal(b, axis1=1, axis2=2), min_diag, max_diag)
        for name, b in blocks.items()
    }


def predicted_decrease(lin: Linearization, delta: Tangent) -> Float[Array, ""]:
    """Decrease of the Gauss-Newton model: `−gᵀδ − ½‖Jδ‖²`."""
    g = gradient(lin)
    gd = sum(jnp.sum(g[k] * delta[k]) for k in g)
    jd = sq_norm(apply_jacobian(lin, delta))
    return -gd - 0.5 * jd


class LevenbergMarquardt(AbstractConvergingSolver):
    """Levenberg-Marquardt on the manifold, robust to singular Gauss-Newton systems.

    Solves `(JᵀJ + λ D) δ = −Jᵀr` with `D = clip(diag(JᵀJ), min_diagonal,
    max_diagonal)` (Marquardt scaling with a floor, so the damped system is
    positive definite even where `JᵀJ` is singular). A step is accepted when
    the gain ratio (actual / predicted cost decrease) exceeds `min_gain`;
    λ then shrinks smoothly (Nielsen's rule), otherwise it grows by a factor
    that doubles on every consecutive rejection. A failed linear solve counts
    as a rejection. Only accepted steps are tested for convergence.

    **Arguments:**

    - `linear_solver`: the linear solver (`None`: chosen from the graph, see
        [`eqsmooth.solve.GaussNewton`][]).
    - `ftol`, `gtol`, `xtol`: Ceres-like tolerances (see
        [`eqsmooth.solve.GaussNewton`][]).
    - `initial_damping`: λ₀, relative to the diagonal of `JᵀJ`. The default
        `1e-8` starts close to Gauss-Newton: λ shrinks by at most a factor 3
        per accepted step, so a large λ₀ costs many steps on long pose-graph
        chains, while a rejected step
        raises λ quickly (factors 2, 4, 8, … in a row).
    - `min_diagonal`, `max_diagonal`: clipping of `D`.
    - `max_damping`: if λ exceeds this, the solve stops with
        `RESULTS.linear_solve_failed` (or success if already converged).
    - `min_gain`: acceptance threshold of the gain ratio.
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

    def __check_init__(self):
        checks = (
            ("ftol", self.ftol >= 0, ">= 0"),
            ("gtol", self.gtol >= 0, ">= 0"),
            ("xtol", self.xtol >= 0, ">= 0"),
            (
                "initial_damping",
                0 <= self.initial_damping < math.inf,
                ">= 0 and finite",
            ),
            ("min_diagonal", 0 < self.min_diagonal < math.inf, "> 0 and finite"),
            ("max_diagonal", self.max_diagonal >= self.min_diagonal, ">= min_diagonal"),
            (
                "max_damping",
                self.max_damping > self.initial_damping,
                "> initial_damping",
            ),
            ("min_gain", 0 <= self.min_gain < 1, "in [0, 1)"),
        )
        for field, ok, need in checks:
            if not ok:  # NaN fails every comparison, so it lands here too
                raise ValueError(
                    f"LevenbergMarquardt.{field} must be {need}, got "
                    f"{getattr(self, field)!r}"
                )

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        del aux_struct, tags
        lin, done, result, step = start(
            fn, y, args, options, f_struct, "LevenbergMarquardt"
        )
        return LevenbergMarquardtState(
            lin=lin,
            delta=zeros_tangent(lin),
            solved=jnp.array(True),
            step=step,
            num_accepted=jnp.array(0),
            damping=jnp.asarray(self.initial_damping, lin.dtype),
            nu=jnp.asarray(2.0, lin.dtype),
            done=done,
            result=result,
            last_step_norm=jnp.asarray(jnp.inf, lin.dtype),
            initial_cost=lin.cost.astype(lin.dtype),
            cost_history=cost_record(options, lin.dtype),
        )

    def step(self, fn, y, args, options: dict[str, Any], state, tags):
        del tags  # fn was checked against the graph's residuals in init
        graph = graph_of(args, "LevenbergMarquardt")
        values = y
        lin = state.lin
        lam = state.damping
        delta = state.delta
        first = state.step == 0
        # The trial point of the step solved in the previous iteration (the
        # initial values in the first iteration, which are always taken).
        trial_values = tree_where(first, values, retract_values(values, delta))
        trial_lin = linearize_graph(graph, trial_values)
        finite = finite_lin(trial_lin)
        predicted = predicted_decrease(lin, delta)
        actual = lin.cost - trial_lin.cost
        gain = actual / jnp.where(predicted > 0, predicted, 1.0)
        accept = (
            state.solved & finite & (predicted > 0) & (gain > self.min_gain) & ~first
        )
        converged = accept & converged_test(
            lin.cost, trial_lin, delta, self.ftol, self.gtol, self.xtol
        )
        # Nielsen's damping update.
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
        new_lam = jnp.where(accept, lam * shrink, lam * state.nu)
        new_lam = jnp.maximum(new_lam, jnp.finfo(lam.dtype).tiny)
        new_nu = jnp.where(accept, 2.0, 2.0 * state.nu)
        # Nothing left to gain: the model's predicted decrease is at the level of
        # floating-point noise in the cost (or not positive), so no accepted
        # step can be told apart from rounding. This is convergence.
        eps = jnp.finfo(lam.dtype).eps
        stalled = state.solved & (predicted <= 16 * eps * jnp.maximum(lin.cost, 1.0))
        stalled = stalled & ~first
        gave_up = (new_lam > self.max_damping) & ~first
        result = RESULTS.where(
            gave_up & ~stalled, RESULTS.linear_solve_failed, RESULTS.successful
        )
        done = converged | stalled | gave_up
        # The first iteration: the initial values, stopped at once if they
        # are not finite or already stationary.
        result = RESULTS.where(first & ~finite, RESULTS.nonfinite_problem, result)
        done = jnp.where(
            first, ~finite | (max_abs(gradient(trial_lin)) <= self.gtol), done
        )
        new_lam = jnp.where(first, lam, new_lam)
        new_nu = jnp.where(first, state.nu, new_nu)
        take = accept | first
        values = tree_where(take, trial_values, values)
        lin = tree_where(take, trial_lin, lin)
        damping = marquardt_damping(lin, new_lam, self.min_diagonal, self.max_diagonal)
        next_delta, solved = solve_unless(
            done, linear_solver_for(self.linear_solver, lin), lin, damping, options
        )
        step_norm = jnp.where(first, jnp.inf, jnp.sqrt(sq_norm(delta))).astype(
            lam.dtype
        )
        new_state = LevenbergMarquardtState(
            lin=lin,
            delta=next_delta,
            solved=solved,
            step=state.step + 1,
            num_accepted=state.num_accepted + accept.astype(state.num_accepted.dtype),
            damping=new_lam.astype(lam.dtype),
            nu=new_nu.astype(lam.dtype),
            done=done,
            result=result,
            last_step_norm=step_norm,
            initial_cost=jnp.where(first, lin.cost, state.initial_cost),
            cost_history=record_iteration(
                options, state.step, state.cost_history, lin.cost, step_norm, new_lam
            ),
        )
        return values, new_state, None

    def terminate(self, fn, y, args, options, state: LevenbergMarquardtState, tags):
        del y, args, options, tags  # fn: checked in init
        return state.done, to_optx_result(state.result)

    def finish(self, graph, values, state: LevenbergMarquardtState):
        del graph
        return values, state, state.lin.cost
