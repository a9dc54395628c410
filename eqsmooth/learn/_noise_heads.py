"""Learned noise heads: features of a frame -> square-root precisions.

A heteroscedastic noise model is a Gaussian whose precision depends on the
data: a virtual sensor that sees the target clearly should be trusted more
than one that does not. A noise head is the learnable map from per-frame
features (a visibility count, the sensor's own uncertainty estimate, ...) to
the square-root precisions `σ⁻¹` of the measurement factor, for example

    sqrt_precision = head(features)              # (T, m)
    noise = eqs.DiagonalNoise(sqrt_precision=sqrt_precision)

Both heads keep `σ⁻¹` above a floor (`σ` below a cap), so that no frame is
ever ignored entirely and no gradient is lost to a vanishing precision, and
both start at the constant `σ⁻¹ = 1/σ₀`: training starts from the
homoscedastic model with the given standard deviations.
"""

import abc

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray


def _above_floor(who: str, sigma, floor) -> np.ndarray:
    """`1/σ₀ − floor`, in float64, after checking the arguments of `who`."""
    try:
        sigma = np.asarray(sigma, np.float64)
        floor_arr = np.asarray(floor, np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{who}: sigma and floor must be numbers: {err}") from None
    if sigma.ndim > 1:
        raise ValueError(
            f"{who}: sigma must have shape () or (m,), one per residual component; "
            f"got {sigma.shape}"
        )
    if not np.all(np.isfinite(sigma) & (sigma > 0)):
        raise ValueError(
            f"{who}: sigma (the initial standard deviation) must be positive and "
            f"finite, got {sigma.tolist()}"
        )
    if floor_arr.ndim > 1 or (floor_arr.ndim == 1 and floor_arr.shape != sigma.shape):
        raise ValueError(
            f"{who}: floor must be a float or one per component of sigma "
            f"{sigma.shape}; got shape {floor_arr.shape}"
        )
    if not np.all(np.isfinite(floor_arr) & (floor_arr >= 0)):
        raise ValueError(f"{who}: floor must be >= 0 and finite, got {floor!r}")
    if np.any(floor_arr >= 1.0 / sigma):
        raise ValueError(
            f"{who}: floor {floor!r} must be below 1/sigma = "
            f"{np.round(1.0 / sigma, 6).tolist()}: the head starts at the square-root "
            "precision 1/sigma and never goes below the floor (lower the floor, or "
            "start from a smaller sigma)"
        )
    return np.asarray(1.0 / sigma - floor_arr)


class AbstractNoiseHead(eqx.Module):
    """Maps features `(*batch, f)` to square-root precisions `(*batch, *m)`.

    `m` is the shape of the `sigma` the head was built with: `()` for one
    precision per frame (an isotropic noise), `(m,)` for one per residual
    component (a diagonal noise).
    """

    @abc.abstractmethod
    def __call__(self, features: Float[Array, "*batch f"]) -> Float[Array, "..."]:
        """`σ⁻¹` of every frame."""


class ConstantNoiseHead(AbstractNoiseHead):
    """One learned square-root precision (per component), shared by every frame.

    `σ⁻¹ = floor + exp(θ)`, starting at `σ⁻¹ = 1/sigma`. The features only
    give the batch shape.

    **Arguments:**

    - `sigma`: the initial standard deviation(s) `σ₀`, shape `()` or `(m,)`.
    - `floor`: the smallest square-root precision (`1/σ_max`), a float or
        one per component.
    - `dtype`: of the parameter (NumPy's float32 by default).
    """

    log_sqrt_precision: Float[Array, "*m"]
    floor: float | tuple[float, ...] = eqx.field(static=True)

    def __init__(
        self,
        sigma: Float[ArrayLike, "*m"],
        *,
        floor: float | tuple[float, ...] = 0.0,
        dtype=np.float32,
    ):
        above = _above_floor("ConstantNoiseHead", sigma, floor)
        self.floor = floor
        self.log_sqrt_precision = jnp.asarray(np.log(above).astype(dtype))

    def __call__(self, features):
        p = jnp.exp(self.log_sqrt_precision)
        s = jnp.broadcast_to(jnp.asarray(self.floor, p.dtype), p.shape) + p
        return jnp.broadcast_to(s, features.shape[:-1] + s.shape)


class HeteroscedasticNoiseHead(AbstractNoiseHead):
    """`σ⁻¹(x) = floor + s₀ · softplus(MLP((x − shift)/scale) + softplus⁻¹(1))`.

    The MLP's last layer starts at zero, so training starts from the
    constant `σ⁻¹ = floor + s₀ = 1/sigma`. `s₀` is either fixed (the
    default) or learned, in log space, beside the MLP.

    **Arguments:**

    - `sigma`: the initial standard deviation(s) `σ₀`, shape `()` (the head
        returns one precision per frame) or `(m,)` (one per component).
    - `in_size`: the number of features per frame.
    - `width`, `depth`: the MLP's hidden layers (ReLU).
    - `key`: initialises the MLP.
    - `floor`: the smallest square-root precision, a float or one per
        component.
    - `learn_scale`: learn `s₀` too (as `log s₀`).
    - `shift`, `scale`: normalise the features before the MLP (e.g. their
        training mean and standard deviation).
    - `dtype`: of the MLP and the learned scale (JAX's default float for the
        MLP and float32 for the scale by default).
    """

    mlp: eqx.nn.MLP
    log_scale: Float[Array, "*m"] | None
    fixed_scale: float | tuple[float, ...] | None = eqx.field(static=True)
    floor: float | tuple[float, ...] = eqx.field(static=True)
    shift: float = eqx.field(static=True)
    scale: float = eqx.field(static=True)

    def __init__(
        self,
        sigma: Float[ArrayLike, "*m"],
        in_size: int,
        *,
        width: int,
        depth: int,
        key: PRNGKeyArray,
        floor: float | tuple[float, ...] = 0.0,
        learn_scale: bool = False,
        shift: float = 0.0,
        scale: float = 1.0,
        dtype=None,
    ):
        who = "HeteroscedasticNoiseHead"
        base = _above_floor(who, sigma, floor)
        for name, value in (("in_size", in_size), ("width", width)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise TypeError(f"{who}: {name} must be an int, got {value!r}")
            if value < 1:
                raise ValueError(f"{who}: {name} must be >= 1, got {value}")
        if isinstance(depth, bool) or not isinstance(depth, (int, np.integer)):
            raise TypeError(f"{who}: depth must be an int, got {depth!r}")
        if depth < 0:
            raise ValueError(f"{who}: depth must be >= 0, got {depth}")
        if not np.isfinite(shift):
            raise ValueError(f"{who}: shift must be finite, got {shift}")
        if not (np.isfinite(scale) and scale > 0):
            raise ValueError(f"{who}: scale must be positive and finite, got {scale}")
        sigma = np.asarray(sigma, np.float32)
        out = 1 if sigma.ndim == 0 else sigma.shape[0]
        mlp = eqx.nn.MLP(
            in_size, out, width, depth, activation=jax.nn.relu, key=key, dtype=dtype
        )
        last = mlp.layers[-1]
        last = eqx.tree_at(
            lambda lin: (lin.weight, lin.bias),
            last,
            (jnp.zeros_like(last.weight), jnp.zeros_like(last.bias)),
        )
        self.mlp = eqx.tree_at(lambda m: m.layers[-1], mlp, last)
        self.floor = floor
        self.shift = shift
        self.scale = scale
        if learn_scale:
            scale_dtype = np.float32 if dtype is None else dtype
            self.log_scale = jnp.asarray(np.log(base).astype(scale_dtype))
            self.fixed_scale = None
        else:
            self.log_scale = None
            self.fixed_scale = float(base) if base.ndim == 0 else tuple(base.tolist())

    def __call__(self, features):
        if features.ndim < 1 or features.shape[-1] != self.mlp.in_size:
            raise ValueError(
                f"HeteroscedasticNoiseHead was built with in_size={self.mlp.in_size} "
                f"features per frame; got features of shape {features.shape} (the "
                "last axis holds a frame's features)"
            )
        dtype = self.mlp.layers[0].weight.dtype
        x = (features.astype(dtype) - self.shift) / self.scale
        lead = x.shape[:-1]
        out = jax.vmap(self.mlp)(x.reshape(-1, x.shape[-1])).reshape(lead + (-1,))
        if self.log_scale is None:
            s0 = jnp.asarray(self.fixed_scale, dtype)
        else:
            s0 = jnp.exp(self.log_scale).astype(dtype)
        if s0.ndim == 0:
            out = out[..., 0]
        shift = float(np.log(np.expm1(1.0)))  # softplus(shift) = 1
        s = jnp.broadcast_to(s0, out.shape) * jax.nn.softplus(out + shift)
        return jnp.broadcast_to(jnp.asarray(self.floor, s.dtype), s.shape) + s
