"""Hostile input to the Lie groups: off-group parameters and matrices, wrong
shapes. Everything here fails eagerly (no JIT) except the one `error_if` case."""

import inspect

import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises


def _lie():
    import eqsmooth.lie as lie

    return lie


GROUPS = ["SO2", "SE2", "SO3", "SE3"]
PARAMS = {"SO2": 2, "SE2": 4, "SO3": 4, "SE3": 7}
FIELDS = {
    "SO2": "unit_complex",
    "SE2": "unit_complex_xy",
    "SO3": "wxyz",
    "SE3": "wxyz_xyz",
}
TANGENT = {"SO2": 1, "SE2": 3, "SO3": 3, "SE3": 6}
MATRIX = {"SO2": 2, "SE2": 3, "SO3": 3, "SE3": 4}
SPACE = {"SO2": 2, "SE2": 2, "SO3": 3, "SE3": 3}


def _bad_params(name, kind):
    p = np.zeros(PARAMS[name])
    if kind == "zero":
        return p
    if kind == "scaled":
        p[0] = 2.0
        return p
    if kind == "nan":
        p[0] = np.nan
        return p
    if kind == "inf":
        p[0] = np.inf
        return p
    if kind == "batch_one_bad":
        q = np.zeros((3, PARAMS[name]))
        q[:, 0] = 1.0
        q[1, 0] = 0.0
        return q
    raise AssertionError(kind)


@pytest.mark.parametrize("kind", ["zero", "scaled", "nan", "inf", "batch_one_bad"])
@pytest.mark.parametrize("name", GROUPS)
def test_off_group_parameters(name, kind):
    cls = getattr(_lie(), name)
    expected = ["rotation part", FIELDS[name], "unit norm"]
    if kind == "batch_one_bad":
        expected.append("batch index (1,)")
    with raises(ValueError, name, *expected):
        cls(jnp.asarray(_bad_params(name, kind)))


@pytest.mark.parametrize("name", GROUPS)
def test_check_false_allows_normalize(name):
    cls = getattr(_lie(), name)
    p = np.zeros(PARAMS[name])
    p[0] = 2.0
    g = cls(jnp.asarray(p), check=False).normalize()
    np.testing.assert_allclose(g.parameters(), cls.identity(dtype=g.dtype).parameters())


@pytest.mark.parametrize("name", GROUPS)
def test_zero_rotation_normalize_raises(name):
    cls = getattr(_lie(), name)
    with raises(ValueError, name.replace("E", "O"), "norm nan"):
        cls(jnp.zeros(PARAMS[name]), check=False).normalize()


def _reflection(n, homogeneous):
    m = np.eye(n)
    k = n - 2 if homogeneous else n - 1
    m[k, k] = -1.0
    return m


def _bad_matrix(name, kind):
    n = MATRIX[name]
    hom = name.startswith("SE")
    m = np.eye(n)
    if kind == "reflection":
        return _reflection(n, hom), "reflection"
    if kind == "scaled":
        m[: n - hom, : n - hom] *= 2.0
        return m, "not orthonormal"
    if kind == "zero":
        m[: n - hom, : n - hom] = 0.0
        return m, "not orthonormal"
    if kind == "garbage":
        return np.arange(n * n, dtype=float).reshape(n, n), "not orthonormal"
    if kind == "nan":
        m[0, 0] = np.nan
        return m, "non-finite"
    if kind == "shear":
        m[0, 1] = 0.5
        return m, "not orthonormal"
    raise AssertionError(kind)


@pytest.mark.parametrize(
    "kind", ["reflection", "scaled", "zero", "garbage", "nan", "shear"]
)
@pytest.mark.parametrize("name", GROUPS)
def test_from_matrix_off_group(name, kind):
    cls = getattr(_lie(), name)
    m, what = _bad_matrix(name, kind)
    with raises(ValueError, f"{name}.from_matrix", what, "check=False"):
        cls.from_matrix(jnp.asarray(m))


@pytest.mark.parametrize("name", ["SE2", "SE3"])
@pytest.mark.parametrize("row", ["first", "last"])
def test_from_matrix_bad_bottom_row(name, row):
    cls = getattr(_lie(), name)
    n = MATRIX[name]
    m = np.eye(n)
    if row == "first":
        m[-1, 0] = 1.0
    else:
        m[-1, -1] = 2.0
    with raises(ValueError, f"{name}.from_matrix", "bottom row"):
        cls.from_matrix(jnp.asarray(m))


@pytest.mark.parametrize("name", GROUPS)
def test_from_matrix_batch_index(name):
    cls = getattr(_lie(), name)
    n = MATRIX[name]
    m = np.stack([np.eye(n)] * 3)
    m[2] = _reflection(n, name.startswith("SE"))
    with raises(ValueError, f"{name}.from_matrix", "batch index (2,)", "reflection"):
        cls.from_matrix(jnp.asarray(m))


@pytest.mark.parametrize("name", GROUPS)
def test_from_matrix_check_false_projects(name):
    cls = getattr(_lie(), name)
    m = np.eye(MATRIX[name])
    hom = name.startswith("SE")
    m[: MATRIX[name] - hom, : MATRIX[name] - hom] *= 1.5
    g = cls.from_matrix(jnp.asarray(m), check=False)
    np.testing.assert_allclose(g.as_matrix(), np.eye(MATRIX[name]), atol=1e-12)


def _unchecked(cls, method):
    """The method without the jaxtyping/beartype wrapper of the test hook, to
    exercise eqsmooth's own check (what users without runtime type checking
    meet)."""
    fn = next(c.__dict__[method] for c in cls.__mro__ if method in c.__dict__)
    fn = getattr(fn, "__func__", fn)
    return inspect.unwrap(fn)


def _shape_case(name, what):
    lie = _lie()
    cls = getattr(lie, name)
    if what == "matrix":
        n = MATRIX[name] + 1
        return cls, "from_matrix", (cls, jnp.eye(n)), [f"({n}, {n})"]
    if what == "tangent":
        d = TANGENT[name] + 1
        return cls, "exp", (cls, jnp.zeros(d)), ["tangent", f"({d},)"]
    if what == "points":
        s = SPACE[name] + 1
        return cls, "apply", (cls.identity(), jnp.zeros(s)), ["points", f"({s},)"]
    if what == "translation":
        rot = lie.SO2.identity() if name == "SE2" else lie.SO3.identity()
        s = SPACE[name] + 1
        args = (cls, rot, jnp.zeros(s))
        return cls, "from_rotation_and_translation", args, ["translation"]
    raise AssertionError(what)


SHAPE_CASES = [(g, w) for g in GROUPS for w in ("matrix", "tangent", "points")] + [
    ("SE2", "translation"),
    ("SE3", "translation"),
]


@pytest.mark.parametrize("name,what", SHAPE_CASES)
def test_wrong_shape_eqsmooth_check(name, what):
    cls, method, args, fragments = _shape_case(name, what)
    with raises(ValueError, name, *fragments):
        _unchecked(cls, method)(*args)


@pytest.mark.parametrize("name,what", SHAPE_CASES)
def test_wrong_shape_under_jaxtyping_hook(name, what):
    import jaxtyping

    cls, method, args, fragments = _shape_case(name, what)
    bound = getattr(args[0], method)
    if what == "matrix":
        # `from_matrix` is the base class's (its annotation says `n n`, not
        # the group's size): the group's own check names the shape.
        with raises(ValueError, name, *fragments):
            bound(*args[1:])
        return
    with raises(jaxtyping.TypeCheckError, "typechecking parameter"):
        bound(*args[1:])


def test_from_matrix_under_jit_error_if():
    import equinox as eqx

    lie = _lie()
    fn = eqx.filter_jit(lambda m: lie.SO3.from_matrix(m).parameters())
    fn(jnp.eye(3))
    with raises(eqx.EquinoxRuntimeError, "SO3.from_matrix", "check=False"):
        fn(jnp.diag(jnp.array([1.0, 1.0, -1.0])))
