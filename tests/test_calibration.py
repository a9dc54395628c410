"""eqsmooth.learn.gaussian_calibration, chi2_quantile and nees_band against scipy."""

import math

import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest


stats = pytest.importorskip("scipy.stats")


def _random_gaussians(rng, n, d):
    a = rng.normal(size=(n, d, d))
    cov = a @ np.swapaxes(a, -1, -2) + 0.2 * np.eye(d)
    err = np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, d)))
    return err, cov


@pytest.mark.parametrize("d", [1, 2, 3, 5])
def test_scores_match_scipy(d):
    import eqsmooth.learn as L

    rng = np.random.default_rng(d)
    err, cov = _random_gaussians(rng, 40, d)
    err = err * rng.uniform(0.2, 3.0, size=(40, 1))  # some far outside
    g = L.gaussian_calibration(err, cov)
    assert g.dim == d and g.nll.shape == (40,)
    assert bool(jnp.all(g.valid))
    nll = [
        -stats.multivariate_normal(np.zeros(d), c).logpdf(e) for e, c in zip(err, cov)
    ]
    nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
    np.testing.assert_allclose(g.nll, nll, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(g.nees, nees, rtol=1e-10)
    np.testing.assert_allclose(g.cdf, stats.chi2.cdf(nees, d), rtol=1e-8, atol=1e-12)
    for q in (0.1, 0.68, 0.95):
        inside = nees <= stats.chi2.ppf(q, d)
        np.testing.assert_allclose(float(g.coverage(q)), inside.mean())
    # Batch axes are kept; coverage reduces over the chosen axis.
    g2 = L.gaussian_calibration(err.reshape(4, 10, d), cov.reshape(4, 10, d, d))
    np.testing.assert_allclose(g2.nees, nees.reshape(4, 10), rtol=1e-10)
    per_row = np.asarray(g2.coverage(0.68, axis=1))
    np.testing.assert_allclose(
        per_row, (nees <= stats.chi2.ppf(0.68, d)).reshape(4, 10).mean(1)
    )


def test_a_consistent_gaussian_is_calibrated():
    import eqsmooth.learn as L

    rng = np.random.default_rng(0)
    d, n = 3, 20000
    err, cov = _random_gaussians(rng, n, d)
    g = L.gaussian_calibration(err, cov)
    assert abs(float(jnp.mean(g.nees)) - d) < 0.1
    for q in (0.1, 0.5, 0.68, 0.95):
        assert abs(float(g.coverage(q)) - q) < 0.012
    # Overconfident by a factor 4 in variance: NEES x4, coverage falls.
    g4 = L.gaussian_calibration(err, cov / 4)
    np.testing.assert_allclose(g4.nees, 4 * np.asarray(g.nees), rtol=1e-10)
    assert float(g4.coverage(0.95)) < 0.5
    # The CDF of the NEES is uniform: its mean is 1/2.
    assert abs(float(jnp.mean(g.cdf)) - 0.5) < 0.01


def test_invalid_covariances_are_marked_not_silent():
    import eqsmooth.learn as L

    rng = np.random.default_rng(1)
    err, cov = _random_gaussians(rng, 6, 2)
    cov[1] = np.nan
    cov[2] = -np.eye(2)
    cov[3] = np.array([[1.0, 2.0], [2.0, 1.0]])  # indefinite
    g = L.gaussian_calibration(err, cov)
    assert np.asarray(g.valid).tolist() == [True, False, False, False, True, True]
    for field in (g.nll, g.nees, g.cdf):
        f = np.asarray(field)
        assert np.all(np.isnan(f[1:4])) and np.all(np.isfinite(f[[0, 4, 5]]))
    # Coverage counts valid frames only.
    ok = [0, 4, 5]
    nees = np.asarray(g.nees)[ok]
    np.testing.assert_allclose(
        float(g.coverage(0.68)), np.mean(nees <= stats.chi2.ppf(0.68, 2))
    )
    # (The jaxtyping hook of the test run catches the shapes first.)
    with pytest.raises((ValueError, jaxtyping.TypeCheckError), match="covariance"):
        L.gaussian_calibration(err, cov[:, :1])
    with pytest.raises(ValueError, match="level"):
        g.coverage(1.0)


def test_nll_gradient_matches_central_differences():
    import eqsmooth.learn as L

    rng = np.random.default_rng(2)
    err, cov = _random_gaussians(rng, 3, 3)

    def f(e, c):
        return jnp.sum(L.gaussian_calibration(e, c).nll)

    ge, gc = jax.grad(f, argnums=(0, 1))(jnp.asarray(err), jnp.asarray(cov))
    h = 1e-6
    num_e = np.zeros_like(err)
    for idx in np.ndindex(err.shape):
        p, m = err.copy(), err.copy()
        p[idx] += h
        m[idx] -= h
        num_e[idx] = (float(f(p, cov)) - float(f(m, cov))) / (2 * h)
    np.testing.assert_allclose(ge, num_e, rtol=1e-6, atol=1e-8)
    # Symmetric perturbations of the covariance (it is symmetrised first).
    for n, i, j in ((0, 0, 0), (1, 0, 2), (2, 1, 2), (2, 2, 2)):
        p, m = cov.copy(), cov.copy()
        for a, b in {(i, j), (j, i)}:
            p[n, a, b] += h
            m[n, a, b] -= h
        num = (float(f(err, p)) - float(f(err, m))) / (2 * h)
        ana = float(gc[n, i, j] + (gc[n, j, i] if i != j else 0.0))
        np.testing.assert_allclose(ana, num, rtol=1e-6, atol=1e-8)


def test_chi2_quantile_and_nees_band():
    import eqsmooth.learn as L

    for q, dof in ((0.025, 2), (0.975, 2), (0.68, 1), (0.95, 3), (0.5, 0.5)):
        np.testing.assert_allclose(
            L.chi2_quantile(q, dof), stats.chi2.ppf(q, dof), rtol=1e-10
        )
    for q, dof in ((0.025, 198), (0.975, 297), (0.999, 7)):
        np.testing.assert_allclose(
            L.chi2_quantile(q, dof), stats.chi2.ppf(q, dof), rtol=1e-10
        )
    lo, hi = L.nees_band(2, 19)
    np.testing.assert_allclose(
        (lo, hi), stats.chi2.ppf([0.025, 0.975], 38) / 19, rtol=1e-10
    )
    lo, hi = L.nees_band(1, 99, probability=0.9)
    np.testing.assert_allclose((lo, hi), stats.chi2.ppf([0.05, 0.95], 99) / 99)
    # For d = 2 the coverage threshold has the closed form −2 log(1 − q).
    np.testing.assert_allclose(L.chi2_quantile(0.68, 2), -2 * math.log(0.32))
    with pytest.raises(ValueError, match="probability"):
        L.chi2_quantile(1.0, 2)
    with pytest.raises(ValueError, match="dim"):
        L.nees_band(0, 3)
