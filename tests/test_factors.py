import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


def test_var_hash_and_errors():
    import eqsmooth as eqs

    a = eqs.Var("x", [0, 1, 2])
    b = eqs.Var("x", np.array([0, 1, 2]))
    assert a == b and hash(a) == hash(b)
    assert a != eqs.Var("y", [0, 1, 2])
    assert len(a) == 3
    with pytest.raises(ValueError, match="non-negative"):
        eqs.Var("x", [-1])
    with pytest.raises(ValueError, match="1-D integer"):
        eqs.Var("x", np.zeros((2, 2), dtype=int))
    with pytest.raises(TypeError, match="group"):
        eqs.Var(3, [0])  # pyright: ignore


def test_var_is_static_under_jit():
    import eqsmooth as eqs

    calls = []

    @jax.jit
    def f(v, x):
        calls.append(1)
        return x[v.ids]

    x = jnp.arange(5.0)
    f(eqs.Var("x", [1, 2]), x)
    f(eqs.Var("x", [1, 2]), x + 1)
    assert len(calls) == 1
    f(eqs.Var("x", [2, 3]), x)
    assert len(calls) == 2


def test_noise_whitening_and_logdet():
    import eqsmooth as eqs

    r = jnp.asarray(np.random.default_rng(0).normal(size=(4, 3)))
    iso = eqs.IsotropicNoise.from_sigma(2.0)
    np.testing.assert_allclose(iso.whiten(r), r / 2)
    np.testing.assert_allclose(iso.log_det_sqrt_information(4, 3), 12 * np.log(0.5))
    per_row = eqs.IsotropicNoise(sqrt_precision=jnp.arange(1.0, 5.0))
    np.testing.assert_allclose(
        per_row.whiten(r), np.asarray(r) * np.arange(1, 5)[:, None]
    )
    diag = eqs.DiagonalNoise(sqrt_precision=jnp.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(diag.whiten(r), np.asarray(r) * np.array([1, 2, 3]))
    cov = jnp.array([[2.0, 0.3, 0.1], [0.3, 1.0, 0.2], [0.1, 0.2, 0.5]])
    full = eqs.SqrtInformationNoise.from_covariance(cov)
    R = np.asarray(full.sqrt_information)
    np.testing.assert_allclose(R.T @ R, np.linalg.inv(cov), rtol=1e-10)
    assert np.allclose(R, np.tril(R))
    full2 = eqs.SqrtInformationNoise.from_information(jnp.linalg.inv(cov))
    R2 = np.asarray(full2.sqrt_information)
    np.testing.assert_allclose(R2.T @ R2, np.linalg.inv(cov), rtol=1e-10)
    assert np.allclose(R2, np.tril(R2))
    np.testing.assert_allclose(
        full.log_det_sqrt_information(4, 3), -2 * np.log(np.linalg.det(cov)), rtol=1e-10
    )
    # whitening a Jacobian (n, m, d) acts on axis 1
    J = jnp.ones((4, 3, 2))
    np.testing.assert_allclose(full.whiten(J)[0], R @ np.ones((3, 2)))


def test_noise_rejects_bad_values():
    import eqsmooth as eqs

    with pytest.raises(
        ValueError, match="IsotropicNoise.sqrt_precision must be positive"
    ):
        eqs.IsotropicNoise(sqrt_precision=-1.0)
    with pytest.raises(ValueError, match="sigmas must be positive"):
        eqs.DiagonalNoise.from_sigmas(jnp.array([1.0, 0.0]))
    with pytest.raises(ValueError, match="diagonal must be positive"):
        eqs.SqrtInformationNoise(-jnp.eye(2))
    with pytest.raises(ValueError, match="HuberNoise.scale must be positive"):
        eqs.HuberNoise(eqs.IsotropicNoise(sqrt_precision=1.0), 0.0)


@pytest.mark.parametrize("kind", ["huber", "cauchy"])
def test_robust_irls_gradient_matches_true_cost(kind):
    """Jᵀ(√ρ' r) from the linearisation is the gradient of the reported cost."""
    import eqsmooth as eqs
    from eqsmooth.solve._linearization import gradient, linearize

    base = eqs.IsotropicNoise(sqrt_precision=1.0)
    noise = eqs.HuberNoise(base, 0.7) if kind == "huber" else eqs.CauchyNoise(base, 0.7)
    data = jnp.asarray(np.random.default_rng(1).normal(size=(5, 2)) * 2)

    def res(x, d, p):
        return x - d

    graph = eqs.FactorGraph(
        [eqs.FunctionFactor(res, (eqs.Var("x", np.arange(5)),), noise, data=data)]
    )
    values = {"x": jnp.zeros((5, 2))}
    lin = linearize(graph, values)
    g = gradient(lin)["x"]
    g_true = jax.grad(lambda x: graph.cost({"x": x}))(values["x"])
    np.testing.assert_allclose(g, g_true, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(lin.cost, graph.cost(values), rtol=1e-12)
    # cost value for any scale: small residuals are quadratic
    small = {"x": data - 1e-3}
    np.testing.assert_allclose(graph.cost(small), 0.5 * 10 * 1e-6, rtol=1e-3)


def test_huber_value_and_derivative_continuous():
    import eqsmooth as eqs

    h = eqs.HuberNoise(eqs.IsotropicNoise(sqrt_precision=1.0), 2.0)
    s = jnp.array([4.0 - 1e-9, 4.0 + 1e-9, 0.0, 100.0])
    rho, d = h.rho(s)
    np.testing.assert_allclose(rho[:2], [4.0, 4.0], atol=1e-6)
    np.testing.assert_allclose(d[:2], [1.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(rho[3], 2 * 2 * 10 - 4)
    assert jnp.all(jnp.isfinite(jax.grad(lambda s: h.rho(s)[0].sum())(s)))


def test_graph_errors_name_the_culprit():
    import eqsmooth as eqs

    def res(x, d, p):
        return x - d

    t = np.arange(3)
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                res,
                (eqs.Var("x", [0, 1, 5]),),
                eqs.IsotropicNoise(sqrt_precision=1.0),
                data=jnp.zeros((3, 2)),
            )
        ]
    )
    with pytest.raises(
        ValueError, match=r"FunctionFactor: variable 0 \(group 'x'\) has indices \[5\]"
    ):
        graph.cost({"x": jnp.zeros((3, 2))})
    with pytest.raises(
        ValueError, match="refers to group 'x', which is not in the values"
    ):
        graph.cost({"y": jnp.zeros((3, 2))})
    bad = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                res,
                (eqs.Var("x", t),),
                eqs.IsotropicNoise(sqrt_precision=1.0),
                data=jnp.zeros((4, 2)),
            )
        ]
    )
    with pytest.raises(
        ValueError, match=r"FunctionFactor.data: per-row leaf of shape \(4, 2\)"
    ):
        bad.cost({"x": jnp.zeros((3, 2))})
    wrong_noise = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                res,
                (eqs.Var("x", t),),
                eqs.DiagonalNoise(sqrt_precision=jnp.ones(5)),
                data=jnp.zeros((3, 2)),
            )
        ]
    )
    from eqsmooth.solve import linearize

    with pytest.raises(
        ValueError,
        match=r"FunctionFactor: DiagonalNoise.sqrt_precision has shape \(5,\)",
    ):
        linearize(wrong_noise, {"x": jnp.zeros((3, 2))})
    with pytest.raises(ValueError, match="same number of rows"):
        eqs.FunctionFactor(
            res,
            (eqs.Var("x", [0]), eqs.Var("x", [0, 1])),
            eqs.IsotropicNoise(sqrt_precision=1.0),
        )


def test_shared_field_gradient_and_nll():
    """Gradients reach shared parameters; NLL = cost − log det + const."""
    from helpers import random_chain

    graph, init, truth = random_chain(0)
    values = {"x": truth}

    def nll(p):
        import equinox as eqx

        g = eqx.tree_at(lambda g: g.factors[0].params, graph, p)
        return g.negative_log_likelihood(values)

    p = jnp.asarray(0.5)
    g = jax.grad(nll)(p)
    eps = 1e-6
    fd = (nll(p + eps) - nll(p - eps)) / (2 * eps)
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    n1, n2, m = 5, 6, 2
    expected = (
        graph.cost(values)
        - (n1 * m * np.log(1 / 0.3) + n2 * m * np.log(1 / 0.2))
        + 0.5 * (n1 + n2) * m * np.log(2 * np.pi)
    )
    np.testing.assert_allclose(
        graph.negative_log_likelihood(values), expected, rtol=1e-10
    )


def test_linearisation_matches_autodiff_on_se2():
    """Jacobian blocks equal d r(x ⊕ δ)/dδ computed independently."""
    from helpers import se2_loop

    import eqsmooth as eqs
    from eqsmooth.solve._linearization import dense_jacobian, linearize

    graph, init, _ = se2_loop(0, N=4)
    # Compiled, not op by op (hundreds of small compilations otherwise).
    J, r = eqx.filter_jit(lambda g, v: dense_jacobian(linearize(g, v)))(graph, init)

    @jax.jit
    def whitened_and_jacobian(delta_flat):
        def whitened(delta_flat):
            vals = {"pose": eqs.retract(init["pose"], delta_flat.reshape(4, 3))}
            rows = graph.whitened_residuals(vals)
            return jnp.concatenate([w.reshape(-1) for w in rows])

        return whitened(delta_flat), jax.jacfwd(whitened)(delta_flat)

    r_ref, J_ref = whitened_and_jacobian(jnp.zeros(12))
    np.testing.assert_allclose(J, J_ref, atol=1e-10)
    np.testing.assert_allclose(r, r_ref, atol=1e-12)


def test_eager_linearize_is_one_compiled_program():
    """`eqs.linearize` called outside `jit` compiles one program (not one per
    JAX operation), and gives what the solvers' uncompiled copy gives."""
    from helpers import compiled_programs, se2_loop

    import eqsmooth as eqs
    from eqsmooth.solve._linearization import linearize_graph

    graph, init, _ = se2_loop(1, N=3)
    with compiled_programs() as names:
        lin = eqs.linearize(graph, init)
    # One program (none if an earlier test compiled this graph structure).
    assert names in ([], ["jit(linearize)"])
    eqns = jax.make_jaxpr(eqs.linearize)(graph, init).eqns
    assert len(eqns) == 1 and eqns[0].params["name"] == "linearize"
    ref = eqx.filter_jit(linearize_graph)(graph, init)
    for a, b in zip(jax.tree_util.tree_leaves(lin), jax.tree_util.tree_leaves(ref)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_eager_cost_and_nll_are_one_compiled_program_each():
    """`FactorGraph.cost` and `.negative_log_likelihood` called outside `jit`
    compile one program each, and equal their uncompiled forms."""
    from helpers import compiled_programs, se2_loop

    from eqsmooth.factors._graph import graph_cost, graph_negative_log_likelihood

    graph, init, _ = se2_loop(2, N=3)
    with compiled_programs() as names:
        cost = graph.cost(init)
        nll = graph.negative_log_likelihood(init)
    assert set(names) <= {"jit(graph_cost)", "jit(graph_negative_log_likelihood)"}
    assert len(names) <= 2, names
    ref = jax.jit(lambda g, v: (graph_cost(g, v), graph_negative_log_likelihood(g, v)))
    ref_cost, ref_nll = ref(graph, init)
    np.testing.assert_allclose(float(cost), float(ref_cost), rtol=1e-14)
    np.testing.assert_allclose(float(nll), float(ref_nll), rtol=1e-14)
    assert float(cost) > 0


def _random_state(kind, n, rng, scale=1.0):
    import eqsmooth as eqs

    group = {"SO2": eqs.lie.SO2, "SO3": eqs.lie.SO3, "SE2": eqs.lie.SE2}
    group |= {"SE3": eqs.lie.SE3}
    if kind == "mixed":
        return {
            "pose": eqs.lie.SE2.exp(jnp.asarray(scale * rng.normal(size=(n, 3)))),
            "v": jnp.asarray(rng.normal(size=(n, 2, 2))),
        }
    G = group[kind]
    return G.exp(jnp.asarray(scale * rng.normal(size=(n, G.tangent_dim))))


def _autodiff_rows(factor, states):
    """Reference: forward-mode Jacobians of `residual` under right perturbations,
    row by row, independent of the closed form."""
    import equinox as eqx

    import eqsmooth as eqs
    from eqsmooth.factors._factor import _row_axes

    dims = [eqs.manifold.tangent_dim(s, batch_ndim=1) for s in states]

    def row(f, *xs):
        def r_of(*deltas):
            return f.residual(*(eqs.retract(x, d) for x, d in zip(xs, deltas)))

        zeros = [jnp.zeros(d) for d in dims]
        jacs = jax.jacfwd(r_of, argnums=tuple(range(len(xs))))(*zeros)
        return r_of(*zeros), jacs

    axes = (_row_axes(factor),) + (0,) * len(states)
    return eqx.filter_vmap(row, in_axes=axes)(factor, *states)


@pytest.mark.parametrize("kind", ["SO2", "SO3", "SE2", "SE3", "mixed"])
def test_closed_form_jacobians_match_autodiff_and_finite_differences(kind):
    """BetweenFactor's and PriorFactor's closed-form Jacobians equal forward-mode
    autodiff of their residuals and float64 central differences in tangent
    coordinates, at generic points and where the residual is zero (the
    small-angle branches)."""
    import eqsmooth as eqs
    from eqsmooth.factors._factor import evaluate_rows, linearize_rows

    rng = np.random.default_rng(1)
    n = 4
    a, b = _random_state(kind, n, rng), _random_state(kind, n, rng)
    # Rows 0 and 1: a measurement equal to a⁻¹b (residual 0) and 1e-9 from it.
    rel = jax.tree_util.tree_map(
        lambda u, v: u.inverse() @ v if eqs.manifold.is_group(u) else v - u,
        a,
        b,
        is_leaf=eqs.manifold.is_group,
    )
    other = _random_state(kind, n, rng, scale=0.5)
    tiny = eqs.retract(rel, jnp.full((n, eqs.manifold.tangent_dim(rel, 1)), 1e-9))
    measurement = jax.tree_util.tree_map(
        lambda x, y, z: jnp.stack([x[0], y[1], z[2], z[3]]),
        rel,
        tiny,
        other,
    )
    noise = eqs.IsotropicNoise(sqrt_precision=1.0)
    factors = [
        eqs.BetweenFactor(
            eqs.Var("x", range(n)), eqs.Var("x", range(n)), measurement, noise
        ),
        eqs.PriorFactor(eqs.Var("x", range(n)), measurement, noise),
    ]
    for factor, states in zip(factors, [(a, b), (a,)]):
        assert isinstance(factor, eqs.AbstractAnalyticFactor)
        r, jacs = jax.jit(linearize_rows)(factor, states)
        r_ref, jacs_ref = jax.jit(_autodiff_rows)(factor, states)
        np.testing.assert_allclose(r, r_ref, atol=1e-12)
        for j, j_ref in zip(jacs, jacs_ref):
            np.testing.assert_allclose(j, j_ref, rtol=1e-9, atol=1e-10)
        # Central differences in tangent coordinates, variable by variable.
        residual = jax.jit(evaluate_rows)
        eps = 1e-6
        for k, (state, jac) in enumerate(zip(states, jacs)):
            d = jac.shape[-1]
            for i in range(d):
                step = jnp.zeros((n, d)).at[:, i].set(eps)
                plus = list(states)
                minus = list(states)
                plus[k], minus[k] = eqs.retract(state, step), eqs.retract(state, -step)
                fd = (
                    residual(factor, tuple(plus)) - residual(factor, tuple(minus))
                ) / (2 * eps)
                np.testing.assert_allclose(jac[..., i], fd, rtol=1e-5, atol=1e-6)
