"""Error metrics between states on the manifold: per-leaf local errors and an MSE."""

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ._manifold import is_group


def _leaf_error(x, y) -> Array:
    # y ⊖ x for one leaf: group leaves give log(x⁻¹ y) of shape (*batch, d),
    # array leaves the plain difference with the leaf's own shape.
    if is_group(x):
        if not is_group(y) or type(x) is not type(y):
            raise TypeError(
                f"manifold_mse: a {type(x).__name__} leaf is compared with "
                f"{type(y).__name__}"
            )
        return (x.inverse() @ y).log()
    x = jnp.asarray(x)
    y = jnp.asarray(y)
    if x.shape != y.shape:
        raise ValueError(
            f"manifold_mse: leaves of shapes {x.shape} and {y.shape} differ"
        )
    return y - x


def manifold_errors(x: PyTree, y: PyTree) -> PyTree:
    """Per-leaf errors `y ⊖ x` of two states (group leaves become tangent arrays).

    **Arguments:**

    - `x`, `y`: pytrees of the same structure whose leaves are float arrays or
        Lie groups ([`eqsmooth.lie.AbstractLieGroup`][]), with any leading
        batch axes.

    **Returns:** a pytree with the structure of `x` in which every array leaf
    is replaced by `y − x` and every group leaf of batch shape `b` by the
    tangent array `log(x⁻¹ y)` of shape `(*b, tangent_dim)`.
    """
    xdef = jax.tree_util.tree_structure(x, is_leaf=is_group)
    ydef = jax.tree_util.tree_structure(y, is_leaf=is_group)
    if xdef != ydef:
        raise ValueError(
            f"manifold_mse: the two states differ in structure: {xdef} vs {ydef}"
        )
    return jax.tree_util.tree_map(_leaf_error, x, y, is_leaf=is_group)


def _weighted_mean_square(errors: PyTree, weights: PyTree | None) -> Float[Array, ""]:
    leaves = jax.tree_util.tree_leaves(errors)
    if not leaves:
        raise ValueError("manifold_mse: the states have no leaves")
    count = sum(e.size for e in leaves)
    if weights is None:
        total = sum(jnp.sum(e * e) for e in leaves)
        return total / count

    def weighted(w, sub):
        w = jnp.asarray(w)
        out = []
        for e in jax.tree_util.tree_leaves(sub):
            if w.ndim > e.ndim or any(
                a not in (1, b) for a, b in zip(w.shape[::-1], e.shape[::-1])
            ):
                raise ValueError(
                    f"manifold_mse: weights of shape {w.shape} do not broadcast "
                    f"against an error of shape {e.shape} (weights align with the "
                    "trailing axes: one weight per tangent component)"
                )
            out.append(jnp.sum(jnp.broadcast_to(w.astype(e.dtype), e.shape) * e * e))
        return sum(out) if out else jnp.zeros((), dtype=w.dtype)

    try:
        parts = jax.tree_util.tree_map(weighted, weights, errors)
    except ValueError as err:
        if "manifold_mse" in str(err):
            raise
        raise ValueError(
            "manifold_mse: `weights` must have the structure of the states (or a "
            f"prefix of it, with group leaves counted as leaves): {err}"
        ) from None
    return sum(jax.tree_util.tree_leaves(parts)) / count


def manifold_mse(
    x: PyTree, y: PyTree, weights: PyTree | None = None
) -> Float[Array, ""]:
    """Mean squared manifold error between two states or trajectories.

    The error of every leaf is taken in local coordinates
    ([`eqsmooth.manifold.manifold_errors`][]): `y − x` for arrays, `log(x⁻¹ y)`
    for Lie groups. The result is `Σ w e² / (number of error entries)`, so with
    no weights it is the mean of the squared tangent components.

    **Arguments:**

    - `x`, `y`: states of the same structure (e.g. two values dicts
        `{group: stacked states}`), leaves float arrays or Lie groups.
    - `weights`: `None`, or a pytree with the structure of `x` (or a prefix of
        it; group leaves count as leaves) whose leaves are non-negative
        arrays broadcast against the trailing axes of the matching error: for
        example `{"x": jnp.array([1.0, 1.0, 0.1, 0.1])}` for a group of 4-D
        Euclidean states, or `{"pose": jnp.array([1.0, 1.0, 10.0])}` for SE(2)
        poses (tangent order `(x, y, θ)`).

    **Returns:** a scalar.
    """
    return _weighted_mean_square(manifold_errors(x, y), weights)
