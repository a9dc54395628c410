"""More robust kernels on [`eqsmooth.factors.AbstractRobustNoise`][].

Every kernel is written in terms of the whitened squared norm `s = ‖R r‖²`
and returns `(ρ(s), ρ'(s))`; the factor's cost is `½ρ(s)` and the IRLS
weight is `ρ'(s)`. In terms of the whitened error `e = √s`, `½ρ` is the
usual M-estimator loss and `ρ'` its weight `ψ(e)/e` (Zhang, "Parameter
estimation techniques: a tutorial with application to conic fitting",
1997; Agarwal et al., "Robust map optimization using dynamic covariance
scaling", ICRA 2013; Yang et al., "Graduated non-convexity for robust
spatial perception", RA-L 2020).

Every formula is written with `jnp.where` and safe square roots so that the
scale is differentiable (learnable) and no branch produces `nan` in reverse
mode.
"""

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from ._noise import AbstractNoiseModel, AbstractRobustNoise, robust_scale


def _safe_sqrt(s: Array) -> Array:
    # √s with a zero (not infinite) derivative at s = 0.
    positive = s > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, s, jnp.ones_like(s))), 0.0)


class TukeyNoise(AbstractRobustNoise):
    """Tukey's biweight: outliers beyond `k` get zero weight.

    `ρ(s) = (k²/3)(1 − (1 − s/k²)³)` and `ρ'(s) = (1 − s/k²)²` for `s ≤ k²`;
    `ρ = k²/3`, `ρ' = 0` beyond. Not convex: start near the solution (or
    from a convex kernel's solution).

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        k2 = jnp.square(self.scale).astype(s.dtype)
        u = jnp.clip(1.0 - s / k2, 0.0, None)
        # `where`, not `u * u`: beyond k the weight is exactly 0, and the
        # solvers' IRLS weight √ρ' has an infinite derivative there; `where`
        # sends that cotangent to the constant branch, `u * u` turned it into
        # a NaN gradient for every parameter (tests/test_gradient_contract.py).
        return k2 / 3.0 * (1.0 - u**3), jnp.where(u > 0, u * u, 0.0)


class GemanMcClureNoise(AbstractRobustNoise):
    """Geman-McClure: `ρ(s) = k² s / (k² + s)`, `ρ'(s) = k⁴ / (k² + s)²`.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        k2 = jnp.square(self.scale).astype(s.dtype)
        d = k2 + s
        return k2 * s / d, jnp.square(k2 / d)


class WelschNoise(AbstractRobustNoise):
    """Welsch (Leclerc): `ρ(s) = k² (1 − exp(−s/k²))`, `ρ'(s) = exp(−s/k²)`.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        k2 = jnp.square(self.scale).astype(s.dtype)
        w = jnp.exp(-s / k2)
        # exp underflows to exactly 0 beyond s ≈ 745 k² (an outlier of 27
        # scales); as for Tukey, `where` keeps the infinite derivative of the
        # IRLS weight √ρ' = 0 out of the gradient (it was NaN).
        return k2 * (1.0 - w), jnp.where(w > 0, w, 0.0)


class DCSNoise(AbstractRobustNoise):
    """Dynamic covariance scaling (Agarwal et al. 2013).

    With `Φ = scale` (note: in SQUARED whitened units, as in the paper and in
    GTSAM's `mEstimator.DCS`): `ρ(s) = s`, `ρ' = 1` for `s ≤ Φ`; beyond,
    `ρ(s) = Φ(3s − Φ)/(Φ + s)` and `ρ'(s) = 4Φ²/(Φ + s)²`.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `Φ > 0`, shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        phi = self.scale.astype(s.dtype)
        inside = s <= phi
        d = phi + s
        value = jnp.where(inside, s, phi * (3.0 * s - phi) / d)
        deriv = jnp.where(inside, jnp.ones_like(s), 4.0 * jnp.square(phi / d))
        return value, deriv


class FairNoise(AbstractRobustNoise):
    """Fair: with `e = √s`, `ρ(s) = 2k² (e/k − log(1 + e/k))`, `ρ'(s) = 1/(1 + e/k)`.

    Convex, with continuous derivatives of every order away from zero.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        k = self.scale.astype(s.dtype)
        x = _safe_sqrt(s) / k
        # ρ = 2k²(x − log(1 + x)) written as 2 s φ(x), φ(x) = (x − log1p(x))/x²
        # (φ → ½ at 0; a series below x = 1e-3, where the quotient cancels).
        # The autodiff derivative of ρ at s = 0 is then ρ'(0) = 1; the first
        # form gave 0 (through √s's zero derivative there), so the cost's
        # Hessian at a zero residual was 0 instead of the identity, and
        # every second-order route (the implicit adjoint's exact Hessian,
        # `jax.hessian` of a cost) was wrong there.
        small = x < 1e-3
        xs = jnp.where(small, 1.0, x)
        phi = jnp.where(
            small,
            0.5 - x / 3.0 + x * x / 4.0 - x * x * x / 5.0,
            (xs - jnp.log1p(xs)) / (xs * xs),
        )
        return 2.0 * s * phi, 1.0 / (1.0 + x)


class L2WithDeadZoneNoise(AbstractRobustNoise):
    """Quadratic outside a dead zone: with `e = √s`, `ρ(s) = (e − k)²` and
    `ρ'(s) = 1 − k/e` for `e > k`; zero inside (`e ≤ k`).

    Errors smaller than `k` cost nothing (an ε-insensitive loss). A graph
    whose every residual can sit in its dead zone has a singular normal
    matrix at the solution: anchor it with other factors.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        k = self.scale.astype(s.dtype)
        outside = s > k * k
        e = jnp.sqrt(jnp.where(outside, s, k * k))  # ≥ k > 0 where used
        value = jnp.where(outside, jnp.square(e - k), jnp.zeros_like(s))
        deriv = jnp.where(outside, 1.0 - k / e, jnp.zeros_like(s))
        return value, deriv


class TruncatedQuadraticNoise(AbstractRobustNoise):
    """Truncated least squares: `ρ(s) = min(s, k²)`; `ρ' = 1` for `s < k²`, else 0.

    Residuals beyond `k` are ignored entirely (weight zero), as in
    GTSAM's `mEstimator.TruncatedLeastSquares` and the TLS cost of
    graduated non-convexity. Not convex; the cost is flat in `k` once every
    residual is inside, so a learned `k` only gets a gradient from the
    rows it truncates.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    scale: Float[Array, "*rows"]

    def __init__(self, base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]):
        self.base = base
        self.scale = robust_scale(type(self).__name__, scale)

    def rho(self, s):
        k2 = jnp.square(self.scale).astype(s.dtype)
        inside = s < k2
        value = jnp.where(inside, s, k2 * jnp.ones_like(s))
        return value, jnp.where(inside, jnp.ones_like(s), jnp.zeros_like(s))
