"""Robust kernels: ρ and ρ' against closed forms (and GTSAM's mEstimators
when installed), ρ' = dρ/ds by autodiff, a gradient w.r.t. the learnable
scale through a solve against finite differences, and an outlier graph
solved to GTSAM's answer."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest


def _kernels():
    import eqsmooth as eqs

    return {
        "tukey": eqs.TukeyNoise,
        "geman_mcclure": eqs.GemanMcClureNoise,
        "welsch": eqs.WelschNoise,
        "dcs": eqs.DCSNoise,
        "fair": eqs.FairNoise,
        "l2_dead_zone": eqs.L2WithDeadZoneNoise,
        "truncated": eqs.TruncatedQuadraticNoise,
    }


def _closed_form(name, e, c):
    """GTSAM-style loss(e) and weight(e) of the whitened error e (textbook
    formulas, written independently of the implementation)."""
    e = abs(e)
    if name == "tukey":
        if e <= c:
            return c * c / 6 * (1 - (1 - (e / c) ** 2) ** 3), (1 - (e / c) ** 2) ** 2
        return c * c / 6, 0.0
    if name == "geman_mcclure":
        return c * c * e * e / (2 * (c * c + e * e)), c**4 / (c * c + e * e) ** 2
    if name == "welsch":
        return c * c / 2 * (1 - np.exp(-((e / c) ** 2))), np.exp(-((e / c) ** 2))
    if name == "dcs":
        if e * e <= c:
            return e * e / 2, 1.0
        return c * (3 * e * e - c) / (2 * (c + e * e)), 4 * c * c / (c + e * e) ** 2
    if name == "fair":
        return c * c * (e / c - np.log1p(e / c)), 1 / (1 + e / c)
    if name == "l2_dead_zone":
        if e <= c:
            return 0.0, 0.0
        return 0.5 * (e - c) ** 2, 1 - c / e
    if name == "truncated":
        if e < c:
            return e * e / 2, 1.0
        return c * c / 2, 0.0
    raise AssertionError(name)


ERRORS = np.array([0.0, 0.3, 0.9, 1.29, 1.31, 2.0, 7.5])
SCALE = 1.3


@pytest.mark.parametrize("name", list(_kernels()))
def test_rho_and_weight_closed_forms(name):
    import eqsmooth as eqs

    noise = _kernels()[name](eqs.IsotropicNoise(sqrt_precision=1.0), SCALE)
    s = jnp.asarray(ERRORS**2)
    rho, drho = noise.rho(s)
    ref = np.array([_closed_form(name, e, SCALE) for e in ERRORS])
    # The cost ½ρ(s) is the M-estimator loss; ρ'(s) is its weight.
    np.testing.assert_allclose(0.5 * np.asarray(rho), ref[:, 0], rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(np.asarray(drho), ref[:, 1], rtol=1e-12, atol=1e-15)
    # ρ' is the derivative of ρ (away from the kinks), and every derivative
    # w.r.t. s and the scale is finite, zero residuals included.
    smooth = jnp.asarray([0.09, 0.81, 4.0, 56.25])
    d_auto = jax.vmap(jax.grad(lambda t: noise.rho(t)[0]))(smooth)
    np.testing.assert_allclose(
        np.asarray(d_auto), np.asarray(noise.rho(smooth)[1]), rtol=1e-10, atol=1e-14
    )

    def total(k):
        n = _kernels()[name](eqs.IsotropicNoise(sqrt_precision=1.0), k)
        r, w = n.rho(s)
        return jnp.sum(r) + jnp.sum(w)

    assert np.isfinite(float(jax.grad(total)(jnp.asarray(SCALE))))
    assert np.all(np.isfinite(np.asarray(jax.jacfwd(lambda t: noise.rho(t)[1])(s))))


def _gtsam_estimator(gtsam, name: str, scale: float):
    """GTSAM's m-estimator of the kernel `name`, at `scale`."""
    M = gtsam.noiseModel.mEstimator
    return {
        "tukey": M.Tukey,
        "geman_mcclure": M.GemanMcClure,
        "welsch": M.Welsch,
        "dcs": M.DCS,
        "fair": M.Fair,
        "l2_dead_zone": M.L2WithDeadZone,
        "truncated": M.TruncatedLeastSquares,
    }[name].Create(scale)


@pytest.mark.parametrize("name", list(_kernels()))
def test_matches_gtsam_mestimators(name):
    gtsam = pytest.importorskip("gtsam")
    import eqsmooth as eqs

    ref = _gtsam_estimator(gtsam, name, SCALE)
    noise = _kernels()[name](eqs.IsotropicNoise(sqrt_precision=1.0), SCALE)
    rho, drho = noise.rho(jnp.asarray(ERRORS**2))
    np.testing.assert_allclose(
        0.5 * np.asarray(rho), [ref.loss(e) for e in ERRORS], rtol=1e-12, atol=1e-15
    )
    np.testing.assert_allclose(
        np.asarray(drho), [ref.weight(e) for e in ERRORS], rtol=1e-12, atol=1e-15
    )


def test_per_row_scale_and_bad_scale():
    import eqsmooth as eqs

    noise = eqs.WelschNoise(
        eqs.IsotropicNoise(sqrt_precision=1.0), jnp.array([1.0, 2.0])
    )
    rho, _ = noise.rho(jnp.array([1.0, 1.0]))
    np.testing.assert_allclose(
        np.asarray(rho), [1 - np.exp(-1.0), 4 * (1 - np.exp(-0.25))]
    )
    with pytest.raises(ValueError, match="scale"):
        eqs.TukeyNoise(eqs.IsotropicNoise(sqrt_precision=1.0), -1.0)


# A robust mean of five 2-D points, one of them an outlier.
POINTS = np.array([[0.1, 0.0], [-0.1, 0.2], [0.0, -0.1], [0.2, 0.1], [3.0, -2.5]])


def _robust_mean(noise_cls, k):
    import eqsmooth as eqs

    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("p", np.zeros(5, int)),
                jnp.asarray(POINTS),
                noise_cls(eqs.IsotropicNoise.from_sigma(0.2), k),
            )
        ]
    )
    solver = eqs.GaussNewton(eqs.DenseCholesky(), ftol=1e-16, gtol=1e-14, xtol=1e-14)
    return eqs.least_squares(
        graph, {"p": jnp.zeros((1, 2))}, solver, max_steps=200
    ).value["p"][0]


@pytest.mark.parametrize(
    "name",
    [
        "welsch",
        "geman_mcclure",
        pytest.param("fair", marks=pytest.mark.slow),
        pytest.param("tukey", marks=pytest.mark.slow),
        pytest.param("dcs", marks=pytest.mark.slow),
    ],
)
def test_scale_gradient_through_solve(name):
    """d(loss of the solution)/d(scale) by the implicit adjoint against
    central finite differences of converged solves."""
    cls = _kernels()[name]
    k0 = {"dcs": 4.0}.get(name, 2.0)
    target = jnp.array([0.5, -0.5])

    @jax.jit
    def loss(k):
        return jnp.sum(jnp.square(_robust_mean(cls, k) - target))

    g = float(jax.grad(loss)(jnp.asarray(k0)))
    h = 1e-5
    fd = (float(loss(jnp.asarray(k0 + h))) - float(loss(jnp.asarray(k0 - h)))) / (2 * h)
    assert abs(g) > 1e-6  # the scale matters here
    np.testing.assert_allclose(g, fd, rtol=1e-4, atol=1e-9)


GPS_OUTLIERS = {2: np.array([4.0, -3.0]), 4: np.array([-2.5, 3.5])}


@pytest.mark.parametrize(
    "name",
    [
        "tukey",
        pytest.param(
            "dcs",
            marks=pytest.mark.xfail(
                reason="open: with DCS the answers differ from GTSAM's by up to "
                "2.2e-9 rad in heading and 2.5e-9 relative in cost (positions "
                "agree to 1e-9), unchanged by restarting GTSAM's LM; not yet "
                "explained (issue 15)",
                strict=False,
            ),
        ),
        pytest.param("geman_mcclure", marks=pytest.mark.slow),
        pytest.param("welsch", marks=pytest.mark.slow),
        pytest.param("fair", marks=pytest.mark.slow),
        pytest.param("l2_dead_zone", marks=pytest.mark.slow),
        pytest.param("truncated", marks=pytest.mark.slow),
    ],
)
def test_outlier_graph_matches_gtsam(name):
    """Pose2 odometry with GPS fixes, two of them gross outliers, each GPS fix
    behind a robust kernel: eqsmooth's optimum equals GTSAM's."""
    gtsam = pytest.importorskip("gtsam")
    import eqsmooth as eqs

    rng = np.random.default_rng(1)
    T = 6
    truth = np.stack(
        [np.arange(T) * 1.0, 0.2 * np.arange(T), 0.1 * np.arange(T)], axis=1
    )
    odo = []
    for i in range(T - 1):
        a = gtsam.Pose2(*truth[i])
        b = gtsam.Pose2(*truth[i + 1])
        d = a.between(b)
        odo.append([d.x(), d.y(), d.theta()] + 0.02 * rng.standard_normal(3))
    odo = np.array(odo)
    gps = truth[:, :2] + 0.1 * rng.standard_normal((T, 2))
    for i, off in GPS_OUTLIERS.items():
        gps[i] += off
    init = truth + 0.1 * rng.standard_normal((T, 3))
    odo_s, gps_s = np.array([0.05, 0.05, 0.02]), 0.1
    scale = {"dcs": 2.0, "l2_dead_zone": 0.5}.get(name, 2.0)
    est = _gtsam_estimator(gtsam, name, scale)

    g = gtsam.NonlinearFactorGraph()
    g.add(
        gtsam.PriorFactorPose2(
            0, gtsam.Pose2(*truth[0]), gtsam.noiseModel.Diagonal.Sigmas(odo_s)
        )
    )
    for i in range(T - 1):
        g.add(
            gtsam.BetweenFactorPose2(
                i, i + 1, gtsam.Pose2(*odo[i]), gtsam.noiseModel.Diagonal.Sigmas(odo_s)
            )
        )
    robust = gtsam.noiseModel.Robust.Create(
        est, gtsam.noiseModel.Isotropic.Sigma(2, gps_s)
    )
    for i in range(T):
        g.add(gtsam.PoseTranslationPrior2D(i, gps[i], robust))
    values = gtsam.Values()
    for i in range(T):
        values.insert(i, gtsam.Pose2(*init[i]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-16)
    params.setAbsoluteErrorTol(1e-16)
    params.setMaxIterations(1000)
    ref = gtsam.LevenbergMarquardtOptimizer(g, values, params).optimize()
    # IRLS converges linearly on robust costs, and GTSAM's LM stops on a
    # relative decrease of the cost: restart it from its answer (fresh
    # damping) until the answer no longer moves.
    for _ in range(5):
        ref = gtsam.LevenbergMarquardtOptimizer(g, ref, params).optimize()

    def se2(a):
        return eqs.SE2.from_xy_theta(
            jnp.asarray(a[:, 0]), jnp.asarray(a[:, 1]), jnp.asarray(a[:, 2])
        )

    ids = np.arange(T)
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", [0]), se2(truth[:1]), eqs.DiagonalNoise.from_sigmas(odo_s)
            ),
            eqs.BetweenFactor(
                eqs.Var("x", ids[:-1]),
                eqs.Var("x", ids[1:]),
                se2(odo),
                eqs.DiagonalNoise.from_sigmas(odo_s),
            ),
            eqs.TranslationPriorFactor(
                eqs.Var("x", ids),
                jnp.asarray(gps),
                _kernels()[name](eqs.IsotropicNoise.from_sigma(gps_s), scale),
            ),
        ]
    )
    # No cost-based stop (ftol=0): iterate until the step or gradient vanishes.
    solver = eqs.LevenbergMarquardt(ftol=0.0, gtol=1e-14, xtol=1e-15)
    sol = eqs.least_squares(
        graph, {"x": se2(init)}, solver, max_steps=500, throw=False
    ).value["x"]
    for i in range(T):
        p = ref.atPose2(i)
        np.testing.assert_allclose(
            [float(sol.x()[i]), float(sol.y()[i])], [p.x(), p.y()], atol=1e-9
        )
        d = float(sol.theta()[i]) - p.theta()
        assert abs(np.arctan2(np.sin(d), np.cos(d))) < 1e-9
    np.testing.assert_allclose(float(graph.cost({"x": sol})), g.error(ref), rtol=1e-9)
    # The outliers are down-weighted: the solution stays near the truth.
    assert np.max(np.abs(np.asarray(sol.translation()) - truth[:, :2])) < 0.5


def test_kernel_sweep_as_data_compiles_once():
    """KernelChoice: the kernel is data, so a sweep over all nine kernels on
    one graph is one compiled solve (issue 34), and each solve equals the one
    with the named kernel."""
    import jax
    from helpers import compiled_programs

    import eqsmooth as eqs
    from eqsmooth.factors._robust_kernels import KERNELS

    rng = np.random.default_rng(0)
    T = 8
    truth = np.cumsum(rng.normal(size=(T, 2)), axis=0)
    meas = truth + 0.1 * rng.normal(size=(T, 2))
    meas[3] += 6.0  # an outlier
    t = np.arange(T)

    def graph(noise):
        return eqs.FactorGraph(
            [
                eqs.PriorFactor(eqs.Var("x", t), jnp.asarray(meas), noise),
                eqs.BetweenFactor(
                    eqs.Var("x", t[:-1]),
                    eqs.Var("x", t[1:]),
                    jnp.asarray(np.diff(truth, axis=0)),
                    eqs.IsotropicNoise.from_sigma(0.1),
                ),
            ]
        )

    base = eqs.IsotropicNoise.from_sigma(0.1)
    solver = eqs.LevenbergMarquardt(eqs.DenseCholesky())
    init = {"x": jnp.asarray(meas)}
    # The first solve compiles; the eight others must not.
    k = jnp.asarray(2.0)
    first = eqs.RobustNoise(base, eqs.factors.KernelChoice(KERNELS[0]), k)
    eqs.least_squares(graph(first), init, solver, throw=False)
    with compiled_programs() as names:
        swept = {}
        for K in KERNELS:
            noise = eqs.RobustNoise(base, eqs.factors.KernelChoice(K), k)
            swept[K] = eqs.least_squares(graph(noise), init, solver, throw=False)
        jax.block_until_ready([s.value for s in swept.values()])
    assert names == [], names
    for K in KERNELS:
        named = eqs.least_squares(
            graph(eqs.RobustNoise(base, K(), jnp.asarray(2.0))),
            init,
            solver,
            throw=False,
        )
        np.testing.assert_allclose(
            swept[K].value["x"], named.value["x"], rtol=1e-9, atol=1e-9, err_msg=K.name
        )


def test_kernel_choice_scale_gradient_matches_finite_differences():
    """d/dk of the robust cost with the kernel chosen by data (lax.switch)."""
    import jax

    import eqsmooth as eqs
    from eqsmooth.factors._robust_kernels import KERNELS

    r = jnp.asarray(np.random.default_rng(3).normal(size=(6, 2)) * 2.0)
    t = np.arange(6)
    for K in KERNELS:

        def cost(log_k, K=K):
            noise = eqs.RobustNoise(
                eqs.IsotropicNoise.from_sigma(1.0),
                eqs.factors.KernelChoice(K),
                jnp.exp(log_k),
            )
            g = eqs.FactorGraph([eqs.PriorFactor(eqs.Var("x", t), r, noise)])
            return eqs.factors._graph.graph_cost(g, {"x": jnp.zeros((6, 2))})

        g = jax.grad(cost)(jnp.asarray(0.4))
        h = 1e-6
        fd = (cost(jnp.asarray(0.4 + h)) - cost(jnp.asarray(0.4 - h))) / (2 * h)
        np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-9, err_msg=K.name)


def test_kernel_choice_compiles_nothing():
    """Building a `KernelChoice` transfers its index: `jnp.asarray` of a
    Python int compiled a conversion program in every fresh process."""
    import jax
    from helpers import compiled_programs

    import eqsmooth as eqs
    from eqsmooth.factors._robust_kernels import KERNELS

    jax.clear_caches()
    with compiled_programs() as names:
        choices = [eqs.factors.KernelChoice(K) for K in KERNELS]
    assert names == [], names
    assert [int(c.index) for c in choices] == list(range(len(KERNELS)))
    assert all(c.index.dtype == jnp.int32 for c in choices)
