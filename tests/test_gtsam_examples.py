"""GTSAM's classic small problems rebuilt with eqsmooth's built-in factors:
the answers agree with GTSAM's to 1e-9 (skipped when gtsam is absent).

The problems have the shape of GTSAM's Pose2SLAM, PlanarSLAM and
GPS+odometry examples, with measurements perturbed so that the optimum is
not the exact data (the conventions of every residual then matter).
"""

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import prior_and_odometry


gtsam = pytest.importorskip("gtsam")

ATOL = 1e-9


def _lm_gtsam(graph, initial):
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-15)
    params.setAbsoluteErrorTol(1e-15)
    params.setMaxIterations(500)
    return gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()


def _solve(graph, values):
    import eqsmooth as eqs

    solver = eqs.LevenbergMarquardt(ftol=1e-15, gtol=1e-13, xtol=1e-14)
    return eqs.least_squares(graph, values, solver, max_steps=300).value


def _pose2s(xyt):
    import eqsmooth as eqs

    xyt = np.asarray(xyt, np.float64)
    return eqs.SE2.from_xy_theta(
        jnp.asarray(xyt[:, 0]), jnp.asarray(xyt[:, 1]), jnp.asarray(xyt[:, 2])
    )


def _compare_pose2(ours, result, keys):
    for i, k in enumerate(keys):
        p = result.atPose2(k)
        np.testing.assert_allclose(float(ours.x()[i]), p.x(), atol=ATOL)
        np.testing.assert_allclose(float(ours.y()[i]), p.y(), atol=ATOL)
        d = float(ours.theta()[i]) - p.theta()
        assert abs(np.arctan2(np.sin(d), np.cos(d))) < ATOL


ODO = np.array(
    [
        [2.0, 0.0, 0.0],
        [2.1, 0.05, np.pi / 2],
        [1.9, -0.03, np.pi / 2 + 0.02],
        [2.05, 0.0, np.pi / 2 - 0.03],
    ]
)
LOOP = np.array([2.1, 0.1, np.pi / 2 + 0.05])  # pose 4 -> pose 1
INIT = np.array(
    [
        [0.4, 0.1, 0.15],
        [2.3, 0.1, -0.2],
        [4.1, 0.2, np.pi / 2],
        [4.0, 2.1, np.pi],
        [2.1, 2.2, -np.pi / 2],
    ]
)


def test_pose2_slam_matches_gtsam():
    import eqsmooth as eqs

    prior_s = np.array([0.3, 0.3, 0.1])
    odo_s = np.array([0.2, 0.2, 0.1])
    g = gtsam.NonlinearFactorGraph()
    g.add(
        gtsam.PriorFactorPose2(
            0, gtsam.Pose2(0, 0, 0), gtsam.noiseModel.Diagonal.Sigmas(prior_s)
        )
    )
    for i, (x, y, t) in enumerate(ODO):
        g.add(
            gtsam.BetweenFactorPose2(
                i, i + 1, gtsam.Pose2(x, y, t), gtsam.noiseModel.Diagonal.Sigmas(odo_s)
            )
        )
    g.add(
        gtsam.BetweenFactorPose2(
            4, 1, gtsam.Pose2(*LOOP), gtsam.noiseModel.Diagonal.Sigmas(odo_s)
        )
    )
    init = gtsam.Values()
    for i, (x, y, t) in enumerate(INIT):
        init.insert(i, gtsam.Pose2(x, y, t))
    ref = _lm_gtsam(g, init)

    graph = eqs.FactorGraph(
        [
            *prior_and_odometry(
                _pose2s([[0.0, 0.0, 0.0]]),
                prior_s,
                [0, 1, 2, 3, 4],
                [1, 2, 3, 4, 1],
                _pose2s(np.vstack([ODO, LOOP])),
                odo_s,
            ),
        ]
    )
    sol = _solve(graph, {"x": _pose2s(INIT)})
    _compare_pose2(sol["x"], ref, range(5))
    np.testing.assert_allclose(
        float(graph.cost(sol)), g.error(ref), rtol=1e-9, atol=1e-12
    )


def test_planar_slam_matches_gtsam():
    import eqsmooth as eqs

    X = lambda i: gtsam.symbol("x", i)  # noqa: E731
    L = lambda j: gtsam.symbol("l", j)  # noqa: E731
    odo = np.array([[2.0, 0.1, 0.02], [1.95, -0.05, -0.03]])
    obs = [  # (pose, landmark, bearing, range)
        (0, 0, np.pi / 4 + 0.02, np.sqrt(8) + 0.05),
        (1, 0, np.pi / 2 - 0.03, 2.0 - 0.04),
        (2, 1, np.pi / 2 + 0.01, 2.0 + 0.1),
        (1, 1, np.pi / 4 - 0.02, np.sqrt(8) - 0.06),
    ]
    prior_s, odo_s, br_s = (
        np.array([0.3, 0.3, 0.1]),
        np.array([0.2, 0.2, 0.1]),
        np.array([0.1, 0.2]),
    )
    init_x = np.array([[-0.25, 0.2, 0.15], [2.3, 0.1, -0.2], [4.1, 0.1, 0.1]])
    init_l = np.array([[1.8, 2.1], [4.1, 1.8]])

    g = gtsam.NonlinearFactorGraph()
    g.add(
        gtsam.PriorFactorPose2(
            X(0), gtsam.Pose2(0, 0, 0), gtsam.noiseModel.Diagonal.Sigmas(prior_s)
        )
    )
    for i, m in enumerate(odo):
        g.add(
            gtsam.BetweenFactorPose2(
                X(i), X(i + 1), gtsam.Pose2(*m), gtsam.noiseModel.Diagonal.Sigmas(odo_s)
            )
        )
    for p, j, b, r in obs:
        g.add(
            gtsam.BearingRangeFactor2D(
                X(p), L(j), gtsam.Rot2(b), r, gtsam.noiseModel.Diagonal.Sigmas(br_s)
            )
        )
    init = gtsam.Values()
    for i, v in enumerate(init_x):
        init.insert(X(i), gtsam.Pose2(*v))
    for j, v in enumerate(init_l):
        init.insert(L(j), np.asarray(v))
    ref = _lm_gtsam(g, init)

    obs_a = np.array(obs)
    graph = eqs.FactorGraph(
        [
            *prior_and_odometry(
                _pose2s([[0.0, 0.0, 0.0]]), prior_s, [0, 1], [1, 2], _pose2s(odo), odo_s
            ),
            eqs.BearingRangeFactor(
                eqs.Var("x", obs_a[:, 0].astype(int)),
                eqs.Var("l", obs_a[:, 1].astype(int)),
                jnp.asarray(obs_a[:, 2]),
                jnp.asarray(obs_a[:, 3]),
                eqs.DiagonalNoise.from_sigmas(br_s),
            ),
        ]
    )
    sol = _solve(graph, {"x": _pose2s(init_x), "l": jnp.asarray(init_l)})
    _compare_pose2(sol["x"], ref, [X(i) for i in range(3)])
    for j in range(2):
        np.testing.assert_allclose(
            np.asarray(sol["l"][j]), ref.atPoint2(L(j)), atol=ATOL
        )
    np.testing.assert_allclose(float(graph.cost(sol)), g.error(ref), rtol=1e-9)


def _pose3_params(p):
    q = p.rotation().toQuaternion()
    return np.array([q.w(), q.x(), q.y(), q.z(), *p.translation()])


def test_gps_odometry_3d_matches_gtsam():
    """Pose3 odometry with GPS (translation-only) fixes and a range to a beacon."""
    import eqsmooth as eqs

    rng = np.random.default_rng(0)
    T = 5
    true_xi = np.zeros((T, 6))
    true_xi[:, 0] = np.arange(T) * 1.0
    true_xi[:, 5] = 0.1 * np.arange(T)
    truth = eqs.SE3.exp(jnp.asarray(true_xi))
    rel = truth[:-1].inverse() @ truth[1:]
    odo = rel @ eqs.SE3.exp(jnp.asarray(0.02 * rng.standard_normal((T - 1, 6))))
    gps = np.asarray(truth.translation()) + 0.3 * rng.standard_normal((T, 3))
    beacon = np.array([2.0, 3.0, 1.0])
    ranges = np.linalg.norm(
        np.asarray(truth.translation()) - beacon, axis=1
    ) + 0.05 * rng.standard_normal(T)
    start = truth @ eqs.SE3.exp(jnp.asarray(0.2 * rng.standard_normal((T, 6))))
    odo_s = np.array([0.05, 0.05, 0.05, 0.02, 0.02, 0.02])  # ours: (v, ω)
    gps_s, range_s = 0.3, 0.05

    def p3(params):
        return gtsam.Pose3(
            gtsam.Rot3.Quaternion(*params[:4]), gtsam.Point3(*params[4:])
        )

    # A prior on the first pose: without it the absolute rotation is fixed
    # only weakly (through GPS lever arms) and both solvers stop on a cost
    # plateau 1e-14 wide, where poses still differ by 1e-7.
    prior_s = np.full(6, 0.1)
    g = gtsam.NonlinearFactorGraph()
    g.add(
        gtsam.PriorFactorPose3(
            0,
            p3(np.asarray(truth.wxyz_xyz[0])),
            gtsam.noiseModel.Diagonal.Sigmas(prior_s),
        )
    )
    gnoise = gtsam.noiseModel.Diagonal.Sigmas(odo_s[[3, 4, 5, 0, 1, 2]])
    for i in range(T - 1):
        g.add(
            gtsam.BetweenFactorPose3(i, i + 1, p3(np.asarray(odo.wxyz_xyz[i])), gnoise)
        )
    for i in range(T):
        g.add(gtsam.GPSFactor(i, gps[i], gtsam.noiseModel.Isotropic.Sigma(3, gps_s)))
        g.add(
            gtsam.RangeFactor3D(
                i, 100, ranges[i], gtsam.noiseModel.Isotropic.Sigma(1, range_s)
            )
        )
    g.add(
        gtsam.PriorFactorPoint3(100, beacon, gtsam.noiseModel.Isotropic.Sigma(3, 1e-3))
    )
    init = gtsam.Values()
    for i in range(T):
        init.insert(i, p3(np.asarray(start.wxyz_xyz[i])))
    init.insert(100, beacon + 0.1)
    ref = _lm_gtsam(g, init)

    ids = np.arange(T)
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", [0]), truth[:1], eqs.DiagonalNoise.from_sigmas(prior_s)
            ),
            eqs.BetweenFactor(
                eqs.Var("x", ids[:-1]),
                eqs.Var("x", ids[1:]),
                odo,
                eqs.DiagonalNoise.from_sigmas(odo_s),
            ),
            eqs.TranslationPriorFactor(
                eqs.Var("x", ids),
                jnp.asarray(gps),
                eqs.IsotropicNoise.from_sigma(gps_s),
            ),
            eqs.RangeFactor(
                eqs.Var("x", ids),
                eqs.Var("b", np.zeros(T, int)),
                jnp.asarray(ranges),
                eqs.IsotropicNoise.from_sigma(range_s),
            ),
            eqs.PriorFactor(
                eqs.Var("b", [0]),
                jnp.asarray(beacon[None]),
                eqs.IsotropicNoise.from_sigma(1e-3),
            ),
        ]
    )
    sol = _solve(graph, {"x": start, "b": jnp.asarray(beacon[None] + 0.1)})
    for i in range(T):
        ref_m = ref.atPose3(i).matrix()
        np.testing.assert_allclose(
            np.asarray(sol["x"][i].as_matrix()), ref_m, atol=ATOL
        )
    np.testing.assert_allclose(np.asarray(sol["b"][0]), ref.atPoint3(100), atol=ATOL)
    np.testing.assert_allclose(float(graph.cost(sol)), g.error(ref), rtol=1e-9)
