"""The fixed-lag smoother one step at a time: `init`, then `update` per new
state, for a robot that receives its measurements as they come.

The state keeps the window's estimates, the prior on its first state, and
the rows (data and square-root information) of the factors of the window
and of the state about to leave it. Each update builds the window's chain
over those `lag + 1` slots and runs the same step as
[`eqsmooth.filters.fixed_lag_smoother`][], so a run of updates gives the
same estimates as the scan. `update_rows` is the same update with the
step's data given as arrays: the factors of `init`, kept in the state, are
rebuilt with the new rows inside the one compiled program.
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PyTree

from ..factors import AbstractFactor, per_row_fields, with_rows
from ..manifold import tangent_dim
from ..solve import (
    AbstractAdjoint,
    AbstractGraphSolver,
    ImplicitAdjoint,
    LevenbergMarquardt,
    RESULTS,
)
from ..solve._misc import all_arrays
from ..solve._solution import result_index
from ._chain import check_smoother_noise, checked_covariance, residual_dim
from ._rows import check_rows, row_whitening
from ._window import ChainRows, floor_of, initial_prior, kept_links, window_step


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
    - `templates`: the factor stacks `init` was given (the transition, then
        each measurement stack): `update_rows` rebuilds each step's factors
        from them, with that step's rows in place of their per-row data
        (their noise, shared fields and structure serve every step).
    - `result`: the [`eqsmooth.solve.RESULTS`][] code of the last update
        (`successful`; with `throw=False`, `nonfinite_problem` for
        non-finite step data or the window solve's failure code).
    - `closure_template`: the closure stack `init` was given (`None`: the
        smoother takes no closures).
    - `closure_rows`: the closures of the last `lag + 1` time steps: their
        per-row data, square-root information (zero for an absent closure)
        and how many steps back each reaches (0: absent).
    - `closure_refused`: per closure row of the last update, whether it was
        given (active) but reached outside the window: before `x_0` or more
        than `max_back` steps back. With `throw=True` such an update raises
        instead; with `throw=False` the row is left out and only this says so.
    """

    t: Int[Array, ""]
    window: PyTree
    window_start: Int[Array, ""]
    prior: tuple
    rows: tuple
    templates: tuple
    result: RESULTS
    closure_template: AbstractFactor | None = None
    closure_rows: tuple = ()
    closure_refused: Bool[Array, " k"] | None = None


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


def _nonfinite(rows) -> Bool[Array, ""]:
    """Whether the new rows hold a non-finite value."""
    bad = jnp.array(False)
    for leaf in jax.tree_util.tree_leaves(rows):
        if eqx.is_inexact_array(leaf):
            bad = bad | ~jnp.all(jnp.isfinite(leaf))
    return bad


def _finite(rows, t, who):
    """Stop on a non-finite value in the new rows (traced data: a runtime
    error naming the step, instead of NaN estimates)."""
    message = f"{who}: non-finite factor data or noise in this step's rows"
    return eqx.error_if(t, _nonfinite(rows), message)


def _checked_rows(who, name, rows, template):
    """`rows` as the per-row fields of `template` (a stack `init` was given):
    the same fields, tree structures, shapes and dtypes (checked while
    tracing, so a compiled update does no Python work)."""
    stack = type(template).__name__
    if not isinstance(rows, dict):
        raise TypeError(
            f"{who}: {name} must be a dict {{per-row field: array}} of the {stack} "
            "stack, as eqsmooth.factors.per_row_fields gives it, got "
            f"{type(rows).__name__}"
        )
    kept = per_row_fields(template)
    unknown = sorted(set(rows) - set(kept))
    if unknown:
        raise ValueError(
            f"{who}: {name} has fields {unknown} that are not per-row fields of "
            f"init's {stack} stack; those are {sorted(kept)}"
        )
    out = {}
    for field, old in kept.items():
        if field not in rows:
            if jax.tree_util.tree_leaves(old):
                raise ValueError(
                    f"{who}: {name} lacks the field {field!r} of init's {stack} "
                    f"stack (its per-row fields: {sorted(kept)})"
                )
            out[field] = old  # a field without data (`data=None`)
            continue
        new = rows[field]
        new_def = jax.tree_util.tree_structure(new)
        old_def = jax.tree_util.tree_structure(old)
        if new_def != old_def:
            raise TypeError(
                f"{who}: {name}[{field!r}] has the structure {new_def}, init's "
                f"{stack} stack has {old_def}"
            )
        pairs = zip(
            jax.tree_util.tree_flatten_with_path(new)[0],
            jax.tree_util.tree_leaves(old),
        )
        for (path, a), b in pairs:
            where = f"{name}[{field!r}]{jax.tree_util.keystr(path)}"
            if jnp.shape(a) != jnp.shape(b):
                raise ValueError(
                    f"{who}: {where} has shape {jnp.shape(a)}, init's {stack} "
                    f"stack has {jnp.shape(b)} (the same rows every step)"
                )
            if jnp.result_type(a) != jnp.result_type(b):
                raise TypeError(
                    f"{who}: {where} has dtype {jnp.result_type(a)}, init's "
                    f"{stack} stack has {jnp.result_type(b)}"
                )
        out[field] = new
    return out


def _check_state(who: str, lag: int, state) -> None:
    """`state` must be a FixedLagState made by a smoother with this `lag`."""
    if not isinstance(state, FixedLagState):
        raise TypeError(
            f"{who}: state must be a FixedLagState, got {type(state).__name__}"
        )
    lags = {jnp.shape(a)[0] for a in jax.tree_util.tree_leaves(state.window)}
    if lags != {lag}:
        raise ValueError(
            f"{who}: the state was made by a FixedLagSmoother with lag="
            f"{sorted(lags)[0]}, this smoother has lag={lag}: update a state with "
            "the smoother whose init made it"
        )


def _data_rows(template: AbstractFactor, rows):
    """`rows` without the fields that hold no data in `template` (e.g.
    `data=None`) when given as None: one form for `{}` and `{"data": None}`."""
    if not isinstance(rows, dict):
        return rows  # refused, with the reason, while tracing
    kept = per_row_fields(template)
    empty = {k for k, v in kept.items() if not jax.tree_util.tree_leaves(v)}
    return {k: v for k, v in rows.items() if not (k in empty and v is None)}


def _reach(state) -> int:
    """The prior's span `S` of a state: its `max_back` (1 without closures)."""
    return jax.tree_util.tree_leaves(state.prior[0])[0].shape[0]


def _check_closure_stack(who, closures, group: str, k: int | None):
    """A closure stack: a factor linking two states of the chain's group,
    with Gaussian (maskable) noise and `k` rows when `k` is given."""
    if not isinstance(closures, AbstractFactor):
        raise TypeError(
            f"{who}: closures must be an AbstractFactor stack (e.g. a BetweenFactor "
            f"of k rows), got {type(closures).__name__}"
        )
    name = type(closures).__name__
    if len(closures.variables) != 2 or any(
        v.group != group for v in closures.variables
    ):
        raise ValueError(
            f"{who}: closure factor {name} must link two states of group {group!r} "
            f"(x_t-back, x_t); it touches "
            f"{[(v.group, len(v)) for v in closures.variables]}"
        )
    if k is not None and closures.num_rows != k:
        raise ValueError(
            f"{who}: closure factor {name} has {closures.num_rows} rows, init's has "
            f"{k}: give the same number of closure rows every step (mask absent ones)"
        )
    check_rows(closures)
    check_smoother_noise(closures.noise, f"{who}: closure factor {name}", maskable=True)


def _host_back(who, back, active, k: int, max_back: int):
    """`closure_back` (and `closure_active`) as arrays; values checked here
    when they are on the host (NumPy, lists): a step that reaches outside
    `1..max_back` is named before any work. Device arrays are checked in
    the compiled update (against the newest time, too)."""
    if back is None:
        raise TypeError(
            f"{who}: this smoother takes closures (init was given a closure stack): "
            "give closure_rows and closure_back every step (absent closures: "
            "closure_active false)"
        )
    if not isinstance(back, jax.Array):
        back = np.asarray(back)
        if back.shape != (k,) or not np.issubdtype(back.dtype, np.integer):
            raise TypeError(
                f"{who}: closure_back has shape {back.shape} and dtype {back.dtype}; "
                f"the closure stack has {k} rows: give ({k},) integers, the steps "
                "back each closure reaches"
            )
    if active is None:
        active = np.ones(k, bool)
    elif not isinstance(active, jax.Array):
        active = np.asarray(active)
    if isinstance(back, np.ndarray) and isinstance(active, np.ndarray):
        on = active.astype(bool) if active.shape == (k,) else np.ones(k, bool)
        bad = on & ((back < 1) | (back > max_back))
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise ValueError(
                f"{who}: closure row {j} reaches {int(back[j])} steps back: a "
                f"closure reaches 1 to max_back = {max_back} steps back (inside "
                "the window; init's max_back); mask it with closure_active, or "
                "give init a larger max_back (at most lag - 1)"
            )
    return back, active


def _step_closures(who, state, closure_rows, back, active):
    """`update_rows`' closures as (factor, back, active): `init`'s closure
    stack with the given rows; shapes and dtypes checked while tracing."""
    template = state.closure_template
    if template is None:
        raise ValueError(
            f"{who}: closure_rows given, but init was given no closure stack: pass "
            "init(..., closures=<a factor stack of k rows>) to take closures"
        )
    if template.noise.active_rows() is not None:
        raise TypeError(
            f"{who}: init's closure stack ({type(template).__name__}) has masked "
            f"noise ({template.noise.name}); its mask would hold for every step. "
            "Give init the unmasked noise and mask steps' closures with "
            "closure_active"
        )
    factor = with_rows(
        template, _checked_rows(who, "closure_rows", closure_rows, template)
    )
    return (factor, *_checked_back(who, template.num_rows, back, active))


def _checked_back(who, k: int, back, active):
    """`closure_back` and `closure_active` as traced (k,) arrays, or an error
    naming the one of the wrong shape or dtype."""
    back, active = jnp.asarray(back), jnp.asarray(active)
    if back.shape != (k,) or not jnp.issubdtype(back.dtype, jnp.integer):
        raise TypeError(
            f"{who}: closure_back has shape {back.shape} and dtype {back.dtype}; the "
            f"closure stack has {k} rows: give ({k},) integers"
        )
    if active.shape != (k,) or active.dtype != jnp.bool_:
        raise TypeError(
            f"{who}: closure_active has shape {active.shape} and dtype "
            f"{active.dtype}; the closure stack has {k} rows: give ({k},) booleans, "
            "false for an absent closure"
        )
    return back, active


def _step_factors(who, lag, state, transition_rows, measurement_rows, active):
    """`update_rows`' step as factors: `init`'s stacks (kept in the state)
    with the given rows, measurement rows masked by `active`."""
    _check_state(who, lag, state)
    trans0, *meas0 = state.templates
    if isinstance(measurement_rows, dict):
        measurement_rows = (measurement_rows,)
    if not isinstance(measurement_rows, (tuple, list)):
        raise TypeError(
            f"{who}: measurement_rows must be a tuple of dicts, one per measurement "
            f"stack, got {type(measurement_rows).__name__}"
        )
    if len(measurement_rows) != len(meas0):
        raise ValueError(
            f"{who}: measurement_rows has {len(measurement_rows)} stacks, init was "
            f"given {len(meas0)}; give one dict per stack, in init's order"
        )
    if active is None:
        active = (None,) * len(meas0)
    if not isinstance(active, (tuple, list)) or len(active) != len(meas0):
        got = (
            f"{len(active)} of them"
            if isinstance(active, (tuple, list))
            else f"a {type(active).__name__}"
        )
        raise ValueError(
            f"{who}: active must be None or a tuple of one (k,) boolean array per "
            f"measurement stack ({len(meas0)} of them), got {got}"
        )
    transition = with_rows(
        trans0, _checked_rows(who, "transition_rows", transition_rows, trans0)
    )
    measurements = []
    for j, (rows, template, mask) in enumerate(zip(measurement_rows, meas0, active)):
        factor = with_rows(
            template, _checked_rows(who, f"measurement_rows[{j}]", rows, template)
        )
        if template.noise.active_rows() is not None:
            # `mask_rows` would combine init's mask with every step's.
            raise TypeError(
                f"{who}: init's measurement stack {j} ({type(template).__name__}) "
                f"has masked noise ({template.noise.name}); its mask would hold for "
                "every step. Give init the stack's unmasked noise (every row of "
                "x_0 counts), mask the steps' rows with `active`, or use `update`"
            )
        if mask is not None:
            mask = jnp.asarray(mask)
            k = template.num_rows
            if mask.shape != (k,) or mask.dtype != jnp.bool_:
                raise TypeError(
                    f"{who}: active[{j}] has shape {mask.shape} and dtype "
                    f"{mask.dtype}; measurement stack {j} has {k} rows: give ({k},) "
                    "booleans, false for a missing row"
                )
            factor = eqx.tree_at(
                lambda f: f.noise, factor, factor.noise.mask_rows(mask)
            )
        measurements.append(factor)
    return transition, tuple(measurements)


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
    `jax.vmap` over robots apply. Every `update` runs one compiled program
    (the state has the same shapes after every step), also when it is not
    wrapped in a `jit`; `init` compiles `update_rows`' program (unless its
    measurement noise is masked), so a robot's loop of `update_rows`
    compiles once, in `init`, and `update` compiles on its first call.

    Loop closures: give `init` a closure stack (a two-state factor such as
    [`eqsmooth.factors.BetweenFactor`][] of `k` rows, linking `(x_t-back, x_t)`) and
    `max_back`; each update then takes `k` closures from the new state back
    to states still in the window, `closure_back` steps back (data: any
    offset in `1..max_back` runs the same compiled program), absent ones
    masked. A closure enters the window with its new state and is
    marginalised with its earlier one, as in the scan's `closures`, so a run
    of updates equals the scan with those closures (tested to 1e-10) when
    `max_back` is the scan's longest closure. With closures the window's
    normal matrix is banded (no factor links states more than `max_back`
    apart; by default it is solved by a block Cholesky in blocks of
    `max_back + 1` states, dense for a short window), and the prior spans
    the window's first `max_back` states: keep `max_back` as short as the
    robot's closures allow.

    `update_rows` is the same update with the step's data as arrays, for a
    robot's loop: no factor objects per step and no Python checks per call
    (they run while the update is traced); the state and the estimate stay
    on the device.

    **Arguments:**

    - `lag`, `solver`, `adjoint`, `prediction_steps`, `max_steps`: as for
        [`eqsmooth.filters.fixed_lag_smoother`][].
        A lag in seconds, as GTSAM gives it: `lag=`
        [`eqsmooth.filters.lag_from_seconds`][]`(smoother_lag, dt)`.
    - `throw`: whether an update with non-finite step data or a failed
        window solve raises an `EquinoxRuntimeError` (the default). With
        `throw=False` the update's program holds no error check (no host
        callback, so JAX's persistent compilation cache can keep it, and
        each call is cheaper) and `state.result` says what went wrong.
    """

    lag: int = eqx.field(static=True)
    solver: AbstractGraphSolver = LevenbergMarquardt()
    adjoint: AbstractAdjoint = ImplicitAdjoint()
    prediction_steps: int = eqx.field(static=True, default=1)
    max_steps: int = eqx.field(static=True, default=100)
    throw: bool = eqx.field(static=True, default=True)

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
        closures: AbstractFactor | None = None,
        max_back: int | None = None,
    ) -> tuple[FixedLagState, PyTree]:
        """The state after the first time step.

        **Arguments:**

        - `initial_mean`, `initial_covariance`: the Gaussian belief on `x_0`.
        - `transition`: a one-row transition of the kind every update will
            give (its data is not used: `x_0` has no predecessor).
        - `measurements`: the measurement stacks of `x_0` (none by default;
            every update must then give the same stacks, with the same rows).
        - `closures`: `None` (no loop closures), or a closure stack of the
            kind every update will give: a factor of `k` rows on two states,
            its first variable the earlier state `x_t-back`, its second the
            new state `x_t` (its data is not used: `x_0` has no closure).
        - `max_back`: the furthest a closure may reach back, `1 ≤ max_back ≤
            lag − 1` (default `lag − 1`, with closures): the prior on the
            window spans its first `max_back` states (as the scan's prior
            spans its longest closure).

        **Returns:** `(state, estimate of x_0)`.
        """
        who = "FixedLagSmoother.init"
        transition, measurements, group = _check_step(
            who, transition, measurements, None
        )
        d = tangent_dim(initial_mean)
        cov0 = checked_covariance(who, initial_covariance, d)
        step = _step_rows(transition, measurements, initial_mean, cov0.dtype)
        n = self.lag + 1  # time steps kept: the window and the state leaving it
        tile = lambda tree: jax.tree_util.tree_map(  # noqa: E731
            lambda a: jnp.concatenate([a] * n, axis=0), tree
        )
        window = jax.tree_util.tree_map(
            lambda a: jnp.broadcast_to(a, (self.lag, *jnp.shape(a))), initial_mean
        )
        S, kept, refused = self._closure_reach(who, closures, max_back, group), (), None
        if closures is not None:
            k, fields = closures.num_rows, per_row_fields(closures)
            m = residual_dim(closures, fields, initial_mean, initial_mean)
            zero = jnp.zeros((k * n, m, m), cov0.dtype)  # no closure yet
            kept = (tile(fields), zero, jnp.zeros(k * n, int))
            refused = jnp.zeros(k, bool)
        floor = floor_of(step[0][1][0], S) if S > 1 else None
        state = FixedLagState(
            jnp.array(-1),
            window,
            jnp.array(0),
            initial_prior(S, initial_mean, cov0, floor),
            tile(step),
            (transition, *measurements),
            RESULTS.successful,
            closures,
            kept,
            refused,
        )
        # NumPy leaves (the result code, NumPy data in the templates) as JAX
        # arrays: the state then takes `update_rows`' `jax.jit` entry, as
        # the states of the updates do.
        state = jax.tree_util.tree_map(
            lambda a: jnp.asarray(a) if isinstance(a, np.ndarray) else a, state
        )
        none = () if closures is None else (np.zeros(k, int), np.zeros(k, bool))
        if any(f.noise.active_rows() is not None for f in measurements) or (
            closures is not None and closures.noise.active_rows() is not None
        ):
            closure = None if closures is None else (closures, *none)
            return _advance(self, state, transition, measurements, step, closure)
        # `update_rows`' program, so that its first call compiles nothing new.
        rows = tuple(_data_rows(f, per_row_fields(f)) for f in measurements)
        trans_rows = _data_rows(transition, per_row_fields(transition))
        if closures is None:
            return self.update_rows(state, trans_rows, rows)
        closure_rows = _data_rows(closures, per_row_fields(closures))
        return self.update_rows(state, trans_rows, rows, None, closure_rows, *none)

    def _closure_reach(self, who, closures, max_back, group) -> int:
        """The prior's span `S`: `max_back` with closures, else 1."""
        if closures is None:
            if max_back is not None:
                raise ValueError(
                    f"{who}: max_back={max_back!r} is given without closures; it "
                    "bounds the closures' reach (give init a closure stack)"
                )
            return 1
        _check_closure_stack(who, closures, group, None)
        if self.lag < 2:
            raise ValueError(
                f"{who}: closures need lag >= 2 (a closure links two states of the "
                f"window), this smoother has lag={self.lag}"
            )
        if max_back is None:
            return self.lag - 1
        if (
            isinstance(max_back, bool)
            or not isinstance(max_back, (int, np.integer))
            or not 1 <= max_back <= self.lag - 1
        ):
            raise ValueError(
                f"{who}: max_back must be an int in 1..lag - 1 = {self.lag - 1} (a "
                f"closure reaches back inside the window), got {max_back!r}"
            )
        return int(max_back)

    def update(
        self,
        state: FixedLagState,
        transition: AbstractFactor,
        measurements: AbstractFactor | Sequence[AbstractFactor] = (),
        closures: AbstractFactor | None = None,
        closure_back: Int[ArrayLike, " k"] | None = None,
    ) -> tuple[FixedLagState, PyTree]:
        """Add the next state: its transition from the newest state, its
        measurements and (if `init` took closures) its closures; solve the
        window.

        `closures` is a stack of the kind and row count `init` was given
        (absent rows masked with [`eqsmooth.factors.MaskedNoise`][]) and
        `closure_back` a `(k,)` integer array: row `j` links the state
        `closure_back[j]` steps back to the new one.

        **Returns:** `(state, estimate of the new state given everything so
        far)`; `state.window` holds the whole window's estimates.
        """
        who = "FixedLagSmoother.update"
        _check_state(who, self.lag, state)
        transition, measurements, group = _check_step(
            who, transition, measurements, None
        )
        closure = None
        if (closures is None) != (state.closure_template is None):
            raise ValueError(
                f"{who}: "
                + (
                    "init was given a closure stack: give closures (absent ones "
                    "masked) and closure_back every step"
                    if closures is None
                    else "closures given, but init was given no closure stack"
                )
            )
        if closures is not None:
            template = state.closure_template
            _check_closure_stack(who, closures, group, template.num_rows)
            _checked_rows(who, "closures", per_row_fields(closures), template)
            mask = closures.noise.active_rows()
            back, mask = _host_back(
                who, closure_back, mask, template.num_rows, _reach(state)
            )
            closure = (closures, *_checked_back(who, template.num_rows, back, mask))
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
        return _advance(self, state, transition, measurements, step, closure)

    def update_rows(
        self,
        state: FixedLagState,
        transition_rows: dict[str, PyTree[ArrayLike]],
        measurement_rows: Sequence[dict[str, PyTree[ArrayLike]]] = (),
        active: Sequence[Bool[ArrayLike, " _k"] | None] | None = None,
        closure_rows: dict[str, PyTree[ArrayLike]] | None = None,
        closure_back: Int[ArrayLike, " k"] | None = None,
        closure_active: Bool[ArrayLike, " k"] | None = None,
    ) -> tuple[FixedLagState, PyTree]:
        """`update` with the step's data as arrays: one compiled call, no
        factor objects built and nothing read back to the host.

        The step's factors are `init`'s stacks (kept in `state.templates`)
        with their per-row data replaced by these rows, so their noise,
        shared fields (learned parameters) and row counts serve every step;
        a step with other noise takes `update`. On the same data a run of
        `update_rows` gives `update`'s estimates (tested to 1e-10). The
        fields, shapes and dtypes are checked while the update is traced
        (a wrong one raises naming the stack and the field), so a compiled
        call does no Python work; a non-finite value stops the update with
        an `EquinoxRuntimeError`, as in `update`.

        **Arguments:**

        - `state`: the state from `init` or the previous update.
        - `transition_rows`: the new transition's per-row data, a dict
            `{field: array with a leading row axis of 1}` as
            [`eqsmooth.factors.per_row_fields`][] gives it for the
            transition `init` was given (e.g. `{"measured": SE2}` for a
            `BetweenFactor`; a field without data, `data=None`, may be left
            out).
        - `measurement_rows`: one such dict per measurement stack given to
            `init`, in that order (leading axis: the stack's `k_j` rows).
        - `active`: `None` (every row counts) or, per measurement stack, a
            `(k_j,)` boolean array (or `None`), false for a missing row:
            the row then adds nothing, exactly as a
            [`eqsmooth.factors.MaskedNoise`][] row in `update` (its data must
            still be finite). Give arrays, not Python booleans, so that every
            mask runs the same compiled program.
        - `closure_rows`, `closure_back`, `closure_active` (with a closure
            stack in `init`, every step): the `k` closures' per-row data (a
            dict as for the measurements), a `(k,)` integer array of how
            many steps back each reaches (`1..max_back`, and not before
            `x_0`), and `None` (all present) or `(k,)` booleans, false for
            an absent closure (its data must still be finite; its
            `closure_back` is not read). An active closure reaching
            outside the window raises (`throw=True`; from NumPy offsets
            before the call, naming the row) or is left out and flagged in
            `state.closure_refused` (`throw=False`).

        **Returns:** `(state, estimate of the new state given everything so
        far)`, both on the device; `state.window` holds the whole window's
        estimates.
        """
        # One form per step structure (fields without data left out, no
        # masks as None), so that `init`'s compiled program serves it.
        templates = state.templates if isinstance(state, FixedLagState) else ()
        k = len(templates) - 1
        if isinstance(measurement_rows, (tuple, list)) and len(measurement_rows) == k:
            transition_rows = _data_rows(templates[0], transition_rows)
            measurement_rows = tuple(
                _data_rows(f, r) for f, r in zip(templates[1:], measurement_rows)
            )
        if isinstance(active, (tuple, list)) and len(active) == k:
            active = None if all(a is None for a in active) else active
        closure = None
        template = getattr(state, "closure_template", None)
        if template is not None or closure_rows is not None:
            who = "FixedLagSmoother.update_rows"
            if template is not None:
                if closure_rows is None:
                    closure_back = None  # refused below, with the way
                k = template.num_rows
                closure_back, closure_active = _host_back(
                    who, closure_back, closure_active, k, _reach(state)
                )
                closure_rows = _data_rows(template, closure_rows)
            if isinstance(closure_back, np.ndarray):  # checked on the host above
                closure_back = jnp.asarray(closure_back)
            if isinstance(closure_active, np.ndarray):
                closure_active = jnp.asarray(closure_active)
            closure = (closure_rows, closure_back, closure_active)
        args = (self, state, transition_rows, measurement_rows, active, closure)
        if not all_arrays(args):
            return _advance_rows(*args)
        if not self.throw:
            return _advance_rows_of_arrays(*args)
        leaves = jax.tree_util.tree_leaves(args)
        if any(isinstance(x, jax.core.Tracer) for x in leaves):
            return _advance_rows(*args)  # under the caller's jit: error_if
        # Concrete: the program without error checks, through `jax.jit`'s
        # C++ dispatch, and the checks on the host after it.
        new, newest = _advance_rows_of_arrays(*args, quiet=True)
        _raise_on_host(new, "FixedLagSmoother.update_rows")
        return new, newest


# One compiled program for `init` and every `update` of a smoother (the state
# has the same shapes before and after each step), also when `update` is
# not wrapped in a `jit`; under a caller's `jit` it is inlined.
@eqx.filter_jit
def _advance(smoother, state, transition, measurements, step, closure):
    who = "FixedLagSmoother.init/update"
    return _solve_step(smoother, state, transition, measurements, step, closure, who)


def _update_rows(
    smoother,
    state,
    transition_rows,
    measurement_rows,
    active,
    closure=None,
    quiet=False,
):
    who = "FixedLagSmoother.update_rows"
    transition, measurements = _step_factors(
        who, smoother.lag, state, transition_rows, measurement_rows, active
    )
    if closure is not None:
        closure = _step_closures(who, state, *closure)
    mean = jax.tree_util.tree_map(lambda a: a[0], state.window)
    step = _step_rows(transition, measurements, mean, state.prior[1].dtype)
    throw = smoother.throw and not quiet
    return _solve_step(
        smoother, state, transition, measurements, step, closure, who, throw
    )


_NONFINITE_STEP = (
    "non-finite factor data or noise in this step's rows, or non-finite "
    "residuals in the window's solve"
)
_REFUSED_CLOSURE = (
    "a closure reaches outside the window: closure_back must be in 1..max_back "
    "(init's) and not reach before x_0 (at most the new state's time); mask an "
    "absent closure with closure_active"
)


def _raise_on_host(state: "FixedLagState", who: str) -> None:
    """`throw=True` of an update run without error checks: raise an
    `EquinoxRuntimeError` naming the failure, read from the new state's
    result code and refused closures (concrete arrays, read on the host)."""
    if state.closure_refused is not None and np.any(np.asarray(state.closure_refused)):
        rows = np.flatnonzero(np.asarray(state.closure_refused)).tolist()
        raise eqx.EquinoxRuntimeError(f"{who}: {_REFUSED_CLOSURE} (rows {rows})")
    code = np.asarray(result_index(state.result))
    if code != result_index(RESULTS.successful):
        if code == result_index(RESULTS.nonfinite_problem):
            message = _NONFINITE_STEP
        else:
            message = RESULTS[state.result]
        raise eqx.EquinoxRuntimeError(f"{who}: {message}")


# `update_rows`: the step's factors are built while tracing, so a call is
# one dispatch of one compiled program (no Python checks once compiled).
# Two entry points to it: without error checks (`throw=False`) and when
# every leaf of the arguments is a JAX array (a robot's loop: the state and
# rows from the previous call), `jax.jit` dispatches in C++, which costs
# less per call than `eqx.filter_jit`'s partition of the arguments (the
# smoother, the state's factor templates) into arrays and the rest;
# anything else goes through `eqx.filter_jit`, which treats non-array leaves
# as static and turns a failed check into an `EquinoxRuntimeError`.
_advance_rows = eqx.filter_jit(_update_rows)
_advance_rows_of_arrays = jax.jit(_update_rows, static_argnames=("quiet",))


def _closure_step(state, closure, t):
    """The new closures' kept rows `(data, R, back)` (refused and absent ones
    with zero `R` and `back`), and which active ones were refused."""
    factor, back, active = closure
    back = back.astype(state.closure_rows[2].dtype)
    reach = jnp.minimum(_reach(state), t)  # inside the window, not before x_0
    refused = active & ((back < 1) | (back > reach))
    keep = active & ~refused
    mean = jax.tree_util.tree_map(lambda a: a[0], state.window)
    fields = per_row_fields(factor)
    m = residual_dim(factor, fields, mean, mean)
    R, _ = row_whitening(factor, m, state.prior[1].dtype)
    R = jnp.where(keep[:, None, None], R, jnp.zeros((), R.dtype))
    return (fields, R, jnp.where(keep, back, jnp.zeros((), back.dtype))), refused


def _solve_step(
    smoother, state, transition, measurements, step, closure, who, throw=None
):
    """Write the step's rows into the state, and solve the new window (with
    error checks in the program when `throw`, by default the smoother's)."""
    throw = smoother.throw if throw is None else throw
    lag = smoother.lag
    t = state.t + 1
    kept, refused, links = state.closure_rows, state.closure_refused, ()
    new = step
    if closure is not None:
        entry, refused = _closure_step(state, closure, t)
        new = (step, entry)
    if throw:
        t, bad = _finite(new, t, who), jnp.array(False)
        if closure is not None:
            t = eqx.error_if(t, jnp.any(refused), f"{who}: {_REFUSED_CLOSURE}")
    else:
        bad = _nonfinite(new)
    vt = jnp.minimum(t, lag)  # the new state's slot among the kept steps
    rows = _write(state.rows, step, vt, t > lag)
    if closure is not None:
        kept = _write(kept, entry, vt, t > lag)
        links = (kept_links(closure[0], *kept, lag + 1, _reach(state)),)
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
        links=links,
        group=transition.variables[0].group,
        T=lag + 1,
        S=_reach(state),
    )
    carry, (window, start, prior, result) = window_step(
        model,
        lag,
        smoother.solver,
        smoother.adjoint,
        smoother.prediction_steps,
        (state.window, state.prior),
        vt,
        smoother.max_steps,
        throw,
    )
    newest = jax.tree_util.tree_map(lambda a: a[vt - start], window)
    result = RESULTS.where(bad, RESULTS.nonfinite_problem, result)
    new = FixedLagState(
        t,
        window,
        t - vt + start,
        prior,
        rows,
        state.templates,
        result,
        state.closure_template,
        kept,
        refused,
    )
    return new, newest
