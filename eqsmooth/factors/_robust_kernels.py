"""Robust noise as a composition: a Gaussian model and a robust kernel.

[`eqsmooth.factors.RobustNoise`][] holds a Gaussian `base`, an
[`eqsmooth.factors.AbstractKernel`][] (the M-estimator: `ρ` and `ρ'` as
functions of the whitened squared norm and the scale) and the learnable
`scale`, as GTSAM composes `Robust(mEstimator, noise)`. The named
constructors (`HuberNoise(base, k)`, `TukeyNoise(base, k)`, ...) build one.

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

import abc
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from ._noise import (
    AbstractNoiseModel,
    AbstractRobustNoise,
    is_concrete,
    robust_scale,
)


def _safe_sqrt(s: Array) -> Array:
    # √s with a zero (not infinite) derivative at s = 0.
    positive = s > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, s, jnp.ones_like(s))), 0.0)


class AbstractKernel(eqx.Module):
    """A robust kernel (M-estimator) of [`eqsmooth.factors.RobustNoise`][].

    Subclasses implement `rho(s, scale) -> (ρ(s), ρ'(s))` of the whitened
    squared norms `s` (shape `(n,)`) with the scale `k` (shared `()` or per
    row `(n,)`), and name the constructor that builds them (`name`, for
    messages). A kernel holds no parameters: the scale lives on the noise
    model, where it is learnable.
    """

    name: ClassVar[str]

    @abc.abstractmethod
    def rho(
        self, s: Float[Array, " n"], scale: Float[Array, "*rows"]
    ) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """`(ρ(s), ρ'(s))` at the whitened squared norms `s`."""


class RobustNoise(AbstractRobustNoise):
    """A Gaussian noise model with a robust kernel: `½ ρ(‖R r‖²)` per row.

    **Arguments:**

    - `base`: the Gaussian noise model (a [`eqsmooth.factors.MaskedNoise`][]
        may be one).
    - `kernel`: an [`eqsmooth.factors.AbstractKernel`][], e.g. `Huber()`.
    - `scale`: the kernel's scale `k > 0` (whitened units; DCS: `Φ` in
        squared units), shared `()` or per row `(n,)`; learnable.
    """

    base: AbstractNoiseModel
    kernel: AbstractKernel
    scale: Float[Array, "*rows"]

    def __init__(
        self,
        base: AbstractNoiseModel,
        kernel: AbstractKernel,
        scale: Float[ArrayLike, "*rows"],
    ):
        if not isinstance(kernel, AbstractKernel):
            raise TypeError(
                "RobustNoise.kernel must be an AbstractKernel such as Huber() or "
                f"Tukey(), got {type(kernel).__name__}"
            )
        self.base = base
        self.kernel = kernel
        self.scale = robust_scale(kernel.name, scale)

    @property
    def name(self) -> str:
        return self.kernel.name

    def rho(self, s):
        return self.kernel.rho(s, self.scale)


class Huber(AbstractKernel):
    """Huber robust loss on top of a Gaussian model.

    With whitened squared norm `s = ‖R r‖²` and scale `k` (in whitened units):
    `ρ(s) = s` for `s ≤ k²`, else `2k√s − k²`. Conventions of
    [`eqsmooth.factors.AbstractRobustNoise`][].

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "HuberNoise"

    def rho(self, s, scale):
        k = scale.astype(s.dtype)
        inside = s <= k * k
        safe_s = jnp.where(inside, k * k, s)  # never sqrt(0) in the untaken branch
        root = jnp.sqrt(safe_s)
        value = jnp.where(inside, s, 2 * k * root - k * k)
        deriv = jnp.where(inside, jnp.ones_like(s), k / root)
        return value, deriv


class Cauchy(AbstractKernel):
    """Cauchy (Lorentzian) robust loss: `ρ(s) = k² log(1 + s/k²)`.

    Conventions of [`eqsmooth.factors.AbstractRobustNoise`][].

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "CauchyNoise"

    def rho(self, s, scale):
        k2 = (scale * scale).astype(s.dtype)
        return k2 * jnp.log1p(s / k2), 1.0 / (1.0 + s / k2)


class Tukey(AbstractKernel):
    """Tukey's biweight: outliers beyond `k` get zero weight.

    `ρ(s) = (k²/3)(1 − (1 − s/k²)³)` and `ρ'(s) = (1 − s/k²)²` for `s ≤ k²`;
    `ρ = k²/3`, `ρ' = 0` beyond. Not convex: start near the solution (or
    from a convex kernel's solution).

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "TukeyNoise"

    def rho(self, s, scale):
        k2 = jnp.square(scale).astype(s.dtype)
        u = jnp.clip(1.0 - s / k2, 0.0, None)
        # `where`, not `u * u`: beyond k the weight is exactly 0, and the
        # solvers' IRLS weight √ρ' has an infinite derivative there; `where`
        # sends that cotangent to the constant branch, `u * u` turned it into
        # a NaN gradient for every parameter (tests/test_gradient_contract.py).
        return k2 / 3.0 * (1.0 - u**3), jnp.where(u > 0, u * u, 0.0)


class GemanMcClure(AbstractKernel):
    """Geman-McClure: `ρ(s) = k² s / (k² + s)`, `ρ'(s) = k⁴ / (k² + s)²`.

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "GemanMcClureNoise"

    def rho(self, s, scale):
        k2 = jnp.square(scale).astype(s.dtype)
        d = k2 + s
        return k2 * s / d, jnp.square(k2 / d)


class Welsch(AbstractKernel):
    """Welsch (Leclerc): `ρ(s) = k² (1 − exp(−s/k²))`, `ρ'(s) = exp(−s/k²)`.

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "WelschNoise"

    def rho(self, s, scale):
        k2 = jnp.square(scale).astype(s.dtype)
        w = jnp.exp(-s / k2)
        # exp underflows to exactly 0 beyond s ≈ 745 k² (an outlier of 27
        # scales); as for Tukey, `where` keeps the infinite derivative of the
        # IRLS weight √ρ' = 0 out of the gradient (it was NaN).
        return k2 * (1.0 - w), jnp.where(w > 0, w, 0.0)


class DCS(AbstractKernel):
    """Dynamic covariance scaling (Agarwal et al. 2013).

    With `Φ = scale` (note: in SQUARED whitened units, as in the paper and in
    GTSAM's `mEstimator.DCS`): `ρ(s) = s`, `ρ' = 1` for `s ≤ Φ`; beyond,
    `ρ(s) = Φ(3s − Φ)/(Φ + s)` and `ρ'(s) = 4Φ²/(Φ + s)²`.

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "DCSNoise"

    def rho(self, s, scale):
        phi = scale.astype(s.dtype)
        inside = s <= phi
        d = phi + s
        value = jnp.where(inside, s, phi * (3.0 * s - phi) / d)
        deriv = jnp.where(inside, jnp.ones_like(s), 4.0 * jnp.square(phi / d))
        return value, deriv


class Fair(AbstractKernel):
    """Fair: with `e = √s`, `ρ(s) = 2k² (e/k − log(1 + e/k))`, `ρ'(s) = 1/(1 + e/k)`.

    Convex, with continuous derivatives of every order away from zero.

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "FairNoise"

    def rho(self, s, scale):
        k = scale.astype(s.dtype)
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


class L2WithDeadZone(AbstractKernel):
    """Quadratic outside a dead zone: with `e = √s`, `ρ(s) = (e − k)²` and
    `ρ'(s) = 1 − k/e` for `e > k`; zero inside (`e ≤ k`).

    Errors smaller than `k` cost nothing (an ε-insensitive loss). A graph
    whose every residual can sit in its dead zone has a singular normal
    matrix at the solution: anchor it with other factors.

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "L2WithDeadZoneNoise"

    def rho(self, s, scale):
        k = scale.astype(s.dtype)
        outside = s > k * k
        e = jnp.sqrt(jnp.where(outside, s, k * k))  # ≥ k > 0 where used
        value = jnp.where(outside, jnp.square(e - k), jnp.zeros_like(s))
        deriv = jnp.where(outside, 1.0 - k / e, jnp.zeros_like(s))
        return value, deriv


class TruncatedQuadratic(AbstractKernel):
    """Truncated least squares: `ρ(s) = min(s, k²)`; `ρ' = 1` for `s < k²`, else 0.

    Residuals beyond `k` are ignored entirely (weight zero), as in
    GTSAM's `mEstimator.TruncatedLeastSquares` and the TLS cost of
    graduated non-convexity. Not convex; the cost is flat in `k` once every
    residual is inside, so a learned `k` only gets a gradient from the
    rows it truncates.

    `scale` is the kernel's `k` (see the noise constructor); the kernel
    itself holds no parameters.
    """

    name: ClassVar[str] = "TruncatedQuadraticNoise"

    def rho(self, s, scale):
        k2 = jnp.square(scale).astype(s.dtype)
        inside = s < k2
        value = jnp.where(inside, s, k2 * jnp.ones_like(s))
        return value, jnp.where(inside, jnp.ones_like(s), jnp.zeros_like(s))


def HuberNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Huber robust loss on top of a Gaussian model.

    With whitened squared norm `s = ‖R r‖²` and scale `k` (in whitened units):
    `ρ(s) = s` for `s ≤ k²`, else `2k√s − k²`. Conventions of
    [`eqsmooth.factors.AbstractRobustNoise`][].

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: threshold `k > 0`, shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, Huber(), scale)`.
    """
    return RobustNoise(base, Huber(), scale)


def CauchyNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Cauchy (Lorentzian) robust loss: `ρ(s) = k² log(1 + s/k²)`.

    Conventions of [`eqsmooth.factors.AbstractRobustNoise`][].

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0`, shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, Cauchy(), scale)`.
    """
    return RobustNoise(base, Cauchy(), scale)


def TukeyNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Tukey's biweight: outliers beyond `k` get zero weight.

    `ρ(s) = (k²/3)(1 − (1 − s/k²)³)` and `ρ'(s) = (1 − s/k²)²` for `s ≤ k²`;
    `ρ = k²/3`, `ρ' = 0` beyond. Not convex: start near the solution (or
    from a convex kernel's solution).

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, Tukey(), scale)`.
    """
    return RobustNoise(base, Tukey(), scale)


def GemanMcClureNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Geman-McClure: `ρ(s) = k² s / (k² + s)`, `ρ'(s) = k⁴ / (k² + s)²`.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, GemanMcClure(), scale)`.
    """
    return RobustNoise(base, GemanMcClure(), scale)


def WelschNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Welsch (Leclerc): `ρ(s) = k² (1 − exp(−s/k²))`, `ρ'(s) = exp(−s/k²)`.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, Welsch(), scale)`.
    """
    return RobustNoise(base, Welsch(), scale)


def DCSNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Dynamic covariance scaling (Agarwal et al. 2013).

    With `Φ = scale` (note: in SQUARED whitened units, as in the paper and in
    GTSAM's `mEstimator.DCS`): `ρ(s) = s`, `ρ' = 1` for `s ≤ Φ`; beyond,
    `ρ(s) = Φ(3s − Φ)/(Φ + s)` and `ρ'(s) = 4Φ²/(Φ + s)²`.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `Φ > 0`, shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, DCS(), scale)`.
    """
    return RobustNoise(base, DCS(), scale)


def FairNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Fair: with `e = √s`, `ρ(s) = 2k² (e/k − log(1 + e/k))`, `ρ'(s) = 1/(1 + e/k)`.

    Convex, with continuous derivatives of every order away from zero.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, Fair(), scale)`.
    """
    return RobustNoise(base, Fair(), scale)


def L2WithDeadZoneNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Quadratic outside a dead zone: with `e = √s`, `ρ(s) = (e − k)²` and
    `ρ'(s) = 1 − k/e` for `e > k`; zero inside (`e ≤ k`).

    Errors smaller than `k` cost nothing (an ε-insensitive loss). A graph
    whose every residual can sit in its dead zone has a singular normal
    matrix at the solution: anchor it with other factors.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, L2WithDeadZone(), scale)`.
    """
    return RobustNoise(base, L2WithDeadZone(), scale)


def TruncatedQuadraticNoise(
    base: AbstractNoiseModel, scale: Float[ArrayLike, "*rows"]
) -> "RobustNoise":
    """Truncated least squares: `ρ(s) = min(s, k²)`; `ρ' = 1` for `s < k²`, else 0.

    Residuals beyond `k` are ignored entirely (weight zero), as in
    GTSAM's `mEstimator.TruncatedLeastSquares` and the TLS cost of
    graduated non-convexity. Not convex; the cost is flat in `k` once every
    residual is inside, so a learned `k` only gets a gradient from the
    rows it truncates.

    **Arguments:**

    - `base`: the Gaussian noise model.
    - `scale`: `k > 0` (whitened units), shared `()` or per row `(n,)`; learnable.

    **Returns:** `RobustNoise(base, TruncatedQuadratic(), scale)`.
    """
    return RobustNoise(base, TruncatedQuadratic(), scale)


# The kernels a KernelChoice selects from, in this order.
KERNELS: tuple[type[AbstractKernel], ...] = (
    Huber,
    Cauchy,
    Tukey,
    GemanMcClure,
    Welsch,
    DCS,
    Fair,
    L2WithDeadZone,
    TruncatedQuadratic,
)


class KernelChoice(AbstractKernel):
    """One of the nine kernels, chosen by data rather than by type.

    Each kernel class is part of a compiled solve's static structure, so a
    sweep over kernels (`HuberNoise`, then `TukeyNoise`, ...) compiles the
    solve once per kernel. A `KernelChoice` holds the choice as an integer
    array, and `rho` selects the kernel at run time (`lax.switch`): a sweep
    over kernels is one program, compiled once, whose solves differ only in
    data. The price is a program that contains all nine kernels (a little
    more to compile the first time).

    **Arguments:**

    - `kernel`: a kernel class (`Huber`, `Tukey`, ...) or its name
        (`"Huber"`).
    """

    index: Int[Array, ""]
    name: ClassVar[str] = "KernelChoice"

    def __init__(self, kernel: type[AbstractKernel] | str):
        names = [k.__name__ for k in KERNELS]
        if not isinstance(kernel, str) and not (
            isinstance(kernel, type) and issubclass(kernel, AbstractKernel)
        ):
            raise TypeError(
                "KernelChoice: kernel must be a kernel class (Huber, Tukey, ...) or "
                f"its name, one of {names}; got {kernel!r} (an index is set as "
                "data: eqx.tree_at(lambda k: k.index, KernelChoice('Huber'), i))"
            )
        key = kernel if isinstance(kernel, str) else kernel.__name__
        if key not in names:
            raise ValueError(f"KernelChoice: unknown kernel {kernel!r}; one of {names}")
        # A transfer of a NumPy scalar of the final dtype: `jnp.asarray` of
        # an int compiles a small conversion program in every fresh process.
        self.index = jax.device_put(np.int32(names.index(key)))

    def __check_init__(self):
        if is_concrete(self.index) and not 0 <= int(self.index) < len(KERNELS):
            raise ValueError(_index_message(int(self.index)))

    def rho(self, s, scale):
        branches = [lambda s, k, K=K: K().rho(s, k) for K in KERNELS]
        # `lax.switch` clamps an index out of range to the last kernel: an
        # index set by `eqx.tree_at` or swept as data is checked at run time.
        index = eqx.error_if(
            self.index,
            (self.index < 0) | (self.index >= len(KERNELS)),
            _index_message(None),
        )
        return jax.lax.switch(index, branches, s, scale)


def _index_message(index: int | None) -> str:
    names = [k.__name__ for k in KERNELS]
    got = "" if index is None else f", got {index}"
    return (
        f"KernelChoice.index must be in 0..{len(KERNELS) - 1}, one per kernel of "
        f"{names}{got} (lax.switch would clamp it to a kernel not chosen)"
    )
