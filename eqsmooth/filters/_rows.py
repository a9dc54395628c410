"""Row access to stacked factors for sequential (filtering) evaluation.

The smoother evaluates a factor stack with `vmap` over its rows; a filter
needs the rows one time step at a time inside a `lax.scan`. These helpers
split a stack into its per-row leaves (scanned over) and the rest (closed
over), rebuild a one-row factor inside the scan, and turn the stack's noise
model into one square-root information matrix per row.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from ..factors import (
    AbstractFactor,
    AbstractNoiseModel,
    per_row_fields as per_row_fields,
    with_rows as with_rows,
)
from ..factors._factor import check_row_leaves


def gather_rows(rows: dict[str, PyTree], index: np.ndarray) -> dict[str, PyTree]:
    """Index the leading (row) axis of every array leaf with a static `index`."""
    return jax.tree_util.tree_map(
        lambda a: jnp.asarray(a)[index] if eqx.is_array(a) else a, rows
    )


def check_gaussian(noise: AbstractNoiseModel, where: str) -> None:
    """Raise a `TypeError` if `noise` is not Gaussian (robust, Student-t) or
    masks rows: the noise model says which (`is_gaussian`, `active_rows`)."""
    if not noise.is_gaussian:
        raise TypeError(
            f"{where}: noise model {type(noise).__name__} is robust (non-Gaussian, "
            f"{noise.name}); a Kalman filter needs Gaussian noise such as "
            "IsotropicNoise, DiagonalNoise or SqrtInformationNoise. Use the "
            "factor-graph smoother for robust losses."
        )
    if noise.active_rows() is not None:
        raise TypeError(
            f"{where}: {noise.name} rows cannot be masked in a Kalman filter (a "
            "masked row has zero information, which the filter's update cannot "
            "invert); leave the masked measurements out of the filter's factors, "
            "or use the factor-graph smoother"
        )


def row_whitening(
    factor: AbstractFactor, m: int, dtype
) -> tuple[Float[Array, "n m m"], Float[Array, " n"]]:
    """Square-root information `R_i` of every row and `log|det R_i|`.

    The noise model gives them (`sqrt_information_rows`), whether its
    parameters are shared or per row.
    """
    n = factor.num_rows
    name = type(factor).__name__
    factor.noise.check_shapes(name, n, m)
    R = factor.noise.sqrt_information_rows(n, m, dtype)
    _, logdet = jnp.linalg.slogdet(R)
    return R, logdet


def check_rows(factor: AbstractFactor) -> None:
    """Per-row leaves must have a leading axis of the stack's length."""
    check_row_leaves(factor)
