"""Retraction and local coordinates for arbitrary state pytrees.

A *state* is any pytree whose leaves are floating-point arrays or Lie group
objects ([`eqsmooth.lie.AbstractLieGroup`][]). Its tangent space is the
concatenation, in pytree-flattening order, of each leaf's tangent space:
an array leaf of shape `s` contributes `prod(s)` coordinates, a group leaf
contributes `tangent_dim` coordinates. The perturbation is on the right:

    retract(x, δ) = x ⊕ δ:   arrays add δ, groups become g @ exp(δ)
    local(x, y)   = y ⊖ x:   arrays subtract, groups give log(x⁻¹ @ y)

so `retract(x, local(x, y)) == y`.
"""

from ._manifold import (
    is_group as is_group,
    local as local,
    retract as retract,
    tangent_dim as tangent_dim,
    tangent_dims as tangent_dims,
)
from ._metrics import manifold_errors as manifold_errors, manifold_mse as manifold_mse
