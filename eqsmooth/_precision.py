"""Matrix products at full float32 precision on every backend.

JAX's default precision for a float32 `dot` lets the backend pick: XLA:CPU
computes in float32, but GPUs with tensor cores (NVIDIA since Ampere) round
the operands to TF32 (a 10-bit mantissa, about three significant digits) and
TPUs to bfloat16. A Lie-group Jacobian, a whitened residual or a normal
matrix computed that way is off by about 1e-3 relative, far beyond what a
float32 smoother otherwise reaches and enough to stall Gauss-Newton. So
eqsmooth's own products ask for `Precision.HIGHEST` explicitly; a user who
wants the faster reduced-precision products in their own networks keeps
JAX's setting there (`jax.default_matmul_precision`), since it governs only
the products that name no precision.
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array


_HIGHEST = jax.lax.Precision.HIGHEST


def matmul(a: Array, b: Array) -> Array:
    """`a @ b` (batched, as `jnp.matmul`) at full precision."""
    return jnp.matmul(a, b, precision=_HIGHEST)


def einsum(subscripts: str, *operands: Array) -> Array:
    """`jnp.einsum` at full precision."""
    return jnp.einsum(subscripts, *operands, precision=_HIGHEST)
