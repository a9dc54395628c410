"""Hostile input, round two (issue 36): the landmark factors, masks, user
residual functions, robust kernel scales, training inputs, loaders, discover
candidates and the diagnosis of failed solves.

Every case expects one exception type whose message names the factor, field,
rows, argument, file or candidate at fault (`hostile.raises`), or checks a
documented rule. Cases by class (this module: 136 test items):

- landmark measurements (41): ranges <= 0 / nan / inf, non-finite 2-D and 3-D
  bearings, GPS positions and pose-to-point offsets, wrong shapes;
- landmark geometry (17): SE2 poses with 3-D points and back (bearing,
  bearing-range, range, pose-to-point, GPS prior), arrays as poses,
  bearings of the other dimension, rows that disagree with the variables;
- landmark on its observer (3): 2-D LM and 3-D GN solves name the factor
  and the cause; under `jit` the result code;
- masks (8, one of them four checks): non-boolean, `None`, 2-D and
  wrong-length masks, robust / nested / Student-t bases, filters;
- FunctionFactor (8): a non-callable `fn`, bad `residual_dim`, a
  broadcasting residual;
- robust kernel scales (27): nine kernels x scale inf / nan / -1;
- training inputs (14): loss shape and dtype, optimiser, seed, trainable
  leaves, data dtypes, paths that are directories;
- loaders (11): KITTI pose files (columns, empty, words, rotations,
  reflections) and g2o files (ids, fields, FIX, duplicates, self edges);
- discover candidates (3): a feature that is not finite on half the states
  is named (and one finite everywhere passes);
- failed-solve diagnosis (4): NaN measurement rows, a gauge freedom and
  float32 ill-conditioning (dense and block-tridiagonal) named on the host.

Earlier round-two cases live beside the code they test:
`test_hostile_noise.py` (kernels and Student-t do not nest: 20; traced
kernel scales: 9), `test_masked_noise.py` (5), `test_landmark_factors.py`
(3-D bearing normalisation, zero distance), `test_train.py` (NaN validation,
all steps skipped; kill during a checkpoint write), `test_hostile_io.py`
(KITTI NaN lines, damaged disk cache), `test_factors.py` (non-array data,
cost of a non-1-D residual), `test_marginals.py` (singular joint marginals).

Apart from the solves of the last classes (one small program each), every
case fails before anything is compiled.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import jaxtyping
import numpy as np
import pytest
from hostile import raises

import eqsmooth as eqs


N1 = eqs.IsotropicNoise.from_sigma(1.0)
X, L = eqs.Var("x", [0]), eqs.Var("l", [0])


def _se2():
    return eqs.SE2.from_xy_theta(jnp.array([0.0]), jnp.array([0.0]), jnp.array([0.0]))


def _se3():
    return eqs.SE3.identity((1,), dtype=jnp.float64)


# ------------------------------------------------------------ landmark measurements

BAD_RANGES = {"zero": 0.0, "negative": -1.0, "nan": np.nan, "inf": np.inf}


@pytest.mark.parametrize("bad", list(BAD_RANGES))
@pytest.mark.parametrize("factor", ["RangeFactor", "BearingRangeFactor"])
def test_bad_range(factor, bad):
    ranges = jnp.array([2.0, BAD_RANGES[bad]])
    xs, ls = eqs.Var("x", [0, 0]), eqs.Var("l", [0, 1])
    with raises(ValueError, f"{factor}.range", "rows [1]", "positive and finite"):
        if factor == "RangeFactor":
            eqs.RangeFactor(xs, ls, ranges, N1)
        else:
            eqs.BearingRangeFactor(xs, ls, jnp.array([0.1, 0.2]), ranges, N1)


@pytest.mark.parametrize(
    "good, bad, says",
    [
        *[(0.1, bad, "not finite") for bad in (np.nan, np.inf, -np.inf)],
        *[
            ([0.0, 0.0, 1.0], row, "zero or non-finite")
            for row in ([0.0, 0.0, 0.0], [np.nan, 0.0, 1.0], [0.0, np.inf, 1.0])
        ],
    ],
    ids=["2d-nan", "2d-inf", "2d-minus-inf", "3d-zero", "3d-nan", "3d-inf"],
)
@pytest.mark.parametrize("factor", ["BearingFactor", "BearingRangeFactor"])
def test_bad_bearing(factor, good, bad, says):
    """A 2-D bearing (an angle) must be finite, a 3-D one (a direction)
    finite and non-zero: row 1 of `[good, bad]` is named."""
    bearing = jnp.array([good, bad])
    xs, ls = eqs.Var("x", [0, 0]), eqs.Var("l", [0, 1])
    with raises(ValueError, f"{factor}.bearing", "rows [1]", says):
        if factor == "BearingFactor":
            eqs.BearingFactor(xs, ls, bearing, N1)
        else:
            eqs.BearingRangeFactor(xs, ls, bearing, jnp.array([1.0, 1.0]), N1)


@pytest.mark.parametrize("shape", [(1, 2), (1, 3, 1), (1, 4), (1, 3, 3)])
@pytest.mark.parametrize("factor", ["BearingFactor", "BearingRangeFactor"])
def test_bearing_shape(factor, shape):
    bearing = jnp.ones(shape)
    with raises(ValueError, f"{factor}.bearing must have shape (n,)", str(shape)):
        if factor == "BearingFactor":
            eqs.BearingFactor(X, L, bearing, N1)
        else:
            eqs.BearingRangeFactor(X, L, bearing, jnp.array([1.0]), N1)


# The suite runs with jaxtyping's import hook, which checks annotated shapes
# first (TypeCheckError naming the function and parameter); without the hook
# eqsmooth's own checks raise ValueError naming the field.
HOOK = jaxtyping.TypeCheckError


@pytest.mark.parametrize("shape", [(1, 1), (1, 2)])
@pytest.mark.parametrize("factor", ["RangeFactor", "BearingRangeFactor"])
def test_range_shape(factor, shape):
    with raises(HOOK, f"{factor}.__init__", "parameter 'range'"):
        if factor == "RangeFactor":
            eqs.RangeFactor(X, L, jnp.ones(shape), N1)
        else:
            eqs.BearingRangeFactor(X, L, jnp.array([0.1]), jnp.ones(shape), N1)


@pytest.mark.parametrize(
    "value", [[[np.nan, 0.0]], [[0.0, np.inf]], [[0.0, 0.0, -np.inf]]]
)
def test_non_finite_gps_position(value):
    with raises(ValueError, "TranslationPriorFactor.position", "rows [0]", "finite"):
        eqs.TranslationPriorFactor(X, jnp.asarray(value), N1)


@pytest.mark.parametrize("shape", [(1, 4), (1, 1)])
def test_gps_position_shape(shape):
    with raises(ValueError, "TranslationPriorFactor.position must have shape"):
        eqs.TranslationPriorFactor(X, jnp.ones(shape), N1)


@pytest.mark.parametrize("value", [[[np.nan, 0.0]], [[0.0, 0.0, np.inf]]])
def test_non_finite_pose_to_point(value):
    with raises(ValueError, "PoseToPointFactor.measured", "rows [0]", "finite"):
        eqs.PoseToPointFactor(X, L, jnp.asarray(value), N1)


@pytest.mark.parametrize("shape", [(1, 1), (1, 4)])
def test_pose_to_point_shape(shape):
    with raises(ValueError, "PoseToPointFactor.measured must have shape"):
        eqs.PoseToPointFactor(X, L, jnp.ones(shape), N1)


# ------------------------------------------------------------ landmark geometry


def _factor(name, pose_dim):
    bearing = jnp.array([0.1]) if pose_dim == 2 else jnp.array([[0.0, 0.0, 1.0]])
    return {
        "BearingFactor": lambda: eqs.BearingFactor(X, L, bearing, N1),
        "BearingRangeFactor": lambda: eqs.BearingRangeFactor(
            X, L, bearing, jnp.array([1.0]), N1
        ),
        "RangeFactor": lambda: eqs.RangeFactor(X, L, jnp.array([1.0]), N1),
        "PoseToPointFactor": lambda: eqs.PoseToPointFactor(
            X, L, jnp.ones((1, pose_dim)), N1
        ),
    }[name]()


@pytest.mark.parametrize(
    "name", ["BearingFactor", "BearingRangeFactor", "RangeFactor", "PoseToPointFactor"]
)
@pytest.mark.parametrize("pose_dim", [2, 3])
def test_point_of_the_other_dimension(name, pose_dim):
    pose = (_se2() if pose_dim == 2 else _se3())[0]
    point = jnp.ones(5 - pose_dim)
    with raises(ValueError, name, f"({pose_dim},)", f"({5 - pose_dim},)"):
        _factor(name, pose_dim).residual(pose, point)


@pytest.mark.parametrize(
    "name", ["BearingFactor", "BearingRangeFactor", "PoseToPointFactor"]
)
def test_array_as_pose(name):
    with raises(TypeError, name, "SE2 or SE3", "ArrayImpl"):
        _factor(name, 2).residual(jnp.zeros(3), jnp.ones(2))


@pytest.mark.parametrize("name", ["BearingFactor", "BearingRangeFactor"])
@pytest.mark.parametrize("pose_dim", [2, 3])
def test_bearing_of_the_other_dimension(name, pose_dim):
    # A factor built with bearings for one dimension, given poses of the other.
    pose = (_se2() if pose_dim == 3 else _se3())[0]
    point = jnp.ones(5 - pose_dim)
    with raises(ValueError, name, "bearings of shape"):
        _factor(name, pose_dim).residual(pose, point)


def test_gps_prior_of_the_other_dimension():
    f = eqs.TranslationPriorFactor(X, jnp.ones((1, 3)), N1)
    with raises(ValueError, "TranslationPriorFactor", "(2,)", "(1, 3)"):
        f.residual(_se2()[0])


def test_range_rows_and_variables_disagree():
    f = eqs.RangeFactor(X, L, jnp.array([1.0, 2.0]), N1)
    graph = eqs.FactorGraph([f])
    with raises(ValueError, "RangeFactor.range", "leading axis"):
        graph.validate({"x": _se2(), "l": jnp.ones((1, 2))})


# ------------------------------------------------------------ landmark on its observer


def _observer_graph(dim):
    if dim == 2:
        pose = _se2()
        noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 0.05]))
        landmark = eqs.BearingRangeFactor(
            X, L, jnp.array([0.5]), jnp.array([3.0]), eqs.IsotropicNoise.from_sigma(0.1)
        )
    else:
        pose = _se3()
        noise = eqs.IsotropicNoise.from_sigma(0.1)
        landmark = eqs.BearingRangeFactor(
            X,
            L,
            jnp.array([[0.6, 0.0, 0.8]]),
            jnp.array([3.0]),
            eqs.IsotropicNoise.from_sigma(0.1),
        )
    graph = eqs.FactorGraph([eqs.PriorFactor(X, pose, noise), landmark])
    return graph, {"x": pose, "l": jnp.zeros((1, dim))}


@pytest.mark.parametrize(
    "dim, solver", [(2, eqs.LevenbergMarquardt()), (3, eqs.GaussNewton())]
)
def test_landmark_on_its_observer_is_named(dim, solver):
    graph, values = _observer_graph(dim)
    with raises(
        eqx.EquinoxRuntimeError,
        "BearingRangeFactor (factor stack 1)",
        "rows [0]",
        "same position as its observer",
    ):
        eqs.least_squares(graph, values, solver)


def test_landmark_on_its_observer_under_jit_is_a_result_code():
    graph, values = _observer_graph(2)
    solve = jax.jit(
        lambda g, v: eqs.least_squares(g, v, eqs.LevenbergMarquardt(), throw=False)
    )
    sol = solve(graph, values)
    assert sol.result == eqs.RESULTS.nonfinite_problem
    assert "observer" in eqs.RESULTS[eqs.RESULTS.nonfinite_problem]


# ------------------------------------------------------------ masks


@pytest.mark.parametrize(
    "active, exc, fragment",
    [
        (np.array([1, 0]), TypeError, ".astype(bool)"),
        (np.array([1.0, 0.0]), TypeError, "must be booleans"),
        (None, HOOK, "parameter 'active'"),
        (np.ones((2, 2), bool), ValueError, "shape (n,)"),
        (np.ones((), bool), ValueError, "shape (n,)"),
    ],
)
def test_bad_mask(active, exc, fragment):
    with raises(exc, "MaskedNoise", fragment):
        eqs.MaskedNoise(N1, active)


def test_mask_bases():
    on = np.ones(2, bool)
    with raises(TypeError, "MaskedNoise.base must be a Gaussian", "HuberNoise(Masked"):
        eqs.MaskedNoise(eqs.HuberNoise(N1, 1.0), on)
    with raises(TypeError, "MaskedNoise.base is itself a MaskedNoise", "&"):
        eqs.MaskedNoise(eqs.MaskedNoise(N1, on), on)
    with raises(TypeError, "StudentTNoise.base cannot be a MaskedNoise"):
        eqs.StudentTNoise(eqs.MaskedNoise(N1, on), 3.0)
    # A robust kernel around a mask is the documented composition.
    robust = eqs.HuberNoise(eqs.MaskedNoise(N1, on), 1.0)
    assert isinstance(robust, eqs.RobustNoise) and isinstance(
        robust.kernel, eqs.factors.Huber
    )


def test_mask_of_the_wrong_length():
    f = eqs.PriorFactor(
        eqs.Var("x", [0, 1, 2]),
        jnp.zeros((3, 1)),
        eqs.MaskedNoise(N1, np.array([True, False])),
    )
    with raises(ValueError, "PriorFactor", "MaskedNoise.active has shape (2,)", "(3,)"):
        f.noise.check_shapes("PriorFactor", 3, 1)


def test_filters_refuse_masks():
    from eqsmooth.filters._rows import check_gaussian

    with raises(TypeError, "MaskedNoise rows cannot be masked in a Kalman filter"):
        check_gaussian(eqs.MaskedNoise(N1, np.array([True])), "ekf: factor 0")


# ------------------------------------------------------------ FunctionFactor


def _meas(x, data, params):
    return x - data


@pytest.mark.parametrize("fn", [3, "x - data"])
def test_function_factor_needs_a_function(fn):
    with raises(HOOK, "FunctionFactor.__init__", "parameter 'fn'"):
        eqs.FunctionFactor(fn, (X,), N1)


@pytest.mark.parametrize(
    "dim, exc, fragment",
    [
        (0, ValueError, "FunctionFactor.residual_dim must be a positive int, got 0"),
        (-1, ValueError, "FunctionFactor.residual_dim must be a positive int"),
        (True, ValueError, "FunctionFactor.residual_dim must be a positive int"),
        (1.0, HOOK, "parameter 'residual_dim'"),
        ("1", HOOK, "parameter 'residual_dim'"),
    ],
)
def test_function_factor_residual_dim(dim, exc, fragment):
    with raises(exc, fragment):
        eqs.FunctionFactor(_meas, (X,), N1, jnp.ones((1, 1)), residual_dim=dim)


def test_broadcasting_residual_is_caught_when_declared():
    # States of dimension 2, data of dimension 1: x - data has 2 entries.
    f = eqs.FunctionFactor(_meas, (X,), N1, jnp.ones((1, 1)), residual_dim=1)
    graph = eqs.FactorGraph([f])
    with raises(ValueError, "FunctionFactor(fn=_meas)", "(2,)", "residual_dim=1"):
        graph.residuals({"x": jnp.zeros((1, 2))})
    # Without the declaration nothing can tell it from a residual of size 2.
    undeclared = eqs.FactorGraph(
        [eqs.FunctionFactor(_meas, (X,), N1, jnp.ones((1, 1)))]
    )
    assert undeclared.residuals({"x": jnp.zeros((1, 2))})[0].shape == (1, 2)


# ------------------------------------------------------------ robust kernel scales

KERNELS = (
    "HuberNoise CauchyNoise TukeyNoise GemanMcClureNoise WelschNoise DCSNoise "
    "FairNoise L2WithDeadZoneNoise TruncatedQuadraticNoise"
).split()


@pytest.mark.parametrize("scale", [np.inf, np.nan, -1.0])
@pytest.mark.parametrize("kernel", KERNELS)
def test_robust_scale(kernel, scale):
    what = "positive" if scale < 0 else "finite"
    with raises(ValueError, f"{kernel}.scale", what):
        getattr(eqs, kernel)(N1, scale)


# ------------------------------------------------------------ training inputs


class _Line(eqx.Module):
    w: jax.Array


def _loss(model, batch):
    return jnp.mean((model.w * batch["x"] - batch["y"]) ** 2)


_DATA = {"x": np.arange(8.0), "y": np.arange(8.0)}


def _train(**kw):
    import optax

    from eqsmooth.learn import Logging, train

    args = dict(
        model=_Line(jnp.asarray(0.0)),
        loss_fn=_loss,
        train_data=_DATA,
        optimizer=optax.sgd(0.01),
        num_steps=2,
        batch_size=2,
        logging=Logging(progress=False),
    )
    args.update(kw)
    return train(**args)


@pytest.mark.parametrize(
    "kw, exc, fragments",
    [
        (dict(loss_fn=lambda m, b: m.w * b["x"]), TypeError, ["scalar", "(2,)"]),
        (dict(loss_fn=lambda m, b: jnp.sum(b["x"] > 0)), TypeError, ["int"]),
        (dict(has_aux=True), TypeError, ["(loss, aux_dict)"]),
        (dict(optimizer="adam"), HOOK, ["train", "parameter 'optimizer'"]),
        (dict(optimizer=None), HOOK, ["train", "parameter 'optimizer'"]),
        (dict(seed=-1), ValueError, ["seed", "-1"]),
        (dict(seed=1.5), HOOK, ["train", "parameter 'seed'"]),
        (dict(seed=True), ValueError, ["seed", "True"]),
        (dict(model=_Line(1.0)), ValueError, ["no trainable leaves", "jnp.asarray"]),
        (
            dict(train_data={"x": np.array(["a"] * 8), "y": np.arange(8.0)}),
            TypeError,
            ["train_data['x']", "numeric"],
        ),
        (
            dict(train_data={"x": np.array([object()] * 8), "y": np.arange(8.0)}),
            TypeError,
            ["train_data['x']", "object"],
        ),
        (
            dict(
                validation=eqs.learn.Validation(
                    {"x": np.array(["a"] * 4), "y": np.arange(4.0)}
                )
            ),
            TypeError,
            ["validation.data['x']"],
        ),
    ],
)
def test_bad_training_input(kw, exc, fragments):
    with raises(exc, *fragments):
        _train(**kw)


@pytest.mark.parametrize("label", ["Checkpoints", "Logging"])
def test_training_path_is_a_directory(label, tmp_path):
    from eqsmooth import learn

    with raises(ValueError, f"{label}: path", "is a directory"):
        getattr(learn, label)(tmp_path)
    with raises(ValueError, f"{label}: every must be an int >= 1", "0"):
        getattr(learn, label)(tmp_path / "f", every=0)


# ------------------------------------------------------------ loaders

_ROW = "1 0 0 0 0 1 0 0 0 0 1 0"


def _read_poses(tmp_path, text):
    from experiments.kitti_vo.data import read_poses

    path = tmp_path / "00.txt"
    path.write_text(text)
    return read_poses(path)


@pytest.mark.parametrize(
    "text, fragment",
    [
        (" ".join(_ROW.split()[:11]) + "\n", "expected 12 floats per line, got 11"),
        ("", "no poses"),
        (_ROW.replace("1", "one", 1) + "\n", "not a KITTI pose file"),
        (_ROW.replace("1", "2", 1) + "\n", "lines [1] do not hold a rotation"),
        ("-" + _ROW + "\n", "lines [1] do not hold a rotation"),
        (_ROW + "\n" + _ROW.replace("0 1 0 0 0", "0 0 1 0 0", 1) + "\n", "lines [2]"),
    ],
)
def test_bad_kitti_pose_file(tmp_path, text, fragment):
    with raises(ValueError, "00.txt", fragment):
        _read_poses(tmp_path, text)


_E2 = "EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n"


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("VERTEX_SE2 0.5 0 0 0\nVERTEX_SE2 1 1 0 0\n" + _E2, "integer id"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n" + _E2[:-1] + " 7\n", "got 12"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n" + _E2 + "FIX 9\n", "FIX"),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n" + _E2, "defined twice"),
        ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", "to itself"),
    ],
)
def test_bad_g2o_file(tmp_path, text, fragment):
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with raises(ValueError, "bad.g2o", fragment):
        eqs.io.load_g2o(path)


# ------------------------------------------------------------ discover candidates


def _half_sqrt(x, u):
    return jnp.stack([0.0 * x[0], jnp.sqrt(x[0])])


def _half_log(x, u):
    return jnp.stack([0.0 * x[0], jnp.log(x[0])])


def _dyn(x, u, params):
    return x


def _meas_first(x, params):
    return x[:1]


def _finite(x, u):
    return jnp.stack([0.0 * x[0], jnp.sqrt(jnp.abs(x[0]))])


def _feature_scales(name, feature):
    """`feature_scales` of a one-candidate model at six states from -1 to 1."""
    import eqsmooth.discover as dc
    from eqsmooth.discover._fit import feature_scales

    model = dc.ChainModel(
        dynamics=_dyn,
        measurement=_meas_first,
        params=jnp.asarray(0.0),
        process_sigma=np.array([0.1, 0.1]),
        measurement_sigma=np.array([0.1]),
        prior_sigma=np.array([1.0, 1.0]),
        candidates=[dc.Candidate(name, feature)],
    )
    states = np.stack([np.linspace(-1, 1, 6), np.zeros(6)], -1)[None]
    data = dc.Sequences(states[..., :1], np.zeros((1, 2)))
    return feature_scales(model, data, states)


@pytest.mark.parametrize("feature", [_half_sqrt, _half_log])
def test_candidate_not_finite_on_half_the_states(feature):
    with raises(ValueError, "Candidate 'half-defined'", "not finite at 3 of 6"):
        _feature_scales("half-defined", feature)


def test_candidate_finite_everywhere_passes():
    assert np.all(np.isfinite(_feature_scales("defined", _finite)))


# ------------------------------------------------------------ failed-solve diagnosis


def _chain(T, prior=True, dtype=jnp.float64, sigma_between=1.0, nan_row=None):
    rows = np.arange(T)
    meas = jnp.asarray(np.arange(T, dtype=float)[:, None] * np.ones((1, 2)), dtype)
    if nan_row is not None:
        meas = meas.at[nan_row, 0].set(jnp.nan)
    factors = [
        eqs.BetweenFactor(
            eqs.Var("x", rows[:-1]),
            eqs.Var("x", rows[1:]),
            jnp.ones((T - 1, 2), dtype),
            eqs.IsotropicNoise.from_sigma(jnp.asarray(sigma_between, dtype)),
        )
    ]
    if prior:
        factors.insert(
            0,
            eqs.PriorFactor(
                eqs.Var("x", rows),
                meas,
                eqs.IsotropicNoise.from_sigma(jnp.asarray(10.0, dtype)),
            ),
        )
    return eqs.FactorGraph(factors), {"x": jnp.zeros((T, 2), dtype)}


def test_nan_measurement_rows_are_named():
    graph, values = _chain(6, nan_row=3)
    with raises(
        eqx.EquinoxRuntimeError, "PriorFactor (factor stack 0)", "residual in rows [3]"
    ):
        eqs.least_squares(graph, values, eqs.GaussNewton(eqs.DenseCholesky()))


def test_gauge_freedom_is_named():
    graph, values = _chain(4, prior=False)
    with raises(
        eqx.EquinoxRuntimeError, "singular in float64 too", "2 unconstrained", "x[0]"
    ):
        eqs.least_squares(graph, values, eqs.GaussNewton(eqs.DenseCholesky()))


@pytest.mark.parametrize("linear_solver", [eqs.DenseCholesky(), eqs.BlockTridiagonal()])
def test_float32_ill_conditioning_is_named(linear_solver):
    graph, values = _chain(50, dtype=jnp.float32, sigma_between=1e-3)
    with raises(
        eqx.EquinoxRuntimeError, "condition number", "float32", "not a missing prior"
    ):
        eqs.least_squares(graph, values, eqs.GaussNewton(linear_solver))
