"""The fixed-lag smoother one step at a time: `init`, then `update` per new
state, for a robot that receives its measurements as they come.

The state keeps the window's estimates, the prior on its first state, and
the rows (data and square-root information) of the factors of the window
and of the state about to leave it. Each update builds the window's chain
over those `lag + 1` slots and runs the same step as
[`eqsmooth.filters.fixed_lag_smoother`][], so a run of updates gives the
same estimates as the scan.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int, PyTree

from ..factors import AbstractFactor, per_row_fields
from ..manifold import tangent_dim
from ..solve import (
    AbstractAdjoint,
    AbstractGraphSolver,
    ImplicitAdjoint,
    LevenbergMarquardt,
)
from ._chain import check_smoother_noise, checked_covariance, residual_dim
from ._rows import check_rows, row_whitening
from ._window import ChainRows, initial_prior, window_step


class FixedLagState(eqx.Module):
    """The state of a [`eqsmooth.filters.FixedLagSmoother`][].

    **Fields:**

    - `t`: the time of the newest state.
    - `window`: the window's estimates, leading axis `lag`; slot `i` holds
        the state of time `window_start + i` (slots past `t` are unused
        before the window fills).
    - `window_start`: the time of the window's first slot.
    - `prior`: the Gaussian prior on the window's first state (anchor,
        square-root information, offset), as the scan keeps it.
    - `rows`: the factor rows of the last `lag + 1` time steps.
    """

    t: Int[Array, ""]
    window: PyTree
    window_start: Int[Array, ""]
    prior: tuple
    rows: tuple


def _step_rows(transition, measurements, mean0, dtype):
    """One time step's rows: (transition rows, R), then per stack (rows, R)."""
    d = tangent_dim(mean0)
    trans_R, _ = row_whitening(transition, d, dtype)
    out = [(per_row_fields(transition), trans_R)]
    for f in measurements:
        R, _ = row_whitening(f, residual_dim(f, per_row_fields(f), mean0), dtype)
        out.append((per_row_fields(f), R))
    return tuple(out)


def _write(buffers, new, slot, shift):
    """Shift every buffer by one time step (when `shift`) and write `new` at
    time `slot` (a buffer holds `k` rows per time step)."""

    def one(buf, rows):
        k = rows.shape[0]
        moved = jnp.where(shift, jnp.roll(buf, -k, axis=0), buf)
        return jax.lax.dynamic_update_slice_in_dim(moved, rows, slot * k, axis=0)

    return jax.tree_util.tree_map(one, buffers, new)


def _check_step(who, transition, measurements, group: str | None):
    """The step's factor stacks: a one-row transition and measurement stacks
    (none, or several) touching one state, all of one group, with Gaussian
    noise (measurement rows may be masked)."""
    if not isinstance(transition, AbstractFactor):
        raise TypeError(
            f"{who}: transition must be an AbstractFactor, got "
            f"{type(transition).__name__}"
        )
    if isinstance(measurements, AbstractFactor):
        measurements = (measurements,)
    measurements = tuple(measurements)
    name = type(transition).__name__
    if len(transition.variables) != 2 or transition.num_rows != 1:
        raise ValueError(
            f"{who}: the transition {name} must be one row linking two states "
            f"(x_t, x_t+1); it has {transition.num_rows} rows on "
            f"{len(transition.variables)} variables"
        )
    group = group or transition.variables[0].group
    for f in (transition, *measurements):
        if not isinstance(f, AbstractFactor):
            raise TypeError(
                f"{who}: measurements must be AbstractFactor stacks, got "
                f"{type(f).__name__}"
            )
        if f is not transition and len(f.variables) != 1:
            raise ValueError(
                f"{who}: measurement factor {type(f).__name__} must touch one "
                f"variable (x_t); it touches {len(f.variables)}"
            )
        if any(v.group != group for v in f.variables):
            raise ValueError(
                f"{who}: factor {type(f).__name__} touches group "
                f"{[v.group for v in f.variables]}, not the chain's {group!r}"
            )
        check_rows(f)
        check_smoother_noise(
            f.noise, f"{who}: factor {type(f).__name__}", maskable=f is not transition
        )
    return transition, measurements, group


def _check_dtypes(who, transition, measurements, kept):
    """A step's factor data must have the dtypes of the rows `init` kept (a
    float32 step after a float64 init failed deep inside the update)."""
    names = ["transition"] + [f"measurements[{i}]" for i in range(len(measurements))]
    stacks = (transition, *measurements)
    if len(stacks) != len(kept):
        return  # another structure: the structure check says so
    for name, factor, (old_rows, _) in zip(names, stacks, kept):
        new = jax.tree_util.tree_leaves(per_row_fields(factor))
        old = jax.tree_util.tree_leaves(old_rows)
        for a, b in zip(new, old):
            if jnp.result_type(a) != jnp.result_type(b):
                raise TypeError(
                    f"{who}: this step's {name} data has dtype "
                    f"{jnp.result_type(a)} where the state (from init) has "
                    f"{jnp.result_type(b)}: give every step the dtype of init's "
                    "factors (a float32 step after a float64 init, or the reverse)"
                )


def _finite(rows, t, who):
    """Stop on a non-finite value in the new rows (traced data: a runtime
    error naming the step, instead of NaN estimates)."""
    bad = jnp.array(False)
    for leaf in jax.tree_util.tree_leaves(rows):
        if eqx.is_inexact_array(leaf):
            bad = bad | ~jnp.all(jnp.isfinite(leaf))
    return eqx.error_if(
        t, bad, f"{who}: non-finite factor data or noise in this step's rows"
    )


class FixedLagSmoother(eqx.Module):
    """The fixed-lag smoother as `init` and `update`, one new state at a
    time (what a robot calls as measurements arrive).

    Each step takes the new state's factors: a one-row `transition` linking
    the previous state to the new one, and measurement stacks touching the
    new state, with the same structure every step (the number of rows per
    stack fixed; mask a missing one with [`eqsmooth.factors.MaskedNoise`][]:
    a masked row adds nothing, exactly as if it were dropped, tested to
    1e-10; its data must still be finite, e.g. the last measurement). A
    step may have no measurement stack at all (odometry only), if every
    step has none.
    The factors' variable indices are not read (build them with fixed ids,
    e.g. `Var("x", [0])` and `Var("x", [1])`, so that every step is the same
    compiled program); only their group, data and noise are. A run of
    updates gives the estimates of [`eqsmooth.filters.fixed_lag_smoother`][]
    on the same factors (tested to 1e-10), and every update is a pure
    function: `jax.jit`, `jax.grad` through a sequence of updates, and
    `jax.vmap` over robots apply. `init` and `update` run one compiled
    program (compiled by `init`: the state has the same shapes after every
    step), also when `update` is not wrapped in a `jit`. Loop closures are
    not taken here (use the scan's `closures`).

    **Arguments:**

    - `lag`, `solver`, `adjoint`, `prediction_steps`, `max_steps`: as for
        [`eqsmooth.filters.fixed_lag_smoother`][].
        A lag in seconds, as GTSAM gives it: `lag=`
        [`eqsmooth.filters.lag_from_seconds`][]`(smoother_lag, dt)`.
    """

    lag: int = eqx.field(static=True)
    solver: AbstractGraphSolver = LevenbergMarquardt()
    adjoint: AbstractAdjoint = ImplicitAdjoint()
    prediction_steps: int = eqx.field(static=True, default=1)
    max_steps: int = eqx.field(static=True, default=100)

    def __check_init__(self):
        lag = self.lag
        if isinstance(lag, bool) or not isinstance(lag, int) or lag < 1:
            raise ValueError(f"FixedLagSmoother: lag must be an int >= 1, got {lag!r}")

    def init(
        self,
        initial_mean: PyTree,
        initial_covariance: Float[ArrayLike, "d d"],
        transition: AbstractFactor,
        measurements: AbstractFactor | Sequence[AbstractFactor] = (),
    ) -> tuple[FixedLagState, PyTree]:
        """The state after the first time step.

        **Arguments:**

        - `initial_mean`, `initial_covariance`: the Gaussian belief on `x_0`.
        - `transition`: a one-row transition of the kind every update will
            give (its data is not used: `x_0` has no predecessor).
        - `measurements`: the measurement stacks of `x_0` (none by default;
            every update must then give the same stacks, with the same rows).

        **Returns:** `(state, estimate of x_0)`.
        """
        who = "FixedLagSmoother.init"
        transition, measurements, _ = _check_step(who, transition, measurements, None)
        d = tangent_dim(initial_mean)
        cov0 = checked_covariance(who, initial_covariance, d)
        step = _step_rows(transition, measurements, initial_mean, cov0.dtype)
        n = self.lag + 1  # time steps kept: the window and the state leaving it
        rows = jax.tree_util.tree_map(lambda a: jnp.concatenate([a] * n, axis=0), step)
        window = jax.tree_util.tree_map(
            lambda a: jnp.broadcast_to(a, (self.lag, *jnp.shape(a))), initial_mean
        )
        state = FixedLagState(
            jnp.array(-1),
            window,
            jnp.array(0),
            initial_prior(1, initial_mean, cov0),
            rows,
        )
        return _advance(self, state, transition, measurements, step)

    def update(
        self,
        state: FixedLagState,
        transition: AbstractFactor,
        measurements: AbstractFactor | Sequence[AbstractFactor] = (),
    ) -> tuple[FixedLagState, PyTree]:
        """Add the next state: its transition from the newest state and its
        measurements; solve the window.

        **Returns:** `(state, estimate of the new state given everything so
        far)`; `state.window` holds the whole window's estimates.
        """
        who = "FixedLagSmoother.update"
        if not isinstance(state, FixedLagState):
            raise TypeError(
                f"{who}: state must be a FixedLagState, got {type(state).__name__}"
            )
        transition, measurements, _ = _check_step(who, transition, measurements, None)
        lags = {jnp.shape(a)[0] for a in jax.tree_util.tree_leaves(state.window)}
        if lags != {self.lag}:
            raise ValueError(
                f"{who}: the state was made by a FixedLagSmoother with lag="
                f"{sorted(lags)[0]}, this smoother has lag={self.lag}: update a "
                "state with the smoother whose init made it"
            )
        _check_dtypes(who, transition, measurements, state.rows)
        mean = jax.tree_util.tree_map(lambda a: a[0], state.window)
        step = _step_rows(transition, measurements, mean, state.prior[1].dtype)
        n = self.lag + 1
        if jax.tree_util.tree_structure(step) != jax.tree_util.tree_structure(
            state.rows
        ) or any(
            a.shape[1:] != b.shape[1:] or b.shape[0] != n * a.shape[0]
            for a, b in zip(
                jax.tree_util.tree_leaves(step), jax.tree_util.tree_leaves(state.rows)
            )
        ):
            raise ValueError(
                f"{who}: this step's factors differ in kind or row count from "
                "those the state was built with (init); every step must have the "
                "same structure"
            )
        return _advance(self, state, transition, measurements, step)


# One compiled program for `init` and every `update` of a smoother (the state
# has the same shapes before and after each step), also when `update` is
# not wrapped in a `jit`; under a caller's `jit` it is inlined.
@eqx.filter_jit
def _advance(smoother, state, transition, measurements, step):
    lag = smoother.lag
    t = _finite(step, state.t + 1, "FixedLagSmoother.init/update")
    vt = jnp.minimum(t, lag)  # the new state's slot among the kept steps
    rows = _write(state.rows, step, vt, t > lag)
    (trans_rows, trans_R), *meas = rows
    k = [R.shape[0] // (lag + 1) for _, R in meas]
    # Kept step v holds the transition into v; the model's row v is the
    # transition v -> v + 1.
    model = ChainRows(
        transition=transition,
        trans_rows=jax.tree_util.tree_map(lambda a: a[1:], trans_rows),
        trans_R=trans_R[1:],
        measurements=measurements,
        meas_rows=tuple(r for r, _ in meas),
        meas_R=tuple(R for _, R in meas),
        meas_table=tuple(np.arange((lag + 1) * kj).reshape(lag + 1, kj) for kj in k),
        meas_mask=tuple(np.ones((lag + 1, kj), bool) for kj in k),
        links=(),
        group=transition.variables[0].group,
        T=lag + 1,
        S=1,
    )
    carry, (window, start, prior) = window_step(
        model,
        lag,
        smoother.solver,
        smoother.adjoint,
        smoother.prediction_steps,
        (state.window, state.prior),
        vt,
        smoother.max_steps,
    )
    newest = jax.tree_util.tree_map(lambda a: a[vt - start], window)
    new = FixedLagState(t, window, t - vt + start, prior, rows)
    return new, newest
