"""eqsmooth.least_squares_batch: many graphs of one structure in one call
equal the graphs solved one by one; failures are named by graph."""

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest
from hostile import raises

import eqsmooth as eqs


T = 5


def _graph(meas, sigma=0.5):
    t = np.arange(T)
    return eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", t), meas, eqs.IsotropicNoise.from_sigma(sigma)
            ),
            eqs.BetweenFactor(
                eqs.Var("x", t[:-1]),
                eqs.Var("x", t[1:]),
                jnp.ones((T - 1, 2)),
                eqs.IsotropicNoise.from_sigma(1.0),
            ),
        ]
    )


def test_batch_equals_one_by_one():
    rng = np.random.default_rng(0)
    graphs = [_graph(jnp.asarray(rng.normal(size=(T, 2)))) for _ in range(4)]
    inits = [{"x": jnp.asarray(rng.normal(size=(T, 2)))} for _ in range(4)]
    solver = eqs.GaussNewton(eqs.DenseCholesky())
    sol = eqs.least_squares_batch(graphs, inits, solver)
    assert sol.value["x"].shape == (4, T, 2)
    for i, (g, v) in enumerate(zip(graphs, inits)):
        one = eqs.least_squares(g, v, solver)
        np.testing.assert_allclose(sol.value["x"][i], one.value["x"], atol=1e-10)


def test_batch_failures_are_named():
    meas = jnp.zeros((T, 2))
    graphs = [_graph(meas), _graph(meas.at[2, 0].set(jnp.nan)), _graph(meas)]
    inits = [{"x": jnp.zeros((T, 2))}] * 3
    solver = eqs.GaussNewton(eqs.DenseCholesky())
    with raises(eqx.EquinoxRuntimeError, "graphs [1] (1 of 3)", "non-finite"):
        eqs.least_squares_batch(graphs, inits, solver)
    sol = eqs.least_squares_batch(graphs, inits, solver, throw=False)
    assert [bool(r) for r in (sol.result == eqs.RESULTS.successful)] == [
        True,
        False,
        True,
    ]


def test_batch_of_different_structures_is_refused():
    with pytest.raises(ValueError, match="stack_trees"):
        eqs.least_squares_batch(
            [_graph(jnp.zeros((T, 2))), _graph(jnp.zeros((T, 2)), sigma=np.ones(T))],
            [{"x": jnp.zeros((T, 2))}] * 2,
            eqs.GaussNewton(),
        )


def test_batch_gradient_matches_finite_differences():
    """d/dσ of a loss on least_squares_batch's solutions (implicit adjoint)."""
    import jax

    rng = np.random.default_rng(1)
    meas = [jnp.asarray(rng.normal(size=(T, 2))) for _ in range(3)]
    inits = [{"x": jnp.zeros((T, 2))}] * 3
    solver = eqs.GaussNewton(eqs.DenseCholesky())

    def loss(log_sigma):
        graphs = [_graph(m, jnp.exp(log_sigma)) for m in meas]
        graphs = eqs.learn.stack_trees(graphs)
        inits_ = eqs.learn.stack_trees(inits)
        sol = eqs.least_squares_batch(graphs, inits_, solver, throw=False)
        return jnp.sum(jnp.sin(sol.value["x"]))

    g = jax.grad(loss)(jnp.asarray(-0.3))
    h = 1e-6
    fd = (loss(jnp.asarray(-0.3 + h)) - loss(jnp.asarray(-0.3 - h))) / (2 * h)
    np.testing.assert_allclose(g, fd, rtol=1e-6)


def test_stack_trees_stacks_concrete_and_traced_leaves_alike():
    """Concrete leaves are stacked on the host, traced ones by `jnp.stack`:
    same values, dtypes and shapes, and a gradient through a traced leaf."""
    import jax

    trees = [
        {"a": jnp.full((2,), float(i)), "n": jnp.asarray([i, i + 1], jnp.int32)}
        for i in range(3)
    ]
    host = eqs.learn.stack_trees(trees)
    traced = jax.jit(eqs.learn.stack_trees)(trees)
    for k in ("a", "n"):
        assert host[k].dtype == traced[k].dtype == trees[0][k].dtype
        np.testing.assert_array_equal(host[k], traced[k])
    assert host["a"].shape == (3, 2)

    def f(s):
        mixed = [{"a": trees[0]["a"] * s}, {"a": trees[1]["a"]}]
        return jnp.sum(eqs.learn.stack_trees(mixed)["a"] ** 2)

    np.testing.assert_allclose(jax.grad(f)(2.0), 0.0)  # leaf 0 is zeros
    mixed_grad = jax.grad(
        lambda s: jnp.sum(
            eqs.learn.stack_trees([{"a": trees[2]["a"] * s}, {"a": trees[1]["a"]}])["a"]
            ** 2
        )
    )(3.0)
    np.testing.assert_allclose(mixed_grad, 2 * 3.0 * 4.0 * 2)


def test_stack_trees_of_concrete_leaves_compiles_nothing():
    """Host stacking transfers the result: `jnp.asarray` of the stacked NumPy
    array compiled a small copy program per shape in every fresh process."""
    import jax
    from helpers import compiled_programs

    trees = [
        {"a": jnp.full((2, 3), float(i)), "n": jnp.asarray([i], jnp.int32)}
        for i in range(4)
    ]
    jax.clear_caches()
    with compiled_programs() as names:
        stacked = eqs.learn.stack_trees(trees)
    assert names == [], names
    assert stacked["a"].shape == (4, 2, 3) and stacked["n"].dtype == jnp.int32
    np.testing.assert_array_equal(stacked["n"][:, 0], np.arange(4))
