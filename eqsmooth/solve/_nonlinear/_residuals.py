"""The residual function eqsmooth's solvers solve: the graph's residuals, with
robust noise folded in so that half their squared norm is the graph's cost."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from ...factors import FactorGraph
from ...factors._graph import Values
from ...lie import AbstractLieGroup


def residual_rows(values: Values, graph: FactorGraph) -> tuple[Array, ...]:
    """The residual rows of every factor stack (no derivative guard)."""
    out = []
    for f, rw in zip(graph.factors, graph.whitened_residuals(values)):
        s = jnp.sum(rw * rw, axis=1)
        positive = s > 0
        safe = jnp.where(positive, s, 1.0)
        rho, _ = f.noise.rho(safe)
        _, drho0 = f.noise.rho(jnp.zeros_like(s))
        scale = jnp.where(positive, jnp.sqrt(rho / safe), jnp.sqrt(drho0))
        out.append(rw * scale[:, None])
    return tuple(out)


_AMBIENT = (
    "eqsmooth.solve.graph_residuals was differentiated with respect to Lie-group "
    "values in their ambient coordinates (the stored parameters). That derivative "
    "is not the derivative on the manifold, and an optimality condition written "
    "with it gives wrong gradients. This happens under optimistix's default "
    "adjoint: call optx.least_squares(eqsmooth.solve.graph_residuals, solver, "
    "values, args=graph, adjoint=eqsmooth.ImplicitAdjoint()) (or UnrolledAdjoint / "
    "TruncatedAdjoint), or eqsmooth.least_squares(graph, values, solver); with "
    "optimistix's own solvers use eqsmooth.solve.tangent_least_squares. To "
    "differentiate residuals on the manifold use eqsmooth.linearize or "
    "eqsmooth.solve.TangentResiduals."
)


@eqx.filter_custom_jvp
def _residuals_on_groups(values, graph):
    return residual_rows(values, graph)


@_residuals_on_groups.def_jvp
def _residuals_on_groups_jvp(primals, tangents):
    values, graph = primals
    t_values, t_graph = tangents
    if jax.tree_util.tree_leaves(t_values):
        raise ValueError(_AMBIENT)
    return eqx.filter_jvp(lambda g: residual_rows(values, g), (graph,), (t_graph,))


def _has_groups(values) -> bool:
    is_group = lambda x: isinstance(x, AbstractLieGroup)
    leaves = jax.tree_util.tree_leaves(values, is_leaf=is_group)
    return any(is_group(x) for x in leaves)


def graph_residuals(
    values: Values, graph: FactorGraph
) -> tuple[Float[Array, "_n _m"], ...]:
    """Residuals of every factor stack whose half squared norm is the graph's cost.

    The residual function to pass to `optx.least_squares` together with
    `args=graph` and an eqsmooth solver: `½ Σ‖r‖² = graph.cost(values)`.
    Gaussian factors give their whitened residuals; a robust noise model
    scales row `i` by `√(ρ(sᵢ)/sᵢ)` (`sᵢ` its squared whitened norm; `√ρ'(0)`
    at `sᵢ = 0`).

    Differentiable with respect to the graph. With respect to `values` it is
    differentiable only where they are Euclidean (arrays): for Lie-group
    values, a derivative in the ambient coordinates of the stored parameters
    is not a derivative on the manifold (optimistix's default
    `optx.ImplicitAdjoint` would build a wrong optimality condition from
    it), so asking for one raises a `ValueError` that says what to use
    instead ([`eqsmooth.solve.linearize`][], [`eqsmooth.solve.TangentResiduals`][],
    or an eqsmooth adjoint).

    **Arguments:**

    - `values`: the values dict `{group: stacked states}`.
    - `graph`: the [`eqsmooth.factors.FactorGraph`][].

    **Returns:** a tuple of `(n, m)` arrays, one per factor stack.
    """
    if not isinstance(graph, FactorGraph):
        raise TypeError(
            f"graph_residuals(values, graph): graph must be a FactorGraph, got "
            f"{type(graph).__name__}"
        )
    if _has_groups(values):
        return _residuals_on_groups(values, graph)
    return residual_rows(values, graph)


def manifold_residuals(values: Values, graph: FactorGraph) -> tuple[Array, ...]:
    """`graph_residuals` without the ambient-derivative guard, for callers whose
    values are already on the manifold's chart (e.g. `x̄ ⊕ δ`)."""
    return residual_rows(values, graph)
