"""eqsmooth.solve.IncrementalSmoother: a growing SE(2) pose graph with loop
closures, updated one pose at a time, answers the batch solve of the graph so
far after every update, compiles nothing while its buffers hold, grows them
by doubling, and refuses what it cannot add."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import compiled_programs

import eqsmooth as eqs


NOISE = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 0.05]))
N = 11  # poses: buffers of 8 grow to 16 on the way
SMOOTHER = eqs.solve.IncrementalSmoother()


def _truth():
    ang = np.linspace(0, 1.5 * np.pi, N)
    return eqs.SE2.from_xy_theta(
        jnp.asarray(np.cos(ang)), jnp.asarray(np.sin(ang)), jnp.asarray(ang + np.pi / 2)
    )


def _between(truth, rng, i, j):
    d = truth[np.array([i])].inverse() @ truth[np.array([j])]
    d = d @ eqs.SE2.exp(jnp.asarray(0.05 * rng.normal(size=(1, 3))))
    return eqs.BetweenFactor(eqs.Var("pose", [i]), eqs.Var("pose", [j]), d, NOISE)


def _replay():
    """`(first graph, its values, [(new factors, new values)] per pose)`:
    odometry each step, a closure to the pose four back at poses 6 and 9."""
    rng = np.random.default_rng(0)
    truth = _truth()
    prior = eqs.PriorFactor(eqs.Var("pose", [0]), truth[np.array([0])], NOISE)
    first = [prior, _between(truth, rng, 0, 1)]
    steps = []
    for j in range(2, N):
        new = [_between(truth, rng, j - 1, j)]
        if j % 3 == 0 and j >= 4:
            new.append(_between(truth, rng, j - 4, j))
        guess = truth[np.array([j])] @ eqs.SE2.exp(jnp.asarray([[0.1, -0.1, 0.05]]))
        steps.append((new, {"pose": guess}))
    return first, {"pose": truth[np.array([0, 1])]}, steps


def _batch(factors, values):
    sol = eqs.least_squares(eqs.FactorGraph(factors), values, eqs.LevenbergMarquardt())
    return np.asarray(sol.value["pose"].unit_complex_xy), float(sol.stats["final_cost"])


def test_every_update_answers_the_batch_solve_and_compiles_only_when_it_grows():
    first, values, steps = _replay()
    state = SMOOTHER.init(eqs.FactorGraph(first), values)
    factors, compiles = list(first), 0
    for j, (new, new_values) in enumerate(steps, start=2):
        capacity = state.capacity
        with compiled_programs() as names:
            state = SMOOTHER.update(state, new, new_values)
            jax.block_until_ready(state.values)
        if state.capacity == capacity:
            # With or without a closure: init compiled the update's program.
            assert names == [], (j, names)
        else:
            compiles += 1
            assert names == ["jit(_step)"], (j, names)  # one program per growth
        factors += new
        est = state.estimate()["pose"]
        assert est.unit_complex_xy.shape == (j + 1, 4)
        if j in (6, N - 1):  # after a closure; after the growth, at the end
            real = {"pose": eqs.SE2(jnp.asarray(est.unit_complex_xy))}
            ref, cost = _batch(factors, real)
            np.testing.assert_allclose(est.unit_complex_xy, ref, atol=1e-7)
            graph_cost = float(eqs.FactorGraph(factors).cost(real))
            np.testing.assert_allclose(graph_cost, cost, rtol=1e-9, atol=1e-12)
            # The padded graph's cost is the real graph's (padding costs 0).
            np.testing.assert_allclose(
                float(state.graph.cost(state.values)), cost, rtol=1e-9, atol=1e-12
            )
    assert compiles == 1
    assert state.capacity == ((8, 16), (("pose", 16),))
    assert state.num_rows == (1, N - 1 + 2)
    assert state.result == eqs.solve.RESULTS.successful


@pytest.mark.slow  # compiles the implicit adjoint of two buffer sizes (~50 s)
def test_the_estimate_is_differentiable_through_updates():
    # d(final estimate)/d(closure measurement) through init and five updates,
    # against float64 central differences in the measurement's tangent.
    first, values, steps = _replay()
    (odo, closure), guess = steps[4]
    assert len(steps[4][0]) == 2

    def final(u):
        moved = eqx.tree_at(
            lambda f: f.measurement, closure, closure.measurement @ eqs.SE2.exp(u)
        )
        state = SMOOTHER.init(eqs.FactorGraph(first), values)
        for new, new_values in steps[:4]:
            state = SMOOTHER.update(state, new, new_values)
        state = SMOOTHER.update(state, [odo, moved], guess)
        return state.values["pose"][np.arange(7)].log().sum()

    u0 = jnp.zeros((1, 3))
    grad = jax.grad(final)(u0)
    eps = 1e-6
    fd = np.zeros(3)
    for k in range(3):
        e = jnp.zeros((1, 3)).at[0, k].set(eps)
        fd[k] = (final(u0 + e) - final(u0 - e)) / (2 * eps)
    np.testing.assert_allclose(np.asarray(grad)[0], fd, rtol=1e-5, atol=1e-7)
    assert np.abs(fd).max() > 1e-3  # the closure moves the estimate


def test_updates_refuse_what_they_cannot_add():
    first, values, steps = _replay()
    state = SMOOTHER.init(eqs.FactorGraph(first), values)
    new, guess = steps[0]
    cases = [
        (
            [
                eqs.PriorFactor(
                    eqs.Var("pose", [2]),
                    guess["pose"],
                    eqs.IsotropicNoise.from_sigma(1.0),
                )
            ],
            guess,
            "of no kind init's graph has",
        ),
        (new, None, "refers to index 2, but the group has 2 variables after this"),
        (new, {"landmark": guess["pose"]}, "new_values has group 'landmark'"),
    ]
    for factors, vals, message in cases:
        with pytest.raises((ValueError, TypeError), match=message):
            SMOOTHER.update(state, factors, vals)
    # (the jaxtyping hook or the method's own check names the parameter)
    with pytest.raises(TypeError, match="state"):
        SMOOTHER.update(values, new, guess)


K = 2  # rows per update_rows block: the odometry and room for one closure


def _rows(new, xnp=np):
    """An update's factors as `update_rows`' arguments: a block of K rows,
    the absent closure masked (a copy of the odometry)."""
    fs = list(new) + [new[0]] * (K - len(new))
    measured = eqs.SE2(xnp.concatenate([f.measurement.unit_complex_xy for f in fs]))
    ids = tuple(np.concatenate([f.variables[i].ids for f in fs]) for i in range(2))
    return (
        [None, {"measurement": measured}],
        [None, ids],
        [None, np.arange(K) < len(new)],
    )


def test_update_rows_gives_update_s_estimates_and_compiles_once_per_capacity():
    # A fixed number of Gauss-Newton steps, so that both runs take the same
    # iterations (LM's stopping tests may stop one step apart on rounding).
    smoother = eqs.solve.IncrementalSmoother(eqs.FixedStepGaussNewton(num_steps=4))
    first, values, steps = _replay()
    a = smoother.init(eqs.FactorGraph(first), values)
    b = smoother.init(eqs.FactorGraph(first), values)
    factors, compiles = list(first), []
    for j, (new, new_values) in enumerate(steps, start=2):
        a = smoother.update(a, new, new_values)
        capacity, rows = b.capacity, _rows(new)
        with compiled_programs() as names:
            b = smoother.update_rows(b, *rows, new_values)
            jax.block_until_ready(b.values)
        # The first call compiles the program, a growth one more; no other
        # program (no eager operations around it).
        assert names in ([], ["jit(_rows_step)"]), (j, names)
        if names:
            compiles.append((j, b.capacity != capacity))
        factors += new
        np.testing.assert_allclose(
            b.estimate()["pose"].unit_complex_xy,
            a.estimate()["pose"].unit_complex_xy,
            rtol=0,
            atol=1e-10,
        )
    assert [grew for _, grew in compiles] == [False, True], compiles
    est = b.estimate()["pose"]
    ref, _ = _batch(factors, {"pose": eqs.SE2(jnp.asarray(est.unit_complex_xy))})
    np.testing.assert_allclose(est.unit_complex_xy, ref, atol=1e-7)
    # Masked rows at the end of a block are written over by the next one.
    assert b.num_rows == (1, len(factors) - 1)
    assert b.result == eqs.solve.RESULTS.successful


def test_update_rows_refuses_what_it_cannot_add():
    first, values, steps = _replay()
    state = SMOOTHER.init(eqs.FactorGraph(first), values)
    new, guess = steps[0]
    rows, ids, active = _rows(new)
    measured = rows[1]["measurement"]
    bad_ids = [None, (ids[1][0], np.array([2, 9]))]
    cases = [
        (dict(rows=rows[1:]), "rows must be a sequence of one entry per stack"),
        (dict(rows=[None, {"measured": measured}]), "has field 'measured'"),
        (
            dict(rows=[None, {"measurement": measured[np.array([0])]}]),
            r"rows\[1\]\['measurement'\] for stack 1 \(BetweenFactor\) has shape",
        ),
        (dict(ids=bad_ids), "refers to index 9, but the group has 3 variables"),
        # (the jaxtyping hook may name it first: beartype samples one entry of
        # each sequence, so which check fires varies between runs)
        (
            dict(active=[None, np.ones(3, bool)]),
            r"active\[1\] .* shape \(3,\)|'active': \[None, bool\[3\]",
        ),
        (dict(new_values={"landmark": guess["pose"]}), "group 'landmark'"),
        (
            dict(new_values={"pose": jnp.zeros((1, 3))}),
            r"new_values\['pose'\] has leaves",
        ),
    ]
    for change, message in cases:
        kw = dict(rows=rows, ids=ids, active=active, new_values=guess) | change
        with pytest.raises((ValueError, TypeError), match=message):
            SMOOTHER.update_rows(state, **kw)


@pytest.mark.slow  # compiles the implicit adjoint of two buffer sizes (~60 s)
def test_update_rows_is_differentiable():
    # As test_the_estimate_is_differentiable_through_updates, through
    # update_rows: d(final estimate)/d(closure measurement).
    first, values, steps = _replay()
    (odo, closure), guess = steps[4]

    def final(u):
        moved = eqx.tree_at(
            lambda f: f.measurement, closure, closure.measurement @ eqs.SE2.exp(u)
        )
        state = SMOOTHER.init(eqs.FactorGraph(first), values)
        for new, new_values in steps[:4]:
            state = SMOOTHER.update_rows(state, *_rows(new), new_values)
        state = SMOOTHER.update_rows(state, *_rows([odo, moved], jnp), guess)
        return state.values["pose"][np.arange(7)].log().sum()

    u0 = jnp.zeros((1, 3))
    grad = jax.grad(final)(u0)
    eps = 1e-6
    fd = np.zeros(3)
    for k in range(3):
        e = jnp.zeros((1, 3)).at[0, k].set(eps)
        fd[k] = (final(u0 + e) - final(u0 - e)) / (2 * eps)
    np.testing.assert_allclose(np.asarray(grad)[0], fd, rtol=1e-5, atol=1e-7)
    assert np.abs(fd).max() > 1e-3
