"""Batched Cholesky factorisations and triangular solves of small blocks, in plain XLA.

The chain solver and the block-Jacobi preconditioner work on thousands of
`D × D` blocks with `D` about 2 to 8. jaxlib's batched LAPACK kernels are a
poor fit for that on CPU:

- they pay a per-matrix call overhead, which dominates for blocks this
  small;
- they split their batch over XLA's intra-op thread pool and block until the
  pieces are done. Two such kernels running at once can take every thread of
  the pool and wait on each other forever: the hang described in
  `eqsmooth/_xla_flags.py`. XLA runs independent operations concurrently.

So for `D <= SMALL_BLOCK_LIMIT` these functions unroll the factorisation and
the substitutions over the `D` rows and columns, each step one element-wise
operation over the whole batch: no LAPACK call, no thread-pool barrier. The
unrolled form grows as `D²` operations and compiles slowly, so it is kept
out of code that is repeated per reduction level: there, the cyclic
reduction calls LAPACK in a chain of data dependencies (never two at once)
and uses these functions only once per level, to form `L⁻¹`.

Products of small blocks have the same problem in another form: XLA:CPU
runs a batched `dot` of `5 × 5` blocks about ten times slower than the
same arithmetic written as a sum of outer products, which it fuses into one
loop over the batch (`block_gram`).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..._precision import einsum


SMALL_BLOCK_LIMIT = 8
"""Largest block size handled by unrolled XLA operations instead of LAPACK."""


def block_gram(
    a: Float[Array, "*#batch M D"], b: Float[Array, "*#batch M E"]
) -> Float[Array, "*batch D E"]:
    """`aᵀ b` for batches of small blocks (batch axes broadcast): the
    `JᵢᵀJⱼ` blocks of a normal matrix, one per factor row.

    For `M <= SMALL_BLOCK_LIMIT` the product is the sum over `k` of the outer
    products of row `k` of `a` and row `k` of `b`: element-wise operations
    that XLA fuses into one loop over the batch, where its batched `dot`
    took 3.1 ms for 10⁴ products of `5 × 5` blocks against 0.31 ms (one
    core of the project machine; `git show c64c9b5:benchmarks/gram_blocks.py`
    measured the effect on a chain's factorisation). Larger `M` uses a batched `einsum`.
    """
    M = a.shape[-2]
    # Equal ranks, so the batch axes broadcast without rank promotion.
    rank = max(a.ndim, b.ndim)
    a = a.reshape((1,) * (rank - a.ndim) + a.shape)
    b = b.reshape((1,) * (rank - b.ndim) + b.shape)
    if M > SMALL_BLOCK_LIMIT:
        return einsum("...md,...me->...de", a, b)
    out = a[..., 0, :, None] * b[..., 0, None, :]
    for k in range(1, M):
        out = out + a[..., k, :, None] * b[..., k, None, :]
    return out


def block_cholesky(a: Float[Array, "*batch D D"]) -> Float[Array, "*batch D D"]:
    """Lower Cholesky factors of a batch of symmetric positive definite blocks.

    Only the lower triangle of `a` is read. A block that is not positive
    definite gets NaN entries (the square root of a non-positive pivot), as
    with `jnp.linalg.cholesky`; callers test the pivots.
    """
    D = a.shape[-1]
    if D > SMALL_BLOCK_LIMIT:
        return jnp.linalg.cholesky(a)
    columns = []
    for j in range(D):
        v = a[..., :, j]
        for c in columns:
            v = v - c * c[..., j : j + 1]
        below = (np.arange(D) >= j).astype(a.dtype).reshape((1,) * (v.ndim - 1) + (D,))
        columns.append(below * v / jnp.sqrt(v[..., j : j + 1]))
    return jnp.stack(columns, axis=-1)


def _substitute(chol, b, transpose: bool):
    """`L⁻¹ b` (forward substitution) or `L⁻ᵀ b` (back substitution)."""
    D = chol.shape[-1]
    if D > SMALL_BLOCK_LIMIT:
        return jax.lax.linalg.triangular_solve(
            chol, b, left_side=True, lower=True, transpose_a=transpose
        )
    x: list = [None] * D
    for i in reversed(range(D)) if transpose else range(D):
        r = b[..., i, :]
        for k in range(i + 1, D) if transpose else range(i):
            # Row i of Lᵀ is column i of L.
            coef = chol[..., k, i : i + 1] if transpose else chol[..., i, k : k + 1]
            r = r - coef * x[k]
        x[i] = r / chol[..., i, i : i + 1]
    return jnp.stack(x, axis=-2)


def block_solve_lower(
    chol: Float[Array, "*batch D D"], b: Float[Array, "*batch D K"]
) -> Float[Array, "*batch D K"]:
    """`L⁻¹ b` for each block, `L = chol` lower triangular."""
    return _substitute(chol, b, transpose=False)


def block_cho_solve(
    chol: Float[Array, "*batch D D"], b: Float[Array, "*batch D K"]
) -> Float[Array, "*batch D K"]:
    """`A⁻¹ b` for each block, given lower Cholesky factors `chol` of `A`."""
    return _substitute(chol, _substitute(chol, b, transpose=False), transpose=True)
