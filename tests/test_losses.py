"""Losses of eqsmooth.learn: values by hand, gradients by finite differences."""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_chain, se2_loop

import eqsmooth as eqs
from eqsmooth.learn import joint_nll, manifold_errors, manifold_mse, surrogate_loss


def _central_fd(f, theta, direction, eps=1e-6):
    plus = jax.tree_util.tree_map(lambda t, d: t + eps * d, theta, direction)
    minus = jax.tree_util.tree_map(lambda t, d: t - eps * d, theta, direction)
    return (f(plus) - f(minus)) / (2 * eps)


def _dot(a, b):
    return sum(
        jnp.sum(x * y)
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    )


# ----------------------------------------------------------------- a Euclidean chain

_GRAPH, _INIT, _TRUTH = random_chain(0, T=6)
_MLP = eqx.nn.MLP(1, 1, 4, 1, activation=jnp.tanh, key=jax.random.key(0))
_SENSOR = eqx.nn.MLP(2, 2, 4, 1, activation=jnp.tanh, key=jax.random.key(1))


def _meas_with_net(x, data, params):
    # A learned correction of the measurement (a tiny "virtual sensor"),
    # held in the factor's shared params.
    return x - data - 0.1 * params(data)


def _chain_graph(theta):
    """The helper chain with learnable noise, coefficient and an MLP noise model."""
    dyn, meas = _GRAPH.factors
    # Heteroscedastic measurement noise: log sqrt-precision from a tiny MLP of
    # the measurement, times a learnable per-component scale.
    feats = meas.data[:, :1]
    log_sp = jax.vmap(theta["mlp"])(feats)  # (T, 1)
    sp = jnp.exp(theta["log_sp"][None, :] + log_sp)  # (T, 2) explicit broadcast
    return eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                dyn.fn,
                dyn.variables,
                eqs.IsotropicNoise(sqrt_precision=jnp.exp(theta["log_sp_dyn"])),
                params=theta["coeff"],
            ),
            eqs.FunctionFactor(
                _meas_with_net,
                meas.variables,
                eqs.DiagonalNoise(sqrt_precision=sp),
                data=meas.data,
                params=theta["sensor"],
            ),
        ]
    )


_THETA = {
    "log_sp": jnp.log(jnp.array([5.0, 4.0])),
    "log_sp_dyn": jnp.log(jnp.asarray(3.0)),
    "coeff": jnp.asarray(0.5),
    "mlp": _MLP,
    "sensor": _SENSOR,
}
_SOLVER = eqs.FixedStepGaussNewton(eqs.BlockTridiagonal(), num_steps=3)


def _chain_surrogate(theta):
    return surrogate_loss(_chain_graph(theta), {"x": _TRUTH}, solver=_SOLVER)


def _chain_nll(theta):
    return joint_nll(_chain_graph(theta), {"x": _TRUTH})


_surrogate_vg = eqx.filter_jit(eqx.filter_value_and_grad(_chain_surrogate))
_nll_vg = eqx.filter_jit(eqx.filter_value_and_grad(_chain_nll))


@pytest.mark.parametrize("which", ["log_sp", "coeff", "sensor", "all"])
def test_surrogate_gradient_matches_finite_differences(which):
    value, grad = _surrogate_vg(_THETA)
    assert np.isfinite(float(value)) and float(value) > 0
    params = eqx.filter(_THETA, eqx.is_inexact_array)
    rng = np.random.default_rng(1)

    def direction_for(path, leaf):
        if leaf is None:
            return None
        name = jax.tree_util.keystr(path[:1])
        on = which == "all" or name == f"['{which}']"
        d = rng.normal(size=leaf.shape) if on else np.zeros(leaf.shape)
        return jnp.asarray(d, dtype=leaf.dtype)

    direction = jax.tree_util.tree_map_with_path(direction_for, params)
    analytic = _dot(eqx.filter(grad, eqx.is_inexact_array), direction)

    def f(p):
        return _surrogate_vg(eqx.combine(p, _THETA))[0]

    numeric = _central_fd(f, params, direction)
    assert abs(float(analytic)) > 1e-6  # the check can fail
    np.testing.assert_allclose(float(analytic), float(numeric), rtol=1e-5, atol=1e-9)


def test_joint_nll_gradient_reaches_mlp():
    _, grad = _nll_vg(_THETA)
    mlp_grads = jax.tree_util.tree_leaves(eqx.filter(grad["mlp"], eqx.is_array))
    assert any(float(jnp.max(jnp.abs(g))) > 1e-6 for g in mlp_grads)
    params = eqx.filter(_THETA, eqx.is_inexact_array)
    rng = np.random.default_rng(2)
    direction = jax.tree_util.tree_map(
        lambda x: jnp.asarray(rng.normal(size=x.shape), dtype=x.dtype), params
    )
    analytic = _dot(eqx.filter(grad, eqx.is_inexact_array), direction)

    def f(p):
        return _nll_vg(eqx.combine(p, _THETA))[0]

    numeric = _central_fd(f, params, direction)
    np.testing.assert_allclose(float(analytic), float(numeric), rtol=1e-6)


def test_joint_nll_matches_hand_computed_gaussian():
    # Two factor types, unit-free numbers: the NLL of the truth is the sum of
    # -log N(r_i; 0, Σ) over every residual.
    T = 4
    rng = np.random.default_rng(3)
    truth = rng.normal(size=(T, 2))
    meas = truth + 0.3 * rng.normal(size=(T, 2))
    sig_dyn, sig_meas = 0.7, np.array([0.2, 0.5])
    t = np.arange(T)

    def dyn(a, b, data, params):
        return b - a

    def obs(x, data, params):
        return x - data

    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                dyn,
                (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                eqs.IsotropicNoise.from_sigma(jnp.asarray(sig_dyn)),
            ),
            eqs.FunctionFactor(
                obs,
                (eqs.Var("x", t),),
                eqs.DiagonalNoise.from_sigmas(jnp.asarray(sig_meas)),
                data=jnp.asarray(meas),
            ),
        ]
    )

    def gauss_nll(r, sigmas):
        return np.sum(
            0.5 * (r / sigmas) ** 2 + np.log(sigmas) + 0.5 * math.log(2 * math.pi)
        )

    expected = gauss_nll(truth[1:] - truth[:-1], np.full(2, sig_dyn)) + gauss_nll(
        truth - meas, sig_meas
    )
    values = {"x": jnp.asarray(truth)}
    total = joint_nll(graph, values, reduction="sum")
    np.testing.assert_allclose(float(total), expected, rtol=1e-12)
    np.testing.assert_allclose(
        float(joint_nll(graph, values)), expected / T, rtol=1e-12
    )
    with pytest.raises(ValueError, match="reduction"):
        joint_nll(graph, values, reduction="median")


# ---------------------------------------------------------------------- SE(2) states


def test_manifold_mse_se2_and_mixed_tree():
    rng = np.random.default_rng(4)
    x = eqs.SE2.exp(jnp.asarray(rng.normal(size=(5, 3))))
    delta = jnp.asarray(0.5 * rng.normal(size=(5, 3)))
    y = x @ eqs.SE2.exp(delta)
    np.testing.assert_allclose(
        float(manifold_mse(x, y)), float(jnp.mean(delta**2)), rtol=1e-10
    )
    w = jnp.array([1.0, 2.0, 10.0])
    expected = float(jnp.sum(w[None, :] * delta**2)) / delta.size
    np.testing.assert_allclose(
        float(manifold_mse({"pose": x}, {"pose": y}, {"pose": w})), expected, rtol=1e-10
    )
    # A group holding (pose, velocity): per-leaf weights, and a scalar prefix.
    v1 = jnp.asarray(rng.normal(size=(5, 2)))
    v2 = jnp.asarray(rng.normal(size=(5, 2)))
    a, b = {"s": (x, v1)}, {"s": (y, v2)}
    errs = manifold_errors(a, b)
    np.testing.assert_allclose(np.asarray(errs["s"][0]), np.asarray(delta), atol=1e-10)
    wv = jnp.array([0.5, 3.0])
    expected = (
        float(jnp.sum(w[None, :] * delta**2))
        + float(jnp.sum(wv[None, :] * (v2 - v1) ** 2))
    ) / (15 + 10)
    np.testing.assert_allclose(
        float(manifold_mse(a, b, {"s": (w, wv)})), expected, rtol=1e-10
    )
    plain = (float(jnp.sum(delta**2)) + float(jnp.sum((v2 - v1) ** 2))) / 25
    np.testing.assert_allclose(
        float(manifold_mse(a, b, {"s": jnp.asarray(2.0)})), 2 * plain, rtol=1e-10
    )
    with pytest.raises(ValueError, match="structure"):
        manifold_mse(a, {"s": (y,)})
    with pytest.raises(ValueError, match="broadcast"):
        manifold_mse({"pose": x}, {"pose": y}, {"pose": jnp.ones(4)})


_SE2_GRAPH, _SE2_INIT, _SE2_TRUTH = se2_loop(0, N=6)
_DENSE = eqs.FixedStepGaussNewton(eqs.DenseCholesky(), num_steps=3)


def _se2_loss(log_sigmas):
    between, prior = _SE2_GRAPH.factors
    between = eqs.BetweenFactor(
        between.variables[0],
        between.variables[1],
        between.measurement,
        eqs.DiagonalNoise(sqrt_precision=jnp.exp(-log_sigmas)),
    )
    return surrogate_loss(
        eqs.FactorGraph([between, prior]),
        {"pose": _SE2_TRUTH},
        solver=_DENSE,
        weights={"pose": jnp.array([1.0, 1.0, 4.0])},
    )


@pytest.mark.slow  # ~30-60 s of compilation on 2 cores
def test_surrogate_gradient_se2():
    # Only ratios of noise scales move the MAP; the prior is fixed, so the
    # odometry sigmas are identifiable and have a nonzero gradient.
    theta = jnp.log(jnp.array([0.1, 0.2, 0.05]))
    vg = jax.jit(jax.value_and_grad(_se2_loss))
    value, grad = vg(theta)

    def f(t):
        return vg(t)[0]

    assert float(value) > 0
    for j in range(3):
        d = jnp.zeros(3).at[j].set(1.0)
        numeric = _central_fd(f, theta, d)
        np.testing.assert_allclose(
            float(grad[j]), float(numeric), rtol=1e-5, atol=1e-10
        )
    assert float(jnp.max(jnp.abs(grad))) > 1e-8


def test_surrogate_loss_rejects_non_dict_truth():
    with pytest.raises(TypeError, match="truth"):
        surrogate_loss(_GRAPH, _TRUTH)


def test_surrogate_loss_can_start_where_the_estimator_starts():
    # A nonlinear graph (an SE(2) loop), so the start matters after 3 steps.
    one_step = eqs.FixedStepGaussNewton(eqs.DenseCholesky(), num_steps=1)
    truth = {"pose": _SE2_TRUTH}
    init = _SE2_INIT  # the truth perturbed by 0.2 rad / units
    from_init = surrogate_loss(_SE2_GRAPH, truth, solver=one_step, init=init)
    sol = eqs.least_squares(_SE2_GRAPH, init, one_step)
    np.testing.assert_allclose(
        float(from_init), float(manifold_mse(truth, sol.value)), rtol=1e-12
    )
    from_truth = surrogate_loss(_SE2_GRAPH, truth, solver=one_step)
    assert abs(float(from_init) - float(from_truth)) > 1e-3 * float(from_truth)


def test_stack_trees_batches_graphs_for_vmap():
    from eqsmooth.learn import stack_trees

    pairs = [random_chain(seed, T=6)[::2] for seed in (0, 1)]  # (graph, truth)
    graphs = stack_trees([g for g, _ in pairs])
    truths = stack_trees([{"x": t} for _, t in pairs])
    batched = jax.vmap(joint_nll)(graphs, truths)
    for i, (g, t) in enumerate(pairs):
        np.testing.assert_allclose(
            float(batched[i]), float(joint_nll(g, {"x": t})), rtol=1e-12
        )
    other, _, _ = random_chain(0, T=7)
    with pytest.raises(ValueError, match="differs in structure"):
        stack_trees([pairs[0][0], other])
