"""The IMU chain of a keyframe smoother, built in one call.

GTSAM's IMU examples (`ImuFactorsExample`, `IMUKittiExampleGPS`) link every
pair of consecutive keyframes by an IMU factor on the preintegrated samples
between them and the biases by a random walk whose standard deviation grows
with the square root of the number of samples it spans. `imu_chain` builds
those two stacks (or one `CombinedImuFactor` stack) from the intervals'
[`eqsmooth.factors.PreintegratedImuMeasurements`][]; the priors and the
position fixes, which differ from one problem to the next, stay with the
caller.
"""

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, Real

from ._builtin import BetweenFactor
from ._factor import AbstractFactor
from ._imu import CombinedImuFactor, ImuFactor
from ._imu_preintegration import ImuParams, PreintegratedImuMeasurements
from ._noise import DiagonalNoise
from ._variables import Var


def bias_walk_sigmas(
    accelerometer_bias_sigma: Float[ArrayLike, "..."],
    gyroscope_bias_sigma: Float[ArrayLike, "..."],
    samples: Real[ArrayLike, " n"] | Sequence[float],
) -> Float[Array, "n 6"]:
    """The standard deviations of a discrete bias random walk over `n`
    intervals: `√samples · (σ_acc, σ_acc, σ_acc, σ_ω, σ_ω, σ_ω)`, the
    `(b_acc, b_omega)` order of the bias variables.

    A walk of standard deviation `σ` per IMU sample drifts by `√k σ` over
    `k` samples. GTSAM's `IMUKittiExampleGPS` passes the running count of
    samples integrated since the start instead of each interval's count;
    either is a `samples` array here. Differentiable in the sigmas (a
    learned walk).

    **Arguments:**

    - `accelerometer_bias_sigma`, `gyroscope_bias_sigma`: per-sample
        standard deviations (scalars, or `(3,)` per axis).
    - `samples`: the number of samples each interval's walk spans, `(n,)`.

    **Returns:** the sigmas, `(n, 6)`, for
    [`eqsmooth.factors.imu_chain`][]'s `bias_walk_sigmas`.
    """
    k = jnp.asarray(samples)
    if k.ndim != 1:
        raise ValueError(
            f"bias_walk_sigmas: samples must have shape (n,), got {k.shape}"
        )
    per_sample = jnp.concatenate(
        [
            jnp.broadcast_to(jnp.asarray(accelerometer_bias_sigma), (3,)),
            jnp.broadcast_to(jnp.asarray(gyroscope_bias_sigma), (3,)),
        ]
    )
    return jnp.sqrt(k)[:, None] * per_sample[None, :]


def imu_chain(
    pim: PreintegratedImuMeasurements,
    gravity: Float[ArrayLike, "..."] | ImuParams,
    bias_walk_sigmas: Float[ArrayLike, "..."] | None = None,
    *,
    ids: Int[ArrayLike, " m"] | Sequence[int] | None = None,
    pose: str = "x",
    velocity: str = "v",
    bias: str = "b",
    combined: bool = False,
) -> list[AbstractFactor]:
    """The factors linking consecutive keyframes of an IMU smoother.

    For `n` preintegrated intervals between the keyframes `ids[0], …,
    ids[n]`, row `k` links keyframe `ids[k]` to `ids[k+1]`:

    - by default an [`eqsmooth.factors.ImuFactor`][] stack and a
        [`eqsmooth.factors.BetweenFactor`][] stack on the biases with zero
        measurement and the [`eqsmooth.factors.DiagonalNoise`][] of
        `bias_walk_sigmas` (GTSAM's `BetweenFactor<imuBias::ConstantBias>`);
    - with `combined=True` one [`eqsmooth.factors.CombinedImuFactor`][]
        stack, whose bias drift comes from the `ImuParams` bias densities
        (then `bias_walk_sigmas` must be `None`).

    To hold each keyframe's `(pose, velocity, bias)` in one variable (the
    chain smoothers such as [`eqsmooth.filters.fixed_lag_smoother`][] want
    that), use
    [`eqsmooth.factors.ImuTransitionFactor`][] with the same arguments.

    **Arguments:**

    - `pim`: the intervals' [`eqsmooth.factors.PreintegratedImuMeasurements`][],
        batch shape `(n,)` (from [`eqsmooth.factors.preintegrate`][]).
    - `gravity`: the navigation-frame gravity `(3,)`, or the
        [`eqsmooth.factors.ImuParams`][] whose gravity to use.
    - `bias_walk_sigmas`: the walk's standard deviations over each
        interval, `(6,)` or `(n, 6)` (e.g. from
        [`eqsmooth.factors.bias_walk_sigmas`][]).
    - `ids`: the `n + 1` keyframe indices, by default `0, …, n`.
    - `pose`, `velocity`, `bias`: the variable groups of the SE(3) poses,
        the `(3,)` velocities and the `(6,)` biases.
    - `combined`: build `CombinedImuFactor` rows instead.

    **Returns:** a list of factor stacks, to extend with the problem's
    priors and measurements and pass to [`eqsmooth.factors.FactorGraph`][].
    """
    if not isinstance(pim, PreintegratedImuMeasurements):
        raise TypeError(
            "imu_chain: pim must be a PreintegratedImuMeasurements (from "
            f"eqsmooth.factors.preintegrate), got {type(pim).__name__}"
        )
    if pim.delta_t.ndim != 1:
        raise ValueError(
            "imu_chain: pim must have one batch axis (one row per interval), got "
            f"batch shape {pim.delta_t.shape}"
        )
    n = pim.delta_t.shape[0]
    ids = np.arange(n + 1) if ids is None else np.asarray(ids)
    if ids.shape != (n + 1,):
        raise ValueError(
            f"imu_chain: ids must hold the {n + 1} keyframes of {n} intervals, got "
            f"shape {ids.shape}"
        )
    i, j = ids[:-1], ids[1:]
    states = (Var(pose, i), Var(velocity, i), Var(pose, j), Var(velocity, j))
    if combined:
        if bias_walk_sigmas is not None:
            raise ValueError(
                "imu_chain: combined=True takes the bias drift from the ImuParams "
                "bias densities; give bias_walk_sigmas=None"
            )
        return [CombinedImuFactor(*states, Var(bias, i), Var(bias, j), pim, gravity)]
    if bias_walk_sigmas is None:
        raise ValueError(
            "imu_chain: give bias_walk_sigmas (the bias random walk over each "
            "interval), or combined=True"
        )
    sigmas = jnp.asarray(bias_walk_sigmas)
    if sigmas.shape not in ((6,), (n, 6)):
        raise ValueError(
            f"imu_chain: bias_walk_sigmas must have shape (6,) or ({n}, 6), got "
            f"{sigmas.shape}"
        )
    sigmas = jnp.broadcast_to(sigmas, (n, 6))
    return [
        ImuFactor(*states, Var(bias, i), pim, gravity),
        BetweenFactor(
            Var(bias, i),
            Var(bias, j),
            jnp.zeros((n, 6), sigmas.dtype),
            DiagonalNoise.from_sigmas(sigmas),
        ),
    ]
