"""Student-t noise: its density, its errors, and its Laplace evidence."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats


def _graph(noise, y):
    import eqsmooth as eqs

    return eqs.FactorGraph([eqs.PriorFactor(eqs.Var("x", np.arange(len(y))), y, noise)])


@pytest.mark.parametrize("m", [1, 2])
def test_negative_log_likelihood_is_the_student_t_density(m):
    import eqsmooth as eqs

    rng = np.random.default_rng(0)
    sig = np.array([0.7, 2.0])[:m]
    y = jnp.asarray(rng.normal(size=(3, m)))
    x = jnp.asarray(rng.normal(size=(3, m)) * 3)
    nus = np.array([2.5, 4.0, 30.0])
    for dof in (3.0, jnp.asarray(nus)):  # shared, then per row
        noise = eqs.StudentTNoise(eqs.DiagonalNoise.from_sigmas(sig), dof, dim=m)
        got = float(_graph(noise, y).negative_log_likelihood({"x": x}))
        nu = np.broadcast_to(np.asarray(dof), (3,))
        want = -sum(
            stats.multivariate_t.logpdf(
                np.asarray(x[i] - y[i]), np.zeros(m), np.diag(sig**2), df=nu[i]
            )
            for i in range(3)
        )
        np.testing.assert_allclose(got, want, rtol=1e-10)


def test_dof_and_scale_gradients_match_finite_differences():
    """The joint NLL can learn ν and the scale: its gradient w.r.t. both
    matches float64 central differences."""
    import eqsmooth as eqs

    rng = np.random.default_rng(1)
    y = jnp.asarray(rng.standard_t(3, size=(6, 2)))
    x = jnp.zeros((6, 2))

    def nll(theta):
        base = eqs.DiagonalNoise(sqrt_precision=jnp.exp(-theta[1]) * jnp.ones(2))
        noise = eqs.StudentTNoise(base, jnp.exp(theta[0]), dim=2)
        return _graph(noise, y).negative_log_likelihood({"x": x})

    nll = jax.jit(nll)  # one program, not op by op
    theta = jnp.asarray([np.log(4.0), np.log(0.8)])
    grad = np.asarray(jax.jit(jax.grad(nll))(theta))
    h = 1e-6
    fd = [
        (float(nll(theta.at[i].add(h))) - float(nll(theta.at[i].add(-h)))) / (2 * h)
        for i in range(2)
    ]
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)


def test_large_dof_approaches_the_gaussian_and_float32_stays_float32():
    import eqsmooth as eqs

    y = jnp.asarray([[0.3], [-1.2]])
    x = jnp.asarray([[1.0], [0.5]])
    base = eqs.IsotropicNoise(sqrt_precision=2.0)
    g = float(_graph(base, y).negative_log_likelihood({"x": x}))
    t = float(_graph(eqs.StudentTNoise(base, 1e7), y).negative_log_likelihood({"x": x}))
    np.testing.assert_allclose(t, g, rtol=1e-5)
    x32, y32 = x.astype(jnp.float32), y.astype(jnp.float32)
    base32 = eqs.IsotropicNoise(sqrt_precision=jnp.float32(2))
    for dof in (4.0, np.float64(4.0), np.full(2, 4.0)):  # weak, strong, per row
        noise32 = eqs.StudentTNoise(base32, dof)
        for noise in (noise32, noise32.fisher_model()):
            nll = _graph(noise, y32).negative_log_likelihood({"x": x32})
            assert nll.dtype == jnp.float32
    # Large dof in float32: the density's constant used to lose 6 nats to
    # cancellation between two log-gammas (the NLL read 16.31 for 22.06).
    for dof in (30.0, 1e3, 1e7):
        want = float(
            _graph(eqs.StudentTNoise(base, dof), y).negative_log_likelihood({"x": x})
        )
        got = _graph(eqs.StudentTNoise(base32, jnp.float32(dof)), y32)
        got = float(got.negative_log_likelihood({"x": x32}))
        np.testing.assert_allclose(got, want, rtol=1e-5, err_msg=f"dof {dof}")


def test_rho_derivative_is_the_irls_weight():
    import eqsmooth as eqs

    noise = eqs.StudentTNoise(eqs.DiagonalNoise.from_sigmas(jnp.ones(2)), 3.5, dim=2)
    s = jnp.asarray([0.0, 0.3, 4.0, 50.0])
    rho, drho = noise.rho(s)
    auto = jax.vmap(jax.grad(lambda v: noise.rho(v[None])[0][0]))(s)
    np.testing.assert_allclose(drho, auto, rtol=1e-12)
    np.testing.assert_allclose(rho, 5.5 * np.log1p(np.asarray(s) / 3.5), rtol=1e-12)


def test_bad_student_t_arguments_name_the_field():
    import eqsmooth as eqs

    base = eqs.DiagonalNoise.from_sigmas(jnp.ones(2))
    with pytest.raises(ValueError, match=r"StudentTNoise\.dof must be positive"):
        eqs.StudentTNoise(base, 0.0, dim=2)
    with pytest.raises(TypeError, match=r"StudentTNoise\.base must be a Gaussian"):
        eqs.StudentTNoise(eqs.HuberNoise(base, 1.0), 3.0, dim=2)
    with pytest.raises(ValueError, match=r"StudentTNoise\.dim must be a positive int"):
        eqs.StudentTNoise(base, 3.0, dim=0)
    graph = _graph(eqs.StudentTNoise(base, 3.0), jnp.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"PriorFactor: StudentTNoise\.dim is 1 .*"):
        graph.cost({"x": jnp.ones((2, 2))})
    fn = eqx.filter_jit(
        lambda nu: eqs.StudentTNoise(base, nu, dim=2).rho(jnp.ones(2))[0]
    )
    with pytest.raises(eqx.EquinoxRuntimeError, match=r"StudentTNoise\.dof"):
        fn(jnp.asarray(-1.0))


def test_filters_reject_student_t_noise():
    import eqsmooth as eqs

    def step(a, b, data, params):
        return b - a

    t = np.arange(5)
    transition = eqs.FunctionFactor(
        step,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        eqs.IsotropicNoise.from_sigma(1.0),
    )
    dof = jnp.full(5, 3.0)  # per row: the probe of user models would misfire
    noise = eqs.StudentTNoise(eqs.IsotropicNoise.from_sigma(1.0), dof)
    measurement = eqs.PriorFactor(eqs.Var("x", t), jnp.zeros((5, 1)), noise)
    with pytest.raises(TypeError, match="StudentTNoise is robust"):
        eqs.ekf(transition, (measurement,), jnp.zeros(1), jnp.eye(1))


# ---------------------------------------------------------------------------
# The discovery model's evidence picks the right noise family
# ---------------------------------------------------------------------------

B, T = 24, 40
SPRING = 0.05
Q = np.array([0.05, 0.5])
PRIOR = np.array([20.0, 4.0])


def _dyn(x, u, params):
    return jnp.stack([x[0] + x[1], x[1] - params * x[0]])


def _meas(x, params):
    return x[:1]


def _oscillator(seed, heavy):
    from helpers import oscillator_states

    rng = np.random.default_rng(seed)
    xs = oscillator_states(rng, lambda p: -SPRING * p, PRIOR, Q, B, T)
    e = rng.standard_t(3, size=(B, T, 1)) if heavy else rng.normal(size=(B, T, 1))
    return jnp.asarray(xs[..., :1] + e)


@eqx.filter_jit
def _evidence(model, y):
    import eqsmooth.discover as dc

    def one(yb):
        graph = model.graph(yb, jnp.zeros((T, 1)), jnp.zeros(2))
        init = jnp.concatenate([yb, jnp.zeros_like(yb)], -1)
        return dc.laplace_log_marginal(graph, {"x": init})[0]

    return jnp.sum(jax.vmap(one)(y))


def _best_evidence(y, dof, scales):
    import eqsmooth.discover as dc

    out = []
    for r in scales:
        model = dc.ChainModel(
            _dyn,
            _meas,
            jnp.asarray(SPRING),
            Q,
            np.array([r]),
            PRIOR,
            (),
            measurement_dof=dof,
        )
        out.append(float(_evidence(model, y)))
    assert np.all(np.isfinite(out)), out
    return max(out)


def test_laplace_evidence_prefers_the_true_noise_family():
    """Student-t(3) measurement noise: the Student-t model's evidence beats the
    Gaussian model's, each at its best scale (seed 1: by 125 nats); Gaussian
    noise: the reverse (by 18.5 nats)."""
    scales = (0.7, 0.8, 1.0, 3**0.5, 2.0)
    heavy = _oscillator(1, heavy=True)
    margin = _best_evidence(heavy, 3.0, scales) - _best_evidence(heavy, None, scales)
    assert margin > 50.0, margin
    light = _oscillator(1, heavy=False)
    margin = _best_evidence(light, None, scales) - _best_evidence(light, 3.0, scales)
    assert margin > 8.0, margin


def test_laplace_evidence_of_student_t_noise_against_quadrature():
    """One scalar x ~ N(0, 3²) seen 20 times through Student-t(3) noise: the
    Laplace evidence (Fisher curvature) is within 0.3 nats of the exact
    marginal likelihood, by quadrature over x, on 8 data sets."""
    from scipy import integrate

    import eqsmooth as eqs
    import eqsmooth.discover as dc

    n, nu = 20, 3.0
    solver = eqs.GaussNewton(eqs.DenseCholesky())
    rng = np.random.default_rng(3)
    errors = []
    for _ in range(8):
        y = rng.normal(0, 3.0) + 0.6 * rng.standard_t(nu, n)
        noise = eqs.StudentTNoise(eqs.IsotropicNoise.from_sigma(1.0), nu)
        graph = eqs.FactorGraph(
            [
                eqs.PriorFactor(
                    eqs.Var("x", [0]),
                    jnp.zeros((1, 1)),
                    eqs.IsotropicNoise.from_sigma(3.0),
                ),
                eqs.PriorFactor(
                    eqs.Var("x", np.zeros(n, int)), jnp.asarray(y)[:, None], noise
                ),
            ]
        )
        start = {"x": jnp.full((1, 1), float(np.median(y)))}
        ll, _ = dc.laplace_log_marginal(graph, start, solver, max_steps=100)

        def density(x, y=y):
            return np.exp(
                stats.norm.logpdf(x, 0, 3) + np.sum(stats.t.logpdf(y - x, nu))
            )

        exact = integrate.quad(density, -30, 30, points=[np.median(y)], limit=400)[0]
        errors.append(float(ll) - np.log(exact))
    assert np.max(np.abs(errors)) < 0.3, errors


def test_chain_model_student_t_options():
    import eqsmooth as eqs
    import eqsmooth.discover as dc

    args = (_dyn, _meas, jnp.asarray(SPRING), Q, np.array([2.0]), PRIOR, ())
    model = dc.ChainModel(*args, measurement_dof=4.0)
    np.testing.assert_allclose(model.measurement_std, [2.0 * np.sqrt(2.0)])
    assert isinstance(model.measurement_noise(), eqs.StudentTNoise)
    assert isinstance(dc.ChainModel(*args).measurement_noise(), eqs.DiagonalNoise)
    np.testing.assert_allclose(dc.ChainModel(*args).measurement_std, [2.0])
    with pytest.raises(ValueError, match=r"measurement_dof must be None .* ν > 2"):
        dc.ChainModel(*args, measurement_dof=2.0)


def test_student_t_diagnostics_do_not_alarm_on_innovation_size():
    """Gaussian data of std 1 under a Student-t(4) model at its best scale
    (0.831, by quadrature): the moment-matched innovations are too small
    (NIS ≈ 0.76), which is the tails' doing, not structure: no alarm. The
    Gaussian model with the same std (1.175) raises one."""
    from scipy import integrate, optimize

    import eqsmooth.discover as dc
    from eqsmooth.discover._diagnostics import (
        innovation_tests,
        innovations_significant,
    )

    def expected_nll(scale):
        def integrand(x):
            return stats.norm.pdf(x) * (stats.t.logpdf(x / scale, 4) - np.log(scale))

        return -integrate.quad(integrand, -12, 12)[0]

    best = optimize.minimize_scalar(expected_nll, bounds=(0.3, 1.5), method="bounded")
    scale = float(best.x)
    y = np.asarray(_oscillator(2, heavy=False))
    data = dc.Sequences(y, np.zeros((B, 2)))
    xhat = np.concatenate([y, np.zeros_like(y)], -1)  # a linear model: any point
    args = (_dyn, _meas, jnp.asarray(SPRING), Q)
    robust = dc.ChainModel(*args, np.array([scale]), PRIOR, (), measurement_dof=4.0)
    out = innovation_tests(robust, data, xhat)
    assert out["nis_mean"] < 0.85 and out["nis_p_value"] < 1e-4, out["nis_mean"]
    assert not out["nis_alarm"] and not innovations_significant(out, 0.05)
    assert abs(out["diagnostic_nis_mean"] - 1.0) < 0.01, out["diagnostic_nis_mean"]
    assert 0.8 < out["diagnostic_scale"] < 0.9, out["diagnostic_scale"]
    std = float(robust.measurement_std[0])
    gaussian = dc.ChainModel(*args, np.array([std]), PRIOR, ())
    out = innovation_tests(gaussian, data, xhat)
    assert out["nis_alarm"] and innovations_significant(out, 0.05)
