"""Is a Gaussian estimate's covariance right? Per-frame NLL, NEES and coverage.

An estimator that returns a mean `x̂` and a covariance `Σ` claims
`x ~ N(x̂, Σ)`. Scored against the truth `x` (error `e = x − x̂`, dimension
`d`):

- NLL: `½ eᵀΣ⁻¹e + ½ log det Σ + (d/2) log 2π` nats;
- NEES (normalised estimation error squared): `eᵀΣ⁻¹e`, χ²(d)-distributed
  when the claim is true (Bar-Shalom, Li and Kirubarajan, "Estimation with
  Applications to Tracking and Navigation", 2001, §5.4.2);
- the χ²(d) CDF of the NEES, `F_d(eᵀΣ⁻¹e)`: the truth lies in the
  ellipsoid holding a fraction `q` of the predicted mass exactly when this
  is `≤ q`, so the fraction of frames with `cdf ≤ q` is the observed
  coverage at level `q` (uniform on [0, 1] for a consistent estimator).
"""

import math

import equinox as eqx
import jax.numpy as jnp
import jax.scipy.special as jsp
from jaxtyping import Array, ArrayLike, Bool, Float

from .._stats import chi2_quantile as _chi2_quantile


class GaussianCalibration(eqx.Module):
    """Per-frame scores of Gaussian estimates, from
    [`eqsmooth.learn.gaussian_calibration`][].

    Frames whose covariance is not finite and positive definite have
    `valid = False` and NaN scores.

    **Fields:**

    - `nll`: negative log-likelihood of the truth, nats.
    - `nees`: `eᵀΣ⁻¹e`.
    - `cdf`: `F_d(nees)`, the χ²(d) CDF: the smallest level whose region
        holds the truth.
    - `valid`: whether the covariance was finite and positive definite.
    - `dim`: the dimension `d` of the scored marginal.
    """

    nll: Float[Array, "*batch"]
    nees: Float[Array, "*batch"]
    cdf: Float[Array, "*batch"]
    valid: Bool[Array, "*batch"]
    dim: int = eqx.field(static=True)

    def coverage(self, level: float, axis: int | None = None) -> Float[Array, "..."]:
        """The fraction of valid frames (over `axis`, default all) whose
        truth lies in the region of probability `level` (NaN without a
        valid frame)."""
        if not 0.0 < level < 1.0:
            raise ValueError(
                f"GaussianCalibration.coverage: level must be in (0, 1), got {level}"
            )
        dtype = self.cdf.dtype
        inside = jnp.where(self.valid, self.cdf <= level, False)
        count = jnp.sum(self.valid, axis=axis).astype(dtype)
        hits = jnp.sum(inside, axis=axis).astype(dtype)
        return hits / jnp.where(count > 0, count, jnp.asarray(jnp.nan, dtype))


def gaussian_calibration(
    error: Float[ArrayLike, "*batch d"],
    covariance: Float[ArrayLike, "*batch d d"],
) -> GaussianCalibration:
    """Score Gaussian estimates `N(x̂, Σ)` of any dimension `d` against the truth.

    The covariance is symmetrised, `½(Σ + Σᵀ)`, and factorised by Cholesky;
    a frame whose factor is not finite (a covariance that is not positive
    definite, or holds a NaN) is marked invalid and scored NaN, never
    silently. Differentiable in `error` and `covariance` (the NLL is the
    Gaussian loss of a variance head); computed in the inputs' dtype.

    **Arguments:**

    - `error`: truth minus estimate, `(*batch, d)` (on a Lie group, the
        tangent error `log(x̂⁻¹ x)` in the covariance's coordinates).
    - `covariance`: the estimate's covariance, `(*batch, d, d)`.

    **Returns:**

    A [`eqsmooth.learn.GaussianCalibration`][] of per-frame NLL, NEES, χ²
    CDF and validity, each `(*batch,)`.

    Raises `ValueError` if the shapes do not match.
    """
    e = jnp.asarray(error)
    c = jnp.asarray(covariance)
    if e.ndim < 1 or c.shape != e.shape + e.shape[-1:]:
        raise ValueError(
            "gaussian_calibration: error must be (*batch, d) and covariance "
            f"(*batch, d, d); got error {e.shape} and covariance {c.shape}"
        )
    dtype = jnp.result_type(e, c)
    if not jnp.issubdtype(dtype, jnp.floating):
        dtype = jnp.result_type(float)
    e, c = e.astype(dtype), c.astype(dtype)
    d = e.shape[-1]
    chol = jnp.linalg.cholesky(0.5 * (c + jnp.swapaxes(c, -1, -2)))
    diag = jnp.diagonal(chol, axis1=-2, axis2=-1)
    valid = jnp.all(jnp.isfinite(chol), axis=(-2, -1)) & jnp.all(diag > 0, axis=-1)
    # A harmless factor on invalid frames keeps their gradients finite.
    eye = jnp.eye(d, dtype=dtype)
    chol = jnp.where(valid[..., None, None], chol, eye)
    white = jnp.linalg.solve(chol, e[..., None])[..., 0]
    nees = jnp.sum(white * white, axis=-1)
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    nll = 0.5 * nees + 0.5 * logdet + 0.5 * d * math.log(2 * math.pi)
    cdf = jsp.gammainc(0.5 * d, 0.5 * nees)
    nan = jnp.asarray(jnp.nan, dtype)
    return GaussianCalibration(
        nll=jnp.where(valid, nll, nan),
        nees=jnp.where(valid, nees, nan),
        cdf=jnp.where(valid, cdf, nan),
        valid=valid,
        dim=d,
    )


def chi2_quantile(probability: float, dof: int | float) -> float:
    """The `probability` quantile of χ²(`dof`) in float64 on the host (a
    static number, e.g. a coverage threshold), by bisection on its CDF."""
    if not 0.0 < probability < 1.0 or not dof > 0:
        raise ValueError(
            "chi2_quantile: need 0 < probability < 1 and dof > 0, got "
            f"probability={probability}, dof={dof}"
        )
    return _chi2_quantile(probability, dof)


def nees_band(dim: int, count: int, probability: float = 0.95) -> tuple[float, float]:
    """The two-sided `probability` band of the mean of `count` independent
    χ²(`dim`) NEES values: `[χ²_{dim·count}((1−p)/2), χ²_{dim·count}((1+p)/2)] / count`.

    A consistent estimator's mean NEES lies in it with probability
    `probability` when its frame errors are independent (a smoother's are
    correlated in time, so there the band is nominal).
    """
    if dim < 1 or count < 1:
        raise ValueError(f"nees_band: need dim ≥ 1 and count ≥ 1, got {dim}, {count}")
    tail = 0.5 * (1.0 - probability)
    dof = dim * count
    return (
        chi2_quantile(tail, dof) / count,
        chi2_quantile(1.0 - tail, dof) / count,
    )
