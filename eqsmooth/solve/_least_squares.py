import abc

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, PyTree

from ..factors import FactorGraph
from ._adjoint import AbstractAdjoint, ImplicitAdjoint
from ._linear_solver import AbstractLinearSolver
from ._linearization import (
    apply_jacobian,
    block_diagonal,
    gradient,
    Linearization,
    linearize,
    retract_values,
    Tangent,
)
from ._solution import RESULTS, Solution


Values = dict[str, PyTree]


class LeastSquaresState(eqx.Module):
    """State shared by the nonlinear least-squares solvers.

    Invariant the adjoints rely on: `lin` is the linearisation at the current
    values.
    """

    lin: Linearization
    step: Int[Array, ""]
    num_accepted: Int[Array, ""]
    damping: Float[Array, ""]
    nu: Float[Array, ""]
    done: Bool[Array, ""]
    result: RESULTS
    last_step_norm: Float[Array, ""]


class AbstractLeastSquaresSolver(eqx.Module):
    """Base of the nonlinear solvers (optimistix shape: init / step / terminate).

    Solvers update the values on the manifold (`x ⊕ δ`), linearise every factor
    stack with forward-mode autodiff and hand the block-sparse Gauss-Newton
    model to their `linear_solver`.
    """

    linear_solver: eqx.AbstractVar[AbstractLinearSolver]

    @abc.abstractmethod
    def init(self, graph: FactorGraph, values: Values) -> LeastSquaresState:
        """Linearise at the initial values and build the state."""

    @abc.abstractmethod
    def step(
        self, graph: FactorGraph, values: Values, state: LeastSquaresState
    ) -> tuple[Values, LeastSquaresState]:
        """One iteration."""

    @abc.abstractmethod
    def terminate(
        self, state: LeastSquaresState, max_steps: int
    ) -> tuple[Bool[Array, ""], RESULTS]:
        """Whether to stop, and with which result."""

    def iteration_limit(self, max_steps: int) -> int:
        """The static iteration limit of a solve called with `max_steps`.

        `max_steps` itself, except for an
        [`eqsmooth.solve.AbstractFixedStepSolver`][], which always runs its
        `num_steps`. [`eqsmooth.solve.UnrolledAdjoint`][] scans this many
        iterations.
        """
        if isinstance(self, AbstractFixedStepSolver):
            return self.num_steps
        return max_steps


class AbstractFixedStepSolver(AbstractLeastSquaresSolver):
    """A solver that always runs exactly `num_steps` iterations.

    [`eqsmooth.solve.least_squares`][] ignores its `max_steps` argument for
    these solvers (see
    [`eqsmooth.solve.AbstractLeastSquaresSolver.iteration_limit`][]).
    """

    num_steps: eqx.AbstractVar[int]


def _tree_where(pred, a, b):
    return jax.tree_util.tree_map(lambda x, y: jnp.where(pred, x, y), a, b)


def _max_abs(tree) -> Float[Array, ""]:
    leaves = jax.tree_util.tree_leaves(tree)
    return jnp.max(jnp.stack([jnp.max(jnp.abs(x)) for x in leaves]))


def _sq_norm(tree) -> Float[Array, ""]:
    return sum(jnp.sum(x * x) for x in jax.tree_util.tree_leaves(tree))


def _finite_lin(lin: Linearization) -> Bool[Array, ""]:
    ok = jnp.isfinite(lin.cost)
    for fl in lin.factors:
        ok = ok & jnp.all(jnp.isfinite(fl.residual))
        for j in fl.jacobians:
            ok = ok & jnp.all(jnp.isfinite(j))
    return ok


def initial_state(
    graph: FactorGraph, values: Values, damping: float, gtol: float
) -> LeastSquaresState:
    lin = linearize(graph, values)
    finite = _finite_lin(lin)
    converged = _max_abs(gradient(lin)) <= gtol
    result = RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_problem)
    dtype = lin.dtype
    return LeastSquaresState(
        lin=lin,
        step=jnp.array(0),
        num_accepted=jnp.array(0),
        damping=jnp.asarray(damping, dtype),
        nu=jnp.asarray(2.0, dtype),
        done=(~finite) | converged,
        result=result,
        last_step_norm=jnp.asarray(jnp.inf, dtype),
    )


def converged_test(
    old_cost, new_lin: Linearization, delta: Tangent, ftol, gtol, xtol
) -> Bool[Array, ""]:
    finfo = jnp.finfo(new_lin.dtype)
    rel = jnp.abs(old_cost - new_lin.cost) / jnp.maximum(old_cost, finfo.tiny)
    # A relative change below a few ulps is rounding: never ask for less.
    ftol = jnp.where(ftol > 0, jnp.maximum(ftol, 4 * finfo.eps), ftol)
    gnorm = _max_abs(gradient(new_lin))
    xnorm = _max_abs(delta)
    return (rel <= ftol) | (gnorm <= gtol) | (xnorm <= xtol)


def gauss_newton_step(
    solver, graph: FactorGraph, values: Values, state: LeastSquaresState
) -> tuple[Values, LeastSquaresState]:
    delta, lres = solver.linear_solver.solve(state.lin, None)
    solved = lres == RESULTS.successful
    new_values = retract_values(values, delta)
    new_lin = linearize(graph, new_values)
    finite = _finite_lin(new_lin)
    ok = solved & finite
    converged = ok & converged_test(
        state.lin.cost, new_lin, delta, solver.ftol, solver.gtol, solver.xtol
    )
    result = RESULTS.where(
        solved,
        RESULTS.where(finite, RESULTS.successful, RESULTS.nonlinear_divergence),
        RESULTS.linear_solve_failed,
    )
    values = _tree_where(ok, new_values, values)
    state = LeastSquaresState(
        lin=_tree_where(ok, new_lin, state.lin),
        step=state.step + 1,
        num_accepted=state.num_accepted + ok.astype(state.num_accepted.dtype),
        damping=state.damping,
        nu=state.nu,
        done=converged | ~ok,
        result=result,
        # Diagnostic only; stopped so that sqrt at a zero step never puts a
        # NaN into masked iterations of an unrolled backward pass.
        last_step_norm=lax.stop_gradient(
            jnp.sqrt(_sq_norm(delta)).astype(state.damping.dtype)
        ),
    )
    return values, state


def least_squares(
    graph: FactorGraph,
    values: Values,
    solver: AbstractLeastSquaresSolver,
    *,
    max_steps: int = 100,
    adjoint: AbstractAdjoint = ImplicitAdjoint(),
    throw: bool = True,
    verbose: bool = False,
) -> Solution:
    """Minimise the cost of `graph` starting from `values`.

    **Arguments:**

    - `graph`: the [`eqsmooth.factors.FactorGraph`][].
    - `values`: initial values, a dict `{group: stacked states}`.
    - `solver`: e.g. `GaussNewton(BlockTridiagonal())` or
        `LevenbergMarquardt(PCG())`.
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

    **Returns:** a [`eqsmooth.solve.Solution`][].
    """
    if not isinstance(solver, AbstractLeastSquaresSolver):
        raise TypeError(
            f"solver must be an AbstractLeastSquaresSolver, got {type(solver).__name__}"
        )
    if not isinstance(adjoint, AbstractAdjoint):
        raise TypeError(
            f"adjoint must be an AbstractAdjoint, got {type(adjoint).__name__}"
        )
    return _least_squares(graph, values, solver, max_steps, adjoint, throw, verbose)


@eqx.filter_jit
def _least_squares(graph, values, solver, max_steps, adjoint, throw, verbose):
    max_steps = solver.iteration_limit(max_steps)

    def init(graph, values):
        state = solver.init(graph, values)
        history = jnp.full((max_steps + 1,), state.lin.cost)
        return values, state, history

    def body(graph, carry):
        values, state, history = carry
        new_values, new_state = solver.step(graph, values, state)
        stop, result = solver.terminate(new_state, max_steps)
        new_state = eqx.tree_at(lambda s: (s.done, s.result), new_state, (stop, result))
        if verbose:
            jax.debug.print(
                "step {step:4d}  cost {cost:.6e}  damping {lam:.2e}  |δ| {dx:.2e}",
                step=new_state.step,
                cost=new_state.lin.cost,
                lam=new_state.damping,
                dx=new_state.last_step_norm,
            )
        history = history.at[new_state.step].set(new_state.lin.cost)
        return new_values, new_state, history

    def cond(carry):
        _, state, _ = carry
        return ~state.done & (state.step < max_steps)

    values, state, history = adjoint.apply(
        init, body, cond, graph, values, solver.linear_solver, max_steps
    )
    steps = state.step
    history = jnp.where(jnp.arange(max_steps + 1) <= steps, history, state.lin.cost)
    _, final_result = solver.terminate(state, max_steps)
    result = RESULTS.where(
        state.result == RESULTS.successful, final_result, state.result
    )
    stats = {
        "num_steps": steps,
        "num_accepted": state.num_accepted,
        "initial_cost": history[0],
        "final_cost": state.lin.cost,
        "cost_history": history,
    }
    if throw:
        values = result.error_if(values, result != RESULTS.successful)
    return Solution(value=values, result=result, stats=stats, state=state)


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
    jd = _sq_norm(apply_jacobian(lin, delta))
    return -gd - 0.5 * jd
