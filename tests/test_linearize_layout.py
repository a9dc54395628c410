"""The autodiff linearisation of a `FunctionFactor` computes one Jacobian per
variable: its blocks, residuals and gradients equal the concatenated-tangent
form and central differences."""

import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs
from eqsmooth.factors._factor import evaluate_rows, linearize_rows


def _residual(pose_a, vel, pose_b, data, params):
    twist = jnp.stack([vel[0], params * vel[1], vel[1] * vel[0]])
    pred = pose_a @ eqs.SE2.exp(0.1 * twist)
    return jnp.concatenate([(pred.inverse() @ pose_b).log(), vel - data])


def _with_empty(x, empty, data, params):
    return jnp.concatenate([x * params, empty, x[:1] ** 2]) - data


def _problem(n=3, seed=0):
    rng = np.random.default_rng(seed)
    poses = eqs.SE2.exp(jnp.asarray(rng.normal(size=(2 * n, 3))))
    pose_a = jax.tree_util.tree_map(lambda x: x[:n], poses)
    pose_b = jax.tree_util.tree_map(lambda x: x[n:], poses)
    vel = jnp.asarray(rng.normal(size=(n, 2)))
    data = jnp.asarray(rng.normal(size=(n, 2)))
    noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.2, 0.05, 0.5, 1.0]))
    t = np.arange(n)
    variables = (eqs.Var("pose", t), eqs.Var("vel", t), eqs.Var("pose", t + n))
    factor = eqs.FunctionFactor(
        _residual, variables, noise, data=data, params=jnp.asarray(0.7)
    )
    return factor, (pose_a, vel, pose_b)


def _concatenated_reference(factor, states):
    """The former formulation: one jacfwd over the concatenated tangent."""
    dims = [eqs.manifold.tangent_dim(s, batch_ndim=1) for s in states]
    ends = np.cumsum(dims)

    def row(data, *xs):
        def r_of(delta):
            pieces = jnp.split(delta, ends[:-1])
            moved = [eqs.retract(x, d) for x, d in zip(xs, pieces)]
            return factor.fn(*moved, data, factor.params)

        zero = jnp.zeros(int(ends[-1]))
        jac = jax.jacfwd(r_of)(zero)
        return r_of(zero), tuple(jnp.split(jac, ends[:-1], axis=1))

    return jax.vmap(row)(factor.data, *states)


def test_blocks_match_concatenated_jacfwd_and_central_differences():
    factor, states = _problem()
    r, jacs = jax.jit(linearize_rows)(factor, states)
    r_ref, jacs_ref = jax.jit(_concatenated_reference)(factor, states)
    np.testing.assert_array_equal(r, r_ref)
    assert [j.shape for j in jacs] == [(3, 5, 3), (3, 5, 2), (3, 5, 3)]
    for j, j_ref in zip(jacs, jacs_ref):
        np.testing.assert_allclose(j, j_ref, rtol=1e-12, atol=1e-12)
    eps = 1e-6
    residual = jax.jit(evaluate_rows)
    for k, jac in enumerate(jacs):
        for i in range(jac.shape[-1]):
            step = jnp.zeros((3, jac.shape[-1])).at[:, i].set(eps)
            plus, minus = list(states), list(states)
            plus[k] = eqs.retract(states[k], step)
            minus[k] = eqs.retract(states[k], -step)
            fd = (residual(factor, tuple(plus)) - residual(factor, tuple(minus))) / (
                2 * eps
            )
            np.testing.assert_allclose(jac[:, :, i], fd, rtol=1e-6, atol=1e-7)


def test_variable_without_tangent_gets_an_empty_block():
    n = 2
    x = jnp.arange(6.0).reshape(n, 3)
    empty = jnp.zeros((n, 0))
    factor = eqs.FunctionFactor(
        _with_empty,
        (eqs.Var("x", range(n)), eqs.Var("e", range(n))),
        eqs.IsotropicNoise(sqrt_precision=1.0),
        data=jnp.ones((n, 4)),
        params=jnp.asarray(2.0),
    )
    r, (jx, je) = jax.jit(linearize_rows)(factor, (x, empty))
    np.testing.assert_allclose(r, jnp.concatenate([2 * x, x[:, :1] ** 2], 1) - 1)
    assert je.shape == (n, 4, 0)
    want = np.zeros((n, 4, 3))
    want[:, :3, :] = 2.0 * np.eye(3)
    want[:, 3, 0] = 2 * np.asarray(x[:, 0])
    np.testing.assert_allclose(jx, want)


def test_gradient_through_linearization_matches_central_differences():
    """Reverse mode through the per-variable Jacobians: the derivative of a
    scalar of the whitened linearisation with respect to the shared
    parameter."""
    factor, states = _problem(seed=1)
    pose = jax.tree_util.tree_map(
        lambda a, b: jnp.concatenate([a, b]), states[0], states[2]
    )
    values = {"pose": pose, "vel": states[1]}

    @jax.jit
    def scalar(p):
        f = eqs.FunctionFactor(
            factor.fn, factor.variables, factor.noise, data=factor.data, params=p
        )
        lin = eqs.linearize(eqs.FactorGraph([f]), values)
        fl = lin.factors[0]
        return sum(jnp.sum(j**2) for j in fl.jacobians) + jnp.sum(fl.residual**3)

    p = jnp.asarray(0.7)
    eps = 1e-6
    fd = (scalar(p + eps) - scalar(p - eps)) / (2 * eps)
    np.testing.assert_allclose(jax.grad(scalar)(p), fd, rtol=1e-6)
