"""Laplace approximation of the log marginal likelihood of a factor graph."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from ..factors import FactorGraph
from ..factors._graph import graph_cost, graph_negative_log_likelihood, Values
from ..factors._padding import padding_size
from ..solve import (
    AbstractGraphSolver,
    BlockTridiagonal,
    GaussNewton,
    least_squares,
    normal_log_det,
    solve_normal,
)
from ..solve._linear._default_solver import linear_solver_for
from ..solve._linearization import gradient, linearize_graph, retract_values


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
    Newton correction `x̃(θ) = x̂ ⊕ δ(θ)`, `δ = −H⁻¹ g(θ)`, with `g` the
    gradient of the cost in tangent coordinates at `x̂` and `H` its exact
    Hessian there, held fixed. Because `g(θ̂) = 0` at the MAP, `δ(θ̂) = 0`
    and `dx̃/dθ = −H⁻¹ ∂g/∂θ` is the implicit derivative of the MAP itself:
    the gradient of the whole evidence, log-determinant included, is that
    of the evidence with the MAP re-solved at every `θ` (checked against
    central differences of re-solved evidences to 1e-5), and the second
    derivative of the cost term is that of the profiled cost (the
    log-determinant's is approximate: it misses the MAP's curvature in
    `θ`). `H⁻¹` is applied by conjugate gradients on exact Hessian products,
    preconditioned by the structured solve of `JᵀJ`, and differentiated as
    a linear solve (`jax.lax.custom_linear_solve`), so `jax.grad`,
    `jax.jacfwd` and `jax.hessian` all work. If CG does not converge (`H` not
    positive definite: `x̂` is not a minimum), the evidence is NaN rather
    than a value with a wrong gradient. (The correction used to take `JᵀJ`
    for `H`, which made the gradient of the log-determinant term, and so
    of the evidence, off by up to 7e-5 relative on small SE(2) loops with
    nonzero residuals and 5e-5 on the oscillator of `tests/test_discover.py`.)

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
    delta = _newton_correction(frozen, x_hat, lin_frozen, linear_solver, rhs)
    x_tilde = retract_values(x_hat, delta)
    lin_t = linearize_graph(_fisher_curvature(graph), x_tilde)
    log_det = normal_log_det(lin_t, linear_solver)
    nll = graph_negative_log_likelihood(graph, x_tilde)
    # Padding variables (pad_graph) have no 2π factor in the NLL either.
    N = jnp.asarray(lin_t.num_tangent - padding_size(graph)[1], lin_t.dtype)
    log_ml = -nll + 0.5 * N * math.log(2 * math.pi) - 0.5 * log_det
    return jnp.asarray(log_ml)


# CG on the exact Hessian, preconditioned by the Gauss-Newton solve: the
# preconditioned eigenvalues cluster at 1 when residuals are small, so a few
# iterations reach the tolerance (on the residual in the preconditioner's
# norm, which rounding lets CG reach however badly scaled the variables are);
# the limit only catches a Hessian that is not positive definite.
_CG_RTOL = 1e-10
_CG_MAX_STEPS = 100


def _newton_correction(frozen, x_hat, lin_frozen, linear_solver, rhs):
    """`H⁻¹ rhs`, with `H` the exact Hessian of the cost of `frozen` in
    tangent coordinates at `x_hat` (constant), as a linear function of `rhs`
    whose derivatives are again solves with `H`."""
    zero = {k: jnp.zeros_like(v) for k, v in rhs.items()}

    def tangent_gradient(d):
        return jax.grad(lambda e: graph_cost(frozen, retract_values(x_hat, e)))(d)

    _, hessian_product = jax.linearize(tangent_gradient, zero)

    def precondition(v):
        w, _ = solve_normal(linear_solver, lin_frozen, None, rhs=v)
        return w

    def solve(matvec, b):
        x, ok = _pcg(matvec, precondition, b)
        return {k: jnp.where(ok, v, jnp.nan) for k, v in x.items()}

    return jax.lax.custom_linear_solve(hessian_product, rhs, solve, symmetric=True)


def _dot(a, b):
    return sum(jnp.sum(a[k] * b[k]) for k in a)


def _pcg(matvec, precondition, b):
    """Preconditioned CG for symmetric positive definite `matvec`; returns
    `(x, converged)`: converged when `rᵀ M r ≤ rtol² bᵀ M b` (`M` the
    preconditioner), not on a direction of non-positive curvature or at the
    iteration limit."""
    z0 = precondition(b)
    bz = _dot(b, z0)
    tol2 = _CG_RTOL * _CG_RTOL * bz

    def cond(carry):
        _, _, _, rz, k, bad = carry
        return (rz > tol2) & (k < _CG_MAX_STEPS) & ~bad

    def body(carry):
        x, r, p, rz, k, _ = carry
        ap = matvec(p)
        pap = _dot(p, ap)
        bad = ~(jnp.isfinite(pap) & (pap > 0))
        alpha = jnp.where(bad, 0.0, rz / jnp.where(bad, 1.0, pap))
        x = {key: x[key] + alpha * p[key] for key in x}
        r = {key: r[key] - alpha * ap[key] for key in r}
        z = precondition(r)
        rz_new = _dot(r, z)
        beta = rz_new / jnp.where(rz == 0, 1.0, rz)
        p = {key: z[key] + beta * p[key] for key in p}
        return x, r, p, rz_new, k + 1, bad

    x0 = {k: jnp.zeros_like(v) for k, v in b.items()}
    init = (x0, b, z0, bz, jnp.asarray(0), jnp.asarray(False))
    x, _, _, rz, _, bad = jax.lax.while_loop(cond, body, init)
    return x, (rz <= tol2) & ~bad


def _fisher_curvature(graph: FactorGraph) -> FactorGraph:
    """`graph` with every noise model replaced by its curvature model (a
    Student-t's Fisher information, a Gaussian), for the log-determinant."""
    factors = []
    for f in graph.factors:
        curvature = f.noise.curvature_model()
        if curvature is not f.noise:
            f = eqx.tree_at(lambda f: f.noise, f, curvature)
        factors.append(f)
    return FactorGraph(factors)
