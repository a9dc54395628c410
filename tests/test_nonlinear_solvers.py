import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


TIGHT = dict(ftol=1e-12, gtol=1e-8, xtol=1e-12)


def _solvers():
    import eqsmooth as eqs

    return {
        "gn-tridiag": eqs.GaussNewton(eqs.BlockTridiagonal(), **TIGHT),
        "lm-tridiag": eqs.LevenbergMarquardt(eqs.BlockTridiagonal(), **TIGHT),
        "lm-dense": eqs.LevenbergMarquardt(eqs.DenseCholesky(), **TIGHT),
        "lm-pcg": eqs.LevenbergMarquardt(eqs.PCG(), **TIGHT),
    }


@pytest.mark.parametrize("name", ["gn-tridiag", "lm-tridiag", "lm-dense", "lm-pcg"])
def test_chain_converges_to_stationary_point(name):
    from helpers import random_chain

    import eqsmooth as eqs

    graph, init, _ = random_chain(0, robust=(name == "lm-dense"))
    sol = eqs.least_squares(graph, init, _solvers()[name], max_steps=50)
    assert sol.result == eqs.RESULTS.successful
    g = jax.grad(lambda x: graph.cost({"x": x}))(sol.value["x"])
    # IRLS (robust) converges linearly, Gauss-Newton quadratically.
    assert float(jnp.max(jnp.abs(g))) < (1e-4 if name == "lm-dense" else 1e-6)
    hist = np.asarray(sol.stats["cost_history"])
    assert np.all(np.diff(hist) <= 1e-12)  # monotone
    assert sol.stats["final_cost"] < sol.stats["initial_cost"]


def test_all_solvers_agree_on_se2_loop():
    from helpers import se2_loop

    import eqsmooth as eqs

    graph, init, truth = se2_loop(1)
    ref = eqs.least_squares(graph, init, eqs.LevenbergMarquardt(eqs.DenseCholesky()))
    for solver in [
        eqs.GaussNewton(eqs.DenseCholesky()),
        eqs.LevenbergMarquardt(eqs.PCG()),
    ]:
        sol = eqs.least_squares(graph, init, solver)
        np.testing.assert_allclose(
            sol.stats["final_cost"], ref.stats["final_cost"], rtol=1e-8
        )
        d = eqs.local(ref.value["pose"], sol.value["pose"], batch_ndim=1)
        assert float(jnp.max(jnp.abs(d))) < 1e-6
    # non-chain graph (loop closure) is refused by the chain solver
    with pytest.raises(ValueError, match="chain"):
        eqs.least_squares(graph, init, eqs.GaussNewton(eqs.BlockTridiagonal()))


def test_lm_handles_gauge_freedom_gn_reports_it():
    """No prior: JᵀJ is singular. LM still converges; GN gives a result code."""
    from helpers import se2_loop

    import eqsmooth as eqs

    graph, init, _ = se2_loop(2)
    free = eqs.FactorGraph(graph.factors[:1])
    sol = eqs.least_squares(free, init, eqs.LevenbergMarquardt(eqs.DenseCholesky()))
    assert sol.result == eqs.RESULTS.successful
    assert all(jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(sol.value))
    gn = eqs.least_squares(
        free, init, eqs.GaussNewton(eqs.DenseCholesky()), throw=False
    )
    assert gn.result != eqs.RESULTS.successful
    assert all(jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(gn.value))
    with pytest.raises(eqx.EquinoxRuntimeError):
        eqs.least_squares(free, init, eqs.GaussNewton(eqs.DenseCholesky()))


def test_nan_measurement_gives_result_code():
    from helpers import random_chain

    import eqsmooth as eqs

    graph, init, _ = random_chain(3)
    bad = eqx.tree_at(
        lambda g: g.factors[1].data, graph, graph.factors[1].data.at[2, 0].set(jnp.nan)
    )
    sol = eqs.least_squares(
        bad, init, eqs.LevenbergMarquardt(eqs.BlockTridiagonal()), throw=False
    )
    assert sol.result == eqs.RESULTS.nonfinite_problem
    assert int(sol.stats["num_steps"]) == 0


def test_throw_inside_jit_and_with_closed_over_arguments():
    """`throw=True` under `jit`: the graph traced, or closed over (concrete
    arrays inside a traced function, which once failed converting the
    result code on the host)."""
    from helpers import random_chain

    import eqsmooth as eqs

    graph, init, _ = random_chain(4)
    solver = eqs.GaussNewton(eqs.BlockTridiagonal())
    ok = eqs.least_squares(graph, init, solver).value
    closed = jax.jit(lambda: eqs.least_squares(graph, init, solver).value)()
    traced = jax.jit(lambda g: eqs.least_squares(g, init, solver).value)(graph)
    for got in (closed, traced):
        np.testing.assert_allclose(got["x"], ok["x"], rtol=1e-12)
    # (Under plain jax.jit the same error arrives wrapped in a JaxRuntimeError.)
    with pytest.raises(eqx.EquinoxRuntimeError, match="maximum number of steps"):
        eqx.filter_jit(lambda g: eqs.least_squares(g, init, solver, max_steps=1).value)(
            graph
        )


def test_max_steps_and_fixed_steps():
    from helpers import random_chain

    import eqsmooth as eqs

    graph, init, _ = random_chain(4)
    sol = eqs.least_squares(
        graph, init, eqs.GaussNewton(eqs.BlockTridiagonal()), max_steps=1, throw=False
    )
    assert sol.result == eqs.RESULTS.nonlinear_max_steps_reached
    fixed = eqs.least_squares(
        graph, init, eqs.FixedStepGaussNewton(eqs.BlockTridiagonal(), num_steps=3)
    )
    assert fixed.result == eqs.RESULTS.successful
    assert int(fixed.stats["num_steps"]) == 3


def test_batched_solve_matches_individual():
    from helpers import random_chain

    import eqsmooth as eqs

    solver = eqs.GaussNewton(eqs.BlockTridiagonal())
    problems = [random_chain(s) for s in range(3)]
    graphs = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[p[0] for p in problems])
    inits = jax.tree_util.tree_map(lambda *a: jnp.stack(a), *[p[1] for p in problems])
    batched = eqx.filter_vmap(lambda g, v: eqs.least_squares(g, v, solver).value)(
        graphs, inits
    )
    for i, (g, v, _) in enumerate(problems):
        single = eqs.least_squares(g, v, solver).value
        np.testing.assert_allclose(batched["x"][i], single["x"], atol=1e-9)


def test_unrolled_gradient_matches_finite_differences():
    """d(solution)/d(shared coefficient) through unrolled GN, float64 FD."""
    from helpers import random_chain

    import eqsmooth as eqs

    graph, init, truth = random_chain(5)
    solver = eqs.FixedStepGaussNewton(eqs.BlockTridiagonal(), num_steps=4)

    def loss(p):
        g = eqx.tree_at(lambda g: g.factors[0].params, graph, p)
        x = eqs.least_squares(
            g, {"x": truth}, solver, adjoint=eqs.UnrolledAdjoint()
        ).value["x"]
        return jnp.sum((x - truth) ** 2)

    p = jnp.asarray(0.7)
    grad = jax.grad(loss)(p)
    eps = 1e-6
    fd = (loss(p + eps) - loss(p - eps)) / (2 * eps)
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


_TRACES = []


def _counting_meas(x, data, params):
    _TRACES.append(1)  # runs only while tracing
    return x - data


def test_changing_data_does_not_recompile():
    import eqsmooth as eqs

    solver = eqs.GaussNewton(eqs.BlockTridiagonal())
    t = np.arange(5)

    def graph(seed):
        data = jnp.asarray(np.random.default_rng(seed).normal(size=(5, 2)))
        return eqs.FactorGraph(
            [
                eqs.FunctionFactor(
                    _counting_meas,
                    (eqs.Var("x", t),),
                    eqs.IsotropicNoise(sqrt_precision=1.0),
                    data=data,
                )
            ]
        )

    init = {"x": jnp.zeros((5, 2))}
    eqs.least_squares(graph(0), init, solver)
    n = len(_TRACES)
    eqs.least_squares(graph(1), init, solver)
    assert len(_TRACES) == n


def test_array_arguments_dispatch_through_jax_jit_with_the_same_result():
    import eqsmooth as eqs
    from eqsmooth.solve._nonlinear import _least_squares as L

    t = np.arange(4)
    data = np.random.default_rng(3).normal(size=(4, 2))
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _meas_only,
                (eqs.Var("x", t),),
                eqs.IsotropicNoise(sqrt_precision=2.0),
                data=jnp.asarray(data),
            )
        ]
    )
    solver = eqs.GaussNewton(eqs.DenseCholesky())
    fast_before = L._least_squares_of_arrays._cache_size()
    # Every leaf a JAX array: the C++ `jax.jit` dispatch.
    a = eqs.least_squares(graph, {"x": jnp.zeros((4, 2))}, solver)
    assert L._least_squares_of_arrays._cache_size() == fast_before + 1
    # A numpy leaf: `jax.jit` too (it transfers numpy arguments in C++), under
    # its own dispatch signature.
    b = eqs.least_squares(graph, {"x": np.zeros((4, 2))}, solver)
    assert L._least_squares_of_arrays._cache_size() == fast_before + 2
    # Per-call options: `eqx.filter_jit`, which keeps non-array leaves static.
    c = eqs.least_squares(graph, {"x": jnp.zeros((4, 2))}, solver, options={"x": 1})
    assert L._least_squares_of_arrays._cache_size() == fast_before + 2
    np.testing.assert_allclose(a.value["x"], b.value["x"], rtol=1e-12)
    np.testing.assert_allclose(a.value["x"], c.value["x"], rtol=1e-12)
    np.testing.assert_allclose(a.value["x"], data, rtol=1e-12)


def _meas_only(x, data, params):
    return x - data
