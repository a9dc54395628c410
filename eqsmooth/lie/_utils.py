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
from fractions import Fraction

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._precision import matmul


def default_float_dtype() -> np.dtype:
    """The floating dtype JAX uses by default (float64 only when x64 is enabled)."""
    return np.dtype(jax.dtypes.canonicalize_dtype(jnp.float64))


def as_float_array(x, dtype=None, like: Array | None = None) -> Array:
    """Convert `x` to a strongly typed floating JAX array, keeping its dtype if
    already floating. Non-floating input becomes `like.dtype` if given, else JAX's
    default float.
    """
    x = jnp.asarray(x, dtype=dtype)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(default_float_dtype() if like is None else like.dtype)
    elif x.weak_type:
        # Python scalars give weakly typed arrays; store a concrete dtype instead, so
        # that group parameters never change dtype (or jit cache entry) silently.
        x = x.astype(x.dtype)
    return x


def _threshold(coeffs: Sequence[float], dtype, limit: float) -> float:
    """Largest angle at which the first term left out of a truncated series,
    `coeffs[n] * theta**(2n)`, is below `eps` relative to the leading term; capped
    at `limit`, beyond which Horner's rule on the alternating series starts losing
    digits to cancellation itself."""
    eps = float(jnp.finfo(dtype).eps)
    n = len(coeffs) - 1
    ratio = eps * abs(coeffs[0]) / abs(coeffs[n])
    return min(ratio ** (1 / (2 * n)), limit)


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


def _bernoulli(n: int) -> list[Fraction]:
    b = [Fraction(1)]
    for m in range(1, n + 1):
        b.append(-sum(math.comb(m + 1, k) * b[k] for k in range(m)) / (m + 1))
    return b


# Taylor coefficients in powers of t = theta**2. Each series keeps _TERMS terms and
# carries one more coefficient, used only to choose the switching angle. They are
# generated exactly from the series of sin, cos and x cot(x).
_TERMS = 10
_K = range(_TERMS + 1)
_F = math.factorial
_BERN = _bernoulli(2 * _TERMS + 2)


def _coeffs(term) -> tuple[float, ...]:
    return tuple(float(term(k)) for k in _K)


_SINC = _coeffs(lambda k: Fraction((-1) ** k, _F(2 * k + 1)))
_A = _coeffs(lambda k: Fraction((-1) ** k, _F(2 * k + 2)))
_B = _coeffs(lambda k: Fraction((-1) ** k, _F(2 * k + 3)))
# 1 - x cot(x) = -sum_{n>=1} (-1)^n B_2n (2x)^2n / (2n)!, with x = theta / 2.
_C = _coeffs(lambda k: (-1) ** k * _BERN[2 * k + 2] / _F(2 * k + 2))
_SE3_A2 = _coeffs(lambda k: Fraction((-1) ** k, _F(2 * k + 4)))
_SE3_A3 = _coeffs(lambda k: Fraction((-1) ** k * (k + 1), _F(2 * k + 5)))
_COS_HALF = _coeffs(lambda k: Fraction((-1) ** k, _F(2 * k) * 4**k))
_SIN_HALF_OVER = _coeffs(
    lambda k: Fraction((-1) ** k, 2 ** (2 * k + 1) * _F(2 * k + 1))
)
_ATAN_OVER_X = _coeffs(lambda k: Fraction((-1) ** k, 2 * k + 1))


def _series_or_closed_form(
    t: Array, coeffs: Sequence[float], closed_form: Callable[[Array], Array]
) -> Array:
    # Below about 2 rad the series, evaluated by Horner's rule, is at least as
    # accurate as any of the closed forms, which cancel up to eps / theta**4.
    threshold = _threshold(coeffs, t.dtype, limit=2.0)
    return series_or_closed_form(t, threshold, coeffs[:-1], closed_form)


def sinc(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`sin(theta) / theta` as a function of `t = theta**2`."""
    return _series_or_closed_form(t, _SINC, lambda th: jnp.sin(th) / th)


def coef_a(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(1 - cos(theta)) / theta**2` as a function of `t = theta**2`."""
    # 2 sin^2(theta/2) avoids the cancellation in 1 - cos(theta).
    return _series_or_closed_form(
        t, _A, lambda th: 2.0 * jnp.square(jnp.sin(0.5 * th) / th)
    )


def coef_b(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(theta - sin(theta)) / theta**3` as a function of `t = theta**2`."""
    return _series_or_closed_form(t, _B, lambda th: (th - jnp.sin(th)) / th**3)


def coef_c(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(1 - (theta/2) cot(theta/2)) / theta**2` as a function of `t = theta**2`.

    This is the coefficient of `hat(w)**2` in the inverse SO(3) Jacobians. Written
    with `cot(theta/2)` it is regular at `theta = pi` (unlike the textbook form with
    `(1 + cos) / sin`, which is 0/0 there) and singular only at `theta = 2 pi`.
    """

    def closed(th):
        half = 0.5 * th
        return (1.0 - half * jnp.cos(half) / jnp.sin(half)) / jnp.square(th)

    return _series_or_closed_form(t, _C, closed)


def se3_a2(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(theta**2 + 2 cos(theta) - 2) / (2 theta**4)` as a function of `t`."""
    return _series_or_closed_form(
        t,
        _SE3_A2,
        lambda th: (jnp.square(th) + 2.0 * jnp.cos(th) - 2.0) / (2.0 * th**4),
    )


def se3_a3(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`(2 theta - 3 sin(theta) + theta cos(theta)) / (2 theta**5)` as a function
    of `t`."""
    return _series_or_closed_form(
        t,
        _SE3_A3,
        lambda th: (2.0 * th - 3.0 * jnp.sin(th) + th * jnp.cos(th)) / (2.0 * th**5),
    )


def cos_half(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`cos(theta / 2)` as a function of `t = theta**2`."""
    return _series_or_closed_form(t, _COS_HALF, lambda th: jnp.cos(0.5 * th))


def sin_half_over(t: Float[Array, "*batch"]) -> Float[Array, "*batch"]:
    """`sin(theta / 2) / theta` as a function of `t = theta**2`."""
    return _series_or_closed_form(t, _SIN_HALF_OVER, lambda th: jnp.sin(0.5 * th) / th)


def quat_log_scale(
    w: Float[Array, "*batch"], v_sq: Float[Array, "*batch"]
) -> Float[Array, "*batch"]:
    """Scale `s` such that `s * v` is the rotation vector of quaternion `(w, v)`.

    `s = 2 atan2(|v|, |w|) sign(w) / |v|`, the sign choosing the representative with
    `w >= 0` so that the angle lies in `[0, pi]`. The result depends only on the
    direction of `(w, v)`, not on its norm. Near the identity (`|v| << |w|`) it is
    evaluated as `(2 / w) atan(x) / x` with `x = |v| / |w|` by Taylor series, which
    avoids the square root of zero; near `pi` (`w -> 0`) `atan2` stays accurate and
    its derivative finite. (At exactly `pi` the logarithm is discontinuous: `w = 0`
    is sent to `+pi`.)
    """
    # atan(x)/x converges slowly (radius 1): this switches at x ~ 0.19 in float64 and
    # ~ 0.49 in float32.
    threshold = _threshold(_ATAN_OVER_X, w.dtype, limit=0.5)
    small = v_sq < threshold**2 * jnp.square(w)
    w_series = jnp.where(small, w, 1.0)
    x_sq = jnp.where(small, v_sq, 0.0) / jnp.square(w_series)
    series = 2.0 * _horner(_ATAN_OVER_X[:-1], x_sq) / w_series
    v_sq_closed = jnp.where(small, 1.0, v_sq)
    norm_v = jnp.sqrt(v_sq_closed)
    sign = jnp.where(w < 0, -1.0, 1.0).astype(w.dtype)
    closed = 2.0 * sign * jnp.arctan2(norm_v, jnp.abs(w)) / norm_v
    return jnp.where(small, series, closed)


def broadcast_batch(*arrays: Array) -> tuple[Array, ...]:
    """Broadcast the leading (batch) axes of arrays, keeping each last axis."""
    batch = jnp.broadcast_shapes(*(a.shape[:-1] for a in arrays))
    return tuple(jnp.broadcast_to(a, batch + a.shape[-1:]) for a in arrays)


def rotate_pairs(v: Float[Array, "*batch n"]) -> Float[Array, "*batch n"]:
    """Turn each consecutive pair `(p, q)` of the last axis by 90°: `(-q, p)`.

    With `v = (c, s, x, y)`, `c₁ v + s₁ rotate_pairs(v)` is the rotation of
    both the complex number `(c, s)` and the point `(x, y)` by `(c₁, s₁)`.
    """
    pairs = v.reshape(v.shape[:-1] + (-1, 2))[..., ::-1]
    return (pairs * signs([-1.0, 1.0], pairs)).reshape(v.shape)


def signs(values: Sequence[float], like: Array) -> Array:
    """Constants for the last axis of `like`, with its rank and dtype (so the
    product broadcasts without rank promotion)."""
    out = jnp.asarray(values, like.dtype)
    return out.reshape((1,) * (like.ndim - 1) + out.shape)


def matvec(m: Array, v: Array) -> Array:
    """Batched matrix-vector product (batch axes must already agree)."""
    return matmul(m, v[..., None])[..., 0]


def stack_matrix(rows: Sequence[Sequence[Array]]) -> Array:
    """Build a `(*batch, n, m)` matrix from nested lists of `(*batch,)` arrays."""
    return jnp.stack([jnp.stack(list(row), axis=-1) for row in rows], axis=-2)


def as_vectors(
    x, size: int, who: str, what: str = "tangent vectors", like: Array | None = None
) -> Array:
    """`as_float_array`, then check that the last axis has `size` entries.

    Without this check, `x[..., i]` past the end is clamped by JAX and a
    wrongly sized input gives a plausible but wrong answer.
    """
    x = as_float_array(x, like=like)
    if x.ndim < 1 or x.shape[-1] != size:
        raise ValueError(
            f"{who}: {what} must have shape (*batch, {size}), got {x.shape}"
        )
    return x


def as_matrices(x, size: int, who: str) -> Array:
    """`as_float_array`, then check that the last two axes are `(size, size)`."""
    x = as_float_array(x)
    if x.ndim < 2 or x.shape[-2:] != (size, size):
        raise ValueError(
            f"{who}: matrices must have shape (*batch, {size}, {size}), got {x.shape}"
        )
    return x


def unit_tolerance(dtype) -> float:
    """How far from 1 the norm of rotation parameters may be when checked."""
    return max(1e-3, 10 * float(jnp.finfo(dtype).eps))


def check_unit_norm(who: str, field: str, params, stop: int) -> None:
    """Raise if the rotation part `params[..., :stop]` is not finite and of unit
    norm (within `unit_tolerance`); traced values are not checked."""
    if isinstance(params, jax.core.Tracer):
        return
    arr = np.asarray(params[..., :stop], dtype=np.float64)
    if arr.size == 0:
        return
    norms = np.linalg.norm(arr, axis=-1)
    bad = ~np.isfinite(norms) | (np.abs(norms - 1.0) > unit_tolerance(params.dtype))
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        where = f" at batch index {idx}" if idx else ""
        raise ValueError(
            f"{who}: the rotation part of {field}{where} has norm "
            f"{norms[bad].flat[0]:.4g}"
            "; a rotation needs unit norm. Normalise the parameters, use "
            f"{who}(..., check=False).normalize(), or build from angles or matrices"
        )


def check_on_group(who: str, matrix: Array, rot: int, homogeneous: bool) -> Array:
    """Check that `matrix` (already shape-checked) is a rotation, or a rigid
    motion with bottom row `(0, ..., 0, 1)` if `homogeneous`.

    Concrete input raises `ValueError` naming the first bad batch element and
    what is wrong; traced input is checked with `eqx.error_if` (the returned
    matrix must be used).
    """
    tol = unit_tolerance(matrix.dtype)
    if not isinstance(matrix, jax.core.Tracer):
        m = np.asarray(matrix, dtype=np.float64)
        R = m[..., :rot, :rot]
        finite = np.all(np.isfinite(m), axis=(-2, -1))
        with np.errstate(invalid="ignore"):
            ortho = np.max(
                np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(rot)), axis=(-2, -1)
            )
            det = np.linalg.det(np.where(np.isfinite(R), R, 0.0))
        block = "rotation block" if homogeneous else "matrix"
        problems = [
            (~finite, "matrix", lambda i: "has non-finite entries"),
            (
                ortho > tol,
                block,
                lambda i: f"is not orthonormal (RᵀR differs from I by {ortho[i]:.3g})",
            ),
            (det < 0, block, lambda i: f"is a reflection (determinant {det[i]:.3g})"),
        ]
        if homogeneous:
            want = np.zeros(rot + 1)
            want[-1] = 1.0
            off = np.max(np.abs(m[..., rot, :] - want), axis=-1)
            problems.append(
                (
                    off > tol,
                    "matrix",
                    lambda i: (
                        f"has bottom row {np.round(m[i][rot], 6).tolist()}, "
                        f"not {want.tolist()}"
                    ),
                )
            )
        for bad, subject, text in problems:
            if np.any(bad):
                idx = tuple(int(i) for i in np.argwhere(bad)[0])
                where = f" at batch index {idx}" if idx else ""
                raise ValueError(
                    f"{who}.from_matrix: the {subject}{where} {text(idx)}; it is not "
                    f"in {who} (pass check=False to project onto the group instead)"
                )
        return matrix
    R = matrix[..., :rot, :rot]
    eye = jnp.broadcast_to(jnp.eye(rot, dtype=R.dtype), R.shape)
    err = jnp.max(jnp.abs(matmul(jnp.swapaxes(R, -1, -2), R) - eye))
    bad = ~(err <= tol) | jnp.any(jnp.linalg.det(R) < 0)
    if homogeneous:
        bottom = matrix[..., rot, :]
        want = jnp.broadcast_to(
            jnp.zeros(rot + 1, matrix.dtype).at[-1].set(1.0), bottom.shape
        )
        bad = bad | ~(jnp.max(jnp.abs(bottom - want)) <= tol)
    return eqx.error_if(
        matrix,
        bad,
        f"{who}.from_matrix: a matrix is not in the group (not orthonormal, a "
        "reflection, non-finite, or a bad bottom row); pass check=False to project",
    )
