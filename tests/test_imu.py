"""IMU preintegration and IMU factors.

Against GTSAM (skipped without it): the preintegrated deltas, covariances
(9x9 and combined 15x15, in the preintegration's and in the residual's
chart), the bias correction (through GTSAM's `predict` at another bias), the
residuals of `ImuFactor` and `CombinedImuFactor` at random states and their
Jacobians (GTSAM's whitened Jacobians unwhitened by its own noise model),
on random data and on a stretch of the KITTI drive GTSAM ships. Then
padding masks, central-difference gradients of the joint NLL and of a small
IMU + GPS solve with respect to the noise densities, the biases and the
samples, and hostile input.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


GTSAM_REASON = "GTSAM parity checks need gtsam (the `bench` extra)"
N, K = 3, 6  # intervals, samples per interval: one compiled preintegration
GRAVITY = np.array([0.1, -0.2, -9.81])
SA = np.array([[0.02, 0.003, 0.0], [0.003, 0.03, -0.002], [0.0, -0.002, 0.04]])
SG = np.array([[1e-3, 1e-4, 0.0], [1e-4, 2e-3, 0.0], [0.0, 0.0, 3e-3]])
SI = np.eye(3) * 1e-4
SBA = np.diag([1e-3, 2e-3, 3e-3])
SBG = np.diag([1e-4, 2e-4, 3e-4])


def _gtsam():
    return pytest.importorskip("gtsam", reason=GTSAM_REASON)


@functools.cache
def _data(seed=0):
    """Random samples, durations, integration biases and states for N rows."""
    rng = np.random.default_rng(seed)
    acc = rng.normal(size=(N, K, 3)) + [0.0, 0.0, 9.8]
    gyro = rng.normal(size=(N, K, 3))
    dt = rng.uniform(0.005, 0.05, size=(N, K))
    bias_hat = rng.normal(size=(N, 6)) * 0.1
    states = dict(
        pose_i=rng.normal(size=(N, 6)),
        pose_j=rng.normal(size=(N, 6)),
        vel_i=rng.normal(size=(N, 3)),
        vel_j=rng.normal(size=(N, 3)),
        bias_i=bias_hat + rng.normal(size=(N, 6)) * 0.05,
        bias_j=rng.normal(size=(N, 6)) * 0.05,
    )
    return acc, gyro, dt, bias_hat, states


def _params():
    import eqsmooth as eqs

    return eqs.ImuParams(jnp.asarray(GRAVITY), SA, SG, SI, SBA, SBG)


@functools.cache
def _ours(seed=0):
    import eqsmooth as eqs

    acc, gyro, dt, bias_hat, _ = _data(seed)
    return eqs.preintegrate(_params(), acc, gyro, dt, bias_hat)


@eqx.filter_jit
def _summary(pim):
    """Everything compared with GTSAM, in one compiled call (eager Lie-group
    calls would compile one small program each)."""
    return dict(
        delta_t=pim.delta_t,
        preintegrated=pim.preintegrated,
        delta_R=pim.delta_R().as_matrix(),
        delta_p=pim.delta_p(),
        delta_v=pim.delta_v(),
        covariance=pim.covariance,
        residual_covariance=pim.residual_covariance(),
        combined_covariance=pim.combined_covariance,
        combined_residual_covariance=pim.combined_residual_covariance(),
        bias_hat=pim.bias_hat,
    )


def _gtsam_pims(acc, gyro, dt, bias_hat, gravity=GRAVITY):
    gtsam = _gtsam()
    p = gtsam.PreintegrationCombinedParams(np.asarray(gravity))
    p.setAccelerometerCovariance(SA)
    p.setGyroscopeCovariance(SG)
    p.setIntegrationCovariance(SI)
    p.setBiasAccCovariance(SBA)
    p.setBiasOmegaCovariance(SBG)
    out = []
    for row in range(acc.shape[0]):
        b = gtsam.imuBias.ConstantBias(bias_hat[row, :3], bias_hat[row, 3:])
        pim = gtsam.PreintegratedImuMeasurements(p, b)
        cpim = gtsam.PreintegratedCombinedMeasurements(p, b)
        for k in range(acc.shape[1]):
            pim.integrateMeasurement(acc[row, k], gyro[row, k], dt[row, k])
            cpim.integrateMeasurement(acc[row, k], gyro[row, k], dt[row, k])
        out.append((pim, cpim))
    return out


def _pose3(gtsam, pose):
    return gtsam.Pose3(np.asarray(pose.as_matrix()))


def _values(gtsam, poses_i, poses_j, states, row):
    v = gtsam.Values()
    v.insert(0, _pose3(gtsam, poses_i[row]))
    v.insert(1, states["vel_i"][row])
    v.insert(2, _pose3(gtsam, poses_j[row]))
    v.insert(3, states["vel_j"][row])
    for key, name in ((4, "bias_i"), (5, "bias_j")):
        b = states[name][row]
        v.insert(key, gtsam.imuBias.ConstantBias(b[:3], b[3:]))
    return v


def _swap_pose_columns(h):
    """GTSAM's Pose3 tangent is (ω, v), eqsmooth's SE3 tangent (v, ω)."""
    return np.concatenate([h[:, 3:6], h[:, 0:3]], axis=1)


def _gtsam_jacobian(factor, values, pose_columns):
    """GTSAM's Jacobian of the unwhitened error, columns in eqsmooth's order."""
    a = factor.linearize(values).jacobian()[0]
    h = np.linalg.solve(factor.noiseModel().R(), a)
    blocks, start = [], 0
    for width, is_pose in pose_columns:
        block = h[:, start : start + width]
        blocks.append(_swap_pose_columns(block) if is_pose else block)
        start += width
    return np.concatenate(blocks, axis=1)


def _pair(pim, gravity, combined=False, first=range(N), second=range(N, 2 * N)):
    """An ImuFactor (or CombinedImuFactor) stack from keyframes `first` to
    `second` (variables x, v, b)."""
    import eqsmooth as eqs

    V = eqs.Var
    states = (V("x", first), V("v", first), V("x", second), V("v", second))
    if combined:
        return eqs.CombinedImuFactor(
            *states, V("b", first), V("b", second), pim, gravity
        )
    return eqs.ImuFactor(*states, V("b", first), pim, gravity)


def _factors(pim):
    return _pair(pim, _params()), _pair(pim, _params(), combined=True)


@eqx.filter_jit
def _rows(factor, states):
    from eqsmooth.factors._factor import linearize_rows

    return linearize_rows(factor, states)


def _states(states, combined):
    import eqsmooth as eqs

    out = (
        eqs.SE3.exp(jnp.asarray(states["pose_i"])),
        jnp.asarray(states["vel_i"]),
        eqs.SE3.exp(jnp.asarray(states["pose_j"])),
        jnp.asarray(states["vel_j"]),
        jnp.asarray(states["bias_i"]),
    )
    return out + (jnp.asarray(states["bias_j"]),) if combined else out


# ------------------------------------------------------------------ GTSAM parity


def test_preintegration_matches_gtsam():
    acc, gyro, dt, bias_hat, _ = _data()
    ours = {k: np.asarray(v) for k, v in _summary(_ours()).items()}
    for row, (pim, cpim) in enumerate(_gtsam_pims(acc, gyro, dt, bias_hat)):
        np.testing.assert_allclose(ours["delta_t"][row], pim.deltaTij(), atol=1e-14)
        np.testing.assert_allclose(
            ours["preintegrated"][row], pim.preintegrated(), atol=1e-12
        )
        np.testing.assert_allclose(
            ours["delta_R"][row], pim.deltaRij().matrix(), atol=1e-12
        )
        np.testing.assert_allclose(ours["delta_p"][row], pim.deltaPij(), atol=1e-12)
        np.testing.assert_allclose(ours["delta_v"][row], pim.deltaVij(), atol=1e-12)
        scale9 = np.abs(pim.preintMeasCov()).max()
        np.testing.assert_allclose(
            ours["covariance"][row], pim.preintMeasCov(), atol=1e-12 * scale9
        )
        np.testing.assert_allclose(
            ours["residual_covariance"][row],
            pim.residualCovariance(),
            atol=1e-12 * scale9,
        )
        scale15 = np.abs(cpim.preintMeasCov()).max()
        np.testing.assert_allclose(
            ours["combined_covariance"][row],
            cpim.preintMeasCov(),
            atol=1e-12 * scale15,
        )
        np.testing.assert_allclose(
            ours["combined_residual_covariance"][row],
            cpim.residualCovariance(),
            atol=1e-12 * scale15,
        )
        np.testing.assert_allclose(ours["bias_hat"][row], bias_hat[row])


@eqx.filter_jit
def _predict(pim, pose_i, vel_i, bias_i):
    pose_j, vel_j = pim.predict(pose_i, vel_i, bias_i, jnp.asarray(GRAVITY))
    return pose_j.as_matrix(), vel_j


def test_predict_matches_gtsam():
    """GTSAM's `predict(state_i, bias)` at a bias other than the integration
    bias: it applies the bias-correction Jacobians, so this checks ours."""
    gtsam = _gtsam()
    import eqsmooth as eqs

    acc, gyro, dt, bias_hat, states = _data()
    poses_i = eqs.SE3.exp(jnp.asarray(states["pose_i"]))
    pose_j, vel_j = _predict(
        _ours(), poses_i, jnp.asarray(states["vel_i"]), jnp.asarray(states["bias_i"])
    )
    for row, (pim, _) in enumerate(_gtsam_pims(acc, gyro, dt, bias_hat)):
        b = states["bias_i"][row]
        nav = gtsam.NavState(_pose3(gtsam, poses_i[row]), states["vel_i"][row])
        want = pim.predict(nav, gtsam.imuBias.ConstantBias(b[:3], b[3:]))
        np.testing.assert_allclose(pose_j[row], want.pose().matrix(), atol=1e-12)
        np.testing.assert_allclose(vel_j[row], want.velocity(), atol=1e-12)


@pytest.mark.parametrize("combined", [False, True], ids=["imu", "combined"])
def test_factor_residual_and_jacobians_match_gtsam(combined):
    gtsam = _gtsam()
    import eqsmooth as eqs

    acc, gyro, dt, bias_hat, states = _data()
    imu, comb = _factors(_ours())
    factor = comb if combined else imu
    row_states = _states(states, combined)
    r, jacs = _rows(factor, row_states)
    ours_j = np.concatenate([np.asarray(j) for j in jacs], axis=2)
    poses_i = eqs.SE3.exp(jnp.asarray(states["pose_i"]))
    poses_j = eqs.SE3.exp(jnp.asarray(states["pose_j"]))
    columns = [(6, True), (3, False), (6, True), (3, False), (6, False)]
    if combined:
        columns.append((6, False))
    for row, (pim, cpim) in enumerate(_gtsam_pims(acc, gyro, dt, bias_hat)):
        if combined:
            g = gtsam.CombinedImuFactor(0, 1, 2, 3, 4, 5, cpim)
        else:
            g = gtsam.ImuFactor(0, 1, 2, 3, 4, pim)
        values = _values(gtsam, poses_i, poses_j, states, row)
        err = g.unwhitenedError(values)
        assert np.abs(err).max() > 0.1  # random states: far from the optimum
        np.testing.assert_allclose(r[row], err, atol=1e-10)
        np.testing.assert_allclose(
            ours_j[row], _gtsam_jacobian(g, values, columns), atol=1e-9
        )
        # The default noise is GTSAM's installed noise model.
        cov = np.linalg.inv(g.noiseModel().R().T @ g.noiseModel().R())
        info = np.asarray(
            factor.noise.sqrt_information[row].T @ factor.noise.sqrt_information[row]
        )
        np.testing.assert_allclose(
            np.linalg.inv(info), cov, rtol=1e-8, atol=1e-12 * np.abs(cov).max()
        )


def _kitti():
    """GTSAM's KITTI IMU file and metadata: calibration row, IMU rows
    `(time, dt, acc, gyro)` and GPS rows `(time, x, y, z)`."""
    gtsam = _gtsam()
    meta = np.loadtxt(
        gtsam.findExampleDataFile("KittiEquivBiasedImu_metadata.txt"), skiprows=1
    )
    imu = np.loadtxt(gtsam.findExampleDataFile("KittiEquivBiasedImu.txt"), skiprows=1)
    gps = np.loadtxt(
        gtsam.findExampleDataFile("KittiGps_converted.txt"), skiprows=1, delimiter=","
    )
    return meta, imu, gps


def _kitti_intervals(imu, gps, first, count):
    """The samples of GTSAM's IMUKittiExampleGPS.py between consecutive GPS
    fixes `first, ..., first + count` (a sample at a fix's time belongs to the
    interval that ends there), padded to one length with a mask."""
    times = imu[:, 0]
    rows, j = [], int(np.searchsorted(times, gps[first, 0]))
    for i in range(first + 1, first + count + 1):
        t_prev, t = gps[i - 1, 0], gps[i, 0]
        take = []
        while j < len(times) and times[j] <= t:
            if times[j] >= t_prev:
                take.append(j)
            j += 1
        rows.append(take)
    k = max(len(r) for r in rows)
    idx = np.array([r + [r[-1]] * (k - len(r)) for r in rows])
    mask = np.array([[s < len(r) for s in range(k)] for r in rows])
    return imu[idx], mask, rows


@eqx.filter_jit
def _navigation_error(*args):
    import eqsmooth as eqs

    return eqs.factors.navigation_error(*args)


def test_kitti_stretch_matches_gtsam():
    gtsam = _gtsam()
    import eqsmooth as eqs

    meta, imu, gps = _kitti()
    acc_sigma, gyro_sigma, int_sigma = meta[6], meta[7], meta[8]
    samples, mask, rows = _kitti_intervals(imu, gps, first=1, count=4)
    assert len({len(r) for r in rows}) > 1  # padded: intervals differ in length
    bias_hat = np.array([0.02, -0.01, 0.03, 1e-4, -2e-4, 3e-4])
    params = eqs.ImuParams.make_u(
        9.8,
        accelerometer_sigma=acc_sigma,
        gyroscope_sigma=gyro_sigma,
        integration_sigma=int_sigma,
    )
    ours = eqs.preintegrate(
        params, samples[..., 2:5], samples[..., 5:8], samples[..., 1], bias_hat, mask
    )
    p = gtsam.PreintegrationParams.MakeSharedU(9.8)
    p.setAccelerometerCovariance(np.eye(3) * acc_sigma**2)
    p.setGyroscopeCovariance(np.eye(3) * gyro_sigma**2)
    p.setIntegrationCovariance(np.eye(3) * int_sigma**2)
    p.setOmegaCoriolis(np.zeros(3))  # as IMUKittiExampleGPS.py sets it
    b = gtsam.imuBias.ConstantBias(bias_hat[:3], bias_hat[3:])
    summary = {k: np.asarray(v) for k, v in _summary(ours).items()}
    for row, take in enumerate(rows):
        pim = gtsam.PreintegratedImuMeasurements(p, b)
        for j in take:
            pim.integrateMeasurement(imu[j, 2:5], imu[j, 5:8], imu[j, 1])
        np.testing.assert_allclose(summary["delta_t"][row], pim.deltaTij(), atol=1e-12)
        np.testing.assert_allclose(
            summary["preintegrated"][row], pim.preintegrated(), atol=1e-10
        )
        np.testing.assert_allclose(
            summary["residual_covariance"][row],
            pim.residualCovariance(),
            atol=1e-10 * np.abs(pim.residualCovariance()).max(),
        )
        # The factor at a state near the drive's: GPS position, identity
        # attitude, a guessed velocity.
        c, z = np.cos(0.005), np.sin(0.005)
        pose_i = eqs.SE3(np.r_[1.0, 0.0, 0.0, 0.0, gps[row + 1, 1:]])
        pose_j = eqs.SE3(np.r_[c, 0.0, 0.0, z, gps[row + 2, 1:]])
        vel = np.array([1.0, 0.5, 0.0])
        g = gtsam.ImuFactor(0, 1, 2, 3, 4, pim)
        v = gtsam.Values()
        v.insert(0, _pose3(gtsam, pose_i))
        v.insert(1, vel)
        v.insert(2, _pose3(gtsam, pose_j))
        v.insert(3, vel)
        v.insert(4, b)
        one = jax.tree_util.tree_map(lambda x: x[row], ours)
        r = _navigation_error(
            one, params.gravity, pose_i, vel, pose_j, vel, jnp.asarray(bias_hat)
        )
        np.testing.assert_allclose(r, g.unwhitenedError(v), atol=1e-9)


# ------------------------------------------------------------------ padding


def test_mask_skips_padding():
    """A padded interval with its padding masked out equals the unpadded one,
    whatever the padding holds."""
    import eqsmooth as eqs

    acc, gyro, dt, bias_hat, _ = _data()
    short = eqs.preintegrate(_params(), acc[:, :4], gyro[:, :4], dt[:, :4], bias_hat)
    junk_acc = acc.copy()
    junk_acc[:, 4:] = 1e3
    junk_acc[0, 5] = np.nan  # a missing sample
    junk_dt = dt.copy()
    junk_dt[:, 4:] = -1.0  # not positive: allowed only because masked out
    mask = np.arange(K) < 4
    padded = eqs.preintegrate(_params(), junk_acc, gyro, junk_dt, bias_hat, mask)
    for a, b in zip(
        jax.tree_util.tree_leaves(short), jax.tree_util.tree_leaves(padded)
    ):
        np.testing.assert_allclose(a, b, atol=1e-14)
    # The NaN in the padding reaches no derivative.
    loss = lambda p: jnp.sum(
        eqs.preintegrate(p, junk_acc, gyro, junk_dt, bias_hat, mask).covariance
    )
    grads = jax.grad(loss)(_params())
    assert all(np.all(np.isfinite(g)) for g in jax.tree_util.tree_leaves(grads))
    assert np.abs(grads.accelerometer_covariance).max() > 0


# ------------------------------------------------------------------ gradients


def _central(fn, x, eps=1e-6):
    x = np.asarray(x, np.float64)
    out = np.zeros(x.shape)
    for idx in np.ndindex(x.shape):
        d = np.zeros(x.shape)
        d[idx] = eps
        out[idx] = (float(fn(jnp.asarray(x + d))) - float(fn(jnp.asarray(x - d)))) / (
            2 * eps
        )
    return out


@eqx.filter_jit
def _nll(sigmas, bias_i, acc, gyro, dt):
    """Joint NLL of an ImuFactor + CombinedImuFactor graph at fixed states, as a
    function of the noise sigmas `(acc, gyro, integration, bias_acc,
    bias_omega)`, the bias at `i` and the samples."""
    import eqsmooth as eqs

    _, _, _, bias_hat, states = _data()
    params = eqs.ImuParams.from_sigmas(jnp.asarray(GRAVITY), *sigmas)
    pim = eqs.preintegrate(params, acc, gyro, dt, jnp.asarray(bias_hat))
    imu, comb = _pair(pim, params), _pair(pim, params, combined=True)
    s = _states(states, combined=True)
    values = {
        "x": eqs.SE3(jnp.concatenate([s[0].wxyz_xyz, s[2].wxyz_xyz])),
        "v": jnp.concatenate([s[1], s[3]]),
        "b": jnp.concatenate([bias_i, s[5]]),
    }
    return eqs.joint_nll(eqs.FactorGraph([imu, comb]), values, reduction="sum")


def test_nll_gradient_matches_central_differences():
    acc, gyro, dt, _, states = _data()
    sigmas = jnp.array([0.15, 0.04, 0.01, 0.03, 0.01])
    bias_i = jnp.asarray(states["bias_i"])
    args = (sigmas, bias_i, jnp.asarray(acc), jnp.asarray(gyro), jnp.asarray(dt))
    grads = jax.grad(_nll, argnums=(0, 1, 2, 3, 4))(*args)
    for k, g in enumerate(grads):

        def f(x, k=k):
            a = list(args)
            a[k] = x
            return _nll(*a)

        # The samples: check a slice (every entry costs two evaluations).
        x = np.asarray(args[k])
        if k in (1, 2, 3, 4):
            sub = (0, slice(0, 2)) if k != 1 else (0,)

            def f(y, k=k, sub=sub, x=x):
                full = np.array(x)
                full[sub] = np.asarray(y)
                a = list(args)
                a[k] = jnp.asarray(full)
                return _nll(*a)

            want = _central(f, x[sub])
            got = np.asarray(g)[sub]
        else:
            want = _central(f, x)
            got = np.asarray(g)
        assert np.abs(want).max() > 1e-3
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * np.abs(want).max())


# A small IMU + GPS smoothing problem: 3 keyframes, 2 IMU intervals.


@eqx.filter_jit
def _solve_position(acc_sigma, bias0, acc, gyro, dt):
    import eqsmooth as eqs

    _, _, _, bias_hat, _ = _data()
    params = eqs.ImuParams.from_sigmas(
        jnp.asarray([0.0, 0.0, -9.81]), acc_sigma, 0.02, 0.01, 0.01, 1e-3
    )
    pim = eqs.preintegrate(params, acc[:2], gyro[:2], dt[:2], jnp.zeros(6))
    V = eqs.Var
    chain = eqs.factors.imu_chain(pim, params, jnp.full(6, 0.05))
    gps = eqs.TranslationPriorFactor(
        V("x", [0, 1, 2]),
        jnp.array([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.05, 0.0]]),
        eqs.IsotropicNoise.from_sigma(jnp.asarray(0.5)),
    )
    prior = eqs.PriorFactor(
        V("x", [0]),
        eqs.SE3.identity((1,), jnp.float64),
        eqs.DiagonalNoise.from_sigmas(jnp.array([[1.0, 1.0, 1.0, 0.1, 0.1, 0.1]])),
    )
    vprior = eqs.PriorFactor(
        V("v", [0]), jnp.zeros((1, 3)), eqs.IsotropicNoise.from_sigma(jnp.asarray(1.0))
    )
    bprior = eqs.PriorFactor(
        V("b", [0]), bias0[None], eqs.IsotropicNoise.from_sigma(jnp.asarray(0.1))
    )
    graph = eqs.FactorGraph([*chain, gps, prior, vprior, bprior])
    values = {
        "x": eqs.SE3.identity((3,), jnp.float64),
        "v": jnp.zeros((3, 3)),
        "b": jnp.zeros((3, 6)),
    }
    sol = eqs.least_squares(
        graph,
        values,
        eqs.LevenbergMarquardt(ftol=1e-14, gtol=1e-12, xtol=1e-14),
        max_steps=60,
    )
    x = sol.value["x"]
    return jnp.sum(x.translation()[2] * jnp.array([1.0, 2.0, 3.0])) + jnp.sum(
        sol.value["b"][2]
    )


@pytest.mark.slow
def test_solve_gradient_matches_central_differences():
    """Through a whole IMU + GPS solve (implicit adjoint): derivatives in the
    accelerometer sigma, the prior bias and a few samples."""
    acc, gyro, dt, _, _ = _data()
    acc = acc * 0.1 + [0.0, 0.0, 9.81 * 0.9]  # a gentle drive
    gyro = gyro * 0.1
    args = [
        jnp.asarray(0.2),
        jnp.full(6, 0.01),
        jnp.asarray(acc),
        jnp.asarray(gyro),
        jnp.asarray(dt),
    ]
    grads = jax.grad(_solve_position, argnums=(0, 1, 2, 3))(*args)

    def partial(k, sub):
        x = np.asarray(args[k])

        def f(y):
            full = np.array(x)
            full[sub] = np.asarray(y)
            a = list(args)
            a[k] = jnp.asarray(full)
            return _solve_position(*a)

        return _central(f, x[sub], eps=1e-5), np.asarray(grads[k])[sub]

    for k, sub in ((0, ()), (1, slice(None)), (2, (0, 1)), (3, (1, 2))):
        want, got = partial(k, sub)
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-6)
    assert np.abs(np.asarray(grads[2])).max() > 1e-4


# ------------------------------------------------------------------ hostile input


def test_hostile_preintegration_input():
    import eqsmooth as eqs

    acc, gyro, dt, bias_hat, _ = _data()
    p = _params()
    with pytest.raises(
        ValueError, match=r"preintegrate: accelerometer must have shape"
    ):
        eqs.preintegrate(p, acc[..., :2], gyro[..., :2], dt)
    with pytest.raises(ValueError, match=r"accelerometer has shape .* gyroscope has"):
        eqs.preintegrate(p, acc, gyro[:, :4], dt)
    with pytest.raises(ValueError, match=r"dt of shape \(3, 4\) does not broadcast"):
        eqs.preintegrate(p, acc, gyro, dt[:, :4])
    bad = dt.copy()
    bad[1, 2] = 0.0
    with pytest.raises(ValueError, match=r"dt must be positive .* dt\[1, 2\] = 0.0"):
        eqs.preintegrate(p, acc, gyro, bad)
    nan = gyro.copy()
    nan[2, 1, 0] = np.nan
    with pytest.raises(ValueError, match=r"gyroscope\[2, 1\] = .* is not finite"):
        eqs.preintegrate(p, acc, nan, dt)
    with pytest.raises(ValueError, match=r"bias_hat must have shape \(\*batch, 6\)"):
        eqs.preintegrate(p, acc, gyro, dt, bias_hat[:, :3])
    with pytest.raises((TypeError, ValueError), match=r"mask"):
        eqs.preintegrate(p, acc, gyro, dt, bias_hat, np.ones((N, K)))
    with pytest.raises(TypeError, match=r"params"):
        eqs.preintegrate(GRAVITY, acc, gyro, dt)
    # Under jit the durations are checked at run time.
    run = jax.jit(lambda d: eqs.preintegrate(p, acc, gyro, d).delta_t)
    with pytest.raises(Exception, match=r"dt must be positive and finite"):
        run(jnp.asarray(bad))


def test_hostile_params():
    import eqsmooth as eqs

    with pytest.raises(ValueError, match=r"ImuParams.gravity must have shape \(3,\)"):
        eqs.ImuParams(jnp.zeros(2), SA, SG)
    with pytest.raises(ValueError, match=r"ImuParams.gyroscope_covariance must have"):
        eqs.ImuParams(jnp.asarray(GRAVITY), SA, np.eye(2))
    with pytest.raises(ValueError, match=r"accelerometer_covariance must be positive"):
        eqs.ImuParams(jnp.asarray(GRAVITY), -np.eye(3), SG)
    asym = SA.copy()
    asym[0, 1] += 0.01
    with pytest.raises(ValueError, match=r"accelerometer_covariance must be symmetric"):
        eqs.ImuParams(jnp.asarray(GRAVITY), asym, SG)
    with pytest.raises(ValueError, match=r"gyroscope_sigma must be non-negative"):
        eqs.ImuParams.make_u(accelerometer_sigma=0.1, gyroscope_sigma=-0.1)
    with pytest.raises(ValueError, match=r"accelerometer_sigma must be a scalar"):
        eqs.ImuParams.make_u(accelerometer_sigma=np.ones(2), gyroscope_sigma=0.1)


def test_hostile_factor_input():
    import eqsmooth as eqs

    pim = _ours()
    V = eqs.Var
    with pytest.raises(
        ValueError,
        match=r"ImuFactor.pim has batch shape \(3,\) but "
        r"the factor has 2 rows",
    ):
        _pair(pim, _params(), first=[0, 1], second=[1, 2])
    # (The type names `pim`: the message of the runtime type check or ours.)
    with pytest.raises(TypeError, match=r"pim"):
        eqs.ImuFactor(
            V("x", [0]),
            V("v", [0]),
            V("x", [1]),
            V("v", [1]),
            V("b", [0]),
            {"delta_t": 1.0},
            _params(),
        )
    with pytest.raises(ValueError, match=r"ImuFactor.gravity must have shape"):
        _pair(pim, jnp.zeros(2))
    # No bias random walk in the parameters: the combined covariance is singular.
    no_walk = eqs.ImuParams(jnp.asarray(GRAVITY), SA, SG, SI)
    acc, gyro, dt, bias_hat, _ = _data()
    pim0 = eqs.preintegrate(no_walk, acc, gyro, dt, bias_hat)
    with pytest.raises(
        ValueError,
        match=r"CombinedImuFactor: the combined "
        r"preintegrated covariance of rows \[0, 1, 2\]"
        r" is not positive definite",
    ):
        _pair(pim0, no_walk, combined=True)
    # Wrong variable kinds name the factor and the variable.
    imu, _ = _factors(pim)
    _, _, _, _, states = _data()
    s = list(_states(states, combined=False))
    with pytest.raises(
        ValueError,
        match=r"ImuFactor: the bias_i variable must hold "
        r"\(6,\) biases",
    ):
        _rows(imu, tuple(s[:4]) + (s[4][:, :3],))
    with pytest.raises(
        TypeError,
        match=r"ImuFactor: the pose_j variable must hold "
        r"SE3 values",
    ):
        _rows(imu, (s[0], s[1], s[1], s[3], s[4]))


# ------------------------------------------------------------------ the chain


WALK = np.array([0.05, 0.06, 0.07, 1e-3, 2e-3, 3e-3])


def _chain_values(states):
    """The random states of `_data` as a chain of 2N keyframes (first, then
    second): per-group values and the same as one `(pose, velocity, bias)`
    group."""
    import eqsmooth as eqs

    s = _states(states, combined=True)
    split = {
        "x": eqs.SE3(jnp.concatenate([s[0].wxyz_xyz, s[2].wxyz_xyz])),
        "v": jnp.concatenate([s[1], s[3]]),
        "b": jnp.concatenate([s[4], s[5]]),
    }
    return split, {"s": (split["x"], split["v"], split["b"])}


@pytest.mark.parametrize("combined", [False, True], ids=["walk", "combined"])
def test_imu_chain_and_transition_match_hand_built_factors(combined):
    """`imu_chain` is the ImuFactor + bias BetweenFactor stacks (or the
    CombinedImuFactor stack) between consecutive keyframes, and
    `ImuTransitionFactor` on one `(pose, velocity, bias)` group has the same
    cost; `bias_walk_sigmas` is √samples times the per-sample sigmas."""
    import eqsmooth as eqs

    _, _, _, _, states = _data()
    pim = _ours()
    walk = None if combined else WALK
    ids = np.array([0, 3, 1, 4])  # keyframes in any order
    pim_chain = jax.tree_util.tree_map(lambda a: a[: len(ids) - 1], pim)
    chain = eqs.factors.imu_chain(
        pim_chain, _params(), walk, ids=ids, combined=combined
    )
    assert len(chain) == (1 if combined else 2)
    i, j = ids[:-1], ids[1:]
    V = eqs.Var
    by_hand = [_pair(pim_chain, _params(), combined, first=i, second=j)]
    if not combined:
        by_hand.append(
            eqs.BetweenFactor(
                V("b", i),
                V("b", j),
                jnp.zeros((len(i), 6)),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(WALK)),
            )
        )
    transition = eqs.factors.ImuTransitionFactor(
        V("s", i), V("s", j), pim_chain, _params(), walk
    )
    split, joint = _chain_values(states)
    costs = [
        float(eqs.FactorGraph(chain).cost(split)),
        float(eqs.FactorGraph(by_hand).cost(split)),
        float(eqs.FactorGraph([transition]).cost(joint)),
    ]
    assert costs[0] > 1.0
    np.testing.assert_allclose(costs, costs[0], rtol=1e-12)
    sig = eqs.factors.bias_walk_sigmas(0.1, jnp.array([1.0, 2.0, 3.0]), [4.0, 9.0])
    np.testing.assert_allclose(
        sig, [[0.2, 0.2, 0.2, 2.0, 4.0, 6.0], [0.3, 0.3, 0.3, 3.0, 6.0, 9.0]]
    )


def test_hostile_chain_input():
    import eqsmooth as eqs

    pim = _ours()
    with pytest.raises(ValueError, match=r"imu_chain: give bias_walk_sigmas"):
        eqs.factors.imu_chain(pim, _params())
    with pytest.raises(ValueError, match=r"imu_chain: combined=True takes"):
        eqs.factors.imu_chain(pim, _params(), WALK, combined=True)
    with pytest.raises(
        ValueError, match=r"imu_chain: bias_walk_sigmas must have shape \(6,\) or"
    ):
        eqs.factors.imu_chain(pim, _params(), WALK[:3])
    with pytest.raises(ValueError, match=r"imu_chain: ids must hold the 4 keyframes"):
        eqs.factors.imu_chain(pim, _params(), WALK, ids=[0, 1, 2])
    # (The type names `pim`: the message of the runtime type check or ours.)
    with pytest.raises(TypeError, match=r"pim"):
        eqs.factors.imu_chain({"delta_t": 1.0}, _params(), WALK)
    # (The runtime type check or ours names `samples`.)
    with pytest.raises((TypeError, ValueError), match=r"samples"):
        eqs.factors.bias_walk_sigmas(0.1, 0.1, np.ones((2, 2)))
    V = eqs.Var
    a, b = V("s", [0, 1, 2]), V("s", [1, 2, 3])
    with pytest.raises(
        ValueError,
        match=r"ImuTransitionFactor.bias_walk_sigmas must have shape \(6,\) or "
        r"\(3, 6\)",
    ):
        eqs.factors.ImuTransitionFactor(a, b, pim, _params(), np.ones((2, 6)))
    with pytest.raises(ValueError, match=r"bias_walk_sigmas must be positive"):
        eqs.factors.ImuTransitionFactor(a, b, pim, _params(), -WALK)
    factor = eqs.factors.ImuTransitionFactor(a, b, pim, _params(), WALK)
    _, _, _, _, states = _data()
    s = _states(states, combined=True)
    with pytest.raises(
        TypeError, match=r"ImuTransitionFactor: the state_i variable must hold"
    ):
        _rows(factor, (s[0], (s[2], s[3], s[5])))


def test_fixed_lag_imu_chain_matches_batch():
    """`ImuTransitionFactor` as the transition of `fixed_lag_smoother`: a
    chain of 12 keyframes with one position fix at keyframe 8 (heading and
    velocity nearly free before it, as in the KITTI example's first
    windows), smoothed with lag = T, gives the batch solution of the same
    graph built by `imu_chain` with the initial belief as priors. The
    windows use λ₀ = 1e-14, as `examples/kitti_imu_gps.py --fixed-lag` does."""
    import eqsmooth as eqs

    rng = np.random.default_rng(3)
    T, k = 12, 10
    n = (T - 1) * k
    # A car turning gently: constant forward acceleration and yaw rate.
    acc = np.tile([0.3, 0.2, 9.81], (n, 1)) + rng.normal(size=(n, 3)) * 0.01
    gyro = np.tile([0.0, 0.0, 0.1], (n, 1)) + rng.normal(size=(n, 3)) * 1e-3
    params = eqs.ImuParams.make_u(
        9.81, accelerometer_sigma=0.01, gyroscope_sigma=1.75e-4
    )
    pim = eqs.preintegrate(
        params,
        acc.reshape(T - 1, k, 3),
        gyro.reshape(T - 1, k, 3),
        np.full((T - 1, k), 0.1),
    )
    walk = eqs.factors.bias_walk_sigmas(1.67e-4, 2.91e-6, np.full(T - 1, k))
    ids = np.arange(T)
    V = eqs.Var
    fix_at, fix = 8, jnp.array([[40.0, 12.0, 0.5]])
    mean = (eqs.SE3.identity(), jnp.array([1.0, 0.0, 0.0]), jnp.zeros(6))
    sigmas = np.r_[[1.0] * 3, [1.0] * 3, [100.0] * 3, [0.1] * 3, [5e-5] * 3]
    solver = eqs.LevenbergMarquardt(
        ftol=1e-12, gtol=1e-9, xtol=1e-12, initial_damping=1e-14
    )
    sol = eqs.filters.fixed_lag_smoother(
        eqs.factors.ImuTransitionFactor(
            V("s", ids[:-1]), V("s", ids[1:]), pim, params, walk
        ),
        [
            eqs.FunctionFactor(
                _fix_residual,
                (V("s", [fix_at]),),
                eqs.IsotropicNoise.from_sigma(0.2),
                data=fix,
                residual_dim=3,
            )
        ],
        mean,
        jnp.diag(jnp.asarray(sigmas) ** 2),
        lag=T,
        solver=solver,
    )
    unit = lambda x: jnp.broadcast_to(x, (1, *jnp.shape(x)))
    graph = eqs.FactorGraph(
        [
            *eqs.factors.imu_chain(pim, params, walk),
            eqs.TranslationPriorFactor(
                V("x", [fix_at]), fix, eqs.IsotropicNoise.from_sigma(0.2)
            ),
            eqs.PriorFactor(
                V("x", [0]),
                eqs.SE3.identity((1,)),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(sigmas[:6])),
            ),
            eqs.PriorFactor(
                V("v", [0]),
                unit(mean[1]),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(sigmas[6:9])),
            ),
            eqs.PriorFactor(
                V("b", [0]),
                unit(mean[2]),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(sigmas[9:])),
            ),
        ]
    )
    last = jax.tree_util.tree_map(lambda a: a[-1], sol.windows)
    batch = eqs.least_squares(
        graph, {"x": last[0], "v": last[1], "b": last[2]}, solver, max_steps=20
    )
    got = np.asarray(sol.lagged_mean[0].translation())
    np.testing.assert_allclose(
        got, np.asarray(batch.value["x"].translation()), atol=1e-6
    )
    np.testing.assert_allclose(sol.lagged_mean[1], batch.value["v"], atol=1e-6)
    assert np.abs(got[fix_at] - fix[0]).max() < 0.5


def _fix_residual(state, position, params):
    return state[0].translation() - position


# ------------------------------------------------------------------ the example


@pytest.mark.slow
def test_kitti_example_quick_matches_gtsam(tmp_path):
    """`python examples/kitti_imu_gps.py --quick`: GTSAM's IMU + GPS example
    as one batch solve, and GTSAM's solve of the same graph in the same run,
    agree. Slow: a whole run in a child process (about 2 minutes on 2 shared
    cores, nearly all compilation)."""
    _gtsam()
    import json
    import subprocess
    import sys
    from pathlib import Path

    from helpers import child_env

    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "kitti.json"
    run = subprocess.run(
        [
            sys.executable,
            str(root / "examples" / "kitti_imu_gps.py"),
            "--quick",
            "--json",
            str(out),
        ],
        env=child_env(),
        cwd=root,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert run.returncode == 0, run.stderr[-3000:]
    summary = json.loads(out.read_text())
    assert summary["keyframes"] == 60
    assert summary["difference"]["max_position_m"] < 1e-6
    assert summary["difference"]["max_rotation_rad"] < 1e-6
    assert summary["eqsmooth"]["rmse_to_all_gps_m"] < 5.0
