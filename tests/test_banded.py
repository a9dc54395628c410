"""The fixed-lag window's banded Cholesky solve (`eqsmooth.filters._banded`)
against the dense one, directly and inside the smoother with closures."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_filters import _lin_meas, _lin_trans, F_MAT, H1, M0, P0, Q_COV
from test_fixed_lag import _lin_link


# A linear 2-D chain long enough for the banded path: closures reach at
# most S = 2 steps back, so blocks of (S + 1) · 2 = 6 coordinates, and a lag
# of 12 slots is 4 blocks (`BANDED_MIN_BLOCKS`).
_T, _S, _LAG = 15, 2, 12
_PAIRS = [(0, 2), (3, 4), (4, 6), (8, 7), (9, 11), (12, 14), (11, 13)]


def _factors(scale=1.0):
    import eqsmooth as eqs

    rng = np.random.default_rng(11)
    t = np.arange(_T)
    sqrt_info = eqs.SqrtInformationNoise.from_covariance
    trans = eqs.FunctionFactor(
        _lin_trans,
        (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
        sqrt_info(jnp.asarray(Q_COV)),
        params=jnp.asarray(F_MAT),
    )
    meas = eqs.FunctionFactor(
        _lin_meas,
        (eqs.Var("x", t),),
        eqs.IsotropicNoise.from_sigma(jnp.asarray(0.3)),
        data=jnp.asarray(rng.normal(size=(_T, 1))),
        params=jnp.asarray(H1),
    )
    a, b = (np.array(v) for v in zip(*_PAIRS))
    links = eqs.FunctionFactor(
        _lin_link,
        (eqs.Var("x", a), eqs.Var("x", b)),
        sqrt_info(jnp.asarray([[0.4, 0.1], [0.1, 0.3]])),
        data=scale * jnp.asarray(rng.normal(size=(len(a), 2))),
        params=jnp.asarray([[0.9, 0.2], [-0.1, 1.1]]),
    )
    return trans, meas, links


def test_banded_factorisation_is_the_dense_one():
    """Solve, log-determinant and marginal blocks of a banded normal matrix
    (28 coordinates: 5 blocks of 6, the last padded) equal the dense
    factorisation's."""
    import eqsmooth as eqs
    from eqsmooth.filters._banded import BandedCholesky

    trans, meas, links = _factors()
    prior = eqs.PriorFactor(
        eqs.Var("x", [0]),
        jnp.asarray(M0)[None],
        eqs.SqrtInformationNoise.from_covariance(jnp.asarray(P0)),
    )
    graph = eqs.FactorGraph([prior, trans, meas, links])
    x = {"x": jnp.asarray(np.random.default_rng(0).normal(size=(_T, 2)))}
    lin = eqs.solve.linearize(graph, x)
    banded = eqs.solve.factorize(lin, BandedCholesky(block=(_S + 1) * 2))
    dense = eqs.solve.factorize(lin, eqs.DenseCholesky())
    b = jnp.asarray(np.random.default_rng(1).normal(size=(2 * _T, 3)))
    np.testing.assert_allclose(banded.solve(b), dense.solve(b), rtol=0, atol=1e-10)
    np.testing.assert_allclose(banded.log_det(), dense.log_det(), rtol=1e-12)
    np.testing.assert_allclose(
        banded.inverse_block_diagonal()["x"],
        dense.inverse_block_diagonal()["x"],
        rtol=0,
        atol=1e-10,
    )


def _smooth(scale, linear_solver=None, unrolled=False):
    import eqsmooth as eqs

    trans, meas, links = _factors(scale)
    solver = eqs.FixedStepGaussNewton(linear_solver=linear_solver, num_steps=2)
    return eqs.filters.fixed_lag_smoother(
        trans,
        [meas],
        jnp.asarray(M0),
        jnp.asarray(P0),
        lag=_LAG,
        closures=links,
        solver=solver,
        adjoint=eqs.solve.UnrolledAdjoint()
        if unrolled
        else eqs.solve.ImplicitAdjoint(),
    )


_smooth_jit = jax.jit(_smooth, static_argnums=(1, 2))


def _loss(scale, unrolled):
    sol = _smooth_jit(scale, None, unrolled)
    return jnp.sum(sol.mean**2) + jnp.sum(sol.prior_covariance)


def _central(scale, unrolled, h=1e-5):
    return (_loss(scale + h, unrolled) - _loss(scale - h, unrolled)) / (2 * h)


def test_fixed_lag_with_closures_banded_equals_dense():
    """The smoother's own choice for a window with closures (banded at this
    lag) gives the estimates and covariances of a dense Cholesky."""
    import eqsmooth as eqs
    from eqsmooth.filters import _window

    # This window takes the banded path (and the dense solver keeps its own).
    trans, meas, links = _factors()
    model = _window.chain_rows(trans, [meas], [links], jnp.asarray(M0), jnp.float64)
    chosen = _window._banded_unless_chain(eqs.FixedStepGaussNewton(), model, _LAG, 2)
    assert type(chosen.linear_solver).__name__ == "BandedCholesky"
    banded = _smooth_jit(1.0)
    dense = _smooth_jit(1.0, eqs.DenseCholesky())
    for a, b in (
        (banded.mean, dense.mean),
        (banded.lagged_mean, dense.lagged_mean),
        (banded.prior_covariance, dense.prior_covariance),
    ):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


def test_fixed_lag_banded_derivative_matches_central_differences():
    """Forward-mode derivative through the banded factorisation (unrolled
    iterations) with respect to the closures' data, against float64 central
    differences."""
    s = 1.3
    _, d = jax.jvp(lambda x: _loss(x, True), (s,), (1.0,))
    assert abs(float(d)) > 1e-3
    np.testing.assert_allclose(float(d), float(_central(s, True)), rtol=1e-6)


@pytest.mark.slow
def test_fixed_lag_banded_gradient_matches_central_differences():
    """`jax.grad` of the banded run under the default implicit adjoint (its
    backward solves go through the banded factorisation's transpose)."""
    s = 1.3
    g = jax.grad(lambda x: _loss(x, False))(s)
    assert abs(float(g)) > 1e-3
    np.testing.assert_allclose(float(g), float(_central(s, False)), rtol=1e-6)
