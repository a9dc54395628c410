"""Measurement factors between poses and points: range, bearing, bearing-range,
translation (GPS) priors and pose-to-point offsets, in 2-D and 3-D.

Poses are [`eqsmooth.lie.SE2`][] or [`eqsmooth.lie.SE3`][] values; points are plain
arrays of shape `(2,)` or `(3,)` per variable. Residuals follow the
"prediction minus measurement" convention, with angles wrapped to `(-π, π]`.

The nonlinearities are given analytic derivatives with `jax.custom_jvp`:
the distance between two positions and the planar angle `atan2(y, x)`.
Neither has a derivative where the two positions coincide (a landmark at its
observer), and there their derivative is NaN on purpose: a zero there would
make every such configuration a stationary point, and a solve started from
it would report success after zero steps with the landmark still on its
observer. A NaN Jacobian makes the solve fail with
`RESULTS.nonfinite_problem`, and the error names the factor and rows (see
`nonfinite_hint`). Everything else is smooth and is differentiated by the
solver's forward-mode linearisation.
"""

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._precision import matmul as mm
from ..lie import SE2, SE3
from ..lie._base import AbstractLieGroup
from ._factor import AbstractFactor
from ._noise import AbstractNoiseModel, is_concrete
from ._variables import Var


# ------------------------------------------------------------------ primitives


@jax.custom_jvp
def _norm(v: Array) -> Array:
    return jnp.sqrt(jnp.sum(v * v, axis=-1))


@_norm.defjvp
def _norm_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    n = _norm(v)
    # d‖v‖ = vᵀdv / ‖v‖; at v = 0 the norm has no derivative and we take the
    # zero subgradient rather than autodiff's nan.
    safe = jnp.where(n > 0, n, jnp.ones_like(n))
    dn = jnp.where(n > 0, jnp.sum(v * dv, axis=-1) / safe, jnp.zeros_like(n))
    return n, dn


@jax.custom_jvp
def _distance(v: Array) -> Array:
    """`‖v‖` between two positions: like `_norm`, but with a NaN derivative at
    `v = 0`, where the distance has none (see the module docs)."""
    return jnp.sqrt(jnp.sum(v * v, axis=-1))


@_distance.defjvp
def _distance_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    n = _distance(v)
    # Linear in dv (a NaN factor, not a NaN constant), so that reverse mode,
    # which transposes this rule, gives NaN at zero distance too.
    scale = jnp.where(n > 0, 1.0 / jnp.where(n > 0, n, 1.0), jnp.nan)
    return n, jnp.sum(v * dv, axis=-1) * scale


@jax.custom_jvp
def _angle(v: Array) -> Array:
    return jnp.arctan2(v[..., 1], v[..., 0])


@_angle.defjvp
def _angle_jvp(primals, tangents):
    (v,), (dv,) = primals, tangents
    a = _angle(v)
    # dθ = (x dy − y dx) / (x² + y²); NaN at the origin, where θ has none.
    n2 = jnp.sum(v * v, axis=-1)
    scale = jnp.where(n2 > 0, 1.0 / jnp.where(n2 > 0, n2, 1.0), jnp.nan)
    cross = v[..., 0] * dv[..., 1] - v[..., 1] * dv[..., 0]
    return a, cross * scale


def _wrapped_difference(v: Array, measured: Array) -> Array:
    """`wrap(angle(v) − measured)` in `(-π, π]`: the angle of `v` rotated by
    `−measured`, one `atan2` and no branch (so no jump in the derivative)."""
    c, s = jnp.cos(measured), jnp.sin(measured)
    rotated = jnp.stack([c * v[0] + s * v[1], c * v[1] - s * v[0]])
    return _angle(rotated)


def _position(x: PyTree) -> Array:
    if isinstance(x, AbstractLieGroup):
        return x.translation()
    return jnp.asarray(x)


def _check_pose(name: str, pose: PyTree) -> None:
    if not isinstance(pose, (SE2, SE3)):
        raise TypeError(
            f"{name}: the pose variable must hold SE2 or SE3 values, got "
            f"{type(pose).__name__}"
        )


def _local_point(name: str, pose: PyTree, point: PyTree) -> Array:
    _check_pose(name, pose)
    p = _position(point)
    if p.shape != (pose.space_dim,):
        raise ValueError(
            f"{name}: a {type(pose).__name__} pose needs points of shape "
            f"({pose.space_dim},), got {p.shape}"
        )
    return pose.inverse().apply(p)


def _sphere_basis(m: Array) -> Array:
    """An orthonormal basis `(3, 2)` of the plane orthogonal to the unit `m`,
    built from the coordinate axis least aligned with `m`."""
    axis = jax.nn.one_hot(jnp.argmin(jnp.abs(m)), 3, dtype=m.dtype)
    b1 = jnp.cross(m, axis)
    b1 = b1 / jnp.sqrt(jnp.sum(b1 * b1))
    b2 = jnp.cross(m, b1)
    return jnp.stack([b1, b2], axis=-1)


def _sphere_log(measured: Array, direction: Array) -> Array:
    """Tangent coordinates (in `_sphere_basis(measured)`) of the unit vector
    `direction` seen from the unit vector `measured`: the geodesic angle times
    the unit tangent direction, so the residual's norm is the angle between
    the two directions."""
    # The basis moves with `measured` (smoothly: the choice of axis is
    # piecewise constant), and so do the residual's coordinates: its
    # derivative w.r.t. the measured direction must include the basis's.
    # (Stopping the gradient here made the cost's gradient w.r.t. a measured
    # bearing too small by the factor sin²(angle): -0.012 against -0.837 by
    # central differences in tests/test_gradient_contract.py.)
    basis = _sphere_basis(measured)
    w = mm(basis.T, direction)  # sin(angle) · unit tangent
    s = _norm(w)
    c = mm(measured, direction)
    angle = _angle(jnp.stack([c, s]))
    small = s < 1e-8
    # angle / sin(angle) → 1 + s²/6 as s → 0 (with c > 0); the double `where`
    # keeps the untaken branch finite for reverse mode.
    ratio = jnp.where(small, 1.0 + s * s / 6.0, angle / jnp.where(small, 1.0, s))
    return w * ratio


def _as_rows(x: ArrayLike, name: str, trailing: tuple[int, ...]) -> Array:
    x = jnp.asarray(x)
    if x.ndim != 1 + len(trailing) or x.shape[1:] != trailing:
        raise ValueError(
            f"{name} must have shape (n, {', '.join(map(str, trailing))}) "
            f"(one row per factor), got {x.shape}"
            if trailing
            else f"{name} must have shape (n,) (one entry per factor), got {x.shape}"
        )
    return x


_COINCIDENT = (
    "a point at the same position as its observer (zero distance) has no "
    "bearing and no range derivative: initialise landmarks away from their "
    "observers, e.g. at the measured bearing and range"
)


def _checked_rows(x: Array, ok, concrete_message, traced_message: str) -> Array:
    """`x`, where every row must be `ok`: concretely, a `ValueError` from
    `concrete_message(bad_rows)`; traced, an `eqx.error_if` with
    `traced_message` (the landmark factors' one validation rule)."""
    if is_concrete(ok):
        bad = np.flatnonzero(~np.asarray(ok))
        if bad.size:
            raise ValueError(concrete_message(bad[:8]))
        return x
    return eqx.error_if(x, ~jnp.all(ok), traced_message)


def _ranges(name: str, range) -> Array:
    """Validated measured ranges: `(n,)`, positive and finite (a `ValueError`
    naming the rows, or `eqx.error_if` under `jit`). A zero range is refused
    too: its solution puts the point on its observer, where the distance has
    no derivative (use a `PoseToPointFactor` or `TranslationPriorFactor` for
    "at the same place")."""
    range = _as_rows(range, f"{name}.range", ())
    return _checked_rows(
        range,
        jnp.isfinite(range) & (range > 0),
        lambda bad: (
            f"{name}.range: rows {bad.tolist()} are not positive and finite "
            f"(got {np.asarray(range)[bad].tolist()}); a zero range has no "
            "derivative at its solution: for 'at the same place' use "
            "PoseToPointFactor or TranslationPriorFactor"
        ),
        f"{name}.range must be positive and finite (checked under jit)",
    )


# ------------------------------------------------------------------ factors


def _finite_rows(name: str, x: Array) -> Array:
    """`x`, with a `ValueError` naming its non-finite rows when it is concrete
    (traced measurements reach the solve, which reports a non-finite problem)."""
    if not is_concrete(x):
        return x
    ok = np.isfinite(np.asarray(x)).reshape(x.shape[0], -1).all(axis=1)
    return _checked_rows(
        x,
        ok,
        lambda bad: f"{name}: rows {bad.tolist()} are not finite (nan or inf)",
        "",
    )


def _positions(field: str, x) -> Array:
    """Validated measured positions: `(n, 2)` or `(n, 3)`, with finite rows."""
    x = jnp.asarray(x)
    if x.ndim != 2 or x.shape[1] not in (2, 3):
        raise ValueError(f"{field} must have shape (n, 2) or (n, 3), got {x.shape}")
    return _finite_rows(field, x)


def _bearings(name: str, bearing) -> Array:
    """Validated bearings of a landmark factor: `(n,)` angles, or `(n, 3)`
    directions normalised to unit vectors (like GTSAM's `Unit3`, so a ray
    `(x, y, 1)` may be passed as it is); a zero or non-finite direction
    raises (a `ValueError` naming the rows, or `eqx.error_if` under `jit`)."""
    bearing = jnp.asarray(bearing)
    if bearing.ndim not in (1, 2) or (bearing.ndim == 2 and bearing.shape[1] != 3):
        raise ValueError(
            f"{name}.bearing must have shape (n,) (angles, 2-D) or (n, 3) "
            f"(directions, 3-D), got {bearing.shape}"
        )
    if bearing.ndim == 1:
        return _finite_rows(f"{name}.bearing", bearing)
    norm = jnp.sqrt(jnp.sum(bearing * bearing, axis=1))
    norm = _checked_rows(
        norm,
        jnp.isfinite(norm) & (norm > 0),
        lambda bad: (
            f"{name}.bearing: rows {bad.tolist()} are zero or non-finite "
            "directions (a 3-D bearing is a direction; it is normalised to a "
            "unit vector)"
        ),
        f"{name}.bearing has a zero or non-finite direction (checked under jit)",
    )
    return bearing / norm[:, None]


class RangeFactor(AbstractFactor):
    """Distance between two positions: residual `‖p_b − p_a‖ − range`.

    Each variable may hold poses ([`eqsmooth.lie.SE2`][]/[`eqsmooth.lie.SE3`][], their
    translation is used) or points (arrays of shape `(2,)` or `(3,)`), so this
    covers pose-to-landmark, pose-to-pose and point-to-point ranges. The
    derivative of the norm is analytic and finite at zero distance (the zero
    subgradient there).

    **Arguments:**

    - `a`, `b`: [`eqsmooth.factors.Var`][]s with `n` rows each.
    - `range`: measured distances, shape `(n,)`.
    - `noise`: noise model on the 1-D residual.
    """

    variables: tuple[Var, ...]
    range: Float[Array, " n"]
    noise: AbstractNoiseModel
    nonfinite_hint: ClassVar[str] = _COINCIDENT

    def __init__(
        self, a: Var, b: Var, range: Float[ArrayLike, " n"], noise: AbstractNoiseModel
    ):
        self.variables = (a, b)
        self.range = _ranges("RangeFactor", range)
        self.noise = noise

    def residual(self, a: PyTree, b: PyTree) -> Float[Array, " 1"]:
        pa, pb = _position(a), _position(b)
        if pa.shape != pb.shape or pa.shape not in ((2,), (3,)):
            raise ValueError(
                f"RangeFactor: both variables need positions of the same dimension "
                f"(2 or 3), got {pa.shape} ({type(a).__name__}) and {pb.shape} "
                f"({type(b).__name__})"
            )
        d = _distance(pb - pa)
        return jnp.reshape(d - self.range, (1,))


class BearingFactor(AbstractFactor):
    """Direction from a pose to a point, in the pose's frame.

    - On [`eqsmooth.lie.SE2`][] poses the measurement is an angle `β` (radians)
        and the residual is `wrap(atan2(l_y, l_x) − β)` (1-D), with
        `l = pose⁻¹ · point`.
    - On [`eqsmooth.lie.SE3`][] poses the measurement is a unit vector `u` (3,)
        and the residual (2-D) holds the tangent coordinates on the sphere of
        the predicted direction `l/‖l‖` at `u`: its norm is the angle between
        the two directions.

    **Arguments:**

    - `pose`: a [`eqsmooth.factors.Var`][] of SE2 or SE3 poses, `n` rows.
    - `point`: a `Var` of points (or poses, whose translation is used).
    - `bearing`: `(n,)` angles (2-D) or `(n, 3)` directions (3-D; normalised
        to unit vectors, like GTSAM's `Unit3`).
    - `noise`: noise model on the residual.
    """

    variables: tuple[Var, ...]
    bearing: Float[Array, "n ..."]
    noise: AbstractNoiseModel
    nonfinite_hint: ClassVar[str] = _COINCIDENT

    def __init__(
        self,
        pose: Var,
        point: Var,
        bearing: Float[ArrayLike, "n ..."],
        noise: AbstractNoiseModel,
    ):
        self.variables = (pose, point)
        self.bearing = _bearings("BearingFactor", bearing)
        self.noise = noise

    def residual(self, pose: PyTree, point: PyTree) -> Float[Array, " k"]:
        local = _local_point("BearingFactor", pose, point)
        return _bearing_residual("BearingFactor", pose, local, self.bearing)


def _bearing_residual(name: str, pose, local: Array, bearing: Array) -> Array:
    if isinstance(pose, SE2):
        if bearing.ndim != 0:
            raise ValueError(f"{name}: SE2 poses need bearings of shape (n,)")
        return jnp.reshape(_wrapped_difference(local, bearing), (1,))
    if bearing.shape != (3,):
        raise ValueError(f"{name}: SE3 poses need unit-vector bearings of shape (n, 3)")
    n = _distance(local)
    direction = local / jnp.where(n > 0, n, jnp.ones_like(n))
    return _sphere_log(bearing, direction)


class BearingRangeFactor(AbstractFactor):
    """Bearing and range from a pose to a point: the residuals of
    [`eqsmooth.factors.BearingFactor`][] followed by that of
    [`eqsmooth.factors.RangeFactor`][] (2-D for SE2 poses, 3-D for SE3).

    **Arguments:**

    - `pose`: a [`eqsmooth.factors.Var`][] of SE2 or SE3 poses, `n` rows.
    - `point`: a `Var` of points.
    - `bearing`: `(n,)` angles (SE2) or `(n, 3)` directions (SE3; normalised
        to unit vectors).
    - `range`: `(n,)` distances.
    - `noise`: noise model on the stacked `(bearing, range)` residual, e.g.
        `DiagonalNoise.from_sigmas([σ_bearing, σ_range])` in 2-D.
    """

    variables: tuple[Var, ...]
    bearing: Float[Array, "n ..."]
    range: Float[Array, " n"]
    noise: AbstractNoiseModel
    nonfinite_hint: ClassVar[str] = _COINCIDENT

    def __init__(
        self,
        pose: Var,
        point: Var,
        bearing: Float[ArrayLike, "n ..."],
        range: Float[ArrayLike, " n"],
        noise: AbstractNoiseModel,
    ):
        self.variables = (pose, point)
        self.bearing = _bearings("BearingRangeFactor", bearing)
        self.range = _ranges("BearingRangeFactor", range)
        self.noise = noise

    def residual(self, pose: PyTree, point: PyTree) -> Float[Array, " k"]:
        local = _local_point("BearingRangeFactor", pose, point)
        b = _bearing_residual("BearingRangeFactor", pose, local, self.bearing)
        r = jnp.reshape(_distance(local) - self.range, (1,))
        return jnp.concatenate([b, r])


class TranslationPriorFactor(AbstractFactor):
    """A position-only (GPS) measurement of a pose: residual `t(pose) − position`.

    The rotation is unconstrained by this factor; works on SE2 and SE3
    poses (and on point variables).

    **Arguments:**

    - `pose`: a [`eqsmooth.factors.Var`][] with `n` rows.
    - `position`: measured positions, `(n, 2)` or `(n, 3)`, in the world frame.
    - `noise`: noise model on the position residual.
    """

    variables: tuple[Var, ...]
    position: Float[Array, "n s"]
    noise: AbstractNoiseModel

    def __init__(
        self, pose: Var, position: Float[ArrayLike, "n s"], noise: AbstractNoiseModel
    ):
        self.variables = (pose,)
        self.position = _positions("TranslationPriorFactor.position", position)
        self.noise = noise

    def residual(self, pose: PyTree) -> Float[Array, " s"]:
        p = _position(pose)
        if p.shape != self.position.shape:
            raise ValueError(
                f"TranslationPriorFactor: positions of shape {p.shape} measured by "
                f"rows of shape {self.position.shape}"
            )
        return p - self.position


class PoseToPointFactor(AbstractFactor):
    """A point measured in a pose's frame: residual `pose⁻¹ · point − measured`.

    **Arguments:**

    - `pose`: a [`eqsmooth.factors.Var`][] of SE2 or SE3 poses, `n` rows.
    - `point`: a `Var` of points (or poses, whose translation is used).
    - `measured`: the point in the pose's frame, `(n, 2)` or `(n, 3)`.
    - `noise`: noise model on the residual.
    """

    variables: tuple[Var, ...]
    measured: Float[Array, "n s"]
    noise: AbstractNoiseModel

    def __init__(
        self,
        pose: Var,
        point: Var,
        measured: Float[ArrayLike, "n s"],
        noise: AbstractNoiseModel,
    ):
        self.variables = (pose, point)
        self.measured = _positions("PoseToPointFactor.measured", measured)
        self.noise = noise

    def residual(self, pose: PyTree, point: PyTree) -> Float[Array, " s"]:
        return _local_point("PoseToPointFactor", pose, point) - self.measured
