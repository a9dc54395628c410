"""IMU factors between keyframes: GTSAM's `ImuFactor` and `CombinedImuFactor`.

A keyframe's navigation state is a pose `T = (R, p)` (an
[`eqsmooth.lie.SE3`][], body to navigation frame) and a velocity `v` in the
navigation frame (a plain `(3,)` array); the IMU bias is a `(6,)` array
`(b_acc, b_omega)`, GTSAM's `imuBias::ConstantBias` order. The factors
predict the state at `j` from the state at `i`, the bias and the
[`eqsmooth.factors.PreintegratedImuMeasurements`][] of the samples between
them, and compare the prediction with the state at `j` through the
logarithm of the extended pose group SE₂(3), the residual GTSAM 4.3 uses by
default (`ImuFactorErrorMode.Logmap`):

```
x      = preintegrated + H_acc (b_acc − b̂_acc) + H_ω (b_ω − b̂_ω)   (θ, Δp, Δv)
R̂_j    = R_i Exp(θ)
p̂_j    = p_i + v_i Δt + ½ g Δt² + R_i Δp
v̂_j    = v_i + g Δt + R_i Δv
r      = Log_SE₂(₃)((R_j, p_j, v_j)⁻¹ (R̂_j, p̂_j, v̂_j))
       = (ω, Jl(ω)⁻¹ R_jᵀ (p̂_j − p_j), Jl(ω)⁻¹ R_jᵀ (v̂_j − v_j)),  ω = Log(R_jᵀ R̂_j)
```

The residual is ordered `(rotation, position, velocity)`, like GTSAM's
`NavState` tangent, and is GTSAM's `evaluateError` sign included
(`state_j.logmap(predicted)`, "predicted relative to estimated"). The pose variables'
tangent is eqsmooth's SE(3) order `(v, ω)` (translation first, GTSAM's Pose3
is `(ω, v)`); both retract by `T Exp(δ)`, so a Jacobian column of ours is
GTSAM's column with the two 3-blocks of a pose swapped.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._precision import matmul as mm
from ..lie import SE3, SO3
from ._factor import AbstractFactor, shared_field
from ._imu_preintegration import ImuParams, PreintegratedImuMeasurements
from ._noise import AbstractNoiseModel, is_concrete, SqrtInformationNoise
from ._variables import Var


def navigation_error(
    pim: PreintegratedImuMeasurements,
    gravity: Float[Array, "3"],
    pose_i: SE3,
    velocity_i: Float[Array, "3"],
    pose_j: SE3,
    velocity_j: Float[Array, "3"],
    bias_i: Float[Array, "6"],
) -> Float[Array, "9"]:
    """The 9-D residual of one IMU factor row (see the module docs), in the
    order `(rotation, position, velocity)`.

    **Arguments:**

    - `pim`: ONE interval's [`eqsmooth.factors.PreintegratedImuMeasurements`][]
        (no batch axes).
    - `gravity`: the navigation-frame gravity, `(3,)`.
    - `pose_i`, `pose_j`: [`eqsmooth.lie.SE3`][] poses (body to navigation).
    - `velocity_i`, `velocity_j`: navigation-frame velocities, `(3,)`.
    - `bias_i`: the bias `(b_acc, b_omega)` at `i`, `(6,)`.

    **Returns:** the residual, `(9,)`.
    """
    pose_hat, v_hat = pim.predict(pose_i, velocity_i, bias_i, gravity)
    rot_j = pose_j.rotation()
    omega = (rot_j.inverse() @ pose_hat.rotation()).log()
    jl_inv = SO3.right_jacobian_inv(-omega)  # Jl(ω)⁻¹ = Jr(−ω)⁻¹
    r_jt = rot_j.inverse()
    p_hat = pose_hat.translation()
    return jnp.concatenate(
        [
            omega,
            mm(jl_inv, r_jt.apply(p_hat - pose_j.translation())),
            mm(jl_inv, r_jt.apply(v_hat - velocity_j)),
        ]
    )


def _check_pim(name: str, pim, n: int) -> None:
    if not isinstance(pim, PreintegratedImuMeasurements):
        raise TypeError(
            f"{name}.pim must be a PreintegratedImuMeasurements (from "
            f"eqsmooth.factors.preintegrate), got {type(pim).__name__}"
        )
    if pim.delta_t.shape != (n,):
        raise ValueError(
            f"{name}.pim has batch shape {pim.delta_t.shape} but the factor has {n} "
            f"rows: preintegrate one interval per row (accelerometer of shape "
            f"({n}, k, 3))"
        )


def _check_gravity(name: str, gravity) -> Array:
    if isinstance(gravity, ImuParams):
        gravity = gravity.gravity
    g = jnp.asarray(gravity)
    if g.shape != (3,):
        raise ValueError(f"{name}.gravity must have shape (3,), got {g.shape}")
    return g


def _check_states(name: str, pose_i, velocity_i, pose_j, velocity_j, *biases):
    for field, pose in (("pose_i", pose_i), ("pose_j", pose_j)):
        if not isinstance(pose, SE3):
            raise TypeError(
                f"{name}: the {field} variable must hold SE3 values, got "
                f"{type(pose).__name__}"
            )
    for field, v in (("velocity_i", velocity_i), ("velocity_j", velocity_j)):
        if jnp.shape(v) != (3,):
            raise ValueError(
                f"{name}: the {field} variable must hold (3,) velocities, got shape "
                f"{jnp.shape(v)}"
            )
    for field, b in zip(("bias_i", "bias_j"), biases):
        if jnp.shape(b) != (6,):
            raise ValueError(
                f"{name}: the {field} variable must hold (6,) biases (b_acc, "
                f"b_omega), got shape {jnp.shape(b)}"
            )


def _noise_from(name: str, covariance: Array, what: str) -> SqrtInformationNoise:
    if is_concrete(covariance):
        cov = np.asarray(covariance, dtype=np.float64)
        low = np.linalg.eigvalsh(cov).min(axis=-1)
        bad = np.flatnonzero(~(low > 0))
        if bad.size:
            raise ValueError(
                f"{name}: the {what} of rows {bad[:8].tolist()} is not positive "
                f"definite (smallest eigenvalue {low[bad[0]]:.3g}); give ImuParams "
                "positive accelerometer and gyroscope covariances"
                + (
                    " and positive bias_acc_covariance and bias_omega_covariance"
                    if "combined" in what
                    else ""
                )
                + ", and intervals with at least one sample"
            )
    return SqrtInformationNoise.from_covariance(covariance)


def _walk_covariance(name: str, pim, sigmas) -> Array:
    """The 15 x 15 covariance of `(navigation error, bias drift)` with the
    drift an independent random walk of per-row standard deviations
    `sigmas` (`(6,)` or `(n, 6)`)."""
    n = pim.delta_t.shape[0]
    s = jnp.asarray(sigmas)
    if s.shape not in ((6,), (n, 6)):
        raise ValueError(
            f"{name}.bias_walk_sigmas must have shape (6,) or ({n}, 6) (one row "
            f"of (b_acc, b_omega) sigmas per interval), got {s.shape}"
        )
    if is_concrete(s) and not np.all(np.asarray(s) > 0):
        raise ValueError(f"{name}.bias_walk_sigmas must be positive and finite")
    walk = jnp.broadcast_to(s * s, (n, 6))
    nav = pim.residual_covariance()
    out = jnp.zeros((n, 15, 15), nav.dtype).at[:, :9, :9].set(nav)
    return out.at[:, 9:, 9:].set(jax.vmap(jnp.diag)(walk.astype(nav.dtype)))


def _imu_fields(name: str, pim, rows: int, gravity, noise, covariance):
    """The `(pim, gravity, noise)` fields every IMU factor checks the same
    way; `covariance(pim) -> (covariance, what)` gives the default noise's."""
    _check_pim(name, pim, rows)
    g = _check_gravity(name, gravity)
    if noise is None:
        noise = _noise_from(name, *covariance(pim))
    return pim, g, noise


def _preintegrated(pim):
    return pim.residual_covariance(), "preintegrated covariance"


def _combined(pim):
    return pim.combined_residual_covariance(), "combined preintegrated covariance"


class ImuFactor(AbstractFactor):
    """Preintegrated IMU measurements between keyframes `i` and `j`: GTSAM's
    `ImuFactor(pose_i, vel_i, pose_j, vel_j, bias_i, pim)`.

    Five variables per row: the SE(3) poses and `(3,)` velocities at `i` and
    `j`, and the `(6,)` bias `(b_acc, b_omega)` at `i`. The residual (9-D,
    `(rotation, position, velocity)`) is
    [`eqsmooth.factors.navigation_error`][]. Its default noise is each row's
    [`eqsmooth.factors.PreintegratedImuMeasurements.residual_covariance`][],
    as in GTSAM; the bias is held constant over the interval, so pair it with
    a bias random walk (a [`eqsmooth.factors.BetweenFactor`][] between the
    bias variables, with zero measurement), or use
    [`eqsmooth.factors.CombinedImuFactor`][]. Jacobians come from the
    library's forward-mode linearisation.

    **Arguments:**

    - `pose_i`, `velocity_i`, `pose_j`, `velocity_j`, `bias_i`:
        [`eqsmooth.factors.Var`][]s with `n` rows each.
    - `pim`: a [`eqsmooth.factors.PreintegratedImuMeasurements`][] of batch
        shape `(n,)`, one interval per row.
    - `gravity`: the navigation-frame gravity `(3,)`, or the
        [`eqsmooth.factors.ImuParams`][] whose `gravity` to use; shared by
        every row (learnable).
    - `noise`: optional noise model on the 9-D residual; by default
        `SqrtInformationNoise.from_covariance(pim.residual_covariance())`.
    """

    variables: tuple[Var, ...]
    pim: PreintegratedImuMeasurements
    gravity: Float[Array, "3"] = shared_field()
    noise: AbstractNoiseModel

    def __init__(
        self,
        pose_i: Var,
        velocity_i: Var,
        pose_j: Var,
        velocity_j: Var,
        bias_i: Var,
        pim: PreintegratedImuMeasurements,
        gravity: Float[ArrayLike, "..."] | ImuParams,
        noise: AbstractNoiseModel | None = None,
    ):
        self.variables = (pose_i, velocity_i, pose_j, velocity_j, bias_i)
        self.pim, self.gravity, self.noise = _imu_fields(
            "ImuFactor", pim, len(pose_i), gravity, noise, _preintegrated
        )

    def residual(
        self,
        pose_i: PyTree,
        velocity_i: PyTree,
        pose_j: PyTree,
        velocity_j: PyTree,
        bias_i: PyTree,
    ) -> Float[Array, "9"]:
        # (States are checked by `_check_states`, which names the variable.)
        _check_states("ImuFactor", pose_i, velocity_i, pose_j, velocity_j, bias_i)
        return navigation_error(
            self.pim, self.gravity, pose_i, velocity_i, pose_j, velocity_j, bias_i
        )


class CombinedImuFactor(AbstractFactor):
    """IMU factor with the bias random walk built in: GTSAM's
    `CombinedImuFactor(pose_i, vel_i, pose_j, vel_j, bias_i, bias_j, pim)`.

    Six variables per row (those of [`eqsmooth.factors.ImuFactor`][] and the
    bias at `j`); the 15-D residual is the navigation error followed by
    `b_i − b_j`, and its default noise is each row's
    [`eqsmooth.factors.PreintegratedImuMeasurements.combined_residual_covariance`][],
    whose cross terms couple the bias drift with the preintegrated motion
    (so `ImuParams.bias_acc_covariance` and `bias_omega_covariance` must be
    positive definite).

    **Arguments:** as [`eqsmooth.factors.ImuFactor`][], with `bias_j` after
    `bias_i`; `noise` acts on the 15-D residual.
    """

    variables: tuple[Var, ...]
    pim: PreintegratedImuMeasurements
    gravity: Float[Array, "3"] = shared_field()
    noise: AbstractNoiseModel

    def __init__(
        self,
        pose_i: Var,
        velocity_i: Var,
        pose_j: Var,
        velocity_j: Var,
        bias_i: Var,
        bias_j: Var,
        pim: PreintegratedImuMeasurements,
        gravity: Float[ArrayLike, "..."] | ImuParams,
        noise: AbstractNoiseModel | None = None,
    ):
        self.variables = (pose_i, velocity_i, pose_j, velocity_j, bias_i, bias_j)
        self.pim, self.gravity, self.noise = _imu_fields(
            "CombinedImuFactor", pim, len(pose_i), gravity, noise, _combined
        )

    def residual(
        self,
        pose_i: PyTree,
        velocity_i: PyTree,
        pose_j: PyTree,
        velocity_j: PyTree,
        bias_i: PyTree,
        bias_j: PyTree,
    ) -> Float[Array, "15"]:
        _check_states(
            "CombinedImuFactor", pose_i, velocity_i, pose_j, velocity_j, bias_i, bias_j
        )
        nav = navigation_error(
            self.pim, self.gravity, pose_i, velocity_i, pose_j, velocity_j, bias_i
        )
        return jnp.concatenate([nav, bias_i - bias_j])


class ImuTransitionFactor(AbstractFactor):
    """The IMU factor and the bias drift between two keyframe states held as
    ONE variable each, `(pose, velocity, bias)`: the transition of
    [`eqsmooth.filters.fixed_lag_smoother`][] and the other chain smoothers,
    which want each time step's state in one group.

    The 15-D residual is that of [`eqsmooth.factors.CombinedImuFactor`][]:
    [`eqsmooth.factors.navigation_error`][] followed by `b_i − b_j`. With
    `bias_walk_sigmas` the drift is an independent random walk of those
    standard deviations (the cost is that of an
    [`eqsmooth.factors.ImuFactor`][] plus a [`eqsmooth.factors.BetweenFactor`][]
    on the biases, as [`eqsmooth.factors.imu_chain`][] builds); without, the
    noise is the combined preintegrated covariance (that of
    `CombinedImuFactor`, whose `ImuParams` bias densities must be positive).

    **Arguments:**

    - `state_i`, `state_j`: [`eqsmooth.factors.Var`][]s with `n` rows each,
        whose values are tuples `(SE3 pose, (3,) velocity, (6,) bias)`.
    - `pim`, `gravity`: as for [`eqsmooth.factors.ImuFactor`][].
    - `bias_walk_sigmas`: the drift's standard deviations over each interval,
        `(6,)` or `(n, 6)` in the order `(b_acc, b_omega)`; `None` for the
        combined covariance.
    - `noise`: optional noise model on the 15-D residual (replaces both).
    """

    variables: tuple[Var, ...]
    pim: PreintegratedImuMeasurements
    gravity: Float[Array, "3"] = shared_field()
    noise: AbstractNoiseModel

    def __init__(
        self,
        state_i: Var,
        state_j: Var,
        pim: PreintegratedImuMeasurements,
        gravity: Float[ArrayLike, "..."] | ImuParams,
        bias_walk_sigmas: Float[ArrayLike, "..."] | None = None,
        noise: AbstractNoiseModel | None = None,
    ):
        name = "ImuTransitionFactor"
        self.variables = (state_i, state_j)

        def covariance(pim):
            if bias_walk_sigmas is None:
                return _combined(pim)
            cov = _walk_covariance(name, pim, bias_walk_sigmas)
            return cov, "preintegrated covariance with the bias walk"

        self.pim, self.gravity, self.noise = _imu_fields(
            name, pim, len(state_i), gravity, noise, covariance
        )

    def residual(self, state_i: PyTree, state_j: PyTree) -> Float[Array, "15"]:
        for field, x in (("state_i", state_i), ("state_j", state_j)):
            if not (isinstance(x, tuple) and len(x) == 3):
                raise TypeError(
                    f"ImuTransitionFactor: the {field} variable must hold "
                    f"(pose, velocity, bias) tuples, got {type(x).__name__}"
                )
        (pose_i, v_i, b_i), (pose_j, v_j, b_j) = state_i, state_j
        _check_states("ImuTransitionFactor", pose_i, v_i, pose_j, v_j, b_i, b_j)
        nav = navigation_error(self.pim, self.gravity, pose_i, v_i, pose_j, v_j, b_i)
        return jnp.concatenate([nav, b_i - b_j])
