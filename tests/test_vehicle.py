"""The planar vehicle state and its dynamics / velocity factors."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def _truth(T=8, dt=0.1, seed=0):
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    v = 8.0 + np.cumsum(0.1 * rng.normal(size=T))
    w = 0.2 + np.cumsum(0.02 * rng.normal(size=T))
    state = eqs.factors.VehicleState(
        eqs.SE2.from_xy_theta(jnp.asarray(1.0), jnp.asarray(-2.0), jnp.asarray(0.4)),
        jnp.asarray([v[0], w[0]]),
    )
    poses = [state.pose.unit_complex_xy]
    for t in range(T - 1):
        state = eqs.factors.vehicle_motion(
            eqs.factors.VehicleState(state.pose, jnp.asarray([v[t], w[t]])), dt
        )
        poses.append(state.pose.unit_complex_xy)
    return eqs.factors.VehicleState(
        eqs.SE2(jnp.stack(poses)), jnp.stack([v, w], axis=1)
    )


def test_from_poses_and_zero_residual():
    import eqsmooth as eqs

    dt = 0.1
    truth = _truth(dt=dt)
    rebuilt = eqs.factors.VehicleState.from_poses(truth.pose, dt)
    np.testing.assert_allclose(rebuilt.velocity[:-1], truth.velocity[:-1], atol=1e-9)
    t = np.arange(truth.velocity.shape[0])
    dyn = eqs.factors.VehicleDynamicsFactor(
        eqs.Var("x", t[:-1]),
        eqs.Var("x", t[1:]),
        eqs.DiagonalNoise(sqrt_precision=jnp.ones(5)),
        dt=dt,
    )
    # Velocities carried over: use the rebuilt trajectory (v_{t+1} = v_t only
    # where the motion is constant), so compare the pose part of the residual.
    r = eqs.FactorGraph([dyn]).residuals({"x": truth})[0]
    np.testing.assert_allclose(r[:, :3], 0.0, atol=1e-9)
    const = eqs.factors.VehicleState(
        truth.pose, jnp.broadcast_to(truth.velocity[:1], truth.velocity.shape)
    )
    poses = [const.pose[0]]
    for _ in range(len(t) - 1):
        s = eqs.factors.vehicle_motion(
            eqs.factors.VehicleState(poses[-1], const.velocity[0]), dt
        )
        poses.append(s.pose)
    const = eqs.factors.VehicleState(
        eqs.SE2(jnp.stack([p.unit_complex_xy for p in poses])), const.velocity
    )
    r = eqs.FactorGraph([dyn]).residuals({"x": const})[0]
    np.testing.assert_allclose(r, 0.0, atol=1e-9)


def _num_jac(f, d, eps=1e-6):
    cols = []
    for i in range(d):
        e = np.zeros(d)
        e[i] = eps
        cols.append((f(jnp.asarray(e)) - f(jnp.asarray(-e))) / (2 * eps))
    return np.stack(cols, axis=1)


def test_jacobians_match_finite_differences():
    import eqsmooth as eqs
    from eqsmooth.factors._factor import linearize_rows

    dt = 0.1
    truth = _truth(T=3, dt=dt)
    rng = np.random.default_rng(1)
    x = eqs.retract(truth, jnp.asarray(0.1 * rng.normal(size=(3, 5))))
    t = np.arange(3)
    dyn = eqs.factors.VehicleDynamicsFactor(
        eqs.Var("x", t[:-1]),
        eqs.Var("x", t[1:]),
        eqs.DiagonalNoise(sqrt_precision=jnp.ones(5)),
        dt,
    )
    meas = eqs.factors.VelocityMeasurementFactor(
        eqs.Var("x", t),
        jnp.zeros((3, 2)),
        eqs.DiagonalNoise(sqrt_precision=jnp.ones((3, 2))),
    )
    a, b = x[:2], x[1:]
    _, (Ja, Jb) = eqx.filter_jit(linearize_rows)(dyn, (a, b))
    for k in range(2):
        ak, bk = a[k], b[k]
        na = _num_jac(lambda d: dyn.residual(eqs.retract(ak, d), bk), 5)
        nb = _num_jac(lambda d: dyn.residual(ak, eqs.retract(bk, d)), 5)
        np.testing.assert_allclose(Ja[k], na, atol=1e-6)
        np.testing.assert_allclose(Jb[k], nb, atol=1e-6)
    _, (Jm,) = eqx.filter_jit(linearize_rows)(meas, (x,))
    expected = np.concatenate([np.zeros((2, 3)), np.eye(2)], axis=1)
    np.testing.assert_allclose(Jm, np.broadcast_to(expected, (3, 2, 5)), atol=1e-9)


def test_smoothing_recovers_trajectory():
    import eqsmooth as eqs

    T, dt = 12, 0.1
    truth = _truth(T=T, dt=dt, seed=3)
    rng = np.random.default_rng(4)
    sigma = np.where(np.arange(T) % 3 == 0, 2.0, 0.05)  # some frames untrusted
    z = truth.velocity + jnp.asarray(rng.normal(size=(T, 2)) * 0.05)
    z = z.at[::3].add(jnp.asarray(rng.normal(size=(4, 2)) * 2.0))
    t = np.arange(T)
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", [0]),
                truth[:1],
                eqs.DiagonalNoise(sqrt_precision=jnp.full(5, 1e3)),
            ),
            eqs.factors.VehicleDynamicsFactor(
                eqs.Var("x", t[:-1]),
                eqs.Var("x", t[1:]),
                eqs.DiagonalNoise.from_sigmas(
                    jnp.asarray([0.01, 0.01, 0.01, 0.2, 0.05])
                ),
                dt,
            ),
            eqs.factors.VelocityMeasurementFactor(
                eqs.Var("x", t),
                z,
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(np.stack([sigma, sigma], 1))),
            ),
        ]
    )
    init = eqs.factors.VehicleState(
        eqs.SE2.identity((T,), jnp.float64), jnp.zeros((T, 2))
    )
    init = eqs.factors.VehicleState(
        jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a[:1], a.shape), truth.pose),
        init.velocity,
    )
    sol = eqs.least_squares(
        graph, {"x": init}, eqs.GaussNewton(eqs.BlockTridiagonal()), max_steps=50
    )
    err = eqs.local(truth, sol.value["x"], batch_ndim=1)
    naive = eqs.local(
        truth,
        eqs.factors.VehicleState(truth.pose, z),
        batch_ndim=1,
    )
    # Dead reckoning from noisy velocities drifts slowly; outliers are ignored.
    assert float(jnp.max(jnp.abs(err[:, :3]))) < 0.2
    assert float(jnp.mean(err[:, 3:] ** 2)) < 0.1 * float(jnp.mean(naive[:, 3:] ** 2))


def _motion_residual(prev, next, data, params):
    import eqsmooth as eqs

    return eqs.local(eqs.factors.vehicle_motion(prev, 0.7), next)


def test_closed_form_jacobians_equal_autodiff():
    """`VehicleDynamicsFactor` linearises in closed form; the same residual
    through forward-mode autodiff (a `FunctionFactor`) gives the same
    residuals and Jacobians, at headings, turn rates and residual angles up
    to near ±π."""
    import eqsmooth as eqs
    from eqsmooth.factors._factor import linearize_rows

    n, dt = 16, 0.7
    rng = np.random.default_rng(5)
    angle = np.linspace(-3.1, 3.1, n)
    prev = eqs.factors.VehicleState(
        eqs.SE2.from_xy_theta(
            *jnp.asarray(rng.normal(size=(2, n))), jnp.asarray(angle)
        ),
        jnp.asarray(np.stack([rng.normal(size=n) * 3, angle / dt], 1)),
    )
    # The next state: the motion, then a perturbation whose heading part
    # sweeps (-3, 3), so the residual angle does too.
    delta = rng.normal(size=(n, 5)) * 0.5
    delta[:, 2] = np.linspace(3.0, -3.0, n)
    next = eqs.retract(eqs.factors.vehicle_motion(prev, dt), jnp.asarray(delta))
    t = np.arange(n)
    noise = eqs.DiagonalNoise(sqrt_precision=jnp.ones(5))
    closed = eqs.factors.VehicleDynamicsFactor(
        eqs.Var("x", t), eqs.Var("y", t), noise, dt
    )
    auto = eqs.FunctionFactor(
        _motion_residual, (eqs.Var("x", t), eqs.Var("y", t)), noise
    )
    assert isinstance(closed, eqs.factors.AbstractAnalyticFactor)
    r1, j1 = eqx.filter_jit(linearize_rows)(closed, (prev, next))
    r2, j2 = eqx.filter_jit(linearize_rows)(auto, (prev, next))
    np.testing.assert_allclose(r1, delta, atol=1e-12)
    np.testing.assert_allclose(r1, r2, atol=1e-12)
    for a, b in zip(j1, j2):
        np.testing.assert_allclose(a, b, atol=1e-11)
    # `residual` (the cost) and the closed form agree on the residual.
    rows = jax.vmap(closed.residual)(prev, next)
    np.testing.assert_allclose(rows, r1, atol=1e-13)
