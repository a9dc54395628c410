"""Fixed-lag smoother: tied to the Kalman filter, the batch smoother and
finite differences (the problems of test_filters)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest
from hostile import raises
from test_filters import (
    _linear_problem,
    _numpy_kalman,
    _se2_initial,
    _se2_problem,
    F_MAT,
    M0,
    P0,
    Q_COV,
    T,
)

import eqsmooth as eqs


@eqx.filter_jit
def _run(trans, meas, mean0, cov0, lag, solver, adjoint):
    return eqs.filters.fixed_lag_smoother(
        trans, meas, mean0, cov0, lag=lag, solver=solver, adjoint=adjoint
    )


_GN = eqs.FixedStepGaussNewton(num_steps=3)
_UNROLLED = eqs.solve.UnrolledAdjoint()


@pytest.mark.parametrize("lag", [1, 3])
def test_linear_chain_is_the_kalman_filter(lag):
    trans, meas, updates = _linear_problem()
    means, _, pmeans, *_ = _numpy_kalman(updates)
    sol = _run(trans, meas, jnp.asarray(M0), jnp.asarray(P0), lag, _GN, _UNROLLED)
    # The newest state is the filter's marginal, whatever the lag.
    np.testing.assert_allclose(sol.mean, means, rtol=0, atol=1e-10)
    # The prior on each window's first state is the exact marginal of what
    # left the window: the filter's prediction of that state.
    first = np.maximum(np.arange(T) - lag + 1, 0)
    _, covs, *_ = _numpy_kalman(updates)
    # The filter's predicted covariances: P0, then F P_t|t Fᵀ + Q.
    pred = [P0] + [F_MAT @ covs[k] @ F_MAT.T + Q_COV for k in range(T - 1)]
    np.testing.assert_allclose(sol.prior_mean, pmeans[first], rtol=0, atol=1e-10)
    np.testing.assert_allclose(
        sol.prior_covariance, np.stack(pred)[first], rtol=0, atol=1e-10
    )


def test_lag_T_is_the_batch_smoother():
    trans, meas, truth = _se2_problem(1.0, 1.0)
    mean0, cov0 = _se2_initial(truth)
    solver = eqs.FixedStepGaussNewton(num_steps=6)
    sol = _run(trans, meas, mean0, cov0, T, solver, _UNROLLED)
    prior = eqs.PriorFactor(
        eqs.Var("s", [0]),
        jax.tree_util.tree_map(lambda a: a[None], mean0),
        eqs.SqrtInformationNoise.from_covariance(cov0),
    )
    graph = eqs.FactorGraph([prior, trans, meas])
    init = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (T, *a.shape)), mean0)
    batch = eqs.least_squares(graph, {"s": init}, eqs.GaussNewton()).value["s"]
    last = jax.tree_util.tree_map(lambda a: a[-1], sol.windows)
    np.testing.assert_allclose(eqs.local(last, batch, batch_ndim=1), 0, atol=1e-6)
    # Every state is in the last window, so the lagged estimate is the batch one.
    np.testing.assert_allclose(
        eqs.local(sol.lagged_mean, batch, batch_ndim=1), 0, atol=1e-6
    )


def _check_gradient(loss, rtol):
    """`jax.grad(loss)` at 1.3 is not small and matches central differences
    (step 1e-5) to `rtol`."""
    s, h = 1.3, 1e-5
    g = jax.grad(loss)(s)
    fd = (loss(s + h) - loss(s - h)) / (2 * h)
    assert abs(float(g)) > 1e-3
    np.testing.assert_allclose(float(g), float(fd), rtol=rtol)


def _loss(scale, solver, adjoint, lag=3):
    trans, meas, truth = _se2_problem(scale, 1.0)
    mean0, cov0 = _se2_initial(truth)
    sol = _run(trans, meas, mean0, cov0, lag, solver, adjoint)
    err = sol.mean["pose"].translation() - truth["pose"].translation()
    return jnp.sum(err**2) + jnp.sum(sol.lagged_mean["vel"] ** 2)


@pytest.mark.parametrize(
    "solver, adjoint, rtol",
    [
        (eqs.FixedStepGaussNewton(num_steps=6), eqs.solve.UnrolledAdjoint(), 1e-7),
        # Exact at a stationary point: what is left is GaussNewton's tolerance.
        (eqs.GaussNewton(), eqs.solve.ImplicitAdjoint(), 1e-4),
        # The default: Levenberg-Marquardt, differentiated implicitly.
        (eqs.LevenbergMarquardt(), eqs.solve.ImplicitAdjoint(), 1e-4),
    ],
)
def test_gradient_matches_central_differences(solver, adjoint, rtol):
    _check_gradient(lambda s: _loss(s, solver, adjoint), rtol)


def test_hostile_input():
    trans, meas, updates = _linear_problem()
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    run = eqs.filters.fixed_lag_smoother
    with raises(ValueError, "lag must be an int >= 1", "0"):
        run(trans, meas, m0, p0, lag=0)
    with raises(ValueError, "lag 7", "6 states"):
        run(trans, meas, m0, p0, lag=T + 1)
    masked = eqx.tree_at(
        lambda f: f.noise, trans, eqs.MaskedNoise(trans.noise, jnp.ones(T - 1, bool))
    )
    with raises(TypeError, "transition's rows cannot be masked", "measurement"):
        run(masked, meas, m0, p0, lag=2)
    # (the test suite's jaxtyping hook checks the annotation first; without
    # it, the function's own check raises a TypeError naming the solver)
    with raises(jaxtyping.TypeCheckError, "fixed_lag_smoother", "parameter 'solver'"):
        run(trans, meas, m0, p0, lag=2, solver=eqs.BlockTridiagonal())
    with raises(ValueError, "initial_covariance", "(2, 2)"):
        run(trans, meas, m0, jnp.eye(3), lag=2)
    # A measurement past the chain's end reaches outside every window.
    late = eqs.FunctionFactor(
        meas[0].fn,
        (eqs.Var("x", [T]),),
        meas[0].noise,
        data=meas[0].data[:1],
        params=meas[0].params,
    )
    with raises(ValueError, "time indices up to 6"):
        run(trans, (late,), m0, p0, lag=2)
    bad = eqx.tree_at(lambda f: f.data, meas[0], meas[0].data.at[2].set(jnp.nan))
    with raises(ValueError, "non-finite", "rows [2]", "times [2]"):
        run(trans, (bad, meas[1]), m0, p0, lag=2)


def test_max_steps_reaches_the_window_solves():
    # A converging solver stopped after one iteration fails its window solve
    # (the limit is passed through, not least_squares' default of 100).
    trans, meas, truth = _se2_problem(1.0, 1.0)
    mean0, cov0 = _se2_initial(truth)

    @eqx.filter_jit
    def run(max_steps):
        return eqs.filters.fixed_lag_smoother(
            trans,
            meas,
            mean0,
            cov0,
            lag=3,
            solver=eqs.GaussNewton(),
            adjoint=_UNROLLED,
            max_steps=max_steps,
        ).mean

    with raises(eqx.EquinoxRuntimeError, "maximum number of steps"):
        run(1)


def test_vmap_over_sequences():
    trans, (meas1, meas2), _ = _linear_problem()
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    data = jnp.stack([meas1.data, meas1.data + 0.5])

    def one(z):
        m = eqx.tree_at(lambda f: f.data, meas1, z)
        return eqs.filters.fixed_lag_smoother(trans, (m, meas2), m0, p0, lag=2).mean

    batched = eqx.filter_jit(jax.vmap(one))(data)
    for i in range(2):
        np.testing.assert_allclose(batched[i], one(data[i]), rtol=0, atol=1e-12)


# --- closures (loop closures inside the window) --------------------------------


def _lin_link(a, b, data, params):
    return b - params @ a - data


def _linear_links(pairs):
    """Linear links `x_b − P x_a − z` between the given (a, b) time pairs."""
    rng = np.random.default_rng(1)
    a, b = (np.array(v) for v in zip(*pairs))
    z = rng.normal(size=(len(pairs), 2))
    P = np.array([[0.9, 0.2], [-0.1, 1.1]])
    cov = np.array([[0.4, 0.1], [0.1, 0.3]])
    link = eqs.FunctionFactor(
        _lin_link,
        (eqs.Var("x", a), eqs.Var("x", b)),
        eqs.SqrtInformationNoise.from_covariance(jnp.asarray(cov)),
        data=jnp.asarray(z),
        params=jnp.asarray(P),
    )
    return link, [(ai, bi, P, cov, zi) for ai, bi, zi in zip(a, b, z)]


def _numpy_posterior_means(updates, links, upto, p0=P0):
    """The exact posterior mean of x_0..x_upto given every factor on those
    states (dense information form)."""
    n = 2 * (upto + 1)
    H, g = np.zeros((n, n)), np.zeros(n)

    def add(rows, J, r0, cov):  # factor ‖J x[rows] + r0‖² with covariance cov
        W = np.linalg.inv(cov)
        idx = np.concatenate([np.arange(2 * k, 2 * k + 2) for k in rows])
        H[np.ix_(idx, idx)] += J.T @ W @ J
        g[idx] -= J.T @ W @ r0

    add([0], np.eye(2), -M0, p0)
    for k in range(upto):
        add([k, k + 1], np.hstack([-F_MAT, np.eye(2)]), np.zeros(2), Q_COV)
    for k in range(upto + 1):
        for Hm, Rm, z in updates[k]:
            add([k], Hm, -z, Rm)
    for a, b, P, cov, z in links:
        if max(a, b) <= upto:
            add([a, b], np.hstack([-P, np.eye(2)]), -z, cov)
    return np.linalg.solve(H, g).reshape(-1, 2)


@pytest.mark.parametrize(
    "lag, pairs, p0_scale",
    [
        (3, [(0, 2), (2, 4), (5, 3)], 1.0),
        (4, [(0, 2), (1, 4), (5, 3)], 1.0),
        # x_0 nearly known: the information floor of the states the prior
        # spans must not scale with it (it would pin x_1 to x_0's mean)
        (3, [(0, 2), (2, 4), (5, 3)], 1e-10),
    ],
)
def test_closures_marginalise_exactly_on_a_linear_chain(lag, pairs, p0_scale):
    trans, meas, updates = _linear_problem()
    link, links = _linear_links(pairs)
    p0 = p0_scale * P0
    sol = eqs.filters.fixed_lag_smoother(
        trans, meas, jnp.asarray(M0), jnp.asarray(p0), lag=lag, closures=link
    )
    for t in range(T):
        exact = _numpy_posterior_means(updates, links, t, p0)
        # online: x_t given everything up to t; lagged: x_t when it leaves
        np.testing.assert_allclose(sol.mean[t], exact[t], rtol=0, atol=1e-6)
        end = min(t + lag - 1, T - 1)
        lagged = _numpy_posterior_means(updates, links, end, p0)[t]
        np.testing.assert_allclose(sol.lagged_mean[t], lagged, rtol=0, atol=1e-6)


def _se2_link(a, b, data, params):
    return 10.0 * (eqs.local(a["pose"], b["pose"]) - data)


def _se2_closures(truth, pairs):
    a, b = (np.array(v) for v in zip(*pairs))
    rel = eqs.local(truth["pose"][a], truth["pose"][b], batch_ndim=1)
    noise = 0.02 * np.random.default_rng(2).normal(size=rel.shape)
    return eqs.FunctionFactor(
        _se2_link,
        (eqs.Var("s", a), eqs.Var("s", b)),
        eqs.IsotropicNoise(sqrt_precision=jnp.asarray(1.0)),
        data=rel + noise,
    )


_SE2_PAIRS = [(0, 3), (4, 1), (2, 5)]


def _se2_links_run(scale, lag, num_steps):
    """The SE(2) problem with the links `_SE2_PAIRS`, run at `lag`."""
    trans, meas, truth = _se2_problem(scale, 1.0)
    links = _se2_closures(truth, _SE2_PAIRS)
    mean0, cov0 = _se2_initial(truth)
    solver = eqs.FixedStepGaussNewton(num_steps=num_steps)
    sol = _run_links(trans, meas, links, mean0, cov0, lag, solver, _UNROLLED)
    return sol, (trans, meas, links, truth, mean0, cov0)


@eqx.filter_jit
def _run_links(trans, meas, links, mean0, cov0, lag, solver, adjoint):
    return eqs.filters.fixed_lag_smoother(
        trans,
        meas,
        mean0,
        cov0,
        lag=lag,
        closures=links,
        solver=solver,
        adjoint=adjoint,
    )


def test_closures_lag_T_is_the_batch_smoother():
    sol, (trans, meas, links, _, mean0, cov0) = _se2_links_run(1.0, T, 6)
    prior = eqs.PriorFactor(
        eqs.Var("s", [0]),
        jax.tree_util.tree_map(lambda a: a[None], mean0),
        eqs.SqrtInformationNoise.from_covariance(cov0),
    )
    graph = eqs.FactorGraph([prior, trans, meas, links])
    init = jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (T, *a.shape)), mean0)
    batch = eqs.least_squares(graph, {"s": init}, eqs.GaussNewton()).value["s"]
    np.testing.assert_allclose(
        eqs.local(sol.lagged_mean, batch, batch_ndim=1), 0, atol=1e-6
    )


def _links_loss(scale, lag=4):
    sol, (*_, truth, _, _) = _se2_links_run(scale, lag, 4)
    err = sol.mean["pose"].translation() - truth["pose"].translation()
    return jnp.sum(err**2) + jnp.sum(sol.prior_covariance)


def test_closures_derivative_matches_central_differences():
    # Forward mode: the same derivative as the reverse-mode test below, whose
    # compile (the transpose of the scan with closures, about 3 minutes on 2
    # cores) keeps it among the slow tests.
    s, h = 1.3, 1e-5
    _, d = jax.jvp(_links_loss, (s,), (1.0,))
    fd = (_links_loss(s + h) - _links_loss(s - h)) / (2 * h)
    assert abs(float(d)) > 1e-3
    np.testing.assert_allclose(float(d), float(fd), rtol=1e-6)


@pytest.mark.slow
def test_closures_gradient_matches_central_differences():
    _check_gradient(_links_loss, 1e-6)


def test_closures_hostile_input():
    trans, meas, _ = _linear_problem()
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    run = eqs.filters.fixed_lag_smoother
    link, _ = _linear_links([(0, 2), (1, 4)])
    with raises(
        ValueError,
        "closure factor FunctionFactor row 1",
        "times 1 and 4",
        "lag - 1 = 2",
        "outside the window",
    ):
        run(trans, meas, m0, p0, lag=3, closures=link)
    same, _ = _linear_links([(2, 2)])
    with raises(ValueError, "row 0 links times 2 and 2", "two different states"):
        run(trans, meas, m0, p0, lag=3, closures=same)
    late, _ = _linear_links([(4, 6)])
    with raises(ValueError, "times 4 and 6", "only T = 6 states"):
        run(trans, meas, m0, p0, lag=3, closures=late)
    other = eqx.tree_at(
        lambda f: f.variables, link, (eqs.Var("y", [0, 1]), eqs.Var("x", [2, 3]))
    )
    with raises(ValueError, "must link two states of group 'x'"):
        run(trans, meas, m0, p0, lag=3, closures=other)
    bad = eqx.tree_at(lambda f: f.data, link, link.data.at[0].set(jnp.nan))
    with raises(ValueError, "non-finite", "rows [0]"):
        run(trans, meas, m0, p0, lag=4, closures=bad)
