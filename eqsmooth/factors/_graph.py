from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from ..manifold import tangent_dim
from ._factor import AbstractFactor, check_row_leaves, evaluate_rows
from ._merge import warn_if_unstacked
from ._variables import Var


Values = dict[str, PyTree]


class GroupLayout(eqx.Module):
    """Static description of one variable group: name, count and tangent dim."""

    name: str = eqx.field(static=True)
    count: int = eqx.field(static=True)
    dim: int = eqx.field(static=True)


def group_count(name: str, group: PyTree) -> int:
    leaves = jax.tree_util.tree_leaves(group)
    if not leaves:
        raise ValueError(f"variable group {name!r} has no array leaves")
    counts = {jnp.shape(leaf)[0] if jnp.ndim(leaf) else None for leaf in leaves}
    if len(counts) != 1 or None in counts:
        raise ValueError(
            f"variable group {name!r}: every leaf needs the same leading axis (one "
            f"entry per variable); got leaf shapes "
            f"{[jnp.shape(leaf) for leaf in leaves]}"
        )
    return counts.pop()


def values_layout(values: Values) -> tuple[GroupLayout, ...]:
    """The static layout (sorted by group name) of a values dict."""
    if not isinstance(values, dict):
        raise TypeError(
            "values must be a dict {group_name: stacked states}, got "
            f"{type(values).__name__}"
        )
    out = []
    for name in sorted(values):
        group = values[name]
        count = group_count(name, group)
        out.append(GroupLayout(name, count, tangent_dim(group, batch_ndim=1)))
    return tuple(out)


def gather(group: PyTree, var: Var) -> PyTree:
    """Select the rows `var.ids` of a stacked group (a static slice if contiguous).

    Dynamic indices ([`eqsmooth.factors.Var.dynamic`][]) out of range gather
    NaN (JAX would otherwise clamp them to the last variable, silently), so a
    solve reports non-finite residuals instead of a wrong answer; concrete
    ones are checked earlier, by `FactorGraph.validate`."""
    if var.is_dynamic:
        # Negative indices would wrap around: send them past the end too.
        ids = jnp.where(var.index < 0, group_count(var.group, group), var.index)
        return jax.tree_util.tree_map(
            lambda a: jnp.take(a, ids, axis=0, mode="fill"), group
        )
    ids = var.ids
    n = ids.shape[0]
    if n and np.array_equal(ids, np.arange(ids[0], ids[0] + n)):
        start = int(ids[0])
        return jax.tree_util.tree_map(lambda a: a[start : start + n], group)
    return jax.tree_util.tree_map(lambda a: a[ids], group)


class FactorGraph(eqx.Module):
    """A factor graph: a tuple of stacked factors (one Module per factor type).

    The graph holds data and parameters only; which variables each row
    touches is static (in each factor's `variables`). Values are a dict
    `{group_name: stacked states}`.

    **Arguments:**

    - `factors`: a sequence of [`eqsmooth.factors.AbstractFactor`][].
    """

    factors: tuple[AbstractFactor, ...]

    def __init__(self, factors: Sequence[AbstractFactor]):
        factors = tuple(factors)
        for f in factors:
            if not isinstance(f, AbstractFactor):
                raise TypeError(
                    "FactorGraph takes AbstractFactor instances, got "
                    f"{type(f).__name__}"
                )
        if not factors:
            raise ValueError("FactorGraph needs at least one factor")
        warn_if_unstacked(factors)
        self.factors = factors

    def validate(self, values: Values) -> tuple[GroupLayout, ...]:
        """Check the graph against `values` (trace-time) and return the layout.

        Raises `ValueError` naming the factor type, variable group and indices
        at fault.
        """
        layout = values_layout(values)
        counts = {g.name: g.count for g in layout}
        for f in self.factors:
            name = type(f).__name__
            for k, var in enumerate(f.variables):
                if var.group not in counts:
                    raise ValueError(
                        f"{name}: variable {k} refers to group {var.group!r}, which "
                        f"is not in the values (groups: {sorted(counts)})"
                    )
                if var.is_dynamic and isinstance(var.index, jax.core.Tracer):
                    continue  # traced: out of range gathers NaN (see gather)
                ids = np.asarray(var.index)
                if len(ids) and (ids.max() >= counts[var.group] or ids.min() < 0):
                    bad = ids[(ids >= counts[var.group]) | (ids < 0)]
                    raise ValueError(
                        f"{name}: variable {k} (group {var.group!r}) has indices "
                        f"{bad[:5].tolist()} out of range for {counts[var.group]} "
                        "variables"
                    )
            check_row_leaves(f)
        return layout

    def states_of(self, factor: AbstractFactor, values: Values) -> tuple[PyTree, ...]:
        """The per-row stacked states touched by `factor`."""
        return tuple(gather(values[v.group], v) for v in factor.variables)

    def residuals(self, values: Values) -> tuple[Float[Array, "_n _m"], ...]:
        """Unwhitened residuals of every factor stack."""
        self.validate(values)
        return tuple(evaluate_rows(f, self.states_of(f, values)) for f in self.factors)

    def whitened_residuals(self, values: Values) -> tuple[Float[Array, "_n _m"], ...]:
        """Whitened (not robustified) residuals of every factor stack."""
        out = []
        for f, r in zip(self.factors, self.residuals(values)):
            f.noise.check_shapes(type(f).__name__, *r.shape)
            out.append(f.noise.whiten(r))
        return tuple(out)

    def cost(self, values: Values) -> Float[Array, ""]:
        """Total cost `½ Σ ρ(‖R r‖²)` (Gaussian factors: half the squared norm).

        Compiled (`eqx.filter_jit`): called outside `jit` it costs one
        program per graph structure and value shapes, not one per JAX
        operation.
        """
        return _compiled_cost(self, values)

    def negative_log_likelihood(self, values: Values) -> Float[Array, ""]:
        """Negative log-likelihood at `values`: cost − Σ log normaliser.

        For Gaussian factors this is `cost − Σ log det R + ½ (Σ n m) log 2π`,
        the paper's "joint NLL" when `values` is the ground truth. A
        [`eqsmooth.factors.StudentTNoise`][] factor contributes its exact
        Student-t density; the robust kernels (Huber, Cauchy, ...) contribute
        their loss with their base model's Gaussian constant (see
        [`eqsmooth.factors.AbstractNoiseModel.log_normalizer`][]). Compiled,
        like [`eqsmooth.factors.FactorGraph.cost`][].
        """
        return _compiled_negative_log_likelihood(self, values)


# The uncompiled forms, for code that is itself traced (solvers, losses): their
# programs stay free of nested calls. The methods above are the compiled ones.


def graph_cost(graph: FactorGraph, values: Values) -> Float[Array, ""]:
    """`FactorGraph.cost`, uncompiled."""
    return _cost_of(graph, graph.whitened_residuals(values))


def graph_negative_log_likelihood(
    graph: FactorGraph, values: Values
) -> Float[Array, ""]:
    """`FactorGraph.negative_log_likelihood`, uncompiled."""
    whitened = graph.whitened_residuals(values)  # traced once, for both terms
    total = _cost_of(graph, whitened)
    for f, rw in zip(graph.factors, whitened):
        n, m = rw.shape
        total = total - f.noise.log_normalizer(n, m)
    return total


def _cost_of(graph: FactorGraph, whitened) -> Float[Array, ""]:
    total = 0.0
    for f, rw in zip(graph.factors, whitened):
        rho, _ = f.noise.rho(jnp.sum(rw * rw, axis=1))
        total = total + 0.5 * jnp.sum(rho)
    return jnp.asarray(total)


_compiled_cost = eqx.filter_jit(graph_cost)
_compiled_negative_log_likelihood = eqx.filter_jit(graph_negative_log_likelihood)
