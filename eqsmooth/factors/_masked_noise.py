"""A row mask on a Gaussian noise model: switch measurements off, also under
`jit` and `vmap`."""

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from ._noise import (
    AbstractNoiseModel,
    check_row_mask,
    is_concrete,
    RowIndex,
    RowMask,
    take_leading,
)


class MaskedNoise(AbstractNoiseModel):
    """A Gaussian noise model whose rows can be switched off.

    Row `i` counts when `active[i]` is true; an inactive row's whitened
    residual and Jacobian are zero, so it adds nothing to the cost, the
    gradient, the normal equations or the negative log-likelihood (its
    `log det R_i` and its `½ m log 2π` are left out too). This is the
    supported way to drop measurements inside `jit` or `vmap`, for example
    a batch of sequences with missing frames: the mask is an array, so
    every batch element keeps its own and one compiled program serves all
    (zero precision is refused, so it cannot be used for this).

    A variable whose every factor row is masked is left unconstrained: the
    solve then reports a singular system, as it would without those rows.

    **Arguments:**

    - `base`: the Gaussian noise model of the rows (`IsotropicNoise`,
        `DiagonalNoise`, `SqrtInformationNoise`, ...). Robust kernels wrap a
        masked model (`HuberNoise(MaskedNoise(...))`); `StudentTNoise` does
        not (its density's constant would count masked rows) and raises.
    - `active`: `(n,)` booleans, one per factor row (under `vmap`, one per
        row of each batch element).
    """

    base: AbstractNoiseModel
    active: Bool[Array, " n"]

    def __init__(self, base: AbstractNoiseModel, active: ArrayLike):
        if active is None:
            raise TypeError(
                "MaskedNoise.active must be booleans, one per row, got None"
            )
        self.base = base
        self.active = jnp.asarray(active)

    def __check_init__(self):
        if isinstance(self.base, MaskedNoise):
            raise TypeError(
                "MaskedNoise.base is itself a MaskedNoise: combine the masks "
                "instead (MaskedNoise(base, active_a & active_b))"
            )
        if not isinstance(self.base, AbstractNoiseModel) or not self.base.is_gaussian:
            raise TypeError(
                "MaskedNoise.base must be a Gaussian noise model such as "
                f"IsotropicNoise or DiagonalNoise, got {type(self.base).__name__} "
                "(mask the Gaussian model inside a robust kernel: "
                "HuberNoise(MaskedNoise(base, active), scale))"
            )
        if self.active.dtype != jnp.bool_:
            if (
                is_concrete(self.active)
                and np.isin(np.asarray(self.active), (0, 1)).all()
            ):
                hint = " (cast with .astype(bool))"
            else:
                hint = ""
            raise TypeError(
                f"MaskedNoise.active must be booleans, got dtype {self.active.dtype}"
                + hint
            )
        if self.active.ndim != 1:
            raise ValueError(
                "MaskedNoise.active must have shape (n,), one entry per factor row, "
                f"got {self.active.shape}"
            )

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        keep = self.active.reshape(self.active.shape + (1,) * (r.ndim - 1))
        zero = jnp.zeros((), r.dtype)
        # Zero an inactive row before the base model sees it, not only after:
        # whatever it holds (NaN data of a missing measurement) must not reach
        # the derivatives of the noise parameters (0 · NaN is NaN).
        w = self.base.whiten(jnp.where(keep, r, zero))
        return jnp.where(keep, w, zero)

    def _row_log_dets(self, n: int, m: int) -> Float[Array, " n"]:
        # Whitening is linear: applied to identities it gives each row's R_i.
        dtype = self.base.log_det_sqrt_information(n, m).dtype
        eye = jnp.broadcast_to(jnp.eye(m, dtype=dtype), (n, m, m))
        _, logdet = jnp.linalg.slogdet(self.base.whiten(eye))
        return logdet

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        logdet = self._row_log_dets(n, m)
        return jnp.sum(jnp.where(self.active, logdet, jnp.zeros((), logdet.dtype)))

    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        log_det = self.log_det_sqrt_information(n, m)
        rows = jnp.sum(self.active).astype(log_det.dtype)
        return log_det - 0.5 * m * math.log(2 * math.pi) * rows

    def rho(
        self, s: Float[Array, " n"]
    ) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        return self.base.rho(s)

    def active_rows(self) -> Bool[Array, " n"]:
        return self.active

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        self.base.check_shapes(factor_name, n, m)
        check_row_mask(factor_name, "MaskedNoise.active", self.active, n)

    def curvature_model(self) -> "MaskedNoise":
        return self

    def take_rows(self, index: RowIndex) -> "MaskedNoise":
        return MaskedNoise(self.base.take_rows(index), take_leading(self.active, index))

    def mask_rows(self, active: RowMask) -> "MaskedNoise":
        # Masks combine rather than nest (a MaskedNoise refuses a masked base).
        if is_concrete(self.active) and is_concrete(active):
            both = jax.device_put(np.asarray(self.active) & np.asarray(active))
        else:
            both = self.active & jnp.asarray(active)
        return MaskedNoise(self.base, both)
