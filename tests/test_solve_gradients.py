"""The gradient contract of the solve routes (docs/differentiating.md).

Every route from a solve to something a user may differentiate is compared
with float64 central differences, with respect to log noise scales: solve
values, the cost statistics, per-variable and joint marginal covariances and
the log-determinant taken from a `Solution` (what its state keeps) under each
adjoint, through `eqs.least_squares` and through `optx.least_squares`; and
the routes that cannot give a right derivative raise (optimistix's default
adjoint on Lie-group values, the implicit adjoint of a fixed-step solve, the
cost history under the implicit adjoint, a residual function the solvers
would ignore). Problems: a 5-pose SE(2) loop (dense Cholesky by default) and
a 6-step Euclidean chain (block-tridiagonal by default).
"""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import random_chain, se2_loop


RTOL = 1e-5


@ft.cache
def _loop():
    graph, init, _ = se2_loop(4, N=5)
    return graph, init


@ft.cache
def _chain():
    graph, init, _ = random_chain(2, T=6)
    return graph, init


def _with_log_sigmas(problem: str, graph, logs):
    import eqsmooth as eqs

    noise = eqs.DiagonalNoise.from_sigmas(jnp.exp(logs))
    index = 0 if problem == "loop" else 1
    return eqx.tree_at(lambda g: g.factors[index].noise, graph, noise)


def _logs0(problem: str):
    return jnp.log(jnp.array([0.1, 0.1, 0.05] if problem == "loop" else [0.2, 0.25]))


def _optx_solve(problem: str, logs, **kw):
    """`optx.least_squares` of `problem` with noise scales `exp(logs)`: 12
    tight Gauss-Newton steps, `kw` to `optx.least_squares`."""
    import eqsmooth as eqs

    graph, init = _loop() if problem == "loop" else _chain()
    return optx.least_squares(
        eqs.solve.graph_residuals,
        eqs.GaussNewton(gtol=1e-13, ftol=0.0, xtol=1e-14),
        init,
        args=_with_log_sigmas(problem, graph, logs),
        max_steps=12,
        **kw,
    )


def _outputs(sol):
    """Scalars a user may differentiate, from one solve."""
    import eqsmooth as eqs

    marg = eqs.marginal_covariances(sol)
    name = next(iter(sol.value))
    joint = eqs.joint_marginal_covariance(sol, [(name, 1), (name, 3)])
    leaves = jax.tree_util.tree_leaves(sol.value)
    return jnp.stack(
        [
            sum(jnp.sum(jnp.linalg.slogdet(c)[1]) for c in marg.values()),
            jnp.linalg.slogdet(joint)[1],
            eqs.solve.normal_log_det(sol.state.lin),
            sol.stats["final_cost"],
            sol.stats["initial_cost"],
            sum(jnp.sum(jnp.sin(3.0 * x)) for x in leaves),
        ]
    )


_NAMES = ("marginals", "joint", "log_det", "final_cost", "initial_cost", "values")


def _adjoint(name):
    import eqsmooth as eqs

    return {
        "implicit": eqs.ImplicitAdjoint(),
        "implicit_gn": eqs.ImplicitAdjoint(hessian="gauss_newton"),
        "unrolled": eqs.UnrolledAdjoint(),
        "truncated": eqs.TruncatedAdjoint(2),
    }[name]


def _assert_matches_fd(f, x, h=1e-5, atol=1e-8):
    """Jacobian of the vector `f` at `x` against central differences."""
    f = eqx.filter_jit(f)
    jac = np.asarray(eqx.filter_jit(jax.jacrev(f))(x))
    fd = np.stack(
        [
            (np.asarray(f(x + h * e)) - np.asarray(f(x - h * e))) / (2 * h)
            for e in np.eye(x.size)
        ],
        axis=-1,
    )
    assert np.all(np.isfinite(jac))
    for i, name in enumerate(_NAMES[: jac.shape[0]]):
        scale = np.max(np.abs(fd[i]))
        assert scale > 1e-6, f"{name}: a gradient that cannot be wrong"
        np.testing.assert_allclose(
            jac[i], fd[i], rtol=RTOL, atol=atol + RTOL * scale, err_msg=name
        )


# The GN-Hessian implicit adjoint is exact only at zero residual and the
# truncated one is the derivative of its last steps: both are checked where
# they are exact in test_adjoint.py, not here.
@pytest.mark.parametrize(
    "problem,adjoint",
    [
        ("loop", "implicit"),
        ("loop", "unrolled"),
        ("chain", "implicit"),
        pytest.param("chain", "unrolled", marks=pytest.mark.slow),
    ],
)
def test_solution_routes_match_finite_differences(problem, adjoint):
    import eqsmooth as eqs

    graph, init = _loop() if problem == "loop" else _chain()
    solver = eqs.GaussNewton(gtol=1e-13, ftol=0.0, xtol=1e-14)
    adj = _adjoint(adjoint)

    def f(logs):
        g = _with_log_sigmas(problem, graph, logs)
        sol = eqs.least_squares(g, init, solver, max_steps=12, adjoint=adj)
        return _outputs(sol)

    _assert_matches_fd(f, _logs0(problem))


def test_optx_route_with_our_implicit_adjoint_stats_are_differentiable():
    # The solver's stats carry the linearisation at the solution,
    # differentiable as in eqsmooth's driver; the last iteration's state
    # optimistix hands back refuses a derivative (never a silent zero).
    import eqsmooth as eqs

    def f(logs, lin_of=lambda sol: sol.stats["linearization"]):
        sol = _optx_solve("loop", logs, adjoint=eqs.ImplicitAdjoint())
        marg = eqs.marginal_covariances(lin_of(sol))["pose"]
        return jnp.stack(
            [
                jnp.sum(jnp.linalg.slogdet(marg)[1]),
                jnp.sum(jnp.sin(3.0 * sol.value["pose"].unit_complex_xy)),
                sol.stats["final_cost"],
            ]
        )

    _assert_matches_fd(f, _logs0("loop"))
    state_lin = lambda logs: f(logs, lambda sol: sol.state.lin)[0]
    with pytest.raises(ValueError, match="stats\\['linearization'\\]"):
        jax.grad(state_lin)(_logs0("loop"))


def test_optx_default_adjoint_is_right_on_euclidean_values():
    # The README's route: optimistix's own ImplicitAdjoint differentiates the
    # ambient optimality condition, which is the right one for arrays.
    def f(logs):
        sol = _optx_solve("chain", logs)
        return jnp.sum(jnp.sin(3.0 * sol.value["x"]))[None]

    _assert_matches_fd(f, _logs0("chain"))


def test_optx_default_adjoint_refuses_lie_group_values():
    import eqsmooth as eqs

    graph, init = _loop()

    def loss(logs):
        g = _with_log_sigmas("loop", graph, logs)
        sol = optx.least_squares(
            eqs.solve.graph_residuals, eqs.GaussNewton(), init, args=g, max_steps=12
        )
        return jnp.sum(sol.value["pose"].translation())

    logs = _logs0("loop")
    assert np.isfinite(float(loss(logs)))  # the forward solve is fine
    with pytest.raises(ValueError, match="ambient coordinates"):
        jax.grad(loss)(logs)
    # optimistix's own solvers (additive updates) are refused on groups too.
    with pytest.raises(ValueError, match="tangent_least_squares"):
        optx.least_squares(
            eqs.solve.graph_residuals,
            optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8),
            init,
            args=graph,
            max_steps=4,
        )


def test_solvers_refuse_another_residual_function():
    import eqsmooth as eqs

    graph, init = _chain()
    doubled = lambda y, g: tuple(2.0 * r for r in eqs.solve.graph_residuals(y, g))
    for solver in (eqs.GaussNewton(), eqs.LevenbergMarquardt()):
        _assert_refused(doubled, solver, graph, init)
    with pytest.raises(ValueError, match="shapes"):
        optx.least_squares(
            lambda y, g: y["x"], eqs.GaussNewton(), init, args=graph, max_steps=4
        )
    # The graph's own residuals, wrapped, are accepted.
    sol = optx.least_squares(
        lambda y, g: eqs.solve.graph_residuals(y, g),
        eqs.GaussNewton(),
        init,
        args=graph,
        max_steps=20,
    )
    assert sol.result == optx.RESULTS.successful


def test_solvers_refuse_a_function_that_agrees_only_at_the_initial_values():
    # The example: the graph's residuals plus 100 |x - x0|^2 agree
    # with the graph at the initial values and nowhere else; no options key
    # skips the check (the one the driver used to set is gone).
    import eqsmooth as eqs

    graph, init = _chain()
    x0 = init["x"]

    def shifted(y, g):
        (first, *rest) = eqs.solve.graph_residuals(y, g)
        bump = 100.0 * jnp.sum((y["x"] - x0) ** 2)
        return (first + bump, *rest)

    assert (
        float(
            jnp.max(
                jnp.abs(
                    shifted(init, graph)[0] - eqs.solve.graph_residuals(init, graph)[0]
                )
            )
        )
        == 0.0
    )
    for options in (None, {"fn_is_graph_residuals": True}):
        _assert_refused(shifted, eqs.LevenbergMarquardt(), graph, init, options)


def _assert_refused(fn, solver, graph, init, options=None):
    """The solve of another `fn` ends before its first step with eqsmooth's
    code (a result code, so the compiled solve holds no host callback);
    optimistix's `throw` raises on it."""
    import eqsmooth as eqs

    sol = optx.least_squares(
        fn, solver, init, args=graph, options=options, max_steps=4, throw=False
    )
    assert sol.state.result == eqs.solve.RESULTS.fn_not_graph_residuals
    assert sol.result != optx.RESULTS.successful
    assert int(sol.stats["num_steps"]) == 0
    with pytest.raises(eqx.EquinoxRuntimeError):
        optx.least_squares(fn, solver, init, args=graph, options=options, max_steps=4)


def test_the_graph_route_is_proven_at_trace_time_and_other_fns_checked_at_run_time(
    monkeypatch,
):
    # optimistix hands the solver a closure-converted copy of fn: the
    # graph's own residuals are recognised from that program (no run-time
    # comparison in the compiled solve); a wrapper that computes the same
    # thing through other operations, or closes over an array, is compared
    # at run time and accepted.
    import eqsmooth as eqs
    from eqsmooth.solve._nonlinear import _graph_solver

    seen = []
    check = _graph_solver.fn_mismatch

    def spy(*args):
        out = check(*args)
        seen.append(out is None)
        return out

    monkeypatch.setattr(_graph_solver, "fn_mismatch", spy)
    graph, init = _chain()
    one = jnp.ones(())

    def same(y, g):
        return eqs.solve.graph_residuals(y, g)

    def rescaled(y, g):
        return tuple(r * one for r in eqs.solve.graph_residuals(y, g))

    for fn in (eqs.solve.graph_residuals, same, rescaled):
        sol = optx.least_squares(
            fn, eqs.GaussNewton(), init, args=graph, max_steps=8, throw=False
        )
        assert sol.result == optx.RESULTS.successful
    assert seen == [True, True, False]
    # Also on Lie-group values, whose residuals capture the library's own
    # constants (the program is compared with them).
    for graph, init in (_chain(), _loop()):
        eqs.least_squares(graph, init, eqs.GaussNewton())
        assert seen[-1] is True


def test_fixed_step_solution_keeps_the_linearisation_at_its_values():
    import eqsmooth as eqs

    graph, init = _loop()
    sol = eqs.least_squares(
        graph,
        init,
        eqs.FixedStepGaussNewton(num_steps=1),
        adjoint=eqs.UnrolledAdjoint(),
    )
    got = eqs.marginal_covariances(sol)["pose"]
    want = eqs.marginal_covariances(eqs.linearize(graph, sol.value))["pose"]
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=1e-9, atol=1e-18)
    assert float(sol.stats["final_cost"]) == pytest.approx(
        float(graph.cost(sol.value)), rel=1e-12
    )


def test_implicit_adjoint_refuses_to_differentiate_fixed_step_solvers():
    # The default adjoint is the implicit one: a fixed-step solve runs, and
    # asking for its implicit gradient raises where it stopped short of a
    # stationary point (two steps from a perturbed start here); a fixed-step
    # solve run to convergence keeps its implicit gradient (test_adjoint.py).
    import eqsmooth as eqs

    graph, init = _loop()
    logs = _logs0("loop")
    fixed = eqs.FixedStepGaussNewton(num_steps=2)

    def eqs_route(logs):
        g = _with_log_sigmas("loop", graph, logs)
        return jnp.sum(eqs.least_squares(g, init, fixed).value["pose"].translation())

    def optx_route(logs):
        g = _with_log_sigmas("loop", graph, logs)
        x = optx.least_squares(
            eqs.solve.graph_residuals,
            fixed,
            init,
            args=g,
            max_steps=4,
            adjoint=eqs.ImplicitAdjoint(),
        ).value
        return jnp.sum(x["pose"].translation())

    for route in (eqs_route, optx_route):
        assert np.isfinite(float(route(logs)))
        with pytest.raises(eqx.EquinoxRuntimeError, match="UnrolledAdjoint"):
            eqx.filter_jit(jax.grad(route))(logs)


def test_cost_history_has_no_implicit_derivative():
    import eqsmooth as eqs

    graph, init = _chain()
    logs = _logs0("chain")

    def history(logs, i):
        g = _with_log_sigmas("chain", graph, logs)
        return eqs.least_squares(g, init, eqs.GaussNewton()).stats["cost_history"][i]

    with pytest.raises(ValueError, match="cost_history"):
        jax.grad(history)(logs, 1)
