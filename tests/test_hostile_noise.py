"""Hostile input to the noise models: non-positive scales, non-PD, asymmetric
or upper-triangular matrices, eagerly and under jit (one shared compiled
callable per model)."""

import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises


def _eqs():
    import eqsmooth as eqs

    return eqs


SCALAR_CTORS = [
    ("IsotropicNoise", None, "sqrt_precision"),
    ("IsotropicNoise", "from_sigma", "sigma"),
    ("IsotropicNoise", "from_precision", "precision"),
    ("DiagonalNoise", None, "sqrt_precision"),
    ("DiagonalNoise", "from_sigmas", "sigmas"),
    ("DiagonalNoise", "from_variances", "variances"),
    ("DiagonalNoise", "from_precision", "precision"),
]
BAD_VALUES = {"zero": 0.0, "negative": -1.0, "nan": np.nan, "inf": np.inf}


def _build(cls_name, ctor):
    cls = getattr(_eqs(), cls_name)
    if ctor is None:
        return lambda value: cls(sqrt_precision=value)
    return getattr(cls, ctor)


def _value(cls_name, bad):
    if cls_name == "IsotropicNoise":
        return jnp.asarray(bad)
    return jnp.array([1.0, bad])


@pytest.mark.parametrize("cls_name", ["IsotropicNoise", "DiagonalNoise"])
def test_positional_scale_is_refused(cls_name):
    # `DiagonalNoise(0.1)` reads like σ = 0.1 but would be 1/σ: refused, and
    # the error names the constructor that takes standard deviations.
    cls = getattr(_eqs(), cls_name)
    with raises(TypeError, cls_name, "by keyword", "from_sigma"):
        cls(_value(cls_name, 2.0))
    with raises(TypeError, cls_name, "by keyword"):
        cls()
    noise = cls(sqrt_precision=_value(cls_name, 2.0))
    assert float(jnp.max(noise.sqrt_precision)) == 2.0


@pytest.mark.parametrize("bad", list(BAD_VALUES))
@pytest.mark.parametrize("cls_name,ctor,field", SCALAR_CTORS)
def test_bad_scale_eager(cls_name, ctor, field, bad):
    value = _value(cls_name, BAD_VALUES[bad])
    # inf sigma/variance is finite-checked; inf precision too.
    what = "finite" if bad in ("nan", "inf") else "positive"
    with raises(ValueError, f"{cls_name}.{field}", what):
        _build(cls_name, ctor)(value)


_JITTED = {}


def _jitted(cls_name, ctor):
    """One compiled `value -> whitened residual` per constructor."""
    import equinox as eqx

    key = (cls_name, ctor)
    if key not in _JITTED:
        build = _build(cls_name, ctor)

        @eqx.filter_jit
        def fn(v):
            return build(v).whiten(jnp.ones((1, 2)))

        _JITTED[key] = fn
    return _JITTED[key]


@pytest.mark.parametrize("bad", ["zero", "negative", "nan"])
@pytest.mark.parametrize("cls_name,ctor,field", SCALAR_CTORS)
def test_bad_scale_under_jit(cls_name, ctor, field, bad):
    import equinox as eqx

    fn = _jitted(cls_name, ctor)
    with raises(eqx.EquinoxRuntimeError, f"{cls_name}.{field}", "under jit"):
        fn(_value(cls_name, BAD_VALUES[bad]))


MATRIX_CASES = {
    "not_pd": (np.array([[1.0, 2.0], [2.0, 1.0]]), "not positive definite"),
    "singular": (np.zeros((2, 2)), "not positive definite"),
    "asymmetric": (np.array([[1.0, 0.5], [0.0, 1.0]]), "not symmetric"),
    "nonsquare": (np.ones((2, 3)), "shape (m, m) or (n, m, m)"),
    "nan": (np.array([[np.nan, 0.0], [0.0, 1.0]]), "non-finite"),
    "vector": (np.ones(2), "shape (m, m) or (n, m, m)"),
}


@pytest.mark.parametrize("case", list(MATRIX_CASES))
@pytest.mark.parametrize(
    "ctor,field",
    [("from_covariance", "covariance"), ("from_information", "information")],
)
def test_bad_matrix(ctor, field, case):
    import jaxtyping

    m, what = MATRIX_CASES[case]
    fn = getattr(_eqs().SqrtInformationNoise, ctor)
    if case in ("vector", "nonsquare"):
        # The jaxtyping hook of the test suite rejects the rank first.
        with raises(jaxtyping.TypeCheckError, field):
            fn(jnp.asarray(m))
        return
    with raises(ValueError, f"SqrtInformationNoise.{ctor}", field, what):
        fn(jnp.asarray(m))


@pytest.mark.parametrize(
    "R,what",
    [
        (np.array([[1.0, 0.5], [0.0, 1.0]]), "lower triangular"),
        (np.array([[0.0, 0.0], [0.5, 1.0]]), "diagonal must be positive"),
        (np.array([[-1.0, 0.0], [0.5, 1.0]]), "diagonal must be positive"),
        (np.array([[np.nan, 0.0], [0.5, 1.0]]), "finite"),
        (np.ones((2, 3)), "shape (m, m) or (n, m, m)"),
        (np.ones((2, 2, 2, 2)), "shape (m, m) or (n, m, m)"),
    ],
)
def test_bad_sqrt_information(R, what):
    import jaxtyping

    cls = _eqs().SqrtInformationNoise
    if R.shape[-1] != R.shape[-2]:
        with raises(jaxtyping.TypeCheckError, "sqrt_information"):
            cls(jnp.asarray(R))
        return
    with raises(ValueError, "SqrtInformationNoise", what):
        cls(jnp.asarray(R))


def test_sqrt_information_under_jit():
    import equinox as eqx

    fn = eqx.filter_jit(
        lambda R: _eqs().SqrtInformationNoise(R).whiten(jnp.ones((1, 2)))
    )
    fn(jnp.eye(2))
    with raises(eqx.EquinoxRuntimeError, "SqrtInformationNoise", "under jit"):
        fn(jnp.array([[0.0, 0.0], [0.5, 1.0]]))


def test_covariance_not_pd_under_jit():
    import equinox as eqx

    fn = eqx.filter_jit(
        lambda C: (
            _eqs().SqrtInformationNoise.from_covariance(C).whiten(jnp.ones((1, 2)))
        )
    )
    with raises(eqx.EquinoxRuntimeError, "from_covariance", "not positive definite"):
        fn(jnp.array([[1.0, 2.0], [2.0, 1.0]]))


@pytest.mark.parametrize("robust", ["HuberNoise", "CauchyNoise", "TukeyNoise"])
def test_robust_base_not_a_noise_model(robust):
    import jaxtyping

    cls = getattr(_eqs(), robust)
    # The test suite's jaxtyping hook rejects it first; without the hook the
    # Module's own check raises TypeError naming `{robust}.base`.
    with raises(jaxtyping.TypeCheckError, "base", robust):
        cls(1.0, 1.0)


@pytest.mark.parametrize("robust", ["HuberNoise", "CauchyNoise", "TukeyNoise"])
def test_robust_scale_not_positive(robust):
    eqs = _eqs()
    cls = getattr(eqs, robust)
    with raises(ValueError, f"{robust}.scale", "positive"):
        cls(eqs.IsotropicNoise(sqrt_precision=1.0), 0.0)


def _robust_kernels() -> list[str]:
    """The named constructor of every robust kernel that eqsmooth exports."""
    from eqsmooth.factors._robust_kernels import KERNELS

    return sorted(k.name for k in KERNELS)


ROBUST = _robust_kernels()


@pytest.mark.parametrize("robust", ROBUST)
def test_robust_scale_not_positive_under_jit(robust):
    import equinox as eqx

    eqs = _eqs()
    cls = getattr(eqs, robust)
    fn = eqx.filter_jit(
        lambda k: cls(eqs.IsotropicNoise(sqrt_precision=1.0), k).rho(jnp.ones(2))[0]
    )
    assert np.all(np.isfinite(np.asarray(fn(jnp.asarray(2.0)))))
    with raises(eqx.EquinoxRuntimeError, f"{robust}.scale", "under jit"):
        fn(jnp.asarray(0.0))


def test_named_constructors_agree():
    eqs = _eqs()
    sig = jnp.array([0.5, 2.0])
    a = eqs.DiagonalNoise.from_sigmas(sig).sqrt_precision
    b = eqs.DiagonalNoise.from_variances(sig**2).sqrt_precision
    c = eqs.DiagonalNoise.from_precision(1 / sig**2).sqrt_precision
    np.testing.assert_allclose(a, b)
    np.testing.assert_allclose(a, c)
    np.testing.assert_allclose(
        eqs.IsotropicNoise.from_precision(4.0).sqrt_precision,
        eqs.IsotropicNoise.from_sigma(0.5).sqrt_precision,
    )


_KERNELS = (
    "HuberNoise CauchyNoise TukeyNoise GemanMcClureNoise WelschNoise DCSNoise "
    "FairNoise L2WithDeadZoneNoise TruncatedQuadraticNoise"
).split()


@pytest.mark.parametrize("inner", ["TukeyNoise", "StudentTNoise"])
@pytest.mark.parametrize("outer", _KERNELS + ["StudentTNoise"])
def test_noise_models_do_not_nest(outer, inner):
    # A kernel acts on its base's whitened residual only: an inner kernel (or
    # Student-t) was accepted and silently dropped.
    eqs = _eqs()
    assert sorted(_KERNELS) == _robust_kernels()
    base = eqs.IsotropicNoise.from_sigma(1.0)
    inner_model = (
        eqs.StudentTNoise(base, 4.0)
        if inner == "StudentTNoise"
        else getattr(eqs, inner)(base, 1.0)
    )
    second = 4.0 if outer == "StudentTNoise" else 1.0
    with raises(TypeError, f"{outer}.base", inner):
        getattr(eqs, outer)(inner_model, second)


def test_pose_sigmas_are_named_by_part():
    # GTSAM orders Pose3 tangents (rotation, translation), eqsmooth
    # (translation, rotation): sigmas passed positionally in GTSAM's order
    # were accepted and wrong. The named constructor is right in both.
    eqs = _eqs()
    se3 = eqs.DiagonalNoise.from_pose_sigmas(
        rotation=np.array([0.01, 0.02, 0.03]), translation=np.array([0.1, 0.2, 0.3])
    )
    np.testing.assert_allclose(
        1.0 / np.asarray(se3.sqrt_precision), [0.1, 0.2, 0.3, 0.01, 0.02, 0.03]
    )
    se2 = eqs.DiagonalNoise.from_pose_sigmas(
        translation=np.array([0.1, 0.2]), rotation=0.05
    )
    np.testing.assert_allclose(1.0 / np.asarray(se2.sqrt_precision), [0.1, 0.2, 0.05])
    rows = eqs.DiagonalNoise.from_pose_sigmas(
        translation=np.full((4, 2), 0.1), rotation=np.full(4, 0.05)
    )
    assert rows.sqrt_precision.shape == (4, 3)
    with raises(ValueError, "from_pose_sigmas", "(3,)", "(1,)"):
        eqs.DiagonalNoise.from_pose_sigmas(
            translation=np.array([0.1, 0.2, 0.3]), rotation=0.05
        )
    with raises(ValueError, "DiagonalNoise.sigmas", "positive"):
        eqs.DiagonalNoise.from_pose_sigmas(
            translation=np.array([0.1, 0.0]), rotation=0.05
        )


@pytest.mark.parametrize("bad", [np.inf, np.nan, -1.0])
def test_traced_kernel_scale_must_be_finite_and_positive(bad):
    # Under jit a scale of inf passed the check ("positive") and the solve
    # then blamed the measurements.
    import equinox as eqx

    eqs = _eqs()
    base = eqs.IsotropicNoise.from_sigma(1.0)

    @eqx.filter_jit
    def rho(scale):
        return jnp.sum(eqs.FairNoise(base, scale).rho(jnp.ones(2))[0])

    assert np.isfinite(float(rho(jnp.asarray(2.0))))
    with pytest.raises(eqx.EquinoxRuntimeError, match="FairNoise.scale must be"):
        rho(jnp.asarray(bad))


def test_unbatched_prior_value_message_fits_builtin_factors():
    # The message used to point only at shared_field(), which does not apply
    # to a PriorFactor's value.
    eqs = _eqs()
    f = eqs.PriorFactor(
        eqs.Var("x", [0, 1]), jnp.zeros(3), eqs.IsotropicNoise.from_sigma(1.0)
    )
    graph = eqs.FactorGraph([f])
    with raises(ValueError, "PriorFactor.value", "leading axis of length 2", "x[None]"):
        graph.validate({"x": jnp.zeros((2, 3))})
