"""eqsmooth's solvers as lineax / optimistix solvers, and theirs on our graphs."""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
import pytest
from helpers import loop_graph, random_chain, se2_loop


def se3_loop(seed: int, N: int = 6, noise_scale: float = 0.05):
    """A noisy SE(3) loop (odometry plus one loop closure), anchored by a prior."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    steps = jnp.asarray(
        np.concatenate(
            [np.tile([[1.0, 0.0, 0.1, 0.0, 0.2, 2 * np.pi / N]], (N, 1))], axis=0
        )
        + 0.05 * rng.normal(size=(N, 6))
    )
    poses = [eqs.SE3.exp(jnp.zeros(6))]
    for t in range(N - 1):
        poses.append(poses[-1] @ eqs.SE3.exp(steps[t]))
    truth = jax.tree_util.tree_map(lambda *x: jnp.stack(x), *poses)
    graph = loop_graph(
        truth, N, 6, rng, noise_scale, eqs.IsotropicNoise(sqrt_precision=10.0)
    )
    init = {"pose": truth @ eqs.SE3.exp(jnp.asarray(0.1 * rng.normal(size=(N, 6))))}
    return graph, init


@ft.cache
def _problems():
    graph_c, init_c, _ = random_chain(3, T=6)
    graph_2, init_2, _ = se2_loop(1)
    graph_3, init_3 = se3_loop(2)
    return {
        "chain": (graph_c, init_c),
        "se2": (graph_2, init_2),
        "se3": (graph_3, init_3),
    }


# ---------------------------------------------------------------------------
# The linear layer
# ---------------------------------------------------------------------------


def test_solvers_are_lineax_and_optimistix():
    import eqsmooth as eqs

    for s in (
        eqs.BlockTridiagonal(),
        eqs.PCG(),
        eqs.DenseCholesky(),
        eqs.solve.SparseLU(),
    ):
        assert isinstance(s, lx.AbstractLinearSolver)
    for s in (eqs.GaussNewton(), eqs.LevenbergMarquardt(), eqs.FixedStepGaussNewton()):
        assert isinstance(s, optx.AbstractLeastSquaresSolver)
    assert eqs.solve.AbstractNormalSolver.__name__ != "AbstractLinearSolver"


@eqx.filter_jit
def _steps(lin, damping):
    import eqsmooth as eqs

    solvers = {
        "ours": eqs.DenseCholesky(),
        "lx.Cholesky": lx.Cholesky(),
        "lx.CG": lx.CG(rtol=1e-12, atol=1e-12, max_steps=500),
        "lx.Auto": lx.AutoLinearSolver(well_posed=None),
    }
    out = {k: eqs.solve.solve_normal(s, lin, damping) for k, s in solvers.items()}
    op = eqs.solve.NormalOperator(lin, damping)
    pre = eqs.solve.BlockJacobi().as_operator(op)
    out["lx.CG+BlockJacobi"] = eqs.solve.solve_normal(
        lx.CG(rtol=1e-12, atol=1e-12, max_steps=500),
        lin,
        damping,
        options={"preconditioner": pre},
    )
    out["PCG+options"] = eqs.solve.solve_normal(
        eqs.PCG(rtol=1e-13), lin, damping, options={"preconditioner": pre}
    )
    return out, op.as_matrix(), lx.diagonal(op), op.mv(out["ours"][0])


@pytest.mark.parametrize("name,damped", [("chain", True), ("se3", False)])
def test_lineax_solvers_give_the_same_step(name, damped):
    import eqsmooth as eqs
    from eqsmooth.solve._linearization import flatten_tangent, gradient

    graph, values = _problems()[name]
    lin = eqs.solve.linearize(graph, values)
    damping = {g.name: jnp.full((g.count, g.dim), 0.5) for g in lin.layout}
    for damp in [damping if damped else None]:
        out, H, diag, Hx = _steps(lin, damp)
        H = np.asarray(H)
        np.testing.assert_allclose(H, H.T, atol=1e-12)
        np.testing.assert_allclose(np.asarray(diag), np.diag(H), rtol=1e-12)
        g = np.asarray(flatten_tangent(lin, gradient(lin)))
        ref = np.linalg.solve(H, -g)
        # mv and as_matrix agree.
        x_ours = np.asarray(flatten_tangent(lin, out["ours"][0]))
        np.testing.assert_allclose(
            np.asarray(flatten_tangent(lin, Hx)), H @ x_ours, rtol=1e-9, atol=1e-9
        )
        for k, (delta, result) in out.items():
            assert result == eqs.RESULTS.successful, k
            got = np.asarray(flatten_tangent(lin, delta))
            np.testing.assert_allclose(got, ref, rtol=1e-7, atol=1e-8, err_msg=k)
    if name == "chain":
        delta, result = eqx.filter_jit(eqs.solve.solve_normal)(
            eqs.BlockTridiagonal(), lin, damping
        )
        assert result == eqs.RESULTS.successful
        np.testing.assert_allclose(
            np.asarray(flatten_tangent(lin, delta)), ref, rtol=1e-9, atol=1e-10
        )


def test_normal_operator_rules():
    import eqsmooth as eqs

    graph, values = _problems()["se2"]
    op = eqs.solve.NormalOperator(eqs.solve.linearize(graph, values))
    assert lx.is_symmetric(op) and lx.is_positive_semidefinite(op)
    assert not lx.is_diagonal(op) and not lx.is_tridiagonal(op)
    assert op.transpose() is op
    assert isinstance(
        lx.AutoLinearSolver(well_posed=None).select_solver(op), lx.Cholesky
    )
    with pytest.raises(ValueError, match="damping has groups"):
        eqs.solve.NormalOperator(op.lin, {"nope": jnp.zeros((1, 1))})
    with pytest.raises(ValueError, match="NormalOperator"):
        eqs.BlockTridiagonal().init(lx.MatrixLinearOperator(jnp.eye(2)), {})
    with pytest.raises(TypeError, match="lineax"):
        eqs.solve.solve_normal("cholesky", op.lin)  # pyright: ignore


def test_default_linear_solver_from_structure():
    import eqsmooth as eqs

    def pick(name):
        graph, values = _problems()[name]
        layout = graph.validate(values)
        return eqs.solve.default_linear_solver(
            layout, tuple(f.variables for f in graph.factors)
        )

    assert isinstance(pick("chain"), eqs.BlockTridiagonal)
    assert isinstance(pick("se2"), eqs.DenseCholesky)  # a loop closure


# ---------------------------------------------------------------------------
# The nonlinear layer
# ---------------------------------------------------------------------------


@ft.cache
def _reference(name):
    import eqsmooth as eqs

    graph, values = _problems()[name]
    sol = eqs.least_squares(
        graph, values, eqs.LevenbergMarquardt(eqs.DenseCholesky()), max_steps=100
    )
    return sol


def _assert_same_minimum(graph, got, ref):
    import eqsmooth as eqs

    cost = eqx.filter_jit(lambda g, v: g.cost(v))
    c_got, c_ref = float(cost(graph, got)), float(cost(graph, ref.value))
    assert c_got == pytest.approx(c_ref, rel=1e-8, abs=1e-12)
    for k in ref.value:
        d = eqx.filter_jit(eqs.local)(ref.value[k], got[k])
        assert float(jnp.max(jnp.abs(d))) < 1e-6


# SE(3) repeats the SE(2) case's code path on another group (slow: 40 s).
@pytest.mark.parametrize("name", ["se2", pytest.param("se3", marks=pytest.mark.slow)])
def test_optx_least_squares_runs_our_solvers(name):
    import eqsmooth as eqs

    graph, values = _problems()[name]
    ref = _reference(name)
    solvers = [eqs.GaussNewton()]
    if name == "se2":
        solvers.append(eqs.GaussNewton(lx.Cholesky()))
    for solver in solvers:
        sol = eqx.filter_jit(
            lambda s, g, v: optx.least_squares(
                eqs.solve.graph_residuals,
                s,
                v,
                args=g,
                max_steps=50,
                adjoint=optx.RecursiveCheckpointAdjoint(),
            )
        )(solver, graph, values)
        assert sol.result == optx.RESULTS.successful
        _assert_same_minimum(graph, sol.value, ref)
    # The residuals optimistix sees are the graph's cost.
    r = eqs.solve.graph_residuals(values, graph)
    np.testing.assert_allclose(
        0.5 * sum(float(jnp.sum(x * x)) for x in r), float(graph.cost(values))
    )


@pytest.mark.parametrize("name", ["se2", pytest.param("se3", marks=pytest.mark.slow)])
def test_tangent_adapter_with_optimistix_solvers(name):
    import eqsmooth as eqs

    graph, values = _problems()[name]
    ref = _reference(name)
    solvers = [optx.LevenbergMarquardt(rtol=1e-10, atol=1e-10)]
    if name == "se2":
        cg = lx.CG(rtol=1e-12, atol=1e-12, max_steps=500)
        solvers.append(
            optx.GaussNewton(rtol=1e-10, atol=1e-10, linear_solver=lx.Normal(cg))
        )
    for solver in solvers:
        sol = eqs.solve.tangent_least_squares(graph, values, solver, max_steps=100)
        assert sol.result == eqs.RESULTS.successful
        _assert_same_minimum(graph, sol.value, ref)


def test_our_solvers_reject_bad_args():
    import eqsmooth as eqs

    graph, values = _problems()["se2"]
    with pytest.raises(TypeError, match="args=graph"):
        optx.least_squares(
            lambda y, a: y, eqs.GaussNewton(), values, args=None, max_steps=2
        )
    with pytest.raises(TypeError, match="tangent_least_squares"):
        eqs.least_squares(graph, values, optx.LevenbergMarquardt(1e-8, 1e-8))  # pyright: ignore


def test_tangent_adapter_gradient_matches_implicit_adjoint():
    """optimistix's implicit adjoint is right in tangent coordinates: it agrees
    with eqsmooth's (exact-Hessian) implicit adjoint."""
    import eqsmooth as eqs

    graph, values = _problems()["se2"]
    w = jnp.asarray(np.random.default_rng(0).normal(size=(8, 3)))

    def loss(scale, which):
        first = eqx.tree_at(lambda f: f.noise.sqrt_precision, graph.factors[0], scale)
        g = eqs.FactorGraph((first,) + graph.factors[1:])
        if which == "ours":
            x = eqs.least_squares(
                g, values, eqs.GaussNewton(eqs.DenseCholesky()), max_steps=50
            ).value
        else:
            x = eqs.solve.tangent_least_squares(
                g, values, optx.LevenbergMarquardt(rtol=1e-12, atol=1e-12)
            ).value
        return jnp.sum(w * eqs.local(values["pose"], x["pose"]))

    scale = graph.factors[0].noise.sqrt_precision
    g_ours = eqx.filter_jit(jax.grad(loss))(scale, "ours")
    g_optx = eqx.filter_jit(jax.grad(loss))(scale, "optx")
    np.testing.assert_allclose(np.asarray(g_optx), np.asarray(g_ours), rtol=1e-5)


# ---------------------------------------------------------------------------
# Result codes
# ---------------------------------------------------------------------------


def test_result_codes_promote_by_name():
    """`promote_result` maps every lineax and optimistix code to the eqsmooth
    code of the same name, as equinox's `RESULTS.promote` does, concrete,
    traced and batched; its name lists cover both libraries' codes."""
    import eqsmooth as eqs
    from eqsmooth.solve._solution import LINEAX_CODES, OPTX_CODES, promote_result

    R = eqs.solve.RESULTS
    assert len(LINEAX_CODES) == len(lx.RESULTS)
    assert len(OPTX_CODES) == len(optx.RESULTS)
    for parent, names in ((lx.RESULTS, LINEAX_CODES), (optx.RESULTS, OPTX_CODES)):
        for name in names:
            code = getattr(parent, name)
            want = getattr(R, name)
            assert promote_result(code) == want, name
            assert R.promote(code) == want, name
            traced = jax.jit(lambda c: promote_result(c) == want)(code)
            assert bool(traced), name
        codes = jax.tree_util.tree_map(
            lambda *x: jnp.stack(x), *[getattr(parent, n) for n in names]
        )
        got = jax.vmap(promote_result)(codes)
        want = jax.tree_util.tree_map(
            lambda *x: jnp.stack(x), *[getattr(R, n) for n in names]
        )
        np.testing.assert_array_equal(
            jax.tree_util.tree_leaves(got)[0], jax.tree_util.tree_leaves(want)[0]
        )


def test_tracing_a_solve_compiles_no_eager_program():
    """Tracing a solve runs nothing eagerly: equinox's `RESULTS.promote` built
    its lookup table inside the trace, which compiled two small programs in
    every fresh process (the kernel sweep counted them)."""
    from helpers import compiled_programs

    import eqsmooth as eqs

    graph, init = _problems()["se2"]
    solver = eqs.LevenbergMarquardt()
    jax.clear_caches()
    with compiled_programs() as names:
        jax.jit(lambda g, v: eqs.least_squares(g, v, solver, throw=False).value).trace(
            graph, init
        )
    assert names == [], names
