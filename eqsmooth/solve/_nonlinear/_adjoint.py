"""How gradients flow through [`eqsmooth.solve.least_squares`][]: the adjoints.

An adjoint decides how the iterations of a nonlinear solve are run, and
therefore what reverse-mode autodiff differentiates:

- [`eqsmooth.solve.UnrolledAdjoint`][]: a `lax.scan` over every iteration;
    the exact derivative of what was computed.
- [`eqsmooth.solve.TruncatedAdjoint`][]: only the last `k` iterations are
    differentiated.
- [`eqsmooth.solve.ImplicitAdjoint`][]: the implicit function theorem at the
    solution, in tangent coordinates.

They are `optimistix.AbstractAdjoint`s: [`eqsmooth.solve.least_squares`][]
runs every solve through `optx.least_squares`, so each adjoint has one code
path, its `apply(primal_fn, rewrite_fn, inputs, tags)`, which chooses the
`while_loop` the solve runs with (a masked `lax.scan`, a stopped
`lax.while_loop` followed by a differentiated scan, or a stopped
`lax.while_loop` under a custom VJP). They find the eqsmooth solver and
graph in optimistix's inputs by type and take the iteration limit from the
`max_steps` optimistix hands to the loop, so they do not depend on the
layout of those inputs. They serve `optx.least_squares(
eqs.solve.graph_residuals, solver, values, args=graph, adjoint=...)` the same
way.
"""

import abc
from typing import Literal

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ...factors import FactorGraph
from ...factors._graph import graph_cost, Values
from .._derivatives import (
    checked_derivative,
    recomputed,
    refuse_derivative,
    stop_arrays,
)
from .._linear._default_solver import linear_solver_for
from .._linear._linear_solver import solve_normal
from .._linearization import Linearization, linearize_graph, retract_values, Tangent
from .._misc import preconditioned_cg, stationary, tree_where
from .._solution import RESULTS
from ._graph_solver import AbstractGraphSolver, graph_of, solve_stats


def _scan_while(cond, body, carry, length: int):
    """`length` iterations of `body(carry)`, each a no-op once `cond` is false."""

    def scan_body(c, _):
        return tree_where(cond(c), body(c), c), None

    carry, _ = lax.scan(scan_body, carry, None, length=length)
    return carry


def _lax_while(cond, body, carry, max_steps: int | None):
    """A `lax.while_loop` that also stops after `max_steps` iterations."""
    if max_steps is None:
        return lax.while_loop(cond, body, carry)

    def cond2(c):
        return cond(c[0]) & (c[1] < max_steps)

    def body2(c):
        return body(c[0]), c[1] + 1

    return lax.while_loop(cond2, body2, (carry, 0))[0]


def _find(tree, cls):
    """The instances of `cls` in a pytree (found by type, so that nothing here
    depends on the order of optimistix's inputs to an adjoint)."""
    is_cls = lambda x: isinstance(x, cls)
    return [x for x in jax.tree_util.tree_leaves(tree, is_leaf=is_cls) if is_cls(x)]


def _graph_solver(inputs) -> AbstractGraphSolver | None:
    """The eqsmooth solver of an optimistix solve (None for optimistix's own)."""
    found = _find(inputs, AbstractGraphSolver)
    return found[0] if len(found) == 1 else None


def _iteration_limit(solver: AbstractGraphSolver | None, max_steps, who: str) -> int:
    """The static number of iterations a scan must cover for an optimistix solve.

    optimistix counts every call of the solver's `step` against its
    `max_steps` (handed to the adjoint's `while_loop`), the first iteration
    of eqsmooth's solvers (which only linearises the initial values)
    included; a fixed-step solver needs only its `num_steps`.
    """
    if max_steps is None:
        raise ValueError(
            f"{who} scans a fixed number of iterations: pass max_steps to "
            "optx.least_squares"
        )
    if solver is not None:
        return min(max_steps, solver.iteration_limit(max_steps))
    return max_steps


class AbstractAdjoint(optx.AbstractAdjoint):
    """How [`eqsmooth.solve.least_squares`][] is differentiated.

    Pass an instance as `least_squares(..., adjoint=...)`, or as
    `optx.least_squares(eqs.solve.graph_residuals, solver, values,
    args=graph, adjoint=...)`: every eqsmooth adjoint is an
    `optimistix.AbstractAdjoint`. Every adjoint gives the same forward
    result; they differ in what reverse-mode autodiff computes and at which
    memory cost.

    Subclasses implement optimistix's `apply(primal_fn, rewrite_fn, inputs,
    tags)` and say whether the solve's intermediate iterates are
    differentiable.
    """

    @abc.abstractmethod
    def differentiates_iterates(self) -> bool:
        """Whether reverse-mode autodiff reaches the intermediate iterates (and
        so `Solution.stats["cost_history"]`); an adjoint that differentiates
        the solution only says no, and differentiating the record raises."""


class UnrolledAdjoint(AbstractAdjoint):
    """Differentiate through every iteration (a `lax.scan` of masked steps).

    The loop always runs `max_steps` iterations of the solver's step; those
    after the solver has stopped are masked out (computed, then discarded),
    so prefer a small `max_steps` or
    [`eqsmooth.solve.FixedStepGaussNewton`][], whose `num_steps` sets the
    length. Reverse-mode autodiff then gives the exact derivative of what
    was computed, including through the initial values. With
    `FixedStepGaussNewton(num_steps=K)` started at the ground truth this is
    the surrogate loss of Yi et al. (2021). Memory grows linearly with the
    number of iterations. Forward mode (`jax.jvp`) works too.

    Through `optx.least_squares` it works with any optimistix solver; the
    scan covers `max_steps` iterations (`num_steps` for
    [`eqsmooth.solve.FixedStepGaussNewton`][]).
    """

    def differentiates_iterates(self) -> bool:
        return True

    def apply(self, primal_fn, rewrite_fn, inputs, tags):
        del rewrite_fn, tags
        solver = _graph_solver(inputs)

        def while_loop(cond, body, carry, max_steps):
            limit = _iteration_limit(solver, max_steps, "UnrolledAdjoint")
            return _scan_while(cond, body, carry, limit)

        return primal_fn(inputs + (while_loop,))


class TruncatedAdjoint(AbstractAdjoint):
    """Differentiate through the last `num_steps` iterations only.

    The earlier iterations run in a `while_loop` with gradients stopped; the
    last `num_steps + 1` iterations are replayed differentiated: the first
    of them tries a step computed from stopped quantities, linearises its
    trial point with the live graph and solves the next step live, so the
    last `num_steps` steps are differentiated. Memory is that of
    `num_steps + 1` iterations. When the solver stops early (convergence),
    the replayed iterations are recomputed from a ring buffer of the loop
    states, so the forward result is the same as with any other adjoint. If
    the solve ends within its first `max_steps - num_steps` iterations and
    takes at most `num_steps` steps (iterations: one more than steps), the
    gradient equals that of [`eqsmooth.solve.UnrolledAdjoint`][], gradients
    with respect to the initial values included; otherwise those are zero.
    For Levenberg-Marquardt, a rejected step among the replayed ones leaves
    one step fewer differentiated. [`eqsmooth.solve.FixedStepGaussNewton`][]
    takes its last step after the loop, so `num_steps` iterations are
    replayed for it: its result is then exactly an unrolled
    `num_steps`-step solve started at the stopped values after the first
    `K - num_steps` steps.

    `num_steps=1` at a converged solution is the "one Gauss-Newton step from
    the stopped solution" approximation of the implicit gradient. The same
    loop serves eqsmooth's driver and `optx.least_squares`.

    **Arguments:**

    - `num_steps`: `k >= 1`, the number of differentiated iterations.
    """

    num_steps: int = eqx.field(static=True, default=1)

    def __check_init__(self):
        if not isinstance(self.num_steps, int) or self.num_steps < 1:
            raise ValueError(
                "TruncatedAdjoint.num_steps must be an int >= 1, got "
                f"{self.num_steps!r}"
            )

    def differentiates_iterates(self) -> bool:
        # The iterates before the last `num_steps` get zero derivatives.
        return True

    def apply(self, primal_fn, rewrite_fn, inputs, tags):
        del rewrite_fn, tags
        solver = _graph_solver(inputs)
        k = self.num_steps
        after = 0 if solver is None else solver.steps_after_loop()

        def while_loop(cond, body, carry, max_steps):
            limit = _iteration_limit(solver, max_steps, "TruncatedAdjoint")
            return _truncated_loop(cond, body, carry, limit, k, after)

        return primal_fn(inputs + (while_loop,))


def _truncated_loop(cond, body, carry0, limit: int, k: int, after: int = 0):
    """The loop of `TruncatedAdjoint`: stopped iterations, then `k + 1 - after`
    replayed ones whose first step is computed from stopped quantities.

    `body` closes over the live problem; the stopped phase stops its outputs.
    A ring buffer of the last `m` loop states lets a solve that stops early
    restart `m` iterations before its end. A solver that takes `after` of
    its steps after the loop (the fixed-step solver's last one) needs that
    many iterations fewer replayed for `k` differentiated steps.
    """
    m = k + 1 - after
    free = limit - m
    if free <= 0:
        return _scan_while(cond, body, carry0, limit)
    start0 = stop_arrays(carry0)
    ring0 = jax.tree_util.tree_map(
        lambda x: jnp.broadcast_to(x, (m,) + jnp.shape(x)), start0
    )

    def cond1(loop):
        carry, n, _ = loop
        return cond(carry) & (n < free)

    def body1(loop):
        carry, n, ring = loop
        ring = jax.tree_util.tree_map(lambda r, x: r.at[n % m].set(x), ring, carry)
        return stop_arrays(body(carry)), n + 1, ring

    carry1, n1, ring = lax.while_loop(cond1, body1, (start0, 0, ring0))
    stopped = ~cond(carry1)
    from_ring = jax.tree_util.tree_map(lambda r: r[(n1 - m) % m], ring)
    resumed = tree_where(stopped & (n1 >= m), from_ring, carry1)
    # At most k iterations in all: differentiate them all (from the live
    # start), as `run` does.
    start = tree_where(stopped & (n1 <= k), carry0, resumed)
    return _scan_while(cond, body, start, m)


_HESSIANS = ("exact", "gauss_newton")


class ImplicitAdjoint(AbstractAdjoint):
    """Differentiate the optimality condition at the solution (implicit function thm).

    The forward pass is the solver's ordinary `while_loop`, run with gradients
    stopped. Write the solution as `x = x* ⊕ δ(θ)` with `x*` the (stopped)
    solution and `θ` every inexact array of the graph. The tangent gradient
    `g(δ, θ) = ∇_δ C(x* ⊕ δ; θ)` of the cost vanishes at `δ = 0`, so
    `dδ/dθ = −H⁻¹ ∂g/∂θ` with `H = ∇²_δ C` at `δ = 0`. Working in tangent
    coordinates at `x*` matters: the same argument in the ambient coordinates
    of Lie groups gives wrong gradients.

    The backward pass (an `eqx.filter_custom_vjp`, so the forward pass costs
    nothing extra) solves `H w = x̄` for the incoming cotangent and returns
    `−(∂g/∂θ)ᵀ w`:

    - `hessian="exact"`: `H` is the exact Hessian of the (robust) cost,
        applied matrix-free as a forward-over-reverse product; the system is
        solved by conjugate gradients preconditioned with the solver's own
        structured solve of `JᵀJ`. Matches the derivative of the converged
        minimiser for nonlinear problems with nonzero residuals. Each CG
        iteration costs one Hessian product and one structured solve; for
        small residuals a few iterations suffice.
    - `hessian="gauss_newton"`: `H ≈ JᵀJ`, one structured solve. Exact for
        linear problems and zero residuals, an approximation otherwise.

    If the solve failed with `RESULTS.nonfinite_problem` or
    `RESULTS.linear_solve_failed` (e.g. with `throw=False`), there is no
    optimum to differentiate and every gradient that reaches the solve is
    NaN (never a plausible finite value or zero), so a training loop sees it
    (see `eqsmooth.learn.train(on_nonfinite=...)`). Other codes (such as
    `max_steps_reached`) give the gradient at the returned point.

    The gradient is exact only at a stationary point: run the solver to
    convergence. A [`eqsmooth.solve.FixedStepGaussNewton`][] solve that stops
    short of a stationary point (`max |Jᵀr| > √ε · max(1, 2 cost)`) raises an
    `EquinoxRuntimeError` when differentiated (use
    [`eqsmooth.solve.UnrolledAdjoint`][] there). Gradients with respect to
    the initial values are zero (the minimiser does not depend on them).
    What the solution's state keeps is differentiable too: `state.lin` (the
    linearisation at the solution, so marginal covariances and
    log-determinants of a `Solution`) and `stats["final_cost"]` /
    `stats["initial_cost"]` carry their exact derivatives, computed in the
    backward pass by differentiating the linearisation at the solution;
    differentiating `stats["cost_history"]` (intermediate iterates) raises.
    Only reverse mode is supported (`jax.grad`, `jax.vjp`), not `jax.jvp`.

    Through `optx.least_squares` (with `args` the graph, any least-squares
    solver that keeps the values' types) it is the adjoint to use for
    Lie-group values: `optx.ImplicitAdjoint` would differentiate the
    optimality condition in ambient coordinates, which is wrong there (and
    so refused by [`eqsmooth.solve.graph_residuals`][]). It linearises once
    more at the solution (eqsmooth's driver reuses the solver's last
    linearisation), and the `lin` of the solver state optimistix returns is
    differentiable as above.

    **Arguments:**

    - `hessian`: `"exact"` or `"gauss_newton"`.
    - `rtol`, `atol`: CG stops when `‖H w − x̄‖₂ ≤ max(rtol ‖x̄‖₂, atol)` (`rtol`
        is raised to `10 ε` of the dtype if smaller).
    - `max_steps`: CG iteration limit; the last iterate is used if it is
        reached.
    """

    hessian: Literal["exact", "gauss_newton"] = eqx.field(static=True, default="exact")
    rtol: float = eqx.field(static=True, default=1e-10)
    atol: float = eqx.field(static=True, default=0.0)
    max_steps: int = eqx.field(static=True, default=50)

    def __check_init__(self):
        if self.hessian not in _HESSIANS:
            raise ValueError(
                f"ImplicitAdjoint.hessian must be one of {_HESSIANS}, got "
                f"{self.hessian!r}"
            )
        if self.rtol < 0 or self.atol < 0:
            raise ValueError(
                f"ImplicitAdjoint needs rtol >= 0 and atol >= 0, got rtol={self.rtol}, "
                f"atol={self.atol}"
            )
        if self.max_steps < 1:
            raise ValueError(
                f"ImplicitAdjoint.max_steps must be >= 1, got {self.max_steps}"
            )

    def differentiates_iterates(self) -> bool:
        return False

    def apply(self, primal_fn, rewrite_fn, inputs, tags):
        del rewrite_fn, tags
        graphs = _find(inputs, FactorGraph)
        if len(graphs) != 1:
            raise TypeError(
                "eqsmooth's ImplicitAdjoint differentiates an eqsmooth graph solve "
                "(optx.least_squares(eqsmooth.solve.graph_residuals, solver, values, "
                "args=graph)); for other problems, or "
                "eqsmooth.solve.tangent_least_squares, use optimistix.ImplicitAdjoint()"
            )
        solver = _graph_solver(inputs)
        if solver is None:
            # Another optimistix solver on the graph: its loop runs stopped, and
            # the values it returns get the implicit derivative.
            (graph,) = graphs
            x_star, residual = primal_fn(stop_arrays(inputs) + (_lax_while,))
            x_star, residual = stop_arrays((x_star, residual))
            lin = linearize_graph(stop_arrays(graph), x_star)
            linear_solver = linear_solver_for(None, lin)
            failed = ~jnp.isfinite(lin.cost)
            delta = _implicit_delta(graph, x_star, lin, self, linear_solver, failed)
            return retract_values(x_star, delta), residual
        # An eqsmooth solver: its loop runs stopped, and its own `finish` and
        # stats, in `postprocess`, see the solution with its implicit
        # derivative (`_Implicitly`).
        (graph,) = graphs
        implicit = _Implicitly(solver, self)
        swap = lambda x: implicit if x is solver else x
        is_solver = lambda x: x is solver
        inputs = jax.tree_util.tree_map(swap, inputs, is_leaf=is_solver)

        def while_loop(cond, body, carry, max_steps):
            # Every output of the loop (the state optimistix hands back as
            # `Solution.state` included) is stopped, and refuses a derivative
            # instead of giving a silent zero.
            out = _lax_while(
                cond, lambda c: stop_arrays(body(c)), stop_arrays(carry), max_steps
            )
            return refuse_derivative(graph, out, _LAST_ITERATION)

        return primal_fn(inputs + (while_loop,))


_LAST_ITERATION = (
    "Under eqsmooth's ImplicitAdjoint the loop's last state (optimistix's "
    "Solution.state) has no derivative: the implicit adjoint differentiates the "
    "solution only. Differentiate Solution.stats['linearization'] (the "
    "linearisation at the solution) or stats['final_cost'], or solve with "
    "eqsmooth.least_squares, whose Solution.state.lin is differentiable"
)


class _Implicitly(eqx.Module):
    """An eqsmooth solver whose solution is differentiated implicitly.

    `init`, `step` and `terminate` are the solver's (its loop runs stopped,
    `_stopped_while`). `postprocess` runs the solver's `finish` with
    gradients stopped, writes the solution as `x* ⊕ δ(θ)` with the implicit
    derivative of `δ` (`_implicit_delta`), and gives the solver's stats the
    linearisation at `x` with its exact derivative.
    """

    solver: AbstractGraphSolver
    adjoint: ImplicitAdjoint

    def init(self, fn, y, args, options, f_struct, aux_struct, tags):
        return self.solver.init(fn, y, args, options, f_struct, aux_struct, tags)

    def step(self, fn, y, args, options, state, tags):
        return self.solver.step(fn, y, args, options, state, tags)

    def terminate(self, fn, y, args, options, state, tags):
        return self.solver.terminate(fn, y, args, options, state, tags)

    def postprocess(self, fn, y, aux, args, options, state, tags, result):
        del fn, options, tags, result
        solver = self.solver
        graph = graph_of(args, type(solver).__name__)
        x_star, state, _ = solver.finish(
            stop_arrays(graph), stop_arrays(y), stop_arrays(state)
        )
        lin = state.lin
        linear_solver = linear_solver_for(solver.linear_solver, lin)
        # A non-finite problem at the returned point is the failure whose
        # gradient must be NaN (see ImplicitAdjoint).
        failed = ~jnp.isfinite(lin.cost)
        delta = _implicit_delta(graph, x_star, lin, self.adjoint, linear_solver, failed)
        x = retract_values(x_star, delta)
        if not solver.reaches_minimum():
            x = checked_derivative(
                x,
                lin,
                lambda lin: ~stationary(lin),
                "ImplicitAdjoint differentiates the optimality condition at a "
                f"minimum, but this {type(solver).__name__} solve stopped after its "
                "fixed number of steps short of a stationary point: use "
                "eqsmooth.UnrolledAdjoint() or TruncatedAdjoint(k)",
            )
        # The linearisation at the solution, with the derivative of
        # linearising the live graph at `x` (so marginals, log-determinants
        # and the final cost are differentiable).
        live = recomputed((graph, x), lin, linearize_graph)
        state = eqx.tree_at(lambda s: s.lin, state, live)
        return x, aux, solve_stats(state, live.cost)


def _zeros(lin: Linearization) -> Tangent:
    # Zeros that (trivially) depend on the linearisation: under `vmap` the
    # output of the custom-vjp function must be batched like its inputs. A
    # constant output would be unbatched, and JAX would then sum its cotangent
    # over the batch before the backward pass, mixing the batch elements.
    keep = jnp.isfinite(lin.cost) | True
    return {
        g.name: jnp.where(keep, jnp.zeros((g.count, g.dim), lin.dtype), 0.0)
        for g in lin.layout
    }


def _tangent_gradient(graph: FactorGraph, x_star: Values, delta: Tangent) -> Tangent:
    """`∇_δ C(x* ⊕ δ)`: gradient of the true (robust) cost in tangent coordinates."""
    return jax.grad(lambda d: graph_cost(graph, retract_values(x_star, d)))(delta)


@eqx.filter_custom_vjp
def _implicit_delta(graph, x_star, lin, adjoint, linear_solver, failed):
    del graph, x_star, adjoint, linear_solver, failed
    return _zeros(lin)


@_implicit_delta.def_fwd
def _implicit_delta_fwd(perturbed, graph, x_star, lin, adjoint, linear_solver, failed):
    del perturbed, graph, x_star, adjoint, linear_solver, failed
    return _zeros(lin), None


@_implicit_delta.def_bwd
def _implicit_delta_bwd(
    residuals, grad_obj, perturbed, graph, x_star, lin, adjoint, linear_solver, failed
):
    del residuals
    zero = _zeros(lin)
    v = {k: zero[k] if grad_obj[k] is None else grad_obj[k] for k in zero}

    def structured_solve(rhs):
        w, result = solve_normal(linear_solver, lin, None, rhs=rhs)
        # A singular or indefinite normal matrix (an unfixed gauge freedom:
        # the solve ended `linear_solve_failed` at a finite cost) leaves the
        # optimum undetermined: NaN, never the zero step of a failed solve.
        # (An inexact PCG iterate, `max_steps_reached`, is still a solve.)
        solved = (result == RESULTS.successful) | (result == RESULTS.max_steps_reached)
        return {k: jnp.where(solved, w[k], jnp.nan) for k in w}

    if adjoint.hessian == "gauss_newton":
        w = structured_solve(v)
    else:
        _, hvp = jax.linearize(lambda d: _tangent_gradient(graph, x_star, d), zero)
        eps = float(np.finfo(lin.dtype).eps)
        rtol = max(adjoint.rtol, 10 * eps)
        # Flexible CG: the preconditioner may itself be an inexact solve (PCG).
        w, *_ = preconditioned_cg(
            hvp, structured_solve, v, rtol, adjoint.atol, adjoint.max_steps, True
        )
        # CG never calls its preconditioner for a zero right-hand side, so one
        # structured solve tells whether the normal matrix is regular.
        regular = jnp.all(
            jnp.stack([jnp.all(jnp.isfinite(a)) for a in structured_solve(v).values()])
        )
        w = {k: jnp.where(regular, w[k], jnp.nan) for k in w}
    neg_w = {k: jnp.where(failed, jnp.nan, -w[k]) for k in w}
    _, vjp_fn = eqx.filter_vjp(lambda g: _tangent_gradient(g, x_star, zero), graph)
    (grad_graph,) = vjp_fn(neg_w)
    return jax.tree_util.tree_map(
        lambda g, p: g if p else None,
        grad_graph,
        perturbed,
        is_leaf=lambda x: x is None,
    )
