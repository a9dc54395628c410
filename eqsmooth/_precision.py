"""Matrix products at full float32 precision on every backend.

JAX's default precision for a float32 `dot` lets the backend pick. GPUs with
tensor cores (NVIDIA since Ampere) round the operands to TF32 (a 10-bit
mantissa, about three significant digits) and TPUs to bfloat16: a Lie-group
Jacobian, a whitened residual or a normal matrix computed that way is off by
about 1e-3 relative, far beyond what a float32 smoother otherwise reaches
(on an H200, float32 SO(3) and SE(3) results were 1e-4 off their float64
values). So on those backends eqsmooth's own products ask for
`Precision.HIGHEST`. XLA:CPU computes float32 products in float32 whatever
they ask for, and compiles a program that names a precision differently: a
float32 chain solve took 1.05-1.21 times as long with it (float64:
0.90-0.97; `benchmarks/precision_ab.py`), so on the CPU they name none and
keep the programs eqsmooth compiled before. The choice is made when a
function is traced, from the default backend. Products in user code keep
JAX's setting (`jax.default_matmul_precision`).
"""

import jax
import jax.numpy as jnp
from jaxtyping import Array


def _backend() -> str:
    return jax.default_backend()


def precision() -> jax.lax.Precision | None:
    """`Precision.HIGHEST`, or `None` (JAX's default) on the CPU, where the
    default is already float32 and faster."""
    return None if _backend() == "cpu" else jax.lax.Precision.HIGHEST


def matmul(a: Array, b: Array) -> Array:
    """`a @ b` (batched, as `jnp.matmul`) at full precision."""
    return jnp.matmul(a, b, precision=precision())


def einsum(subscripts: str, *operands: Array) -> Array:
    """`jnp.einsum` at full precision."""
    return jnp.einsum(subscripts, *operands, precision=precision())
