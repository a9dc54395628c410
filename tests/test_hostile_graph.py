"""Hostile input to graph construction, linearisation and the solver entry
point. Every case fails at construction or at trace time (no compilation),
except the two gradient cases, which share one compiled solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises


T = 6
t = np.arange(T)


def _eqs():
    import eqsmooth as eqs

    return eqs


def _meas(x, data, params):
    return x - data


def _meas_first(x, data, params):
    return (x - data)[:1]


def _meas_matrix(x, data, params):
    return jnp.outer(x, x)


def _dyn(a, b, data, params):
    return b - a * params


def _hook(exc):
    """Cases the test suite's jaxtyping/beartype hook rejects before eqsmooth's
    own checks run (users without the hook get eqsmooth's ValueError or
    TypeError, which names the same argument)."""
    if exc == "hook":
        import jaxtyping

        return jaxtyping.TypeCheckError
    return exc


def _lin(factors, values):
    eqs = _eqs()
    return eqs.linearize(eqs.FactorGraph(factors), values)


def _iso():
    return _eqs().IsotropicNoise(sqrt_precision=1.0)


# (mean shape per row) on (T, 3) Euclidean states.
@pytest.mark.parametrize("shape", [(1,), (4,), (3, 1), (), (1, 3)])
@pytest.mark.parametrize("api", ["linearize", "cost"])
def test_prior_mean_shape(shape, api):
    eqs = _eqs()
    x = jnp.zeros((T, 3))
    prior = eqs.PriorFactor(eqs.Var("x", t), jnp.zeros((T,) + shape), _iso())
    with raises(ValueError, "PriorFactor.value", f"{shape}", "(3,)"):
        if api == "linearize":
            _lin([prior], {"x": x})
        else:
            eqs.FactorGraph([prior]).cost({"x": x})


@pytest.mark.parametrize("shape", [(1,), (2,), (4,), (3, 1)])
@pytest.mark.parametrize("api", ["linearize", "cost"])
def test_between_measurement_shape(shape, api):
    eqs = _eqs()
    x = jnp.zeros((T, 3))
    f = eqs.BetweenFactor(
        eqs.Var("x", t[:-1]), eqs.Var("x", t[1:]), jnp.zeros((T - 1,) + shape), _iso()
    )
    with raises(ValueError, "BetweenFactor.measurement", f"{shape}", "(3,)"):
        if api == "linearize":
            _lin([f], {"x": x})
        else:
            eqs.FactorGraph([f]).cost({"x": x})


def _groups():
    eqs = _eqs()
    return {
        "R3": jnp.zeros((T, 3)),
        "SE2": eqs.SE2.identity((T,)),
        "SO2": eqs.SO2.identity((T,)),
        "SE3": eqs.SE3.identity((T,)),
        "dict": {"p": jnp.zeros((T, 3))},
    }


MISMATCH = [
    ("SE2", "R3", "is a SE2 but the state it is compared with is an array"),
    ("R3", "SE2", "is an array but the state it is compared with is a SE2"),
    ("SO2", "SE2", "is a SO2 but the state it is compared with is a SE2"),
    ("SE3", "SE2", "is a SE3 but the state it is compared with is a SE2"),
    ("dict", "R3", "structure"),
    ("R3", "dict", "structure"),
]


@pytest.mark.parametrize("mean,state,what", MISMATCH)
def test_prior_mean_type(mean, state, what):
    eqs = _eqs()
    g = _groups()
    prior = eqs.PriorFactor(eqs.Var("x", t), g[mean], _iso())
    with raises(ValueError, "PriorFactor.value", what):
        _lin([prior], {"x": g[state]})


@pytest.mark.parametrize("meas,state,what", MISMATCH)
def test_between_measurement_type(meas, state, what):
    eqs = _eqs()
    g = _groups()
    meas_value = jax.tree_util.tree_map(lambda a: a[1:], g[meas])
    f = eqs.BetweenFactor(eqs.Var("x", t[:-1]), eqs.Var("x", t[1:]), meas_value, _iso())
    with raises(ValueError, "BetweenFactor.measurement", what):
        _lin([f], {"x": g[state]})


def test_between_across_groups_of_different_shape():
    eqs = _eqs()
    f = eqs.BetweenFactor(
        eqs.Var("x", t[:-1]), eqs.Var("y", t[1:]), jnp.zeros((T - 1, 3)), _iso()
    )
    with raises(ValueError, "BetweenFactor.variables", "(3,)", "(2,)"):
        _lin([f], {"x": jnp.zeros((T, 3)), "y": jnp.zeros((T, 2))})


@pytest.mark.parametrize(
    "fn,noise,dims",
    [
        (_meas_first, "diag3", "(3,)"),
        (_meas, "diag1", "(1,)"),
        (_meas, "diag2", "(2,)"),
        (_meas, "sqrt1", "(1, 1)"),
        (_meas_first, "sqrt3", "(3, 3)"),
        (_meas, "iso_rows", "(4,)"),
    ],
)
@pytest.mark.parametrize("api", ["linearize", "cost", "nll", "whitened"])
def test_residual_dimension_vs_noise(fn, noise, dims, api):
    eqs = _eqs()
    models = {
        "diag3": eqs.DiagonalNoise(sqrt_precision=jnp.ones(3)),
        "diag1": eqs.DiagonalNoise(sqrt_precision=jnp.ones(1)),
        "diag2": eqs.DiagonalNoise(sqrt_precision=jnp.ones(2)),
        "sqrt1": eqs.SqrtInformationNoise(jnp.ones((1, 1))),
        "sqrt3": eqs.SqrtInformationNoise(jnp.eye(3)),
        "iso_rows": eqs.IsotropicNoise(sqrt_precision=jnp.ones(4)),
    }
    x = jnp.zeros((T, 3))
    f = eqs.FunctionFactor(fn, (eqs.Var("x", t),), models[noise], data=x)
    graph = eqs.FactorGraph([f])
    with raises(ValueError, "FunctionFactor", dims):
        if api == "linearize":
            eqs.linearize(graph, {"x": x})
        elif api == "cost":
            graph.cost({"x": x})
        elif api == "nll":
            graph.negative_log_likelihood({"x": x})
        else:
            graph.whitened_residuals({"x": x})


def test_residual_not_1d():
    eqs = _eqs()
    x = jnp.zeros((T, 3))
    f = eqs.FunctionFactor(_meas_matrix, (eqs.Var("x", t),), _iso(), data=x)
    import jaxtyping

    # The jaxtyping hook checks the return annotation first; without it the
    # linearisation raises ValueError "FunctionFactor.residual must return a
    # 1-D array".
    with raises(jaxtyping.TypeCheckError, "FunctionFactor.residual"):
        _lin([f], {"x": x})


@pytest.mark.parametrize(
    "case,exc,fragments",
    [
        ("data_rows", ValueError, ["FunctionFactor.data", "(4, 3)", "10"]),
        ("out_of_range", ValueError, ["FunctionFactor", "group 'x'", "out of range"]),
        ("missing_group", ValueError, ["FunctionFactor", "'y'", "not in the values"]),
        ("int_values", TypeError, ["int64", "floating-point"]),
        ("ragged_group", ValueError, ["group 'x'", "(10, 3)", "(9, 2)"]),
        ("scalar_group", ValueError, ["group 'x'", "()"]),
        ("values_not_dict", "hook", ["linearize", "values"]),
    ],
)
def test_graph_against_values(case, exc, fragments):
    eqs = _eqs()
    n = 10
    tt = np.arange(n)
    x = jnp.zeros((n, 3))
    factor = eqs.FunctionFactor(_meas, (eqs.Var("x", tt),), _iso(), data=x)
    values = {"x": x}
    if case == "data_rows":
        factor = eqs.FunctionFactor(_meas, (eqs.Var("x", tt),), _iso(), data=x[:4])
    elif case == "out_of_range":
        factor = eqs.FunctionFactor(_meas, (eqs.Var("x", tt + 5),), _iso(), data=x)
    elif case == "missing_group":
        factor = eqs.FunctionFactor(_meas, (eqs.Var("y", tt),), _iso(), data=x)
    elif case == "int_values":
        values = {"x": jnp.zeros((n, 3), int)}
    elif case == "ragged_group":
        values = {"x": {"a": x, "b": jnp.zeros((n - 1, 2))}}
    elif case == "scalar_group":
        values = {"x": jnp.zeros(())}
    elif case == "values_not_dict":
        values = x
    with raises(_hook(exc), *fragments):
        eqs.linearize(eqs.FactorGraph([factor]), values)


@pytest.mark.parametrize(
    "build,exc,fragments",
    [
        (lambda e: e.Var("x", [-1, 0]), ValueError, ["Var('x'", "non-negative"]),
        (lambda e: e.Var("x", np.array([0.5, 1.0])), ValueError, ["'x'", "float64"]),
        (lambda e: e.Var("x", [[0, 1]]), "hook", ["Var.__init__"]),
        (lambda e: e.Var(3, [0]), "hook", ["Var.__init__", "group"]),
        (
            lambda e: e.FunctionFactor(
                _dyn,
                (e.Var("x", [0, 1]), e.Var("x", [0, 1, 2])),
                e.IsotropicNoise(sqrt_precision=1.0),
            ),
            ValueError,
            ["FunctionFactor", "same number of rows", "[2, 3]"],
        ),
        (lambda e: e.FactorGraph([]), ValueError, ["at least one factor"]),
        (lambda e: e.FactorGraph([1]), "hook", ["FactorGraph.__init__"]),
    ],
)
def test_construction(build, exc, fragments):
    with raises(_hook(exc), *fragments):
        build(_eqs())


def _solve_graph():
    eqs = _eqs()
    x = jnp.zeros((T, 3))
    prior = eqs.PriorFactor(eqs.Var("x", [0]), jnp.zeros((1, 3)), _iso())
    dyn = eqs.FunctionFactor(
        _dyn, (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])), _iso(), params=1.0
    )
    return eqs.FactorGraph([prior, dyn]), {"x": x}


@pytest.mark.parametrize(
    "field,value,need",
    [
        ("initial_damping", -1.0, ">= 0"),
        ("initial_damping", float("nan"), ">= 0"),
        ("min_diagonal", 0.0, "> 0"),
        ("max_diagonal", 1e-9, ">= min_diagonal"),
        ("max_damping", 1e-9, "> initial_damping"),
        ("min_gain", 1.0, "in [0, 1)"),
        ("ftol", -1e-3, ">= 0"),
    ],
)
def test_levenberg_marquardt_fields(field, value, need):
    import eqsmooth as eqs

    with raises(ValueError, f"LevenbergMarquardt.{field}", need):
        eqs.LevenbergMarquardt(**{field: value})


@pytest.mark.parametrize(
    "max_steps,exc,fragment",
    [
        (-1, ValueError, ">= 1, got -1"),
        (0, ValueError, ">= 1, got 0"),
        (2.5, "hook", "least_squares"),
        ("3", "hook", "least_squares"),
        (True, TypeError, "True"),
        (None, "hook", "least_squares"),
    ],
)
def test_least_squares_max_steps(max_steps, exc, fragment):
    eqs = _eqs()
    graph, values = _solve_graph()
    with raises(_hook(exc), "max_steps", fragment):
        eqs.least_squares(graph, values, eqs.GaussNewton(), max_steps=max_steps)


@pytest.mark.parametrize("dtype", ["bfloat16", "float16"])
def test_least_squares_low_precision(dtype):
    eqs = _eqs()
    graph, values = _solve_graph()
    values = {"x": values["x"].astype(dtype)}
    with raises(TypeError, "values['x']", dtype, "float32 or float64"):
        eqs.least_squares(graph, values, eqs.GaussNewton())


@pytest.mark.parametrize(
    "kw,exc,fragments",
    [
        ({"solver": "gn"}, TypeError, ["solver", "str"]),
        ({"adjoint": "implicit"}, TypeError, ["adjoint", "str"]),
        ({"graph": [1]}, TypeError, ["graph", "list"]),
    ],
)
def test_least_squares_argument_types(kw, exc, fragments):
    import jaxtyping

    eqs = _eqs()
    graph, values = _solve_graph()
    args = {"graph": graph, "solver": eqs.GaussNewton()} | kw
    adjoint = args.pop("adjoint", eqs.ImplicitAdjoint())
    # The test suite's jaxtyping hook checks the annotations first.
    with raises(jaxtyping.TypeCheckError, fragments[0]):
        eqs.least_squares(args["graph"], values, args["solver"], adjoint=adjoint)


_GRAD = {}


def _grad_fn(hessian):
    """d/dp of a loss through a solve whose measurement is NaN (throw=False)."""
    import equinox as eqx

    eqs = _eqs()
    if hessian in _GRAD:
        return _GRAD[hessian]

    @eqx.filter_jit
    def fn(p, z):
        def loss(p):
            meas = eqs.FunctionFactor(_meas, (eqs.Var("x", t),), _iso(), data=z)
            dyn = eqs.FunctionFactor(
                _dyn, (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])), _iso(), params=p
            )
            sol = eqs.least_squares(
                eqs.FactorGraph([meas, dyn]),
                {"x": jnp.zeros((T, 3))},
                eqs.GaussNewton(),
                adjoint=eqs.ImplicitAdjoint(hessian=hessian),
                throw=False,
                max_steps=5,
            )
            return jnp.sum(sol.value["x"] ** 2), sol.result

        (value, result), grad = jax.value_and_grad(loss, has_aux=True)(p)
        return grad, result

    _GRAD[hessian] = fn
    return fn


@pytest.mark.parametrize("hessian", ["gauss_newton"])
def test_implicit_gradient_of_failed_solve_is_nan(hessian):
    eqs = _eqs()
    fn = _grad_fn(hessian)
    z = jnp.ones((T, 3))
    grad, result = fn(jnp.asarray(1.0), z)
    assert result == eqs.RESULTS.successful and np.isfinite(grad)
    grad, result = fn(jnp.asarray(1.0), z.at[2, 1].set(jnp.nan))
    assert result == eqs.RESULTS.nonfinite_problem
    assert np.isnan(grad)


def _matrix_factor():
    """A user factor (outside the jaxtyping-checked packages) whose residual
    is `(1, m)` instead of `(m,)`."""
    import equinox as eqx

    eqs = _eqs()

    class MatrixResidual(eqs.AbstractFactor):
        variables: tuple
        noise: eqs.IsotropicNoise

        def residual(self, x):
            return x[None, :]

    return MatrixResidual((eqs.Var("x", t),), _iso()), eqx


@pytest.mark.parametrize("api", ["cost", "nll"])
def test_residual_not_1d_in_cost(api):
    # The cost and the NLL name the factor and the shape, as the solve does
    # (they raised "check_shapes() takes 4 positional arguments but 5 were
    # given" before).
    eqs = _eqs()
    f, _ = _matrix_factor()
    graph = eqs.FactorGraph([f])
    x = {"x": jnp.zeros((T, 1))}
    fn = graph.cost if api == "cost" else graph.negative_log_likelihood
    with raises(ValueError, "MatrixResidual.residual", "1-D", "(1, 1)"):
        fn(x)


class _ForeignPose:
    """Stands in for a `gtsam.Pose2` passed where eqsmooth wants arrays."""

    def __init__(self, x, y, theta):
        self.xyt = (x, y, theta)


@pytest.mark.parametrize("field", ["data", "measurement"])
def test_foreign_objects_as_factor_data_name_the_field(field):
    # A gtsam object passed as a value was accepted and failed later inside
    # JAX without naming the factor or the field.
    eqs = _eqs()
    pose = _ForeignPose(0.0, 0.0, 0.0)
    if field == "data":
        make = lambda: eqs.FunctionFactor(
            _meas, (eqs.Var("x", t[:1]),), _iso(), data=pose
        )
        fragments = ["FunctionFactor.data", "_ForeignPose", "not an array"]
    else:
        make = lambda: eqs.BetweenFactor(
            eqs.Var("x", t[:1]), eqs.Var("x", t[1:2]), [pose], _iso()
        )
        fragments = ["BetweenFactor.measurement", "_ForeignPose", "not an array"]
    with raises(TypeError, *fragments):
        make()
