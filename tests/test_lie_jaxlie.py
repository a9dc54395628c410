"""Cross-check eqsmooth.lie against jaxlie (same parameter and tangent layouts)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import eqsmooth.lie as lie


jaxlie = pytest.importorskip("jaxlie")

PAIRS = [
    (lie.SO2, "SO2"),
    (lie.SE2, "SE2"),
    (lie.SO3, "SO3"),
    (lie.SE3, "SE3"),
]
ROTATION_SLICE = {
    lie.SO2: slice(0, 1),
    lie.SE2: slice(2, 3),
    lie.SO3: slice(0, 3),
    lie.SE3: slice(3, 6),
}
BATCH = 8


def _tangents(group, rng):
    # Rotation angles below pi, so both libraries pick the same logarithm.
    xi = rng.normal(size=(BATCH, group.tangent_dim))
    sl = ROTATION_SLICE[group]
    rot = xi[:, sl]
    angles = rng.uniform(0.0, np.pi - 0.1, size=(BATCH, 1))
    xi[:, sl] = rot / np.linalg.norm(rot, axis=-1, keepdims=True) * angles
    return jnp.asarray(xi)


def _compare(group, theirs_cls, xi, xi2, points):
    ours_a, ours_b = group.exp(xi), group.exp(xi2)
    theirs_a, theirs_b = theirs_cls.exp(xi), theirs_cls.exp(xi2)
    ours_matrix = ours_a.as_matrix()
    theirs_matrix = theirs_a.as_matrix()
    return {
        "exp": (ours_a.parameters(), theirs_a.parameters()),
        "as_matrix": (ours_matrix, theirs_matrix),
        "log": (group(theirs_b.parameters()).log(), theirs_b.log()),
        "compose": (
            (ours_a @ ours_b).parameters(),
            (theirs_a @ theirs_b).parameters(),
        ),
        "inverse": (ours_a.inverse().parameters(), theirs_a.inverse().parameters()),
        "apply": (ours_a @ points, theirs_a @ points),
        "adjoint": (ours_a.adjoint(), theirs_a.adjoint()),
        "from_matrix": (
            group.from_matrix(theirs_matrix).as_matrix(),
            theirs_cls.from_matrix(ours_matrix).as_matrix(),
        ),
        "jlog": (ours_a.jlog(), theirs_a.jlog()),
    }


@pytest.mark.parametrize("group, name", PAIRS, ids=[name for _, name in PAIRS])
def test_matches_jaxlie(group, name):
    rng = np.random.default_rng(0)
    xi, xi2 = _tangents(group, rng), _tangents(group, rng)
    points = jnp.asarray(rng.normal(size=(BATCH, group.space_dim)))
    # jaxlie relies on implicit rank and dtype promotion.
    with jax.numpy_rank_promotion("allow"), jax.numpy_dtype_promotion("standard"):
        out = jax.jit(_compare, static_argnums=(0, 1))(
            group, getattr(jaxlie, name), xi, xi2, points
        )
    for key, (ours, theirs) in out.items():
        assert ours.dtype == jnp.float64, key
        np.testing.assert_allclose(ours, theirs, atol=1e-9, err_msg=key)
