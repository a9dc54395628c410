"""Numerical helpers shared by the Lie groups.

Every scalar coefficient below is an even analytic function of an angle, so it is
written as a function of `t = theta**2`. Close to `t = 0` the closed form loses
precision (cancellation) or divides zero by zero, so a truncated Taylor series is
used instead. The switch uses the "double where" pattern: the branch that is not
taken is evaluated at a harmless dummy input, so its derivative can never be
`inf`/`nan` and poison the gradient of the selected branch.
"""

import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


def default_float_dtype() -> np.dtype:
    """The floating dtype JAX uses by default (float64 only when x64 is enabled)."""
    return np.dtype(jax.dtypes.canonicalize_dtype(jnp.float64))


def as_float_array(x, dtype=None) -> Array:
    """Convert `x` to a floating JAX array, keeping its dtype if already floating."""
    x = jnp.asarray(x, dtype=dtype)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(default_float_dtype())
    return x


def series_threshold(dtype) -> float:
    """Angle below which the Taylor series of the coefficients below are used.

    The closed forms lose about `eps / theta**4` relative precision (the worst case is
    `se3_a3`), while the series truncated after the `t**4` term err by roughly
    `5e-10 * theta**10`. Balancing the two gives `theta ~ 6 * eps**(1/14)`: about 0.46
    for float64 and 1.9 for float32.
    """
    eps = float(jnp.finfo(dtype).eps)
    return min(6.0 * eps ** (1 / 14), 2.5)


def atan_threshold(dtype) -> float:
    """Ratio `x` below which `atan(x) / x` is evaluated by its Taylor series.

    That series (`sum_k (-x**2)**k / (2k + 1)`, truncated after 8 terms) converges
    slowly, so it is cut where its first neglected term `x**16 / 17` reaches `eps`:
    about 0.12 for float64 and 0.44 for float32.
    """
    eps = float(jnp.finfo(dtype).eps)
    return (17.0 * eps) ** (1 / 16)


def _horner(coeffs: Sequence[float], t: Array) -> Array:
    out = jnp.full_like(t, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        out = out * t + c
    return out


def series_or_closed_form(
    t: Float[Array, "*batch"],
    threshold: float,
    coeffs: Sequence[float],
    closed_form: Callable[[Array], Array],
) -> Float[Array, "*batch"]:
    """Evaluate an even function of `theta` given `t = theta**2`.

    `coeffs` are its Taylor coefficients in powers of `t`; `closed_form` receives
    `theta = sqrt(t)` and is only ever evaluated away from zero.
    """
    small = t < threshold**2
    t_series = jnp.where(small, t, 0.0)
    # A dummy angle of 1 rad is safe for every closed form used here.
    t_closed = jnp.where(small, 1.0, t)
    series = _horner(coeffs, t_series)
    closed = closed_form(jnp.sqrt(t_closed))
    return jnp.where(small, series, closed)


# Taylor coefficients (in powers of t = theta**2) of the coefficients below; each
# series is truncated after the t**4 term.
_SINC = (1.0, -1 / 6, 1 / 120, -1 / 5040, 1 / 362880)
_A = (1 / 2, -1 / 24, 1 / 720, -1 / 40320, 1 / 3628800)
_B = (1 / 6, -1 / 120, 1 / 5040, -1 / 362880, 1 / 39916800)
_C = (1 / 12, 1 / 720, 1 / 30240, 1 / 1209600, 1 / 47900160)
_SE3_A2 = (1 / 24, -1 / 720, 1 / 40320, -1 / 3628800, 1 / 479001600)
_SE3_A3 = (1 / 120, -1 / 2520, 1 / 120960, -1 / 9979200, 1 / 1245404160)
_COS_HALF = (1.0, -1 / 8, 1 / 384, -1 / 46080, 1 / 10321920)
_SINC_HALF_OVER_2 = (1 / 2, -1 / 48, 1 / 3840, -1 / 645120, 1 / 185794560)


def sinc(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`sin(theta) / theta` as a function of `t = theta**2`."""
    thr = series_threshold(t.dtype)
    return series_or_closed_form(t, thr, _SINC, lambda th: jnp.sin(th) / th)


def coef_a(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(1 - cos(theta)) / theta**2` as a function of `t = theta**2`."""
    thr = series_threshold(t.dtype)
    # 2 sin^2(theta/2) avoids the cancellation in 1 - cos(theta).
    return series_or_closed_form(
        t, thr, _A, lambda th: 2.0 * jnp.square(jnp.sin(0.5 * th) / th)
    )


def coef_b(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(theta - sin(theta)) / theta**3` as a function of `t = theta**2`."""
    thr = series_threshold(t.dtype)
    return series_or_closed_form(t, thr, _B, lambda th: (th - jnp.sin(th)) / th**3)


def coef_c(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(1 - (theta/2) cot(theta/2)) / theta**2` as a function of `t = theta**2`.

    This is the coefficient of `hat(w)**2` in the inverse SO(3) Jacobians. Written
    with `cot(theta/2)` it is regular at `theta = pi` (unlike the textbook form with
    `(1 + cos) / sin`) and singular only at `theta = 2 pi`.
    """
    thr = series_threshold(t.dtype)

    def closed(th):
        half = 0.5 * th
        return (1.0 - half * jnp.cos(half) / jnp.sin(half)) / jnp.square(th)

    return series_or_closed_form(t, thr, _C, closed)


def se3_a2(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(theta**2 + 2 cos(theta) - 2) / (2 theta**4)` as a function of `t`."""
    thr = series_threshold(t.dtype)
    return series_or_closed_form(
        t,
        thr,
        _SE3_A2,
        lambda th: (jnp.square(th) + 2.0 * jnp.cos(th) - 2.0) / (2.0 * th**4),
    )


def se3_a3(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(2 theta - 3 sin(theta) + theta cos(theta)) / (2 theta**5)` as a function of
    `t`."""
    thr = series_threshold(t.dtype)
    return series_or_closed_form(
        t,
        thr,
        _SE3_A3,
        lambda th: (2.0 * th - 3.0 * jnp.sin(th) + th * jnp.cos(th)) / (2.0 * th**5),
    )


def cos_half(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`cos(theta / 2)` as a function of `t = theta**2`."""
    thr = series_threshold(t.dtype)
    return series_or_closed_form(t, thr, _COS_HALF, lambda th: jnp.cos(0.5 * th))


def sin_half_over(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`sin(theta / 2) / theta` as a function of `t = theta**2`."""
    thr = series_threshold(t.dtype)
    return series_or_closed_form(
        t, thr, _SINC_HALF_OVER_2, lambda th: jnp.sin(0.5 * th) / th
    )


_ATAN_OVER_X = tuple((-1.0) ** k / (2 * k + 1) for k in range(8))


def quat_log_scale(
    w: Float[Array, "*batch"], v_sq: Float[Array, "*batch"]
) -> Float[Array, "*batch"]:
    """Scale `s` such that `s * v` is the rotation vector of quaternion `(w, v)`.

    `s = 2 atan2(|v|, |w|) sign(w) / |v|`, the sign choosing the representative with
    `w >= 0` so that the angle lies in `[0, pi]`. The result depends only on the
    direction of `(w, v)`, not on its norm. Near the identity (`|v| << |w|`) it is
    evaluated as `(2 / w) * atan(x) / x` with `x = |v| / |w|` by Taylor series,
    which avoids the square root of zero; near `pi` (`w -> 0`) `atan2` stays
    accurate and its derivative finite.
    """
    thr = atan_threshold(w.dtype)
    w_sq = jnp.square(w)
    small = v_sq < thr**2 * w_sq
    w_series = jnp.where(small, w, 1.0)
    x_sq = jnp.where(small, v_sq, 0.0) / jnp.square(w_series)
    series = 2.0 * _horner(_ATAN_OVER_X, x_sq) / w_series
    v_sq_closed = jnp.where(small, 1.0, v_sq)
    norm_v = jnp.sqrt(v_sq_closed)
    sign = jnp.where(w < 0, -1.0, 1.0).astype(w.dtype)
    closed = 2.0 * sign * jnp.arctan2(norm_v, jnp.abs(w)) / norm_v
    return jnp.where(small, series, closed)


def broadcast_batch(*arrays: Array) -> tuple[Array, ...]:
    """Broadcast the leading (batch) axes of arrays, keeping each last axis."""
    batch = jnp.broadcast_shapes(*(a.shape[:-1] for a in arrays))
    return tuple(jnp.broadcast_to(a, batch + a.shape[-1:]) for a in arrays)


def matvec(m: Array, v: Array) -> Array:
    """Batched matrix-vector product (batch axes must already agree)."""
    return (m @ v[..., None])[..., 0]


def stack_matrix(rows: Sequence[Sequence[Array]]) -> Array:
    """Build a `(*batch, n, m)` matrix from nested lists of `(*batch,)` arrays."""
    return jnp.stack([jnp.stack(list(row), axis=-1) for row in rows], axis=-2)


def pi_like(x: Array) -> Array:
    return jnp.asarray(math.pi, dtype=x.dtype)
