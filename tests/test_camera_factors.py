"""Camera factors: calibrations, pinhole and stereo projection.

Closed-form Jacobians against autodiff; pixels, residuals and Jacobians
against GTSAM (`PinholeCameraCal3_S2`/`Cal3DS2.project` with their H
matrices, `GenericProjectionFactor`, `StereoCamera`, `GenericStereoFactor3D`)
when it is installed; cheirality (points behind a camera are flagged and
inert, or raise); gradients w.r.t. the intrinsics and the camera mount
through a solve against float64 central differences in tangent coordinates;
and a small bundle adjustment solved by Levenberg-Marquardt (and by GTSAM,
for parity).
"""

import functools
import importlib.util

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


GTSAM_REASON = "GTSAM parity checks need gtsam (the `bench` extra)"
DS2 = (500.0, 510.0, 0.1, 320.0, 240.0, 0.1, -0.05, 0.001, 0.002)
S2 = (500.0, 510.0, 0.1, 320.0, 240.0)
STEREO = (500.0, 510.0, 320.0, 240.0, 0.3)


@functools.cache
def _scene(n=24, seed=0):
    """`n` random camera poses (camera-to-world) and points 2-6 m in front."""
    import eqsmooth as eqs

    rng = np.random.default_rng(seed)
    tangent = rng.normal(size=(n, 6)) * [1, 1, 1, 0.5, 0.5, 0.5]
    local = np.column_stack(
        [rng.uniform(-1, 1, n), rng.uniform(-1, 1, n), rng.uniform(2, 6, n)]
    )

    @eqx.filter_jit
    def make(tangent, local):
        poses = eqs.SE3.exp(tangent)
        return poses, poses.apply(local)

    return make(jnp.asarray(tangent), jnp.asarray(local))


def _body():
    import eqsmooth as eqs

    return eqs.SE3.exp(jnp.array([0.1, -0.05, 0.2, 0.02, -0.1, 0.05]))


def _factor(kind, n, measured=None, body=None, **kw):
    import eqsmooth as eqs

    if kind == "stereo":
        cls, cal, width = eqs.StereoProjectionFactor, eqs.Cal3_S2Stereo(*STEREO), 3
    else:
        cls, width = eqs.ProjectionFactor, 2
        cal = eqs.Cal3_S2(*S2) if kind == "s2" else eqs.Cal3DS2(*DS2)
    rows = np.arange(n)
    return cls(
        eqs.Var("x", rows),
        eqs.Var("l", rows),
        jnp.zeros((n, width)) if measured is None else measured,
        eqs.IsotropicNoise.from_sigma(1.0),
        cal,
        body_P_sensor=body,
        **kw,
    )


@eqx.filter_jit
def _linearized(factor, poses, points):
    """Rows' residuals and closed-form Jacobians (the solver's linearisation)."""
    from eqsmooth.factors._factor import linearize_rows

    r, (jp, jl) = linearize_rows(factor, (poses, points))
    return r, jp, jl


@eqx.filter_jit
def _autodiff(factor, poses, points):
    """Rows' Jacobians by forward autodiff of `residual` in tangent
    coordinates, `(n, m, 6 + 3)`: `∂ r(pose ⊕ δ, point + ε) / ∂(δ, ε)` at 0.

    `pose ⊕ δ` is taken as `(q ⊗ (1, ω/2), t + R v)`, which agrees with
    `pose · exp(δ)` to first order (SE3 applies an unnormalised quaternion
    as the rotation it represents), so the derivative is the same and its
    program compiles in a fraction of the time of `exp`'s."""
    import eqsmooth as eqs
    from eqsmooth.factors._factor import _row_axes

    def one(f, pose, point):
        def res(d):
            v, w = d[:3], d[3:6]
            dq = eqs.SO3(jnp.concatenate([jnp.ones(1), 0.5 * w]), check=False)
            rot = eqs.SO3(pose.rotation().compose(dq).wxyz, check=False)
            moved = eqs.SE3(
                jnp.concatenate(
                    [rot.wxyz, pose.translation() + pose.rotation().apply(v)]
                ),
                check=False,
            )
            return f.residual(moved, point + d[6:])

        return jax.jacfwd(res)(jnp.zeros(9))

    return eqx.filter_vmap(one, in_axes=(_row_axes(factor), 0, 0))(
        factor, poses, points
    )


@pytest.mark.parametrize("kind", ["s2", "ds2", "stereo"])
def test_closed_form_jacobians_match_autodiff(kind):
    """On a mounted camera (`body_P_sensor`; the unmounted path is the same
    without the final adjoint, and is checked against GTSAM below)."""
    poses, points = _scene()
    f = _factor(kind, 24, body=_body())
    r, jp, jl = _linearized(f, poses, points)
    auto = _autodiff(f, poses, points)
    assert np.all(np.isfinite(np.asarray(r)))
    np.testing.assert_allclose(jp, auto[..., :6], rtol=1e-10, atol=1e-8)
    np.testing.assert_allclose(jl, auto[..., 6:], rtol=1e-10, atol=1e-8)


def test_calibrate_inverts_uncalibrate():
    import eqsmooth as eqs

    rng = np.random.default_rng(3)
    xy = jnp.asarray(rng.uniform(-0.5, 0.5, size=(50, 2)))
    for cal in (eqs.Cal3_S2(*S2), eqs.Cal3DS2(*DS2)):
        back = cal.calibrate(cal.uncalibrate(xy))
        np.testing.assert_allclose(back, xy, atol=1e-12)
        k = cal.matrix() if isinstance(cal, eqs.Cal3_S2) else None
        if k is not None:
            hom = jnp.concatenate([xy, jnp.ones((50, 1))], axis=1) @ k.T
            np.testing.assert_allclose(hom[:, :2], cal.uncalibrate(xy), atol=1e-9)


def test_bad_input_is_refused_with_names():
    import eqsmooth as eqs

    with pytest.raises(ValueError, match=r"Cal3_S2\.fx must be positive"):
        eqs.Cal3_S2(0.0, 500.0)
    with pytest.raises(ValueError, match=r"Cal3DS2\.k1 must be finite"):
        eqs.Cal3DS2(500.0, 500.0, k1=float("nan"))
    with pytest.raises(ValueError, match=r"Cal3_S2Stereo\.baseline must be positive"):
        eqs.Cal3_S2Stereo(500.0, 500.0, 320.0, 240.0, 0.0)
    with pytest.raises(ValueError, match=r"ProjectionFactor\.measured must have shape"):
        _factor("s2", 2, measured=jnp.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"rows \[1\] are not finite"):
        _factor("s2", 2, measured=jnp.array([[1.0, 2.0], [np.nan, 0.0]]))
    with pytest.raises(TypeError, match="Cal3_S2Stereo"):
        eqs.StereoProjectionFactor(
            eqs.Var("x", [0]),
            eqs.Var("l", [0]),
            jnp.zeros((1, 3)),
            eqs.IsotropicNoise.from_sigma(1.0),
            eqs.Cal3_S2(*S2),
        )
    with pytest.raises(ValueError, match="body_P_sensor must be one SE3"):
        _factor("s2", 1, body=eqs.SE3.exp(jnp.zeros((2, 6))))
    f = _factor("s2", 1)
    graph = eqs.FactorGraph([f])
    with pytest.raises(TypeError, match="must hold SE3 values"):
        graph.residuals({"x": eqs.SE2.identity((1,)), "l": jnp.ones((1, 3))})


# ----------------------------------------------------------------- cheirality


def test_cheirality_project_flags_and_nan():
    import eqsmooth as eqs

    pose = eqs.SE3.identity()
    pts = jnp.array([[0.1, 0.2, 2.0], [0.1, 0.2, -2.0], [0.1, 0.2, 0.0]])
    uv, front = eqs.factors.project(pose, pts, eqs.Cal3_S2(*S2))
    np.testing.assert_array_equal(front, [True, False, False])
    assert np.all(np.isfinite(uv[0])) and np.all(np.isnan(uv[1:]))
    np.testing.assert_allclose(uv[0], [320 + 25 + 0.01, 240 + 51], atol=1e-12)
    uvv, front = eqs.factors.project_stereo(pose, pts, eqs.Cal3_S2Stereo(*STEREO))
    np.testing.assert_array_equal(front, [True, False, False])
    assert np.all(np.isfinite(uvv[0])) and np.all(np.isnan(uvv[1:]))
    np.testing.assert_allclose(uvv[0, 0] - uvv[0, 1], 500.0 * 0.3 / 2.0, atol=1e-12)


@functools.cache
def _behind_scene():
    """The scene of `_scene`, seen by the mounted camera (`_body`), with the
    points of rows 1 and 2 moved behind it and onto its plane (depth 1e-9)."""
    import eqsmooth as eqs

    poses, points = _scene()

    @eqx.filter_jit
    def move(poses, points):
        cams = poses @ _body()
        local = cams.inverse().apply(points)
        local = local.at[1, 2].set(-2.0).at[2, 2].set(1e-9)
        return cams.apply(local)

    del eqs
    return poses, move(poses, points)


@pytest.mark.parametrize("kind", ["s2", "stereo"])
def test_cheirality_rows_are_inert_and_flagged(kind):
    """Points behind their (mounted) camera and on its plane: the rows'
    Jacobians are zero (closed form and autodiff of `residual`), their
    residual GTSAM's constant 2 fx (not a projection), `in_front` flags
    them, and `throw_cheirality=True` raises."""
    import eqsmooth as eqs

    poses, points = _behind_scene()
    f = _factor(kind, 24, body=_body())
    r, jp, jl = _linearized(f, poses, points)
    auto = _autodiff(f, poses, points)
    flags = np.asarray(f.in_front({"x": poses, "l": points}))
    np.testing.assert_array_equal(flags, (np.arange(24) > 2) | (np.arange(24) == 0))
    np.testing.assert_allclose(r[1:3], 1000.0)
    # GTSAM's constant too, behind the camera (row 1; GTSAM projects the
    # point of row 2, at depth 1e-9 > 0, to ~1e11 pixels: its threshold is 0)
    if importlib.util.find_spec("gtsam") is not None:
        import gtsam

        gcal = (
            gtsam.Cal3_S2(*S2)
            if kind == "s2"
            else gtsam.Cal3_S2Stereo(*STEREO[:2], 0.0, *STEREO[2:])
        )
        unit = gtsam.noiseModel.Unit.Create(2 if kind == "s2" else 3)
        for i in (1,):
            v = gtsam.Values()
            v.insert(1, _gtsam_pose(poses[i]))
            v.insert(2, np.asarray(points[i]))
            if kind == "s2":
                gf = gtsam.GenericProjectionFactorCal3_S2(
                    np.zeros(2), unit, 1, 2, gcal, _gtsam_pose(_body())
                )
            else:
                gf = gtsam.GenericStereoFactor3D(
                    gtsam.StereoPoint2(0.0, 0.0, 0.0),
                    unit,
                    1,
                    2,
                    gcal,
                    _gtsam_pose(_body()),
                )
            np.testing.assert_allclose(r[i], gf.unwhitenedError(v))
    assert np.all(np.abs(np.asarray(r[~flags])) == 1000.0)
    for j in (jp, jl, auto):
        assert np.all(np.isfinite(np.asarray(j)))
        assert np.all(np.asarray(j)[1:3] == 0.0)
        assert np.all(np.any(np.asarray(j)[flags] != 0.0, axis=(1, 2)))
    graph = eqs.FactorGraph([f])
    with pytest.raises(ValueError, match=r"factor stack 0\): rows \[1, 2\] see"):
        eqs.factors.check_cheirality(graph, {"x": poses, "l": points})
    eqs.factors.check_cheirality(graph, {"x": poses, "l": _scene()[1]})
    if kind == "s2":  # the same helper raises for both kinds
        graph = eqs.FactorGraph(
            [_factor(kind, 24, body=_body(), throw_cheirality=True)]
        )
        with pytest.raises(eqx.EquinoxRuntimeError, match="not in front of its camera"):
            graph.cost({"x": poses, "l": points})
        assert np.isfinite(graph.cost({"x": poses, "l": _scene()[1]}))


# ----------------------------------------------------------- bundle adjustment


@eqx.filter_jit
def _ba_arrays(pts, angles, cal):
    import eqsmooth as eqs

    # Camera z axes towards the origin, from radius 6 in the x-z plane.
    rot = eqs.SO3.from_y_radians(-angles)
    centre = jnp.stack([6 * jnp.sin(angles), 0 * angles, -6 * jnp.cos(angles)], 1)
    cams = eqs.SE3.from_rotation_and_translation(rot, centre)
    body = _body()
    pi, li = np.meshgrid(np.arange(5), np.arange(12), indexing="ij")
    uv, front = eqs.factors.project(cams[pi.ravel()], pts[li.ravel()], cal)
    return cams @ body.inverse(), body, uv, front  # camera = pose · body


@functools.cache
def _ba_problem():
    """Five cameras (on a robot body, with a mounted, distorted camera) on an
    arc around twelve points; noise-free pixels."""
    import eqsmooth as eqs

    rng = np.random.default_rng(0)
    pts = jnp.asarray(rng.uniform(-1, 1, size=(12, 3)))
    cal = eqs.Cal3DS2(*DS2)
    poses, body, uv, front = _ba_arrays(pts, jnp.linspace(-0.6, 0.6, 5), cal)
    assert bool(np.all(front))
    pi, li = np.meshgrid(np.arange(5), np.arange(12), indexing="ij")
    return poses, pts, cal, body, pi.ravel(), li.ravel(), uv


def _ba_graph(cal, body, uv):
    """Projections and, for the gauge (7 degrees of freedom), priors on the
    positions of three points (array priors: a small program)."""
    import eqsmooth as eqs

    poses, pts, _, _, pi, li, _ = _ba_problem()
    return eqs.FactorGraph(
        [
            eqs.ProjectionFactor(
                eqs.Var("x", pi),
                eqs.Var("l", li),
                uv,
                eqs.IsotropicNoise.from_sigma(1.0),
                cal,
                body_P_sensor=body,
            ),
            eqs.PriorFactor(
                eqs.Var("l", [0, 1, 2]), pts[:3], eqs.IsotropicNoise.from_sigma(1e-3)
            ),
        ]
    )


@functools.cache
def _noisy_start():
    import eqsmooth as eqs

    poses, pts, *_ = _ba_problem()
    rng = np.random.default_rng(1)
    dx, dl = rng.normal(size=(5, 6)), rng.normal(size=pts.shape)
    move = eqx.filter_jit(lambda p, d: eqs.retract(p, d))
    return {
        "x": move(poses, jnp.asarray(0.05 * dx)),
        "l": jnp.asarray(np.asarray(pts) + 0.1 * dl),
    }


# One solver configuration (one compiled solve) for every solve below.
_LM = dict(ftol=1e-12, gtol=1e-14, xtol=1e-14)


def _solve(cal, body, uv, start):
    import eqsmooth as eqs

    graph = _ba_graph(cal, body, uv)
    return graph, eqs.least_squares(graph, start, eqs.LevenbergMarquardt(**_LM))


def test_bundle_adjustment_recovers_truth():
    import eqsmooth as eqs

    poses, pts, cal, body, _, _, uv = _ba_problem()
    start = _noisy_start()
    _, sol = _solve(cal, body, uv, start)
    assert float(jnp.max(jnp.abs(eqs.local(poses, start["x"])))) > 0.05
    np.testing.assert_allclose(eqs.local(poses, sol.value["x"]), 0.0, atol=1e-8)
    np.testing.assert_allclose(sol.value["l"], pts, atol=1e-8)


def test_bundle_adjustment_matches_gtsam():
    """Noisy pixels (the optimum is not the truth): the same optimum and cost
    as GTSAM's Levenberg-Marquardt on the same graph."""
    gtsam = pytest.importorskip("gtsam", reason=GTSAM_REASON)

    _, pts, cal, body, pi, li, uv = _ba_problem()
    uv = uv + jnp.asarray(np.random.default_rng(5).normal(size=uv.shape))
    start = _noisy_start()
    graph, sol = _solve(cal, body, uv, start)

    g, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    K = gtsam.Cal3DS2(*DS2)
    unit = gtsam.noiseModel.Isotropic.Sigma(2, 1.0)
    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    L = lambda j: gtsam.symbol("l", j)  # noqa: E731
    for k in range(len(pi)):
        g.add(
            gtsam.GenericProjectionFactorCal3DS2(
                np.asarray(uv[k]),
                unit,
                X(int(pi[k])),
                L(int(li[k])),
                K,
                False,
                False,
                _gtsam_pose(body),
            )
        )
    for j in range(3):
        g.add(
            gtsam.PriorFactorPoint3(
                L(j), np.asarray(pts[j]), gtsam.noiseModel.Isotropic.Sigma(3, 1e-3)
            )
        )
    for i in range(5):
        init.insert(X(i), _gtsam_pose(start["x"][i]))
    for j in range(12):
        init.insert(L(j), np.asarray(start["l"][j]))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    result = gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()
    their_l = np.stack([result.atPoint3(L(j)) for j in range(12)])
    their_x = np.stack([result.atPose3(X(i)).matrix() for i in range(5)])
    np.testing.assert_allclose(sol.value["l"], their_l, atol=1e-8)
    np.testing.assert_allclose(sol.value["x"].as_matrix(), their_x, atol=1e-8)
    np.testing.assert_allclose(float(graph.cost(sol.value)), g.error(result), rtol=1e-9)


# -------------------------------------------------- gradients through a solve


def _perturb(theta, xi):
    """`θ ⊕ ξ`: SE(3) leaves compose `exp` on the right, array leaves add."""
    import eqsmooth as eqs

    leaves, treedef = jax.tree_util.tree_flatten(theta, is_leaf=eqs.manifold.is_group)
    out, k = [], 0
    for leaf in leaves:
        if eqs.manifold.is_group(leaf):
            out.append(leaf @ type(leaf).exp(xi[k : k + 6]))
            k += 6
        else:
            out.append(leaf + xi[k : k + leaf.size].reshape(leaf.shape))
            k += leaf.size
    return jax.tree_util.tree_unflatten(treedef, out), k


def _loss(theta):
    """A scalar of the bundle adjustment's solution, as a function of the
    intrinsics, the camera mount and the measured pixels."""
    import eqsmooth as eqs

    poses, pts, *_ = _ba_problem()
    _, sol = _solve(
        theta["calibration"], theta["body"], theta["measured"], _noisy_start()
    )
    w = jnp.linspace(0.5, 1.5, pts.size).reshape(pts.shape)
    return jnp.sum(w * (sol.value["l"] - pts) ** 2) + jnp.sum(
        eqs.local(poses, sol.value["x"]) ** 2
    )


def _directional(f, dim, rng, blocks, h=1e-4):
    """Unit directions, one per block of coordinates `(start, stop)`, and
    the fourth-order central differences of `f` along them (steps ±h, ±2h)."""
    dirs, fds = [], []
    for start, stop in blocks:
        d = np.zeros(dim)
        d[start:stop] = rng.normal(size=stop - start)
        d = jnp.asarray(d / np.linalg.norm(d))
        vals = [np.asarray(f(s * h * d)) for s in (1, -1, 2, -2)]
        fds.append((8 * (vals[0] - vals[1]) - (vals[2] - vals[3])) / (12 * h))
        dirs.append(d)
    return jnp.stack(dirs), np.stack(fds)


# Leaf order of θ: body (6, tangent), calibration (fx fy skew u0 v0 k1 k2 p1
# p2), measured pixels.
_BLOCKS = [(0, 6), (6, 15), (15, 135)]


def test_linearization_gradients_match_differences():
    """What the implicit adjoint differentiates: the rows' residuals and
    closed-form Jacobians w.r.t. the intrinsics, the camera mount (tangent
    coordinates) and the pixels, by reverse mode against float64 central
    differences (fast; the solve itself is the slow test below)."""
    poses, pts, cal, body, pi, li, uv = _ba_problem()
    start = _noisy_start()
    theta = {"body": body, "calibration": cal, "measured": uv}
    _, dim = _perturb(theta, jnp.zeros(10_000))

    def lin(xi):
        t = _perturb(theta, xi)[0]
        graph = _ba_graph(t["calibration"], t["body"], t["measured"])
        f = graph.factors[0]
        r, jp, jl = _linearized.__wrapped__(f, *graph.states_of(f, start))
        w = jnp.linspace(0.5, 1.5, jp.size).reshape(jp.shape)
        return jnp.stack([jnp.sum(r**2), jnp.sum(w * jp), jnp.sum(jl**2)])

    rng = np.random.default_rng(3)
    dirs = np.zeros((len(_BLOCKS), dim))
    for k, (lo, hi) in enumerate(_BLOCKS):
        dirs[k, lo:hi] = rng.normal(size=hi - lo)
    dirs = jnp.asarray(dirs / np.linalg.norm(dirs, axis=1, keepdims=True))

    @eqx.filter_jit
    def both(dirs):  # one program: the Jacobian and the differences
        h = 1e-4
        steps = jnp.stack([h, -h, 2 * h, -2 * h])[:, None, None] * dirs[None]
        vals = jax.vmap(jax.vmap(lin))(steps)
        fd = (8 * (vals[0] - vals[1]) - (vals[2] - vals[3])) / (12 * h)
        return jax.jacrev(lin)(jnp.zeros(dim)), fd

    jac, fd = map(np.asarray, both(dirs))
    assert np.all(np.any(jac[:, :15] != 0, axis=0))  # every intrinsic, the mount
    np.testing.assert_allclose(jac @ np.asarray(dirs).T, fd.T, rtol=1e-6)


@pytest.mark.slow  # ~30 s of CPU to compile the SE(3) implicit adjoint
def test_gradients_through_solve_match_differences():
    """d(a loss of the bundle adjustment's solution) / d(the 9 intrinsics and
    distortion coefficients, the camera mount in tangent coordinates, the
    measured pixels): reverse mode through the solve (the implicit adjoint)
    against float64 fourth-order central differences of re-solves."""
    _, _, cal, body, _, _, uv = _ba_problem()
    _noisy_start()  # cached: made here, not under the trace below
    rng = np.random.default_rng(7)
    theta = {
        "body": body,
        "calibration": cal,
        "measured": uv + jnp.asarray(rng.normal(size=uv.shape)),
    }
    _, dim = _perturb(theta, jnp.zeros(10_000))
    f = lambda xi: _loss(_perturb(theta, xi)[0])  # noqa: E731
    g = np.asarray(eqx.filter_jit(jax.grad(f))(jnp.zeros(dim)))
    assert np.all(g[:15] != 0), g[:15]  # every intrinsic and the mount move it
    dirs, fd = _directional(f, dim, rng, _BLOCKS)
    np.testing.assert_allclose(np.asarray(dirs) @ g, fd, rtol=1e-5)


# ------------------------------------------------------------- GTSAM parity


def _gtsam_pose(pose):
    import gtsam

    return gtsam.Pose3(np.asarray(pose.as_matrix()))


def _swap(h):
    """A GTSAM `Pose3` Jacobian `(ω, v)` in eqsmooth's tangent order `(v, ω)`."""
    return np.concatenate([h[:, 3:], h[:, :3]], axis=1)


@pytest.mark.parametrize("kind", ["s2", "ds2"])
def test_pinhole_matches_gtsam(kind):
    """Pixels and H matrices (pose, point, calibration) of
    `PinholeCamera<Cal3_S2/Cal3DS2>::project`, and the factor's residual and
    blocks from `GenericProjectionFactor`'s linearisation with and without
    `body_P_sensor`: the same to 1e-9 (pixels and pixel Jacobians, whose
    entries reach ~1e3: 1e-9 absolute or 1e-12 relative)."""
    gtsam = pytest.importorskip("gtsam", reason=GTSAM_REASON)

    poses, points = _scene()
    rng = np.random.default_rng(2)
    measured = jnp.asarray(rng.normal(320, 50, size=(24, 2)))
    gcal = gtsam.Cal3_S2(*S2) if kind == "s2" else gtsam.Cal3DS2(*DS2)
    Camera = gtsam.PinholeCameraCal3_S2 if kind == "s2" else gtsam.PinholeCameraCal3DS2
    Factor = (
        gtsam.GenericProjectionFactorCal3_S2
        if kind == "s2"
        else gtsam.GenericProjectionFactorCal3DS2
    )
    body = _body()
    plain = _factor(kind, 24, measured=measured)
    uv, dcal, (r0, jp0, jl0) = _pinhole_arrays(plain, poses, points)
    n_cal = dcal.shape[-1]
    mounted = _factor(kind, 24, measured=measured, body=body)
    r1, jp1, jl1 = _linearized(mounted, poses, points)
    for i in range(24):
        # The camera's projection and its H matrices.
        cam = Camera(_gtsam_pose(poses[i]), gcal)
        hp, hl, hc = (np.zeros((2, d), order="F") for d in (6, 3, n_cal))
        their = cam.project(np.asarray(points[i]), hp, hl, hc)
        _close(uv[i], their)
        _close(r0[i], their - np.asarray(measured[i]))
        _close(jp0[i], _swap(hp))
        _close(jl0[i], hl)
        _close(dcal[i], hc)
        # The factor, with and without a mount.
        for r, jp, jl, m in ((r0, jp0, jl0, False), (r1, jp1, jl1, True)):
            args = (np.asarray(measured[i]), gtsam.noiseModel.Unit.Create(2), 1, 2)
            gf = Factor(*args, gcal, _gtsam_pose(body)) if m else Factor(*args, gcal)
            v = gtsam.Values()
            v.insert(1, _gtsam_pose(poses[i]))
            v.insert(2, np.asarray(points[i]))
            _close(r[i], gf.unwhitenedError(v))
            A, _ = gf.linearize(v).jacobian()
            _close(jp[i], _swap(A[:, :6]))
            _close(jl[i], A[:, 6:])


@eqx.filter_jit
def _pinhole_arrays(factor, poses, points):
    """One program: `project`, `∂uv/∂(calibration vector)` by autodiff of
    `uncalibrate`, and the (unmounted) factor's linearisation."""
    import eqsmooth as eqs

    cal = factor.calibration
    uv, _ = eqs.factors.project(poses, points, cal)
    local = poses.inverse().apply(points)
    xy = local[:, :2] / local[:, 2:]

    def pixel(vec, xy):
        return type(cal)(*vec).uncalibrate(xy)

    dcal = jax.vmap(jax.jacfwd(pixel), in_axes=(None, 0))(cal.vector(), xy)
    return uv, dcal, _linearized.__wrapped__(factor, poses, points)


def _close(ours, theirs):
    np.testing.assert_allclose(ours, theirs, rtol=1e-12, atol=1e-9)


def test_stereo_matches_gtsam():
    """`StereoCamera::project2` with its H matrices and
    `GenericStereoFactor3D`'s residual and blocks (with a mount), to 1e-9."""
    gtsam = pytest.importorskip("gtsam", reason=GTSAM_REASON)
    import eqsmooth as eqs

    poses, points = _scene()
    rng = np.random.default_rng(4)
    measured = jnp.asarray(rng.normal(320, 50, size=(24, 3)))
    fx, fy, u0, v0, b = STEREO
    gcal = gtsam.Cal3_S2Stereo(fx, fy, 0.0, u0, v0, b)
    body = _body()
    project = eqx.filter_jit(eqs.factors.project_stereo)
    uvv, front = project(poses, points, eqs.Cal3_S2Stereo(*STEREO))
    assert bool(np.all(front))
    for mounted in (False, True):
        f = _factor("stereo", 24, measured=measured, body=body if mounted else None)
        r, jp, jl = _linearized(f, poses, points)
        for i in range(24):
            unit = gtsam.noiseModel.Unit.Create(3)
            sp = gtsam.StereoPoint2(*np.asarray(measured[i]))
            args = (sp, unit, 1, 2, gcal)
            gf = (
                gtsam.GenericStereoFactor3D(*args, _gtsam_pose(body))
                if mounted
                else gtsam.GenericStereoFactor3D(*args)
            )
            v = gtsam.Values()
            v.insert(1, _gtsam_pose(poses[i]))
            v.insert(2, np.asarray(points[i]))
            np.testing.assert_allclose(r[i], gf.unwhitenedError(v), atol=1e-9)
            A, _ = gf.linearize(v).jacobian()
            np.testing.assert_allclose(jp[i], _swap(A[:, :6]), rtol=1e-11, atol=1e-9)
            np.testing.assert_allclose(jl[i], A[:, 6:], rtol=1e-11, atol=1e-9)
            if not mounted:
                cam = gtsam.StereoCamera(_gtsam_pose(poses[i]), gcal)
                h1, h2 = np.zeros((3, 6), order="F"), np.zeros((3, 3), order="F")
                sp = cam.project2(np.asarray(points[i]), h1, h2)
                their = np.array([sp.uL(), sp.uR(), sp.v()])
                np.testing.assert_allclose(r[i] + measured[i], their, atol=1e-9)
                np.testing.assert_allclose(uvv[i], their, rtol=1e-12, atol=1e-9)
                np.testing.assert_allclose(jp[i], _swap(h1), rtol=1e-11, atol=1e-9)
                np.testing.assert_allclose(jl[i], h2, rtol=1e-11, atol=1e-9)


@pytest.mark.slow  # about two minutes: three solves and a gradient, compiled
def test_docs_cameras_page_runs(capsys):
    """The Python blocks of docs/tutorial/cameras.md run in order and do what
    their comments say."""
    import re
    from pathlib import Path

    page = Path(__file__).resolve().parents[1] / "docs" / "tutorial" / "cameras.md"
    blocks = re.findall(r"```python\n(.*?)```", page.read_text(), re.S)
    assert len(blocks) == 3
    scope = {}
    with jax.numpy_dtype_promotion("standard"):  # a user's session
        for k, block in enumerate(blocks):
            exec(compile(block, f"docs/tutorial/cameras.md:{k}", "exec"), scope)
    capsys.readouterr()
    err = np.abs(np.asarray(scope["sol"].value["l"] - scope["points"])).max()
    assert err < 0.05
    err = np.abs(np.asarray(scope["stereo_sol"].value["l"] - scope["points"])).max()
    assert err < 0.05
    assert float(scope["grads"].fx) != 0.0 and float(scope["grads"].k1) != 0.0
