"""Marginal covariances against the dense inverse of JᵀJ."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


def _dense_blocks(lin):
    """Diagonal blocks of (JᵀJ)⁻¹ per group, with numpy."""
    from test_linear_solvers import _dense_jacobian

    J, _ = (np.asarray(a) for a in _dense_jacobian(lin))
    cov = np.linalg.inv(J.T @ J)
    out, start = {}, 0
    for g in lin.layout:
        for i in range(g.count):
            s = start + i * g.dim
            out.setdefault(g.name, []).append(cov[s : s + g.dim, s : s + g.dim])
        start += g.count * g.dim
    return {k: np.stack(v) for k, v in out.items()}


def test_chain_marginals_match_dense_inverse():
    from test_linear_solvers import _chain_lin

    import eqsmooth as eqs

    lin = _chain_lin(0)  # T = 6: reduction levels of even and odd sizes
    ref = _dense_blocks(lin)
    chain = eqs.marginal_covariances(lin)
    dense = eqs.marginal_covariances(lin, eqs.DenseCholesky())
    for name in ("p", "v"):
        assert chain[name].shape == (6, 2, 2)
        np.testing.assert_allclose(chain[name], ref[name], rtol=0, atol=1e-9)
        np.testing.assert_allclose(dense[name], ref[name], rtol=0, atol=1e-9)
        np.testing.assert_allclose(chain[name], np.swapaxes(chain[name], 1, 2))
    only_v = eqs.marginal_covariances(lin, eqs.BlockTridiagonal(), groups=("v",))
    assert set(only_v) == {"v"}
    np.testing.assert_allclose(only_v["v"], ref["v"], rtol=0, atol=1e-9)


def test_graph_marginals_use_dense_inverse():
    from test_linear_solvers import _loop_lin

    import eqsmooth as eqs

    lin = _loop_lin(0)
    ref = _dense_blocks(lin)
    cov = eqs.marginal_covariances(lin)
    for name in ("x", "l"):
        np.testing.assert_allclose(cov[name], ref[name], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="chain"):
        eqs.marginal_covariances(lin, eqs.BlockTridiagonal())
    with pytest.raises(ValueError, match="unknown groups"):
        eqs.marginal_covariances(lin, groups=("nope",))


def test_singular_marginals_raise():
    from test_linear_solvers import _gauge_free_chain

    import eqsmooth as eqs

    lin = _gauge_free_chain()
    # Every linear solver, per-variable and joint: the message alone (checked
    # on the host), naming the route and the missing prior. PCG used to stop
    # with finite garbage in some columns of the joint covariance.
    for solver in (None, eqs.PCG(), eqs.DenseCholesky()):
        with pytest.raises(eqx.EquinoxRuntimeError, match="prior") as info:
            eqs.marginal_covariances(lin, solver)
        assert str(info.value).startswith("marginal_covariances: the normal matrix")
        with pytest.raises(eqx.EquinoxRuntimeError, match="singular") as info:
            eqs.joint_marginal_covariance(lin, [("x", 0), ("x", 3)], solver)
        assert "Equinox" not in str(info.value)
    # float32: the message names the precision as a possible cause.
    lin32 = jax.tree_util.tree_map(
        lambda x: (
            x.astype(jnp.float32)
            if eqx.is_array(x) and jnp.issubdtype(x.dtype, jnp.floating)
            else x
        ),
        lin,
    )
    with pytest.raises(eqx.EquinoxRuntimeError, match="float32"):
        eqs.marginal_covariances(lin32)
