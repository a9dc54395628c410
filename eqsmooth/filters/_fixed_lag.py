"""A differentiable fixed-lag smoother on manifolds, built from factors.

Each step adds the newest state, marginalises the state that leaves the
window into a Gaussian prior on its successor (the Schur complement of the
normal matrix at the current estimates: GTSAM's convention), and solves the
window by Gauss-Newton. One step is a pure function of the window, so a
recorded sequence is one `lax.scan`, batched with `vmap` and differentiated
through the solves with the adjoints of [`eqsmooth.solve.least_squares`][].
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._precision import matmul as mm
from ..factors import AbstractFactor, per_row_fields
from ..manifold import retract, tangent_dim
from ..solve import (
    AbstractAdjoint,
    AbstractGraphSolver,
    ImplicitAdjoint,
    LevenbergMarquardt,
)
from ._chain import (
    chain_order,
    check_smoother_noise,
    checked_covariance,
    checked_measurements,
)
from ._rows import check_rows
from ._window import chain_rows, information_floor, initial_prior, window_step


class FixedLagSolution(eqx.Module):
    """What [`eqsmooth.filters.fixed_lag_smoother`][] returns.

    **Fields:**

    - `mean`: the online estimate of every state, `x_{t|0:t}` (the newest
        state of the window solved at step `t`), leading axis `T`.
    - `lagged_mean`: the estimate of `x_t` when it leaves the window,
        `x_{t|0:t+L-1}` (the states of the last window: at the end), leading
        axis `T`.
    - `windows`: every step's solved window, leading axes `(T, L)`; slot `i`
        of step `t` holds the state of time `window_start[t] + i` (slots past
        `t` are unused before the window fills).
    - `window_start`: the time of each window's first slot, `(T,)`.
    - `prior_mean`: the mean of the Gaussian prior on each window's first
        state (the marginal of everything that left the window, or the
        initial belief), leading axis `T`. With `closures` the prior spans
        the window's first `S` states; this is its marginal on the first.
    - `prior_covariance`: its covariance in the tangent coordinates of
        `prior_mean`, `(T, d, d)`.
    """

    mean: PyTree
    lagged_mean: PyTree
    windows: PyTree
    window_start: Array
    prior_mean: PyTree
    prior_covariance: Float[Array, "T d d"]


def fixed_lag_smoother(
    transition: AbstractFactor,
    measurements: AbstractFactor | Sequence[AbstractFactor],
    initial_mean: PyTree,
    initial_covariance: Float[ArrayLike, "d d"],
    *,
    lag: int,
    closures: AbstractFactor | Sequence[AbstractFactor] = (),
    solver: AbstractGraphSolver = LevenbergMarquardt(),
    adjoint: AbstractAdjoint = ImplicitAdjoint(),
    prediction_steps: int = 1,
    max_steps: int = 100,
) -> FixedLagSolution:
    """Fixed-lag smoothing of a chain `x_0 → … → x_{T−1}`, one step at a time.

    At step `t` the window holds the `lag` newest states (fewer at the
    start). The new state is predicted from the transition, the state that
    leaves the window is marginalised into a Gaussian prior on its successor
    (the Schur complement of the normal matrix of the factors that touch it,
    linearised at the current estimates, as GTSAM's
    `BatchFixedLagSmoother` does; the prior is then kept linear in the
    tangent space of that estimate, the "first-estimate" choice), and the
    window is solved by `solver` from the previous estimates. With
    `lag ≥ T` the last window is the batch smoother's solution; with a
    linear-Gaussian model the newest state is the Kalman filter's marginal
    for every `lag`, and the prior on a window's first state is the
    filter's prediction.

    The factors are those of [`eqsmooth.filters.ekf`][]: `transition`, a
    stack whose rows link `x_t` to `x_{t+1}` with a residual that determines
    `x_{t+1}`, and measurement stacks touching one state each (several rows
    per time step allowed, or none), with Gaussian noise; and `closures`,
    links between two states inside the window (loop closures). A
    measurement row masked by [`eqsmooth.factors.MaskedNoise`][] adds
    nothing, exactly as if it were dropped (tested to 1e-10); its data must
    still be finite. A masked closure row adds no information either, but
    its span still counts for the prior's `S` states (and their information
    floor, a relative effect of about 1e-8 in float64). The transition's
    rows cannot be masked.

    **Arguments:**

    - `transition`, `measurements`: as for [`eqsmooth.filters.ekf`][].
    - `initial_mean`, `initial_covariance`: the Gaussian belief on `x_0`
        (covariance in its tangent coordinates).
    - `lag`: the number of states in the window, `1 ≤ lag ≤ T`. From
        GTSAM's lag in seconds: [`eqsmooth.filters.lag_from_seconds`][].
    - `closures`: factor stacks whose rows link two states of the chain at
        most `lag − 1` steps apart (loop closures, skip links). A row enters
        the window with its later state and is marginalised with its
        earlier one, so the prior then spans the states up to the longest
        link ahead (a dense Gaussian on those `S` states, every state with
        an information floor of `√ε` times the transition's information,
        so that states no factor has informed yet keep it factorisable).
    - `solver`: the window's solver. By default
        [`eqsmooth.solve.LevenbergMarquardt`][]: damped and converging, so
        every window is solved (a window that does not converge within
        `max_steps` raises). [`eqsmooth.solve.FixedStepGaussNewton`][]`(K)`
        with `UnrolledAdjoint()` gives every update the same cost (the
        paper's K unrolled steps), but K undamped steps are not a solved
        window on every chain: on the SE(2) + velocity chain of
        `benchmarks/fixed_lag.py` the estimates drift about 1 away from the
        solved windows' within 100 steps, with K = 3 and with K = 10.
    - `adjoint`: how each window solve is differentiated (see
        [`eqsmooth.solve.least_squares`][]): implicit by default (exact at a
        solved window); `UnrolledAdjoint()` differentiates the iterations
        themselves (for `FixedStepGaussNewton`).
    - `prediction_steps`: Newton steps that predict a new state from the
        transition.
    - `max_steps`: the iteration limit of each window solve (a converging
        `solver`; `FixedStepGaussNewton` runs its `num_steps`). Under
        `UnrolledAdjoint` every window runs all `max_steps` iterations
        (masked once converged): a warm-started window converges in a few,
        so keep it small there.

    **Returns:** a [`eqsmooth.filters.FixedLagSolution`][].
    """
    measurements, closures = _checked_arguments(
        transition, measurements, closures, lag, solver
    )
    T = transition.num_rows + 1
    d = tangent_dim(initial_mean)
    cov0 = checked_covariance("fixed_lag_smoother", initial_covariance, d)
    dtype = cov0.dtype
    model = chain_rows(transition, measurements, closures, initial_mean, dtype)
    prior = initial_prior(model.S, initial_mean, cov0, information_floor(model, 0))
    values = jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (lag, *jnp.shape(a))), initial_mean
    )

    def step(carry, t):
        return window_step(
            model, lag, solver, adjoint, prediction_steps, carry, t, max_steps
        )

    _, (windows, start, priors, _) = lax.scan(step, (values, prior), jnp.arange(T))
    return _solution(windows, start, priors, lag, T)


def lag_from_seconds(smoother_lag: float | int, dt: float | int) -> int:
    """The `lag`, in states, of the window a GTSAM fixed-lag smoother with a
    lag of `smoother_lag` seconds optimises when a state comes every `dt`
    seconds.

    GTSAM's `BatchFixedLagSmoother(smoother_lag)` and
    `IncrementalFixedLagSmoother(smoother_lag)` keep, after each update, the
    states whose timestamp is within `smoother_lag` of the newest
    (`⌊smoother_lag / dt⌋ + 1` of them), and optimise those plus the new
    one: `⌊smoother_lag / dt⌋ + 2` states, which is what
    [`eqsmooth.filters.fixed_lag_smoother`][] and
    [`eqsmooth.filters.FixedLagSmoother`][] call `lag` (checked against
    GTSAM's own smoothers, e.g. 0.3 s at 0.1 s per state: 5). A ratio within
    1e-9 of a whole number counts as that number (0.3 / 0.1 is
    2.9999999999999996 in floating point).

    **Arguments:**

    - `smoother_lag`: GTSAM's `smootherLag`, in seconds, `≥ 0`.
    - `dt`: the time between consecutive states, in seconds, `> 0`.

    **Returns:** the number of states, an `int ≥ 2`, to pass as `lag=`.
    """
    for name, value in (("smoother_lag", smoother_lag), ("dt", dt)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.number)):
            raise TypeError(
                f"lag_from_seconds: {name} must be a number of seconds, got "
                f"{type(value).__name__}"
            )
        if not np.isfinite(value):
            raise ValueError(f"lag_from_seconds: {name} must be finite, got {value}")
    if dt <= 0:
        raise ValueError(f"lag_from_seconds: dt must be > 0 seconds, got {dt}")
    if smoother_lag < 0:
        raise ValueError(
            f"lag_from_seconds: smoother_lag must be >= 0 seconds, got {smoother_lag}"
        )
    ratio = float(smoother_lag) / float(dt)
    whole = round(ratio)
    steps = whole if abs(ratio - whole) <= 1e-9 * max(1.0, ratio) else int(ratio)
    return steps + 2


def _checked_arguments(transition, measurements, closures, lag, solver):
    """`fixed_lag_smoother`'s checks: the measurement and closure stacks as
    tuples, or an error naming the argument."""
    if isinstance(lag, bool) or not isinstance(lag, int) or lag < 1:
        raise ValueError(f"fixed_lag_smoother: lag must be an int >= 1, got {lag!r}")
    if not isinstance(transition, AbstractFactor):
        raise TypeError(
            "fixed_lag_smoother: transition must be an AbstractFactor, got "
            f"{type(transition).__name__}"
        )
    measurements = checked_measurements(transition, measurements, maskable=True)
    T = transition.num_rows + 1
    if lag > T:
        raise ValueError(
            f"fixed_lag_smoother: lag {lag} is longer than the {T} states of the "
            "chain (use lag = T for the batch smoother's answer)"
        )
    if not isinstance(solver, AbstractGraphSolver):
        raise TypeError(
            "fixed_lag_smoother: solver must be an eqsmooth graph solver such as "
            f"LevenbergMarquardt or FixedStepGaussNewton, got {type(solver).__name__}"
        )
    closures = _checked_closures(transition, closures, lag)
    for f in (transition, *measurements, *closures):
        _check_finite_rows(f)
    return measurements, closures


def _checked_closures(transition, closures, lag: int) -> tuple[AbstractFactor, ...]:
    """The link stacks as a tuple, each checked against the chain and the lag."""
    if isinstance(closures, AbstractFactor):
        closures = (closures,)
    closures = tuple(closures)
    group, _ = chain_order(transition)
    T = transition.num_rows + 1
    for f in closures:
        if not isinstance(f, AbstractFactor):
            raise TypeError(
                "fixed_lag_smoother: closures must be AbstractFactor stacks, got "
                f"{type(f).__name__}"
            )
        name = type(f).__name__
        if len(f.variables) != 2 or any(v.group != group for v in f.variables):
            raise ValueError(
                f"fixed_lag_smoother: closure factor {name} must link two states of "
                f"group {group!r}; it touches "
                f"{[(v.group, len(v)) for v in f.variables]}"
            )
        ia, ib = (np.asarray(v.ids) for v in f.variables)
        if ia.size == 0:
            raise ValueError(f"fixed_lag_smoother: closure factor {name} has no rows")
        span = np.abs(ib - ia)
        for bad, why in (
            (span == 0, "a link must join two different states"),
            (
                span >= lag,
                f"a link must join states at most lag - 1 = {lag - 1} steps "
                f"apart: it would reach outside the window of {lag} states",
            ),
            (np.maximum(ia, ib) >= T, f"the chain has only T = {T} states"),
        ):
            if bad.any():
                k = int(np.flatnonzero(bad)[0])
                raise ValueError(
                    f"fixed_lag_smoother: closure factor {name} row {k} links times "
                    f"{int(ia[k])} and {int(ib[k])}: {why} ({int(bad.sum())} such "
                    "rows)"
                )
        check_rows(f)
        check_smoother_noise(
            f.noise, f"fixed_lag_smoother: closure factor {name}", maskable=True
        )
    return closures


def _check_finite_rows(factor: AbstractFactor) -> None:
    """A non-finite measurement would fail every window it enters: name the
    stack and the rows up front (concrete arrays only; traced ones are the
    solver's to report)."""
    bad = None
    for leaf in jax.tree_util.tree_leaves(per_row_fields(factor)):
        if isinstance(leaf, jax.core.Tracer) or not eqx.is_inexact_array(leaf):
            continue
        a = np.asarray(leaf)
        rows = ~np.isfinite(a.reshape(a.shape[0], -1)).all(axis=1)
        bad = rows if bad is None else bad | rows
    if bad is not None and bad.any():
        raise ValueError(
            f"fixed_lag_smoother: factor {type(factor).__name__} has non-finite "
            f"data in rows {np.flatnonzero(bad)[:10].tolist()} (times "
            f"{factor.variables[0].ids[bad][:10].tolist()}); drop those rows, or "
            "mask them with MaskedNoise and fill them with any finite placeholder "
            "(a masked row's residual is multiplied by zero, and 0 * NaN is NaN)"
        )


def _prior_moments(anchor, R, c):
    """Mean and covariance of the first slot's marginal of the prior
    `½‖R [local(anchorᵢ, xᵢ)]ᵢ + c‖²`."""
    first = jax.tree_util.tree_map(lambda a: a[0], anchor)
    d = tangent_dim(first)
    mean = retract(first, -jnp.linalg.solve(R, c)[:d])
    return mean, jnp.linalg.inv(mm(R.T, R))[:d, :d]


def _solution(windows, start, priors, lag: int, T: int) -> FixedLagSolution:
    pmean, pcov = jax.vmap(_prior_moments)(*priors)
    t = np.arange(T)
    start_np = np.maximum(t - lag + 1, 0)
    online = jax.tree_util.tree_map(lambda w: w[t, t - start_np], windows)
    # x_t leaves the window after step t + lag - 1 (or stays to the end).
    final = np.minimum(t + lag - 1, T - 1)
    lagged = jax.tree_util.tree_map(lambda w: w[final, t - start_np[final]], windows)
    # (fields in order: mean, lagged_mean, windows, window_start, prior_mean,
    # prior_covariance)
    return FixedLagSolution(online, lagged, windows, start, pmean, pcov)
