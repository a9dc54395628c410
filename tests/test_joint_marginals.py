"""Joint marginal covariances (cross-covariances included) against the dense
inverse of JᵀJ, and the fast path from a Solution's stored linearisation."""

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import prior_and_odometry


def _dense_cov(lin):
    from eqsmooth.solve._linearization import dense_jacobian

    J, _ = (np.asarray(a) for a in dense_jacobian(lin))
    cov = np.linalg.inv(J.T @ J)
    offsets, start = {}, 0
    for g in lin.layout:
        offsets[g.name] = (start, g.dim)
        start += g.count * g.dim
    return cov, offsets


def _index(offsets, chosen):
    idx = []
    for g, i in chosen:
        s, d = offsets[g]
        idx.extend(range(s + i * d, s + (i + 1) * d))
    return np.array(idx)


def test_joint_marginals_match_dense_inverse():
    from test_linear_solvers import _loop_lin

    import eqsmooth as eqs

    lin = _loop_lin(0)  # a graph with a loop: groups "x" and "l"
    cov, offsets = _dense_cov(lin)
    chosen = [("x", 3), ("l", 0), ("x", 0)]
    got = eqs.joint_marginal_covariance(lin, chosen)
    idx = _index(offsets, chosen)
    np.testing.assert_allclose(
        np.asarray(got), cov[np.ix_(idx, idx)], rtol=0, atol=1e-9
    )
    # Cross-covariances are really there (not a block-diagonal answer).
    dx = offsets["x"][1]
    assert np.max(np.abs(np.asarray(got)[:dx, dx:])) > 1e-6
    # A Var selects all its rows, in order.
    got_var = eqs.joint_marginal_covariance(lin, [eqs.Var("x", [3, 0])])
    idx = _index(offsets, [("x", 3), ("x", 0)])
    np.testing.assert_allclose(
        np.asarray(got_var), cov[np.ix_(idx, idx)], rtol=0, atol=1e-9
    )
    with pytest.raises(ValueError, match="out of range"):
        eqs.joint_marginal_covariance(lin, [("x", 10**6)])
    with pytest.raises(ValueError, match="unknown group"):
        eqs.joint_marginal_covariance(lin, [("nope", 0)])


def test_marginals_from_a_solution():
    """`marginal_covariances(sol)` and `joint_marginal_covariance(sol, ...)` use
    the final state's linearisation: the same numbers as relinearising."""
    import eqsmooth as eqs

    xyt = np.array([[0.0, 0.0, 0.0], [1.0, 0.1, 0.2], [2.0, 0.3, 0.1]])
    poses = eqs.SE2.from_xy_theta(*(jnp.asarray(xyt[:, i]) for i in range(3)))
    graph = eqs.FactorGraph(
        [
            *prior_and_odometry(
                poses[:1],
                jnp.array([0.1, 0.1, 0.05]),
                [0, 1],
                [1, 2],
                poses[:2].inverse() @ poses[1:],
                jnp.array([0.2, 0.2, 0.1]),
            ),
            eqs.TranslationPriorFactor(
                eqs.Var("x", [2]),
                jnp.array([[2.1, 0.2]]),
                eqs.IsotropicNoise.from_sigma(0.3),
            ),
        ]
    )
    sol = eqs.least_squares(graph, {"x": poses}, eqs.GaussNewton())
    lin = eqs.linearize(graph, sol.value)
    fast = eqs.marginal_covariances(sol)
    slow = eqs.marginal_covariances(lin)
    np.testing.assert_allclose(
        np.asarray(fast["x"]), np.asarray(slow["x"]), rtol=1e-9, atol=1e-12
    )
    joint = eqs.joint_marginal_covariance(sol, [("x", 0), ("x", 2)])
    np.testing.assert_allclose(
        np.asarray(joint[:3, :3]), np.asarray(slow["x"][0]), rtol=1e-9, atol=1e-12
    )
    np.testing.assert_allclose(
        np.asarray(joint[3:, 3:]), np.asarray(slow["x"][2]), rtol=1e-9, atol=1e-12
    )
    assert str(sol.result).endswith("<successful>")
