import numpy as np

from ..factors import AbstractFactor, PriorFactor
from ..lie import SE2, SE3
from ._pose_graph import POSE, PoseGraph


def _import_gtsam():
    try:
        import gtsam
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError(
            "this function needs GTSAM: pip install gtsam (or eqsmooth[bench])"
        ) from e
    return gtsam


# eqsmooth's SE(3) tangent is (v, ω); GTSAM's Pose3 tangent is (ω, v).
_SE3_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])


def _gtsam_poses(gtsam, kind: str, params: np.ndarray) -> list:
    if kind == "se2":
        theta = np.arctan2(params[:, 1], params[:, 0])
        return [
            gtsam.Pose2(float(x), float(y), float(t))
            for x, y, t in zip(params[:, 2], params[:, 3], theta)
        ]
    return [
        gtsam.Pose3(gtsam.Rot3.Quaternion(*map(float, p[:4])), gtsam.Point3(*p[4:]))
        for p in params
    ]


def _params(values) -> np.ndarray:
    if isinstance(values, dict):
        values = values[POSE]
    if isinstance(values, SE2):
        return np.asarray(values.unit_complex_xy, np.float64)
    if isinstance(values, SE3):
        return np.asarray(values.wxyz_xyz, np.float64)
    raise TypeError(f"expected SE2/SE3 poses, got {type(values).__name__}")


def _information(factor: AbstractFactor, kind: str, what: str) -> np.ndarray:
    """Each row's information matrix `RᵀR`, `(n, d, d)`, in GTSAM's tangent
    order, from the factor's noise model (Gaussian and unmasked)."""
    noise = factor.noise
    if not noise.is_gaussian or noise.active_rows() is not None:
        raise TypeError(
            f"to_gtsam: {what} need a Gaussian noise model without masked rows, "
            f"got {noise.name}"
        )
    d = 3 if kind == "se2" else 6
    R = np.asarray(noise.sqrt_information_rows(factor.num_rows, d), np.float64)
    info = np.swapaxes(R, 1, 2) @ R
    if kind == "se3":
        info = info[:, _SE3_TO_GTSAM][:, :, _SE3_TO_GTSAM]
    return info


def to_gtsam(pose_graph: PoseGraph, values=None):
    """Build the same problem in GTSAM (for comparisons; needs `gtsam`).

    Every edge becomes a `BetweenFactorPose2`/`BetweenFactorPose3` with the
    same information matrix (reordered to GTSAM's `(ω, v)` tangent for
    SE(3)), and the gauge prior a `PriorFactorPose2`/`PriorFactorPose3` with
    its information matrix likewise (any Gaussian noise model without masked
    rows gives its rows' square-root information), so that GTSAM's
    `graph.error(values)` equals `pose_graph.graph.cost(values)`. Keys are
    pose indices `0..N-1`.

    **Arguments:**

    - `pose_graph`: a [`eqsmooth.io.PoseGraph`][].
    - `values`: poses to convert instead of the pose graph's initial values.

    **Returns:** `(gtsam.NonlinearFactorGraph, gtsam.Values)`.
    """
    gtsam = _import_gtsam()
    kind = pose_graph.kind
    params = _params(pose_graph.values if values is None else values)
    factor = pose_graph.between
    info = _information(factor, kind, "edges")
    meas = _gtsam_poses(gtsam, kind, _params(factor.measurement))
    a, b = factor.variables
    between = gtsam.BetweenFactorPose2 if kind == "se2" else gtsam.BetweenFactorPose3
    prior = gtsam.PriorFactorPose2 if kind == "se2" else gtsam.PriorFactorPose3
    Gaussian = gtsam.noiseModel.Gaussian
    graph = gtsam.NonlinearFactorGraph()
    for i, j, z, m in zip(a.ids.tolist(), b.ids.tolist(), meas, info):
        graph.add(between(i, j, z, Gaussian.Information(m)))
    for f in pose_graph.graph.factors:
        if not isinstance(f, PriorFactor):
            continue
        poses = _gtsam_poses(gtsam, kind, _params(f.value))
        for k, p, m in zip(
            f.variables[0].ids.tolist(), poses, _information(f, kind, "priors")
        ):
            graph.add(prior(k, p, Gaussian.Information(m)))
    initial = gtsam.Values()
    for k, p in enumerate(_gtsam_poses(gtsam, kind, params)):
        initial.insert(k, p)
    return graph, initial


def from_gtsam(pose_graph: PoseGraph, values) -> dict:
    """Poses from a `gtsam.Values` keyed `0..N-1`, as an eqsmooth values dict."""
    n = pose_graph.num_poses
    if pose_graph.kind == "se2":
        rows = []
        for k in range(n):
            p = values.atPose2(k)
            rows.append([np.cos(p.theta()), np.sin(p.theta()), p.x(), p.y()])
        group = SE2
    else:
        rows = []
        for k in range(n):
            p = values.atPose3(k)
            q = p.rotation().toQuaternion()
            rows.append([q.w(), q.x(), q.y(), q.z(), *np.asarray(p.translation())])
        group = SE3
    dtype = pose_graph.values[POSE].parameters().dtype
    return {POSE: group(np.asarray(rows).astype(dtype))}
