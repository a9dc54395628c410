"""Hostile input to the file reader (g2o), the EKF's initial belief and the
discovery workflow's entry point. Each case fails before any compilation."""

import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises


def _eqs():
    import eqsmooth as eqs

    return eqs


EDGE = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"
V01 = "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n"


G2O_CASES = {
    "non_utf8": (
        b"VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 \xff0\n" + EDGE.encode(),
        2,
        "not UTF-8",
    ),
    "latin1_comment": (b"# caf\xe9\n" + (V01 + EDGE).encode(), 1, "not UTF-8"),
    "overflow_vertex_id": (
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 99999999999999999999999 1 0 0\n" + EDGE),
        2,
        "out of range",
    ),
    "overflow_edge_id": (
        V01 + "EDGE_SE2 0 99999999999999999999999 1 0 0 1 0 0 1 0 1\n",
        3,
        "out of range",
    ),
    "float_id": (
        "VERTEX_SE2 0.5 0 0 0\nVERTEX_SE2 1 1 0 0\n" + EDGE,
        1,
        "as an integer id",
    ),
    "word_number": (V01.replace("1 1 0 0", "1 one 0 0") + EDGE, 2, "as a number"),
    "inf_number": (V01.replace("1 1 0 0", "1 inf 0 0") + EDGE, 2, "non-finite"),
    "too_few_fields": (
        "VERTEX_SE2 0 0 0\nVERTEX_SE2 1 1 0 0\n" + EDGE,
        1,
        "needs 4 fields",
    ),
    "unknown_vertex": (V01 + "EDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n", 3, "vertex 7"),
    "self_loop": (V01 + "EDGE_SE2 1 1 1 0 0 1 0 0 1 0 1\n", 3, "to itself"),
    "not_pd_information": (
        V01 + "EDGE_SE2 0 1 1 0 0 -1 0 0 1 0 1\n",
        3,
        "not positive definite",
    ),
    "mixed_dimensions": (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n",
        2,
        "mixes 2-D and 3-D",
    ),
    "unsupported_tag": (V01 + EDGE + "EDGE_FOO 1 2\n", 4, "unsupported tag"),
}


@pytest.mark.parametrize("case", list(G2O_CASES))
def test_g2o_names_file_and_line(case, tmp_path):
    text, line, what = G2O_CASES[case]
    path = tmp_path / f"{case}.g2o"
    path.write_bytes(text if isinstance(text, bytes) else text.encode())
    with raises(ValueError, f"{path}:{line}:", what):
        _eqs().io.load_g2o(path)


def test_g2o_empty_file(tmp_path):
    path = tmp_path / "empty.g2o"
    path.write_text("")
    with raises(ValueError, str(path), "no pose vertices or edges"):
        _eqs().io.load_g2o(path)


@pytest.mark.parametrize("dtype", ["int32", "float16", "bfloat16"])
def test_g2o_dtype(dtype, tmp_path):
    path = tmp_path / "ok.g2o"
    path.write_text(V01 + EDGE)
    with raises(TypeError, "load_g2o", "dtype", dtype):
        _eqs().io.load_g2o(path, dtype=jnp.dtype(dtype))


def test_g2o_missing_file(tmp_path):
    with raises(FileNotFoundError, "nope.g2o"):
        _eqs().io.load_g2o(tmp_path / "nope.g2o")


def _trans(a, b, data, params):
    return b - a


def _meas(x, data, params):
    return x - data


def _ekf_factors():
    eqs = _eqs()
    t = np.arange(4)
    tr = eqs.FunctionFactor(
        _trans,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        eqs.IsotropicNoise(sqrt_precision=1.0),
    )
    me = eqs.FunctionFactor(
        _meas,
        (eqs.Var("x", t),),
        eqs.IsotropicNoise(sqrt_precision=1.0),
        data=jnp.zeros((4, 2)),
    )
    return tr, [me]


EKF_CASES = {
    "mean_nan": (jnp.array([jnp.nan, 0.0]), jnp.eye(2), "initial_mean", "non-finite"),
    "mean_inf": (jnp.array([0.0, jnp.inf]), jnp.eye(2), "initial_mean", "non-finite"),
    "cov_negative": (
        jnp.zeros(2),
        -jnp.eye(2),
        "initial_covariance",
        "not positive definite",
    ),
    "cov_singular": (
        jnp.zeros(2),
        jnp.zeros((2, 2)),
        "initial_covariance",
        "not positive definite",
    ),
    "cov_indefinite": (
        jnp.zeros(2),
        jnp.array([[1.0, 2.0], [2.0, 1.0]]),
        "initial_covariance",
        "not positive definite",
    ),
    "cov_asymmetric": (
        jnp.zeros(2),
        jnp.array([[1.0, 0.5], [0.0, 1.0]]),
        "initial_covariance",
        "not symmetric",
    ),
    "cov_nan": (
        jnp.zeros(2),
        jnp.full((2, 2), jnp.nan),
        "initial_covariance",
        "non-finite",
    ),
    "cov_wrong_shape": (jnp.zeros(2), jnp.eye(3), "initial_covariance", "(2, 2)"),
}


@pytest.mark.parametrize("case", list(EKF_CASES))
def test_ekf_initial_belief(case):
    mean, cov, field, what = EKF_CASES[case]
    tr, me = _ekf_factors()
    with raises(ValueError, "ekf", field, what):
        _eqs().ekf(tr, me, mean, cov)


EKF_MEANS = {
    "mean_too_long": (
        jnp.zeros(3),
        jnp.eye(3),
        ["array of shape (3,)", "incompatible"],
    ),
    # Under the test suite's jaxtyping hook the residual's return annotation
    # fails first; without it the message says "without a time axis".
    "mean_with_time_axis": (jnp.zeros((1, 2)), jnp.eye(2), ["(1, 2)"]),
    "mean_wrong_type": ({"a": jnp.zeros(2)}, jnp.eye(2), ["dict of", "initial_mean"]),
}


@pytest.mark.parametrize("case", list(EKF_MEANS))
def test_ekf_initial_mean_that_does_not_fit(case):
    mean, cov, fragments = EKF_MEANS[case]
    tr, me = _ekf_factors()
    with raises(ValueError, "ekf", "FunctionFactor", "initial_mean", *fragments):
        _eqs().ekf(tr, me, mean, cov)


def test_ekf_integer_covariance():
    import jaxtyping

    tr, me = _ekf_factors()
    # Caught by the test suite's jaxtyping hook; without it eqsmooth raises
    # TypeError "ekf: initial_covariance must be a floating-point array".
    with raises(jaxtyping.TypeCheckError, "ekf", "initial_covariance"):
        _eqs().ekf(tr, me, jnp.zeros(2), np.eye(2, dtype=int))


def _dyn(x, u, params):
    return jnp.stack([x[0] + x[1], x[1] - params * x[0]])


def _h(x, params):
    return x[:1]


_MODEL = []


def _model():
    import eqsmooth.discover as dc

    if not _MODEL:
        lib = dc.mechanical_library([0], [1], 2, measured_positions=[0])
        _MODEL.append(
            dc.ChainModel(
                _dyn,
                _h,
                jnp.asarray(0.05),
                np.array([0.05, 0.5]),
                np.array([1.0]),
                np.array([20.0, 4.0]),
                lib,
            )
        )
    return _MODEL[0]


def _data(B=3, T=5, m=1, n=2, bad=None):
    import eqsmooth.discover as dc

    y = np.zeros((B, T, m))
    x0 = np.zeros((B, n))
    u = None
    if bad == "nan_y":
        y[1, 2, 0] = np.nan
    if bad == "inf_y":
        y[0, 0, 0] = np.inf
    if bad == "nan_x0":
        x0[2, 1] = np.nan
    if bad == "nan_u":
        u = np.zeros((B, T, 1))
        u[0, 3, 0] = np.nan
    return dc.Sequences(y, x0, inputs=u)


DISCOVER_CASES = {
    "T0": (dict(T=0), "T = 0"),
    "T1": (dict(T=1), "T = 1"),
    "B0": (dict(B=0), "B = 0"),
    "nan_measurement": (
        dict(bad="nan_y"),
        "data.measurements",
    ),
    "inf_measurement": (dict(bad="inf_y"), "data.measurements"),
    "nan_x0": (dict(bad="nan_x0"), "data.x0_mean"),
    "nan_input": (dict(bad="nan_u"), "data.inputs"),
    "measurement_dim": (dict(m=2), "m = 2"),
    "state_dim": (dict(n=3), "state dimension 3"),
}


@pytest.mark.parametrize("case", list(DISCOVER_CASES))
def test_discover_find_inputs(case):
    import eqsmooth.discover as dc

    kw, *fragments = DISCOVER_CASES[case]
    with raises(ValueError, "find", *fragments):
        dc.find(_model(), _data(**kw))


def test_ragged_sequences():
    import jaxtyping

    import eqsmooth.discover as dc
    from eqsmooth.discover._model import _stacked

    y = [np.zeros((5, 1)), np.zeros((6, 1))]
    # The test suite's jaxtyping hook rejects the ragged list first ...
    with raises(jaxtyping.TypeCheckError, "Sequences.__init__", "measurements"):
        dc.Sequences(y, np.zeros((2, 2)))
    # ... and without it, Sequences names the lengths (its own check).
    with raises(ValueError, "Sequences.measurements", "ragged", "(5, 1)", "(6, 1)"):
        _stacked("measurements", y)
    assert _stacked("inputs", [np.zeros((5, 1))] * 2).shape == (2, 5, 1)


@pytest.mark.parametrize(
    "field,value",
    [("process_sigma", -1.0), ("measurement_sigma", 0.0), ("prior_sigma", np.nan)],
)
def test_chain_model_sigmas_at_construction(field, value):
    import eqsmooth.discover as dc

    model = _model()
    kwargs = dict(
        process_sigma=model.process_sigma,
        measurement_sigma=model.measurement_sigma,
        prior_sigma=model.prior_sigma,
    )
    bad = np.asarray(kwargs[field]).copy()
    bad[0] = value
    kwargs[field] = bad
    with raises(ValueError, f"ChainModel.{field}", "positive"):
        dc.ChainModel(
            _dyn, _h, jnp.asarray(0.05), candidates=model.candidates, **kwargs
        )


@pytest.mark.parametrize(
    "field,index",
    [("process_sigma", 0), ("measurement_sigma", 0), ("prior_sigma", 1)],
)
def test_discover_model_sigmas(field, index):
    import equinox as eqx

    import eqsmooth.discover as dc

    model = _model()
    bad = np.asarray(getattr(model, field)).copy()
    bad[index] = -1.0
    model = eqx.tree_at(lambda m: getattr(m, field), model, jnp.asarray(bad))
    with raises(ValueError, "find", f"model.{field}", "positive"):
        dc.find(model, _data())
