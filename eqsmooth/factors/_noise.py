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
import math
from typing import ClassVar, TYPE_CHECKING

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .._precision import einsum


if TYPE_CHECKING:
    from ._masked_noise import MaskedNoise


def is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_positive(name: str, field: str, value) -> None:
    if is_concrete(value):
        arr = np.asarray(value)
        if arr.size and not np.all(np.isfinite(arr)):
            bad = np.argwhere(~np.isfinite(arr))[0].tolist()
            raise ValueError(
                f"{name}.{field} must be finite, got {arr.ravel()[:8]} (first bad "
                f"entry at index {tuple(bad)})"
            )
        if arr.size and not np.all(arr > 0):
            raise ValueError(
                f"{name}.{field} must be positive, got min {arr.min()} "
                f"(shape {arr.shape})"
            )


def positive_under_jit(name: str, field: str, value: Array) -> Array:
    """`value`, with a run-time check (`eqx.error_if`) when it is traced.

    Concrete values are checked eagerly by `check_positive`; a traced value
    (noise built inside `jit`, e.g. from learned parameters) would otherwise
    turn σ ≤ 0 into a silent inf/NaN cost.
    """
    if is_concrete(value) or not jnp.issubdtype(value.dtype, jnp.inexact):
        return value
    return eqx.error_if(
        value,
        ~jnp.all((value > 0) & jnp.isfinite(value)),
        f"{name}.{field} must be positive and finite (checked under jit)",
    )


def _check_square(name: str, field: str, value: Array) -> None:
    if value.ndim not in (2, 3) or value.shape[-1] != value.shape[-2]:
        raise ValueError(
            f"{name}: {field} must have shape (m, m) or (n, m, m), got {value.shape}"
        )


def _check_symmetric(name: str, field: str, value: Array) -> None:
    """Raise if a concrete matrix is not symmetric (no silent symmetrisation)."""
    if not is_concrete(value):
        return
    arr = np.asarray(value, dtype=np.float64)
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: {field} has non-finite entries")
    asym = np.max(np.abs(arr - np.swapaxes(arr, -1, -2)), initial=0.0)
    scale = max(np.max(np.abs(arr), initial=0.0), 1e-300)
    if asym > 1e-8 * scale + 1e-12:
        raise ValueError(
            f"{name}: {field} is not symmetric (largest |A - Aᵀ| entry {asym:.3g}); "
            "eqsmooth does not symmetrise it for you"
        )


def _cholesky_checked(name: str, field: str, value: Array) -> Array:
    """`cholesky(value)`, raising (concrete) or `error_if` (traced) if `value`
    is not positive definite."""
    L = jnp.linalg.cholesky(value)
    ok = jnp.all(jnp.isfinite(L)) & jnp.all(jnp.diagonal(L, axis1=-2, axis2=-1) > 0)
    if is_concrete(L):
        if not bool(ok):
            eig = np.linalg.eigvalsh(np.asarray(value, dtype=np.float64))
            raise ValueError(
                f"{name}: {field} is not positive definite (smallest eigenvalue "
                f"{eig.min():.3g}); a covariance or information matrix must be "
                "symmetric positive definite"
            )
        return L
    return eqx.error_if(
        L, ~ok, f"{name}: {field} is not positive definite (checked under jit)"
    )


def as_float(x) -> Array:
    # A value that is not a tracer (a number, a NumPy or concrete JAX array)
    # stays concrete even inside `jit`: it is then checked when the noise
    # model is built, instead of by an `eqx.error_if` in the program (a host
    # callback, which keeps JAX's persistent cache from storing it).
    with jax.ensure_compile_time_eval():
        x = jnp.asarray(x)
        if not jnp.issubdtype(x.dtype, jnp.inexact):
            x = x.astype(jax.dtypes.canonicalize_dtype(jnp.float64))
    return x


def _expand(x: Array, ndim: int) -> Array:
    return x.reshape(x.shape + (1,) * (ndim - x.ndim))


RowIndex = Int[np.ndarray, " k"] | Int[Array, " k"]
RowMask = Bool[np.ndarray, " n"] | Bool[Array, " n"]


def take_leading(a: ArrayLike, index: RowIndex) -> Array:
    """`a[index]` along the leading (row) axis, on the host for concrete
    arrays: eager JAX indexing would compile a small program for every new
    shape, which is what padding a graph is there to avoid."""
    if isinstance(a, jax.core.Tracer) or isinstance(index, jax.core.Tracer):
        return jnp.asarray(a)[index]
    return jax.device_put(np.asarray(a)[np.asarray(index)])


def device_mask(active: RowMask) -> Bool[Array, " n"]:
    """A row mask as a JAX array, transferred (not computed) when concrete."""
    if isinstance(active, np.ndarray):
        return jax.device_put(active)
    return jnp.asarray(active)


def check_row_mask(factor_name: str, what: str, active: Array, n: int) -> None:
    """Raise a `ValueError` naming `factor_name` and `what` (the mask's
    owner) unless the row mask `active` has one entry per row, `(n,)`."""
    if active.shape != (n,):
        raise ValueError(
            f"{factor_name}: {what} has shape {active.shape}; expected ({n},), "
            "one entry per row"
        )


def mask_gaussian(noise: "AbstractNoiseModel", active: RowMask) -> "MaskedNoise":
    """`MaskedNoise(noise, active)`: how a Gaussian model masks its rows."""
    # Imported here: MaskedNoise wraps the models defined in this module.
    from ._masked_noise import MaskedNoise

    return MaskedNoise(noise, device_mask(active))


def take_per_row(
    noise: "AbstractNoiseModel", field: str, per_row_ndim: int, index: RowIndex
) -> "AbstractNoiseModel":
    """`noise` with its parameter `field` indexed by row when it is per row
    (it then has `per_row_ndim` axes), unchanged when it is shared."""
    value = getattr(noise, field)
    if value.ndim != per_row_ndim:
        return noise
    return eqx.tree_at(lambda m: getattr(m, field), noise, take_leading(value, index))


def gaussian_log_normalizer(noise: "AbstractNoiseModel", n: int, m: int) -> Array:
    """`Σ log det R_i − ½ n m log 2π`: the Gaussian density's log constant."""
    # A Python float stays weakly typed: float32 models stay float32.
    return noise.log_det_sqrt_information(n, m) - 0.5 * n * m * math.log(2 * math.pi)


class AbstractNoiseModel(eqx.Module):
    """Base class of noise models (see the module docs for shapes).

    A noise model answers for itself whatever the rest of the library needs
    to know about it, so that no code elsewhere tests its class:

    - `is_gaussian` (a class attribute): whether the model is a Gaussian
        density (whitening only). Robust kernels and Student-t wrap one, and
        only one; Kalman filters accept only Gaussian models.
    - `name`: the name messages give it.
    - [`active_rows`][eqsmooth.factors.AbstractNoiseModel.active_rows]: its
        rows' mask.
    - [`curvature_model`][eqsmooth.factors.AbstractNoiseModel.curvature_model]:
        the Gaussian model of its curvature (the Laplace evidence's
        log-determinant).
    - [`take_rows`][eqsmooth.factors.AbstractNoiseModel.take_rows] and
        [`mask_rows`][eqsmooth.factors.AbstractNoiseModel.mask_rows]: its
        per-row parts, as [`eqsmooth.solve.pad_graph`][] needs them.
    - `sqrt_information_rows`: each row's square-root information matrix
        (filters, exporters).
    """

    is_gaussian: ClassVar[bool] = True

    @property
    def name(self) -> str:
        """The name messages give this model: by default its type without a
        leading underscore (`"DiagonalNoise"`); a robust model gives its
        constructor (`"HuberNoise"`)."""
        return type(self).__name__.lstrip("_")

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
    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        """Log normalising constant of `n` rows of dimension `m`.

        The negative log-likelihood of a stacked factor is
        `½ Σ ρ(‖R_i r_i‖²) − log_normalizer(n, m)`. Gaussian models return
        `Σ log det R_i − ½ n m log 2π`;
        [`eqsmooth.factors.StudentTNoise`][] returns its own (it is a
        normalised density); the robust kernels return their base model's
        Gaussian constant (they are losses, not normalised densities). A
        user-defined Gaussian model implements it as
        `return eqsmooth.factors.gaussian_log_normalizer(self, n, m)`.
        """

    @abc.abstractmethod
    def rho(
        self, s: Float[Array, " n"]
    ) -> tuple[Float[Array, " n"], Float[Array, " n"]]:
        """Robust loss `ρ(s)` and its derivative `ρ'(s)` at squared norms `s`."""

    @abc.abstractmethod
    def active_rows(self) -> Bool[Array, " n"] | None:
        """The rows that count (`(n,)` booleans), or `None` when every row
        does. Inactive rows (a [`eqsmooth.factors.MaskedNoise`][] mask) are
        inert: their whitened residuals and Jacobians are zero, and the
        factor's per-row data there is never read, so nothing they hold (NaN
        for a missing measurement) reaches a value or a derivative."""

    @abc.abstractmethod
    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        """Raise a `ValueError` naming `factor_name` if shapes do not fit `(n, m)`."""

    @abc.abstractmethod
    def curvature_model(self) -> "AbstractNoiseModel":
        """The noise model whose whitening gives this model's curvature in the
        Laplace evidence's log-determinant.

        Gaussian models, masked models and the robust kernels return
        themselves (the solvers' IRLS weights); a density whose curvature
        depends on the residual returns a Gaussian with its Fisher
        information ([`eqsmooth.factors.StudentTNoise.fisher_model`][]).
        """

    @abc.abstractmethod
    def take_rows(self, index: RowIndex) -> "AbstractNoiseModel":
        """The model of the rows `index` of the stack (a row may repeat).

        Per-row parameters (and a row mask) are indexed along their row
        axis; shared parameters are kept.

        **Arguments:**

        - `index`: `(k,)` integer row indices into the stack's `n` rows.

        **Returns:** a noise model of `k` rows, of the same kind.
        """

    @abc.abstractmethod
    def mask_rows(self, active: RowMask) -> "AbstractNoiseModel":
        """This model with the rows where `active` is false switched off.

        Gaussian models are wrapped in a [`eqsmooth.factors.MaskedNoise`][],
        a masked model combines the masks, a robust model masks its Gaussian
        base; a model that cannot mask rows raises `TypeError`.

        **Arguments:**

        - `active`: `(n,)` booleans, one per row.

        **Returns:** a noise model of the same `n` rows.
        """

    def sqrt_information_rows(
        self, n: int, m: int, dtype=None
    ) -> Float[Array, "n m m"]:
        """Each row's square-root information matrix `R_i`, `(n, m, m)`.

        Whitening is linear, so this is the model applied to identity
        matrices, whether its parameters are shared or per row. A robust or
        Student-t model gives its Gaussian base's `R_i` (the kernel is not a
        matrix); a masked row gives zeros.

        **Arguments:**

        - `n`, `m`: the stack's rows and residual dimension.
        - `dtype`: of the result; by default JAX's default float.

        **Returns:** the `(n, m, m)` matrices `R_i`.
        """
        eye = jnp.broadcast_to(jnp.eye(m, dtype=dtype), (n, m, m))
        return self.whiten(eye)


class AbstractGaussianNoise(AbstractNoiseModel):
    """A Gaussian noise model: whitening only (`ρ` is the identity), every
    row counts, its curvature model is itself, and it masks rows by being
    wrapped in a [`eqsmooth.factors.MaskedNoise`][]. Its `name` is its type's.

    Subclasses give `whiten`, `log_det_sqrt_information`, `check_shapes` and
    `take_rows`.
    """

    def rho(self, s):
        return s, jnp.ones_like(s)

    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        return gaussian_log_normalizer(self, n, m)

    def active_rows(self) -> None:
        return None

    def curvature_model(self) -> "AbstractGaussianNoise":
        return self

    def mask_rows(self, active: RowMask) -> "MaskedNoise":
        return mask_gaussian(self, active)


def _positive(name: str, field: str, value) -> Array:
    """`value` as a float array, checked positive and finite: at once when
    concrete, with `eqx.error_if` when traced."""
    value = positive_under_jit(name, field, as_float(value))
    check_positive(name, field, value)
    return value


def _sqrt_precision(name: str, positional: tuple, sqrt_precision) -> Array:
    """The keyword-only `sqrt_precision` of `name`, as a float array (checked
    positive, with `eqx.error_if` when traced)."""
    sqrt_precision = _keyword_only(name, positional, sqrt_precision)
    return positive_under_jit(name, "sqrt_precision", as_float(sqrt_precision))


def _keyword_only(name: str, positional: tuple, sqrt_precision):
    # `IsotropicNoise(0.1)` reads like a standard deviation but would be a
    # square-root precision: the field is keyword-only so that it cannot be
    # misread, and the error says which constructor was probably meant.
    if positional or sqrt_precision is None:
        sigma = "from_sigma" if name == "IsotropicNoise" else "from_sigmas"
        raise TypeError(
            f"{name} takes its square-root precision by keyword: "
            f"{name}(sqrt_precision=1/σ). Use {name}.{sigma}(σ) for standard "
            f"deviations, or {name}.from_precision(1/σ²)"
            + (f"; got {len(positional)} positional argument(s)" if positional else "")
        )
    return sqrt_precision


class IsotropicNoise(AbstractGaussianNoise):
    """Isotropic Gaussian noise: `R = sqrt_precision · I`.

    **Arguments:**

    - `sqrt_precision`: `1/σ`, shared (shape `()`) or per row (shape `(n,)`).
    """

    sqrt_precision: Float[Array, "*rows"]

    def __init__(
        self,
        *positional: object,
        sqrt_precision: Float[ArrayLike, "*rows"] | None = None,
    ):
        self.sqrt_precision = _sqrt_precision(
            "IsotropicNoise", positional, sqrt_precision
        )

    def __check_init__(self):
        check_positive("IsotropicNoise", "sqrt_precision", self.sqrt_precision)

    @classmethod
    def from_sigma(cls, sigma: Float[ArrayLike, "*rows"]) -> "IsotropicNoise":
        """Build from standard deviation(s) σ (`sqrt_precision = 1/σ`)."""
        sigma = _positive("IsotropicNoise", "sigma", sigma)
        return cls(sqrt_precision=1.0 / sigma)

    @classmethod
    def from_precision(cls, precision: Float[ArrayLike, "*rows"]) -> "IsotropicNoise":
        """Build from precision(s) `1/σ²` (`sqrt_precision = √precision`)."""
        p = _positive("IsotropicNoise", "precision", precision)
        return cls(sqrt_precision=jnp.sqrt(p))

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        s = self.sqrt_precision.astype(r.dtype)
        return r * (_expand(s, r.ndim) if s.ndim else s)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        s = self.sqrt_precision
        if s.ndim == 0:
            return n * m * jnp.log(s)
        return m * jnp.sum(jnp.log(s))

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        if self.sqrt_precision.shape not in ((), (n,)):
            raise ValueError(
                f"{factor_name}: IsotropicNoise.sqrt_precision has shape "
                f"{self.sqrt_precision.shape}; expected () or ({n},)"
            )

    def take_rows(self, index: RowIndex) -> "IsotropicNoise":
        return take_per_row(self, "sqrt_precision", 1, index)


class DiagonalNoise(AbstractGaussianNoise):
    """Diagonal Gaussian noise: `R = diag(sqrt_precision)`.

    **Arguments:**

    - `sqrt_precision`: `1/σ_j`, shared (shape `(m,)`) or per row (`(n, m)`).
    """

    sqrt_precision: Float[Array, "*rows m"]

    def __init__(
        self,
        *positional: object,
        sqrt_precision: Float[ArrayLike, "*rows m"] | None = None,
    ):
        self.sqrt_precision = _sqrt_precision(
            "DiagonalNoise", positional, sqrt_precision
        )

    def __check_init__(self):
        if self.sqrt_precision.ndim not in (1, 2):
            raise ValueError(
                "DiagonalNoise.sqrt_precision must have shape (m,) or (n, m), got "
                f"{self.sqrt_precision.shape}"
            )
        check_positive("DiagonalNoise", "sqrt_precision", self.sqrt_precision)

    @classmethod
    def from_sigmas(cls, sigmas: Float[ArrayLike, "*rows m"]) -> "DiagonalNoise":
        """Build from per-coordinate standard deviations σ_j (`1/σ_j`)."""
        sigmas = _positive("DiagonalNoise", "sigmas", sigmas)
        return cls(sqrt_precision=1.0 / sigmas)

    @classmethod
    def from_pose_sigmas(
        cls,
        *,
        translation: Float[ArrayLike, "*rows t"],
        rotation: Float[ArrayLike, "..."],
    ) -> "DiagonalNoise":
        """Build the noise of a pose from its translation and rotation σ, named.

        eqsmooth's pose tangents put the translation first (`SE2`: `(vx, vy,
        ω)`, `SE3`: `(v, ω)`), while GTSAM's `Pose3` puts the rotation first:
        naming the parts (keywords only) makes a port from either order
        right. `translation=[σx, σy, σz], rotation=[σroll, σpitch, σyaw]` for
        `SE3`; `translation=[σx, σy], rotation=[σθ]` (or a scalar) for `SE2`.
        Per-row σ carry a leading row axis on both.
        """
        t = as_float(translation)
        r = as_float(rotation)
        if r.ndim == 0 or (t.ndim == 2 and r.ndim == 1 and r.shape[0] == t.shape[0]):
            r = r[..., None]
        if (
            t.ndim not in (1, 2)
            or t.shape[-1] not in (2, 3)
            or r.shape[-1] != (1 if t.shape[-1] == 2 else 3)
            or t.shape[:-1] != r.shape[:-1]
        ):
            raise ValueError(
                "DiagonalNoise.from_pose_sigmas: translation must have 2 (SE2) or 3 "
                "(SE3) sigmas and rotation 1 or 3 to match, with the same leading "
                f"row axis; got translation {t.shape}, rotation {r.shape}"
            )
        return cls.from_sigmas(jnp.concatenate([t, r.astype(t.dtype)], axis=-1))

    @classmethod
    def from_variances(cls, variances: Float[ArrayLike, "*rows m"]) -> "DiagonalNoise":
        """Build from per-coordinate variances σ_j² (`1/σ_j`)."""
        v = _positive("DiagonalNoise", "variances", variances)
        return cls(sqrt_precision=1.0 / jnp.sqrt(v))

    @classmethod
    def from_precision(cls, precision: Float[ArrayLike, "*rows m"]) -> "DiagonalNoise":
        """Build from per-coordinate precisions `1/σ_j²` (`√precision`)."""
        p = _positive("DiagonalNoise", "precision", precision)
        return cls(sqrt_precision=jnp.sqrt(p))

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        s = self.sqrt_precision.astype(r.dtype)
        if s.ndim == 1:
            s = s[None]
        return r * _expand(s, r.ndim)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        s = self.sqrt_precision
        total = jnp.sum(jnp.log(s))
        return n * total if s.ndim == 1 else total

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        if self.sqrt_precision.shape not in ((m,), (n, m)):
            raise ValueError(
                f"{factor_name}: DiagonalNoise.sqrt_precision has shape "
                f"{self.sqrt_precision.shape}; expected ({m},) or ({n}, {m})"
            )

    def take_rows(self, index: RowIndex) -> "DiagonalNoise":
        return take_per_row(self, "sqrt_precision", 2, index)


class SqrtInformationNoise(AbstractGaussianNoise):
    """Full Gaussian noise given by a lower-triangular square-root information `R`.

    The whitened residual is `R r` and the information matrix is `RᵀR`.
    `sqrt_information` must be lower triangular with a positive diagonal:
    a concrete matrix with a nonzero entry above the diagonal raises
    `ValueError` (it is never silently dropped); under `jit` the upper
    triangle is ignored and the diagonal is checked with `eqx.error_if`.
    Prefer the named constructors `from_covariance` and `from_information`.

    **Arguments:**

    - `sqrt_information`: shared `(m, m)` or per row `(n, m, m)`.
    """

    sqrt_information: Float[Array, "*rows m m"]

    def __init__(self, sqrt_information: Float[ArrayLike, "*rows m m"]):
        R = as_float(sqrt_information)
        _check_square("SqrtInformationNoise", "sqrt_information", R)
        if is_concrete(R):
            upper = np.abs(np.triu(np.asarray(R, dtype=np.float64), 1))
            if upper.size and np.max(upper) > 0:
                raise ValueError(
                    "SqrtInformationNoise: sqrt_information must be lower triangular; "
                    f"it has entries up to {np.max(upper):.3g} above the diagonal. "
                    "Transpose an upper-triangular factor, or use "
                    "SqrtInformationNoise.from_information / from_covariance"
                )
        else:
            diag = jnp.diagonal(R, axis1=-2, axis2=-1)
            R = eqx.error_if(
                R,
                ~jnp.all(diag > 0),
                "SqrtInformationNoise.sqrt_information diagonal must be positive and "
                "finite (checked under jit)",
            )
        self.sqrt_information = jnp.tril(R)

    def __check_init__(self):
        R = self.sqrt_information
        if R.ndim not in (2, 3) or R.shape[-1] != R.shape[-2]:
            raise ValueError(
                "SqrtInformationNoise.sqrt_information must have shape (m, m) or "
                f"(n, m, m), got {R.shape}"
            )
        check_positive(
            "SqrtInformationNoise",
            "sqrt_information diagonal",
            jnp.diagonal(R, axis1=-2, axis2=-1),
        )

    @classmethod
    def from_covariance(
        cls, covariance: Float[ArrayLike, "*rows m m"]
    ) -> "SqrtInformationNoise":
        """Build from covariance matrices Σ (`R = chol(Σ)⁻¹`, so `RᵀR = Σ⁻¹`).

        Σ must be square, symmetric (it is not symmetrised for you) and
        positive definite; otherwise `ValueError` (concrete input) or an
        `eqx.error_if` run-time error (under `jit`) names the fault.
        """
        cov = as_float(covariance)
        _check_square("SqrtInformationNoise.from_covariance", "covariance", cov)
        _check_symmetric("SqrtInformationNoise.from_covariance", "covariance", cov)
        L = _cholesky_checked("SqrtInformationNoise.from_covariance", "covariance", cov)
        eye = jnp.broadcast_to(jnp.eye(cov.shape[-1], dtype=cov.dtype), cov.shape)
        R = jax.scipy.linalg.solve_triangular(L, eye, lower=True)
        return cls(R)

    @classmethod
    def from_information(
        cls, information: Float[ArrayLike, "*rows m m"]
    ) -> "SqrtInformationNoise":
        """Build from information (precision) matrices Λ (a lower-triangular `R`
        with `RᵀR = Λ`); Λ is checked like `from_covariance` checks Σ."""
        info = as_float(information)
        who = "SqrtInformationNoise.from_information"
        _check_square(who, "information", info)
        _check_symmetric(who, "information", info)
        _cholesky_checked(who, "information", info)
        # Reverse-order Cholesky: with J the exchange matrix, J Λ J = L Lᵀ gives
        # Λ = (J L J)(J Lᵀ J); R = J Lᵀ J is lower triangular.
        flip = info[..., ::-1, ::-1]
        L = jnp.linalg.cholesky(flip)
        R = jnp.swapaxes(L, -1, -2)[..., ::-1, ::-1]
        return cls(R)

    def whiten(self, r: Float[Array, "n m *rest"]) -> Float[Array, "n m *rest"]:
        R = self.sqrt_information.astype(r.dtype)
        if R.ndim == 2:
            return einsum("ij,nj...->ni...", R, r)
        return einsum("nij,nj...->ni...", R, r)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        R = self.sqrt_information
        total = jnp.sum(jnp.log(jnp.diagonal(R, axis1=-2, axis2=-1)))
        return n * total if R.ndim == 2 else total

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        if self.sqrt_information.shape not in ((m, m), (n, m, m)):
            raise ValueError(
                f"{factor_name}: SqrtInformationNoise.sqrt_information has shape "
                f"{self.sqrt_information.shape}; expected ({m}, {m}) or ({n}, {m}, {m})"
            )

    def take_rows(self, index: RowIndex) -> "SqrtInformationNoise":
        return take_per_row(self, "sqrt_information", 3, index)


def _check_scale(name: str, scale) -> None:
    check_positive(name, "scale", scale)


def robust_scale(name: str, scale: ArrayLike) -> Array:
    """A robust kernel's scale, with an `eqx.error_if` when it is traced."""
    return positive_under_jit(name, "scale", jnp.asarray(scale))


class AbstractRobustNoise(AbstractNoiseModel):
    """A robust loss `ρ` on top of a Gaussian noise model.

    Whitening, shapes and `log_det_sqrt_information` are those of `base`;
    subclasses give `ρ(s)` and `ρ'(s)` of the whitened squared norm
    `s = ‖R r‖²` through `rho` ([`eqsmooth.factors.RobustNoise`][] with an
    [`eqsmooth.factors.AbstractKernel`][], built by `HuberNoise`,
    `TukeyNoise`, ...), and the name messages use (`name`). Solvers use
    IRLS weights `√ρ'(s)` on residuals and Jacobians, whose Gauss-Newton
    gradient equals the gradient of the true cost `½ρ(s)`; the reported cost
    is `½ρ(s)`. Filters (which are Gaussian) reject robust models.

    **Fields:**

    - `base`: the Gaussian noise model.
    - `scale`: the loss's scale `k > 0` (whitened units), shared `()` or per
        row `(n,)`; learnable.
    """

    base: eqx.AbstractVar[AbstractNoiseModel]
    scale: eqx.AbstractVar[Float[Array, "*rows"]]
    is_gaussian: ClassVar[bool] = False

    def __check_init__(self):
        if not isinstance(self.base, AbstractNoiseModel):
            raise TypeError(
                f"{self.name}.base must be a Gaussian noise model such as "
                f"IsotropicNoise or DiagonalNoise, got {type(self.base).__name__}"
            )
        if not self.base.is_gaussian:
            # The kernel acts on the base's whitened residual only: an inner
            # kernel's ρ would be silently dropped.
            raise TypeError(
                f"{self.name}.base must be a Gaussian noise model such as "
                f"IsotropicNoise or DiagonalNoise, got {self.base.name}, "
                "which is not Gaussian: kernels do not nest (the inner one would "
                "be ignored); wrap the Gaussian model in one kernel"
            )
        _check_scale(self.name, self.scale)

    def whiten(self, r):
        return self.base.whiten(r)

    def log_det_sqrt_information(self, n: int, m: int) -> Float[Array, ""]:
        return self.base.log_det_sqrt_information(n, m)

    def log_normalizer(self, n: int, m: int) -> Float[Array, ""]:
        # A robust loss is not a normalised density: the constant is the base
        # Gaussian's (its own, so that masked rows are left out), so
        # likelihoods built from it are only indicative.
        return self.base.log_normalizer(n, m)

    def active_rows(self) -> Bool[Array, " n"] | None:
        return self.base.active_rows()

    def check_shapes(self, factor_name: str, n: int, m: int) -> None:
        self.base.check_shapes(factor_name, n, m)
        if self.scale.shape not in ((), (n,)):
            raise ValueError(
                f"{factor_name}: {self.name}.scale has shape "
                f"{self.scale.shape}; expected () or ({n},)"
            )

    def curvature_model(self) -> AbstractNoiseModel:
        # The IRLS weights are the curvature the solvers use; a robust loss
        # is not a density, so its evidence is only indicative anyway.
        return self

    def take_rows(self, index: RowIndex) -> AbstractNoiseModel:
        out = eqx.tree_at(lambda m: m.base, self, self.base.take_rows(index))
        return take_per_row(out, "scale", 1, index)

    def mask_rows(self, active: RowMask) -> AbstractNoiseModel:
        # The kernel acts on the base's whitened residual, which a masked
        # base zeroes: masking the base masks the rows.
        return eqx.tree_at(lambda m: m.base, self, self.base.mask_rows(active))
