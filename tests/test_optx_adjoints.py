"""eqsmooth's adjoints are optimistix adjoints: `optx.least_squares(...,
adjoint=eqs.XAdjoint())` gives the gradients of `eqs.least_squares(...,
adjoint=eqs.XAdjoint())` (those are checked against finite differences in
test_adjoint.py), on an SE(2) loop."""

import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
from helpers import se2_loop


MAX_STEPS = 8


@ft.cache
def _problem():
    graph, init, _ = se2_loop(4, N=6)
    w = jnp.asarray(np.random.default_rng(1).normal(size=(6, 2)))
    return graph, init, w


def _graph_with(graph, scale):
    return eqx.tree_at(lambda g: g.factors[0].noise.sqrt_precision, graph, scale)


@ft.cache
def _grad_fn(path: str):
    import eqsmooth as eqs

    solver = eqs.GaussNewton(eqs.DenseCholesky())

    def loss(scale, graph, init, w, adjoint):
        g = _graph_with(graph, scale)
        if path == "eqsmooth":
            x = eqs.least_squares(
                g, init, solver, max_steps=MAX_STEPS, adjoint=adjoint
            ).value
        else:
            x = optx.least_squares(
                eqs.solve.graph_residuals,
                solver,
                init,
                args=g,
                max_steps=MAX_STEPS,
                adjoint=adjoint,
            ).value
        return jnp.sum(w * x["pose"].translation())

    return eqx.filter_jit(jax.value_and_grad(loss))


# Unrolled (about 50 s) is slow: its optimistix `apply` only swaps in a
# masked scan, which the truncated case also runs (and unrolled gradients are
# checked against finite differences in test_adjoint.py). Truncated stays: its
# `apply` has its own replay loop.
@pytest.mark.parametrize(
    "name",
    [pytest.param("unrolled", marks=pytest.mark.slow), "truncated", "implicit"],
)
def test_optx_least_squares_with_our_adjoint(name):
    import eqsmooth as eqs

    adjoint = {
        "unrolled": eqs.UnrolledAdjoint(),
        "truncated": eqs.TruncatedAdjoint(1),
        "implicit": eqs.ImplicitAdjoint(),
    }[name]
    assert isinstance(adjoint, optx.AbstractAdjoint)
    graph, init, w = _problem()
    scale = graph.factors[0].noise.sqrt_precision
    v_ref, g_ref = _grad_fn("eqsmooth")(scale, graph, init, w, adjoint)
    v, g = _grad_fn("optimistix")(scale, graph, init, w, adjoint)
    np.testing.assert_allclose(float(v), float(v_ref), rtol=1e-12)
    assert float(jnp.max(jnp.abs(g_ref))) > 1e-3  # a gradient that can be wrong
    np.testing.assert_allclose(np.asarray(g), np.asarray(g_ref), rtol=1e-7, atol=1e-10)


def test_implicit_adjoint_needs_a_graph():
    import eqsmooth as eqs

    with pytest.raises(TypeError, match="optimistix.ImplicitAdjoint"):
        optx.least_squares(
            lambda y, a: y - a,
            optx.LevenbergMarquardt(1e-8, 1e-8),
            jnp.zeros(2),
            args=jnp.ones(2),
            adjoint=eqs.ImplicitAdjoint(),
        )
