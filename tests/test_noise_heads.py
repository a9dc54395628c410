"""The learned noise heads (eqsmooth.learn): start at 1/σ₀, stay above the
floor, give the shapes they document, and their gradients match central
differences (float64)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import eqsmooth.learn as L


def test_constant_head_starts_at_one_over_sigma():
    head = L.ConstantNoiseHead(np.array([0.5, 2.0]), floor=0.1)
    out = head(jnp.zeros((7, 3, 4)))
    assert out.shape == (7, 3, 2)
    np.testing.assert_allclose(out[0, 0], [2.0, 0.5], rtol=1e-6)
    scalar = L.ConstantNoiseHead(4.0)(jnp.zeros((5, 1)))
    assert scalar.shape == (5,)
    np.testing.assert_allclose(scalar, 0.25, rtol=1e-6)


def _head(inputs: int, depth: int, key, floor, **kw):
    """A heteroscedastic head of width 8 around the constant `[0.5, 2.0]`."""
    return L.HeteroscedasticNoiseHead(
        np.array([0.5, 2.0]), inputs, width=8, depth=depth, key=key, floor=floor, **kw
    )


@pytest.mark.parametrize("learn_scale", [False, True])
def test_heteroscedastic_head(learn_scale):
    key = jax.random.key(0)
    head = _head(3, 2, key, (0.1, 0.2), learn_scale=learn_scale, shift=1.0, scale=2.0)
    x = jax.random.normal(key, (4, 6, 3))
    out = head(x)
    assert out.shape == (4, 6, 2)
    np.testing.assert_allclose(out[0, 0], [2.0, 0.5], rtol=1e-6)  # starts constant
    params = eqx.filter(head, eqx.is_inexact_array)
    assert (params.log_scale is not None) == learn_scale
    # Far from the start the precision never falls below the floor.
    far = eqx.tree_at(
        lambda h: h.mlp.layers[-1].bias,
        head,
        jnp.full_like(head.mlp.layers[-1].bias, -1e3),
    )
    np.testing.assert_allclose(far(x)[0, 0], [0.1, 0.2], rtol=1e-6)
    one = L.HeteroscedasticNoiseHead(4.0, 1, width=4, depth=1, key=key)
    assert one(jnp.ones((9, 1))).shape == (9,)


def test_head_gradients_match_finite_differences():
    key = jax.random.key(1)
    head = _head(2, 1, key, 0.1, learn_scale=True, dtype=jnp.float64)
    head = eqx.tree_at(
        lambda h: h.mlp.layers[-1].weight,
        head,
        0.3 * jax.random.normal(key, (2, 8), jnp.float64),
    )
    head = eqx.tree_at(lambda h: h.log_scale, head, head.log_scale.astype(jnp.float64))
    x = jax.random.normal(jax.random.key(2), (5, 2), jnp.float64)
    params, static = eqx.partition(head, eqx.is_inexact_array)
    flat, unravel = jax.flatten_util.ravel_pytree(params)

    def f(v):
        h = eqx.combine(unravel(v), static)
        return jnp.sum(jnp.log(h(x)) * jnp.arange(1.0, 11.0).reshape(5, 2))

    g = jax.grad(f)(flat)
    eps = 1e-6
    rng = np.random.default_rng(0)
    for i in rng.choice(flat.size, 12, replace=False):
        e = jnp.zeros_like(flat).at[i].set(eps)
        fd = (f(flat + e) - f(flat - e)) / (2 * eps)
        np.testing.assert_allclose(g[i], fd, rtol=1e-6, atol=1e-9)
