"""Many small graphs of one structure in one call: one compiled, vmapped solve."""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from ..._stack import stack_trees
from ...factors import FactorGraph
from ...factors._graph import Values
from .._solution import RESULTS, Solution
from ._adjoint import AbstractAdjoint, ImplicitAdjoint
from ._least_squares import least_squares


def _check_batch_axes(graphs: FactorGraph, values: Values) -> None:
    """The graphs' and the values' leading axes must agree (one values dict
    given for a batch was read as already batched: a `vmap` size error)."""
    sizes = {
        jnp.shape(a)[0] for a in jax.tree_util.tree_leaves(graphs) if eqx.is_array(a)
    }
    if len(sizes) != 1:
        return  # not a stacked graph: vmap names what it cannot map
    (B,) = sizes
    for path, leaf in jax.tree_util.tree_flatten_with_path(values)[0]:
        if jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != B:
            raise ValueError(
                f"least_squares_batch: values{jax.tree_util.keystr(path)} has shape "
                f"{jnp.shape(leaf)} but the batch has {B} graphs: give one values "
                "dict per graph (a sequence), or one dict whose leaves carry the "
                f"batch axis first (e.g. eqsmooth.learn.stack_trees([values] * {B}))"
            )


def least_squares_batch(
    graphs: Sequence[FactorGraph] | FactorGraph,
    values: Sequence[Values] | Values,
    solver: optx.AbstractLeastSquaresSolver,
    *,
    max_steps: int = 100,
    adjoint: AbstractAdjoint = ImplicitAdjoint(),
    throw: bool = True,
) -> Solution:
    """Solve many graphs of one structure in one call (one compiled program).

    The graphs must share their structure (factor types, stack sizes and
    variable indices, which are static); their measurements, noise and
    initial values may differ. They are stacked along a new leading axis and
    solved by one `jax.vmap`-ed, compiled [`eqsmooth.solve.least_squares`][]:
    one Python call and one program for the whole batch, instead of one
    dispatch per graph.

    **Arguments:**

    - `graphs`: a sequence of [`eqsmooth.factors.FactorGraph`][]s, or one
        graph whose array leaves already carry the batch axis (e.g. from
        [`eqsmooth.learn.stack_trees`][]).
    - `values`: the initial values: a sequence of values dicts, or one dict
        with the batch axis.
    - `solver`, `max_steps`, `adjoint`: as for `least_squares`.
    - `throw`: raise if any graph's solve did not succeed, naming which
        (otherwise read `Solution.result`, one code per graph).

    **Returns:** a [`eqsmooth.solve.Solution`][] whose leaves carry the batch
    axis (`sol.value["x"][i]` is graph `i`'s solution).
    """
    if not isinstance(graphs, FactorGraph):
        graphs = list(graphs)
        if not graphs:
            raise ValueError("least_squares_batch: no graphs")
        for i, g in enumerate(graphs):
            if not isinstance(g, FactorGraph):
                raise TypeError(
                    f"least_squares_batch: graphs[{i}] is a {type(g).__name__}, "
                    "not a FactorGraph"
                )
        graphs = stack_trees(graphs)
    if not isinstance(values, dict):
        values = stack_trees(list(values))
    _check_batch_axes(graphs, values)
    sol = _solve_batch(graphs, values, solver, adjoint, max_steps=max_steps)
    if throw:
        (code,) = jax.tree_util.tree_leaves(sol.result)
        code = np.asarray(code)
        (success,) = jax.tree_util.tree_leaves(RESULTS.successful)
        bad = np.flatnonzero(code != np.asarray(success))
        if bad.size:
            first = jax.tree_util.tree_map(lambda x: x[int(bad[0])], sol.result)
            raise eqx.EquinoxRuntimeError(
                f"least_squares_batch: the solves of graphs {bad[:8].tolist()} "
                f"({bad.size} of {code.size}) did not succeed; graph {int(bad[0])}: "
                f"{RESULTS[first]}"
            )
    return sol


@eqx.filter_jit
def _solve_batch(graphs, values, solver, adjoint, *, max_steps):
    def one(graph, init):
        return least_squares(
            graph, init, solver, max_steps=max_steps, adjoint=adjoint, throw=False
        )

    return jax.vmap(one)(graphs, values)
