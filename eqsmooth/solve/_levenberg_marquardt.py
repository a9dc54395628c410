import equinox as eqx
import jax.numpy as jnp

from ._gauss_newton import _terminate
from ._least_squares import (
    _finite_lin,
    _sq_norm,
    _tree_where,
    AbstractLeastSquaresSolver,
    converged_test,
    initial_state,
    LeastSquaresState,
    marquardt_damping,
    predicted_decrease,
)
from ._linear_solver import AbstractLinearSolver
from ._linearization import linearize, retract_values
from ._solution import RESULTS


class LevenbergMarquardt(AbstractLeastSquaresSolver):
    """Levenberg-Marquardt on the manifold, robust to singular Gauss-Newton systems.

    Solves `(JᵀJ + λ D) δ = −Jᵀr` with `D = clip(diag(JᵀJ), min_diagonal,
    max_diagonal)` (Marquardt scaling with a floor, so the damped system is
    positive definite even where `JᵀJ` is singular). A step is accepted when
    the gain ratio (actual / predicted cost decrease) exceeds `min_gain`;
    λ then shrinks smoothly (Nielsen's rule), otherwise it grows by a factor
    that doubles on every consecutive rejection. A failed linear solve counts
    as a rejection. Only accepted steps are tested for convergence.

    **Arguments:**

    - `linear_solver`: the linear solver.
    - `ftol`, `gtol`, `xtol`: Ceres-like tolerances (see
        [`eqsmooth.solve.GaussNewton`][]).
    - `initial_damping`: λ₀, relative to the diagonal of `JᵀJ`. The default
        `1e-8` starts close to Gauss-Newton: λ shrinks by at most a factor 3
        per accepted step, so a large λ₀ costs many steps on long pose-graph
        chains (MIT.g2o: 55 steps to GTSAM's optimum from `1e-8`, not
        converged after 100 from `1e-4`), while a rejected step raises λ
        quickly (factors 2, 4, 8, … in a row).
    - `min_diagonal`, `max_diagonal`: clipping of `D`.
    - `max_damping`: if λ exceeds this, the solve stops with
        `RESULTS.linear_solve_failed` (or success if already converged).
    - `min_gain`: acceptance threshold of the gain ratio.
    """

    linear_solver: AbstractLinearSolver
    ftol: float = eqx.field(static=True, default=1e-8)
    gtol: float = eqx.field(static=True, default=1e-10)
    xtol: float = eqx.field(static=True, default=1e-10)
    initial_damping: float = eqx.field(static=True, default=1e-8)
    min_diagonal: float = eqx.field(static=True, default=1e-6)
    max_diagonal: float = eqx.field(static=True, default=1e32)
    max_damping: float = eqx.field(static=True, default=1e16)
    min_gain: float = eqx.field(static=True, default=1e-3)

    def init(self, graph, values):
        return initial_state(graph, values, self.initial_damping, self.gtol)

    def step(self, graph, values, state: LeastSquaresState):
        lin = state.lin
        lam = state.damping
        damping = marquardt_damping(lin, lam, self.min_diagonal, self.max_diagonal)
        delta, lres = self.linear_solver.solve(lin, damping)
        solved = lres == RESULTS.successful
        trial_values = retract_values(values, delta)
        trial_lin = linearize(graph, trial_values)
        predicted = predicted_decrease(lin, delta)
        actual = lin.cost - trial_lin.cost
        gain = actual / jnp.where(predicted > 0, predicted, 1.0)
        accept = (
            solved & _finite_lin(trial_lin) & (predicted > 0) & (gain > self.min_gain)
        )
        converged = accept & converged_test(
            lin.cost, trial_lin, delta, self.ftol, self.gtol, self.xtol
        )
        # Nielsen's damping update.
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain - 1.0) ** 3)
        new_lam = jnp.where(accept, lam * shrink, lam * state.nu)
        new_lam = jnp.maximum(new_lam, jnp.finfo(lin.dtype).tiny)
        new_nu = jnp.where(accept, 2.0, 2.0 * state.nu)
        # Nothing left to gain: the model's predicted decrease is at the level of
        # floating-point noise in the cost (or not positive), so no accepted
        # step can be told apart from rounding. This is convergence.
        eps = jnp.finfo(lin.dtype).eps
        stalled = solved & (predicted <= 16 * eps * jnp.maximum(lin.cost, 1.0))
        converged = converged | (stalled & ~accept)
        gave_up = new_lam > self.max_damping
        result = RESULTS.where(
            gave_up & ~stalled, RESULTS.linear_solve_failed, RESULTS.successful
        )
        values = _tree_where(accept, trial_values, values)
        new_state = LeastSquaresState(
            lin=_tree_where(accept, trial_lin, lin),
            step=state.step + 1,
            num_accepted=state.num_accepted + accept.astype(state.num_accepted.dtype),
            damping=new_lam.astype(lam.dtype),
            nu=new_nu.astype(lam.dtype),
            done=converged | stalled | gave_up,
            result=result,
            last_step_norm=jnp.sqrt(_sq_norm(delta)).astype(lam.dtype),
        )
        return values, new_state

    def terminate(self, state, max_steps):
        return _terminate(state, max_steps, RESULTS.nonlinear_max_steps_reached)
