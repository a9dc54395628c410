"""Stacking many graphs (or values) of identical structure for `jax.vmap`."""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree


def stack_trees(trees: Sequence[PyTree]) -> PyTree:
    """Stack pytrees of identical structure along a new leading batch axis.

    Use it to batch [`eqsmooth.factors.FactorGraph`][]s of one structure
    (same factor types and the same variable indices, which are static) or
    their values dicts, then `jax.vmap` a loss over the batch:

    ```python
    graphs = stack_trees([build_graph(d) for d in sequences])
    truths = stack_trees(truth_list)
    losses = jax.vmap(surrogate_loss)(graphs, truths)
    ```

    Array leaves are stacked; non-array leaves must be equal.

    **Arguments:**

    - `trees`: a non-empty sequence of pytrees.

    **Returns:** one pytree whose array leaves have a new leading axis of
    length `len(trees)`.
    """
    trees = list(trees)
    if not trees:
        raise ValueError("stack_trees: nothing to stack")
    arrays0, static0 = eqx.partition(trees[0], eqx.is_array)
    def0 = jax.tree_util.tree_structure(arrays0)
    shapes0 = [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(arrays0)]
    parts = []
    for i, tree in enumerate(trees):
        arrays, static = eqx.partition(tree, eqx.is_array)
        if jax.tree_util.tree_structure(arrays) != def0 or not eqx.tree_equal(
            static, static0
        ):
            raise ValueError(
                f"stack_trees: tree {i} differs in structure from tree 0 (a "
                "different factor set, variable indices or static field)"
            )
        shapes = [(x.shape, x.dtype) for x in jax.tree_util.tree_leaves(arrays)]
        if shapes != shapes0:
            raise ValueError(
                f"stack_trees: tree {i} has leaf shapes/dtypes {shapes}, tree 0 has "
                f"{shapes0}"
            )
        parts.append(arrays)
    stacked = jax.tree_util.tree_map(_stack, *parts)
    return eqx.combine(stacked, static0)


def _stack(*xs):
    # `jnp.stack` of N operands compiles a program with N inputs: its
    # compilation grows with N (28.6 s for 2,000 five-pose graphs; measured
    # 2026-11-28, commit 1a1f8c2).
    # Concrete leaves are stacked on the host instead; traced ones (a call
    # under `jit` or `vmap`) keep `jnp.stack`.
    try:
        host = [np.asarray(x) for x in xs]
    except jax.errors.TracerArrayConversionError:
        return jnp.stack(xs)
    # `device_put`, not `jnp.asarray`: the latter compiles a small copy
    # program per shape in every fresh process.
    return jax.device_put(np.stack(host))
