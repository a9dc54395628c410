"""The disk experiment's uncertainty scores and two-level bootstrap (no training)."""

import math

import numpy as np
import pytest


U = pytest.importorskip("experiments.disk_tracking.uncertainty")
F = pytest.importorskip("experiments.disk_tracking.fresh_more")


def test_calibrated_gaussian_scores_nominal():
    rng = np.random.default_rng(0)
    n, t = 400, 20
    a = rng.uniform(0.5, 3.0, size=(n, t))
    cov = np.zeros((n, t, 2, 2))
    cov[..., 0, 0], cov[..., 1, 1] = a**2, (0.5 * a) ** 2
    cov[..., 0, 1] = cov[..., 1, 0] = 0.3 * a * (0.5 * a)
    chol = np.linalg.cholesky(cov)
    truth = rng.normal(size=(n, t, 2)) * 10
    pred = truth - np.einsum("ntij,ntj->nti", chol, rng.normal(size=(n, t, 2)))
    s = U.fold_summary(U.gaussian_scores(pred, cov, truth))
    assert s["invalid_sequences"] == 0
    assert s["scored_frames_per_sequence"] == t - 1
    assert abs(s["nees"] - 2.0) < 0.1
    assert abs(s["coverage"]["0.68"] - 0.68) < 0.02
    assert abs(s["coverage"]["0.95"] - 0.95) < 0.01
    assert abs(s["frames_in_band"] - 0.95) < 0.01
    assert s["sequences_in_band"] > 0.9
    # NLL of a standard 2-D Gaussian: E[½ NEES] + ½ E[log det] + log 2π.
    logdet = np.linalg.slogdet(cov[:, 1:])[1].mean()
    assert abs(s["nll"] - (1.0 + 0.5 * logdet + math.log(2 * math.pi))) < 0.05
    # Overconfident covariances: NEES scales with 1/c, coverage falls.
    s2 = U.fold_summary(U.gaussian_scores(pred, cov / 100, truth))
    assert s2["nees"] > 150 and s2["coverage"]["0.95"] < 0.1
    bad = cov.copy()
    bad[3, 5] = np.nan
    assert U.fold_summary(U.gaussian_scores(pred, bad, truth))["invalid_sequences"] == 1


def test_two_level_bootstrap_paired_and_centred():
    rng = np.random.default_rng(1)
    mse = rng.gamma(2.0, 1.0, size=(2, 5, 50))
    mse[1] = mse[0] * 1.21  # RMSE 10% higher on every sequence
    draws = F.bootstrap(mse, 200, seed=3)
    assert draws.shape == (200, 2)
    ratio = draws[:, 1] / draws[:, 0]
    np.testing.assert_allclose(ratio, 1.1, rtol=1e-12)  # the same draws (paired)
    point = np.sqrt(mse.mean(axis=2)).mean(axis=1)
    lo, hi = np.percentile(draws[:, 0], [2.5, 97.5])
    assert lo < point[0] < hi
