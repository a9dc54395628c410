"""Float32 matrix products at full precision on every backend.

XLA:CPU computes a float32 product in float32 whatever precision it is
given, but GPUs with tensor cores (and TPUs) round the operands of a product
that asks for JAX's default precision to TF32 (or bfloat16): about three
significant digits, which put float32 Lie-group results 1e-4 off their
float64 values on an H200 (jax 0.11.2) where the CPU agrees to 1e-6. Off
the CPU the library asks for `Precision.HIGHEST` in its own products
(`eqsmooth/_precision.py`). These tests trace the programs as for a GPU
(the backend the choice reads is patched) and read them, so a CPU run
catches a product that would be rounded on a GPU.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import reduced_precision_products

import eqsmooth as eqs


GROUPS = [eqs.SO2, eqs.SE2, eqs.SO3, eqs.SE3]


@pytest.fixture(autouse=True)
def _traced_as_for_a_gpu(monkeypatch):
    import eqsmooth._precision as precision

    monkeypatch.setattr(precision, "_backend", lambda: "gpu")


def test_on_the_cpu_products_name_no_precision(monkeypatch):
    """XLA:CPU computes float32 in float32 anyway, and keeps a product that
    names a precision as a `dot` instead of fusing it (slower): on the CPU
    the library's products name none."""
    import eqsmooth._precision as precision

    monkeypatch.setattr(precision, "_backend", lambda: "cpu")
    xi = jnp.ones((4, 3), jnp.float32)
    found = reduced_precision_products(eqs.SO3.right_jacobian, xi)
    assert found and all("None" in f for f in found)
    monkeypatch.setattr(precision, "_backend", lambda: "gpu")
    assert reduced_precision_products(eqs.SO3.right_jacobian, xi) == []


def test_the_check_sees_a_default_precision_product():
    a = jnp.ones((3, 3), jnp.float32)
    assert reduced_precision_products(lambda a: a @ a, a) == ["(3, 3) x (3, 3) (None)"]
    # Inside a loop body, too.
    scan = lambda a: jax.lax.scan(lambda c, _: (c @ a, None), a, None, length=2)[0]
    assert len(reduced_precision_products(scan, a)) == 1
    assert reduced_precision_products(lambda a: eqs.SO3.exp(a[0]).adjoint(), a) == []


def _lie_routes(group):
    def routes(xi):
        g, h = group.exp(xi), group.exp(2.0 * xi)
        points = jnp.ones(xi.shape[:-1] + (group.space_dim,), xi.dtype)
        return (
            (g @ h).log(),
            g.inverse().parameters(),
            g.adjoint(),
            group.right_jacobian(xi),
            group.right_jacobian_inv(xi),
            group.left_jacobian(xi),
            group.left_jacobian_inv(xi),
            g.jlog(),
            g.interpolate(h, 0.3).parameters(),
            g @ points,
            group.from_matrix(g.as_matrix()).parameters(),
        )

    return routes


@pytest.mark.parametrize("group", GROUPS, ids=lambda g: g.__name__)
def test_lie_group_products_are_full_precision(group):
    xi = jnp.asarray(
        np.random.default_rng(0).normal(size=(4, group.tangent_dim)), jnp.float32
    )
    routes = _lie_routes(group)
    total = lambda xi: sum(jnp.sum(out) for out in routes(xi))
    assert reduced_precision_products(routes, xi) == []
    assert reduced_precision_products(jax.jacfwd(lambda x: routes(x)[0]), xi) == []
    assert reduced_precision_products(jax.grad(total), xi) == []


def _se2_chain(T: int = 6):
    rng = np.random.default_rng(1)
    f32 = lambda a: jnp.asarray(a, jnp.float32)
    truth = eqs.SE2.exp(f32(np.cumsum(rng.normal(size=(T, 3)), axis=0)))
    t = np.arange(T)
    odometry = eqs.BetweenFactor(
        eqs.Var("x", t[:-1]),
        eqs.Var("x", t[1:]),
        truth[t[:-1]].inverse() @ truth[t[1:]],
        eqs.DiagonalNoise.from_sigmas(f32([0.1, 0.1, 0.05])),
    )
    seen = eqs.PriorFactor(
        eqs.Var("x", t), truth, eqs.DiagonalNoise.from_sigmas(f32([0.3, 0.3, 0.1]))
    )
    init = {"x": truth @ eqs.SE2.exp(f32(0.1 * rng.normal(size=(T, 3))))}
    return odometry, seen, init


@pytest.mark.parametrize(
    "linear_solver",
    [eqs.BlockTridiagonal(), eqs.DenseCholesky(), eqs.PCG()],
    ids=lambda s: type(s).__name__,
)
def test_solver_routes_are_full_precision(linear_solver):
    odometry, seen, init = _se2_chain()
    graph = eqs.FactorGraph([odometry, seen])

    def solve(values):
        solver = eqs.LevenbergMarquardt(linear_solver=linear_solver)
        return eqs.least_squares(graph, values, solver, adjoint=eqs.ImplicitAdjoint())

    def value_and_marginals(values):
        sol = solve(values)
        return sol.value["x"].parameters(), eqs.marginal_covariances(sol)["x"]

    grad = jax.grad(lambda v: jnp.sum(solve(v).value["x"].parameters()))
    assert reduced_precision_products(value_and_marginals, init) == []
    assert reduced_precision_products(grad, init) == []


def test_filter_routes_are_full_precision():
    odometry, seen, init = _se2_chain()
    mean0 = init["x"][0]
    cov0 = jnp.eye(3, dtype=jnp.float32)

    def filters(mean0):
        sol = eqs.ekf(odometry, [seen], mean0, cov0)
        smoothed = eqs.rts_smoother(sol)
        lagged = eqs.filters.fixed_lag_smoother(odometry, (seen,), mean0, cov0, lag=2)
        return sol.covariance, smoothed.covariance, lagged.prior_covariance

    assert reduced_precision_products(filters, mean0) == []
