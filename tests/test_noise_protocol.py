"""Noise models answer for themselves (issue 55, item 3): whether they are
Gaussian, their name, their rows' mask, their curvature model, their per-row
parts (for padding) and their rows' square-root information. Code outside
`eqsmooth/factors/` asks them instead of testing their class."""

import functools
import inspect

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises

import eqsmooth as eqs
from eqsmooth.factors import AbstractNoiseModel


N, M = 4, 2
INDEX = np.array([2, 0, 3, 3, 1])  # rows may repeat, as padding repeats row 0
SIGMAS = np.array([[0.5, 2.0], [1.0, 0.25], [4.0, 1.0], [0.5, 0.5]])


def _gaussians():
    cov = np.array([[2.0, 0.3], [0.3, 1.0]])
    return {
        "isotropic": eqs.IsotropicNoise.from_sigma(0.5),
        "isotropic per row": eqs.IsotropicNoise.from_sigma(SIGMAS[:, 0]),
        "diagonal": eqs.DiagonalNoise.from_sigmas(SIGMAS[0]),
        "diagonal per row": eqs.DiagonalNoise.from_sigmas(SIGMAS),
        "sqrt information": eqs.SqrtInformationNoise.from_covariance(cov),
        "sqrt information per row": eqs.SqrtInformationNoise.from_covariance(
            np.stack([cov * s for s in SIGMAS[:, 0]])
        ),
    }


ACTIVE = np.array([True, False, True, True])


@functools.cache
def _models():
    models = dict(_gaussians())
    diag = models["diagonal per row"]
    models["masked"] = eqs.MaskedNoise(diag, ACTIVE)
    models["huber"] = eqs.HuberNoise(diag, 1.5)
    models["tukey per-row scale over masked"] = eqs.TukeyNoise(
        models["masked"], np.array([1.0, 2.0, 3.0, 4.0])
    )
    models["kernel choice"] = eqs.RobustNoise(
        diag, eqs.factors.KernelChoice("Cauchy"), 2.0
    )
    models["student-t"] = eqs.StudentTNoise(diag, np.array([3.0, 4.0, 5.0, 6.0]), M)
    models["student-t fisher"] = models["student-t"].fisher_model()
    return models


KEYS = [
    "isotropic",
    "isotropic per row",
    "diagonal",
    "diagonal per row",
    "sqrt information",
    "sqrt information per row",
    "masked",
    "huber",
    "tukey per-row scale over masked",
    "kernel choice",
    "student-t",
    "student-t fisher",
]
GAUSSIAN = set(KEYS[:7]) | {"student-t fisher"}


def _residuals():
    return jnp.asarray(np.arange(N * M, dtype=np.float64).reshape(N, M) - 3.5)


def test_every_concrete_noise_model_is_tested():
    """Every concrete noise class in eqsmooth answers the protocol (none is
    abstract), and this file builds one of each."""
    import eqsmooth.factors._padding as padding

    assert sorted(_models()) == sorted(KEYS)
    seen = {type(m) for m in _models().values()} | {padding._PaddingNoise}

    def concrete(cls):
        out = set()
        for sub in cls.__subclasses__():
            if sub.__module__.startswith("eqsmooth"):
                if not inspect.isabstract(sub):
                    out.add(sub)
                out |= concrete(sub)
        return out

    missing = concrete(AbstractNoiseModel) - seen
    assert not missing, sorted(c.__name__ for c in missing)


@pytest.mark.parametrize("key", KEYS)
def test_protocol(key):
    noise = _models()[key]
    assert noise.is_gaussian == (key in GAUSSIAN)
    assert isinstance(noise.name, str) and noise.name
    active = noise.active_rows()
    if "masked" in key:
        np.testing.assert_array_equal(np.asarray(active), ACTIVE)
    else:
        assert active is None
    noise.check_shapes("PriorFactor", N, M)

    # Each row's R_i: whitening a residual is R_i r_i.
    R = noise.sqrt_information_rows(N, M, jnp.float64)
    assert R.shape == (N, M, M)
    r = _residuals()
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", R, r), noise.whiten(r), rtol=1e-12
    )

    # The model of some rows whitens those rows as the whole model does.
    taken = noise.take_rows(INDEX)
    assert type(taken) is type(noise)
    taken.check_shapes("PriorFactor", len(INDEX), M)
    np.testing.assert_allclose(
        taken.whiten(r[INDEX]), noise.whiten(r)[INDEX], rtol=1e-12
    )
    # Per-row kernel parameters (scale, degrees of freedom) follow their rows.
    s = jnp.sum(noise.whiten(r) ** 2, axis=1)
    np.testing.assert_allclose(taken.rho(s[INDEX])[1], noise.rho(s)[1][INDEX])


@pytest.mark.parametrize("key", [k for k in KEYS if k != "student-t"])
def test_mask_rows(key):
    noise = _models()[key]
    keep = np.array([True, True, False, True])
    masked = noise.mask_rows(keep)
    masked.check_shapes("PriorFactor", N, M)
    assert masked.is_gaussian == noise.is_gaussian
    assert masked.name == noise.name or masked.name == "MaskedNoise"
    expect = keep if noise.active_rows() is None else keep & ACTIVE
    np.testing.assert_array_equal(np.asarray(masked.active_rows()), expect)
    r = _residuals()
    w = np.asarray(masked.whiten(r))
    np.testing.assert_array_equal(w[~expect], 0.0)
    np.testing.assert_allclose(w[expect], np.asarray(noise.whiten(r))[expect])
    # A masked row leaves the normaliser: it is the kept rows' own.
    kept = noise.take_rows(np.flatnonzero(expect))
    if noise.is_gaussian:
        np.testing.assert_allclose(
            masked.log_normalizer(N, M),
            kept.log_normalizer(int(expect.sum()), M),
            rtol=1e-12,
        )


def test_student_t_refuses_a_mask():
    with raises(TypeError, "StudentTNoise rows cannot be masked"):
        _models()["student-t"].mask_rows(ACTIVE)


def test_robust_per_row_parts():
    noise = _models()["tukey per-row scale over masked"]
    taken = noise.take_rows(INDEX)
    np.testing.assert_array_equal(taken.scale, noise.scale[INDEX])
    np.testing.assert_array_equal(taken.active_rows(), ACTIVE[INDEX])
    # A shared scale stays shared.
    assert _models()["huber"].take_rows(INDEX).scale.shape == ()
    # Masking a robust model masks its Gaussian base, keeping the kernel.
    masked = _models()["huber"].mask_rows(ACTIVE)
    assert masked.name == "HuberNoise"
    assert isinstance(masked.base, eqs.MaskedNoise)


def test_curvature_model():
    t = _models()["student-t"]
    assert eqx.tree_equal(t.curvature_model(), t.fisher_model())
    assert t.curvature_model().is_gaussian
    for key, noise in _models().items():
        if key != "student-t":
            assert noise.curvature_model() is noise, key


def test_names():
    assert _models()["huber"].name == "HuberNoise"
    assert _models()["kernel choice"].name == "KernelChoice"
    assert _models()["student-t"].name == "StudentTNoise"
    assert _models()["masked"].name == "MaskedNoise"
    with raises(TypeError, "HuberNoise.base", "TukeyNoise", "not Gaussian"):
        eqs.HuberNoise(_models()["tukey per-row scale over masked"], 1.0)


def test_filters_ask_the_noise_model():
    from eqsmooth.filters._rows import check_gaussian

    for key, noise in _models().items():
        if key in GAUSSIAN and key != "masked":
            check_gaussian(noise, "ekf: factor 0")
        elif key == "masked":
            with raises(TypeError, "MaskedNoise rows cannot be masked"):
                check_gaussian(noise, "ekf: factor 0")
        else:
            with raises(TypeError, "ekf: factor 0", "is robust"):
                check_gaussian(noise, "ekf: factor 0")


def _pose_graph():
    poses = np.array([[1.0, 0.0, 0.0, 0.0], [1.0, 0.0, 1.0, 0.0], [0, 1, 2, 0.5]])
    edges = np.array([[0, 1], [1, 2]])
    meas = np.array([[1.0, 0.0, 1.0, 0.0], [0.0, 1.0, 1.0, 0.5]])
    info = np.stack([np.diag([4.0, 9.0, 16.0]), np.diag([1.0, 25.0, 100.0])])
    return eqs.io.make_pose_graph("se2", poses, edges, meas, info), info


def test_g2o_export_asks_the_noise_model(tmp_path):
    pg, info = _pose_graph()
    eqs.io.save_g2o(tmp_path / "full.g2o", pg)
    # The same information as a diagonal model writes the same file.
    diag = eqs.DiagonalNoise(sqrt_precision=np.sqrt(np.diagonal(info, 0, 1, 2)))
    swapped = eqx.tree_at(lambda p: p.graph.factors[0].noise, pg, diag)
    eqs.io.save_g2o(tmp_path / "diag.g2o", swapped)
    full = (tmp_path / "full.g2o").read_text()
    assert (tmp_path / "diag.g2o").read_text() == full
    robust = eqx.tree_at(
        lambda p: p.graph.factors[0].noise, pg, eqs.HuberNoise(diag, 1.0)
    )
    with raises(TypeError, "save_g2o", "Gaussian", "HuberNoise"):
        eqs.io.save_g2o(tmp_path / "robust.g2o", robust)
