"""EKF / RTS built from factors, tied to Kalman theory and the factor-graph MAP."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


T = 6
F_MAT = np.array([[1.0, 0.5], [0.0, 1.0]])
Q_COV = np.array([[0.05, 0.01], [0.01, 0.2]])
H1 = np.array([[1.0, 0.0]])
R2_COV = np.array([[0.3, 0.1], [0.1, 0.5]])
M0 = np.array([0.3, -0.2])
P0 = np.array([[1.0, 0.2], [0.2, 2.0]])


def _lin_trans(a, b, data, params):
    return b - params @ a


def _lin_meas(x, data, params):
    return params @ x - data


def _linear_problem():
    """Linear-Gaussian chain with two measurement stacks.

    Stack 1: scalar position measurements with per-row noise at t = 0, 1, 2, 4, 5
    (t = 3 missing). Stack 2: full 2-D measurements with a full covariance,
    twice at t = 2 (two rows at one time step) and once at t = 5.
    """
    import eqsmooth as eqs

    rng = np.random.default_rng(0)
    t1 = np.array([0, 1, 2, 4, 5])
    sig1 = np.array([0.2, 0.4, 0.3, 0.25, 0.5])
    z1 = rng.normal(size=(5, 1))
    t2 = np.array([2, 5, 2])
    z2 = rng.normal(size=(3, 2))
    t = np.arange(T)
    trans = eqs.FunctionFactor(
        _lin_trans,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        eqs.SqrtInformationNoise.from_covariance(jnp.asarray(Q_COV)),
        params=jnp.asarray(F_MAT),
    )

    def meas(times, noise, z, H):
        z, H = jnp.asarray(z), jnp.asarray(H)
        return eqs.FunctionFactor(
            _lin_meas, (eqs.Var("x", times),), noise, data=z, params=H
        )

    meas1 = meas(t1, eqs.IsotropicNoise.from_sigma(jnp.asarray(sig1)), z1, H1)
    R2 = eqs.SqrtInformationNoise.from_covariance(jnp.asarray(R2_COV))
    meas2 = meas(t2, R2, z2, jnp.eye(2, dtype=jnp.float64))
    # Per time step, the updates in the filter's order (stack 1, then stack 2).
    updates = {k: [] for k in range(T)}
    for i, k in enumerate(t1):
        updates[k].append((H1, np.array([[sig1[i] ** 2]]), z1[i]))
    for i, k in enumerate(t2):
        updates[k].append((np.eye(2), R2_COV, z2[i]))
    return trans, (meas1, meas2), updates


def _numpy_kalman(updates):
    """Textbook Kalman filter and RTS smoother in numpy."""
    m, P = M0.copy(), P0.copy()
    means, covs, pmeans, pcovs, ll = [], [], [], [], 0.0
    innov = []
    for k in range(T):
        if k > 0:
            m = F_MAT @ m
            P = F_MAT @ P @ F_MAT.T + Q_COV
        pmeans.append(m)
        pcovs.append(P)
        for H, R, z in updates[k]:
            y = z - H @ m
            S = H @ P @ H.T + R
            K = P @ H.T @ np.linalg.inv(S)
            m = m + K @ y
            P = (np.eye(2) - K @ H) @ P
            ll += -0.5 * (
                y @ np.linalg.solve(S, y)
                + np.linalg.slogdet(S)[1]
                + len(y) * np.log(2 * np.pi)
            )
            innov.append((y, S, R))
        means.append(m)
        covs.append(P)
    sm, sP = [means[-1]], [covs[-1]]
    for k in range(T - 2, -1, -1):
        G = covs[k] @ F_MAT.T @ np.linalg.inv(pcovs[k + 1])
        sm.insert(0, means[k] + G @ (sm[0] - pmeans[k + 1]))
        sP.insert(0, covs[k] + G @ (sP[0] - pcovs[k + 1]) @ G.T)
    return (
        np.stack(means),
        np.stack(covs),
        np.stack(pmeans),
        ll,
        innov,
        np.stack(sm),
        np.stack(sP),
    )


@pytest.fixture(scope="module")
def linear_run():
    import eqsmooth as eqs

    trans, meas, updates = _linear_problem()
    sol = eqs.filters.ekf(trans, meas, jnp.asarray(M0), jnp.asarray(P0))
    return trans, meas, updates, sol


def test_ekf_equals_kalman_filter(linear_run):
    import eqsmooth as eqs

    trans, meas, updates, sol = linear_run
    means, covs, pmeans, ll, innov, _, _ = _numpy_kalman(updates)
    np.testing.assert_allclose(sol.mean, means, rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.covariance, covs, rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.predicted_mean, pmeans, rtol=0, atol=1e-10)
    np.testing.assert_allclose(sol.log_likelihood, ll, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.sum(sol.step_log_likelihood), ll, rtol=0, atol=1e-10)
    assert sol.step_log_likelihood[3] == 0.0  # no measurement at t = 3
    # The covariance reset is the identity on vector spaces.
    reset = eqs.filters.ekf(
        trans, meas, jnp.asarray(M0), jnp.asarray(P0), reset_covariance=True
    )
    np.testing.assert_allclose(reset.covariance, covs, rtol=0, atol=1e-10)
    # Transition rows may come in any order.
    rev = eqs.FunctionFactor(
        _lin_trans,
        tuple(eqs.Var("x", v.ids[::-1]) for v in trans.variables),
        trans.noise,
        params=trans.params,
    )
    sol_rev = eqs.filters.ekf(rev, meas, jnp.asarray(M0), jnp.asarray(P0))
    np.testing.assert_allclose(sol_rev.mean, means, rtol=0, atol=1e-10)
    np.testing.assert_allclose(
        sol.transition_jacobian, np.broadcast_to(F_MAT, (T - 1, 2, 2)), atol=1e-12
    )
    # Whitened innovations per row: y_w = R_w y, S_w = R_w S R_wᵀ, with the
    # rows of each stack in the filter's order (stack 1: t = 0,1,2,4,5;
    # stack 2: rows 0 and 2 at t = 2, row 1 at t = 5).
    order = [(0, 0), (0, 1), (0, 2), (1, 0), (1, 2), (0, 3), (0, 4), (1, 1)]
    for (j, i), (y, S, R) in zip(order, innov):
        Rw = np.linalg.inv(np.linalg.cholesky(R))
        np.testing.assert_allclose(sol.innovations[j][i], Rw @ y, atol=1e-10)
        np.testing.assert_allclose(
            sol.innovation_covariances[j][i], Rw @ S @ Rw.T, atol=1e-10
        )


def test_rts_equals_factor_graph_map(linear_run):
    import eqsmooth as eqs

    trans, meas, updates, sol = linear_run
    _, _, _, _, _, sm, sP = _numpy_kalman(updates)
    rts = eqs.filters.rts_smoother(sol)
    np.testing.assert_allclose(rts.mean, sm, rtol=0, atol=1e-10)
    np.testing.assert_allclose(rts.covariance, sP, rtol=0, atol=1e-10)

    prior = eqs.PriorFactor(
        eqs.Var("x", [0]),
        jnp.asarray(M0)[None],
        eqs.SqrtInformationNoise.from_covariance(jnp.asarray(P0)),
    )
    graph = eqs.FactorGraph([prior, trans, *meas])
    values = {"x": jnp.zeros((T, 2))}
    map_sol = eqs.least_squares(graph, values, eqs.GaussNewton(eqs.BlockTridiagonal()))
    np.testing.assert_allclose(map_sol.value["x"], rts.mean, rtol=0, atol=1e-9)
    lin = eqs.solve.linearize(graph, map_sol.value)
    cov = eqs.marginal_covariances(lin)["x"]
    np.testing.assert_allclose(cov, rts.covariance, rtol=0, atol=1e-9)


# ------------------------------------------------------------------- SE(2)


DT = 0.5


def _se2_trans(a, b, data, params):
    # Constant-velocity motion of a mixed state {pose: SE2, vel: body twist}.
    import eqsmooth as eqs

    pred = {"pose": a["pose"] @ eqs.SE2.exp(DT * a["vel"]), "vel": a["vel"]}
    return eqs.local(pred, b)


def _se2_meas(x, data, params):
    return x["pose"].translation() - data


def _se2_problem(meas_scale, trans_scale, seed=0):
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    vel = [np.array([0.8, 0.1, 0.6])]
    poses = [eqs.SE2.identity(dtype=jnp.float64)]
    for _ in range(T - 1):
        poses.append(poses[-1] @ eqs.SE2.exp(jnp.asarray(DT * vel[-1])))
        vel.append(vel[-1] + 0.05 * rng.normal(size=3))
    truth = {
        "pose": eqs.SE2(jnp.stack([p.parameters() for p in poses])),
        "vel": jnp.asarray(np.stack(vel)),
    }
    z = truth["pose"].translation() + 0.1 * jnp.asarray(rng.normal(size=(T, 2)))
    t = np.arange(T)
    sig = jnp.asarray(np.linspace(0.1, 0.3, T))  # heteroscedastic rows
    sqrt_prec = jnp.asarray([50.0, 50.0, 30.0, 20.0, 20.0, 20.0])
    trans = eqs.FunctionFactor(
        _se2_trans,
        (eqs.Var("s", t[:-1]), eqs.Var("s", t[1:])),
        eqs.DiagonalNoise(sqrt_precision=trans_scale * sqrt_prec),
    )
    meas = eqs.FunctionFactor(
        _se2_meas,
        (eqs.Var("s", t),),
        eqs.IsotropicNoise(sqrt_precision=meas_scale / sig),
        data=z,
    )
    return trans, meas, truth


def _se2_initial(truth):
    import eqsmooth as eqs

    mean0 = {
        "pose": truth["pose"][0] @ eqs.SE2.exp(jnp.asarray([0.05, -0.05, 0.02])),
        "vel": truth["vel"][0] + 0.1,
    }
    return mean0, 0.01 * jnp.eye(6)


def _se2_losses(meas_scale, trans_scale, reset):
    import eqsmooth as eqs

    trans, meas, truth = _se2_problem(meas_scale, trans_scale)
    mean0, cov0 = _se2_initial(truth)
    sol = eqs.filters.ekf(trans, [meas], mean0, cov0, reset_covariance=reset)
    w = {"pose": jnp.asarray([1.0, 1.0, 4.0]), "vel": jnp.asarray(0.5)}
    return jnp.stack(
        [
            eqs.filters.ekf_mse_loss(sol, truth, w),
            eqs.filters.ekf_marginal_nll(sol, truth),
            eqs.filters.ekf_innovation_nll(sol),
            eqs.filters.ekf_marginal_nll(eqs.filters.rts_smoother(sol), truth),
        ]
    )


_se2_losses_jit = jax.jit(_se2_losses, static_argnums=2)
# Reverse mode, one VJP per loss (what training uses).
_se2_jac_jit = jax.jit(jax.jacrev(_se2_losses, argnums=(0, 1)), static_argnums=2)


def test_se2_prediction_and_jacobians():
    import eqsmooth as eqs

    trans, meas, truth = _se2_problem(1.0, 1.0)
    mean0, cov0 = _se2_initial(truth)

    @jax.jit  # one program, not the Lie-group operations one by one
    def run(trans, meas, truth, mean0, cov0):
        sol = eqs.filters.ekf(trans, [meas], mean0, cov0)
        pose, vel = sol.mean["pose"][: T - 1], sol.mean["vel"][: T - 1]
        pred = pose @ eqs.SE2.exp(DT * vel)
        checks = {
            "pred": eqs.local(pred, sol.predicted_mean["pose"][1:], batch_ndim=1),
            "vel": vel,
            "adjoint": eqs.SE2.exp(-DT * vel).adjoint(),
            "jr": DT * eqs.SE2.right_jacobian(DT * vel),
            "err": eqs.local(truth, sol.mean, batch_ndim=1),
        }
        return sol, eqs.filters.rts_smoother(sol), checks

    sol, rts, c = run(trans, meas, truth, mean0, cov0)
    assert np.all(np.isfinite(sol.covariance))
    # One Newton step is exact for b ⊖ f(a): x_{t+1|t} = f(x_{t|t}).
    np.testing.assert_allclose(c["pred"], 0.0, atol=1e-12)
    np.testing.assert_allclose(sol.predicted_mean["vel"][1:], c["vel"], atol=1e-12)
    # F = [[Ad(exp(v dt)⁻¹), Jr(v dt) dt], [0, I]] for right perturbations.
    F = np.asarray(sol.transition_jacobian)
    np.testing.assert_allclose(F[:, :3, :3], c["adjoint"], atol=1e-10)
    np.testing.assert_allclose(F[:, :3, 3:], c["jr"], atol=1e-10)
    np.testing.assert_allclose(F[:, 3:, :3], 0.0, atol=1e-12)
    np.testing.assert_allclose(F[:, 3:, 3:], np.broadcast_to(np.eye(3), (T - 1, 3, 3)))
    # The filter tracks the truth better than the raw measurements' noise.
    assert np.sqrt(np.mean(np.asarray(c["err"][:, :2]) ** 2)) < 0.1
    # Positive definite beliefs.
    assert np.all(np.linalg.eigvalsh(np.asarray(sol.covariance)) > 0)
    assert np.all(np.linalg.eigvalsh(np.asarray(rts.covariance)) > 0)


@pytest.mark.parametrize("reset", [False, pytest.param(True, marks=pytest.mark.slow)])
def test_se2_loss_gradients_match_finite_differences(reset):
    # Gradients of every loss w.r.t. a scale of the (per-row) measurement
    # noise and of the transition noise, against central differences.
    a, b, eps = 1.3, 0.8, 1e-6
    jac_a, jac_b = _se2_jac_jit(a, b, reset)
    f = _se2_losses_jit
    fd_a = (f(a + eps, b, reset) - f(a - eps, b, reset)) / (2 * eps)
    fd_b = (f(a, b + eps, reset) - f(a, b - eps, reset)) / (2 * eps)
    assert np.all(np.abs(np.asarray(fd_a)) > 1e-6)  # the check can fail
    assert np.all(np.abs(np.asarray(fd_b)) > 1e-6)
    np.testing.assert_allclose(jac_a, fd_a, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(jac_b, fd_b, rtol=1e-5, atol=1e-7)


def test_reset_covariance_changes_the_se2_belief():
    losses = _se2_losses_jit(1.0, 1.0, False)
    losses_reset = _se2_losses_jit(1.0, 1.0, True)
    assert np.all(np.isfinite(losses_reset))
    assert not np.allclose(losses[1], losses_reset[1], rtol=1e-9, atol=0)


def test_vmap_over_sequences(linear_run):
    import eqsmooth as eqs

    trans, meas, _, sol = linear_run
    meas1, meas2 = meas
    shift = jnp.asarray([0.0, 1.5])

    def run(s):
        m1 = eqs.FunctionFactor(
            _lin_meas,
            meas1.variables,
            meas1.noise,
            data=meas1.data + s,
            params=meas1.params,
        )
        return eqs.filters.ekf(trans, (m1, meas2), jnp.asarray(M0), jnp.asarray(P0))

    batched = jax.vmap(run)(shift)
    np.testing.assert_allclose(batched.mean[0], sol.mean, atol=1e-12)
    single = run(shift[1])
    np.testing.assert_allclose(batched.mean[1], single.mean, atol=1e-12)
    np.testing.assert_allclose(batched.log_likelihood[1], single.log_likelihood)


@pytest.mark.slow
def test_more_newton_steps_change_nothing_when_one_is_exact():
    import eqsmooth as eqs

    trans, meas, truth = _se2_problem(1.0, 1.0)
    mean0, cov0 = _se2_initial(truth)
    sol = eqs.filters.ekf(trans, [meas], mean0, cov0)
    sol2 = eqs.filters.ekf(trans, [meas], mean0, cov0, prediction_steps=2)
    np.testing.assert_allclose(sol2.covariance, sol.covariance, atol=1e-12)
    np.testing.assert_allclose(sol2.mean["vel"], sol.mean["vel"], atol=1e-12)


# ------------------------------------------------------------------- errors


def test_clear_errors():
    import eqsmooth as eqs

    trans, meas, _ = _linear_problem()
    meas1 = meas[0]
    m0, p0 = jnp.asarray(M0), jnp.asarray(P0)
    noise = eqs.IsotropicNoise(sqrt_precision=1.0)
    t = np.arange(T)
    not_chain = eqs.FunctionFactor(
        _lin_trans, (eqs.Var("x", t[:-1]), eqs.Var("x", t[:-1] + 2)), noise
    )
    with pytest.raises(ValueError, match="must form a chain"):
        eqs.filters.ekf(not_chain, [meas1], m0, p0)
    two_groups = eqs.FunctionFactor(
        _lin_trans, (eqs.Var("x", t[:-1]), eqs.Var("y", t[1:])), noise
    )
    with pytest.raises(ValueError, match="both variables must be in one group"):
        eqs.filters.ekf(two_groups, [meas1], m0, p0)
    other_group = eqs.FunctionFactor(
        _lin_meas,
        (eqs.Var("y", t),),
        noise,
        data=jnp.zeros((T, 1)),
        params=jnp.asarray(H1),
    )
    with pytest.raises(ValueError, match="touches group 'y'"):
        eqs.filters.ekf(trans, [other_group], m0, p0)
    late = eqs.FunctionFactor(
        _lin_meas,
        (eqs.Var("x", [T]),),
        noise,
        data=jnp.zeros((1, 1)),
        params=jnp.asarray(H1),
    )
    with pytest.raises(ValueError, match="time indices up to"):
        eqs.filters.ekf(trans, [late], m0, p0)
    robust = eqs.FunctionFactor(
        _lin_meas,
        meas1.variables,
        eqs.HuberNoise(eqs.IsotropicNoise(sqrt_precision=1.0), 1.0),
        data=meas1.data,
        params=meas1.params,
    )
    with pytest.raises(TypeError, match="robust"):
        eqs.filters.ekf(trans, [robust], m0, p0)
    with pytest.raises(ValueError, match=r"must be \(2, 2\)"):
        eqs.filters.ekf(trans, [meas1], m0, jnp.eye(3))
    empty = eqs.FunctionFactor(
        _lin_meas,
        (eqs.Var("x", np.zeros((0,), np.int64)),),
        noise,
        data=jnp.zeros((0, 1)),
        params=jnp.asarray(H1),
    )
    with pytest.raises(ValueError, match="has no rows"):
        eqs.filters.ekf(trans, [empty], m0, p0)
    with pytest.raises(ValueError, match="prediction_steps"):
        eqs.filters.ekf(trans, [meas1], m0, p0, prediction_steps=0)
    bad = eqs.FunctionFactor(
        _lin_meas,
        meas1.variables,
        meas1.noise,
        data=meas1.data.at[2].set(jnp.nan),
        params=meas1.params,
    )
    with pytest.raises(eqx.EquinoxRuntimeError, match="not finite"):
        eqs.filters.ekf(trans, [bad], m0, p0)
    sol = eqs.filters.ekf(trans, [meas1], m0, p0)
    with pytest.raises(ValueError, match="do not broadcast"):
        eqs.filters.ekf_mse_loss(sol, jnp.zeros((T, 2)), jnp.ones(3))
    with pytest.raises(ValueError, match="leading time axis of length"):
        eqs.filters.ekf_marginal_nll(sol, jnp.zeros((T + 1, 2)))
