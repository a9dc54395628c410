"""IMU noise parameters and on-manifold preintegration of IMU samples.

Preintegration summarises the accelerometer and gyroscope samples between two
keyframes `i` and `j` as one relative motion, independent of the states at
`i` (Lupton and Sukkarieh, IEEE T-RO 2012; Forster, Carlone, Dellaert and
Scaramuzza, "On-Manifold Preintegration for Real-Time Visual-Inertial
Odometry", IEEE T-RO 2017). The summary is kept in tangent coordinates: a
9-vector `(θ, Δp, Δv)` whose rotation part is a rotation vector,
`ΔR = Exp(θ)`. This is the parameterisation of GTSAM's
`TangentPreintegration`, the one its Python wheel's
`PreintegratedImuMeasurements` uses; in it the bias-correction Jacobians are
exact derivatives of the recursion and the first-order bias correction of
all nine coordinates is linear.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._precision import matmul as mm
from ..lie import SE3, SO3
from ..lie._so3 import skew
from ..lie._utils import coef_c
from ._noise import is_concrete


# ------------------------------------------------------------------ parameters


def _as_vector3(name: str, x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jax.dtypes.canonicalize_dtype(jnp.float64))
    if x.shape != (3,):
        raise ValueError(f"ImuParams.{name} must have shape (3,), got {x.shape}")
    return x


def _sigmas_to_covariance(name: str, sigma: ArrayLike) -> Array:
    s = jnp.asarray(sigma)
    if not jnp.issubdtype(s.dtype, jnp.floating):
        s = s.astype(jax.dtypes.canonicalize_dtype(jnp.float64))
    if s.shape not in ((), (3,)):
        raise ValueError(
            f"ImuParams.from_sigmas: {name} must be a scalar or have shape (3,), "
            f"got {s.shape}"
        )
    if is_concrete(s) and np.any(np.asarray(s) < 0):
        raise ValueError(
            f"ImuParams.from_sigmas: {name} must be non-negative, got {np.asarray(s)}"
        )
    return jnp.diag(jnp.broadcast_to(s * s, (3,)))


_COVARIANCES = (
    "accelerometer_covariance",
    "gyroscope_covariance",
    "integration_covariance",
    "bias_acc_covariance",
    "bias_omega_covariance",
)


class ImuParams(eqx.Module):
    """Noise densities and gravity of an IMU: GTSAM's `PreintegrationParams`
    and `PreintegrationCombinedParams` in one Module.

    Every field is an array leaf, so each may be learned (through
    [`eqsmooth.factors.ImuParams.from_sigmas`][] a learned standard deviation
    stays a valid covariance). The covariances are continuous-time densities,
    as in GTSAM: a sample over `dt` contributes `Σ_acc / dt` and `Σ_gyro / dt`
    (white noise) and `Σ_int · dt`, `Σ_bias · dt` (random walks).

    Not modelled: the Earth's rotation (GTSAM's `omegaCoriolis`) and an IMU
    mounted away from the body frame (`body_P_sensor`).

    **Arguments:**

    - `gravity`: the gravity vector in the navigation frame, shape `(3,)`
        (`(0, 0, -9.81)` for a z-up frame: see `make_u`, `make_d`).
    - `accelerometer_covariance`: `(3, 3)`, units `(m/s²)²/Hz`.
    - `gyroscope_covariance`: `(3, 3)`, units `(rad/s)²/Hz`.
    - `integration_covariance`: `(3, 3)`, the error of integrating position
        from velocity (default zero).
    - `bias_acc_covariance`, `bias_omega_covariance`: `(3, 3)` random-walk
        densities of the accelerometer and gyroscope biases, used only by
        [`eqsmooth.factors.CombinedImuFactor`][] (default zero).
    """

    gravity: Float[Array, "3"]
    accelerometer_covariance: Float[Array, "3 3"]
    gyroscope_covariance: Float[Array, "3 3"]
    integration_covariance: Float[Array, "3 3"]
    bias_acc_covariance: Float[Array, "3 3"]
    bias_omega_covariance: Float[Array, "3 3"]

    def __init__(
        self,
        gravity: Float[ArrayLike, "..."],
        accelerometer_covariance: Float[ArrayLike, "..."],
        gyroscope_covariance: Float[ArrayLike, "..."],
        integration_covariance: Float[ArrayLike, "..."] | None = None,
        bias_acc_covariance: Float[ArrayLike, "..."] | None = None,
        bias_omega_covariance: Float[ArrayLike, "..."] | None = None,
    ):
        self.gravity = _as_vector3("gravity", gravity)
        dtype = self.gravity.dtype
        given = (
            accelerometer_covariance,
            gyroscope_covariance,
            integration_covariance,
            bias_acc_covariance,
            bias_omega_covariance,
        )
        for name, value in zip(_COVARIANCES, given):
            cov = jnp.zeros((3, 3), dtype) if value is None else jnp.asarray(value)
            if not jnp.issubdtype(cov.dtype, jnp.floating):
                cov = cov.astype(dtype)
            if cov.shape != (3, 3):
                raise ValueError(
                    f"ImuParams.{name} must have shape (3, 3), got {cov.shape}"
                )
            if cov.dtype != dtype:
                raise ValueError(
                    f"ImuParams.{name} has dtype {cov.dtype} but gravity has "
                    f"{dtype}; give every field one dtype"
                )
            setattr(self, name, cov)

    def __check_init__(self):
        for name in ("gravity",) + _COVARIANCES:
            value = getattr(self, name)
            if not is_concrete(value):
                continue
            arr = np.asarray(value, dtype=np.float64)
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"ImuParams.{name} must be finite, got {arr}")
            if name == "gravity":
                continue
            if np.max(np.abs(arr - arr.T)) > 1e-12 * max(np.max(np.abs(arr)), 1e-300):
                raise ValueError(f"ImuParams.{name} must be symmetric, got {arr}")
            low = np.linalg.eigvalsh(arr).min()
            if low < -1e-12 * max(np.max(np.abs(arr)), 1e-300):
                raise ValueError(
                    f"ImuParams.{name} must be positive semi-definite (smallest "
                    f"eigenvalue {low:.3g})"
                )

    @classmethod
    def from_sigmas(
        cls,
        gravity: Float[ArrayLike, "..."],
        accelerometer_sigma: Float[ArrayLike, "..."],
        gyroscope_sigma: Float[ArrayLike, "..."],
        integration_sigma: Float[ArrayLike, "..."] = 0.0,
        bias_acc_sigma: Float[ArrayLike, "..."] = 0.0,
        bias_omega_sigma: Float[ArrayLike, "..."] = 0.0,
    ) -> "ImuParams":
        """Diagonal densities from standard deviations (scalars or per axis,
        shape `(3,)`): `Σ = diag(σ²)`. Differentiable in every σ, which is
        the natural leaf to learn.

        **Arguments:** as the class's, with `*_sigma` for `*_covariance`
        (units `m/s²/√Hz`, `rad/s/√Hz`, ...).

        **Returns:** an `ImuParams`.
        """
        g = _as_vector3("gravity", gravity)
        covs = [
            _sigmas_to_covariance(name, s).astype(g.dtype)
            for name, s in (
                ("accelerometer_sigma", accelerometer_sigma),
                ("gyroscope_sigma", gyroscope_sigma),
                ("integration_sigma", integration_sigma),
                ("bias_acc_sigma", bias_acc_sigma),
                ("bias_omega_sigma", bias_omega_sigma),
            )
        ]
        return cls(g, *covs)

    @classmethod
    def make_u(cls, g: float = 9.81, **sigmas) -> "ImuParams":
        """Parameters for a z-up navigation frame (ENU): gravity `(0, 0, -g)`;
        the keyword arguments are those of `from_sigmas` (GTSAM's
        `PreintegrationParams.MakeSharedU`, without its identity defaults)."""
        return cls.from_sigmas(jnp.array([0.0, 0.0, -g]), **sigmas)

    @classmethod
    def make_d(cls, g: float = 9.81, **sigmas) -> "ImuParams":
        """Parameters for a z-down navigation frame (NED): gravity `(0, 0, g)`;
        see `make_u`."""
        return cls.from_sigmas(jnp.array([0.0, 0.0, g]), **sigmas)


# ---------------------------------------------------------------- preintegration


class PreintegratedImuMeasurements(eqx.Module):
    """The IMU samples between keyframes, summarised (any batch shape).

    Made by [`eqsmooth.factors.preintegrate`][]; the counterpart of GTSAM's
    `PreintegratedImuMeasurements` and `PreintegratedCombinedMeasurements`
    (both summaries: the combined covariance is propagated alongside).
    With a leading axis of length `n` it is the data of `n` IMU factor rows.

    **Fields** (`*batch` is the batch shape, e.g. `(n,)`):

    - `delta_t`: the integrated time `Δt_ij`, shape `(*batch,)`.
    - `preintegrated`: `(θ, Δp, Δv)`, shape `(*batch, 9)`: the rotation vector
        of `ΔR_ij`, and the position and velocity increments in the frame of
        keyframe `i`, all at the bias `bias_hat`, without gravity.
    - `H_bias_acc`, `H_bias_omega`: `∂ preintegrated / ∂ bias`, `(*batch, 9, 3)`
        each (GTSAM's `preintegrated_H_biasAcc`, `preintegrated_H_biasOmega`).
    - `covariance`: the covariance of `preintegrated`, `(*batch, 9, 9)`, in
        the order `(θ, Δp, Δv)` (GTSAM's `preintMeasCov` of
        `PreintegratedImuMeasurements`).
    - `combined_covariance`: `(*batch, 15, 15)`, the joint covariance of
        `preintegrated` and the bias random walk `(b_acc, b_omega)` over the
        interval (GTSAM's `preintMeasCov` of `PreintegratedCombinedMeasurements`).
    - `bias_hat`: the bias `(b_acc, b_omega)` the samples were corrected with,
        `(*batch, 6)`.
    """

    delta_t: Float[Array, "*batch"]
    preintegrated: Float[Array, "*batch 9"]
    H_bias_acc: Float[Array, "*batch 9 3"]
    H_bias_omega: Float[Array, "*batch 9 3"]
    covariance: Float[Array, "*batch 9 9"]
    combined_covariance: Float[Array, "*batch 15 15"]
    bias_hat: Float[Array, "*batch 6"]

    def delta_R(self) -> SO3:
        """`ΔR_ij = Exp(θ)` (GTSAM's `deltaRij`)."""
        return SO3.exp(self.preintegrated[..., :3])

    def delta_p(self) -> Float[Array, "*batch 3"]:
        """`Δp_ij` (GTSAM's `deltaPij`)."""
        return self.preintegrated[..., 3:6]

    def delta_v(self) -> Float[Array, "*batch 3"]:
        """`Δv_ij` (GTSAM's `deltaVij`)."""
        return self.preintegrated[..., 6:9]

    def bias_corrected(
        self, bias: Float[Array, "*#batch 6"]
    ) -> Float[Array, "*batch 9"]:
        """`preintegrated` corrected to first order for another bias
        `(b_acc, b_omega)`: `x + H_acc (b_acc − b̂_acc) + H_ω (b_ω − b̂_ω)`."""
        d = bias - self.bias_hat
        return (
            self.preintegrated
            + mm(self.H_bias_acc, d[..., :3, None])[..., 0]
            + mm(self.H_bias_omega, d[..., 3:, None])[..., 0]
        )

    def predict(
        self,
        pose_i: SE3,
        velocity_i: Float[Array, "*batch 3"],
        bias_i: Float[Array, "*batch 6"],
        gravity: Float[Array, "3"],
    ) -> tuple[SE3, Float[Array, "*batch 3"]]:
        """The state at `j` predicted from the state at `i` and the bias
        (GTSAM's `predict(NavState(pose_i, velocity_i), bias_i)`):
        `R_j = R_i Exp(θ)`, `p_j = p_i + v_i Δt + ½ g Δt² + R_i Δp`,
        `v_j = v_i + g Δt + R_i Δv`, with `(θ, Δp, Δv)` corrected for `bias_i`.
        Useful to initialise the states of a new keyframe.

        **Arguments:**

        - `pose_i`: an [`eqsmooth.lie.SE3`][] (body to navigation) of the
            batch shape of `self`.
        - `velocity_i`: navigation-frame velocities, `(*batch, 3)`.
        - `bias_i`: `(b_acc, b_omega)`, `(*batch, 6)`.
        - `gravity`: the navigation-frame gravity, `(3,)`.

        **Returns:** `(pose_j, velocity_j)`.
        """
        x = self.bias_corrected(bias_i)
        dt = self.delta_t[..., None]
        g = jnp.broadcast_to(gravity, x[..., :3].shape)
        rot_i = pose_i.rotation()
        p = pose_i.translation() + velocity_i * dt + 0.5 * g * dt * dt
        p = p + rot_i.apply(x[..., 3:6])
        v = velocity_i + g * dt + rot_i.apply(x[..., 6:9])
        rot_j = rot_i @ SO3.exp(x[..., :3])
        return SE3.from_rotation_and_translation(rot_j, p), v

    def _chart_jacobian(self) -> Float[Array, "*batch 9 9"]:
        # From additive (θ, Δp, Δv) perturbations to the NavState chart of the
        # factor's residual: Jr(θ) for the rotation, ΔRᵀ for the increments.
        theta = self.preintegrated[..., :3]
        rt = jnp.swapaxes(SO3.exp(theta).as_matrix(), -1, -2)
        jr = SO3.right_jacobian(theta)
        zero = jnp.zeros_like(rt)
        return jnp.concatenate(
            [
                jnp.concatenate([jr, zero, zero], axis=-1),
                jnp.concatenate([zero, rt, zero], axis=-1),
                jnp.concatenate([zero, zero, rt], axis=-1),
            ],
            axis=-2,
        )

    def residual_covariance(self) -> Float[Array, "*batch 9 9"]:
        """The covariance of [`eqsmooth.factors.ImuFactor`][]'s residual:
        `covariance` carried into the residual's chart, `J Σ Jᵀ` with
        `J = diag(Jr(θ), ΔRᵀ, ΔRᵀ)` (GTSAM's `residualCovariance`)."""
        j = self._chart_jacobian()
        return _symmetric(mm(mm(j, self.covariance), jnp.swapaxes(j, -1, -2)))

    def combined_residual_covariance(self) -> Float[Array, "*batch 15 15"]:
        """The covariance of [`eqsmooth.factors.CombinedImuFactor`][]'s 15-D
        residual: `combined_covariance` carried by `diag(J, −I₆)` (the bias
        residual is `b_i − b_j`)."""
        j9 = self._chart_jacobian()
        batch = j9.shape[:-2]
        j = jnp.zeros((*batch, 15, 15), j9.dtype)
        j = j.at[..., :9, :9].set(j9)
        j = j.at[..., 9:, 9:].set(-jnp.eye(6, dtype=j9.dtype))
        c = mm(mm(j, self.combined_covariance), jnp.swapaxes(j, -1, -2))
        return _symmetric(c)


def _symmetric(c: Array) -> Array:
    return 0.5 * (c + jnp.swapaxes(c, -1, -2))


def _step(x, acc, omega, dt):
    """One sample of GTSAM's tangent-space recursion (bias already removed):
    the new `(θ, Δp, Δv)` and its Jacobians `A = ∂/∂x` (as its three nonzero
    off-identity blocks), `B = ∂/∂acc`, `C = ∂/∂ω`."""
    theta, pos, vel = x[:3], x[3:6], x[6:]
    r = SO3.exp(theta).as_matrix()
    u = omega * dt
    # θ' = θ + Jr⁻¹(θ) u, integrating dθ/dt = Jr⁻¹(θ) ω, with
    # Jr⁻¹(θ) = I + ½[θ]× + c(|θ|²)[θ]×², so (differentiating θ×(θ×u) =
    # θ(θ·u) − u|θ|²) its derivative in θ is
    # −½[u]× + c ((θ·u) I + θuᵀ − 2uθᵀ) + 2c' (θ×(θ×u)) θᵀ.
    t = jnp.sum(theta * theta)
    c, dc = jax.jvp(coef_c, (t,), (jnp.ones_like(t),))
    sk_theta = skew(theta)
    txu = mm(sk_theta, u)
    ttu = mm(sk_theta, txu)
    jr_inv = jnp.eye(3, dtype=x.dtype) + 0.5 * sk_theta + c * mm(sk_theta, sk_theta)
    tu = jnp.sum(theta * u)
    inv_h = (
        -0.5 * skew(u)
        + c
        * (
            tu * jnp.eye(3, dtype=x.dtype)
            + jnp.outer(theta, u)
            - 2.0 * jnp.outer(u, theta)
        )
        + 2.0 * dc * jnp.outer(ttu, theta)
    )
    a_nav = mm(r, acc)
    dt22 = 0.5 * dt * dt
    new = jnp.concatenate(
        [
            theta + u + 0.5 * txu + c * ttu,
            pos + vel * dt + a_nav * dt22,
            vel + a_nav * dt,
        ]
    )
    # ∂(Exp(θ) a)/∂θ = −R [a]× Jr(θ).
    a_nav_h_theta = -mm(mm(r, skew(acc)), SO3.right_jacobian(theta))
    eye = jnp.eye(3, dtype=x.dtype)
    zero = jnp.zeros((3, 3), x.dtype)
    big_a = jnp.block(
        [
            [eye + inv_h, zero, zero],
            [a_nav_h_theta * dt22, eye, eye * dt],
            [a_nav_h_theta * dt, zero, eye],
        ]
    )
    big_b = jnp.concatenate([zero, r * dt22, r * dt], axis=0)
    big_c = jnp.concatenate([jr_inv * dt, zero, zero], axis=0)
    return new, big_a, big_b, big_c


def _one_interval(params, acc, gyro, dt, mask, bias_hat):
    dtype = acc.dtype
    zero3 = jnp.zeros((3, 3), dtype)
    # The integration noise enters the position block only.
    select_pos = jnp.concatenate([zero3, jnp.eye(3, dtype=dtype), zero3], axis=0)

    def body(carry, sample):
        x, h_bias, cov, cov15, total = carry
        a_m, w_m, h, keep = sample
        # A skipped (padding) sample integrates nothing. Its data are
        # replaced (dt by 1, the samples by 0) so that the branch thrown away
        # stays finite: a NaN there would still make gradients NaN (0 · NaN).
        h_safe = jnp.where(keep, h, 1.0)
        a_m = jnp.where(keep, a_m, 0.0)
        w_m = jnp.where(keep, w_m, 0.0)
        new, big_a, big_b, big_c = _step(
            x, a_m - bias_hat[:3], w_m - bias_hat[3:], h_safe
        )
        # G = [B C] = ∂x'/∂(acc, ω); the bias enters with a minus sign
        # (acc = a_m − b_acc, ω = w_m − b_ω): H' = A H − G.
        g = jnp.concatenate([big_b, big_c], axis=1)
        new_h_bias = mm(big_a, h_bias) - g
        white = jax.scipy.linalg.block_diag(
            params.accelerometer_covariance / h_safe,
            params.gyroscope_covariance / h_safe,
        )
        noise9 = mm(mm(g, white), g.T) + mm(
            mm(select_pos, params.integration_covariance * h_safe), select_pos.T
        )
        new_cov = mm(mm(big_a, cov), big_a.T) + noise9
        # Combined: the bias random walk is a state too, F = [[A, G], [0, I]].
        p11, p12, p22 = cov15[:9, :9], cov15[:9, 9:], cov15[9:, 9:]
        q12 = mm(big_a, p12) + mm(g, p22)
        q11 = mm(mm(big_a, p11), big_a.T) + mm(mm(g, p12.T), big_a.T)
        q11 = q11 + mm(q12, g.T) + noise9
        walk = jax.scipy.linalg.block_diag(
            params.bias_acc_covariance * h_safe, params.bias_omega_covariance * h_safe
        )
        new_cov15 = jnp.block([[q11, q12], [q12.T, p22 + walk]])
        pick = lambda a, b: jnp.where(keep, a, b)
        out = (
            pick(new, x),
            pick(new_h_bias, h_bias),
            pick(new_cov, cov),
            pick(new_cov15, cov15),
            total + jnp.where(keep, h, 0.0),
        )
        return out, None

    init = (
        jnp.zeros(9, dtype),
        jnp.zeros((9, 6), dtype),
        jnp.zeros((9, 9), dtype),
        jnp.zeros((15, 15), dtype),
        jnp.zeros((), dtype),
    )
    (x, h_bias, cov, cov15, total), _ = jax.lax.scan(body, init, (acc, gyro, dt, mask))
    return PreintegratedImuMeasurements(
        delta_t=total,
        preintegrated=x,
        H_bias_acc=h_bias[:, :3],
        H_bias_omega=h_bias[:, 3:],
        covariance=cov,
        combined_covariance=cov15,
        bias_hat=bias_hat,
    )


def preintegrate(
    params: ImuParams,
    accelerometer: Float[ArrayLike, "..."],
    gyroscope: Float[ArrayLike, "..."],
    dt: Float[ArrayLike, "..."],
    bias_hat: Float[ArrayLike, "..."] | None = None,
    mask: Bool[ArrayLike, "..."] | None = None,
) -> PreintegratedImuMeasurements:
    """Preintegrate IMU samples between keyframes (a `lax.scan` over samples,
    vectorised over any leading batch axes, e.g. one per keyframe interval).

    Sample `k` is the specific force `accelerometer[k]` and angular rate
    `gyroscope[k]` measured in the body frame, held for `dt[k]` seconds
    (GTSAM's `integrateMeasurement(acc, omega, dt)` called once per sample, in
    order). Intervals stacked along a batch axis have the same number of
    samples `k`; intervals with fewer samples are padded and the padding is
    switched off by `mask` (`False` = skip the sample).

    **Arguments:**

    - `params`: an [`eqsmooth.factors.ImuParams`][].
    - `accelerometer`, `gyroscope`: `(*batch, k, 3)` measured samples.
    - `dt`: the sample durations, broadcastable to `(*batch, k)`; every
        sample that is not masked out must have `dt > 0`.
    - `bias_hat`: the bias estimate `(b_acc, b_omega)` to correct the samples
        with, broadcastable to `(*batch, 6)`; zero if not given.
    - `mask`: optional booleans, broadcastable to `(*batch, k)`.

    **Returns:** a [`eqsmooth.factors.PreintegratedImuMeasurements`][] of batch
    shape `*batch`.
    """
    return _preintegrate_checked(params, accelerometer, gyroscope, dt, bias_hat, mask)


def _float_like(x, dtype):
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        return x.astype(dtype)
    return x


def _preintegrate_checked(params, accelerometer, gyroscope, dt, bias_hat, mask):
    if not isinstance(params, ImuParams):
        raise TypeError(
            f"preintegrate: params must be an ImuParams, got {type(params).__name__}"
        )
    dtype = params.gravity.dtype
    acc = _float_like(accelerometer, dtype)
    gyro = _float_like(gyroscope, dtype)
    for name, x in (("accelerometer", acc), ("gyroscope", gyro)):
        if x.ndim < 2 or x.shape[-1] != 3:
            raise ValueError(
                f"preintegrate: {name} must have shape (*batch, k, 3) (k samples of "
                f"a 3-vector), got {x.shape}"
            )
        if x.dtype != dtype:
            raise ValueError(
                f"preintegrate: {name} has dtype {x.dtype} but params has {dtype}"
            )
    if acc.shape != gyro.shape:
        raise ValueError(
            f"preintegrate: accelerometer has shape {acc.shape} but gyroscope has "
            f"{gyro.shape}; give both one sample per row"
        )
    if acc.shape[-2] == 0:
        raise ValueError("preintegrate: no samples (k = 0)")
    lead = acc.shape[:-1]  # (*batch, k)
    dt = _float_like(dt, dtype)
    try:
        dt = jnp.broadcast_to(dt, lead)
    except ValueError:
        raise ValueError(
            f"preintegrate: dt of shape {dt.shape} does not broadcast to the samples' "
            f"(*batch, k) = {lead}"
        ) from None
    if mask is None:
        mask = jnp.ones(lead, bool)
    else:
        mask = jnp.asarray(mask)
        if mask.dtype != bool:
            raise ValueError(f"preintegrate: mask must be boolean, got {mask.dtype}")
        try:
            mask = jnp.broadcast_to(mask, lead)
        except ValueError:
            raise ValueError(
                f"preintegrate: mask of shape {mask.shape} does not broadcast to the "
                f"samples' (*batch, k) = {lead}"
            ) from None
    batch = lead[:-1]
    if bias_hat is None:
        bias = jnp.zeros((*batch, 6), dtype)
    else:
        bias = _float_like(bias_hat, dtype)
        if bias.shape[-1:] != (6,):
            raise ValueError(
                "preintegrate: bias_hat must have shape (*batch, 6), (b_acc, "
                f"b_omega), got {bias.shape}"
            )
        try:
            bias = jnp.broadcast_to(bias, (*batch, 6))
        except ValueError:
            raise ValueError(
                f"preintegrate: bias_hat of shape {bias.shape} does not broadcast to "
                f"(*batch, 6) = {(*batch, 6)}"
            ) from None
    ok = jnp.where(mask, (dt > 0) & jnp.isfinite(dt), True)
    if is_concrete(ok) and is_concrete(mask):
        bad = np.argwhere(~np.asarray(ok))
        if bad.size:
            where = tuple(int(i) for i in bad[0])
            raise ValueError(
                f"preintegrate: dt must be positive and finite for every sample that "
                f"is not masked out; dt{list(where)} = {np.asarray(dt)[where]} "
                f"({bad.shape[0]} bad samples)"
            )
    for name, x in (("accelerometer", acc), ("gyroscope", gyro)):
        if is_concrete(x) and is_concrete(mask):
            bad = np.argwhere(
                np.asarray(mask) & ~np.all(np.isfinite(np.asarray(x)), axis=-1)
            )
            if bad.size:
                where = [int(i) for i in bad[0]]
                raise ValueError(
                    f"preintegrate: {name}{where} = {np.asarray(x)[tuple(where)]} is "
                    f"not finite ({bad.shape[0]} such samples); mask out missing "
                    "samples instead"
                )
    return _preintegrate_jit(params, acc, gyro, dt, bias, mask)


@eqx.filter_jit
def _preintegrate_jit(params, acc, gyro, dt, bias, mask):
    ok = jnp.all(jnp.where(mask, (dt > 0) & jnp.isfinite(dt), True))
    dt = eqx.error_if(
        dt,
        ~ok,
        "preintegrate: dt must be positive and finite for every sample that is not "
        "masked out (checked under jit)",
    )
    finite = jnp.all(jnp.isfinite(acc) & jnp.isfinite(gyro), axis=-1)
    acc = eqx.error_if(
        acc,
        ~jnp.all(jnp.where(mask, finite, True)),
        "preintegrate: a sample that is not masked out is not finite (checked under "
        "jit); mask out missing samples instead",
    )
    batch = acc.shape[:-2]
    k = acc.shape[-2]
    flat = lambda x, tail: x.reshape((-1, *tail))
    fn = jax.vmap(_one_interval, in_axes=(None, 0, 0, 0, 0, 0))
    out = fn(
        params,
        flat(acc, (k, 3)),
        flat(gyro, (k, 3)),
        flat(dt, (k,)),
        flat(mask, (k,)),
        flat(bias, (6,)),
    )
    return jax.tree_util.tree_map(
        lambda leaf: leaf.reshape(*batch, *leaf.shape[1:]), out
    )
