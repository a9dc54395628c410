"""Linear solvers of the Gauss-Newton model against a dense numpy reference."""

import functools as ft
import importlib.util

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


# ---------------------------------------------------------------------------
# Problems (Euclidean states; built lazily so the jaxtyping hook sees eqsmooth)
# ---------------------------------------------------------------------------


def _dynamics(p, v, p1, v1, data, params):
    # Nonlinear in v so that the Jacobians depend on the linearisation point.
    return jnp.concatenate([p1 - p - 0.1 * jnp.sin(v) - data, v1 - v])


def _measure(p, data, params):
    return jnp.stack([p[0] * p[1], p[1]]) - data


def _offset(x, data, params):
    return x - data


def chain_problem(seed: int, T: int = 6, dtype=jnp.float64):
    """Groups "p" and "v" (dim 2 each, T steps): dynamics touching four variables,
    unary measurements, priors on scattered steps, a reversed between factor."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    t = np.arange(T)

    def arr(*shape):
        return jnp.asarray(rng.normal(size=shape), dtype)

    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _dynamics,
                (
                    eqs.Var("p", t[:-1]),
                    eqs.Var("v", t[:-1]),
                    eqs.Var("p", t[1:]),
                    eqs.Var("v", t[1:]),
                ),
                eqs.IsotropicNoise(sqrt_precision=jnp.asarray(3.0, dtype)),
                data=arr(T - 1, 2),
            ),
            eqs.FunctionFactor(
                _measure,
                (eqs.Var("p", t),),
                eqs.DiagonalNoise(sqrt_precision=jnp.asarray([2.0, 0.5], dtype)),
                data=arr(T, 2),
            ),
            eqs.PriorFactor(
                eqs.Var("v", [3, 0]),
                arr(2, 2),
                eqs.IsotropicNoise(sqrt_precision=jnp.asarray(1.0, dtype)),
            ),
            # (t+1, t): contributes to super-diagonal blocks through a transpose.
            eqs.BetweenFactor(
                eqs.Var("v", t[1:][::2]),
                eqs.Var("v", t[:-1][::2]),
                arr(len(t[1:][::2]), 2),
                eqs.IsotropicNoise(sqrt_precision=jnp.asarray(0.7, dtype)),
            ),
        ]
    )
    values = {"p": arr(T, 2), "v": arr(T, 2)}
    return graph, values


def loop_problem(seed: int, N: int = 8):
    """Not a chain: a cycle of between factors with loop closures and landmarks."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    a = np.concatenate([np.arange(N - 1), [0, 2]])
    b = np.concatenate([np.arange(1, N), [5, 7]])
    lm_x, lm_l = np.array([0, 3, 5, 6]), np.array([0, 1, 1, 0])
    graph = eqs.FactorGraph(
        [
            eqs.BetweenFactor(
                eqs.Var("x", a),
                eqs.Var("x", b),
                jnp.asarray(rng.normal(size=(len(a), 2))),
                eqs.IsotropicNoise(sqrt_precision=2.0),
            ),
            eqs.FunctionFactor(
                _offset,
                (eqs.Var("x", [0]),),
                eqs.IsotropicNoise(sqrt_precision=1.0),
                data=jnp.zeros((1, 2)),
            ),
            eqs.BetweenFactor(
                eqs.Var("x", lm_x),
                eqs.Var("l", lm_l),
                jnp.asarray(rng.normal(size=(4, 2))),
                eqs.DiagonalNoise(sqrt_precision=jnp.asarray([1.0, 3.0])),
            ),
        ]
    )
    values = {
        "x": jnp.asarray(rng.normal(size=(N, 2))),
        "l": jnp.asarray(rng.normal(size=(2, 2))),
    }
    return graph, values


def closure_problem(seed: int, N: int = 9):
    """One group numbered along a trajectory: odometry plus loop closures (not a
    chain), with a prior on a middle variable: what ChainPreconditioner is for."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    a = np.concatenate([np.arange(N - 1), [0, 2, 8]])
    b = np.concatenate([np.arange(1, N), [5, 7, 3]])
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _dynamics,
                (eqs.Var("p", a), eqs.Var("v", a), eqs.Var("p", b), eqs.Var("v", b)),
                eqs.IsotropicNoise(sqrt_precision=2.0),
                data=jnp.asarray(rng.normal(size=(len(a), 2))),
            ),
            eqs.PriorFactor(
                eqs.Var("p", [4]),
                jnp.zeros((1, 2)),
                eqs.IsotropicNoise(sqrt_precision=1.0),
            ),
            eqs.PriorFactor(
                eqs.Var("v", [4]),
                jnp.zeros((1, 2)),
                eqs.IsotropicNoise(sqrt_precision=1.0),
            ),
        ]
    )
    values = {
        "p": jnp.asarray(rng.normal(size=(N, 2))),
        "v": jnp.asarray(rng.normal(size=(N, 2))),
    }
    return graph, values


def random_damping(lin, seed):
    rng = np.random.default_rng(seed)
    return {
        g.name: jnp.asarray(rng.uniform(0.1, 1.0, size=(g.count, g.dim)), lin.dtype)
        for g in lin.layout
    }


@eqx.filter_jit
def _dense_jacobian(lin):
    from eqsmooth.solve._linearization import dense_jacobian

    return dense_jacobian(lin)


def reference(lin, damping):
    """Dense numpy solution of (JᵀJ + diag(damping)) δ = −Jᵀr, group-major."""
    J, r = (np.asarray(a) for a in _dense_jacobian(lin))
    H = J.T @ J
    if damping is not None:
        H = H + np.diag(flat(lin, damping))
    return np.linalg.solve(H, -J.T @ r)


def flat(lin, delta):
    from eqsmooth.solve._linearization import flatten_tangent

    return np.asarray(flatten_tangent(lin, delta))


@eqx.filter_jit
def _solve(solver, lin, damping):
    from eqsmooth.solve import solve_normal

    return solve_normal(solver, lin, damping)


@eqx.filter_jit
def _linearize(graph, values):
    from eqsmooth.solve._linearization import linearize

    return linearize(graph, values)


_HAVE_CHOLMOD = importlib.util.find_spec("sksparse") is not None
# SparseCholesky needs the optional scikit-sparse (CHOLMOD); CI does not have it.
CHOLMOD = pytest.param(
    "cholmod",
    marks=pytest.mark.skipif(
        not _HAVE_CHOLMOD, reason="scikit-sparse (CHOLMOD) is not installed"
    ),
)


_HAVE_SPARSAX = importlib.util.find_spec("sparsax") is not None
# SparsaxCholesky needs the optional sparsax (the `sparse` extra).
SPARSAX = pytest.param(
    "sparsax",
    marks=pytest.mark.skipif(not _HAVE_SPARSAX, reason="sparsax is not installed"),
)


def _solvers():
    import eqsmooth as eqs

    return {
        "dense": eqs.DenseCholesky(),
        "tridiag": eqs.BlockTridiagonal(),
        "pcg": eqs.PCG(rtol=1e-13, max_steps=200),
        "pcg-chain": eqs.PCG(
            rtol=1e-13, max_steps=200, preconditioner=eqs.solve.ChainPreconditioner()
        ),
        "sparse": eqs.solve.SparseLU(),
        **({"cholmod": eqs.solve.SparseCholesky()} if _HAVE_CHOLMOD else {}),
        **({"sparsax": eqs.solve.SparsaxCholesky()} if _HAVE_SPARSAX else {}),
    }


@ft.cache
def _chain_lin(seed):
    return _linearize(*chain_problem(seed))


@ft.cache
def _loop_lin(seed):
    return _linearize(*loop_problem(seed))


@ft.cache
def _closure_lin(seed):
    return _linearize(*closure_problem(seed))


def _mixed(x, p, data, params):
    # A 3-vector and a 2-vector, coupled nonlinearly (every block nonzero).
    return jnp.concatenate([jnp.sin(x[:2]) * p + data, jnp.reshape(x[2] * p[0], (1,))])


def test_sparse_assembly_matches_dense_normal_matrix():
    """The block-wise CSC assembly equals JᵀJ + diag(damping) entry for entry:
    blocks of two shapes (3×3, 3×2, 2×2), variable pairs in both orders, the
    same variable in both slots of a row, and a variable no factor touches."""
    import eqsmooth as eqs
    from eqsmooth.solve._linear._linear_solver import NormalOperator
    from eqsmooth.solve._linear._sparse import _host_csc, assemble_sparse

    rng = np.random.default_rng(0)
    a, b = np.array([0, 2, 3, 1, 2]), np.array([1, 0, 3, 3, 2])  # 2→0; 3,3; 2,2
    xs, ls = np.array([0, 3, 1, 2]), np.array([1, 0, 0, 2])
    graph = eqs.FactorGraph(
        [
            eqs.BetweenFactor(
                eqs.Var("x", a),
                eqs.Var("x", b),
                jnp.asarray(rng.normal(size=(5, 3))),
                eqs.IsotropicNoise(sqrt_precision=2.0),
            ),
            eqs.FunctionFactor(
                _mixed,
                (eqs.Var("x", xs), eqs.Var("l", ls)),
                eqs.IsotropicNoise(sqrt_precision=1.5),
                data=jnp.asarray(rng.normal(size=(4, 2))),
            ),
        ]
    )
    values = {  # x: 5 variables (x[4] untouched), l: 3
        "x": jnp.asarray(rng.normal(size=(5, 3))),
        "l": jnp.asarray(rng.normal(size=(3, 2))),
    }

    @jax.jit
    def normal(values, damping):
        lin = _linearize(graph, values)
        return lin, assemble_sparse(NormalOperator(lin, damping)).data

    lin = jax.eval_shape(_linearize, graph, values)
    damping = {
        g.name: jnp.asarray(rng.uniform(0.5, 1.0, (g.count, g.dim))) for g in lin.layout
    }
    lin, data = normal(values, damping)
    state = assemble_sparse(NormalOperator(lin, damping))  # the pattern
    got = _host_csc(state.pattern, data).toarray()
    J = np.asarray(_dense_jacobian(lin)[0])
    want = J.T @ J + np.diag(flat(lin, damping))
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)
    # The pattern holds whole blocks: those of variable pairs sharing a row,
    # and every variable's diagonal block.
    var = np.repeat(np.arange(3 + 5), [2] * 3 + [3] * 5)  # layout: l, then x
    touch = np.zeros((J.shape[0], 8), bool)
    np.logical_or.at(touch, (slice(None), var), J != 0)
    blocks = (touch.T.astype(int) @ touch.astype(int) > 0) | np.eye(8, dtype=bool)
    stored = _host_csc(state.pattern, np.ones(state.pattern.nnz)).toarray() != 0
    np.testing.assert_array_equal(stored, blocks[var][:, var])


# ---------------------------------------------------------------------------
# Agreement with the reference
# ---------------------------------------------------------------------------


def _assert_matches_reference(name, lin, damping):
    """The solver `name` solves `lin` (damped by `damping`) to the reference."""
    import eqsmooth as eqs

    delta, result = _solve(_solvers()[name], lin, damping)
    assert result == eqs.RESULTS.successful
    np.testing.assert_allclose(
        flat(lin, delta), reference(lin, damping), rtol=0, atol=1e-9
    )


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize(
    "name", ["dense", "tridiag", "pcg", "pcg-chain", "sparse", CHOLMOD]
)
def test_chain_matches_reference(name, damped):
    for seed in (0, 1):
        lin = _chain_lin(seed)
        damping = random_damping(lin, seed) if damped else None
        _assert_matches_reference(name, lin, damping)


@pytest.mark.parametrize(
    "name, damped",
    [
        ("dense", False),
        ("pcg", False),
        ("pcg", True),
        ("sparse", False),
        pytest.param("cholmod", False, marks=CHOLMOD.marks),
        pytest.param("sparsax", True, marks=SPARSAX.marks),
    ],
)
def test_graph_matches_reference(name, damped):
    lin = _loop_lin(0)
    damping = random_damping(lin, 3) if damped else None
    _assert_matches_reference(name, lin, damping)


@pytest.mark.parametrize("damped", [False, True])
@pytest.mark.parametrize(
    "name", ["dense", "pcg", "pcg-chain", "sparse", CHOLMOD, SPARSAX]
)
def test_loop_closures_match_reference(name, damped):
    for seed in (0, 1):
        lin = _closure_lin(seed)
        damping = random_damping(lin, seed) if damped else None
        _assert_matches_reference(name, lin, damping)


def _residual_norms(lin, damping, delta):
    J, r = (np.asarray(a) for a in _dense_jacobian(lin))
    H = J.T @ J
    if damping is not None:
        H = H + np.diag(flat(lin, damping))
    b = -J.T @ r
    return np.linalg.norm(b - H @ flat(lin, delta)), np.linalg.norm(b)


@pytest.mark.parametrize("rtol", [1e-3, 1e-8])
def test_pcg_stops_on_residual_norm(rtol):
    """‖b − Hδ‖₂ ≤ rtol‖b‖₂ at exit, and not grossly tighter than asked
    (lineax's per-component test would run on to the smallest entries)."""
    import eqsmooth as eqs

    lin = _closure_lin(0)
    delta, result = _solve(eqs.PCG(rtol=rtol), lin, None)
    assert result == eqs.RESULTS.successful
    res, b = _residual_norms(lin, None, delta)
    assert res <= rtol * b * (1 + 1e-6)
    if rtol == 1e-3:
        # One fewer iteration would not have met the tolerance: the last
        # iterate is not far below it.
        assert res > 1e-3 * rtol * b


def test_chain_preconditioner_is_exact_on_chains():
    """On a chain M = JᵀJ + damping, so one CG iteration solves the system."""
    import eqsmooth as eqs

    lin = _chain_lin(0)
    damping = random_damping(lin, 0)
    solver = eqs.PCG(
        rtol=1e-10,
        max_steps=1,
        accept_inexact=False,
        preconditioner=eqs.solve.ChainPreconditioner(),
    )
    delta, result = _solve(solver, lin, damping)
    assert result == eqs.RESULTS.successful
    np.testing.assert_allclose(
        flat(lin, delta), reference(lin, damping), rtol=0, atol=1e-9
    )
    with pytest.raises(ValueError, match="same number of variables"):
        _solve(solver, _loop_lin(0), None)


def test_chain_float32_keeps_dtype():
    import eqsmooth as eqs

    lin = _linearize(*chain_problem(4, dtype=jnp.float32))
    delta, result = _solve(eqs.BlockTridiagonal(), lin, None)
    assert result == eqs.RESULTS.successful
    assert all(v.dtype == jnp.float32 for v in delta.values())
    np.testing.assert_allclose(flat(lin, delta), reference(lin, None), atol=1e-3)


# ---------------------------------------------------------------------------
# Structure errors and numerical failures
# ---------------------------------------------------------------------------


def test_block_tridiagonal_rejects_non_chain():
    import eqsmooth as eqs

    graph, values = chain_problem(0)
    t = np.arange(6)
    skip = eqs.BetweenFactor(
        eqs.Var("p", t[:-2]), eqs.Var("p", t[2:]), jnp.zeros((4, 2)),
        eqs.IsotropicNoise(sqrt_precision=1.0),
    )  # fmt: skip
    lin = _linearize(eqs.FactorGraph(list(graph.factors) + [skip]), values)
    with pytest.raises(
        ValueError, match=r"BetweenFactor.*row 0 touches p\[0\], p\[2\]"
    ):
        _solve(eqs.BlockTridiagonal(), lin, None)
    with pytest.raises(ValueError, match="same number of variables"):
        _solve(eqs.BlockTridiagonal(), _loop_lin(0), None)


def _gauge_free_chain(T=7):
    import eqsmooth as eqs

    t = np.arange(T)
    rng = np.random.default_rng(0)
    graph = eqs.FactorGraph(
        [
            eqs.BetweenFactor(
                eqs.Var("x", t[:-1]),
                eqs.Var("x", t[1:]),
                jnp.asarray(rng.normal(size=(T - 1, 2))),
                eqs.IsotropicNoise(sqrt_precision=10.0),
            )
        ]
    )
    return _linearize(graph, {"x": jnp.asarray(rng.normal(size=(T, 2)))})


@pytest.mark.parametrize("name", ["dense", "tridiag", "pcg", "sparse", CHOLMOD])
def test_singular_system_reports_and_stays_finite(name):
    import eqsmooth as eqs

    lin = _gauge_free_chain()
    delta, result = _solve(_solvers()[name], lin, None)
    assert np.all(np.isfinite(flat(lin, delta)))
    if name == "pcg":
        # Consistent singular system: CG may converge to a solution; it must be one.
        if result == eqs.RESULTS.successful:
            J, r = (np.asarray(a) for a in _dense_jacobian(lin))
            g = J.T @ (J @ flat(lin, delta) + r)
            assert np.max(np.abs(g)) < 1e-8
    else:
        assert result != eqs.RESULTS.successful
        assert np.all(flat(lin, delta) == 0)


def test_pcg_out_of_steps():
    """By default the last iterate counts (LM's gain ratio judges it); it
    decreases the quadratic model. `accept_inexact=False` reports it."""
    import eqsmooth as eqs
    from eqsmooth.solve._nonlinear._descent import predicted_decrease

    lin = _closure_lin(0)
    delta, result = _solve(eqs.PCG(max_steps=2), lin, None)
    assert result == eqs.RESULTS.successful
    assert np.all(np.isfinite(flat(lin, delta)))
    assert float(eqx.filter_jit(predicted_decrease)(lin, delta)) > 0
    res, b = _residual_norms(lin, None, delta)
    assert res > 1e-6 * b  # really inexact
    strict = eqs.PCG(max_steps=2, accept_inexact=False)
    delta2, result = _solve(strict, lin, None)
    assert result == eqs.RESULTS.max_steps_reached
    np.testing.assert_array_equal(flat(lin, delta2), flat(lin, delta))


def test_pcg_rejects_bad_config():
    import eqsmooth as eqs

    with pytest.raises(ValueError, match="rtol"):
        eqs.PCG(rtol=0.0, atol=0.0)
    with pytest.raises(ValueError, match="max_steps"):
        eqs.PCG(max_steps=0)
    with pytest.raises(TypeError, match="AbstractPreconditioner"):
        eqs.PCG(preconditioner="jacobi")  # pyright: ignore


# ---------------------------------------------------------------------------
# The lineax operator and solver directly, on odd and even lengths
# ---------------------------------------------------------------------------


def _random_blocks(T, D, seed):
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(T, 3 * D, D))
    diag = np.einsum("tmd,tme->tde", X, X) + 2 * D * np.eye(D)
    upper = rng.normal(size=(max(T - 1, 0), D, D))
    return jnp.asarray(diag), jnp.asarray(upper)


@pytest.mark.parametrize("T", [1, 2])
def test_cyclic_reduction_operator(T):
    # Longer chains (6 -> 3 -> 2 -> 1 blocks) are covered by the graph tests.
    import lineax as lx

    from eqsmooth.solve._linear._block_tridiagonal import (
        BlockCyclicReduction,
        BlockTridiagonalOperator,
    )

    D = 3
    diag, upper = _random_blocks(T, D, T)
    op = BlockTridiagonalOperator(diag, upper)
    dense = np.asarray(op.as_matrix())
    np.testing.assert_allclose(dense, dense.T)
    x = jnp.asarray(np.random.default_rng(1).normal(size=(T, D)))
    np.testing.assert_allclose(np.asarray(op.mv(x)).ravel(), dense @ np.ravel(x))
    np.testing.assert_allclose(np.asarray(lx.diagonal(op)), np.diag(dense))
    assert lx.is_symmetric(op) and lx.is_positive_semidefinite(op)
    sol = lx.linear_solve(op, x, BlockCyclicReduction())
    np.testing.assert_allclose(
        np.asarray(sol.value).ravel(), np.linalg.solve(dense, np.ravel(x)), atol=1e-12
    )


@pytest.mark.parametrize("tail", [1, 2, 3, 32])
def test_cyclic_reduction_levels_and_tail(tail):
    # Reduction levels of odd and even sizes down to `tail` blocks, then the
    # sequential tail: solve and selected inversion against a dense inverse.
    from eqsmooth.solve._linear import _block_tridiagonal as bt

    T, D = 11, 2
    diag, upper = _random_blocks(T, D, 5)
    dense = np.asarray(bt.BlockTridiagonalOperator(diag, upper).as_matrix())
    b = np.random.default_rng(2).normal(size=(T, D))
    # Compiled, not op by op (hundreds of small compilations otherwise).
    factor = eqx.filter_jit(bt.cyclic_reduction_factor)
    state = factor(diag, upper, tail)
    assert len(state.levels) == len(bt._level_sizes(T, tail))
    assert 1 <= state.tail.chol_inv.shape[0] <= tail
    assert bool(state.ok)
    x = np.asarray(eqx.filter_jit(bt.cyclic_reduction_solve)(state, jnp.asarray(b)))
    np.testing.assert_allclose(x.ravel(), np.linalg.solve(dense, b.ravel()), atol=1e-12)
    inv = np.linalg.inv(dense).reshape(T, D, T, D)
    cov, cross = eqx.filter_jit(bt.cyclic_reduction_inverse_blocks)(state, T)
    t = np.arange(T)
    np.testing.assert_allclose(np.asarray(cov), inv[t, :, t, :], atol=1e-12)
    np.testing.assert_allclose(
        np.asarray(cross), inv[t[:-1], :, t[:-1] + 1, :], atol=1e-12
    )
    # An indefinite matrix is reported, wherever its bad pivot falls.
    bad = np.array(diag)
    bad[T - 1] = -bad[T - 1]
    assert not bool(factor(jnp.asarray(bad), upper).ok)


@pytest.mark.parametrize("D", [1, 4, 9])  # 9: above SMALL_BLOCK_LIMIT, LAPACK
def test_small_blocks_match_numpy(D):
    from eqsmooth.solve._linear._small_blocks import block_cho_solve, block_cholesky

    diag, _ = _random_blocks(5, D, 3)
    a = np.array(diag)
    b = np.random.default_rng(4).normal(size=(5, D, 2))
    chol = np.asarray(block_cholesky(jnp.asarray(a)))
    np.testing.assert_allclose(chol, np.linalg.cholesky(a), rtol=1e-12, atol=1e-12)
    x = np.asarray(block_cho_solve(jnp.asarray(chol), jnp.asarray(b)))
    np.testing.assert_allclose(x, np.linalg.solve(a, b), rtol=1e-10, atol=1e-12)
    # An indefinite block gives non-finite factors (callers test the pivots).
    a[2] = -a[2]
    assert not np.all(np.isfinite(np.asarray(block_cholesky(jnp.asarray(a)))[2]))
    assert np.all(np.isfinite(np.asarray(block_cholesky(jnp.asarray(a)))[1]))


@pytest.mark.parametrize("M", [1, 5, 9])  # 9: above SMALL_BLOCK_LIMIT, einsum
def test_block_gram_matches_matmul(M):
    """`aᵀ b` of small blocks (the Gram blocks of every assembly), with
    broadcast batch axes, and its gradients."""
    from eqsmooth.solve._linear._small_blocks import block_gram

    rng = np.random.default_rng(M)
    a = jnp.asarray(rng.normal(size=(4, 1, M, 3)))
    b = jnp.asarray(rng.normal(size=(2, M, 2)))

    def ref(a, b):
        return jnp.swapaxes(a, -1, -2) @ b

    np.testing.assert_allclose(block_gram(a, b), ref(a, b), rtol=1e-13, atol=1e-13)
    w = jnp.asarray(rng.normal(size=(4, 2, 3, 2)))
    grads = jax.grad(lambda a, b: jnp.sum(w * block_gram(a, b)), (0, 1))(a, b)
    expected = jax.grad(lambda a, b: jnp.sum(w * ref(a, b)), (0, 1))(a, b)
    for g, e in zip(grads, expected):
        np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-12)


@pytest.mark.cpu_only
def test_chain_solve_calls_no_lapack():
    # jaxlib's batched LAPACK kernels can deadlock XLA:CPU's thread pool when two
    # run at once, and a cyclic reduction solve has one independent triangular
    # solve per level: the solve and the selected inversion must not call them.
    from eqsmooth.solve._linear._block_tridiagonal import (
        cyclic_reduction_factor,
        cyclic_reduction_inverse_blocks,
        cyclic_reduction_solve,
    )

    T = 40  # two reduction levels, then the sequential tail
    diag, upper = _random_blocks(T, 5, 0)
    state = cyclic_reduction_factor(diag, upper)
    assert state.levels
    b = jnp.ones((T, 5))
    hlo = [
        jax.jit(cyclic_reduction_solve).lower(state, b).as_text(),
        jax.jit(cyclic_reduction_inverse_blocks, static_argnums=1)
        .lower(state, T)
        .as_text(),
    ]
    factor_hlo = jax.jit(cyclic_reduction_factor).lower(diag, upper).as_text()
    assert "lapack" in factor_hlo  # the check below can see LAPACK calls
    for text in hlo:
        assert "lapack" not in text


# ---------------------------------------------------------------------------
# vmap and autodiff
# ---------------------------------------------------------------------------


def _stack(trees):
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *trees)


@pytest.mark.parametrize(
    "name", ["tridiag", "pcg", "pcg-chain", "sparse", CHOLMOD, SPARSAX]
)
def test_vmap_over_graphs(name):
    import eqsmooth as eqs

    problems = [chain_problem(seed) for seed in (5, 6, 7)]
    graphs, values = zip(*problems)
    solver = _solvers()[name]

    @eqx.filter_jit
    @eqx.filter_vmap
    def batched(graph, vals):
        return eqs.solve.solve_normal(solver, _linearize(graph, vals))

    deltas, results = batched(_stack(graphs), _stack(values))
    assert np.all(results == eqs.RESULTS.successful)
    for i, (graph, vals) in enumerate(problems):
        lin = _linearize(graph, vals)
        ref = reference(lin, None)
        got = flat(lin, {k: v[i] for k, v in deltas.items()})
        np.testing.assert_allclose(got, ref, atol=1e-9)


@pytest.mark.parametrize("name", ["tridiag", "pcg", "sparse", CHOLMOD, SPARSAX])
def test_grad_matches_finite_differences(name):
    """Reverse mode through lineax's solve rule: w.r.t. data and values (one
    Gauss-Newton step's solve, differentiated)."""
    import eqsmooth as eqs

    graph, values = chain_problem(2)
    rng = np.random.default_rng(0)
    weights = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in values.items()}

    def loss(solver, data, vals):
        first = eqx.tree_at(lambda f: f.data, graph.factors[0], data)
        g = eqs.FactorGraph((first,) + graph.factors[1:])
        delta, _ = eqs.solve.solve_normal(solver, _linearize(g, vals))
        return sum(jnp.sum(weights[k] * delta[k] ** 2) for k in delta)

    loss = eqx.filter_jit(loss)
    data = graph.factors[0].data
    solver = _solvers()[name]
    g_data, g_vals = eqx.filter_jit(jax.grad(loss, argnums=(1, 2)))(
        solver, data, values
    )
    eps = 1e-6
    for _ in range(2):
        d_data = jnp.asarray(rng.normal(size=data.shape))
        d_vals = {k: jnp.asarray(rng.normal(size=v.shape)) for k, v in values.items()}
        plus = loss(
            solver,
            data + eps * d_data,
            {k: values[k] + eps * d_vals[k] for k in values},
        )
        minus = loss(
            solver,
            data - eps * d_data,
            {k: values[k] - eps * d_vals[k] for k in values},
        )
        fd = (plus - minus) / (2 * eps)
        ad = jnp.sum(g_data * d_data) + sum(
            jnp.sum(g_vals[k] * d_vals[k]) for k in values
        )
        np.testing.assert_allclose(float(ad), float(fd), rtol=1e-6, atol=1e-8)


def test_sparse_cholesky_without_scikit_sparse_says_so(monkeypatch):
    import sys

    import eqsmooth as eqs

    monkeypatch.setitem(sys.modules, "sksparse", None)
    monkeypatch.setitem(sys.modules, "sksparse.cholmod", None)
    with pytest.raises(ImportError, match="scikit-sparse"):
        eqs.solve.SparseCholesky()


@pytest.mark.skipif(not _HAVE_SPARSAX, reason="sparsax is not installed")
def test_sparsax_factorization_matches_dense():
    """Log-determinant and marginal blocks (selected inversion) of a loopy graph."""
    import eqsmooth as eqs

    lin = _loop_lin(0)
    ours = eqs.solve.factorize(lin, eqs.solve.SparsaxCholesky())
    ref = eqs.solve.factorize(lin, eqs.DenseCholesky())
    assert isinstance(ours, eqs.solve.SparsaxFactorization)
    np.testing.assert_allclose(float(ours.log_det()), float(ref.log_det()), rtol=1e-12)
    got, want = ours.inverse_block_diagonal(), ref.inverse_block_diagonal()
    for k in want:
        np.testing.assert_allclose(got[k], want[k], rtol=0, atol=1e-12)


@pytest.mark.skipif(not _HAVE_SPARSAX, reason="sparsax is not installed")
def test_sparsax_not_positive_definite_raises():
    """CHOLMOD's failure stops the program (documented): no silent result."""
    import eqsmooth as eqs

    lin = _gauge_free_chain()
    with pytest.raises(Exception, match="not positive definite"):
        jax.block_until_ready(eqs.solve.solve_normal(eqs.solve.SparsaxCholesky(), lin))


def _have_mkl() -> bool:
    from eqsmooth.solve._linear._sparsax import _mkl_runtime

    return _mkl_runtime() is not None


@pytest.mark.skipif(
    not (_HAVE_SPARSAX and _have_mkl()), reason="sparsax or the mkl wheel is missing"
)
def test_sparsax_runs_on_mkl_when_installed():
    """With the `mkl` wheel installed, CHOLMOD's BLAS calls go to MKL: after a
    supernodal factorisation MKL has loaded its compute kernels."""
    import re
    from pathlib import Path

    import eqsmooth as eqs
    from eqsmooth.solve._linear._sparsax import _import_sparsax

    assert eqs.solve.sparsax_blas() == "mkl"
    sparsax = _import_sparsax()
    # Dense enough that CHOLMOD picks its supernodal (BLAS) factorisation.
    n = 150
    m = np.random.default_rng(0).normal(size=(n, n))
    a = m @ m.T + n * np.eye(n)
    rows, cols = np.triu_indices(n)
    b = np.arange(n, dtype=np.float64)
    x = sparsax.solve(rows, cols, jnp.asarray(a[rows, cols]), jnp.asarray(b))
    np.testing.assert_allclose(a @ np.asarray(x), b, rtol=1e-10, atol=1e-10)
    maps = Path("/proc/self/maps").read_text()
    assert re.search(r"libmkl_(avx\d*|def|mc3)\.so", maps), "MKL computed nothing"


def test_sparsax_missing_says_so(monkeypatch):
    import eqsmooth as eqs
    from eqsmooth.solve._linear import _default_solver, _sparsax

    lin = _loop_lin(0)
    layout, variables = lin.layout, tuple(f.variables for f in lin.factors)
    monkeypatch.setattr(_default_solver, "DENSE_LIMIT", 0)
    if _HAVE_SPARSAX:  # installed: the default for large non-chain graphs
        assert isinstance(
            _default_solver.default_linear_solver(layout, variables),
            eqs.solve.SparsaxCholesky,
        )
    monkeypatch.setattr(_sparsax.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ImportError, match="sparsax"):
        eqs.solve.SparsaxCholesky()
    # Without it, the default for large non-chain graphs is SparseLU.
    assert isinstance(
        _default_solver.default_linear_solver(layout, variables), eqs.solve.SparseLU
    )
