import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..lie import AbstractLieGroup


def is_group(x: object) -> bool:
    """Whether `x` is a Lie group leaf (an [`eqsmooth.lie.AbstractLieGroup`][])."""
    return isinstance(x, AbstractLieGroup)


def _leaves(x: PyTree) -> list:
    return jax.tree_util.tree_leaves(x, is_leaf=is_group)


def _leaf_dim(leaf, batch_ndim: int) -> int:
    if is_group(leaf):
        return type(leaf).tangent_dim
    shape = jnp.shape(leaf)[batch_ndim:]
    dtype = jnp.result_type(leaf)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise TypeError(
            f"state leaves must be floating-point arrays or Lie groups; got a leaf "
            f"of dtype {dtype} and shape {jnp.shape(leaf)}"
        )
    return math.prod(shape)


def _group_dtype(g) -> jnp.dtype:
    return jax.tree_util.tree_leaves(g)[0].dtype


def tangent_dims(x: PyTree, batch_ndim: int = 0) -> tuple[int, ...]:
    """Tangent dimension of each leaf of a state, in flattening order.

    **Arguments:**

    - `x`: a state pytree (arrays and Lie groups).
    - `batch_ndim`: number of leading batch axes to ignore on every leaf
        (for example 1 for a stack of states).

    **Returns:** a tuple with one static int per leaf.
    """
    return tuple(_leaf_dim(leaf, batch_ndim) for leaf in _leaves(x))


def tangent_dim(x: PyTree, batch_ndim: int = 0) -> int:
    """Static tangent dimension of one state (ignoring `batch_ndim` leading axes)."""
    return sum(tangent_dims(x, batch_ndim))


def retract(x: PyTree, delta: Float[Array, "*batch d"]) -> PyTree:
    """Return `x ⊕ δ`: arrays add their slice of `delta`, groups right-compose exp.

    **Arguments:**

    - `x`: a state pytree; leaves may carry leading batch axes, which must
        match `delta.shape[:-1]`.
    - `delta`: tangent vector(s), last axis of size `tangent_dim(x)`.

    **Returns:** a state of the same structure as `x`.
    """
    batch = delta.shape[:-1]
    leaves, treedef = jax.tree_util.tree_flatten(x, is_leaf=is_group)
    dims = [_leaf_dim(leaf, len(batch)) for leaf in leaves]
    if sum(dims) != delta.shape[-1]:
        raise ValueError(
            f"retract: state has tangent dimension {sum(dims)} but delta has "
            f"shape {delta.shape}"
        )
    out = []
    start = 0
    for leaf, d in zip(leaves, dims):
        piece = delta[..., start : start + d]
        start += d
        if is_group(leaf):
            out.append(leaf @ type(leaf).exp(piece.astype(_group_dtype(leaf))))
        else:
            leaf = jnp.asarray(leaf)
            out.append(leaf + piece.reshape(leaf.shape).astype(leaf.dtype))
    return jax.tree_util.tree_unflatten(treedef, out)


def local(x: PyTree, y: PyTree, batch_ndim: int = 0) -> Float[Array, "*batch d"]:
    """Return `y ⊖ x`, the tangent vector with `retract(x, local(x, y)) == y`.

    **Arguments:**

    - `x`, `y`: states of the same structure.
    - `batch_ndim`: number of leading batch axes shared by all leaves.

    **Returns:** an array of shape `(*batch, tangent_dim(x))`.
    """
    xl, xdef = jax.tree_util.tree_flatten(x, is_leaf=is_group)
    yl, ydef = jax.tree_util.tree_flatten(y, is_leaf=is_group)
    if xdef != ydef:
        raise ValueError(f"local: states differ in structure: {xdef} vs {ydef}")
    pieces = []
    for a, b in zip(xl, yl):
        if is_group(a):
            pieces.append((a.inverse() @ b).log())
        else:
            a = jnp.asarray(a)
            diff = jnp.asarray(b) - a
            pieces.append(diff.reshape(diff.shape[:batch_ndim] + (-1,)))
    return jnp.concatenate(pieces, axis=-1)
