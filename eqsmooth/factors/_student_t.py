"""Student-t noise: heavy tails with a normalised density."""

import math
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax.scipy.special import gammaln
from jaxtyping import Array, ArrayLike, Bool, Float

from ._noise import (
    AbstractNoiseModel,
    as_float,
    check_positive,
    gaussian_log_normalizer,
    mask_gaussian,
    positive_under_jit,
    RowIndex,
    RowMask,
    take_per_row,
)


class StudentTNoise(AbstractNoiseModel):
    """Multivariate Student-t noise: heavy tails, and a proper density.

    Each row's whitened residual `e = R r` (`R` from the Gaussian `base`) is
    a standard multivariate t with `ν` degrees of freedom in `m` dimensions:

        −log p(r) = ((ν + m)/2) log(1 + ‖e‖²/ν) − log det R − log c(ν, m)
        c(ν, m)   = Γ((ν + m)/2) / (Γ(ν/2) (νπ)^{m/2})

    In the conventions of the other noise models, `ρ(s) = (ν + m) log(1 + s/ν)`
    and `ρ'(s) = (ν + m)/(ν + s)`: solvers weight residuals and Jacobians by
    `√ρ'(s)` (at `s = 0` that is the density's exact curvature at its mode),
    and `log_normalizer` is the t density's own. So
    [`eqsmooth.factors.FactorGraph.negative_log_likelihood`][] and the
    Laplace evidence ([`eqsmooth.discover.laplace_log_marginal`][]) are those
    of a normalised density, unlike the robust kernels (Huber, Cauchy, ...),
    which are losses. The Laplace evidence's log-determinant uses the
    density's Fisher information instead of these weights
    ([`fisher_model`][eqsmooth.factors.StudentTNoise.fisher_model]).

    `R` sets the scale, not the covariance: for `ν > 2` the covariance is
    `ν/(ν − 2) (RᵀR)⁻¹`. As `ν → ∞` the model becomes `base`. The density is
    not log-concave (its curvature is negative beyond `‖e‖² = ν`): start a
    solve near the answer, for instance from the Gaussian model's. Kalman
    filters reject it, as they reject robust kernels.

    **Arguments:**

    - `base`: the Gaussian noise model that gives `R`.
    - `dof`: degrees of freedom `ν > 0`, shared `()` or per row `(n,)`;
        learnable.
    - `dim`: the residual dimension `m` of the factor it belongs to (the
        density's constant depends on it); checked against the factor.
    """

    base: AbstractNoiseModel
    dof: Float[Array, "*rows"]
    dim: int = eqx.field(static=True)
    is_gaussian: ClassVar[bool] = False

    def __init__(
        self, base: AbstractNoiseModel, dof: Float[ArrayLike, "*rows"], dim: int = 1
    ):
        self.base = base
        self.dof = positive_under_jit("StudentTNoise", "dof", as_float(dof))
        self.dim = dim

    def __check_init__(self):
        if not isinstance(self.base, AbstractNoiseModel) or not self.base.is_gaussian:
            raise TypeError(
                "StudentTNoise.base must be a Gaussian noise model such as "
                f"IsotropicNoise or DiagonalNoise, got {self.base.name}"
            )
        if self.base.active_rows() is not None:
            raise TypeError(
                "StudentTNoise.base cannot be a MaskedNoise: the Student-t "
                "density's constant would count the masked rows; mask rows of a "
                "Gaussian or robust model, or split the factor stack instead"
            )
        if isinstance(self.dim, bool) or not isinstance(self.dim, int) or self.dim < 1:
            raise ValueError(
                f"StudentTNoise.dim must be a positive int (the residual dimension), "
                f"got {self.dim!r}"
            )
        check_positive("StudentTNoise", "dof", self.dof)

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        return self.base.whiten(r)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        return self.base.log_det_sqrt_information(n, m)

    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        log_det = self.base.log_det_sqrt_information(n, m)
        nu = self.dof.astype(log_det.dtype)
        const = (
            n * _log_t_constant(nu, m)
            if nu.ndim == 0
            else jnp.sum(_log_t_constant(nu, m))
        )
        return log_det + const

    def fisher_model(self) -> AbstractNoiseModel:
        """The Gaussian noise model with this density's Fisher information.

        The Fisher information of a multivariate t location is
        `(ν + m)/(ν + m + 2) RᵀR`: the curvature of `−log p` averaged over
        the noise, which unlike the curvature at one residual does not
        depend on the residual. The Laplace evidence uses it for its
        log-determinant (see [`eqsmooth.discover.laplace_at_map`][]), which
        makes the evidence a smooth function of the parameters.
        """
        nu = self.dof
        return _ScaledGaussian(
            self.base, jnp.sqrt((nu + self.dim) / (nu + self.dim + 2.0))
        )

    def rho(self, s):
        nu = self.dof.astype(s.dtype)
        a = nu + self.dim
        return a * jnp.log1p(s / nu), a / (nu + s)

    def active_rows(self) -> None:
        return None

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        self.base.check_shapes(factor_name, n, m)
        if m != self.dim:
            raise ValueError(
                f"{factor_name}: StudentTNoise.dim is {self.dim} but the factor's "
                f"residual has dimension {m}; pass dim={m}"
            )
        if self.dof.shape not in ((), (n,)):
            raise ValueError(
                f"{factor_name}: StudentTNoise.dof has shape {self.dof.shape}; "
                f"expected () or ({n},)"
            )

    def curvature_model(self) -> AbstractNoiseModel:
        # The curvature at one residual changes with the residual, which
        # makes the Laplace evidence rough in the parameters; the Fisher
        # information does not.
        return self.fisher_model()

    def take_rows(self, index: RowIndex) -> "StudentTNoise":
        out = eqx.tree_at(lambda m: m.base, self, self.base.take_rows(index))
        return take_per_row(out, "dof", 1, index)

    def mask_rows(self, active: RowMask) -> AbstractNoiseModel:
        raise TypeError(
            "StudentTNoise rows cannot be masked: the Student-t density's "
            "constant would count the masked rows; mask rows of a Gaussian or "
            "robust model, or split the factor stack instead"
        )


class _ScaledGaussian(AbstractNoiseModel):
    """`base` with its square-root information multiplied by `weight`
    (shared `()` or per row `(n,)`)."""

    base: AbstractNoiseModel
    weight: Float[Array, "*rows"]

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        w = self.weight.astype(r.dtype)
        w = w.reshape(w.shape + (1,) * (r.ndim - w.ndim)) if w.ndim else w
        return self.base.whiten(r) * w

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        log_det = self.base.log_det_sqrt_information(n, m)
        log_w = jnp.log(self.weight.astype(log_det.dtype))
        extra = n * m * log_w if log_w.ndim == 0 else m * jnp.sum(log_w)
        return log_det + extra

    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        return gaussian_log_normalizer(self, n, m)

    def rho(self, s):
        return s, jnp.ones_like(s)

    def active_rows(self) -> Bool[Array, " n"] | None:
        return self.base.active_rows()

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        self.base.check_shapes(factor_name, n, m)

    def curvature_model(self) -> "_ScaledGaussian":
        return self

    def take_rows(self, index: RowIndex) -> "_ScaledGaussian":
        out = eqx.tree_at(lambda m: m.base, self, self.base.take_rows(index))
        return take_per_row(out, "weight", 1, index)

    def mask_rows(self, active: RowMask) -> AbstractNoiseModel:
        return mask_gaussian(self, active)


def _log_t_constant(nu, m: int):
    """`log Γ((ν+m)/2) − log Γ(ν/2) − (m/2) log(νπ)`, without cancellation.

    For large `ν` the two log-gammas are large and nearly equal (in float32,
    ν = 1e7 lost 6 of the 22 nats). There the difference comes from its
    asymptotic series in `x = ν/2`, `h = m/2` (Bernoulli polynomials):
    `log Γ(x+h) − log Γ(x) = h log x + h(h−1)/(2x) − h(h−1)(2h−1)/(12x²) +
    h²(h−1)²/(12x³) + O(x⁻⁴)`, whose `h log x` cancels analytically against
    `(m/2) log ν`.
    """
    x, h = 0.5 * nu, 0.5 * m
    direct = gammaln(x + h) - gammaln(x) - h * jnp.log(nu * math.pi)
    big = jnp.maximum(x, 1.0)  # the series is only used for large x
    series = (
        h * (h - 1) / (2 * big)
        - h * (h - 1) * (2 * h - 1) / (12 * big**2)
        + h**2 * (h - 1) ** 2 / (12 * big**3)
        - h * math.log(2 * math.pi)
    )
    # Switch where the direct form's cancellation (≈ ε x log x) exceeds the
    # series' first omitted term (≈ h⁵/(20x⁴)): x = 50 in float32 (both
    # below 1e-5 there), 1e4 in float64.
    start = 50.0 if jnp.result_type(nu) == jnp.float32 else 1e4
    return jnp.where(x > max(start, 10.0 * h * h), series, direct)
