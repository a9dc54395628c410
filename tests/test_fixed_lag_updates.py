"""The fixed-lag smoother one update at a time (`FixedLagSmoother.init`,
`update`, `update_rows`): tied to the scan of test_fixed_lag and to finite
differences. A file of its own so that the test workers share the work."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest
from hostile import raises
from test_filters import (
    _linear_problem,
    _se2_initial,
    _se2_meas,
    _se2_problem,
    _se2_trans,
    F_MAT,
    M0,
    P0,
    Q_COV,
    T,
)
from test_fixed_lag import _check_gradient, _GN, _run, _run_links, _UNROLLED

import eqsmooth as eqs


# --- one update at a time ------------------------------------------------------


def _se2_steps(meas_scale):
    """The SE(2) problem's factors split into per-step stacks with fixed ids;
    the transition's noise differs per step (so that a transition row read
    at the wrong step changes the answer)."""
    trans, meas, truth = _se2_problem(meas_scale, 1.0)
    per_step = (1.0 + 0.3 * jnp.arange(T - 1.0))[:, None] * trans.noise.sqrt_precision[
        None
    ]
    trans = eqx.tree_at(
        lambda f: f.noise, trans, eqs.DiagonalNoise(sqrt_precision=per_step)
    )
    one = (eqs.Var("s", [0]), eqs.Var("s", [1]))
    step_trans = [
        eqs.FunctionFactor(
            _se2_trans, one, eqs.DiagonalNoise(sqrt_precision=per_step[t : t + 1])
        )
        for t in range(T - 1)
    ]
    step_meas = [
        eqs.FunctionFactor(
            _se2_meas,
            one[:1],
            eqs.IsotropicNoise(sqrt_precision=meas.noise.sqrt_precision[t : t + 1]),
            data=meas.data[t : t + 1],
        )
        for t in range(T)
    ]
    return (trans, meas, truth), step_trans, step_meas


def _updates(smoother, step_trans, step_meas, mean0, cov0):
    state, first = smoother.init(mean0, cov0, step_trans[0], step_meas[0])
    update = eqx.filter_jit(smoother.update)
    out = [first]
    starts = [int(state.window_start)]
    for t in range(1, T):
        state, x = update(state, step_trans[t - 1], step_meas[t])
        out.append(x)
        starts.append(int(state.window_start))
    stack = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *out)
    return stack, state, starts


@pytest.mark.parametrize("lag", [1, 3])
def test_updates_equal_the_scan(lag):
    (trans, meas, truth), step_trans, step_meas = _se2_steps(1.0)
    mean0, cov0 = _se2_initial(truth)
    smoother = eqs.filters.FixedLagSmoother(lag=lag, solver=_GN, adjoint=_UNROLLED)
    online, state, starts = _updates(smoother, step_trans, step_meas, mean0, cov0)
    sol = _run(trans, meas, mean0, cov0, lag, _GN, _UNROLLED)
    np.testing.assert_allclose(eqs.local(online, sol.mean, batch_ndim=1), 0, atol=1e-10)
    last = jax.tree_util.tree_map(lambda a: a[-1], sol.windows)
    np.testing.assert_allclose(
        eqs.local(state.window, last, batch_ndim=1), 0, atol=1e-10
    )
    assert starts == np.asarray(sol.window_start).tolist()
    assert int(state.t) == T - 1


@pytest.mark.slow
def test_updates_gradient_matches_central_differences():
    # Slow (reverse mode through a Python loop of updates, several minutes
    # on 2 cores); update_rows' gradient test below differentiates the same
    # compiled step by default.
    def loss(scale):
        (_, _, truth), step_trans, step_meas = _se2_steps(scale)
        mean0, cov0 = _se2_initial(truth)
        online, _, _ = _updates(
            eqs.filters.FixedLagSmoother(lag=2, solver=_GN, adjoint=_UNROLLED),
            step_trans,
            step_meas,
            mean0,
            cov0,
        )
        err = online["pose"].translation() - truth["pose"].translation()
        return jnp.sum(err**2)

    _check_gradient(loss, 1e-7)


def test_updates_hostile_input():
    (_, meas, truth), step_trans, step_meas = _se2_steps(1.0)
    mean0, cov0 = _se2_initial(truth)
    with raises(ValueError, "lag must be an int >= 1", "0"):
        eqs.filters.FixedLagSmoother(lag=0)
    smoother = eqs.filters.FixedLagSmoother(lag=2)
    trans0 = step_trans[0]
    masked = eqx.tree_at(
        lambda f: f.noise, trans0, eqs.MaskedNoise(trans0.noise, jnp.ones(1, bool))
    )
    with raises(TypeError, "FixedLagSmoother.init", "transition's rows cannot be"):
        smoother.init(mean0, cov0, masked, step_meas[0])
    with raises(ValueError, "the transition FunctionFactor must be one row", "2 rows"):
        two = eqs.FunctionFactor(
            _se2_trans,
            (eqs.Var("s", [0, 1]), eqs.Var("s", [1, 2])),
            meas.noise.__class__(sqrt_precision=jnp.asarray(1.0)),
        )
        smoother.init(mean0, cov0, two, step_meas[0])
    state, _ = smoother.init(mean0, cov0, trans0, step_meas[0])
    with raises(ValueError, "differ in kind or row count"):
        smoother.update(state, trans0, (step_meas[1], step_meas[2]))
    # two rows where the state holds one per step (the buffer length is a
    # multiple of two: a divisibility check would let it through)
    rows2 = eqs.FunctionFactor(
        _se2_meas,
        (eqs.Var("s", [0, 0]),),
        eqs.IsotropicNoise(sqrt_precision=jnp.ones(2)),
        data=jnp.zeros((2, 2)),
    )
    with raises(ValueError, "differ in kind or row count"):
        smoother.update(state, trans0, rows2)
    bad = eqx.tree_at(lambda f: f.data, step_meas[1], step_meas[1].data * jnp.nan)
    with raises(eqx.EquinoxRuntimeError, "non-finite factor data"):
        smoother.update(state, trans0, bad)


def test_updates_name_another_lag_and_another_dtype():
    """A state from a smoother of another lag was blamed on "factors differ in
    kind"; a float32 step after a float64 init failed inside
    `lax.dynamic_update_slice`. Each now says what differs."""
    (_, _, truth), step_trans, step_meas = _se2_steps(1.0)
    mean0, cov0 = _se2_initial(truth)
    state, _ = eqs.filters.FixedLagSmoother(lag=2).init(
        mean0, cov0, step_trans[0], step_meas[0]
    )
    with raises(ValueError, "FixedLagSmoother.update", "lag=2", "lag=3"):
        eqs.filters.FixedLagSmoother(lag=3).update(state, step_trans[0], step_meas[1])
    f32 = jax.tree_util.tree_map(
        lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a,
        step_meas[1],
    )
    with raises(TypeError, "measurements[0] data has dtype float32", "float64"):
        eqs.filters.FixedLagSmoother(lag=2).update(state, step_trans[0], f32)


# --- masked rows and lags in seconds -------------------------------------------

_MISSING = (2, 4)  # the times whose GPS fix is masked


def _masked(factor, active):
    return eqx.tree_at(
        lambda f: f.noise, factor, eqs.MaskedNoise(factor.noise, jnp.asarray(active))
    )


@pytest.fixture(scope="module")
def dropped_fixes():
    """The SE(2) problem per step, the fixes' mask, and the scan without the
    masked fixes' rows (what masking must equal)."""
    (trans, meas, truth), step_trans, step_meas = _se2_steps(1.0)
    mean0, cov0 = _se2_initial(truth)
    keep = np.ones(T, bool)
    keep[list(_MISSING)] = False
    dropped = eqs.FunctionFactor(
        meas.fn,
        (eqs.Var("s", np.flatnonzero(keep)),),
        eqs.IsotropicNoise(sqrt_precision=meas.noise.sqrt_precision[keep]),
        data=meas.data[keep],
    )
    want = _run(trans, dropped, mean0, cov0, 3, _GN, _UNROLLED)
    return (trans, meas, mean0, cov0), (step_trans, step_meas), keep, want


def test_masked_measurements_are_dropped_measurements(dropped_fixes):
    """A `MaskedNoise` row adds nothing: the scan with masked fixes equals
    the scan without those rows (every field)."""
    (trans, meas, mean0, cov0), _, keep, want = dropped_fixes
    got = _run(trans, _masked(meas, keep), mean0, cov0, 3, _GN, _UNROLLED)
    for field in ("mean", "lagged_mean", "windows", "prior_mean"):
        a, b = getattr(got, field), getattr(want, field)
        np.testing.assert_allclose(
            eqs.local(a, b, batch_ndim=jnp.ndim(b["vel"]) - 1), 0, atol=1e-10
        )
    np.testing.assert_allclose(
        got.prior_covariance, want.prior_covariance, rtol=0, atol=1e-10
    )


def test_masked_updates_are_dropped_measurements(dropped_fixes):
    """A run of updates whose missing fixes are masked (one row per step,
    `MaskedNoise(noise, [False])`) equals the scan without them."""
    (_, _, mean0, cov0), (step_trans, step_meas), keep, want = dropped_fixes
    smoother = eqs.filters.FixedLagSmoother(lag=3, solver=_GN, adjoint=_UNROLLED)
    steps = [_masked(f, [bool(keep[t])]) for t, f in enumerate(step_meas)]
    online, _, _ = _updates(smoother, step_trans, steps, mean0, cov0)
    np.testing.assert_allclose(
        eqs.local(online, want.mean, batch_ndim=1), 0, atol=1e-10
    )


@pytest.mark.slow
def test_updates_without_measurements_are_all_masked(dropped_fixes):
    """Odometry only: updates without a measurement stack equal the scan with
    every fix masked."""
    (trans, meas, mean0, cov0), (step_trans, _), _, _ = dropped_fixes
    none = _run(trans, _masked(meas, np.zeros(T, bool)), mean0, cov0, 3, _GN, _UNROLLED)
    smoother = eqs.filters.FixedLagSmoother(lag=3, solver=_GN, adjoint=_UNROLLED)
    state, first = smoother.init(mean0, cov0, step_trans[0])
    update = eqx.filter_jit(smoother.update)
    out = [first]
    for t in range(1, T):
        state, x = update(state, step_trans[t - 1])
        out.append(x)
    online = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *out)
    np.testing.assert_allclose(
        eqs.local(online, none.mean, batch_ndim=1), 0, atol=1e-10
    )


def test_masked_row_needs_finite_data():
    trans, meas, _ = _linear_problem()
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    n = meas[0].num_rows
    bad = eqx.tree_at(lambda f: f.data, meas[0], meas[0].data.at[2].set(jnp.nan))
    bad = _masked(bad, np.arange(n) != 2)
    with raises(ValueError, "non-finite", "rows [2]", "finite placeholder"):
        eqs.filters.fixed_lag_smoother(trans, (bad, meas[1]), m0, p0, lag=2)


def test_lag_from_seconds_is_gtsams_window():
    # GTSAM keeps the states within smoother_lag of the newest and optimises
    # them with the new one (counted on gtsam.BatchFixedLagSmoother: after an
    # update it holds 3, 4, 3, 3 states for these).
    lag = eqs.filters.lag_from_seconds
    assert [lag(2.0, 1.0), lag(0.3, 0.1), lag(0.25, 0.1), lag(1.0, 0.5)] == [4, 5, 4, 4]
    assert lag(0.0, 0.1) == 2
    assert lag(8, 1) == 10  # the benchmarks' GTSAM lag L - 2 for lag L = 10
    with raises(ValueError, "lag_from_seconds", "dt must be > 0", "0.0"):
        lag(1.0, 0.0)
    with raises(ValueError, "smoother_lag must be >= 0", "-1.0"):
        lag(-1.0, 0.1)
    with raises(ValueError, "dt must be finite", "nan"):
        lag(1.0, float("nan"))
    # (the jaxtyping hook names the parameter first; without it, the
    # function's own check says "must be a number of seconds")
    with raises(jaxtyping.TypeCheckError, "smoother_lag"):
        lag("2s", 0.1)  # type: ignore[arg-type]


# --- update_rows: each step's data as arrays ---------------------------------

_ROWS_SMOOTHER = eqs.filters.FixedLagSmoother(lag=2, solver=_GN, adjoint=_UNROLLED)


@pytest.fixture(scope="module")
def row_steps():
    """The linear chain of test_filters one step at a time: a transition
    (no per-row data), a 1-row position stack and a 2-row 2-D stack per
    step; each step's data as `update_rows` takes it, and masks for both
    stacks (a missing position at `_MISSING`, every other second row)."""
    from test_filters import _lin_meas, _lin_trans, H1, R2_COV

    one = (eqs.Var("x", [0]), eqs.Var("x", [1]))
    sqrt_info = eqs.SqrtInformationNoise.from_covariance
    trans = eqs.FunctionFactor(
        _lin_trans, one, sqrt_info(jnp.asarray(Q_COV)), params=jnp.asarray(F_MAT)
    )
    stacks = (
        eqs.FunctionFactor(
            _lin_meas,
            one[1:],
            eqs.IsotropicNoise.from_sigma(jnp.asarray([0.3])),
            data=jnp.zeros((1, 1)),
            params=jnp.asarray(H1),
        ),
        eqs.FunctionFactor(
            _lin_meas,
            (eqs.Var("x", [1, 1]),),
            sqrt_info(jnp.asarray(R2_COV)),
            data=jnp.zeros((2, 2)),
            params=jnp.eye(2),
        ),
    )
    rng = np.random.default_rng(2)
    data = [jnp.asarray(rng.normal(size=(T, *f.data.shape))) for f in stacks]
    rows = [tuple({"data": z[t]} for z in data) for t in range(T)]
    active = [
        (jnp.asarray([t not in _MISSING]), jnp.asarray([True, t % 2 == 0]))
        for t in range(T)
    ]
    state0, _ = _ROWS_SMOOTHER.init(
        jnp.asarray(M0),
        jnp.asarray(P0),
        trans,
        [eqs.factors.with_rows(f, r) for f, r in zip(stacks, rows[0])],
    )
    return state0, (trans, stacks), rows, active


def _rows_run(state, rows, active=None):
    """`update_rows` for steps 1..T-1 (no transition rows: its data is
    `None`); the newest estimates and the last state."""
    out = []
    for t in range(1, T):
        mask = None if active is None else active[t]
        state, x = _ROWS_SMOOTHER.update_rows(state, {}, rows[t], mask)
        out.append(x)
    return jnp.stack(out), state


def _factor_run(state, factors, rows, active=None):
    """`update` for the same steps, with factors (masked rows: `MaskedNoise`)."""
    trans, stacks = factors
    out = []
    for t in range(1, T):
        step = [eqs.factors.with_rows(f, r) for f, r in zip(stacks, rows[t])]
        if active is not None:
            step = [_masked(f, a) for f, a in zip(step, active[t])]
        state, x = _ROWS_SMOOTHER.update(state, trans, step)
        out.append(x)
    return jnp.stack(out), state


def test_update_rows_equal_updates(row_steps, monkeypatch):
    """A run of `update_rows` gives `update`'s estimates and window (1e-10),
    on the device; its checks run while tracing only, and `init` (the
    fixture's) already traced and compiled its program."""
    state0, factors, rows, _ = row_steps
    want, want_state = _factor_run(state0, factors, rows)
    module = eqs.filters._fixed_lag_update
    traced, checks = [], module._step_factors
    monkeypatch.setattr(
        module, "_step_factors", lambda *a: traced.append(1) or checks(*a)
    )
    got, state = _rows_run(state0, rows)
    assert not traced  # init compiled update_rows' program: no trace here
    assert isinstance(got, jax.Array) and got.shape == (T - 1, 2)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
    np.testing.assert_allclose(state.window, want_state.window, rtol=0, atol=1e-10)
    assert int(state.t) == T - 1 and int(state.window_start) == T - 2


def test_update_rows_masks_are_masked_noise(row_steps):
    """`active` false for missing rows (of both stacks, one of two rows) equals
    `update` with those rows masked by `MaskedNoise` (1e-10), and differs
    from the run without masks."""
    state0, factors, rows, active = row_steps
    want, _ = _factor_run(state0, factors, rows, active)
    got, _ = _rows_run(state0, rows, active)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-10)
    every = [tuple(jnp.ones_like(a) for a in step) for step in active]
    unmasked, _ = _rows_run(state0, rows, every)
    assert float(jnp.abs(got - unmasked).max()) > 1e-3


def test_update_rows_gradient_matches_central_differences(row_steps):
    """`jax.grad` through three `update_rows` calls with respect to the
    measurements' data matches float64 central differences."""
    state0, _, rows, _ = row_steps
    direction = jnp.asarray(np.random.default_rng(3).normal(size=(3, 2, 2)))

    def loss(s):
        # Every call gets a state with a tangent (zero for the first), so the
        # three calls share one differentiated program (compile time).
        state = jax.tree_util.tree_map(
            lambda a: a + 0 * s if eqx.is_inexact_array(a) else a, state0
        )
        total = 0.0
        for t in range(1, 4):
            z = rows[t][1]["data"] + s * direction[t - 1]
            state, x = _ROWS_SMOOTHER.update_rows(state, {}, (rows[t][0], {"data": z}))
            total = total + jnp.sum(x**2)
        return total

    _check_gradient(loss, 1e-7)


def test_update_rows_hostile_input(row_steps):
    """Wrong fields, shapes, dtypes, masks and states are named while tracing;
    non-finite data stops the compiled update."""
    state, (trans, stacks), rows, _ = row_steps
    update = _ROWS_SMOOTHER.update_rows
    z, z2 = rows[1][0]["data"], rows[1][1]["data"]  # (1, 1), (2, 2)
    who = "FixedLagSmoother.update_rows"
    with raises(ValueError, who, "measurement_rows[1] has fields ['z']", "['data']"):
        update(state, {}, ({"data": z}, {"z": z2}))
    with raises(
        ValueError, who, "measurement_rows[0]['data'] has shape (2, 1)", "(1, 1)"
    ):
        update(state, {}, ({"data": jnp.concatenate([z, z])}, {"data": z2}))
    with raises(TypeError, "measurement_rows[1]['data'] has dtype float32", "float64"):
        update(state, {}, ({"data": z}, {"data": z2.astype(jnp.float32)}))
    with raises(TypeError, "measurement_rows[0]['data'] has the structure"):
        update(state, {}, ({"data": (z, z)}, {"data": z2}))
    with raises(ValueError, "transition_rows has fields ['params']", "['data']"):
        update(state, {"data": None, "params": z}, rows[1])
    with raises(ValueError, "measurement_rows has 1 stacks, init was given 2"):
        update(state, {}, rows[1][:1])
    with raises(ValueError, who, "active must be None or a tuple", "got 1 of them"):
        update(state, {}, rows[1], (None,))
    with raises(TypeError, "active[1] has shape (1,)", "2 rows"):
        update(state, {}, rows[1], (None, jnp.ones(1, bool)))
    with raises(ValueError, who, "lag=2", "lag=3"):
        eqs.filters.FixedLagSmoother(lag=3).update_rows(state, {}, rows[1])
    masked = [_masked(stacks[0], [True]), stacks[1]]
    mstate, _ = _ROWS_SMOOTHER.init(jnp.asarray(M0), jnp.asarray(P0), trans, masked)
    with raises(TypeError, who, "measurement stack 0", "masked noise", "`active`"):
        update(mstate, {}, rows[1])
    with raises(eqx.EquinoxRuntimeError, who, "non-finite factor data"):
        update(state, {}, ({"data": z * jnp.nan}, {"data": z2}))
    # The annotations name a wrong type first (the jaxtyping hook); the
    # update's own checks say it without the hook.
    with raises(jaxtyping.TypeCheckError, "measurement_rows"):
        update(state, {}, (z, z2))
    advance = eqs.filters._fixed_lag_update._advance_rows
    with raises(TypeError, who, "measurement_rows[0] must be a dict"):
        advance(_ROWS_SMOOTHER, state, {}, (z, z2), None)
    with raises(TypeError, who, "state must be a FixedLagState", "str"):
        advance(_ROWS_SMOOTHER, "state", {}, rows[1], None)
    with raises(TypeError, "active[0] has shape (1,) and dtype int"):
        advance(_ROWS_SMOOTHER, state, {}, rows[1], (jnp.ones(1, int), None))


def test_update_rows_without_throw_holds_no_host_callback(row_steps):
    """`throw=False`: the compiled update has no error check (no host
    callback, which JAX's persistent cache would refuse), gives the same
    estimates, and a non-finite step is reported in `state.result` instead
    of raising; with the default `throw=True` the check is there."""
    state0, _, rows, _ = row_steps
    quiet = eqs.filters.FixedLagSmoother(
        lag=2, solver=_GN, adjoint=_UNROLLED, throw=False
    )

    def program(smoother):
        update = lambda s, r: smoother.update_rows(s, {}, r)
        return str(eqx.filter_make_jaxpr(update)(state0, rows[1])[0])

    assert "callback" in program(_ROWS_SMOOTHER)
    assert "callback" not in program(quiet)
    state, want = _ROWS_SMOOTHER.update_rows(state0, {}, rows[1])
    state, got = quiet.update_rows(state0, {}, rows[1])
    np.testing.assert_allclose(got, want, rtol=0, atol=0)
    assert state.result == eqs.solve.RESULTS.successful
    bad = jax.tree_util.tree_map(lambda a: a.at[0].set(jnp.nan), rows[2])
    state, _ = quiet.update_rows(state, {}, bad)
    assert state.result == eqs.solve.RESULTS.nonfinite_problem
    with pytest.raises(eqx.EquinoxRuntimeError, match="non-finite"):
        _ROWS_SMOOTHER.update_rows(state0, {}, bad)


# --- loop closures in the online updates -------------------------------------

_CT, _CLAG, _CBACK = 10, 4, 3  # steps, lag, max_back of the closure chain


def _lin_link(a, b, data, params):
    return b - params @ a - data


@pytest.fixture(scope="module")
def closure_chain():
    """A linear 2-D chain of `_CT` steps, a position fix per step and two
    closure rows per step (`_lin_link`, x_t-back -> x_t) with offsets and a
    mask that vary; the scan's factors for the same data (the active
    closures only: their longest span is `_CBACK`, the smoother's
    `max_back`)."""
    from test_filters import _lin_meas, _lin_trans, H1

    rng = np.random.default_rng(7)
    sqrt_info = eqs.SqrtInformationNoise.from_covariance
    one = (eqs.Var("x", [0]), eqs.Var("x", [1]))
    trans = eqs.FunctionFactor(
        _lin_trans, one, sqrt_info(jnp.asarray(Q_COV)), params=jnp.asarray(F_MAT)
    )
    fix_noise = eqs.IsotropicNoise.from_sigma(jnp.asarray(0.3))
    fix = (
        lambda z: eqs.FunctionFactor(  # noqa: E731
            _lin_meas, one[1:], fix_noise, data=z, params=jnp.asarray(H1)
        )
    )
    P = jnp.asarray([[0.9, 0.2], [-0.1, 1.1]])
    link_noise = sqrt_info(jnp.asarray([[0.4, 0.1], [0.1, 0.3]]))
    pair = (eqs.Var("x", [0, 0]), eqs.Var("x", [1, 1]))
    link = eqs.FunctionFactor(
        _lin_link, pair, link_noise, data=jnp.zeros((2, 2)), params=P
    )
    z = jnp.asarray(rng.normal(size=(_CT, 1, 1)))
    cz = jnp.asarray(rng.normal(size=(_CT, 2, 2)))
    back = np.stack([1 + np.arange(_CT) % _CBACK, np.full(_CT, 2)], axis=1)
    back = np.minimum(back, np.arange(_CT)[:, None])  # not before x_0
    active = (back >= 1) & (np.arange(_CT)[:, None] % 3 != 1)
    active[:, 1] &= np.arange(_CT) % 2 == 0
    t, j = np.nonzero(active)
    full = lambda ids: eqs.Var("x", ids)  # noqa: E731
    scan = dict(
        trans=eqs.FunctionFactor(
            _lin_trans,
            (full(np.arange(_CT - 1)), full(np.arange(1, _CT))),
            sqrt_info(jnp.asarray(Q_COV)),
            params=jnp.asarray(F_MAT),
        ),
        meas=eqs.FunctionFactor(
            _lin_meas,
            (full(np.arange(_CT)),),
            fix_noise,
            data=z[:, 0],
            params=jnp.asarray(H1),
        ),
        links=eqs.FunctionFactor(
            _lin_link,
            (full(t - back[t, j]), full(t)),
            link_noise,
            data=cz[t, j],
            params=P,
        ),
    )
    assert int((back[t, j]).max()) == _CBACK
    smoother = eqs.filters.FixedLagSmoother(lag=_CLAG, solver=_GN, adjoint=_UNROLLED)
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    state0, x0 = smoother.init(m0, p0, trans, fix(z[0]), link, max_back=_CBACK)
    steps = [
        (({"data": z[t]},), {"data": cz[t]}, back[t], active[t]) for t in range(_CT)
    ]
    return smoother, state0, x0, steps, scan, (trans, fix, link)


def _closure_run(smoother, state, steps, first=1):
    out = []
    for rows, crows, back, active in steps[first:]:
        state, x = smoother.update_rows(state, {}, rows, None, crows, back, active)
        out.append(x)
    return jnp.stack(out), state


def test_update_rows_with_closures_equal_the_scan(closure_chain):
    """A run of `update_rows` with closures (offsets and masks changing every
    step) gives the scan's online estimates and last window (1e-10), and
    the scan without the masked closures; closures change the answer."""
    smoother, state0, x0, steps, scan, _ = closure_chain
    got, state = _closure_run(smoother, state0, steps)
    sol = _run_links(
        scan["trans"],
        scan["meas"],
        scan["links"],
        jnp.asarray(M0),
        jnp.asarray(P0),
        _CLAG,
        _GN,
        _UNROLLED,
    )
    np.testing.assert_allclose(x0, sol.mean[0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(got, sol.mean[1:], rtol=0, atol=1e-10)
    np.testing.assert_allclose(state.window, sol.windows[-1], rtol=0, atol=1e-10)
    assert not bool(state.closure_refused.any())
    none = [(r, c, b, np.zeros_like(a)) for r, c, b, a in steps]
    without, _ = _closure_run(smoother, state0, none)
    assert float(jnp.abs(got - without).max()) > 1e-2


def test_masked_closures_are_dropped_closures(closure_chain):
    """A masked closure adds nothing, whatever its offset and data: the run
    with junk offsets and data in the masked rows equals the plain run."""
    smoother, state0, _, steps, _, _ = closure_chain
    want, _ = _closure_run(smoother, state0, steps)
    junk = [
        (r, {"data": jnp.where(a[:, None], c["data"], 7.0)}, np.where(a, b, 99), a)
        for r, c, b, a in steps
    ]
    got, _ = _closure_run(smoother, state0, junk)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_update_with_closure_factors_equals_update_rows(closure_chain):
    """`update` with closure factors (absent rows masked by `MaskedNoise`)
    gives `update_rows`' estimates."""
    smoother, state0, _, steps, _, (trans, fix, link) = closure_chain
    want, _ = _closure_run(smoother, state0, steps[:5])
    state, out = state0, []
    for rows, crows, back, active in steps[1:5]:
        closures = _masked(eqs.factors.with_rows(link, crows), active)
        meas = fix(rows[0]["data"])
        state, x = smoother.update(state, trans, meas, closures, back)
        out.append(x)
    np.testing.assert_allclose(jnp.stack(out), want, rtol=0, atol=1e-10)


def test_closure_offsets_and_masks_compile_nothing(closure_chain):
    """`init` compiled `update_rows`' program: updates with any offsets and
    masks (NumPy or device arrays) compile nothing more."""
    from helpers import compiled_programs

    smoother, state0, _, steps, _, _ = closure_chain
    state = state0
    with compiled_programs() as names:
        for i, (rows, crows, back, active) in enumerate(steps[1:6]):
            if i % 2:
                back, active = jnp.asarray(back), jnp.asarray(~active & (back >= 1))
            state, x = smoother.update_rows(state, {}, rows, None, crows, back, active)
        jax.block_until_ready(x)
    assert names == [], names


def test_closures_hostile_input(closure_chain):
    """Closure stacks, rows, offsets and masks of the wrong kind are named;
    an active closure reaching outside the window raises (or, without
    `throw`, is left out and flagged)."""
    smoother, state0, _, steps, _, (trans, fix, link) = closure_chain
    rows, crows, back, active = steps[3]
    update, who = smoother.update_rows, "FixedLagSmoother.update_rows"
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    with raises(ValueError, who, "closure row 0 reaches 4 steps back", "max_back = 3"):
        update(state0, {}, rows, None, crows, np.array([4, 1]), active)
    with raises(TypeError, who, "closure_back has shape (3,)", "2 rows"):
        update(state0, {}, rows, None, crows, np.array([1, 1, 1]), None)
    # (the jaxtyping hook names a float offset first; without it, the
    # update's own check does, as `_advance_rows` below)
    with raises(jaxtyping.TypeCheckError, "closure_back"):
        update(state0, {}, rows, None, crows, np.array([1.0, 1.0]), None)
    with raises(TypeError, who, "give closure_rows and closure_back every step"):
        update(state0, {}, rows)
    with raises(ValueError, who, "closure_rows['data'] has shape (1, 2)", "(2, 2)"):
        update(state0, {}, rows, None, {"data": crows["data"][:1]}, back, active)
    advance = eqs.filters._fixed_lag_update._advance_rows
    with raises(TypeError, who, "closure_active has shape (2,) and dtype int64"):
        advance(smoother, state0, {}, rows, None, (crows, back, np.ones(2, int)))
    with raises(TypeError, "closure_back has shape (2,) and dtype float64"):
        advance(smoother, state0, {}, rows, None, (crows, back * 1.0, active))
    # reaching before x_0: known on the device only (state.t)
    with raises(eqx.EquinoxRuntimeError, who, "closure reaches outside the window"):
        update(state0, {}, rows, None, crows, jnp.asarray([2, 1]), jnp.ones(2, bool))
    quiet = eqs.filters.FixedLagSmoother(
        lag=_CLAG, solver=_GN, adjoint=_UNROLLED, throw=False
    )
    qstate, _ = quiet.init(m0, p0, trans, fix(rows[0]["data"]), link, max_back=_CBACK)
    qstate, x = quiet.update_rows(
        qstate, {}, rows, None, crows, jnp.asarray([2, 1]), jnp.ones(2, bool)
    )
    assert qstate.closure_refused.tolist() == [True, False]
    one = jnp.ones(2, bool).at[0].set(False)
    _, want = quiet.update_rows(
        quiet.init(m0, p0, trans, fix(rows[0]["data"]), link, max_back=_CBACK)[0],
        {},
        rows,
        None,
        crows,
        jnp.asarray([2, 1]),
        one,
    )
    np.testing.assert_allclose(x, want, rtol=0, atol=1e-12)
    init = smoother.init
    with raises(
        ValueError, "FixedLagSmoother.init", "max_back must be an int in 1..lag - 1 = 3"
    ):
        init(m0, p0, trans, fix(rows[0]["data"]), link, max_back=4)
    with raises(ValueError, "max_back=2 is given without closures"):
        init(m0, p0, trans, fix(rows[0]["data"]), max_back=2)
    with raises(ValueError, "closure factor FunctionFactor must link two states"):
        init(m0, p0, trans, fix(rows[0]["data"]), fix(rows[0]["data"]))
    with raises(ValueError, "closures need lag >= 2"):
        eqs.filters.FixedLagSmoother(lag=1).init(m0, p0, trans, (), link)
    plain, _ = smoother.init(m0, p0, trans, fix(rows[0]["data"]))
    with raises(ValueError, who, "init was given no closure stack"):
        update(plain, {}, rows, None, crows, back, active)
    with raises(ValueError, "FixedLagSmoother.update", "give closures"):
        smoother.update(state0, trans, fix(rows[0]["data"]))
    three = eqx.tree_at(
        lambda f: (f.variables, f.data),
        link,
        ((eqs.Var("x", [0] * 3), eqs.Var("x", [1] * 3)), jnp.zeros((3, 2))),
    )
    with raises(ValueError, "FixedLagSmoother.update", "has 3 rows, init's has 2"):
        smoother.update(state0, trans, fix(rows[0]["data"]), three, np.ones(3, int))


@pytest.mark.parametrize(
    "mode", ["forward", pytest.param("reverse", marks=pytest.mark.slow)]
)
def test_update_rows_closure_derivative_matches_central_differences(
    closure_chain, mode
):
    """The derivative through four `update_rows` calls with closures with
    respect to a closure measurement matches float64 central differences:
    forward mode by default, `jax.grad` among the slow tests (its compile,
    about 30 s on 2 cores)."""
    smoother, state0, _, steps, _, _ = closure_chain
    direction = jnp.asarray(np.random.default_rng(4).normal(size=(4, 2, 2)))

    def loss(s):
        state = jax.tree_util.tree_map(
            lambda a: a + 0 * s if eqx.is_inexact_array(a) else a, state0
        )
        total = 0.0
        for i, (rows, crows, back, active) in enumerate(steps[1:5]):
            c = {"data": crows["data"] + s * direction[i]}
            state, x = smoother.update_rows(state, {}, rows, None, c, back, active)
            total = total + jnp.sum(x**2)
        return total

    if mode == "reverse":
        _check_gradient(loss, 1e-7)
        return
    s, h = 1.3, 1e-5
    _, d = jax.jvp(loss, (s,), (1.0,))
    fd = (loss(s + h) - loss(s - h)) / (2 * h)
    assert abs(float(d)) > 1e-3
    np.testing.assert_allclose(float(d), float(fd), rtol=1e-7)
