"""A planar vehicle: SE(2) pose plus forward and yaw velocity.

The state and factors of the visual-odometry task of Yi et al. (IROS 2021,
Sec. V-B, after Kloss et al.): `x_t = (T_t ∈ SE(2), v_t, ω_t)`, tangent
dimension 5, with a constant-velocity unicycle motion model and a
measurement of the velocities (for example from a learned virtual sensor).
"""

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._precision import matmul as mm
from ..lie import SE2, SO2
from ..manifold import local
from ._factor import AbstractAnalyticFactor, AbstractFactor
from ._noise import AbstractNoiseModel
from ._variables import Var


class VehicleState(eqx.Module):
    """A planar vehicle state: pose `T ∈ SE(2)` and velocities `(v, ω)`.

    A state pytree (tangent dimension 5, in the order `(δx, δy, δθ)` of the
    pose, then `(δv, δω)`); with leading batch axes it is a trajectory or a
    stack of states, and it works with [`eqsmooth.manifold.retract`][],
    [`eqsmooth.manifold.local`][] and every solver.

    **Fields:**

    - `pose`: an [`eqsmooth.lie.SE2`][] (vehicle frame: x forward, y left).
    - `velocity`: `(v, ω)`, forward speed and yaw rate, shape `(*batch, 2)`.
    """

    pose: SE2
    velocity: Float[Array, "*batch 2"]

    def __init__(self, pose: SE2, velocity: Float[ArrayLike, "*batch 2"]):
        self.pose = pose
        self.velocity = jnp.asarray(velocity, dtype=pose.unit_complex_xy.dtype)

    def __check_init__(self):
        if self.velocity.shape[-1:] != (2,):
            raise ValueError(
                f"VehicleState.velocity must have shape (*batch, 2), got "
                f"{self.velocity.shape}"
            )
        if self.velocity.shape[:-1] != self.pose.unit_complex_xy.shape[:-1]:
            raise ValueError(
                f"VehicleState: pose has batch shape "
                f"{self.pose.unit_complex_xy.shape[:-1]} but velocity has "
                f"{self.velocity.shape[:-1]}"
            )

    @classmethod
    def from_poses(cls, poses: SE2, dt: float = 1.0) -> "VehicleState":
        """A trajectory whose velocities are read off consecutive poses.

        `v_t` and `ω_t` are the forward translation and the rotation of
        `T_t⁻¹ T_{t+1}`, divided by `dt`, so [`eqsmooth.factors.vehicle_motion`][]
        reproduces every pose whose motion has no sideways component. The
        last state repeats the previous velocities.

        **Arguments:**

        - `poses`: an [`eqsmooth.lie.SE2`][] of batch shape `(T,)`, `T ≥ 2`.
        - `dt`: the time between poses.

        **Returns:** a `VehicleState` of batch shape `(T,)`.
        """
        rel = poses[:-1].inverse() @ poses[1:]
        c, s, x = (rel.unit_complex_xy[..., i] for i in range(3))
        vel = jnp.stack([x, jnp.arctan2(s, c)], axis=-1) / dt
        vel = jnp.concatenate([vel, vel[-1:]], axis=0)
        return cls(poses, vel)

    def __getitem__(self, index) -> "VehicleState":
        return VehicleState(self.pose[index], self.velocity[index])


def vehicle_motion(state: VehicleState, dt: float | Float[Array, ""] = 1.0):
    """The noise-free next state: `T ∘ (rotate by ω dt, translate [v dt, 0])`.

    The pose moves `v dt` along its heading and turns by `ω dt`; the
    velocities carry over.

    **Arguments:**

    - `state`: a [`eqsmooth.factors.VehicleState`][] (any batch shape).
    - `dt`: the time step.

    **Returns:** the predicted `VehicleState`.
    """
    return VehicleState(state.pose @ _step(state.velocity, dt), state.velocity)


def _step(velocity: Float[Array, "*batch 2"], dt) -> SE2:
    """The motion `S(v, ω)` over one step: turn by `ω dt`, move `[v dt, 0]`."""
    v, w = velocity[..., 0], velocity[..., 1]
    return SE2.from_rotation_and_translation(
        SO2.from_radians(w * dt), jnp.stack([v * dt, jnp.zeros_like(v)], axis=-1)
    )


class VehicleDynamicsFactor(AbstractAnalyticFactor):
    """Constant-velocity unicycle dynamics between `x_t` and `x_{t+1}`.

    Residual `x_{t+1} ⊖ f(x_t)` in tangent coordinates (5-D), with `f`
    [`eqsmooth.factors.vehicle_motion`][]. Its noise is normally one learnable
    [`eqsmooth.factors.DiagonalNoise`][] of shape `(5,)` shared by every step.

    Its Jacobians are given in closed form. With the step `S = S(v_t, ω_t)`,
    `X = T_t⁻¹ T_{t+1}`, `E = S⁻¹ X` and the pose residual `e = log(E)`:
    `∂e/∂δT_{t+1} = Jr⁻¹(e)`, `∂e/∂δT_t = −Jr⁻¹(e) Ad(X⁻¹)` and
    `∂e/∂(δv, δω) = −Jr⁻¹(e) Ad(E⁻¹) J_S`, where `J_S = [[c dt, 0], [−s dt, 0],
    [0, dt]]` (`c, s = cos ω dt, sin ω dt`) moves `S` in its own tangent
    space; the velocity residual has `−I` and `I`. The linearisation uses them
    instead of forward-mode autodiff through `residual` (the same values, in
    a fraction of the time: see the performance page).

    **Arguments:**

    - `prev`, `next`: [`eqsmooth.factors.Var`][]s with `n` rows (usually
        `Var("x", t[:-1])` and `Var("x", t[1:])`).
    - `noise`: noise model on the 5-D residual.
    - `dt`: the time step (static).
    """

    variables: tuple[Var, ...]
    noise: AbstractNoiseModel
    dt: float = eqx.field(static=True)

    def __init__(
        self, prev: Var, next: Var, noise: AbstractNoiseModel, dt: float = 1.0
    ):
        self.variables = (prev, next)
        self.noise = noise
        self.dt = float(dt)

    def residual(self, prev: VehicleState, next: VehicleState) -> Float[Array, " 5"]:
        return local(vehicle_motion(prev, self.dt), next)

    def residual_and_jacobians(
        self, prev: VehicleState, next: VehicleState
    ) -> tuple[Float[Array, " 5"], tuple[Float[Array, "5 5"], Float[Array, "5 5"]]]:
        dt = self.dt
        step = _step(prev.velocity, dt)
        # The same arithmetic as `residual`: E = (T_t S)⁻¹ T_{t+1}.
        err = (prev.pose @ step).inverse() @ next.pose
        e = err.log()
        jr_inv = SE2.right_jacobian_inv(e)
        jr_ad = mm(jr_inv, err.inverse().adjoint())  # Jr⁻¹(e) Ad(E⁻¹)
        c, s = step.unit_complex_xy[0], step.unit_complex_xy[1]
        zero = jnp.zeros_like(c)
        j_step = jnp.stack(
            [
                jnp.stack([c * dt, zero]),
                jnp.stack([-s * dt, zero]),
                jnp.stack([zero, zero + dt]),
            ]
        )
        # Ad(E⁻¹) Ad(S⁻¹) = Ad(X⁻¹).
        d_pose_prev = -mm(jr_ad, step.inverse().adjoint())
        d_vel_prev = -mm(jr_ad, j_step)
        eye2 = jnp.eye(2, dtype=e.dtype)
        zeros32 = jnp.zeros((3, 2), e.dtype)
        j_prev = jnp.block([[d_pose_prev, d_vel_prev], [zeros32.T, -eye2]])
        j_next = jnp.block([[jr_inv, zeros32], [zeros32.T, eye2]])
        r = jnp.concatenate([e, next.velocity - prev.velocity])
        return r, (j_prev, j_next)


class VelocityMeasurementFactor(AbstractFactor):
    """A measurement `z_t = (v_t, ω_t)` of a vehicle's velocities.

    Residual `(v_t, ω_t) − z_t` (2-D). With a per-row noise model (for
    example `DiagonalNoise` of shape `(n, 2)`) every frame has its own trust:
    the heteroscedastic virtual sensor of Yi et al.

    **Arguments:**

    - `variable`: a [`eqsmooth.factors.Var`][] with `n` rows.
    - `measurement`: `(n, 2)` measured `(v, ω)`.
    - `noise`: noise model on the 2-D residual (shared or per row).
    """

    variables: tuple[Var, ...]
    measurement: Float[Array, "n 2"]
    noise: AbstractNoiseModel

    def __init__(
        self,
        variable: Var,
        measurement: Float[ArrayLike, "n 2"],
        noise: AbstractNoiseModel,
    ):
        self.variables = (variable,)
        self.measurement = jnp.asarray(measurement)
        self.noise = noise

    def __check_init__(self):
        if self.measurement.ndim != 2 or self.measurement.shape[1] != 2:
            raise ValueError(
                "VelocityMeasurementFactor.measurement must have shape (n, 2), got "
                f"{self.measurement.shape}"
            )

    def residual(self, x: VehicleState) -> Float[Array, " 2"]:
        return x.velocity - self.measurement.astype(x.velocity.dtype)
