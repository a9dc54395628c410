"""LevenbergMarquardt's damping-update rules: Nielsen's and a fixed factor.

The case for the fixed factor is a large pose graph (`w20000.txt`, where
Nielsen's λ settles near 0.2 and the cost creeps down); no small problem we
tried shows it, so only `python -m benchmarks.pgo --gtsam-files` does (see
docs/performance.md). These tests check the rules themselves.
"""

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest


def _pose_graph():
    from eqsmooth.io import synthetic_pose_graph_2d

    pg, _ = synthetic_pose_graph_2d(40, seed=1, sigma_xy=0.1, sigma_theta=0.1)
    return pg


@pytest.mark.parametrize(
    "field, value",
    [
        ("damping_update", "gtsam"),
        ("damping_update", ""),
        ("damping_factor", 1.0),
        ("damping_factor", 0.5),
        ("damping_factor", math.inf),
        ("damping_factor", math.nan),
    ],
)
@pytest.mark.parametrize("owner", ["LevenbergMarquardt", "DampedDescent"])
def test_bad_rule_raises_naming_field(owner, field, value):
    import eqsmooth as eqs

    cls = getattr(eqs.solve, owner)
    with pytest.raises(ValueError, match=rf"{owner}\.{field} must be"):
        cls(**{field: value})


def test_rule_reaches_the_descent():
    import eqsmooth as eqs

    lm = eqs.LevenbergMarquardt(damping_update="fixed", damping_factor=4.0)
    assert lm.descent.damping_update == "fixed"
    assert lm.descent.damping_factor == 4.0


def _linear_graph():
    import eqsmooth as eqs

    def fn(x, data, params):
        return x - data

    data = jnp.arange(6.0).reshape(3, 2)
    fac = eqs.FunctionFactor(
        fn,
        (eqs.Var("x", np.arange(3)),),
        eqs.IsotropicNoise(sqrt_precision=1.0),
        data=data,
    )
    return eqs.FactorGraph([fac]), {"x": jnp.zeros((3, 2))}


@pytest.mark.parametrize("rule, factor", [("nielsen", 3.0), ("fixed", 7.0)])
def test_accepted_steps_divide_damping(rule, factor):
    # A linear problem: every step has gain ratio 1 and is accepted, so
    # Nielsen's rule divides λ by 3 per step and the fixed rule by its factor.
    import eqsmooth as eqs

    graph, init = _linear_graph()
    lm = eqs.LevenbergMarquardt(
        eqs.DenseCholesky(),
        initial_damping=1e-2,
        damping_update=rule,
        damping_factor=7.0,
    )
    sol = eqs.least_squares(graph, init, lm, max_steps=20)
    n = int(sol.stats["num_accepted"])
    assert n >= 1
    np.testing.assert_allclose(float(sol.state.damping), 1e-2 / factor**n, rtol=1e-9)


def test_both_rules_reach_the_same_minimum():
    import eqsmooth as eqs

    pg = _pose_graph()
    sols = [
        eqs.least_squares(
            pg.graph,
            pg.values,
            eqs.LevenbergMarquardt(eqs.DenseCholesky(), ftol=1e-12, damping_update=r),
            max_steps=100,
        )
        for r in ("nielsen", "fixed")
    ]
    costs = [float(s.stats["final_cost"]) for s in sols]
    assert costs[1] < 0.05 * float(sols[1].stats["initial_cost"])
    np.testing.assert_allclose(costs[0], costs[1], rtol=1e-9)
    name = next(iter(sols[0].value))
    d = eqs.local(sols[0].value[name], sols[1].value[name], batch_ndim=1)
    assert float(jnp.max(jnp.abs(d))) < 1e-6


@pytest.mark.slow  # two implicit-adjoint compilations: 84 s on a loaded 2-core machine
def test_gradient_does_not_depend_on_the_rule():
    # The implicit adjoint differentiates the minimiser, not the path to it:
    # the gradient of a function of the solution with respect to log noise
    # scales is the same under both rules, and matches central differences.
    import equinox as eqx
    from helpers import se2_loop

    import eqsmooth as eqs

    graph, init, _ = se2_loop(4, N=5, noise_scale=0.3)

    def f(logs, rule):
        noise = eqs.DiagonalNoise.from_sigmas(jnp.exp(logs))
        g = eqx.tree_at(lambda g: g.factors[0].noise, graph, noise)
        lm = eqs.LevenbergMarquardt(
            eqs.DenseCholesky(), ftol=0.0, gtol=1e-13, xtol=1e-14, damping_update=rule
        )
        sol = eqs.least_squares(g, init, lm, max_steps=100)
        x = sol.value["pose"]
        return jnp.sum(jnp.sin(3.0 * x.log())) + sol.stats["final_cost"]

    logs = jnp.log(jnp.array([0.1, 0.1, 0.05]))
    grad, value = eqx.filter_jit(jax.grad(f)), eqx.filter_jit(f)
    grads = {r: np.asarray(grad(logs, r)) for r in ("nielsen", "fixed")}
    np.testing.assert_allclose(grads["fixed"], grads["nielsen"], rtol=1e-7)
    h = 1e-5
    fd = [
        (value(logs + h * e, "fixed") - value(logs - h * e, "fixed")) / (2 * h)
        for e in jnp.eye(3)
    ]
    np.testing.assert_allclose(grads["fixed"], np.asarray(fd), rtol=1e-5, atol=1e-8)
