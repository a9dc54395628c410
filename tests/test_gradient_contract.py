"""The gradient contract, route by route (docs/differentiating.md).

Every public route that returns something a user may differentiate is
compared here with float64 central differences in tangent coordinates
(`x ⊕ δ` for Lie-group leaves, `a + δ` for arrays), with respect to noise
parameters, factor data and values, unless an FD test elsewhere already
covers it (the table in docs/differentiating.md says which). The solver
routes (least_squares with each adjoint, marginals, log-determinants) are
tested by their own modules.

How a check works: a route `F(θ) -> (K,)` of a parameter pytree `θ` (arrays
and Lie groups) is differentiated in reverse mode (`jax.jacrev` of
`ξ ↦ F(θ ⊕ ξ)` at `ξ = 0`; `jax.jacfwd` where a test says forward mode) and
compared, along one random direction per leaf of `θ`, with a fourth-order
central difference (steps ±h, ±2h), both in one compiled program. Every
leaf whose difference is nonzero must have a nonzero gradient (a zero or
NaN gradient fails), and the two must agree to 1e-5 relative.

Compile time is most of this module's time (about 50 s with `-n0` on 2
shared cores): one program per test, tiny shapes; the SE(3) linearisation
and the Laplace evidence on SE(2) are marked slow.
"""

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest


RTOL = 1e-5
H = 1e-4


# --------------------------------------------------------------------- helpers


def _is_group(x):
    import eqsmooth as eqs

    return eqs.manifold.is_group(x)


def _leaves(theta):
    return jax.tree_util.tree_flatten_with_path(theta, is_leaf=_is_group)[0]


def _leaf_size(leaf) -> int:
    if _is_group(leaf):
        return math.prod(leaf.batch_shape) * type(leaf).tangent_dim
    if eqx.is_inexact_array(leaf):
        return leaf.size
    return 0


def _perturb(theta, xi):
    """`θ ⊕ ξ`: group leaves compose `exp` on the right (per batch element),
    inexact array leaves add; `ξ` is flat, in leaf order."""
    leaves, treedef = jax.tree_util.tree_flatten(theta, is_leaf=_is_group)
    out, k = [], 0
    for leaf in leaves:
        d = _leaf_size(leaf)
        piece = xi[k : k + d]
        k += d
        if _is_group(leaf):
            tangent = piece.reshape(leaf.batch_shape + (type(leaf).tangent_dim,))
            out.append(leaf @ type(leaf).exp(tangent))
        elif d:
            out.append(leaf + piece.reshape(leaf.shape))
        else:
            out.append(leaf)
    return jax.tree_util.tree_unflatten(treedef, out)


def _directions(theta, seed):
    """One random unit direction per leaf (zero on every other leaf): `(L, D)`,
    and the leaves' names."""
    sizes = [(jax.tree_util.keystr(p), _leaf_size(leaf)) for p, leaf in _leaves(theta)]
    sizes = [(name, d) for name, d in sizes if d]
    total = sum(d for _, d in sizes)
    rng = np.random.default_rng(seed)
    rows, k = [], 0
    for _, d in sizes:
        row = np.zeros(total)
        v = rng.normal(size=d)
        row[k : k + d] = v / np.linalg.norm(v)
        rows.append(row)
        k += d
    return jnp.asarray(np.stack(rows)), [name for name, _ in sizes]


@functools.cache
def _program(route, mode, h):
    """One compiled program: the directional derivatives of `route` by
    autodiff (`mode` "rev": `jax.jacrev`, "fwd": `jax.jacfwd`) and its
    fourth-order central differences, along the rows of `dirs`."""

    @eqx.filter_jit
    def run(theta, dirs):
        def f(xi):
            return route(_perturb(theta, xi))

        zero = jnp.zeros(dirs.shape[1], dirs.dtype)
        jac = (jax.jacrev if mode == "rev" else jax.jacfwd)(f)(zero)
        analytic = jac @ dirs.T  # (K, L)
        steps = jnp.stack([h, -h, 2 * h, -2 * h])[:, None, None] * dirs[None]
        vals = jax.vmap(jax.vmap(f))(steps)  # (4, L, K)
        fd = (8 * (vals[0] - vals[1]) - (vals[2] - vals[3])) / (12 * h)
        return f(zero), analytic, fd.T

    return run


def gradients(route, theta, *, seed=0, mode="rev", h=H):
    """`(value, analytic, fd, leaf names)` of `route` at `theta`: the
    autodiff and central-difference (step `h`) directional derivatives
    `(K, L)` along one random direction per leaf."""
    dirs, names = _directions(theta, seed)
    value, analytic, fd = _program(route, mode, h)(theta, dirs)
    return (*map(np.asarray, (value, analytic, fd)), names)


def assert_gradients(result, outputs, *, rows=None, zero_leaves=()):
    """Assert that the derivatives of `result` (from `gradients`) agree with
    the differences, output by output (only `rows`, if given).

    Leaves named in `zero_leaves` must have a zero gradient (and a zero
    difference); every other leaf must move at least one output, and where
    the difference is nonzero the gradient must be nonzero and agree to
    `RTOL`."""
    value, analytic, fd, names = result
    if rows is not None:
        value, analytic, fd = value[rows], analytic[rows], fd[rows]
        outputs = [outputs[i] for i in rows]
    assert np.all(np.isfinite(value)), value
    finite = np.isfinite(analytic)
    assert np.all(finite), _report(analytic, fd, names, outputs, finite)
    scale = np.max(np.abs(fd), axis=1, keepdims=True)  # per output
    for j, name in enumerate(names):
        moved = np.abs(fd[:, j]) > 1e-7 * np.maximum(scale[:, 0], 1.0)
        if any(z in name for z in zero_leaves):
            assert not np.any(moved), f"{name}: expected no dependence"
            np.testing.assert_array_equal(analytic[:, j], 0.0, err_msg=name)
            continue
        assert np.any(moved), f"{name}: no output depends on it (a useless check)"
        # A nonzero difference must meet a nonzero gradient.
        assert np.all(np.abs(analytic[moved, j]) > 0), _report(
            analytic, fd, names, outputs
        )
    ok = np.abs(analytic - fd) <= RTOL * np.abs(fd) + 1e-9 * np.maximum(scale, 1.0)
    assert np.all(ok), _report(analytic, fd, names, outputs, ok)


def check_gradients(route, theta, outputs, *, seed=0, mode="rev", h=H, zero_leaves=()):
    """`gradients` then `assert_gradients` on every output."""
    result = gradients(route, theta, seed=seed, mode=mode, h=h)
    assert_gradients(result, outputs, zero_leaves=zero_leaves)
    return result


def _report(analytic, fd, names, outputs, ok=None):
    lines = ["gradient vs central differences (output, leaf, grad, fd):"]
    for k in range(analytic.shape[0]):
        for j, name in enumerate(names):
            if ok is None or not ok[k, j]:
                out = outputs[k] if outputs else k
                lines.append(f"  {out} {name}: {analytic[k, j]:.10g} {fd[k, j]:.10g}")
    return "\n".join(lines[:60])


def _summary(tree, seed):
    """A fixed random linear functional of every inexact leaf of `tree`
    (so that every entry of, e.g., a Jacobian block is checked)."""
    rng = np.random.default_rng(seed)
    total = 0.0
    for leaf in jax.tree_util.tree_leaves(tree):
        if eqx.is_inexact_array(leaf):
            w = jnp.asarray(rng.normal(size=leaf.shape), leaf.dtype)
            total = total + jnp.sum(w * leaf)
    return total


def _graph_outputs(graph, values, truth):
    """Every graph-level route on one graph, as one vector."""
    import eqsmooth as eqs

    lin = eqs.linearize(graph, values)
    return jnp.stack(
        [
            graph.cost(values),
            graph.negative_log_likelihood(values),
            eqs.joint_nll(graph, values),
            _summary(graph.residuals(values), 1),
            _summary(graph.whitened_residuals(values), 2),
            _summary(tuple(f.residual for f in lin.factors), 3),
            _summary(tuple(f.jacobians for f in lin.factors), 4),
            lin.cost,
            eqs.manifold_mse(truth, values, _mse_weights(values)),
            _summary(eqs.learn.manifold_errors(truth, values), 5),
        ]
    )


GRAPH_OUTPUTS = (
    "cost",
    "negative_log_likelihood",
    "joint_nll",
    "residuals",
    "whitened_residuals",
    "linearize.residual",
    "linearize.jacobians",
    "linearize.cost",
    "manifold_mse",
    "manifold_errors",
)


def _mse_weights(values):
    import eqsmooth as eqs

    return {
        k: jnp.linspace(1.0, 2.0, eqs.manifold.tangent_dim(v, batch_ndim=1))
        if _is_group(v)
        else jnp.asarray(1.5)
        for k, v in values.items()
    }


# ------------------------------------------------------- SE(2) with landmarks


def _poses_and_marks(group, dof: int, seed: int, num_poses: int, mark_shape):
    """`rng = default_rng(seed)`, `draw(n, s=1.0)` (`n` poses of `group`,
    `dof` tangent coordinates, at tangent scale `s`, drawn from `rng`), then
    `num_poses` poses and landmarks of shape `mark_shape` (scale 2) drawn."""
    rng = np.random.default_rng(seed)

    def draw(n, s=1.0):
        return group.exp(jnp.asarray(s * rng.normal(size=(n, dof))))

    poses = draw(num_poses)
    return rng, draw, poses, jnp.asarray(rng.normal(size=mark_shape) * 2.0)


def _truth_and_theta(draw, poses, marks, num_poses: int):
    """The truth, and the start of a `theta`: values a solve starts from (the
    poses moved by `draw(num_poses, 0.05)`, the landmarks by 0.05), then the
    data's prior on the first pose (moved by `draw(1, 0.1)`), drawn in this
    order; the caller adds the other data and the noise parameters."""
    truth = {"pose": poses, "mark": marks}
    start = {"pose": poses @ draw(num_poses, 0.05), "mark": marks + 0.05}
    return truth, {"values": start, "data": {"prior": poses[:1] @ draw(1, 0.1)}}


@functools.cache
def _se2_theta():
    import eqsmooth as eqs

    rng, se2, poses, marks = _poses_and_marks(eqs.SE2, 3, 0, 3, (2, 2))
    odo = poses[:2].inverse() @ poses[1:] @ se2(2, 0.1)
    local = (poses[np.array([0, 1, 2])].inverse()).apply(marks[np.array([0, 1, 1])])
    noisy = local + 0.1 * rng.normal(size=local.shape)
    truth, theta = _truth_and_theta(se2, poses, marks, 3)
    theta["data"] |= {
        "odo": odo,
        "bearing": jnp.arctan2(noisy[:, 1], noisy[:, 0]),
        "range": jnp.linalg.norm(noisy, axis=1),
        "gps": poses.translation() + jnp.asarray(0.1 * rng.normal(size=(3, 2))),
        "point": noisy,
    }
    theta["noise"] = {
        "prior_cov_factor": jnp.asarray(0.1 * rng.normal(size=(3, 3))),
        "odo_log_sp": jnp.asarray(rng.normal(size=(2, 3)) * 0.2 + 2.0),
        "br_log_sp": jnp.asarray([2.0, 1.5]),
        "huber_k": jnp.asarray(0.3),
        "range_sp": jnp.asarray([3.0, 2.0, 4.0]),
        "bearing_info": jnp.asarray([[[9.0]], [[16.0]], [[25.0]]]),
        "gps_sigmas": jnp.asarray([0.2, 0.3]),
        "gps_log_dof": jnp.asarray(1.2),
        "point_sp": jnp.asarray(5.0),
    }
    return truth, theta


def _se2_graph(theta):
    import eqsmooth as eqs

    d, nz = theta["data"], theta["noise"]
    A = nz["prior_cov_factor"]
    pose3 = eqs.Var("pose", [0, 1, 2])
    mark3 = eqs.Var("mark", [0, 1, 1])
    return eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("pose", [0]),
                d["prior"],
                eqs.SqrtInformationNoise.from_covariance(A @ A.T + 0.01 * jnp.eye(3)),
            ),
            eqs.BetweenFactor(
                eqs.Var("pose", [0, 1]),
                eqs.Var("pose", [1, 2]),
                d["odo"],
                eqs.DiagonalNoise(sqrt_precision=jnp.exp(nz["odo_log_sp"])),
            ),
            eqs.BearingRangeFactor(
                pose3,
                mark3,
                d["bearing"],
                d["range"],
                eqs.HuberNoise(
                    eqs.DiagonalNoise(sqrt_precision=jnp.exp(nz["br_log_sp"])),
                    nz["huber_k"],
                ),
            ),
            eqs.RangeFactor(
                pose3,
                mark3,
                d["range"],
                eqs.IsotropicNoise(sqrt_precision=nz["range_sp"]),
            ),
            eqs.BearingFactor(
                pose3,
                mark3,
                d["bearing"],
                eqs.SqrtInformationNoise.from_information(nz["bearing_info"]),
            ),
            eqs.TranslationPriorFactor(
                pose3,
                d["gps"],
                eqs.StudentTNoise(
                    eqs.DiagonalNoise.from_sigmas(nz["gps_sigmas"]),
                    jnp.exp(nz["gps_log_dof"]),
                    dim=2,
                ),
            ),
            eqs.PoseToPointFactor(
                pose3,
                mark3,
                d["point"],
                eqs.IsotropicNoise(sqrt_precision=nz["point_sp"]),
            ),
        ]
    )


def _se2_route(theta):
    return _graph_outputs(_se2_graph(theta), theta["values"], _se2_theta()[0])


def test_graph_routes_on_se2_landmarks():
    """cost, NLL, joint_nll, residuals, linearize (residuals, Jacobian
    blocks, cost), manifold_mse and manifold_errors on an SE(2) graph with
    landmark, range, bearing, GPS (Student-t), pose-to-point, prior
    (full sqrt-information from a covariance) and between (per-row
    diagonal) factors: w.r.t. every noise parameter, every measurement
    (SE(2) ones in tangent coordinates) and every value."""
    _, _, _, names = check_gradients(_se2_route, _se2_theta()[1], GRAPH_OUTPUTS)
    assert any("['values']['pose']" in n for n in names)


# ------------------------------------------------- planar vehicle dynamics


def _vehicle_theta():
    import eqsmooth as eqs

    rng = np.random.default_rng(11)
    poses = eqs.SE2.exp(jnp.asarray(rng.normal(size=(4, 3))))
    vel = jnp.asarray(rng.normal(size=(4, 2)))
    truth = eqs.factors.VehicleState(poses, vel)
    values = eqs.retract(truth, jnp.asarray(0.2 * rng.normal(size=(4, 5))))
    return {"x": truth}, {
        "values": {"x": values},
        "data": {"vel": jnp.asarray(rng.normal(size=(4, 2)))},
        "noise": {
            "dyn_log_sp": jnp.asarray([0.3, -0.2, 0.5, 0.1, -0.4]),
            "vel_sp": jnp.asarray(rng.uniform(0.5, 2.0, size=(4, 2))),
        },
    }


def _vehicle_route(theta):
    import eqsmooth as eqs

    t = np.arange(4)
    nz = theta["noise"]
    graph = eqs.FactorGraph(
        [
            eqs.factors.VehicleDynamicsFactor(
                eqs.Var("x", t[:-1]),
                eqs.Var("x", t[1:]),
                eqs.DiagonalNoise(sqrt_precision=jnp.exp(nz["dyn_log_sp"])),
                dt=0.8,
            ),
            eqs.factors.VelocityMeasurementFactor(
                eqs.Var("x", t),
                theta["data"]["vel"],
                eqs.DiagonalNoise(sqrt_precision=nz["vel_sp"]),
            ),
        ]
    )
    return _graph_outputs(graph, theta["values"], _vehicle_theta()[0])


def test_graph_routes_on_vehicle_dynamics():
    """The graph routes through `VehicleDynamicsFactor`'s closed-form
    Jacobians (and the velocity factor's autodiff ones): w.r.t. the states
    (SE(2) poses in tangent coordinates, velocities), the measurements and
    the noise parameters."""
    _, _, _, names = check_gradients(_vehicle_route, _vehicle_theta()[1], GRAPH_OUTPUTS)
    assert any("['values']['x']" in n for n in names)


# --------------------------------------------------------- SE(3) landmarks


@functools.cache
def _se3_theta():
    import eqsmooth as eqs

    rng, se3, poses, mark = _poses_and_marks(eqs.SE3, 6, 1, 2, (1, 3))
    local = poses.inverse().apply(mark[np.array([0, 0])])
    # Bearings are unit vectors: the builder normalises these raw vectors, so
    # a perturbation of the raw vector is one in tangent coordinates of S².
    raw_dirs = local + 0.2 * rng.normal(size=local.shape)
    truth, theta = _truth_and_theta(se3, poses, mark, 2)
    theta["data"] |= {
        "odo": poses[:1].inverse() @ poses[1:] @ se3(1, 0.1),
        "bearing_raw": raw_dirs,
        "range": jnp.linalg.norm(local, axis=1) + 0.1,
        "gps": poses.translation() + jnp.asarray(0.1 * rng.normal(size=(2, 3))),
        "point": local + 0.1 * rng.normal(size=local.shape),
        "pose_range": jnp.asarray([1.7]),
    }
    theta["noise"] = {
        "prior_log_sp": jnp.asarray(rng.normal(size=6) * 0.2 + 1.0),
        "odo_cov_factor": jnp.asarray(0.2 * rng.normal(size=(1, 6, 6))),
        "bearing_sp": jnp.asarray(4.0),
        "br_sp": jnp.asarray([3.0, 3.0, 2.0]),
        "cauchy_k": jnp.asarray(0.7),
        "gps_sp": jnp.asarray([2.0, 3.0]),
        "point_sp": jnp.asarray([4.0, 3.0, 2.0]),
        "pose_range_sp": jnp.asarray(3.0),
    }
    return truth, theta


def _se3_graph(theta):
    import eqsmooth as eqs

    d, nz = theta["data"], theta["noise"]
    A = nz["odo_cov_factor"]
    return eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("pose", [0]),
                d["prior"],
                eqs.DiagonalNoise(sqrt_precision=jnp.exp(nz["prior_log_sp"])),
            ),
            eqs.BetweenFactor(
                eqs.Var("pose", [0]),
                eqs.Var("pose", [1]),
                d["odo"],
                eqs.SqrtInformationNoise.from_covariance(
                    A @ jnp.swapaxes(A, 1, 2) + 0.01 * jnp.eye(6)[None]
                ),
            ),
            *_se3_landmark_factors(theta),
        ]
    )


def _se3_landmark_factors(theta):
    import eqsmooth as eqs

    d, nz = theta["data"], theta["noise"]
    raw = d["bearing_raw"]
    unit = raw / jnp.linalg.norm(raw, axis=1, keepdims=True)
    pose2 = eqs.Var("pose", [0, 1])
    mark2 = eqs.Var("mark", [0, 0])
    return [
        eqs.BearingFactor(
            pose2, mark2, unit, eqs.IsotropicNoise(sqrt_precision=nz["bearing_sp"])
        ),
        eqs.BearingRangeFactor(
            pose2,
            mark2,
            unit,
            d["range"],
            eqs.CauchyNoise(
                eqs.DiagonalNoise(sqrt_precision=nz["br_sp"]), nz["cauchy_k"]
            ),
        ),
        eqs.TranslationPriorFactor(
            pose2, d["gps"], eqs.IsotropicNoise(sqrt_precision=nz["gps_sp"])
        ),
        eqs.PoseToPointFactor(
            pose2, mark2, d["point"], eqs.DiagonalNoise(sqrt_precision=nz["point_sp"])
        ),
        eqs.RangeFactor(
            eqs.Var("pose", [0]),
            eqs.Var("pose", [1]),
            d["pose_range"],
            eqs.IsotropicNoise(sqrt_precision=nz["pose_range_sp"]),
        ),
    ]


def _se3_route(theta):
    return _graph_outputs(_se3_graph(theta), theta["values"], _se3_theta()[0])


def _se3_landmark_route(theta):
    """The residual-level routes (no linearisation) on the landmark, GPS and
    range factors of the SE(3) graph: a tenth of its compile time."""
    import eqsmooth as eqs

    graph = eqs.FactorGraph(_se3_landmark_factors(theta))
    values = theta["values"]
    return jnp.stack(
        [
            graph.cost(values),
            graph.negative_log_likelihood(values),
            _summary(graph.residuals(values), 1),
            _summary(graph.whitened_residuals(values), 2),
            eqs.manifold_mse(_se3_theta()[0], values),
        ]
    )


def test_landmark_factors_on_se3():
    """cost, NLL and residuals of the SE(3) bearing (unit vectors, perturbed
    in tangent coordinates of the sphere), bearing-range (Cauchy), GPS,
    pose-to-point and pose-to-pose range factors, w.r.t. every measurement,
    noise parameter and value.

    Found by this test: the gradient of a 3-D bearing's residual w.r.t. its
    measured direction missed the motion of the residual's tangent basis
    (stopped): -0.0119 against -0.837 by central differences for the cost."""
    theta = _se3_theta()[1]
    theta = {
        "values": theta["values"],
        "data": {k: v for k, v in theta["data"].items() if k not in ("prior", "odo")},
        "noise": {
            k: v
            for k, v in theta["noise"].items()
            if k not in ("prior_log_sp", "odo_cov_factor")
        },
    }
    check_gradients(
        _se3_landmark_route,
        theta,
        ("cost", "negative_log_likelihood", "residuals", "whitened_residuals", "mse"),
    )


@pytest.mark.slow  # about a minute of compilation on 2 cores (SE(3), 2nd order)
def test_graph_routes_on_se3():
    """The routes of the SE(2) test on SE(3), linearisation included, with
    prior and between factors (per-row full sqrt-information from
    covariances) besides the factors of `test_landmark_factors_on_se3`."""
    check_gradients(_se3_route, _se3_theta()[1], GRAPH_OUTPUTS)


# ------------------------------------------------- robust kernels, Student-t


def _point_residual(x, data, params):
    return x - data


def _kernel_classes():
    import eqsmooth as eqs

    return (
        eqs.HuberNoise,
        eqs.CauchyNoise,
        eqs.TukeyNoise,
        eqs.GemanMcClureNoise,
        eqs.WelschNoise,
        eqs.DCSNoise,
        eqs.FairNoise,
        eqs.L2WithDeadZoneNoise,
        eqs.TruncatedQuadraticNoise,
    )


# Whitened residual norms of the rows of every kernel's stack: an exact zero,
# one inside every kernel's scale, one beyond it, and a gross outlier (beyond
# the underflow of Welsch's weight). Every one is far from a kink.
_NORMS = np.array([0.0, 0.45, 2.5, 40.0])


@functools.cache
def _kernel_theta(exact_zero_fair=False):
    """The kernels' parameters. Fair's first row is an exact zero only with
    `exact_zero_fair`: its IRLS weight `1/(1 + ‖e‖/k)` is not twice
    differentiable in `e` at zero, and the differences of the linearisation
    there have an O(h) error (6e-6 relative) that is not the gradient's."""
    rng = np.random.default_rng(2)
    values = jnp.asarray(rng.normal(size=(4, 2)))
    theta = {"values": {"p": values}, "data": {}, "noise": {}}
    names = [c.__name__ for c in _kernel_classes()] + ["StudentTNoise"]
    for name in names:
        log_sp = jnp.asarray(0.3 * rng.normal(size=2))
        if name in _ISOTROPIC_BASE:
            log_sp = jnp.full(2, log_sp[0])
        u = rng.normal(size=(4, 2))
        u = u / np.linalg.norm(u, axis=1, keepdims=True)
        # data = values − R⁻¹ e with ‖e‖ = the row's norm (scale 1 below).
        norms = _NORMS.copy()
        if name == "FairNoise" and not exact_zero_fair:
            norms[0] = 0.05
        e = u * norms[:, None]
        theta["data"][name] = values - jnp.asarray(e) / jnp.exp(log_sp)[None]
        theta["noise"][name] = {"log_sp": log_sp, "scale": jnp.asarray(1.0)}
    # Per-row (heteroscedastic) scales on one kernel.
    theta["noise"]["HuberNoise"]["scale"] = jnp.asarray([1.0, 1.1, 0.9, 1.2])
    theta["noise"]["StudentTNoise"]["scale"] = jnp.asarray(4.0)  # ν
    return theta


# The base noise of each kernel, built by each public constructor in turn
# (all equal to DiagonalNoise(sqrt_precision=exp(log_sp))).
_ISOTROPIC_BASE = ("WelschNoise", "DCSNoise")


def _base_noise(name, log_sp):
    import eqsmooth as eqs

    if name == "HuberNoise":
        return eqs.DiagonalNoise.from_sigmas(jnp.exp(-log_sp))
    if name == "CauchyNoise":
        return eqs.DiagonalNoise.from_variances(jnp.exp(-2 * log_sp))
    if name == "TukeyNoise":
        return eqs.DiagonalNoise.from_precision(jnp.exp(2 * log_sp))
    if name == "GemanMcClureNoise":
        return eqs.SqrtInformationNoise.from_information(jnp.diag(jnp.exp(2 * log_sp)))
    if name == "WelschNoise":
        return eqs.IsotropicNoise.from_sigma(jnp.exp(-log_sp[0]))
    if name == "DCSNoise":
        return eqs.IsotropicNoise.from_precision(jnp.exp(2 * log_sp[0]))
    return eqs.DiagonalNoise(sqrt_precision=jnp.exp(log_sp))


def _kernel_graph(theta):
    import eqsmooth as eqs

    rows = eqs.Var("p", [0, 1, 2, 3])
    factors = []
    for cls in _kernel_classes() + (eqs.StudentTNoise,):
        name = cls.__name__
        nz = theta["noise"][name]
        base = _base_noise(name, nz["log_sp"])
        if cls is eqs.StudentTNoise:
            noise = cls(base, nz["scale"], dim=2)
        else:
            noise = cls(base, nz["scale"])
        data = theta["data"][name]
        factors.append(eqs.FunctionFactor(_point_residual, (rows,), noise, data=data))
    return eqs.FactorGraph(factors)


def _kernel_route(theta):
    return _graph_outputs(
        _kernel_graph(theta), theta["values"], _kernel_theta()["values"]
    )


def test_robust_kernels_and_student_t():
    """Every robust kernel (and Student-t): cost, NLL and the linearisation
    (residuals and Jacobian blocks weighted by √ρ') w.r.t. the kernel's scale
    (ν for Student-t), its base noise, the data and the values, on rows with
    a zero residual (Fair: a small one), an inlier, an outlier and a gross
    outlier.

    Found by this test: Tukey's gradients were NaN (every parameter) through
    the linearisation of a graph with an outlier beyond its scale, and
    Welsch's with an outlier beyond 27 scales (its weight underflows to 0)."""
    check_gradients(_kernel_route, _kernel_theta(), GRAPH_OUTPUTS)


def _tangent_cost_gradient(values):
    graph = _kernel_graph(_kernel_theta(exact_zero_fair=True))
    return jax.grad(graph.cost)(values)["p"].reshape(-1)


def test_cost_hessian_of_every_kernel():
    """`jax.hessian` of the cost (forward over reverse, what the exact-Hessian
    implicit adjoint applies) against central differences of its gradient,
    with a zero residual in every stack. Found by this test: the Fair
    kernel's Hessian at a zero residual was 0 instead of the identity (along
    the test's first direction: 0.4903 against 0.6288 by differences)."""
    check_gradients(
        _tangent_cost_gradient,
        _kernel_theta(exact_zero_fair=True)["values"],
        [f"dcost/dp[{i}]" for i in range(8)],
        mode="fwd",
        # Small steps: Fair's gradient `e/(1 + ‖e‖/k)` has an `e‖e‖` term, whose
        # central difference at zero is off by O(h).
        h=1e-6,
    )


@functools.cache
def _kernel_forward():
    return gradients(_kernel_route, _kernel_theta(), mode="fwd")


_LINEARIZE_ROWS = [
    GRAPH_OUTPUTS.index(n) for n in ("linearize.residual", "linearize.jacobians")
]


def test_robust_kernels_forward_mode():
    """The routes of `test_robust_kernels_and_student_t` in forward mode
    (`jax.jvp`, `jax.jacfwd`), but for the linearisation's residuals and
    Jacobian blocks (next test)."""
    rows = [i for i in range(len(GRAPH_OUTPUTS)) if i not in _LINEARIZE_ROWS]
    assert_gradients(_kernel_forward(), GRAPH_OUTPUTS, rows=rows)


def test_linearize_forward_mode_with_zero_weight_rows():
    # The linearisation weights rows by √ρ'; its forward-mode derivative was
    # 0·∞ = NaN on rows with ρ' = 0 (Tukey and Welsch outliers, dead-zone
    # inliers) until a safe square root replaced it.
    # A truncated quadratic's residual weight is 1 inside its scale and 0
    # beyond: only its cost (not these rows) moves with the scale.
    assert_gradients(
        _kernel_forward(),
        GRAPH_OUTPUTS,
        rows=_LINEARIZE_ROWS,
        zero_leaves=("TruncatedQuadraticNoise']['scale",),
    )


# ------------------------------------------------------------ EKF and RTS


def _position_residual(x, data, params):
    return x.pose.translation() - data


_VEL_ROWS = np.array([0, 1, 2, 3])
_POS_ROWS = np.array([0, 2, 3])  # none at t = 1


@functools.cache
def _ekf_theta():
    import eqsmooth as eqs

    rng = np.random.default_rng(3)
    steps = eqs.SE2.exp(
        jnp.asarray([[0.8, 0.0, 0.3], [0.9, 0.0, -0.2], [0.7, 0.0, 0.1]])
    )
    poses = [eqs.SE2.identity((1,), dtype=jnp.float64)]
    for k in range(3):
        poses.append(poses[-1] @ steps[k : k + 1])
    poses = eqs.SE2(jnp.concatenate([p.parameters() for p in poses]))
    truth = eqs.factors.VehicleState.from_poses(poses)
    vel = truth.velocity[_VEL_ROWS] + 0.05 * jnp.asarray(rng.normal(size=(4, 2)))
    pos = poses.translation()[_POS_ROWS] + 0.1 * jnp.asarray(rng.normal(size=(3, 2)))
    mean0 = eqs.factors.VehicleState(
        poses[0] @ eqs.SE2.exp(jnp.asarray([0.05, -0.05, 0.02])),
        truth.velocity[0] + 0.1,
    )
    return truth, {
        "initial": {
            "mean": mean0,
            "cov_factor": jnp.asarray(0.1 * rng.normal(size=(5, 5))),
        },
        "data": {"vel": vel, "pos": pos},
        "noise": {
            "dyn_log_sp": jnp.asarray([2.0, 2.5, 2.2, 1.5, 1.8]),
            "vel_sp": jnp.asarray(rng.uniform(5.0, 15.0, size=(4, 2))),
            "pos_cov_factor": jnp.asarray([[0.1, 0.0], [0.03, 0.2]]),
        },
    }


def _ekf_route(theta):
    import eqsmooth as eqs

    truth = _ekf_theta()[0]
    nz, d, init = theta["noise"], theta["data"], theta["initial"]
    t = np.arange(4)
    transition = eqs.factors.VehicleDynamicsFactor(
        eqs.Var("x", t[:-1]),
        eqs.Var("x", t[1:]),
        eqs.DiagonalNoise(sqrt_precision=jnp.exp(nz["dyn_log_sp"])),
    )
    velocity = eqs.factors.VelocityMeasurementFactor(
        eqs.Var("x", _VEL_ROWS),
        d["vel"],
        eqs.DiagonalNoise(sqrt_precision=nz["vel_sp"]),
    )
    L = nz["pos_cov_factor"]
    position = eqs.FunctionFactor(
        _position_residual,
        (eqs.Var("x", _POS_ROWS),),
        eqs.SqrtInformationNoise.from_covariance(L @ L.T),
        data=d["pos"],
    )
    A = init["cov_factor"]
    sol = eqs.filters.ekf(
        transition, [velocity, position], init["mean"], A @ A.T + 0.05 * jnp.eye(5)
    )
    rts = eqs.filters.rts_smoother(sol)
    return jnp.stack(
        [
            eqs.filters.ekf_mse_loss(sol, truth, jnp.asarray(2.0)),
            eqs.filters.ekf_marginal_nll(sol, truth),
            eqs.filters.ekf_innovation_nll(sol),
            _summary(eqs.local(truth, sol.mean, batch_ndim=1), 10),
            _summary(sol.covariance, 11),
            _summary(eqs.local(truth, sol.predicted_mean, batch_ndim=1), 12),
            _summary(sol.predicted_covariance, 13),
            _summary(sol.transition_jacobian, 14),
            _summary(sol.innovations, 15),
            _summary(sol.innovation_covariances, 16),
            _summary(sol.step_log_likelihood, 17),
            _summary(eqs.local(truth, rts.mean, batch_ndim=1), 18),
            _summary(rts.covariance, 19),
            eqs.filters.ekf_mse_loss(rts, truth),
            eqs.filters.ekf_marginal_nll(rts, truth),
        ]
    )


EKF_OUTPUTS = (
    "ekf_mse_loss",
    "ekf_marginal_nll",
    "ekf_innovation_nll",
    "EKFSolution.mean (tangent)",
    "EKFSolution.covariance",
    "EKFSolution.predicted_mean (tangent)",
    "EKFSolution.predicted_covariance",
    "EKFSolution.transition_jacobian",
    "EKFSolution.innovations",
    "EKFSolution.innovation_covariances",
    "EKFSolution.step_log_likelihood",
    "RTSSolution.mean (tangent)",
    "RTSSolution.covariance",
    "ekf_mse_loss(rts)",
    "ekf_marginal_nll(rts)",
)


def test_ekf_rts_and_their_losses():
    """Every EKF and RTS output and the three filter losses on an SE(2)
    vehicle (pose + velocities, tangent dimension 5) with two measurement
    stacks (one missing at t = 1): w.r.t. the
    transition noise, per-row measurement noise, a full measurement
    sqrt-information (from a covariance), the measurements, the initial mean
    (tangent coordinates) and the initial covariance."""
    check_gradients(_ekf_route, _ekf_theta()[1], EKF_OUTPUTS)


# ------------------------------------------------------ the Laplace evidence


@functools.cache
def _laplace_problem():
    from helpers import se2_loop

    import eqsmooth as eqs

    graph, init, _ = se2_loop(0, N=4, noise_scale=0.3)  # nonzero residuals
    between = graph.factors[0]
    assert isinstance(between, eqs.BetweenFactor)
    theta = {
        "values": init,
        "data": {"odo": between.measurement},
        # Not the gauge prior's noise: its log-determinant cancels that of
        # the normal matrix exactly, so the evidence does not depend on it.
        "noise": {"odo_log_sp": jnp.log(jnp.asarray([10.0, 8.0, 20.0]))},
    }
    # Converged to rounding, so that differences of re-solved evidences are
    # differences of the evidence.
    solver = eqs.GaussNewton(eqs.DenseCholesky(), ftol=0.0, gtol=0.0, xtol=0.0)
    return graph, theta, solver


def _laplace_graph(graph, theta):
    import eqsmooth as eqs

    between, prior = graph.factors
    return eqs.FactorGraph(
        [
            eqs.BetweenFactor(
                between.variables[0],
                between.variables[1],
                theta["data"]["odo"],
                eqs.DiagonalNoise(sqrt_precision=jnp.exp(theta["noise"]["odo_log_sp"])),
            ),
            prior,
        ]
    )


def _laplace_route(theta):
    import eqsmooth as eqs

    base, _, solver = _laplace_problem()
    evidence, _ = eqs.discover.laplace_log_marginal(
        _laplace_graph(base, theta), theta["values"], solver, max_steps=30
    )
    return evidence[None]


@pytest.mark.slow  # ~25 s of compilation on 2 cores (re-solved MAPs under vmap)
def test_laplace_evidence():
    """`laplace_log_marginal` (which is `laplace_at_map` at the solved MAP)
    w.r.t. noise parameters and measurements (SE(2), tangent coordinates)
    against differences of re-solved evidences, on a nonlinear SE(2) loop
    with nonzero residuals; its gradient w.r.t. the initial values is zero
    (the MAP does not depend on them).

    Found by this test: the gradient w.r.t. the measurements was -14.15126
    against -14.15055 by differences of re-solved evidences (5e-5 relative):
    the Gauss-Newton correction approximated the MAP's derivative. The same
    fault on a Euclidean chain fails the default-run
    `test_discover.py::test_scores_match_finite_differences_nonlinear`."""
    check_gradients(
        _laplace_route,
        _laplace_problem()[1],
        ("laplace_log_marginal",),
        zero_leaves=("['values']",),
    )
