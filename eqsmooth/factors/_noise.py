"""Noise models acting on *stacked* residuals.

A noise model belongs to a stacked factor with `n` rows of residual dimension
`m`. Its parameters are either shared by all rows or given per row
(heteroscedastic); which one is decided by the number of axes of the
parameter, so there is never any ambiguity:

| model | shared | per row |
|---|---|---|
| `IsotropicNoise.sqrt_precision` | `()` | `(n,)` |
| `DiagonalNoise.sqrt_precision` | `(m,)` | `(n, m)` |
| `SqrtInformationNoise.sqrt_information` | `(m, m)` | `(n, m, m)` |

Whitening maps a residual `r` to `R r` with information `RᵀR`; the factor's
cost is `½ ρ(‖R r‖²)` where `ρ` is the identity for Gaussian models.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_positive(name: str, field: str, value) -> None:
    if _is_concrete(value):
        arr = np.asarray(value)
        if arr.size and not np.all(np.isfinite(arr)):
            raise ValueError(f"{name}.{field} must be finite, got {arr}")
        if arr.size and not np.all(arr > 0):
            raise ValueError(
                f"{name}.{field} must be positive, got min {arr.min()} "
                f"(shape {arr.shape})"
            )


def _expand(x: Array, ndim: int) -> Array:
    return x.reshape(x.shape + (1,) * (ndim - x.ndim))


class AbstractNoiseModel(eqx.Module):
    """Base class of noise models (see the module docs for shapes)."""

    @abc.abstractmethod
    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        """Multiply by the square-root information along axis 1.

        Applies to stacked residuals `(n, m)` and stacked Jacobians `(n, m, d)`.
        """

    @abc.abstractmethod
    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        """`Σ_rows log det R_i` for `n` rows of dimension `m`.

        The Gaussian negative log-likelihood of a stacked factor is
        `½ Σ‖R_i r_i‖² − Σ log det R_i + ½ n m log 2π`.
        """

    @abc.abstractmethod
    def rho(
        self, s: Float[Array, " n"]
    ) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """Robust loss `ρ(s)` and its derivative `ρ'(s)` at squared norms `s`."""

    @abc.abstractmethod
    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        """Raise a `ValueError` naming `factor_name` if shapes do not fit `(n, m)`."""


class IsotropicNoise(AbstractNoiseModel):
    """Isotropic Gaussian noise: `R = sqrt_precision · I`.

    **Arguments:**

    - `sqrt_precision`: `1/σ`, shared (shape `()`) or per row (shape `(n,)`).
    """

    sqrt_precision: Float[Array, "*rows"]

    def __init__(self, sqrt_precision: Float[ArrayLike, "*rows"]):
        self.sqrt_precision = jnp.asarray(sqrt_precision)

    def __check_init__(self):
        _check_positive("IsotropicNoise", "sqrt_precision", self.sqrt_precision)

    @classmethod
    def from_sigma(cls, sigma: Float[ArrayLike, "*rows"]) -> "IsotropicNoise":
        """Build from standard deviation(s) σ."""
        sigma = jnp.asarray(sigma)
        _check_positive("IsotropicNoise", "sigma", sigma)
        return cls(1.0 / sigma)

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        s = self.sqrt_precision.astype(r.dtype)
        return r * (_expand(s, r.ndim) if s.ndim else s)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        s = self.sqrt_precision
        if s.ndim == 0:
            return n * m * jnp.log(s)
        return m * jnp.sum(jnp.log(s))

    def rho(self, s):
        return s, jnp.ones_like(s)

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        if self.sqrt_precision.shape not in ((), (n,)):
            raise ValueError(
                f"{factor_name}: IsotropicNoise.sqrt_precision has shape "
                f"{self.sqrt_precision.shape}; expected () or ({n},)"
            )


class DiagonalNoise(AbstractNoiseModel):
    """Diagonal Gaussian noise: `R = diag(sqrt_precision)`.

    **Arguments:**

    - `sqrt_precision`: `1/σ_j`, shared (shape `(m,)`) or per row (`(n, m)`).
    """

    sqrt_precision: Float[Array, "*rows m"]

    def __init__(self, sqrt_precision: Float[ArrayLike, "*rows m"]):
        self.sqrt_precision = jnp.asarray(sqrt_precision)

    def __check_init__(self):
        if self.sqrt_precision.ndim not in (1, 2):
            raise ValueError(
                "DiagonalNoise.sqrt_precision must have shape (m,) or (n, m), got "
                f"{self.sqrt_precision.shape}"
            )
        _check_positive("DiagonalNoise", "sqrt_precision", self.sqrt_precision)

    @classmethod
    def from_sigmas(cls, sigmas: Float[ArrayLike, "*rows m"]) -> "DiagonalNoise":
        """Build from per-coordinate standard deviations."""
        sigmas = jnp.asarray(sigmas)
        _check_positive("DiagonalNoise", "sigmas", sigmas)
        return cls(1.0 / sigmas)

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        s = self.sqrt_precision.astype(r.dtype)
        if s.ndim == 1:
            s = s[None]
        return r * _expand(s, r.ndim)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        s = self.sqrt_precision
        total = jnp.sum(jnp.log(s))
        return n * total if s.ndim == 1 else total

    def rho(self, s):
        return s, jnp.ones_like(s)

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        if self.sqrt_precision.shape not in ((m,), (n, m)):
            raise ValueError(
                f"{factor_name}: DiagonalNoise.sqrt_precision has shape "
                f"{self.sqrt_precision.shape}; expected ({m},) or ({n}, {m})"
            )


class SqrtInformationNoise(AbstractNoiseModel):
    """Full Gaussian noise given by a lower-triangular square-root information `R`.

    The whitened residual is `R r` and the information matrix is `RᵀR`. Only
    the lower triangle of `sqrt_information` is used; its diagonal must be
    positive.

    **Arguments:**

    - `sqrt_information`: shared `(m, m)` or per row `(n, m, m)`.
    """

    sqrt_information: Float[Array, "*rows m m"]

    def __init__(self, sqrt_information: Float[ArrayLike, "*rows m m"]):
        self.sqrt_information = jnp.tril(jnp.asarray(sqrt_information))

    def __check_init__(self):
        R = self.sqrt_information
        if R.ndim not in (2, 3) or R.shape[-1] != R.shape[-2]:
            raise ValueError(
                "SqrtInformationNoise.sqrt_information must have shape (m, m) or "
                f"(n, m, m), got {R.shape}"
            )
        _check_positive(
            "SqrtInformationNoise",
            "sqrt_information diagonal",
            jnp.diagonal(R, axis1=-2, axis2=-1),
        )

    @classmethod
    def from_covariance(
        cls, covariance: Float[ArrayLike, "*rows m m"]
    ) -> "SqrtInformationNoise":
        """Build from covariance matrices Σ (`R = chol(Σ)⁻¹`, so `RᵀR = Σ⁻¹`)."""
        cov = jnp.asarray(covariance)
        L = jnp.linalg.cholesky(cov)
        eye = jnp.broadcast_to(jnp.eye(cov.shape[-1], dtype=cov.dtype), cov.shape)
        R = jax.scipy.linalg.solve_triangular(L, eye, lower=True)
        return cls(R)

    @classmethod
    def from_information(
        cls, information: Float[ArrayLike, "*rows m m"]
    ) -> "SqrtInformationNoise":
        """Build from information matrices Λ (a lower-triangular `R` with `RᵀR = Λ`)."""
        info = jnp.asarray(information)
        # Reverse-order Cholesky: with J the exchange matrix, J Λ J = L Lᵀ gives
        # Λ = (J L J)(J Lᵀ J); R = J Lᵀ J is lower triangular.
        flip = info[..., ::-1, ::-1]
        L = jnp.linalg.cholesky(flip)
        R = jnp.swapaxes(L, -1, -2)[..., ::-1, ::-1]
        return cls(R)

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        R = self.sqrt_information.astype(r.dtype)
        if R.ndim == 2:
            return jnp.einsum("ij,nj...->ni...", R, r)
        return jnp.einsum("nij,nj...->ni...", R, r)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        R = self.sqrt_information
        total = jnp.sum(jnp.log(jnp.diagonal(R, axis1=-2, axis2=-1)))
        return n * total if R.ndim == 2 else total

    def rho(self, s):
        return s, jnp.ones_like(s)

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        if self.sqrt_information.shape not in ((m, m), (n, m, m)):
            raise ValueError(
                f"{factor_name}: SqrtInformationNoise.sqrt_information has shape "
                f"{self.sqrt_information.shape}; expected ({m}, {m}) or ({n}, {m}, {m})"
            )


def _check_scale(name: str, scale) -> None:
    _check_positive(name, "scale", scale)


class AbstractRobustNoise(AbstractNoiseModel):
    """A robust loss `ρ` on top of a Gaussian noise model.

    Whitening, shapes and `log_det_sqrt_information` are those of `base`;
    subclasses give `ρ(s)` and `ρ'(s)` of the whitened squared norm
    `s = ‖R r‖²` through `rho`. Solvers use IRLS weights `√ρ'(s)` on
    residuals and Jacobians, whose Gauss-Newton gradient equals the gradient
    of the true cost `½ρ(s)`; the reported cost is `½ρ(s)`. Filters (which
    are Gaussian) reject robust models.

    **Fields:**

    - `base`: the Gaussian noise model.
    - `scale`: the loss's scale `k > 0` (whitened units), shared `()` or per
        row `(n,)`; learnable.
    """

    base: eqx.AbstractVar[AbstractNoiseModel]
    scale: eqx.AbstractVar[Float[Array, "*rows"]]

    def __check_init__(self):
        _check_scale(type(self).__name__, self.scale)

    def whiten(self, r):
        return self.base.whiten(r)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        return self.base.log_det_sqrt_information(n, m)

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        self.base.check_shapes(factor_name, n, m)
        if self.scale.shape not in ((), (n,)):
            raise ValueError(
                f"{factor_name}: {type(self).__name__}.scale has shape "
                f"{self.scale.shape}; expected () or ({n},)"
            )


class HuberNoise(AbstractRobustNoise):
    """Huber robust loss on top of a Gaussian model.

    With whitened squared norm `s = ‖R r‖²` and scale `k` (in whitened units):
    `ρ(s) = s` for `s ≤ k²`, else `2k√s − k²`. Conventions of
    [`eqsmooth.factors.AbstractRobustNoise`][].

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: threshold `k > 0`, shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = jnp.asarray(scale)

    def rho(self, s):
        k = self.scale.astype(s.dtype)
        inside = s <= k * k
        safe_s = jnp.where(inside, k * k, s)  # never sqrt(0) in the untaken branch
        root = jnp.sqrt(safe_s)
        value = jnp.where(inside, s, 2 * k * root - k * k)
        deriv = jnp.where(inside, jnp.ones_like(s), k / root)
        return value, deriv


class CauchyNoise(AbstractRobustNoise):
    """Cauchy (Lorentzian) robust loss: `ρ(s) = k² log(1 + s/k²)`.

    Conventions of [`eqsmooth.factors.AbstractRobustNoise`][].

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0`, shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = jnp.asarray(scale)

    def rho(self, s):
        k2 = (self.scale * self.scale).astype(s.dtype)
        return k2 * jnp.log1p(s / k2), 1.0 / (1.0 + s / k2)
