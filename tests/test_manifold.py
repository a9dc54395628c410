import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st


def _mixed_state(seed: int, batch=()):
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    return {
        "pose": eqs.SE2.exp(jnp.asarray(rng.normal(size=batch + (3,)))),
        "rot": eqs.SO3.exp(jnp.asarray(rng.normal(size=batch + (3,)))),
        "vel": jnp.asarray(rng.normal(size=batch + (2,))),
        "bias": (jnp.asarray(rng.normal(size=batch + (2, 2))),),
    }


def test_tangent_dims():
    import eqsmooth as eqs

    x = _mixed_state(0)
    # flattening order of dict keys: bias, pose, rot, vel
    assert eqs.manifold.tangent_dims(x) == (4, 3, 3, 2)
    assert eqs.manifold.tangent_dim(x) == 12
    xb = _mixed_state(0, batch=(5,))
    assert eqs.manifold.tangent_dim(xb, batch_ndim=1) == 12
    with pytest.raises(TypeError, match="floating-point"):
        eqs.manifold.tangent_dim({"i": jnp.arange(3)})


@settings(max_examples=20, deadline=None)
@given(st.integers(0, 2**16))
def test_retract_local_round_trip(seed):
    x = _mixed_state(seed, batch=(3,))
    y = _mixed_state(seed + 1, batch=(3,))
    delta = 0.1 * jnp.asarray(np.random.default_rng(seed).normal(size=(3, 12)))
    d, y2, back = _round_trips(x, y, delta)
    assert d.shape == (3, 12)
    # compare groups by matrices (quaternion sign ambiguity)
    np.testing.assert_allclose(y2["pose"].as_matrix(), y["pose"].as_matrix(), atol=1e-9)
    np.testing.assert_allclose(y2["rot"].as_matrix(), y["rot"].as_matrix(), atol=1e-9)
    np.testing.assert_allclose(y2["vel"], y["vel"], atol=1e-12)
    np.testing.assert_allclose(y2["bias"][0], y["bias"][0], atol=1e-12)
    # small δ: local(x, retract(x, δ)) == δ
    np.testing.assert_allclose(back, delta, atol=1e-9)


@jax.jit  # one program for all examples, not each Lie-group operation alone
def _round_trips(x, y, delta):
    import eqsmooth as eqs

    d = eqs.local(x, y, batch_ndim=1)
    back = eqs.local(x, eqs.retract(x, delta), batch_ndim=1)
    return d, eqs.retract(x, d), back


def test_retract_checks_dimension():
    import eqsmooth as eqs

    with pytest.raises(ValueError, match="tangent dimension 12"):
        eqs.retract(_mixed_state(0), jnp.zeros(5))


def test_retract_is_differentiable():
    import eqsmooth as eqs

    x = _mixed_state(3)
    f = lambda d: eqs.local(x, eqs.retract(x, d))  # noqa: E731
    J = jax.jit(jax.jacfwd(f))(jnp.zeros(12))
    np.testing.assert_allclose(J, np.eye(12), atol=1e-9)
