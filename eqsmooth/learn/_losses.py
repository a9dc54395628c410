"""Training losses: the surrogate loss, the joint NLL and a manifold MSE."""

import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..factors import FactorGraph
from ..factors._graph import graph_negative_log_likelihood, Values
from ..manifold import manifold_mse
from ..solve import (
    AbstractAdjoint,
    AbstractGraphSolver,
    BlockTridiagonal,
    FixedStepGaussNewton,
    least_squares,
    UnrolledAdjoint,
)
from ..solve._padding import padding_size


_DEFAULT_SOLVER = FixedStepGaussNewton(BlockTridiagonal(), num_steps=3)


def surrogate_loss(
    graph: FactorGraph,
    truth: Values,
    *,
    solver: AbstractGraphSolver = _DEFAULT_SOLVER,
    adjoint: AbstractAdjoint = UnrolledAdjoint(),
    weights: PyTree | None = None,
    max_steps: int = 100,
    throw: bool = True,
    init: Values | None = None,
) -> Float[Array, ""]:
    """The surrogate loss of Yi et al. (2021): solve from ground truth, compare.

    The solve starts AT the ground truth and runs the solver (by default
    exactly K = 3 Gauss-Newton steps); the loss is the (weighted) mean squared
    manifold error `x_K ⊖ truth` over every state of every group. Its
    gradient reaches every inexact leaf of `graph`: noise parameters, network
    weights and physical coefficients held in the factors.

    Starting at the truth keeps the solve in its basin of attraction, so K
    small and an undamped solver suffice, and a model whose MAP estimate
    drifts away from the truth is penalised directly.

    **Arguments:**

    - `graph`: the [`eqsmooth.factors.FactorGraph`][], built from the model
        being trained and one sequence's data.
    - `truth`: ground-truth values `{group: stacked states}`; also the initial
        values of the solve.
    - `solver`: the nonlinear solver; default
        `FixedStepGaussNewton(BlockTridiagonal(), num_steps=3)` (chains). Use
        `DenseCholesky()` or `PCG()` for other graph shapes.
    - `adjoint`: how the solve is differentiated:
        [`eqsmooth.solve.UnrolledAdjoint`][] (default: backpropagate through
        every step, the paper's method), [`eqsmooth.solve.TruncatedAdjoint`][]
        (only the last k steps) or [`eqsmooth.solve.ImplicitAdjoint`][] (at a
        converged solve: pair it with a converging solver such as
        `GaussNewton`).
    - `weights`: per-component weights, as in
        [`eqsmooth.manifold.manifold_mse`][] (e.g. `{"x": jnp.array([1., 1., 0.,
        0.])}` to score positions only).
    - `max_steps`: step limit for converging solvers (a fixed-step solver
        runs its own `num_steps`).
    - `throw`: raise if the solve fails (see [`eqsmooth.solve.least_squares`][]).
    - `init`: start the solve here instead of at the truth, e.g. at the
        estimator's own initialisation (dead reckoning), so that the K steps
        are the ones the estimator takes at test time. When K steps converge
        from either start (nearly linear problems) the loss is the same.

    **Returns:** a scalar loss.
    """
    if not isinstance(truth, dict):
        raise TypeError(
            "surrogate_loss: truth must be a values dict {group: stacked states}, "
            f"got {type(truth).__name__}"
        )
    start = truth if init is None else init
    sol = least_squares(
        graph, start, solver, max_steps=max_steps, adjoint=adjoint, throw=throw
    )
    return manifold_mse(truth, sol.value, weights)


def joint_nll(
    graph: FactorGraph, truth: Values, *, reduction: str = "mean"
) -> Float[Array, ""]:
    """Joint negative log-likelihood of the ground truth under the graph's model.

    The Gaussian NLL of every factor at the ground truth: half the whitened
    squared residuals, minus the log-determinants of the square-root
    informations, plus `½ log 2π` per residual component (robust noise models
    use `½ρ(s)` in place of `½s`, with the base model's log-determinant, which
    is not a normalised density). This is the loss that can learn
    heteroscedastic and absolute noise scales, which the surrogate loss
    cannot tell apart when all noise scales change together.

    **Arguments:**

    - `graph`: the [`eqsmooth.factors.FactorGraph`][].
    - `truth`: ground-truth values `{group: stacked states}`.
    - `reduction`: `"mean"` divides the total by the number of variables
        (over all groups: per time step for a chain), so losses of sequences
        of different lengths compare; `"sum"` returns the total.

    **Returns:** a scalar.
    """
    if reduction not in ("mean", "sum"):
        raise ValueError(
            f"joint_nll: reduction must be 'mean' or 'sum', got {reduction!r}"
        )
    layout = graph.validate(truth)
    total = graph_negative_log_likelihood(graph, truth)
    if reduction == "sum":
        return total
    # A padded graph (pad_graph) divides by its real variables only.
    count = sum(g.count for g in layout) - padding_size(graph)[0]
    return total / jnp.asarray(count, total.dtype)
