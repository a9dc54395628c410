"""Camera models and factors: calibrations, pinhole projection, and the
monocular and stereo projection factors of bundle adjustment and visual SLAM.

Conventions (GTSAM's, so that a port keeps its numbers):

- A camera pose is an [`eqsmooth.lie.SE3`][] from the camera frame to the
    world (GTSAM's `PinholeCamera` pose); the camera looks down its `+z`
    axis, `x` to the right and `y` down the image.
- A point `P` (world frame) is seen at `p = pose⁻¹ · P`, its normalised
    image coordinates are `(p_x / p_z, p_y / p_z)`, and a calibration maps
    them to pixels.
- Residuals are "prediction minus measurement", in pixels.
- Jacobians are given in closed form (the factors are
    [`eqsmooth.factors.AbstractAnalyticFactor`][]s), w.r.t. right
    perturbations in eqsmooth's SE(3) tangent order `(v, ω)`: translation
    first. GTSAM orders a `Pose3` tangent `(ω, v)`, so its `H_pose` is ours
    with the two column blocks swapped.

**Cheirality.** A point at depth `p_z ≤ min_depth` (behind the camera or on
its plane) has no projection. The default `min_depth` is `1e-6` (GTSAM's
threshold is 0, which lets a point at depth 1e-9 project to ~1e11 pixels;
pass `min_depth=0.0` for GTSAM's rule). [`eqsmooth.factors.project`][] returns NaN
pixels there with an `in_front` flag. A factor row whose point is not in
front is *inert*: its Jacobians are zero, so it takes no part in the step,
and its residual is GTSAM's constant `2 fx` per coordinate (without a
derivative), not zero: a zero residual would make moving a point behind a
camera lower the cost, and Levenberg-Marquardt would accept that step and
then report success with the point stuck there. The constant makes such a
step raise the cost instead, so it is rejected. Which rows are inert is
read with the factors' `in_front(values)` (one flag per row, e.g. at a
solution) or named by [`eqsmooth.factors.check_cheirality`][] (a solve does
not fail on them: a point behind every camera that sees it is left where it
started); `throw_cheirality=True` raises instead (`eqx.error_if`, at any
evaluation, trial steps included: GTSAM's `throwCheirality`).
"""

import abc
from collections.abc import Callable
from typing import Any, ClassVar, Generic, NamedTuple, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, PyTree

from .._precision import matmul as mm
from ..lie import SE3
from ..lie._so3 import skew as _skew
from ..lie._utils import as_float_array
from ._factor import AbstractAnalyticFactor, shared_field
from ._graph import FactorGraph, gather
from ._noise import AbstractNoiseModel, is_concrete
from ._variables import Var


# ------------------------------------------------------------------ calibrations


def _scalar(name: str, field: str, value) -> Array:
    x = as_float_array(value)
    if x.shape != ():
        raise ValueError(
            f"{name}.{field} must be a scalar (one camera; for several cameras "
            f"use one factor stack per camera), got shape {x.shape}"
        )
    return x


def _check_focal(name: str, **fields: Array) -> None:
    """Focal lengths (and a baseline) must be positive and finite; checked when
    concrete (a traced calibration is the user's learnable parameter)."""
    for field, value in fields.items():
        if is_concrete(value):
            v = float(np.asarray(value))
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}.{field} must be positive and finite, got {v}")


def _check_finite(name: str, **fields: Array) -> None:
    for field, value in fields.items():
        if is_concrete(value) and not np.isfinite(np.asarray(value)):
            raise ValueError(f"{name}.{field} must be finite, got {value}")


class AbstractCalibration(eqx.Module):
    """Intrinsics of a monocular camera: the map from normalised image
    coordinates `(x, y) = (p_x / p_z, p_y / p_z)` to pixels `(u, v)`.

    Every parameter is a scalar array leaf, so a calibration is learnable:
    put it in a factor and differentiate through the solve w.r.t. it.
    """

    fx: eqx.AbstractVar[Float[Array, ""]]

    @abc.abstractmethod
    def uncalibrate(self, xy: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        """Pixels `(u, v)` of normalised image coordinates `xy`."""

    @abc.abstractmethod
    def uncalibrate_jacobian(
        self, xy: Float[Array, "*batch 2"]
    ) -> Float[Array, "*batch 2 2"]:
        """`∂(u, v) / ∂(x, y)` at `xy`."""

    @abc.abstractmethod
    def vector(self) -> Float[Array, " k"]:
        """The parameters as one vector, in GTSAM's order."""


def _affine(cal, xy: Array) -> Array:
    """`K · (x, y, 1)` with `K = [[fx, s, u0], [0, fy, v0]]`."""
    x, y = xy[..., 0], xy[..., 1]
    u = cal.fx * x + cal.skew * y + cal.u0
    v = cal.fy * y + cal.v0
    return jnp.stack([u, v], axis=-1)


def _unaffine(cal, uv: ArrayLike) -> Array:
    """`K⁻¹ · (u, v, 1)`, the inverse of `_affine`."""
    uv = jnp.asarray(uv)
    y = (uv[..., 1] - cal.v0) / cal.fy
    x = (uv[..., 0] - cal.u0 - cal.skew * y) / cal.fx
    return jnp.stack([x, y], axis=-1)


def _affine_matrix(cal, like: Array) -> Array:
    zero = jnp.zeros_like(cal.fx)
    k = jnp.stack([jnp.stack([cal.fx, cal.skew]), jnp.stack([zero, cal.fy])])
    return jnp.broadcast_to(k, (*like.shape[:-1], 2, 2))


class Cal3_S2(AbstractCalibration):
    """Five-parameter pinhole calibration (GTSAM's `Cal3_S2`):
    `u = fx x + s y + u0`, `v = fy y + v0`.

    **Arguments:**

    - `fx`, `fy`: focal lengths in pixels (positive).
    - `skew`: skew `s` (0 for square pixel axes).
    - `u0`, `v0`: principal point in pixels.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    skew: Float[Array, ""]
    u0: Float[Array, ""]
    v0: Float[Array, ""]

    def __init__(
        self,
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        skew: Float[ArrayLike, ""] = 0.0,
        u0: Float[ArrayLike, ""] = 0.0,
        v0: Float[ArrayLike, ""] = 0.0,
    ):
        name = "Cal3_S2"
        self.fx, self.fy = _scalar(name, "fx", fx), _scalar(name, "fy", fy)
        self.skew = _scalar(name, "skew", skew)
        self.u0, self.v0 = _scalar(name, "u0", u0), _scalar(name, "v0", v0)

    def __check_init__(self):
        _check_focal("Cal3_S2", fx=self.fx, fy=self.fy)
        _check_finite("Cal3_S2", skew=self.skew, u0=self.u0, v0=self.v0)

    def uncalibrate(self, xy: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        return _affine(self, xy)

    def uncalibrate_jacobian(
        self, xy: Float[Array, "*batch 2"]
    ) -> Float[Array, "*batch 2 2"]:
        return _affine_matrix(self, xy)

    def calibrate(self, uv: Float[ArrayLike, "*batch 2"]) -> Float[Array, "*batch 2"]:
        """Normalised image coordinates of pixels `uv` (the inverse of
        `uncalibrate`): the direction `(x, y, 1)` of the ray through them."""
        return _unaffine(self, uv)

    def matrix(self) -> Float[Array, "3 3"]:
        """The calibration matrix `K` (3×3)."""
        zero, one = jnp.zeros_like(self.fx), jnp.ones_like(self.fx)
        return jnp.stack(
            [
                jnp.stack([self.fx, self.skew, self.u0]),
                jnp.stack([zero, self.fy, self.v0]),
                jnp.stack([zero, zero, one]),
            ]
        )

    def vector(self) -> Float[Array, " 5"]:
        """`(fx, fy, s, u0, v0)`."""
        return jnp.stack([self.fx, self.fy, self.skew, self.u0, self.v0])


class Cal3DS2(AbstractCalibration):
    """Pinhole calibration with radial-tangential (Brown-Conrady) distortion,
    GTSAM's `Cal3DS2` (OpenCV's first four distortion coefficients).

    With `r² = x² + y²` and `g = 1 + k1 r² + k2 r⁴`, the distorted
    coordinates are `x' = g x + 2 p1 x y + p2 (r² + 2x²)` and
    `y' = g y + p1 (r² + 2y²) + 2 p2 x y`, and the pixel is
    `u = fx x' + s y' + u0`, `v = fy y' + v0`.

    **Arguments:**

    - `fx`, `fy`, `skew`, `u0`, `v0`: as [`eqsmooth.factors.Cal3_S2`][].
    - `k1`, `k2`: radial distortion coefficients.
    - `p1`, `p2`: tangential distortion coefficients.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    skew: Float[Array, ""]
    u0: Float[Array, ""]
    v0: Float[Array, ""]
    k1: Float[Array, ""]
    k2: Float[Array, ""]
    p1: Float[Array, ""]
    p2: Float[Array, ""]

    def __init__(
        self,
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        skew: Float[ArrayLike, ""] = 0.0,
        u0: Float[ArrayLike, ""] = 0.0,
        v0: Float[ArrayLike, ""] = 0.0,
        k1: Float[ArrayLike, ""] = 0.0,
        k2: Float[ArrayLike, ""] = 0.0,
        p1: Float[ArrayLike, ""] = 0.0,
        p2: Float[ArrayLike, ""] = 0.0,
    ):
        name = "Cal3DS2"
        self.fx, self.fy = _scalar(name, "fx", fx), _scalar(name, "fy", fy)
        self.skew = _scalar(name, "skew", skew)
        self.u0, self.v0 = _scalar(name, "u0", u0), _scalar(name, "v0", v0)
        self.k1, self.k2 = _scalar(name, "k1", k1), _scalar(name, "k2", k2)
        self.p1, self.p2 = _scalar(name, "p1", p1), _scalar(name, "p2", p2)

    def __check_init__(self):
        _check_focal("Cal3DS2", fx=self.fx, fy=self.fy)
        _check_finite(
            "Cal3DS2",
            skew=self.skew,
            u0=self.u0,
            v0=self.v0,
            k1=self.k1,
            k2=self.k2,
            p1=self.p1,
            p2=self.p2,
        )

    def distort(self, xy: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        """The distorted normalised coordinates `(x', y')` of `xy`."""
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        g = 1.0 + r2 * (self.k1 + self.k2 * r2)
        xd = g * x + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x)
        yd = g * y + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y
        return jnp.stack([xd, yd], axis=-1)

    def _distort_jacobian(self, xy: Array) -> Array:
        x, y = xy[..., 0], xy[..., 1]
        r2 = x * x + y * y
        g = 1.0 + r2 * (self.k1 + self.k2 * r2)
        dg = 2.0 * (self.k1 + 2.0 * self.k2 * r2)  # ∂g/∂x = dg x, ∂g/∂y = dg y
        dxx = g + dg * x * x + 2.0 * self.p1 * y + 6.0 * self.p2 * x
        dxy = dg * x * y + 2.0 * self.p1 * x + 2.0 * self.p2 * y
        dyy = g + dg * y * y + 6.0 * self.p1 * y + 2.0 * self.p2 * x
        return jnp.stack(
            [jnp.stack([dxx, dxy], axis=-1), jnp.stack([dxy, dyy], axis=-1)], axis=-2
        )

    def uncalibrate(self, xy: Float[Array, "*batch 2"]) -> Float[Array, "*batch 2"]:
        return _affine(self, self.distort(xy))

    def uncalibrate_jacobian(
        self, xy: Float[Array, "*batch 2"]
    ) -> Float[Array, "*batch 2 2"]:
        return mm(_affine_matrix(self, xy), self._distort_jacobian(xy))

    def calibrate(
        self, uv: Float[ArrayLike, "*batch 2"], *, iterations: int = 10
    ) -> Float[Array, "*batch 2"]:
        """Normalised image coordinates of pixels `uv`: the distortion is
        inverted by `iterations` Newton steps from the undistorted guess
        (ample for the distortion of real lenses inside the image)."""
        target = _unaffine(self, uv)
        xy = target
        for _ in range(iterations):
            e = self.distort(xy) - target
            j = self._distort_jacobian(xy)
            det = j[..., 0, 0] * j[..., 1, 1] - j[..., 0, 1] * j[..., 1, 0]
            dx = (j[..., 1, 1] * e[..., 0] - j[..., 0, 1] * e[..., 1]) / det
            dy = (j[..., 0, 0] * e[..., 1] - j[..., 1, 0] * e[..., 0]) / det
            xy = xy - jnp.stack([dx, dy], axis=-1)
        return xy

    def vector(self) -> Float[Array, " 9"]:
        """`(fx, fy, s, u0, v0, k1, k2, p1, p2)`."""
        return jnp.stack(
            [
                self.fx,
                self.fy,
                self.skew,
                self.u0,
                self.v0,
                self.k1,
                self.k2,
                self.p1,
                self.p2,
            ]
        )


class Cal3_S2Stereo(eqx.Module):
    """Calibration of a rectified stereo pair (GTSAM's `Cal3_S2Stereo`): both
    cameras share `fx`, `fy`, `u0`, `v0`; the right one sits `baseline` along
    the left one's `x` axis.

    A point `p` in the left camera's frame is seen at
    `(uL, uR, v) = (u0 + fx p_x / p_z, u0 + fx (p_x − b) / p_z, v0 + fy p_y / p_z)`.
    GTSAM's `Cal3_S2Stereo(fx, fy, s, u0, v0, b)` also holds a skew, which its
    `StereoCamera` ignores; it is left out here (so a positional port of the
    six arguments fails loudly rather than shifting them).

    **Arguments:**

    - `fx`, `fy`: focal lengths in pixels (positive).
    - `u0`, `v0`: principal point in pixels.
    - `baseline`: distance between the two camera centres (positive).
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    u0: Float[Array, ""]
    v0: Float[Array, ""]
    baseline: Float[Array, ""]

    def __init__(
        self,
        fx: Float[ArrayLike, ""],
        fy: Float[ArrayLike, ""],
        u0: Float[ArrayLike, ""],
        v0: Float[ArrayLike, ""],
        baseline: Float[ArrayLike, ""],
    ):
        name = "Cal3_S2Stereo"
        self.fx, self.fy = _scalar(name, "fx", fx), _scalar(name, "fy", fy)
        self.u0, self.v0 = _scalar(name, "u0", u0), _scalar(name, "v0", v0)
        self.baseline = _scalar(name, "baseline", baseline)

    def __check_init__(self):
        _check_focal("Cal3_S2Stereo", fx=self.fx, fy=self.fy, baseline=self.baseline)
        _check_finite("Cal3_S2Stereo", u0=self.u0, v0=self.v0)

    def vector(self) -> Float[Array, " 5"]:
        """`(fx, fy, u0, v0, baseline)`."""
        return jnp.stack([self.fx, self.fy, self.u0, self.v0, self.baseline])


# ------------------------------------------------------------------ projection


_DEFAULT_MIN_DEPTH = 1e-6


def _camera_pose(pose: SE3, body_P_sensor: SE3 | None) -> SE3:
    return pose if body_P_sensor is None else pose @ body_P_sensor


def _safe_depth(p: Array, min_depth: float) -> tuple[Array, Array]:
    """`(front, z)`: whether the point is in front, and its depth there (1
    elsewhere, so that the untaken branch stays finite for autodiff)."""
    front = p[..., 2] > min_depth
    return front, jnp.where(front, p[..., 2], jnp.ones_like(p[..., 2]))


def _mono_pixels(cal: AbstractCalibration, p: Array, z: Array) -> Array:
    return cal.uncalibrate(p[..., :2] / z[..., None])


def _mono_d(cal: AbstractCalibration, p: Array, z: Array) -> Array:
    xy = p[:2] / z
    # ∂(x, y)/∂p = [[1, 0, −x], [0, 1, −y]] / z
    dxy = jnp.concatenate([jnp.eye(2, dtype=p.dtype), -xy[:, None]], axis=1) / z
    return mm(cal.uncalibrate_jacobian(xy), dxy)


def _stereo_pixels(k: Cal3_S2Stereo, p: Array, z: Array) -> Array:
    x, y = p[..., 0] / z, p[..., 1] / z
    xr = (p[..., 0] - k.baseline) / z
    return jnp.stack([k.u0 + k.fx * x, k.u0 + k.fx * xr, k.v0 + k.fy * y], axis=-1)


def _stereo_d(k: Cal3_S2Stereo, p: Array, z: Array) -> Array:
    x, y = p[0] / z, p[1] / z
    xr = (p[0] - k.baseline) / z
    zero = jnp.zeros_like(x)
    return (
        jnp.stack(
            [
                jnp.stack([k.fx, zero, -k.fx * x]),
                jnp.stack([k.fx, zero, -k.fx * xr]),
                jnp.stack([zero, k.fy, -k.fy * y]),
            ]
        )
        / z
    )


class _Camera(NamedTuple):
    """What a monocular and a stereo camera differ in; everything else about
    projecting a point, and the two factors, is shared."""

    calibration: type  # the calibration class it takes
    calibration_names: str  # the same, in words, for errors
    width: int  # pixel coordinates per point
    # The pixels of camera-frame points `p` (`(*batch, 3)`) at safe depths
    # `z` (see `_safe_depth`), and their derivative w.r.t. one `p` (`width×3`).
    pixels: Callable[[Any, Array, Array], Array]
    pixels_d: Callable[[Any, Array, Array], Array]


_MONO = _Camera(AbstractCalibration, "a Cal3_S2 or Cal3DS2", 2, _mono_pixels, _mono_d)
_STEREO = _Camera(Cal3_S2Stereo, "a Cal3_S2Stereo", 3, _stereo_pixels, _stereo_d)


def _check_calibration(what: str, calibration, camera: _Camera) -> None:
    if not isinstance(calibration, camera.calibration):
        raise TypeError(
            f"{what} must be {camera.calibration_names}, got "
            f"{type(calibration).__name__}"
        )


def _project(name: str, camera: _Camera, pose, point, calibration, min_depth):
    """`project` and `project_stereo`, for `camera`."""
    if not isinstance(pose, SE3):
        raise TypeError(f"{name}: pose must be an SE3, got {type(pose).__name__}")
    _check_calibration(f"{name}: calibration", calibration, camera)
    p = pose.inverse().apply(jnp.asarray(point))
    front, z = _safe_depth(p, min_depth)
    pixels = camera.pixels(calibration, p, z)
    return jnp.where(front[..., None], pixels, jnp.nan), front


def project(
    pose: SE3,
    point: Float[ArrayLike, "*batch 3"],
    calibration: AbstractCalibration,
    *,
    min_depth: float = _DEFAULT_MIN_DEPTH,
) -> tuple[Float[Array, "*batch 2"], Bool[Array, "*batch"]]:
    """Project world points into a camera (GTSAM's `PinholeCamera.projectSafe`).

    **Arguments:**

    - `pose`: the camera's pose, camera-to-world, an [`eqsmooth.lie.SE3`][]
        (any batch shape broadcasting with the points').
    - `point`: world points, `(*batch, 3)`.
    - `calibration`: an [`eqsmooth.factors.Cal3_S2`][] or
        [`eqsmooth.factors.Cal3DS2`][].
    - `min_depth`: points at depth `≤ min_depth` in the camera frame are not
        in front of it.

    **Returns:** `(pixels, in_front)`: pixels `(*batch, 2)`, NaN where the
    point is not in front of the camera (so that an unchecked use shows),
    and the flags `(*batch,)`.
    """
    return _project("project", _MONO, pose, point, calibration, min_depth)


def project_stereo(
    pose: SE3,
    point: Float[ArrayLike, "*batch 3"],
    calibration: Cal3_S2Stereo,
    *,
    min_depth: float = _DEFAULT_MIN_DEPTH,
) -> tuple[Float[Array, "*batch 3"], Bool[Array, "*batch"]]:
    """Project world points into a rectified stereo camera (GTSAM's
    `StereoCamera.project`).

    **Arguments:**

    - `pose`: the left camera's pose, camera-to-world, an
        [`eqsmooth.lie.SE3`][].
    - `point`: world points, `(*batch, 3)`.
    - `calibration`: an [`eqsmooth.factors.Cal3_S2Stereo`][].
    - `min_depth`: as for [`eqsmooth.factors.project`][].

    **Returns:** `(uvv, in_front)`: `(uL, uR, v)` of shape `(*batch, 3)`, NaN
    where the point is not in front of the camera, and the flags.
    """
    return _project("project_stereo", _STEREO, pose, point, calibration, min_depth)


def _point_jacobians(pose: SE3, p: Array) -> tuple[Array, Array]:
    """`∂p/∂δ_pose` (3×6, tangent `(v, ω)`) and `∂p/∂P` (3×3) of the camera-frame
    point `p = pose⁻¹ · P`: with `pose ⊕ δ = pose · exp(δ)`,
    `p(δ) ≈ p − v + p × ω`."""
    eye = jnp.eye(3, dtype=p.dtype)
    return (
        jnp.concatenate([-eye, _skew(p)], axis=-1),
        pose.rotation().inverse().as_matrix(),
    )


def _check_row(name: str, pose, point) -> None:
    if not isinstance(pose, SE3):
        raise TypeError(
            f"{name}: the pose variable must hold SE3 values (camera-to-world), got "
            f"{type(pose).__name__}"
        )
    if jnp.shape(point) != (3,):
        raise ValueError(
            f"{name}: the point variable must hold arrays of shape (3,), got "
            f"{jnp.shape(point)}"
        )


def _body_pose(name: str, body_P_sensor) -> SE3 | None:
    if body_P_sensor is None:
        return None
    if not isinstance(body_P_sensor, SE3) or body_P_sensor.batch_shape != ():
        raise ValueError(
            f"{name}.body_P_sensor must be one SE3 (the camera's pose in the body "
            f"frame, shared by every row), got {body_P_sensor!r}"
        )
    return body_P_sensor


def _min_depth(name: str, min_depth) -> float:
    md = float(min_depth)
    if not (np.isfinite(md) and md >= 0):
        raise ValueError(f"{name}.min_depth must be finite and >= 0, got {min_depth}")
    return md


def _pixels(name: str, measured, k: int) -> Array:
    measured = jnp.asarray(measured)
    if measured.ndim != 2 or measured.shape[1] != k:
        raise ValueError(
            f"{name}.measured must have shape (n, {k}) (one row per factor), got "
            f"{measured.shape}"
        )
    if is_concrete(measured):
        ok = np.isfinite(np.asarray(measured)).all(axis=1)
        if not ok.all():
            bad = np.flatnonzero(~ok)[:8].tolist()
            raise ValueError(
                f"{name}.measured: rows {bad} are not finite (nan or inf); mask a "
                "missing measurement with MaskedNoise instead"
            )
    return measured


def _cheirality(name: str, r: Array, front: Array, throw: bool) -> Array:
    if not throw:
        return r
    return eqx.error_if(
        r,
        ~front,
        f"{name}: a point is not in front of its camera (depth <= min_depth); "
        "with throw_cheirality=False the row is inert instead (zero Jacobians, "
        "constant residual) and factor.in_front(values) names such rows",
    )


def _in_front(factor, values: dict[str, PyTree]) -> Bool[Array, " n"]:
    pose_var, point_var = factor.variables
    pose = gather(values[pose_var.group], pose_var)
    point = gather(values[point_var.group], point_var)
    cam = _camera_pose(pose, factor.body_P_sensor)
    return cam.inverse().apply(jnp.asarray(point))[..., 2] > factor.min_depth


_Calibration = TypeVar("_Calibration", AbstractCalibration, Cal3_S2Stereo)


class AbstractCameraFactor(AbstractAnalyticFactor, Generic[_Calibration]):
    """A landmark seen by a camera: the fields, constructor, residual and
    closed-form Jacobians that [`eqsmooth.factors.ProjectionFactor`][] and
    [`eqsmooth.factors.StereoProjectionFactor`][] share. A final subclass names
    its camera (`_camera`, a `_Camera`: the calibration it takes and its
    projection) and documents its arguments and `in_front`.
    """

    # Unlike STYLE.md's "a final class holds all its fields and its
    # `__init__`", both live here: the two camera factors differ only in
    # their `_camera`, so they would repeat seven fields and the constructor.
    variables: tuple[Var, ...]
    measured: Float[Array, "n m"]
    noise: AbstractNoiseModel
    calibration: _Calibration = shared_field()
    body_P_sensor: SE3 | None = shared_field()
    min_depth: float = eqx.field(static=True)
    throw_cheirality: bool = eqx.field(static=True)
    _camera: eqx.AbstractClassVar[_Camera]

    def __init__(
        self,
        pose: Var,
        point: Var,
        measured: Float[ArrayLike, "n _"],
        noise: AbstractNoiseModel,
        calibration: _Calibration,
        *,
        body_P_sensor: SE3 | None = None,
        min_depth: float = _DEFAULT_MIN_DEPTH,
        throw_cheirality: bool = False,
    ):
        name = type(self).__name__
        _check_calibration(f"{name}.calibration", calibration, self._camera)
        self.variables = (pose, point)
        self.measured = _pixels(name, measured, self._camera.width)
        self.noise = noise
        self.calibration = calibration
        self.body_P_sensor = _body_pose(name, body_P_sensor)
        self.min_depth = _min_depth(name, min_depth)
        self.throw_cheirality = bool(throw_cheirality)

    def _row(self, pose: PyTree, point: PyTree, jacobians: bool):
        """One row's residual and, with `jacobians`, its pose and point blocks
        (zero where the row is inert)."""
        name = type(self).__name__
        _check_row(name, pose, point)
        cam = _camera_pose(pose, self.body_P_sensor)
        p = cam.inverse().apply(point)
        front, z = _safe_depth(p, self.min_depth)
        cal = self.calibration
        predicted = self._camera.pixels(cal, p, z)
        penalty = jax.lax.stop_gradient(jnp.broadcast_to(2.0 * cal.fx, predicted.shape))
        r = jnp.where(front, predicted - self.measured, penalty)
        r = _cheirality(name, r, front, self.throw_cheirality)
        if not jacobians:
            return r, ()
        d = self._camera.pixels_d(cal, p, z)
        dp_pose, dp_point = _point_jacobians(cam, p)
        h_pose = mm(d, dp_pose)
        if self.body_P_sensor is not None:
            h_pose = mm(h_pose, self.body_P_sensor.inverse().adjoint())
        h_point = mm(d, dp_point)
        return r, (
            jnp.where(front, h_pose, jnp.zeros_like(h_pose)),
            jnp.where(front, h_point, jnp.zeros_like(h_point)),
        )

    def residual(self, pose: PyTree, point: PyTree) -> Float[Array, " m"]:
        return self._row(pose, point, jacobians=False)[0]

    def residual_and_jacobians(
        self, pose: PyTree, point: PyTree
    ) -> tuple[Float[Array, " m"], tuple[Float[Array, "m 6"], Float[Array, "m 3"]]]:
        r, jacs = self._row(pose, point, jacobians=True)
        return r, jacs

    # Abstract (each final class gives it as `_in_front(self, values)`) so
    # that each documents it: the API pages show a class's own members.
    @abc.abstractmethod
    def in_front(self, values: dict[str, PyTree]) -> Bool[Array, " n"]:
        """Whether each row's point is in front of its camera at `values`."""


class ProjectionFactor(AbstractCameraFactor[AbstractCalibration]):
    """A landmark seen by a monocular camera (GTSAM's `GenericProjectionFactor`):
    residual `project(pose · body_P_sensor, point) − measured`, in pixels.

    Jacobians are closed form: with `p = cam⁻¹ · P` the point in the camera
    frame and `D = ∂uv/∂(x, y) · ∂(x, y)/∂p`, the pose block is
    `D [−I, [p]×] Ad(body_P_sensor⁻¹)` (tangent `(v, ω)`) and the point block
    `D Rᵀ`. A point at depth `≤ min_depth` gives an inert row (see the
    module's note on cheirality); `in_front(values)` flags such rows.

    **Arguments:**

    - `pose`: a [`eqsmooth.factors.Var`][] of [`eqsmooth.lie.SE3`][] poses
        (camera-to-world, or body-to-world with `body_P_sensor`), `n` rows.
    - `point`: a `Var` of world points, arrays of shape `(3,)`.
    - `measured`: measured pixels `(u, v)`, shape `(n, 2)`.
    - `noise`: noise model on the 2-D residual (in pixels).
    - `calibration`: an [`eqsmooth.factors.Cal3_S2`][] or
        [`eqsmooth.factors.Cal3DS2`][] shared by every row (learnable: its
        parameters receive gradients through a solve).
    - `body_P_sensor`: the camera's pose in the body frame, one
        [`eqsmooth.lie.SE3`][] shared by every row (`None`: the pose is the
        camera's).
    - `min_depth`: the depth at or below which a point is not in front
        (GTSAM's is 0).
    - `throw_cheirality`: raise (`eqx.error_if`) when a point is not in
        front, at any evaluation (trial steps of a solve included), instead
        of making the row inert.
    """

    _camera: ClassVar[_Camera] = _MONO

    def in_front(self, values: dict[str, PyTree]) -> Bool[Array, " n"]:
        """Whether each row's point is in front of its camera (depth
        `> min_depth`) at `values`; `False` marks the inert rows.

        **Arguments:**

        - `values`: the graph's values `{group: stacked states}`, e.g. a
            solution's `sol.value`.

        **Returns:** one flag per row, shape `(n,)`.
        """
        return _in_front(self, values)


class StereoProjectionFactor(AbstractCameraFactor[Cal3_S2Stereo]):
    """A landmark seen by a rectified stereo camera (GTSAM's
    `GenericStereoFactor`): residual `(uL, uR, v)(pose · body_P_sensor, point)
    − measured`, in pixels (see [`eqsmooth.factors.Cal3_S2Stereo`][]).

    Unlike a monocular projection, one stereo measurement fixes the point's
    depth. Jacobians are closed form (as for
    [`eqsmooth.factors.ProjectionFactor`][]); a point at depth
    `≤ min_depth` gives an inert row with GTSAM's constant residual `2 fx`
    (see the module's note on cheirality), flagged by `in_front(values)`.

    **Arguments:**

    - `pose`: a [`eqsmooth.factors.Var`][] of [`eqsmooth.lie.SE3`][] poses of
        the left camera (camera-to-world, or body-to-world with
        `body_P_sensor`), `n` rows.
    - `point`: a `Var` of world points, arrays of shape `(3,)`.
    - `measured`: measured `(uL, uR, v)`, shape `(n, 3)`.
    - `noise`: noise model on the 3-D residual (in pixels).
    - `calibration`: a [`eqsmooth.factors.Cal3_S2Stereo`][] shared by every
        row (learnable).
    - `body_P_sensor`, `min_depth`, `throw_cheirality`: as for
        [`eqsmooth.factors.ProjectionFactor`][].
    """

    _camera: ClassVar[_Camera] = _STEREO

    def in_front(self, values: dict[str, PyTree]) -> Bool[Array, " n"]:
        """Whether each row's point is in front of its (left) camera at
        `values`; `False` marks the inert rows (see
        [`eqsmooth.factors.ProjectionFactor.in_front`][])."""
        return _in_front(self, values)


def check_cheirality(graph: FactorGraph, values: dict[str, PyTree]) -> None:
    """Raise if a camera factor of `graph` sees a point that is not in front
    of its camera at `values` (an inert row; see the module's note on
    cheirality).

    A solve does not fail on inert rows: a point behind every camera that
    sees it is left unconstrained (Levenberg-Marquardt's damping keeps it
    where it was) and the solve can report success. Call this on the
    initial values, or on `sol.value`, to have such rows named.

    **Arguments:**

    - `graph`: a [`eqsmooth.factors.FactorGraph`][].
    - `values`: concrete values `{group: stacked states}`.

    **Raises:** `ValueError` naming each camera factor stack, its rows that
    are not in front, and the variables of the first.
    """
    parts = []
    for k, f in enumerate(graph.factors):
        if not isinstance(f, AbstractCameraFactor):
            continue
        front = np.asarray(f.in_front(values))
        bad = np.flatnonzero(~front)
        if bad.size:
            first = ", ".join(
                f"{v.group}[{int(np.asarray(v.index)[bad[0]])}]" for v in f.variables
            )
            more = f" and {bad.size - 8} more" if bad.size > 8 else ""
            parts.append(
                f"{type(f).__name__} (factor stack {k}): rows {bad[:8].tolist()}"
                f"{more} see their point at depth <= min_depth={f.min_depth} "
                f"(first row: {first})"
            )
    if parts:
        raise ValueError(
            "points not in front of their cameras (these rows are inert: zero "
            "Jacobians, a constant residual): "
            + "; ".join(parts)
            + ". Initialise such points in front of the cameras that see them, "
            "e.g. along the measured pixel's ray (calibration.calibrate)."
        )
