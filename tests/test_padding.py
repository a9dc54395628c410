"""Structure as data: eqsmooth.solve.pad_graph and Var.dynamic.

A padded graph solves to the original's answer (values, cost, NLL,
marginals, gradients), and a second graph of another size or connectivity in
the same buckets reuses the compiled solve."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compiled_programs, se2_loop
from hostile import raises

import eqsmooth as eqs


SOLVER = eqs.LevenbergMarquardt()


def _pose_error(a, b) -> float:
    return float(jnp.max(jnp.abs((a.inverse() @ b).log())))


def test_padded_solve_equals_the_original_and_reuses_its_program():
    # Loops of 6 and 7 poses (one closure each): 8 variables and 8 rows
    # after padding, so the second one compiles nothing.
    first, init, _ = se2_loop(0, N=6)
    second, init2, _ = se2_loop(1, N=7)
    for graph, values in ((first, init), (second, init2)):
        ref = eqs.least_squares(graph, values, SOLVER)
        with compiled_programs() as names:
            padded = eqs.solve.pad_graph(graph, values)
            sol = eqs.least_squares(padded.graph, padded.values, SOLVER)
            out = padded.unpad(sol.value)
            jax.block_until_ready(out)
        assert out["pose"].unit_complex_xy.shape == values["pose"].unit_complex_xy.shape
        assert _pose_error(out["pose"], ref.value["pose"]) < 1e-8
        np.testing.assert_allclose(
            sol.stats["final_cost"], ref.stats["final_cost"], rtol=1e-6, atol=1e-12
        )
    assert names == [], names  # the 7-pose loop: no new program at all


def test_padded_cost_nll_and_marginals_equal_the_original():
    graph, values, _ = se2_loop(2, N=5)
    # A robust kernel and a per-row masked stack ride along.
    rows = jnp.ones(2, dtype=bool).at[1].set(False)
    extra = eqs.PriorFactor(
        eqs.Var("pose", [2, 3]),
        values["pose"][np.array([2, 3])],
        eqs.HuberNoise(
            eqs.MaskedNoise(
                eqs.IsotropicNoise(sqrt_precision=jnp.array([2.0, 3.0])), rows
            ),
            0.5,
        ),
    )
    graph = eqs.FactorGraph(graph.factors + (extra,))
    padded = eqs.solve.pad_graph(graph, values, bucket=lambda n: n + 3)
    assert padded.values["pose"].unit_complex_xy.shape == (8, 4)
    np.testing.assert_allclose(
        padded.graph.cost(padded.values), graph.cost(values), rtol=1e-12
    )
    np.testing.assert_allclose(
        padded.graph.negative_log_likelihood(padded.values),
        graph.negative_log_likelihood(values),
        rtol=1e-12,
    )
    ref = eqs.least_squares(graph, values, SOLVER)
    sol = eqs.least_squares(padded.graph, padded.values, SOLVER)
    assert _pose_error(padded.unpad(sol.value)["pose"], ref.value["pose"]) < 1e-8
    cov = padded.unpad(eqs.marginal_covariances(sol))
    np.testing.assert_allclose(
        cov["pose"], eqs.marginal_covariances(ref)["pose"], rtol=1e-6, atol=1e-12
    )


def test_padded_gradient_matches_central_differences():
    """d/dθ of a loss on the unpadded solution, θ scaling the odometry noise
    and shifting one measurement (implicit adjoint, float64)."""
    graph, values, truth = se2_loop(3, N=5)
    between = graph.factors[0]

    def loss(theta):
        # Per-row sigmas: row 2's scale is learned.
        scale = jnp.ones(5).at[2].set(jnp.exp(theta[0]))
        noise = eqs.DiagonalNoise.from_sigmas(
            scale[:, None] * jnp.array([[0.1, 0.1, 0.05]])
        )
        shift = eqs.SE2.exp(jnp.zeros((5, 3)).at[1, 0].set(theta[1]))
        f = eqx.tree_at(
            lambda b: (b.noise, b.measurement),
            between,
            (noise, between.measurement @ shift),
        )
        g = eqs.FactorGraph((f,) + graph.factors[1:])
        padded = eqs.solve.pad_graph(g, values)
        sol = eqs.least_squares(padded.graph, padded.values, eqs.GaussNewton())
        x = padded.unpad(sol.value)["pose"]
        return jnp.sum((truth.inverse() @ x).log() ** 2)

    theta = jnp.array([0.3, 0.05])
    grad = jax.grad(loss)(theta)
    eps = 1e-6
    fd = [
        (loss(theta.at[i].add(eps)) - loss(theta.at[i].add(-eps))) / (2 * eps)
        for i in range(2)
    ]
    np.testing.assert_allclose(grad, np.array(fd), rtol=1e-5, atol=1e-8)
    assert float(jnp.abs(grad).min()) > 1e-6  # neither derivative vanishes


def test_padded_graphs_of_different_connectivity_batch_in_one_call():
    problems = [se2_loop(s, N=n)[:2] for s, n in ((4, 5), (5, 7), (6, 6))]
    padded = [eqs.solve.pad_graph(g, v) for g, v in problems]
    sol = eqs.least_squares_batch(
        [p.graph for p in padded], [p.values for p in padded], SOLVER
    )
    for i, ((g, v), p) in enumerate(zip(problems, padded)):
        one = eqs.least_squares(g, v, SOLVER)
        got = p.unpad({"pose": sol.value["pose"][i]})["pose"]
        assert _pose_error(got, one.value["pose"]) < 1e-8


def test_dynamic_indices_refuse_what_needs_structure():
    graph, values, _ = se2_loop(7, N=5)
    padded = eqs.solve.pad_graph(graph, values)
    with raises(
        ValueError, "BlockTridiagonal needs static variable indices", "BetweenFactor"
    ):
        eqs.least_squares(
            padded.graph, padded.values, eqs.GaussNewton(eqs.BlockTridiagonal())
        )
    with raises(TypeError, "Var.dynamic('pose', ...)", "needs static variable"):
        eqs.least_squares(
            padded.graph, padded.values, eqs.GaussNewton(eqs.solve.SparseLU())
        )
    # Matrix-free CG with block-Jacobi takes any connectivity.
    cg = eqs.least_squares(
        padded.graph, padded.values, eqs.LevenbergMarquardt(eqs.PCG())
    )
    ref = eqs.least_squares(graph, values, SOLVER)
    assert _pose_error(padded.unpad(cg.value)["pose"], ref.value["pose"]) < 1e-6
    var = padded.graph.factors[0].variables[0]
    assert var.is_dynamic
    with raises(TypeError, "needs static variable indices", "'pose'"):
        var.ids
    with raises(ValueError, "pad_graph", "already has dynamic indices"):
        eqs.solve.pad_graph(padded.graph, padded.values)
    with raises(ValueError, "bucket(5) = 4", "a bucket must be at least"):
        eqs.solve.pad_graph(graph, values, bucket=lambda n: 4)
    with raises(ValueError, "Var.dynamic('x', ids)", "1-D integer"):
        eqs.Var.dynamic("x", jnp.zeros((2, 3), dtype=int))


def test_dynamic_indices_out_of_range_are_caught():
    x = {"x": jnp.zeros((3, 2))}
    bad = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var.dynamic("x", np.array([0, 5])),
                jnp.ones((2, 2)),
                eqs.IsotropicNoise(sqrt_precision=1.0),
            )
        ]
    )
    # Concrete: named at validation.
    with raises(ValueError, "PriorFactor", "[5] out of range for 3"):
        bad.validate(x)
    # Traced (inside jit): the row gathers NaN and the solve says so.
    solve = jax.jit(
        lambda g, v: eqs.least_squares(g, v, eqs.GaussNewton(), throw=False).result
    )
    assert solve(bad, x) != eqs.RESULTS.successful


def test_padding_refuses_noise_it_cannot_extend():
    graph, values, _ = se2_loop(8, N=5)
    f = graph.factors[0]
    student = eqx.tree_at(lambda b: b.noise, f, eqs.StudentTNoise(f.noise, 4.0))
    with raises(TypeError, "BetweenFactor (factor stack 0)", "StudentTNoise"):
        eqs.solve.pad_graph(eqs.FactorGraph((student,) + graph.factors[1:]), values)


@pytest.mark.parametrize("n", [1, 8, 9])
def test_power_of_two(n):
    assert eqs.solve.power_of_two(n) == {1: 8, 8: 8, 9: 16}[n]


def test_a_failed_padded_solve_names_its_rows():
    graph, values, _ = se2_loop(9, N=5)
    f = graph.factors[0]
    bad = eqx.tree_at(
        lambda b: b.measurement,
        f,
        eqs.SE2(f.measurement.unit_complex_xy.at[2, 2].set(jnp.nan)),
    )
    padded = eqs.solve.pad_graph(eqs.FactorGraph((bad,) + graph.factors[1:]), values)
    with raises(eqx.EquinoxRuntimeError, "BetweenFactor (factor stack 0)", "rows [2]"):
        eqs.least_squares(padded.graph, padded.values, SOLVER)


def test_other_values_padded_alike_keep_cost_nll_and_evidence():
    from eqsmooth.discover._laplace import laplace_at_map

    graph, values, truth = se2_loop(10, N=5)
    padded = eqs.solve.pad_graph(graph, values)
    at_truth = padded.pad({"pose": truth})
    np.testing.assert_allclose(
        padded.graph.cost(at_truth), graph.cost({"pose": truth}), rtol=1e-12
    )
    # joint_nll's mean counts the real variables only.
    np.testing.assert_allclose(
        eqs.learn.joint_nll(padded.graph, at_truth),
        eqs.learn.joint_nll(graph, {"pose": truth}),
        rtol=1e-12,
    )
    # The Laplace evidence leaves the padding coordinates out of its 2π term.
    ref = eqs.least_squares(graph, values, SOLVER)
    sol = eqs.least_squares(padded.graph, padded.values, SOLVER)
    np.testing.assert_allclose(
        laplace_at_map(padded.graph, sol.value),
        laplace_at_map(graph, ref.value),
        rtol=1e-9,
    )
    with raises(ValueError, "PaddedGraph.pad", "'pose' has 4 variables", "5"):
        padded.pad({"pose": truth[np.arange(4)]})


def test_dynamic_var_edge_cases():
    # Filtered out of a pytree, a dynamic Var still prints.
    var = eqs.Var.dynamic("x", np.array([0, 1]))
    assert "<no index>" in repr(eqx.filter([var], eqx.is_inexact_array))
    # A traced negative index does not wrap around to the last variable.
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var.dynamic("x", np.array([0, 1])),
                jnp.ones((2, 2)),
                eqs.IsotropicNoise(sqrt_precision=1.0),
            )
        ]
    )

    @jax.jit
    def result(graph, ids):
        f = eqx.tree_at(
            lambda g: g.factors[0].variables, graph, (eqs.Var.dynamic("x", ids),)
        )
        sol = eqs.least_squares(
            f, {"x": jnp.zeros((2, 2))}, eqs.GaussNewton(), throw=False
        )
        return sol.result

    assert result(graph, jnp.array([0, 1])) == eqs.RESULTS.successful
    assert result(graph, jnp.array([0, -1])) != eqs.RESULTS.successful
    with raises(ValueError, "pad_graph", "group 'y' has no variables"):
        eqs.solve.pad_graph(graph, {"x": jnp.ones((2, 2)), "y": jnp.zeros((0, 2))})
