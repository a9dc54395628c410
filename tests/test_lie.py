"""Tests of eqsmooth.lie: properties (hypothesis), special angles, dtypes, batching.

Compilation dominates the run time, so each check is one jitted function per group
(the group class is a static argument) evaluated on a small batch.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from hypothesis import given, settings, strategies as st

import eqsmooth.lie as lie


GROUPS = [lie.SO2, lie.SE2, lie.SO3, lie.SE3]
# Where the rotation part sits in each tangent vector.
ROTATION_SLICE = {
    lie.SO2: slice(0, 1),
    lie.SE2: slice(2, 3),
    lie.SO3: slice(0, 3),
    lie.SE3: slice(3, 6),
}
PI = math.pi
# 1.9 and 2.1 straddle the float32 switch between Taylor series and closed forms.
SPECIAL_ANGLES = (
    *(0.0, 1e-12, 1e-8, 1e-4, 1.0, 1.9, 2.1),
    *(PI - 1e-4, PI - 1e-8, PI - 1e-9, PI),
)
FD_STEP = 1e-6
BATCH = 4


def _jit(fn):
    """Jit with the group class as static first argument. These tests are bound by
    compile time, which XLA's backend optimizations roughly double."""
    return jax.jit(
        fn, static_argnums=0, compiler_options={"xla_backend_optimization_level": 0}
    )


group_param = pytest.mark.parametrize("group", GROUPS, ids=lambda g: g.__name__)
prop_settings = settings(max_examples=25, deadline=None)
angle_strategy = st.one_of(
    st.sampled_from(SPECIAL_ANGLES), st.floats(0.0, PI, allow_nan=False)
)


def _tangents(group, rng, angles):
    """Random tangent vectors (numpy) whose rotation parts have norms `angles`.

    Inputs are drawn on the host: random number generation inside the jitted
    checks would dominate their compile time.
    """
    xi = rng.normal(size=(BATCH, group.tangent_dim))
    sl = ROTATION_SLICE[group]
    rot = xi[:, sl]
    angles = np.broadcast_to(np.asarray(angles, dtype=np.float64), (BATCH,))
    xi[:, sl] = rot / np.linalg.norm(rot, axis=-1, keepdims=True) * angles[:, None]
    return jnp.asarray(xi)


def _random_inputs(group, seed, angle):
    rng = np.random.default_rng(seed)
    return dict(
        xi=_tangents(group, rng, angle),
        a_xi=_tangents(group, rng, rng.uniform(0, PI, BATCH)),
        b_xi=_tangents(group, rng, rng.uniform(0, PI, BATCH)),
        # Interpolation steps alpha * near_xi, alpha in [-0.5, 1.5], stay below pi.
        near_xi=_tangents(group, rng, rng.uniform(0, 2.0, BATCH)),
        points=jnp.asarray(rng.normal(size=(BATCH, group.space_dim))),
        alphas=jnp.asarray(rng.uniform(-0.5, 1.5, BATCH)),
        angle=jnp.asarray(angle),
    )


def _fixed_tangents(group, angles, dtype=jnp.float64):
    """One tangent per angle: fixed rotation axis, fixed translation."""
    angles = jnp.asarray(angles, dtype)
    direction = jnp.asarray([1.0, -2.0, 3.0], dtype)[: group.tangent_dim]
    direction = direction[: ROTATION_SLICE[group].stop - ROTATION_SLICE[group].start]
    direction = direction / jnp.linalg.norm(direction)
    xi = jnp.broadcast_to(
        jnp.asarray([0.3, -0.2, 0.5, 0.1, 0.7, -0.4], dtype)[: group.tangent_dim],
        (angles.shape[0], group.tangent_dim),
    )
    return xi.at[:, ROTATION_SLICE[group]].set(angles[:, None] * direction[None])


def _max_abs(x):
    return jnp.max(jnp.abs(x))


def _fd_jacobian(f, x):
    """Central finite differences of `f: (*b, n) -> (*b, m)` at `x`, `(*b, m, n)`."""
    n = x.shape[-1]
    eye = jnp.eye(n, dtype=x.dtype)[None]
    xp = x[:, None, :] + FD_STEP * eye
    xm = x[:, None, :] - FD_STEP * eye
    return jnp.swapaxes((f(xp) - f(xm)) / (2 * FD_STEP), -1, -2)


def _apply_matrix(group, matrix, points):
    """Act on points with a (possibly homogeneous) matrix."""
    if group.matrix_dim > group.space_dim:
        ones = jnp.ones((*points.shape[:-1], 1), points.dtype)
        points = jnp.concatenate([points, ones], axis=-1)
    return (matrix @ points[..., None])[..., : group.space_dim, 0]


def _eye_batch(n, batch, dtype=jnp.float64):
    return jnp.broadcast_to(jnp.eye(n, dtype=dtype), (*batch, n, n))


# ------------------------------------------------------------ property checks


@_jit
def _check_algebra(group, inputs):
    xi, points = inputs["xi"], inputs["points"]
    g = group.exp(xi)
    a = group.exp(inputs["a_xi"])
    b = group.exp(inputs["b_xi"])
    ident = group.identity((BATCH,))
    m = lambda x: x.as_matrix()
    eye = _eye_batch(group.matrix_dim, (BATCH,))
    errors = {
        "exp_log_exp": _max_abs(m(group.exp(g.log())) - m(g)),
        "exp_log_random": _max_abs(m(group.exp(a.log())) - m(a)),
        "hat_vee": _max_abs(group.vee(group.hat(xi)) - xi),
        "left_identity": _max_abs(m(ident @ a) - m(a)),
        "right_identity": _max_abs(m(a @ ident) - m(a)),
        "inverse": _max_abs(m(a @ a.inverse()) - eye),
        "inverse_left": _max_abs(m(a.inverse() @ a) - eye),
        "associativity": _max_abs(m((a @ b) @ g) - m(a @ (b @ g))),
        "homomorphism": _max_abs(m(a @ b) - m(a) @ m(b)),
        "inverse_of_product": _max_abs(
            m((a @ b).inverse()) - m(b.inverse() @ a.inverse())
        ),
        "action": _max_abs((a @ b) @ points - a @ (b @ points)),
        "action_matrix": _max_abs(a @ points - _apply_matrix(group, m(a), points)),
        "from_matrix": _max_abs(m(group.from_matrix(m(a))) - m(a)),
        "normalize": _max_abs(m(a.normalize()) - m(a)),
        "adjoint": _max_abs(
            m(group.exp((a.adjoint() @ xi[..., None])[..., 0]))
            - m(a @ group.exp(xi) @ a.inverse())
        ),
    }
    if group in (lie.SO3, lie.SE3):
        # q and -q are the same rotation: log must not care which one it gets.
        flipped = group(a.parameters().at[:, :4].multiply(-1.0))
        errors["double_cover"] = _max_abs(flipped.log() - a.log())
    # log(exp(xi)) == xi away from the cut locus at pi.
    log_err = jnp.max(jnp.abs(g.log() - xi))
    errors["log_exp"] = jnp.where(inputs["angle"] < PI - 1e-6, log_err, 0.0)
    # Geodesic interpolation: end points, equal half steps, scaled tangent.
    c = a @ group.exp(inputs["near_xi"])
    mid = a.interpolate(c, 0.5)
    alphas = inputs["alphas"]
    errors["interp_start"] = _max_abs(m(a.interpolate(c, 0.0)) - m(a))
    errors["interp_end"] = _max_abs(m(a.interpolate(c, 1.0)) - m(c))
    errors["interp_mid"] = _max_abs(
        (a.inverse() @ mid).log() - (mid.inverse() @ c).log()
    )
    errors["interp_alpha"] = _max_abs(
        (a.inverse() @ a.interpolate(c, alphas)).log()
        - alphas[:, None] * inputs["near_xi"]
    )
    return errors


@_jit
def _check_jacobians(group, inputs):
    xi = inputs["xi"]
    d = group.tangent_dim
    g = group.exp(xi)
    eye = _eye_batch(d, (BATCH,))
    jr = group.right_jacobian(xi)
    jl = group.left_jacobian(xi)
    # exp(xi + delta) = exp(xi) exp(Jr delta) = exp(Jl delta) exp(xi)
    jr_fd = _fd_jacobian(lambda x: (g[:, None].inverse() @ group.exp(x)).log(), xi)
    jl_fd = _fd_jacobian(lambda x: (group.exp(x) @ g[:, None].inverse()).log(), xi)
    jlog_fd = _fd_jacobian(lambda x: (g[:, None] @ group.exp(x)).log(), 0 * xi)
    # The FD of log(g exp(delta)) would straddle the cut at angle pi.
    smooth = inputs["angle"] < PI - 1e-4
    return {
        "jr_fd": _max_abs(jr - jr_fd),
        "jl_fd": _max_abs(jl - jl_fd),
        "jr_inv": _max_abs(jr @ group.right_jacobian_inv(xi) - eye),
        "jl_inv": _max_abs(jl @ group.left_jacobian_inv(xi) - eye),
        "jl_is_jr_minus": _max_abs(jl - group.right_jacobian(-xi)),
        "jlog_fd": jnp.where(smooth, _max_abs(g.jlog() - jlog_fd), 0.0),
    }


def _assert_small(errors, tol):
    bad = {k: float(v) for k, v in errors.items() if not float(v) <= tol}
    assert not bad, bad


@group_param
@pytest.mark.parametrize(
    "check, tol",
    [(_check_algebra, 1e-9), (_check_jacobians, 1e-7)],
    ids=["algebra", "jacobians"],
)
@prop_settings
@given(seed=st.integers(0, 2**32 - 1), angle=angle_strategy)
def test_properties(group, check, tol, seed, angle):
    """The algebra's identities to 1e-9 and the Jacobians to 1e-7."""
    _assert_small(check(group, _random_inputs(group, seed, angle)), tol)


# ---------------------------------------------------- special angles and gradients


@_jit
def _special_angle_derivatives(group, xi):
    """Values and derivatives of exp, log, jlog and the Jacobians at each `xi`."""
    d = group.tangent_dim
    g = group.exp(xi)
    params = g.parameters()
    weights = jnp.linspace(0.5, 1.5, d)

    def log_loss(p):
        return group(p).log() @ weights

    def exp_params(x):
        return group.exp(x).as_matrix()

    out = {
        "log": g.log(),
        "matrix": g.as_matrix(),
        "exp_log": group.exp(g.log()).as_matrix(),
        "hat": group.hat(xi),
        "jlog": g.jlog(),
        "exp_jac": jax.vmap(jax.jacfwd(exp_params))(xi),
        "exp_jac_fd": _fd_jacobian(
            lambda x: exp_params(x).reshape(*x.shape[:-1], -1), xi
        ).reshape(xi.shape[0], group.matrix_dim, group.matrix_dim, d),
        "log_grad": jax.vmap(jax.grad(log_loss))(params),
        "log_grad_fd": _fd_jacobian(
            lambda p: (group(p).log() @ weights)[..., None], params
        )[:, 0, :],
        "log_jac_tangent": jax.vmap(
            lambda gi: jax.jacfwd(lambda x: (gi @ group.exp(x)).log())(jnp.zeros(d))
        )(g),
        "jlog_grad": jax.vmap(jax.grad(lambda p: jnp.sum(group(p).jlog())))(params),
        "jlog_grad_fd": _fd_jacobian(
            lambda p: jnp.sum(group(p).jlog(), axis=(-1, -2))[..., None], params
        )[:, 0, :],
    }
    # left_jacobian(xi) is right_jacobian(-xi), checked by test_properties[jacobians].
    for name in ("right_jacobian", "right_jacobian_inv"):
        fn = getattr(group, name)
        out[name + "_jac"] = jax.vmap(jax.jacfwd(fn))(xi)
        out[name + "_jac_fd"] = _fd_jacobian(
            lambda x: fn(x).reshape(*x.shape[:-1], -1), xi
        ).reshape(xi.shape[0], d, d, d)
    return out


@group_param
def test_special_angles(group):
    angles = jnp.asarray(SPECIAL_ANGLES)
    xi = _fixed_tangents(group, angles)
    out = _special_angle_derivatives(group, xi)
    for name, value in out.items():
        assert bool(jnp.all(jnp.isfinite(value))), name
    # log(exp(xi)) == xi up to the cut at exactly pi, where only exp(log(g)) == g.
    np.testing.assert_allclose(out["log"][:-1], xi[:-1], atol=1e-12)
    np.testing.assert_allclose(out["exp_log"], out["matrix"], atol=1e-12)
    expm = np.stack([scipy.linalg.expm(h) for h in np.asarray(out["hat"])])
    np.testing.assert_allclose(out["matrix"], expm, atol=1e-12)
    # Autodiff through log(g exp(delta)) agrees with the closed-form jlog.
    np.testing.assert_allclose(out["log_jac_tangent"], out["jlog"], atol=1e-9)
    # exp and the Jacobian helpers are smooth at all these angles.
    np.testing.assert_allclose(out["exp_jac"], out["exp_jac_fd"], atol=1e-7)
    for name in ("right_jacobian", "right_jacobian_inv"):
        np.testing.assert_allclose(
            out[name + "_jac"], out[name + "_jac_fd"], atol=1e-7, err_msg=name
        )
    # log (and so jlog) is discontinuous at pi: compare with FD only away from it.
    smooth = np.asarray(angles) < PI - 1e-4
    np.testing.assert_allclose(
        out["log_grad"][smooth], out["log_grad_fd"][smooth], atol=1e-7
    )
    np.testing.assert_allclose(
        out["jlog_grad"][smooth], out["jlog_grad_fd"][smooth], atol=1e-6
    )


@_jit
def _unnormalized(group, xi, scale):
    g = group.exp(xi)
    params = g.parameters()
    n_rot = 2 if group in (lie.SO2, lie.SE2) else 4
    scaled = group(params.at[:, :n_rot].multiply(scale))
    weights = jnp.linspace(0.5, 1.5, group.tangent_dim)
    grads = jax.vmap(
        jax.grad(lambda p: (group(p).log() @ weights) + jnp.sum(group(p).jlog()))
    )(scaled.parameters())
    return g.log(), scaled.log(), g.jlog(), scaled.jlog(), grads


@group_param
@pytest.mark.parametrize("scale", [1 + 1e-6, 1 - 1e-6, 1.01])
def test_unnormalized_inputs(group, scale):
    angles = jnp.asarray([0.0, 1e-6, 1.0, PI - 1e-8])
    xi = _fixed_tangents(group, angles)
    log, log_scaled, jlog, jlog_scaled, grads = _unnormalized(group, xi, scale)
    np.testing.assert_allclose(log_scaled, log, atol=1e-12)
    np.testing.assert_allclose(jlog_scaled, jlog, atol=1e-12)
    assert bool(jnp.all(jnp.isfinite(grads)))


# --------------------------------------------------------- dtypes and batching


def _all_outputs(group, key, batch, dtype):
    k1, k2, k3 = jax.random.split(key, 3)
    xi = jax.random.normal(k1, (*batch, group.tangent_dim), dtype)
    g = group.exp(xi)
    h = group.sample_uniform(k2, batch, dtype)
    points = jax.random.normal(k3, (*batch, group.space_dim), dtype)
    return {
        "identity": group.identity(batch, dtype).parameters(),
        "exp": g.parameters(),
        "sample": h.parameters(),
        "log": g.log(),
        "inverse": g.inverse().parameters(),
        "compose": (g @ h).parameters(),
        "apply": g @ points,
        "adjoint": g.adjoint(),
        "as_matrix": g.as_matrix(),
        "from_matrix": group.from_matrix(g.as_matrix()).parameters(),
        "normalize": g.normalize().parameters(),
        "jlog": g.jlog(),
        "hat": group.hat(xi),
        "vee": group.vee(group.hat(xi)),
        "jr": group.right_jacobian(xi),
        "jr_inv": group.right_jacobian_inv(xi),
        "jl": group.left_jacobian(xi),
        "jl_inv": group.left_jacobian_inv(xi),
        "interpolate": g.interpolate(h, 0.3).parameters(),
        "exp_grad": jax.grad(lambda x: jnp.sum(group.exp(x).parameters()))(xi),
        "log_grad": jax.grad(lambda p: jnp.sum(group(p).log()))(g.parameters()),
    }


@group_param
@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_dtype_and_batch_shape(group, dtype, getkey):
    # Shapes and dtypes only: abstract evaluation traces without compiling.
    batch = (2, 3)
    out = eqx.filter_eval_shape(_all_outputs, group, getkey(), batch, dtype)
    d, n, p = group.tangent_dim, group.matrix_dim, group.parameters_dim
    s = group.space_dim
    shapes = {
        "log": (d,),
        "apply": (s,),
        "adjoint": (d, d),
        "as_matrix": (n, n),
        "jlog": (d, d),
        "hat": (n, n),
        "vee": (d,),
        "jr": (d, d),
        "jr_inv": (d, d),
        "jl": (d, d),
        "jl_inv": (d, d),
        "exp_grad": (d,),
        "log_grad": (p,),
    }
    for name, value in out.items():
        assert value.dtype == dtype, name
        assert value.shape == batch + shapes.get(name, (p,)), name


@_jit
def _float32_special(group, xi):
    g = group.exp(xi)
    weights = jnp.linspace(0.5, 1.5, group.tangent_dim, dtype=xi.dtype)
    params = g.parameters()
    return {
        "log": g.log(),
        "jlog": g.jlog(),
        "log_grad": jax.vmap(jax.grad(lambda p: group(p).log() @ weights))(params),
        "jlog_grad": jax.vmap(jax.grad(lambda p: jnp.sum(group(p).jlog())))(params),
        "right_jacobian_inv_jac": jax.vmap(jax.jacfwd(group.right_jacobian_inv))(xi),
    }


@group_param
def test_float32_special_angles(group):
    angles = np.asarray(SPECIAL_ANGLES)
    out32 = _float32_special(group, _fixed_tangents(group, angles, jnp.float32))
    out64 = _special_angle_derivatives(group, _fixed_tangents(group, angles))
    # float32(pi - 1e-8) rounds to float32(pi) > pi, on the other side of the cut.
    below_pi = angles < PI - 1e-5
    for name, value in out32.items():
        assert value.dtype == jnp.float32, name
        assert bool(jnp.all(jnp.isfinite(value))), name
        np.testing.assert_allclose(
            value[below_pi], out64[name][below_pi], atol=5e-5, rtol=1e-4, err_msg=name
        )


@group_param
def test_batch_broadcasting_and_indexing(group):
    rng = np.random.default_rng(0)
    g = group.exp(jnp.asarray(rng.normal(size=(2, 3, group.tangent_dim))))
    single = group.exp(jnp.asarray(rng.normal(size=(group.tangent_dim,))))
    points = jnp.asarray(rng.normal(size=(5, group.space_dim)))
    s = group.space_dim

    def shapes(g, single, points):
        return (
            (g @ single).parameters(),
            (single @ g).parameters(),
            single @ points,
            g[:, :, None] @ points,
            g[np.array([0, 1, 1])].parameters(),
        )

    out = [x.shape for x in eqx.filter_eval_shape(shapes, g, single, points)]
    p = group.parameters_dim
    assert out == [(2, 3, p), (2, 3, p), (5, s), (2, 3, 5, s), (3, 3, p)]
    assert g.batch_shape == (2, 3)
    np.testing.assert_allclose(g[1, 2].parameters(), g.parameters()[1, 2])
    np.testing.assert_allclose(g[..., 0].parameters(), g.parameters()[:, 0])
    # vmap over a group agrees with the batched call.
    np.testing.assert_allclose(
        jax.jit(jax.vmap(jax.vmap(lambda x: x.log())))(g), g.log(), atol=1e-12
    )


@group_param
def test_sample_uniform(group, getkey):
    g = group.sample_uniform(getkey(), (500,), jnp.float32)
    assert g.batch_shape == (500,) and g.dtype == jnp.float32
    np.testing.assert_allclose(g.normalize().parameters(), g.parameters(), atol=1e-6)
    # Haar measure: the rotation block averages to zero.
    s = group.space_dim
    mean = jnp.mean(g.as_matrix()[:, :s, :s], axis=0)
    assert float(jnp.max(jnp.abs(mean))) < 0.15


def test_invalid_inputs():
    with pytest.raises((ValueError, TypeError)):
        lie.SO3(jnp.ones((2, 3)))
    with pytest.raises(TypeError):
        _ = lie.SO2.identity() @ lie.SO3.identity()


def test_named_constructors():
    np.testing.assert_allclose(lie.SO2.from_radians(0.3).as_radians(), 0.3)
    assert lie.SE2.from_xy_theta(1, 2, 0).dtype == lie.SE2.identity().dtype
    pose = lie.SE2.from_xy_theta(1.0, 2.0, 0.3)
    np.testing.assert_allclose(pose.translation(), jnp.array([1.0, 2.0]))
    np.testing.assert_allclose(pose.rotation().as_radians(), 0.3)
    rotation = lie.SO3.from_rpy_radians(0.1, -0.2, 0.3)
    expected = (
        lie.SO3.from_z_radians(0.3).as_matrix()
        @ lie.SO3.from_y_radians(-0.2).as_matrix()
        @ lie.SO3.from_x_radians(0.1).as_matrix()
    )
    np.testing.assert_allclose(rotation.as_matrix(), expected, atol=1e-12)
    t = jnp.array([1.0, 2.0, 3.0])
    pose3 = lie.SE3.from_rotation_and_translation(rotation, t)
    np.testing.assert_allclose(pose3.translation(), t)
    np.testing.assert_allclose(pose3.rotation().wxyz, rotation.wxyz)
    assert lie.SE3.tangent_dim == 6 and lie.SE3.parameters_dim == 7
    assert lie.SE3.matrix_dim == 4 and lie.SE3.space_dim == 3
