"""Laplace approximation of the log marginal likelihood of a factor graph."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float, PyTree

from ..factors import FactorGraph, StudentTNoise
from ..factors._graph import graph_negative_log_likelihood
from ..solve import (
    AbstractGraphSolver,
    BlockTridiagonal,
    GaussNewton,
    least_squares,
    normal_log_det,
    solve_normal,
)
from ..solve._default_solver import linear_solver_for
from ..solve._linearization import gradient, linearize_graph, retract_values


Values = dict[str, PyTree]


def laplace_log_marginal(
    graph: FactorGraph,
    values: Values,
    solver: AbstractGraphSolver | None = None,
    *,
    max_steps: int = 50,
) -> tuple[Float[Array, ""], Values]:
    """Laplace approximation of `log p(y | θ)`, the log marginal likelihood.

    The graph's factors define a joint density `p(x, y | θ) ∝ exp(−cost)`
    whose normalisation comes from the noise models' log-determinants. At the
    MAP `x̂` (found by [`eqsmooth.solve.least_squares`][]):

        log p(y | θ) ≈ −cost(x̂) + Σ log det R − ½ M log 2π
                       + ½ N log 2π − ½ log det(JᵀJ)

    with `M` residual and `N` tangent dimensions and `J` the whitened
    Jacobian at `x̂`. It is exact for linear-Gaussian graphs (equal to the
    Kalman-filter likelihood of a chain), provided every factor is a
    normalised density in its residual (`r = y − h(x)`, `r = x' − f(x)`, a
    proper prior on the first state).

    **Gradients.** The MAP is computed at a stop-gradient copy of the graph;
    derivatives w.r.t. the graph's parameters `θ` then flow through one
    Gauss-Newton correction `x̃(θ) = x̂ ⊕ δ(θ)`, `δ = −(JᵀJ)⁻¹ Jᵀr(x̂, θ)`, with
    the normal matrix held fixed. Because `δ(θ̂) = 0` and `dx̃/dθ` is the
    implicit derivative of the (Gauss-Newton) optimum, the gradient of the
    cost term is exact (the envelope theorem) and its second derivative is
    that of the profiled cost; only the dependence of `log det` on `x̂` uses
    the Gauss-Newton approximation of `dx̂/dθ`. `jax.grad`, `jax.jacfwd` and
    `jax.hessian` all work.

    [`eqsmooth.factors.StudentTNoise`][] is a normalised density, so a graph
    with Student-t factors gets a proper Laplace evidence. Its
    log-determinant uses the t density's Fisher information
    ([`StudentTNoise.fisher_model`][eqsmooth.factors.StudentTNoise.fisher_model])
    rather than the curvature at each residual: the latter changes with the
    residuals, which makes the one-step correction's gradient inexact and
    the evidence rough in `θ`. The robust kernels (Huber, Cauchy, ...) are
    losses, not densities, and their result is only indicative.

    **Arguments:**

    - `graph`: the [`eqsmooth.factors.FactorGraph`][] (parameters may be traced).
    - `values`: initial values for the MAP solve.
    - `solver`: default `GaussNewton(BlockTridiagonal())` (chains); pass e.g.
        `GaussNewton(DenseCholesky())` for general graphs.
    - `max_steps`: iteration limit of the MAP solve.

    **Returns:**

    `(log_marginal, map_values)`; the MAP values are stop-gradient.
    """
    if solver is None:
        solver = GaussNewton(BlockTridiagonal())
    if not isinstance(solver, AbstractGraphSolver):
        raise TypeError(
            "laplace_log_marginal: solver must be an AbstractGraphSolver, "
            f"got {type(solver).__name__}"
        )
    frozen = jax.lax.stop_gradient(graph)
    sol = least_squares(frozen, values, solver, max_steps=max_steps, throw=False)
    x_hat = jax.lax.stop_gradient(sol.value)
    return laplace_at_map(graph, x_hat, solver.linear_solver), x_hat


@eqx.filter_jit  # an eager call would dispatch (and compile) op by op
def laplace_at_map(
    graph: FactorGraph,
    map_values: Values,
    linear_solver: lx.AbstractLinearSolver | None = None,
) -> Float[Array, ""]:
    """The Laplace log marginal likelihood given the MAP `map_values`.

    The differentiable part of [`eqsmooth.discover.laplace_log_marginal`][]:
    `map_values` must be the MAP of `graph` (treated as constant); derivatives
    w.r.t. the graph's parameters flow through one Gauss-Newton correction
    (see there). Splitting the MAP solve off keeps the solver's loop out of
    the differentiated (and compiled) function.

    **Arguments:**

    - `graph`: the factor graph (parameters may be traced).
    - `map_values`: its MAP values.
    - `linear_solver`: e.g. `BlockTridiagonal()` (chains) or `DenseCholesky()`;
        `None` picks one from the graph's structure.

    **Returns:** the scalar log marginal likelihood.
    """
    x_hat = jax.lax.stop_gradient(map_values)
    frozen = jax.lax.stop_gradient(graph)
    lin_frozen = linearize_graph(frozen, x_hat)
    lin = linearize_graph(graph, x_hat)
    g = gradient(lin)
    rhs = {k: -v for k, v in g.items()}
    linear_solver = linear_solver_for(linear_solver, lin_frozen)
    delta, _ = solve_normal(linear_solver, lin_frozen, None, rhs)
    x_tilde = retract_values(x_hat, delta)
    lin_t = linearize_graph(_fisher_curvature(graph), x_tilde)
    log_det = normal_log_det(lin_t, linear_solver)
    nll = graph_negative_log_likelihood(graph, x_tilde)
    N = lin_t.num_tangent
    log_ml = -nll + 0.5 * N * math.log(2 * math.pi) - 0.5 * log_det
    return jnp.asarray(log_ml)


def _fisher_curvature(graph: FactorGraph) -> FactorGraph:
    """`graph` with every Student-t noise model replaced by its Fisher
    information (a Gaussian), for the log-determinant."""
    factors = [
        eqx.tree_at(lambda f: f.noise, f, f.noise.fisher_model())
        if isinstance(f.noise, StudentTNoise)
        else f
        for f in graph.factors
    ]
    return FactorGraph(factors)
