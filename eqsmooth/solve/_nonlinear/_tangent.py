"""Any optimistix least-squares solver on an eqsmooth graph, in tangent coordinates.

optimistix's solvers update `y` additively, which is wrong for Lie-group
values (a rotation matrix plus a step is not a rotation). In the tangent
chart at a base point `x̄` the unknown is a flat tangent dict `δ` and the
values are `x̄ ⊕ δ`, so the problem is an ordinary Euclidean least-squares
problem that any optimistix solver can take.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, Float

from ...factors import FactorGraph
from ...factors._graph import graph_cost, Values
from .._linearization import retract_values, Tangent
from .._solution import promote_result, raise_unless_successful, Solution
from ._residuals import manifold_residuals


class TangentResiduals(eqx.Module):
    """`δ ↦ graph_residuals(x̄ ⊕ δ, graph)`, with `args = (graph, x̄)`.

    The residual function [`eqsmooth.solve.tangent_least_squares`][] hands to
    `optx.least_squares`; `δ` is a tangent dict `{group: (N_g, d_g)}`.
    """

    def __call__(
        self, delta: Tangent, args: tuple[FactorGraph, Values]
    ) -> tuple[Float[Array, "_n _m"], ...]:
        graph, base = args
        return manifold_residuals(retract_values(base, delta), graph)


def tangent_least_squares(
    graph: FactorGraph,
    values: Values,
    solver: optx.AbstractLeastSquaresSolver | optx.AbstractMinimiser,
    *,
    max_steps: int = 256,
    num_charts: int = 1,
    adjoint: optx.AbstractAdjoint = optx.ImplicitAdjoint(),
    options: dict[str, Any] | None = None,
    throw: bool = True,
) -> Solution:
    """Minimise the cost of `graph` with an optimistix solver, in tangent coordinates.

    Runs `optx.least_squares(TangentResiduals(), solver, δ₀ = 0, args=(graph,
    x̄))` with `x̄ = values`: the solver sees the Euclidean problem
    `min_δ ½‖r(x̄ ⊕ δ)‖²`, whatever the values' groups. With `num_charts > 1`
    the solve is repeated from the chart at the previous solution (useful
    when the solution is far from `values`, e.g. rotations near π away).
    Because the problem is Euclidean, optimistix's own adjoints are correct
    for it (its default `optx.ImplicitAdjoint` differentiates the optimality
    condition in tangent coordinates).

    **Arguments:**

    - `graph`: the [`eqsmooth.factors.FactorGraph`][].
    - `values`: initial values, a dict `{group: stacked states}`.
    - `solver`: e.g. `optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)` or
        `optx.GaussNewton(rtol, atol, linear_solver=lx.Normal(lx.CG(...)))`.
    - `max_steps`: iteration limit of each chart's solve.
    - `num_charts`: how many charts to solve in (at least 1).
    - `adjoint`: an optimistix adjoint.
    - `options`: passed to `optx.least_squares`.
    - `throw`: raise if the (last) solve did not succeed.

    **Returns:**

    A [`eqsmooth.solve.Solution`][] whose `value` is the values dict, `stats`
    has `num_steps` (summed over charts), `initial_cost` and `final_cost`,
    and `state` is optimistix's final solver state.
    """
    if not isinstance(graph, FactorGraph):
        raise TypeError(f"graph must be a FactorGraph, got {type(graph).__name__}")
    if not isinstance(
        solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)
    ):
        raise TypeError(
            "solver must be an optimistix least-squares solver or minimiser, got "
            f"{type(solver).__name__}"
        )
    if not isinstance(num_charts, int) or num_charts < 1:
        raise ValueError(f"num_charts must be an int >= 1, got {num_charts!r}")
    sol = _tangent_least_squares(
        graph, values, solver, max_steps, num_charts, adjoint, options
    )
    return raise_unless_successful(sol) if throw else sol


@eqx.filter_jit
def _tangent_least_squares(
    graph, values, solver, max_steps, num_charts, adjoint, options
):
    layout = graph.validate(values)
    leaves = jax.tree_util.tree_leaves(values)
    dtype = jnp.result_type(*[x.dtype for x in leaves])
    initial_cost = graph_cost(graph, values)
    base = values
    num_steps = jnp.array(0)
    sol = None
    for _ in range(num_charts):
        delta0 = {g.name: jnp.zeros((g.count, g.dim), dtype) for g in layout}
        sol = optx.least_squares(
            TangentResiduals(),
            solver,
            delta0,
            args=(graph, base),
            options=options,
            max_steps=max_steps,
            adjoint=adjoint,
            throw=False,
        )
        base = retract_values(base, sol.value)
        num_steps = num_steps + sol.stats["num_steps"]
    assert sol is not None
    result = promote_result(sol.result)
    stats = {
        "num_steps": num_steps,
        "initial_cost": initial_cost,
        "final_cost": graph_cost(graph, base),
    }
    return Solution(value=base, result=result, stats=stats, state=sol.state)
