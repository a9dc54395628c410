"""`merge_stacks`: factors built one at a time, joined into one stack per kind
with the same cost, solution and derivatives; the warning for unstacked
graphs."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import eqsmooth as eqs
from eqsmooth.factors import merge_stacks


def se2(xyt) -> eqs.SE2:
    xyt = np.asarray(xyt, float).reshape(-1, 3)
    return eqs.SE2.from_xy_theta(*(jnp.asarray(c) for c in xyt.T))


def _one_at_a_time(T, noise, loop_noise=None, seed=0):
    """A Pose2 loop as a GTSAM port builds it: one factor object per edge."""
    rng = np.random.default_rng(seed)
    x = lambda i: eqs.Var("x", [i])
    fs = [eqs.PriorFactor(x(0), se2([0, 0, 0]), noise)]
    for i in range(T - 1):
        m = se2(np.array([1.0, 0.0, 0.3]) + 0.05 * rng.normal(size=3))
        fs.append(eqs.BetweenFactor(x(i), x(i + 1), m, noise))
    fs.append(
        eqs.BetweenFactor(x(0), x(T - 1), se2([0.5, 1.0, 0.2]), loop_noise or noise)
    )
    return fs


def _values(T):
    return {"x": se2(np.c_[np.arange(T), 0.1 * np.arange(T), np.zeros(T)])}


NOISE = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 0.05]))


def test_merged_graph_same_cost_and_solution():
    T = 4
    fs = _one_at_a_time(T, NOISE)
    merged = merge_stacks(fs)
    assert [type(f).__name__ for f in merged] == ["PriorFactor", "BetweenFactor"]
    assert [f.num_rows for f in merged] == [1, T]
    # Rows keep their order: the loop closure is the last row.
    np.testing.assert_array_equal(merged[1].variables[1].ids, [*range(1, T), T - 1])
    values = _values(T)
    g, gm = eqs.FactorGraph(fs), eqs.FactorGraph(merged)
    np.testing.assert_allclose(gm.cost(values), g.cost(values), rtol=1e-14)
    a = eqs.least_squares(g, values, eqs.LevenbergMarquardt()).value["x"]
    b = eqs.least_squares(gm, values, eqs.LevenbergMarquardt()).value["x"]
    np.testing.assert_allclose(b.log(), a.log(), atol=1e-10)


def test_noise_decides_what_merges():
    T = 5
    other = eqs.DiagonalNoise.from_sigmas(jnp.array([0.2, 0.2, 0.1]))
    # Shared parameters that differ: the loop closure keeps a stack of its own.
    merged = merge_stacks(_one_at_a_time(T, NOISE, loop_noise=other))
    assert [f.num_rows for f in merged] == [1, T - 1, 1]
    # Equal values in different objects merge.
    same = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 0.05]))
    assert len(merge_stacks(_one_at_a_time(T, NOISE, loop_noise=same))) == 2
    # Per-row parameters and masks are concatenated, shared ones kept.
    x = lambda i: eqs.Var("x", [i])
    rows = [
        eqs.BetweenFactor(
            x(i),
            x(i + 1),
            se2([1.0, 0.0, 0.1 * i]),
            eqs.MaskedNoise(
                eqs.DiagonalNoise.from_sigmas(jnp.array([[0.1, 0.2, 0.05 + 0.01 * i]])),
                jnp.array([i != 2]),
            ),
        )
        for i in range(T - 1)
    ]
    (merged,) = merge_stacks(rows)
    assert merged.noise.base.sqrt_precision.shape == (T - 1, 3)
    np.testing.assert_array_equal(merged.noise.active, [True, True, False, True])
    values = _values(T)
    np.testing.assert_allclose(
        eqs.FactorGraph([merged]).cost(values),
        eqs.FactorGraph(rows).cost(values),
        rtol=1e-14,
    )


def test_what_never_merges():
    x = lambda i: eqs.Var("x", [i])
    fn_a = lambda s, data, params: s - data
    fn_b = lambda s, data, params: 2.0 * (s - data)
    iso = eqs.IsotropicNoise.from_sigma(1.0)
    fa = [
        eqs.FunctionFactor(fn_a, (x(i),), iso, data=jnp.ones((1, 2))) for i in range(3)
    ]
    fb = eqs.FunctionFactor(fn_b, (x(3),), iso, data=jnp.ones((1, 2)))
    dyn = eqs.FunctionFactor(
        fn_a, (eqs.Var.dynamic("x", np.array([4])),), iso, data=jnp.ones((1, 2))
    )
    wide = eqs.FunctionFactor(fn_a, (x(5),), iso, data=jnp.ones((1, 3)))
    merged = merge_stacks([*fa, fb, dyn, dyn, wide])
    assert [f.num_rows for f in merged] == [3, 1, 1, 1, 1]
    assert merged[2] is dyn and merged[3] is dyn and merged[4] is wide


def test_bad_input_named():
    # Our message, or the jaxtyping hook's (which runs first under pytest).
    message = r"merge_stacks(: factors\[1\] is of type str)?"
    with pytest.raises(TypeError, match=message):
        merge_stacks([_one_at_a_time(3, NOISE)[0], "BetweenFactorPose2"])


def test_factor_graph_warns_for_unstacked_graphs():
    fs = _one_at_a_time(80, NOISE)
    with pytest.warns(UserWarning, match=r"81 factor stacks of 2 kinds.*merge_stacks"):
        eqs.FactorGraph(fs)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        eqs.FactorGraph(merge_stacks(fs))
        eqs.FactorGraph(fs[:60])


def test_gradient_through_merged_graph_matches_central_differences():
    """A learnable noise scale and the measurements, traced: the merged graph's
    leaves are concatenations of theirs, so derivatives reach every factor."""
    T = 5
    base = _one_at_a_time(T, NOISE)
    meas = jnp.stack([f.measurement.log()[0] for f in base[1:]])

    def loss(log_sigma, meas):
        noise = eqs.DiagonalNoise.from_sigmas(jnp.exp(log_sigma))
        fs = [eqs.PriorFactor(base[0].variables[0], base[0].value, noise)]
        for f, m in zip(base[1:], meas):
            fs.append(eqs.BetweenFactor(*f.variables, eqs.SE2.exp(m[None]), noise))
        merged = merge_stacks(fs)
        assert len(merged) == 2  # one noise object: its tracers merge
        sol = eqs.least_squares(eqs.FactorGraph(merged), _values(T), eqs.GaussNewton())
        return jnp.sum(sol.value["x"].log()[:, :2] ** 2) + sol.stats["final_cost"]

    log_sigma = jnp.log(jnp.array([0.1, 0.1, 0.05]))
    g_sigma, g_meas = jax.jit(jax.grad(loss, argnums=(0, 1)))(log_sigma, meas)
    loss = jax.jit(loss)
    eps = 1e-6
    for i in range(3):
        e = jnp.zeros(3).at[i].set(eps)
        fd = (loss(log_sigma + e, meas) - loss(log_sigma - e, meas)) / (2 * eps)
        np.testing.assert_allclose(g_sigma[i], fd, rtol=1e-5, atol=1e-7)
    for k, j in ((0, 0), (2, 2), (T - 1, 1)):
        e = jnp.zeros_like(meas).at[k, j].set(eps)
        fd = (loss(log_sigma, meas + e) - loss(log_sigma, meas - e)) / (2 * eps)
        np.testing.assert_allclose(g_meas[k, j], fd, rtol=1e-5, atol=1e-7)
