"""MaskedNoise: the supported row mask (issue 36). A masked row is the same as a
row left out, for the solution, the cost and the negative log-likelihood, also
under `vmap` with one mask per batch element (one compiled program)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises

import eqsmooth as eqs


T = 6
SOLVER = eqs.GaussNewton(eqs.DenseCholesky())


def _graph(meas, active, *, robust=False):
    rows = np.arange(T)
    noise = eqs.MaskedNoise(eqs.IsotropicNoise.from_sigma(0.5), active)
    if robust:
        noise = eqs.HuberNoise(noise, scale=1.0)
    return eqs.FactorGraph(
        [
            eqs.PriorFactor(eqs.Var("x", rows), meas, noise),
            eqs.BetweenFactor(
                eqs.Var("x", rows[:-1]),
                eqs.Var("x", rows[1:]),
                jnp.full((T - 1, 1), 0.5),
                eqs.IsotropicNoise.from_sigma(1.0),
            ),
        ]
    )


def _dropped(meas, active, *, robust=False):
    """The same graph with the inactive rows left out."""
    rows = np.arange(T)[np.asarray(active)]
    noise = eqs.IsotropicNoise.from_sigma(0.5)
    if robust:
        noise = eqs.HuberNoise(noise, scale=1.0)
    return eqs.FactorGraph(
        [
            eqs.PriorFactor(eqs.Var("x", rows), meas[np.asarray(active)], noise),
            eqs.BetweenFactor(
                eqs.Var("x", np.arange(T - 1)),
                eqs.Var("x", np.arange(1, T)),
                jnp.full((T - 1, 1), 0.5),
                eqs.IsotropicNoise.from_sigma(1.0),
            ),
        ]
    )


@pytest.mark.parametrize("robust", [False, True])
def test_masked_rows_equal_dropped_rows(robust):
    meas = jnp.asarray(np.random.default_rng(0).normal(size=(T, 1)) * 3.0)
    active = np.array([True, False, True, True, False, True])
    init = {"x": jnp.zeros((T, 1))}
    masked = _graph(meas, jnp.asarray(active), robust=robust)
    dropped = _dropped(meas, active, robust=robust)
    a = eqs.least_squares(masked, init, SOLVER)
    b = eqs.least_squares(dropped, init, SOLVER)
    np.testing.assert_allclose(a.value["x"], b.value["x"], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(masked.cost(a.value), dropped.cost(a.value), rtol=1e-12)
    np.testing.assert_allclose(
        masked.negative_log_likelihood(a.value),
        dropped.negative_log_likelihood(a.value),
        rtol=1e-12,
    )


def test_mask_per_batch_element_under_vmap():
    rng = np.random.default_rng(1)
    meas = jnp.asarray(rng.normal(size=(3, T, 1)))
    active = np.ones((3, T), bool)
    active[0, 2] = active[1, :3] = False
    init = {"x": jnp.zeros((T, 1))}

    @jax.jit
    @jax.vmap
    def solve(meas, active):
        sol = eqs.least_squares(_graph(meas, active), init, SOLVER, throw=False)
        return sol.value["x"], sol.result

    xs, results = solve(meas, jnp.asarray(active))
    assert np.all(results == eqs.RESULTS.successful)
    for b in range(3):
        want = eqs.least_squares(_dropped(meas[b], active[b]), init, SOLVER)
        np.testing.assert_allclose(xs[b], want.value["x"], rtol=1e-9, atol=1e-12)


def test_mask_gradient_matches_dropped_rows():
    meas = jnp.asarray(np.random.default_rng(2).normal(size=(T, 1)))
    active = np.array([True, True, False, True, True, False])
    x = {"x": jnp.asarray(np.random.default_rng(3).normal(size=(T, 1)))}

    def nll(log_sigma, graph_fn):
        g = graph_fn(jnp.exp(log_sigma))
        return g.negative_log_likelihood(x)

    def masked(sigma):
        return eqs.FactorGraph(
            [
                eqs.PriorFactor(
                    eqs.Var("x", np.arange(T)),
                    meas,
                    eqs.MaskedNoise(eqs.IsotropicNoise.from_sigma(sigma), active),
                )
            ]
        )

    def dropped(sigma):
        rows = np.arange(T)[active]
        return eqs.FactorGraph(
            [
                eqs.PriorFactor(
                    eqs.Var("x", rows),
                    meas[active],
                    eqs.IsotropicNoise.from_sigma(sigma),
                )
            ]
        )

    g1 = jax.grad(nll)(jnp.asarray(0.3), masked)
    g2 = jax.grad(nll)(jnp.asarray(0.3), dropped)
    np.testing.assert_allclose(g1, g2, rtol=1e-12)
    # and against central differences
    h = 1e-6
    fd = (nll(0.3 + h, masked) - nll(0.3 - h, masked)) / (2 * h)
    np.testing.assert_allclose(g1, fd, rtol=1e-6)


def test_mask_errors():
    base = eqs.IsotropicNoise.from_sigma(1.0)
    with raises(TypeError, "MaskedNoise.active must be booleans", ".astype(bool)"):
        eqs.MaskedNoise(base, np.array([1, 0, 1]))
    with raises(ValueError, "MaskedNoise.active must have shape (n,)"):
        eqs.MaskedNoise(base, np.ones((2, 3), bool))
    with raises(TypeError, "MaskedNoise.base must be a Gaussian", "HuberNoise"):
        eqs.MaskedNoise(eqs.HuberNoise(base, scale=1.0), np.ones(3, bool))
    with raises(TypeError, "StudentTNoise.base cannot be a MaskedNoise"):
        eqs.StudentTNoise(eqs.MaskedNoise(base, np.ones(3, bool)), 4.0)
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", np.arange(T)),
                jnp.zeros((T, 1)),
                eqs.MaskedNoise(base, np.ones(T - 1, bool)),
            )
        ]
    )
    with raises(ValueError, "PriorFactor", "MaskedNoise.active has shape (5,)", "(6,)"):
        graph.cost({"x": jnp.zeros((T, 1))})


def _scaled(x, data, params):
    return x - params * data


@pytest.mark.parametrize("robust", [False, True])
def test_nan_in_a_masked_row_reaches_no_value_and_no_derivative(robust):
    """A masked row's data is never read: NaN there (a missing measurement)
    gives the same solution, negative log-likelihood and gradients (with
    respect to the noise, a shared parameter and the data) as 0.0 there, all
    finite, and the masked datum's own derivative is exactly zero. (Before,
    the gradients of the noise and of a parameter multiplying the data were
    NaN: 0 · NaN.)"""
    rows = np.arange(T)
    active = jnp.asarray([True, True, False, True, True, True])

    def graph(meas, log_sigma, scale):
        noise = eqs.MaskedNoise(
            eqs.IsotropicNoise.from_sigma(jnp.exp(log_sigma)), active
        )
        if robust:
            noise = eqs.HuberNoise(noise, scale=1.0)
        return eqs.FactorGraph(
            [
                eqs.FunctionFactor(
                    _scaled, (eqs.Var("x", rows),), noise, data=meas, params=scale
                ),
                eqs.BetweenFactor(
                    eqs.Var("x", rows[:-1]),
                    eqs.Var("x", rows[1:]),
                    jnp.full((T - 1, 1), 0.5),
                    eqs.IsotropicNoise.from_sigma(1.0),
                ),
            ]
        )

    def losses(meas, log_sigma, scale):
        g = graph(meas, log_sigma, scale)
        x = eqs.least_squares(g, {"x": jnp.zeros((T, 1))}, SOLVER).value["x"]
        nll = eqs.joint_nll(g, {"x": jnp.linspace(0.0, 2.0, T)[:, None]})
        return jnp.sum(x**2), nll

    both = jax.jit(
        lambda *a: (
            losses(*a),
            jax.grad(lambda *b: losses(*b)[0], argnums=(0, 1, 2))(*a),
            jax.grad(lambda *b: losses(*b)[1], argnums=(0, 1, 2))(*a),
        )
    )
    meas = jnp.linspace(1.0, 3.0, T)[:, None]
    args = (jnp.asarray(-0.5), jnp.asarray(1.3))
    clean = both(meas.at[2, 0].set(0.0), *args)
    dirty = both(meas.at[2, 0].set(jnp.nan), *args)
    for a, b in zip(jax.tree_util.tree_leaves(clean), jax.tree_util.tree_leaves(dirty)):
        assert np.all(np.isfinite(np.asarray(b)))
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-14)
    _, grad_solution, grad_nll = dirty
    assert float(grad_solution[0][2, 0]) == 0.0 and float(grad_nll[0][2, 0]) == 0.0
