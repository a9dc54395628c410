"""eqsmooth's linear solvers on plain lineax operators (issue 55).

`PCG` and `DenseCholesky` solve any real symmetric positive semidefinite
lineax operator (a matrix, a function of a dict of arrays, a pytree of
blocks), under `jit` and `grad` through `lx.linear_solve`, against a dense
`jnp.linalg.solve` reference in float64; an operator without the tag gets an
error naming it. The structured solvers refuse a plain operator with a
`TypeError` naming the solver and what it needs.
"""

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest
from jax.flatten_util import ravel_pytree


# The unknowns as a dict of arrays: 2 + 3 = 5 coordinates, in `tree_leaves`
# order ("a" then "b").
_STRUCTURE = {
    "a": jax.ShapeDtypeStruct((2,), jnp.float64),
    "b": jax.ShapeDtypeStruct((3,), jnp.float64),
}
_N = 5


def _spd(theta):
    """A symmetric positive definite 5 × 5 matrix, smooth in `theta` (25,)."""
    L = theta.reshape(_N, _N)
    return L @ L.T + jnp.eye(_N, dtype=theta.dtype)


def _like(flat):
    _, unravel = ravel_pytree(
        jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), _STRUCTURE)
    )
    return unravel(flat)


def _matrix_op(A):
    return lx.MatrixLinearOperator(A, lx.positive_semidefinite_tag)


def _function_op(A):
    def mv(x):
        flat, _ = ravel_pytree(x)
        return _like(A @ flat)

    return lx.FunctionLinearOperator(mv, _STRUCTURE, lx.positive_semidefinite_tag)


def _pytree_op(A):
    # lineax's layout: for each output leaf, a tree of the input structure
    # whose leaves have shape `out_shape + in_shape`.
    sl = {"a": slice(0, 2), "b": slice(2, 5)}
    blocks = {o: {i: A[sl[o], sl[i]] for i in sl} for o in sl}
    return lx.PyTreeLinearOperator(blocks, _STRUCTURE, lx.positive_semidefinite_tag)


_OPERATORS = {
    "matrix": (_matrix_op, False),
    "function": (_function_op, True),
    "pytree": (_pytree_op, True),
}


def _solvers():
    import eqsmooth as eqs

    return {
        "PCG": eqs.PCG(rtol=1e-13, atol=1e-300, max_steps=50),
        "DenseCholesky": eqs.DenseCholesky(),
    }


def _data(seed=0):
    rng = np.random.default_rng(seed)
    theta = jnp.asarray(rng.normal(size=_N * _N) * 0.5)
    b = jnp.asarray(rng.normal(size=_N))
    return theta, b


def _solve(make, solver, theta, b, as_tree):
    operator = make(_spd(theta))
    rhs = _like(b) if as_tree else b
    sol = lx.linear_solve(operator, rhs, solver)
    flat, _ = ravel_pytree(sol.value)
    return flat


def _reference(theta, b):
    return jnp.linalg.solve(_spd(theta), b)


@pytest.mark.parametrize("solver_name", ["PCG", "DenseCholesky"])
@pytest.mark.parametrize("op_name", list(_OPERATORS))
def test_solves_lineax_operators(solver_name, op_name):
    solver = _solvers()[solver_name]
    make, as_tree = _OPERATORS[op_name]
    theta, b = _data()

    def solve(theta, b):
        return _solve(make, solver, theta, b, as_tree)

    want = _reference(theta, b)
    np.testing.assert_allclose(jax.jit(solve)(theta, b), want, rtol=1e-10, atol=1e-12)
    if as_tree:  # the solution keeps the operator's structure
        x = jax.eval_shape(
            lambda: lx.linear_solve(make(_spd(theta)), _like(b), solver).value
        )
        assert x == _STRUCTURE

    # Reverse mode through lx.linear_solve, with respect to the operator's
    # entries and the right-hand side, against the dense reference.
    w = jnp.arange(1.0, _N + 1.0)

    def loss(fn):
        return lambda theta, b: jnp.sum(w * fn(theta, b) ** 2)

    got = jax.jit(jax.grad(loss(solve), argnums=(0, 1)))(theta, b)
    ref = jax.grad(loss(_reference), argnums=(0, 1))(theta, b)
    for g, r in zip(got, ref):
        np.testing.assert_allclose(g, r, rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize("solver_name", ["PCG", "DenseCholesky"])
def test_vmap_over_operators(solver_name):
    solver = _solvers()[solver_name]
    thetas = jnp.stack([_data(s)[0] for s in range(3)])
    bs = jnp.stack([_data(s)[1] for s in range(3)])
    got = jax.vmap(lambda t, b: _solve(_matrix_op, solver, t, b, False))(thetas, bs)
    want = jax.vmap(_reference)(thetas, bs)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("solver_name", ["PCG", "DenseCholesky"])
def test_untagged_operator_names_the_tag(solver_name):
    solver = _solvers()[solver_name]
    theta, b = _data()
    A = _spd(theta)
    untagged = [
        lx.MatrixLinearOperator(A),
        lx.MatrixLinearOperator(A, lx.symmetric_tag),  # symmetric is not enough
        lx.FunctionLinearOperator(lambda x: x, _STRUCTURE),
    ]
    for op in untagged:
        rhs = b if isinstance(op, lx.MatrixLinearOperator) else _like(b)
        with pytest.raises(ValueError, match="positive_semidefinite_tag") as info:
            lx.linear_solve(op, rhs, solver)
        assert solver_name in str(info.value)


@pytest.mark.parametrize("solver_name", ["PCG", "DenseCholesky"])
def test_complex_operator_raises(solver_name):
    solver = _solvers()[solver_name]
    op = lx.MatrixLinearOperator(
        jnp.eye(2, dtype=jnp.complex128), lx.positive_semidefinite_tag
    )
    with pytest.raises(ValueError, match="real"):
        solver.init(op, {})


def test_dense_cholesky_singular_operator_is_a_result():
    import eqsmooth as eqs

    A = jnp.diag(jnp.array([1.0, 0.0, 2.0]))
    sol = jax.jit(
        lambda A: lx.linear_solve(
            _matrix_op(A), jnp.ones(3), eqs.DenseCholesky(), throw=False
        )
    )(A)
    assert sol.result == lx.RESULTS.singular
    np.testing.assert_array_equal(sol.value, np.zeros(3))
    state = jax.jit(lambda A: eqs.DenseCholesky().init(_matrix_op(A), {}))(
        2 * jnp.eye(3)
    )
    np.testing.assert_allclose(state.log_det(), 3 * np.log(2.0))
    with pytest.raises(ValueError, match="NormalOperator"):
        state.inverse_block_diagonal()


def test_issue_example():
    """The call from issue 55, verbatim."""
    import eqsmooth as eqs

    op = lx.MatrixLinearOperator(2 * jnp.eye(3), lx.positive_semidefinite_tag)
    for solver in (eqs.PCG(), eqs.DenseCholesky()):
        x = lx.linear_solve(op, jnp.ones(3), solver).value
        np.testing.assert_allclose(x, 0.5 * np.ones(3), rtol=1e-12)


def _structured_solvers():
    import eqsmooth as eqs

    solvers = [eqs.BlockTridiagonal(), eqs.SparseLU()]
    for cls in (eqs.solve.SparseCholesky, eqs.solve.SparsaxCholesky):
        try:
            solvers.append(cls())
        except ImportError:  # optional packages
            pass
    return solvers


def test_structured_solvers_refuse_plain_operators():
    import eqsmooth as eqs

    op = _matrix_op(2 * jnp.eye(3))
    for solver in _structured_solvers():
        name = type(solver).__name__
        with pytest.raises(TypeError, match=f"{name} .*NormalOperator"):
            lx.linear_solve(op, jnp.ones(3), solver)
        # Also a ValueError, as these checks raised before.
        with pytest.raises(ValueError, match=name):
            solver.init(op, {})
    with pytest.raises(TypeError, match="BlockCyclicReduction .*BlockTridiagonal"):
        eqs.solve.BlockCyclicReduction().init(op, {})


def test_linear_solve_result_travels_as_lineax_result():
    """The normal solve hands lineax's result on as an `lx.RESULTS` item,
    which `promote_result` maps to eqsmooth's code by name."""
    import eqsmooth as eqs
    from eqsmooth.solve._linear._linear_solver import _linear_solve
    from eqsmooth.solve._solution import promote_result, result_index

    A = jnp.diag(jnp.array([1.0, 0.0, 2.0]))
    x, result = _linear_solve(_matrix_op(A), jnp.ones(3), eqs.DenseCholesky(), {})
    assert isinstance(result, lx.RESULTS)
    assert result == lx.RESULTS.singular
    assert promote_result(result) == eqs.RESULTS.singular
    _, ok = jax.jit(
        lambda b: _linear_solve(_matrix_op(2 * jnp.eye(3)), b, eqs.PCG(), {})
    )(jnp.ones(3))
    assert isinstance(ok, lx.RESULTS) and ok == lx.RESULTS.successful
    assert int(result_index(eqs.RESULTS.successful)) == 0
    with pytest.raises(TypeError, match="RESULTS"):
        result_index(lx.RESULTS.successful)  # pyright: ignore[reportArgumentType]
