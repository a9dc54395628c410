import equinox as eqx

from ._least_squares import (
    AbstractFixedStepSolver,
    AbstractLeastSquaresSolver,
    gauss_newton_step,
    initial_state,
    LeastSquaresState,
)
from ._linear_solver import AbstractLinearSolver
from ._solution import RESULTS


def _terminate(state: LeastSquaresState, max_steps: int, at_max: RESULTS):
    failed = state.result != RESULTS.successful
    out_of_steps = state.step >= max_steps
    stop = state.done | out_of_steps
    result = RESULTS.where(
        failed,
        state.result,
        RESULTS.where(state.done, RESULTS.successful, at_max),
    )
    return stop, RESULTS.where(stop, result, RESULTS.successful)


class GaussNewton(AbstractLeastSquaresSolver):
    """Gauss-Newton on the manifold: solve `JᵀJ δ = −Jᵀr`, set `x ← x ⊕ δ`.

    Converges when the relative cost change is at most `ftol`, the largest
    gradient entry at most `gtol`, or the largest step entry at most `xtol`
    (Ceres-like tolerances). Undamped: prefer
    [`eqsmooth.solve.LevenbergMarquardt`][] far from the solution.

    **Arguments:**

    - `linear_solver`: e.g. `BlockTridiagonal()`, `PCG()`, `DenseCholesky()`.
    - `ftol`, `gtol`, `xtol`: tolerances.
    """

    linear_solver: AbstractLinearSolver
    ftol: float = eqx.field(static=True, default=1e-8)
    gtol: float = eqx.field(static=True, default=1e-10)
    xtol: float = eqx.field(static=True, default=1e-10)

    def init(self, graph, values):
        return initial_state(graph, values, 0.0, self.gtol)

    def step(self, graph, values, state):
        return gauss_newton_step(self, graph, values, state)

    def terminate(self, state, max_steps):
        return _terminate(state, max_steps, RESULTS.nonlinear_max_steps_reached)


class FixedStepGaussNewton(AbstractFixedStepSolver):
    """Exactly `num_steps` Gauss-Newton steps (the paper's unrolled solver).

    Reaching `num_steps` is success; no tolerance stops it early, so the
    computation (and its gradient under
    [`eqsmooth.solve.UnrolledAdjoint`][]) is the same for every input. Used
    by the surrogate loss (start at ground truth, K steps).

    **Arguments:**

    - `linear_solver`: the linear solver.
    - `num_steps`: K.
    """

    linear_solver: AbstractLinearSolver
    num_steps: int = eqx.field(static=True, default=3)
    ftol: float = eqx.field(static=True, default=0.0)
    gtol: float = eqx.field(static=True, default=-1.0)
    xtol: float = eqx.field(static=True, default=-1.0)

    def __check_init__(self):
        if self.num_steps < 1:
            raise ValueError(
                f"FixedStepGaussNewton.num_steps must be >= 1, got {self.num_steps}"
            )

    def init(self, graph, values):
        return initial_state(graph, values, 0.0, -1.0)

    def step(self, graph, values, state):
        values, state = gauss_newton_step(self, graph, values, state)
        # Never stop early on convergence: only failures stop.
        done = state.result != RESULTS.successful
        return values, eqx.tree_at(lambda s: s.done, state, done)

    def terminate(self, state, max_steps):
        return _terminate(state, max_steps, RESULTS.successful)
