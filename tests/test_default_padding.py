"""`least_squares` pads small dense graphs itself (its `pad_to` argument).

A graph solved with dense Cholesky, called with concrete arrays, is padded
to capacity buckets on the host, so another graph of the same factor types
in the same buckets compiles nothing; the answer, the cost and the marginals
are those of the graph as built, and the padding never shows in `value`.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compiled_programs, se2_loop
from hostile import raises

import eqsmooth as eqs
from eqsmooth.factors._padding import pad_concrete


SOLVER = eqs.LevenbergMarquardt()


def _pose_error(a, b) -> float:
    return float(jnp.max(jnp.abs((a.inverse() @ b).log())))


def test_another_size_compiles_nothing_and_answers_as_built():
    # Loops of 9 and 13 poses: 16 variables and 16 rows once padded.
    first, init, _ = se2_loop(10, N=9)
    second, init2, _ = se2_loop(11, N=13)
    eqs.least_squares(first, init, SOLVER)
    with compiled_programs() as names:
        sol = eqs.least_squares(second, init2, SOLVER)
        jax.block_until_ready(sol.value)
    assert names == [], names
    assert sol.padding == (("pose", 13),)
    ref = eqs.least_squares(second, init2, SOLVER, pad_to=None)
    assert ref.padding is None
    assert sol.value["pose"].unit_complex_xy.shape == (13, 4)
    assert _pose_error(sol.value["pose"], ref.value["pose"]) < 1e-9
    for key in ("initial_cost", "final_cost"):
        np.testing.assert_allclose(sol.stats[key], ref.stats[key], rtol=1e-9)
    assert int(sol.stats["num_steps"]) == int(ref.stats["num_steps"])


def test_marginals_of_a_padded_solve_are_the_real_variables():
    graph, values, _ = se2_loop(12, N=6)
    sol = eqs.least_squares(graph, values, SOLVER)
    ref = eqs.least_squares(graph, values, SOLVER, pad_to=None)
    assert sol.padding is not None
    cov = eqs.marginal_covariances(sol)["pose"]
    assert cov.shape == (6, 3, 3)
    np.testing.assert_allclose(
        cov, eqs.marginal_covariances(ref)["pose"], rtol=1e-8, atol=1e-12
    )
    pick = [("pose", 0), ("pose", 5)]
    np.testing.assert_allclose(
        eqs.joint_marginal_covariance(sol, pick),
        eqs.joint_marginal_covariance(ref, pick),
        rtol=1e-8,
        atol=1e-12,
    )
    # Index 6 exists in the padded graph (8 slots), not in the user's.
    with raises(ValueError, "index 6 out of range for group 'pose' with 6"):
        eqs.joint_marginal_covariance(sol, [("pose", 6)])


def test_what_is_solved_as_built():
    graph, values, _ = se2_loop(13, N=6)
    # Another linear solver, no padding asked for, or a traced call.
    assert (
        eqs.least_squares(graph, values, eqs.LevenbergMarquardt(eqs.PCG())).padding
        is None
    )
    assert eqs.least_squares(graph, values, SOLVER, pad_to=None).padding is None
    traced = jax.jit(lambda g, v: eqs.least_squares(g, v, SOLVER, throw=False))
    assert traced(graph, values).padding is None
    # A chain keeps its block-tridiagonal solver.
    T = 6
    chain = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", [0]),
                jnp.zeros((1, 2)),
                eqs.IsotropicNoise(sqrt_precision=1.0),
            ),
            eqs.BetweenFactor(
                eqs.Var("x", np.arange(T - 1)),
                eqs.Var("x", np.arange(1, T)),
                jnp.ones((T - 1, 2)),
                eqs.IsotropicNoise(sqrt_precision=1.0),
            ),
        ]
    )
    assert eqs.least_squares(chain, {"x": jnp.zeros((T, 2))}, SOLVER).padding is None


def test_the_learnt_padding_equals_pad_graph():
    # Per-row and shared noise parameters, a robust kernel over a masked
    # stack (a boolean leaf), float leaves of two groups.
    graph, values, _ = se2_loop(14, N=5)
    rows = np.array([True, False])
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
    sqrt_info = jnp.asarray(
        np.tril(np.random.default_rng(0).normal(size=(3, 2, 2))) + 2 * np.eye(2)
    )
    point = eqs.PriorFactor(
        eqs.Var("p", [0, 1, 1]), jnp.ones((3, 2)), eqs.SqrtInformationNoise(sqrt_info)
    )
    graph = eqs.FactorGraph(graph.factors + (extra, point))
    values = {**values, "p": jnp.zeros((2, 2))}
    bucket = lambda n: n + 3  # noqa: E731
    for _ in range(2):  # learnt, then from the cache
        fast = pad_concrete(graph, values, bucket)
        slow = eqs.solve.pad_graph(graph, values, bucket)
        a, ta = jax.tree_util.tree_flatten(fast)
        b, tb = jax.tree_util.tree_flatten(slow)
        assert ta == tb
        for x, y in zip(a, b):
            assert x.dtype == y.dtype and x.shape == y.shape
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    # Other numbers in the same structure: the plan gathers them.
    moved = {**values, "p": jnp.full((2, 2), 7.0)}
    np.testing.assert_array_equal(
        np.asarray(pad_concrete(graph, moved, bucket).values["p"]),
        np.asarray(eqs.solve.pad_graph(graph, moved, bucket).values["p"]),
    )


@pytest.mark.parametrize("dtype", [jnp.float32])
def test_float32_graphs_pad_too(dtype):
    graph, values, _ = se2_loop(15, N=6)
    graph = jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, graph
    )
    values = jax.tree_util.tree_map(lambda a: a.astype(dtype), values)
    sol = eqs.least_squares(graph, values, SOLVER)
    ref = eqs.least_squares(graph, values, SOLVER, pad_to=None)
    assert sol.padding is not None
    assert sol.value["pose"].unit_complex_xy.dtype == dtype
    assert _pose_error(sol.value["pose"], ref.value["pose"]) < 1e-4


def test_a_padding_that_computes_from_the_data_is_not_planned():
    # A noise model whose take_rows does arithmetic on its parameter (not a
    # gather): the learnt plan would replay a wrong constant, so none is kept.
    import equinox as eqx

    class _Rescaled(eqs.IsotropicNoise):
        def take_rows(self, index):
            taken = super().take_rows(index)
            return eqx.tree_at(
                lambda m: m.sqrt_precision, taken, taken.sqrt_precision**0.5
            )

    graph, values, _ = se2_loop(16, N=5)
    odd = eqs.PriorFactor(
        eqs.Var("pose", [0]),
        values["pose"][np.array([0])],
        _Rescaled(sqrt_precision=jnp.full((1,), 4.0)),
    )
    graph = eqs.FactorGraph(graph.factors + (odd,))
    assert pad_concrete(graph, values) is None
    # least_squares then solves it as built, with the right answer.
    sol = eqs.least_squares(graph, values, SOLVER)
    assert sol.padding is None
