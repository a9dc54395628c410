"""Range, bearing, bearing-range, translation-prior and pose-to-point factors:
residual values against hand computations, Jacobians against float64 central
finite differences in tangent coordinates, and behaviour at the singular
points (zero distance, angles across ±π)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


def _se2(x, y, th):
    import eqsmooth as eqs

    return eqs.SE2.from_xy_theta(jnp.array([x]), jnp.array([y]), jnp.array([th]))


def _se3(key):
    import eqsmooth as eqs

    return eqs.SE3.exp(0.7 * jax.random.normal(key, (1, 6)))


@eqx.filter_jit
def _residual(factor, *states):
    return factor.residual(*states)


def _fd_jacobians(factor, states, h=1e-6):
    """Central differences of the one-row residual in tangent coordinates."""
    from eqsmooth.factors import per_row_fields, with_rows
    from eqsmooth.manifold import retract, tangent_dim

    row = jax.tree_util.tree_map(lambda a: a[0], per_row_fields(factor))
    factor = with_rows(factor, row)
    out = []
    for k, x in enumerate(states):
        d = tangent_dim(x, batch_ndim=1)
        cols = []
        for i in range(d):
            e = jnp.zeros((1, d)).at[0, i].set(h)
            plus = list(states)
            minus = list(states)
            plus[k] = retract(x, e)
            minus[k] = retract(x, -e)
            rp = _residual(
                factor, *[jax.tree_util.tree_map(lambda a: a[0], s) for s in plus]
            )
            rm = _residual(
                factor, *[jax.tree_util.tree_map(lambda a: a[0], s) for s in minus]
            )
            cols.append((rp - rm) / (2 * h))
        out.append(jnp.stack(cols, axis=-1))
    return out


def _check_jacobians(factor, states, atol=1e-6):
    from eqsmooth.factors._factor import linearize_rows

    # Both sides compiled: op by op, each new factor type costs hundreds of
    # small compilations.
    r, jacs = eqx.filter_jit(linearize_rows)(factor, tuple(states))
    assert np.all(np.isfinite(np.asarray(r)))
    ref = _fd_jacobians(factor, states)
    for j, jr in zip(jacs, ref):
        assert np.all(np.isfinite(np.asarray(j)))
        np.testing.assert_allclose(np.asarray(j[0]), jr, rtol=1e-6, atol=atol)
    return np.asarray(r[0])


def _noise(m):
    import eqsmooth as eqs

    return eqs.DiagonalNoise(sqrt_precision=jnp.ones(m))


def test_bearing_range_2d_values_and_jacobians():
    import eqsmooth as eqs

    pose = _se2(1.0, 2.0, 0.3)
    point = jnp.array([[4.0, 6.0]])
    local = np.array([3.0, 4.0])
    c, s = np.cos(0.3), np.sin(0.3)
    local = np.array([c * local[0] + s * local[1], -s * local[0] + c * local[1]])
    bearing = np.arctan2(local[1], local[0])
    p, lv = eqs.Var("x", [0]), eqs.Var("l", [0])
    f = eqs.BearingRangeFactor(
        p, lv, jnp.array([bearing - 0.1]), jnp.array([4.5]), _noise(2)
    )
    r = _check_jacobians(f, [pose, point])
    np.testing.assert_allclose(r, [0.1, 0.5], atol=1e-12)
    fb = eqs.BearingFactor(p, lv, jnp.array([bearing + 0.2]), _noise(1))
    np.testing.assert_allclose(_check_jacobians(fb, [pose, point]), [-0.2], atol=1e-12)
    fr = eqs.RangeFactor(p, lv, jnp.array([5.5]), _noise(1))
    np.testing.assert_allclose(_check_jacobians(fr, [pose, point]), [-0.5], atol=1e-12)


@pytest.mark.parametrize("theta", [np.pi - 1e-3, -np.pi + 1e-3, np.pi])
def test_bearing_wraps_across_pi(theta):
    """A landmark straight behind the pose, measured just across ±π: the
    residual is small and its derivative continuous (no 2π jump)."""
    import eqsmooth as eqs

    pose = _se2(0.0, 0.0, 0.0)
    point = jnp.array([[np.cos(theta), np.sin(theta)]]) * 3.0
    measured = -theta if abs(theta) < np.pi else np.pi - 1e-4
    f = eqs.BearingFactor(
        eqs.Var("x", [0]), eqs.Var("l", [0]), jnp.array([measured]), _noise(1)
    )
    r = _check_jacobians(f, [pose, point])
    assert abs(r[0]) < 3e-3


def test_range_at_zero_distance_has_no_derivative():
    """The documented rule: at zero distance the distance has no derivative and
    the Jacobian is NaN (a zero would make a landmark on its observer a false
    stationary point), so a solve from there fails and names the factor."""
    import eqsmooth as eqs
    from eqsmooth.factors._factor import linearize_rows

    pose = _se2(1.0, 2.0, 0.3)
    point = jnp.array([[1.0, 2.0]])
    f = eqs.RangeFactor(
        eqs.Var("x", [0]), eqs.Var("l", [0]), jnp.array([1.0]), _noise(1)
    )
    r, (jx, jl) = eqx.filter_jit(linearize_rows)(f, (pose, point))
    np.testing.assert_allclose(np.asarray(r), [[-1.0]])
    assert np.all(np.isnan(np.asarray(jl)))
    g = jax.grad(lambda q: f.residual(pose[0], q)[0])(point[0])
    assert np.all(np.isnan(np.asarray(g)))
    # Away from zero distance the derivative is the unit direction.
    g = jax.grad(lambda q: f.residual(pose[0], q)[0])(point[0] + jnp.array([0.6, 0.8]))
    np.testing.assert_allclose(np.asarray(g), [0.6, 0.8], atol=1e-12)


def test_3d_factors_jacobians(getkey):
    import eqsmooth as eqs

    pose = _se3(getkey())
    point = jnp.array([[1.5, -0.7, 2.0]])
    local = np.asarray(pose[0].inverse().apply(point[0]))
    u = local / np.linalg.norm(local)
    # A measured direction a little off the predicted one.
    m = u + np.array([0.05, -0.03, 0.02])
    m = m / np.linalg.norm(m)
    x, lv = eqs.Var("x", [0]), eqs.Var("l", [0])
    fb = eqs.BearingFactor(x, lv, jnp.array([m]), _noise(2))
    r = _check_jacobians(fb, [pose, point])
    angle = np.arccos(np.clip(np.dot(m, u), -1, 1))
    np.testing.assert_allclose(np.linalg.norm(r), angle, rtol=1e-9)
    fbr = eqs.BearingRangeFactor(x, lv, jnp.array([m]), jnp.array([2.0]), _noise(3))
    r = _check_jacobians(fbr, [pose, point])
    np.testing.assert_allclose(r[2], np.linalg.norm(local) - 2.0, atol=1e-12)
    fp = eqs.PoseToPointFactor(x, lv, jnp.array([local + 0.1]), _noise(3))
    np.testing.assert_allclose(_check_jacobians(fp, [pose, point]), -0.1, atol=1e-12)
    fg = eqs.TranslationPriorFactor(x, jnp.array([[0.1, 0.2, 0.3]]), _noise(3))
    t = np.asarray(pose.translation()[0])
    np.testing.assert_allclose(
        _check_jacobians(fg, [pose]), t - np.array([0.1, 0.2, 0.3]), atol=1e-12
    )
    fr = eqs.RangeFactor(x, eqs.Var("x", [0]), jnp.array([1.0]), _noise(1))
    _check_jacobians(fr, [pose, _se3(getkey())])


def test_3d_bearing_at_measured_direction():
    """The residual is zero, with finite Jacobians, when prediction = measurement."""
    import eqsmooth as eqs
    from eqsmooth.factors._factor import linearize_rows

    pose = eqs.SE3.identity((1,), dtype=jnp.float64)
    point = jnp.array([[0.0, 0.0, 2.0]])
    f = eqs.BearingFactor(
        eqs.Var("x", [0]), eqs.Var("l", [0]), jnp.array([[0.0, 0.0, 1.0]]), _noise(2)
    )
    r, jacs = eqx.filter_jit(linearize_rows)(f, (pose, point))
    np.testing.assert_allclose(np.asarray(r), 0.0, atol=1e-15)
    ref = _fd_jacobians(f, [pose, point])
    for j, jr in zip(jacs, ref):
        np.testing.assert_allclose(np.asarray(j[0]), jr, atol=1e-6)


def test_3d_bearings_are_normalised_and_zero_ones_refused():
    # (0, 0, 2) was taken as a unit vector: the angle to a point 45° off read
    # 26.6°. Directions are normalised (GTSAM's Unit3); zero / NaN ones raise.
    import eqsmooth as eqs

    pose = eqs.SE3.identity((1,), dtype=jnp.float64)
    for cls, extra in (
        (eqs.BearingFactor, ()),
        (eqs.BearingRangeFactor, (jnp.ones(1),)),
    ):
        f = cls(
            eqs.Var("x", [0]),
            eqs.Var("l", [0]),
            jnp.array([[0.0, 0.0, 2.0]]),
            *extra,
            _noise(2 + len(extra)),
        )
        np.testing.assert_allclose(np.asarray(f.bearing), [[0.0, 0.0, 1.0]])
        graph = eqs.FactorGraph([f])
        r = graph.residuals({"x": pose, "l": jnp.array([[1.0, 0.0, 1.0]])})[0][0]
        np.testing.assert_allclose(float(jnp.linalg.norm(r[:2])), np.pi / 4, rtol=1e-12)
        for bad in ([[0.0, 0.0, 0.0]], [[np.nan, 0.0, 1.0]]):
            with pytest.raises(
                ValueError, match=f"{cls.__name__}.bearing: rows \\[0\\]"
            ):
                cls(
                    eqs.Var("x", [0]),
                    eqs.Var("l", [0]),
                    jnp.array(bad),
                    *extra,
                    _noise(2 + len(extra)),
                )


def test_pose2_accessors():
    pose = _se2(1.5, -2.0, 3.0)
    np.testing.assert_allclose(np.asarray(pose.x()), [1.5])
    np.testing.assert_allclose(np.asarray(pose.y()), [-2.0])
    np.testing.assert_allclose(np.asarray(pose.theta()), [3.0])


def test_shape_errors_name_the_factor():
    import eqsmooth as eqs

    # The jaxtyping hook (a TypeError) or our own check (a ValueError).
    with pytest.raises((ValueError, TypeError), match="range"):
        eqs.RangeFactor(
            eqs.Var("x", [0]), eqs.Var("l", [0]), jnp.zeros((1, 2)), _noise(1)
        )
    with pytest.raises(ValueError, match="BearingFactor.bearing"):
        eqs.BearingFactor(
            eqs.Var("x", [0]), eqs.Var("l", [0]), jnp.zeros((1, 2)), _noise(1)
        )
    f = eqs.PoseToPointFactor(
        eqs.Var("x", [0]), eqs.Var("l", [0]), jnp.zeros((1, 3)), _noise(3)
    )
    with pytest.raises(ValueError, match="PoseToPointFactor"):
        f.residual(_se2(0.0, 0.0, 0.0)[0], jnp.zeros(3))


def test_planar_slam_recovers_truth():
    """Three poses, two landmarks, exact odometry and bearing-range: the
    solution is the ground truth (self-contained, no GTSAM)."""
    import eqsmooth as eqs

    truth = eqs.SE2.from_xy_theta(
        jnp.array([0.0, 2.0, 4.0]),
        jnp.array([0.0, 0.0, 0.0]),
        jnp.array([0.0, 0.0, 0.0]),
    )
    lms = jnp.array([[2.0, 2.0], [4.0, 2.0]])
    pairs = [(0, 0), (1, 0), (2, 1)]
    xi = np.array([p for p, _ in pairs])
    li = np.array([q for _, q in pairs])
    local = jax.vmap(lambda p, q: p.inverse().apply(q))(truth[xi], lms[li])
    bearing = jnp.arctan2(local[:, 1], local[:, 0])
    rng = jnp.linalg.norm(local, axis=1)
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(eqs.Var("x", [0]), truth[:1], _noise(3)),
            eqs.BetweenFactor(
                eqs.Var("x", [0, 1]),
                eqs.Var("x", [1, 2]),
                truth[:2].inverse() @ truth[1:],
                _noise(3),
            ),
            eqs.BearingRangeFactor(
                eqs.Var("x", xi),
                eqs.Var("l", li),
                bearing,
                rng,
                eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.2])),
            ),
        ]
    )
    start = {
        "x": eqs.SE2.from_xy_theta(
            jnp.array([0.3, 2.2, 3.9]),
            jnp.array([-0.2, 0.1, 0.2]),
            jnp.array([0.1, -0.1, 0.05]),
        ),
        "l": lms + jnp.array([[0.3, -0.2], [-0.1, 0.3]]),
    }
    sol = eqs.least_squares(graph, start, eqs.LevenbergMarquardt())
    np.testing.assert_allclose(np.asarray(sol.value["l"]), np.asarray(lms), atol=1e-8)
    np.testing.assert_allclose(
        np.asarray(sol.value["x"].parameters()),
        np.asarray(truth.parameters()),
        atol=1e-8,
    )
