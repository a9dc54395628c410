from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, DTypeLike, Float, PRNGKeyArray, Real

from .._precision import matmul as mm
from ._base import AbstractLieGroup
from ._utils import (
    as_float_array,
    broadcast_batch,
    coef_a,
    coef_b,
    coef_c,
    cos_half,
    quat_log_scale,
    sin_half_over,
    stack_matrix,
)


def skew(v: Float[Array, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
    """Cross-product matrix: `skew(v) @ u == cross(v, u)`."""
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    zero = jnp.zeros_like(x)
    return stack_matrix([[zero, -z, y], [z, zero, -x], [-y, x, zero]])


def _eye_like(x: Array, n: int) -> Array:
    return jnp.broadcast_to(jnp.eye(n, dtype=x.dtype), (*x.shape[:-1], n, n))


class SO3(AbstractLieGroup):
    """Rotations of space.

    Parameters are a quaternion `(w, x, y, z)` (scalar first); the tangent space is
    the rotation vector (axis times angle, dimension 3). `q` and `-q` are the same
    rotation. `log`, `as_matrix` and `apply` do not depend on the norm of the
    quaternion; `compose` and `inverse` preserve unit norm but do not restore it
    (see `normalize`).
    """

    wxyz: Float[Array, "*batch 4"]
    """Quaternion `(w, x, y, z)`, shape `(*batch, 4)`."""

    tangent_dim: ClassVar[int] = 3
    parameters_dim: ClassVar[int] = 4
    matrix_dim: ClassVar[int] = 3
    space_dim: ClassVar[int] = 3

    def __init__(self, wxyz: Float[ArrayLike, "*batch 4"], check: bool = True):
        """**Arguments:**

        - `wxyz`: quaternion `(w, x, y, z)`, shape `(*batch, 4)`.
        - `check`: check concrete parameters (see
            [`eqsmooth.lie.AbstractLieGroup`][]).
        """
        self.wxyz = self._checked_parameters("wxyz", wxyz, 4, check)

    # ---------------------------------------------------------------- constructors

    @classmethod
    def from_x_radians(cls, theta: Real[ArrayLike, "*batch"]) -> "SO3":
        """Rotation by `theta` radians about the x axis."""
        return cls._from_axis_radians(0, theta)

    @classmethod
    def from_y_radians(cls, theta: Real[ArrayLike, "*batch"]) -> "SO3":
        """Rotation by `theta` radians about the y axis."""
        return cls._from_axis_radians(1, theta)

    @classmethod
    def from_z_radians(cls, theta: Real[ArrayLike, "*batch"]) -> "SO3":
        """Rotation by `theta` radians about the z axis."""
        return cls._from_axis_radians(2, theta)

    @classmethod
    def _from_axis_radians(cls, axis: int, theta: ArrayLike) -> "SO3":
        """Rotation by `theta` radians about coordinate axis `axis` (0, 1 or 2)."""
        theta = as_float_array(theta)
        zero = jnp.zeros_like(theta)
        omega = [theta if i == axis else zero for i in range(3)]
        return cls.exp(jnp.stack(omega, axis=-1))

    @classmethod
    def from_rpy_radians(
        cls,
        roll: Real[ArrayLike, "*#batch"],
        pitch: Real[ArrayLike, "*#batch"],
        yaw: Real[ArrayLike, "*#batch"],
    ) -> "SO3":
        """Rotation from roll, pitch and yaw: `Rz(yaw) @ Ry(pitch) @ Rx(roll)`.

        **Arguments:**

        - `roll`, `pitch`, `yaw`: angles in radians, broadcasting to `(*batch,)`.

        **Returns:**

        The rotation.
        """
        roll, pitch, yaw = jnp.broadcast_arrays(
            as_float_array(roll), as_float_array(pitch), as_float_array(yaw)
        )
        return (
            cls.from_z_radians(yaw)
            .compose(cls.from_y_radians(pitch))
            .compose(cls.from_x_radians(roll))
        )

    @classmethod
    def exp(cls, tangent: Float[ArrayLike, "*batch 3"]) -> "SO3":
        omega = cls._as_tangent(tangent)
        t = jnp.sum(jnp.square(omega), axis=-1)
        w = cos_half(t)
        v = sin_half_over(t)[..., None] * omega
        return cls(jnp.concatenate([w[..., None], v], axis=-1), check=False)

    @classmethod
    def _from_group_matrix(cls, m: Float[Array, "*batch n n"]) -> "SO3":
        # Shepperd's method without square roots: each candidate below equals
        # 4 q_i q for one component q_i; the one with the largest |q_i| is well
        # conditioned (|q_i| >= 1/2) and is normalized.
        r = [[m[..., i, j] for j in range(3)] for i in range(3)]
        t_w = 1.0 + r[0][0] + r[1][1] + r[2][2]
        t_x = 1.0 + r[0][0] - r[1][1] - r[2][2]
        t_y = 1.0 - r[0][0] + r[1][1] - r[2][2]
        t_z = 1.0 - r[0][0] - r[1][1] + r[2][2]
        d_x = r[2][1] - r[1][2]
        d_y = r[0][2] - r[2][0]
        d_z = r[1][0] - r[0][1]
        s_xy = r[0][1] + r[1][0]
        s_xz = r[0][2] + r[2][0]
        s_yz = r[1][2] + r[2][1]
        candidates = stack_matrix(
            [
                [t_w, d_x, d_y, d_z],
                [d_x, t_x, s_xy, s_xz],
                [d_y, s_xy, t_y, s_yz],
                [d_z, s_xz, s_yz, t_z],
            ]
        )
        best = jnp.argmax(jnp.stack([t_w, t_x, t_y, t_z], axis=-1), axis=-1)
        q = jnp.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
        q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
        q = jnp.where(q[..., :1] < 0, -q, q)
        return cls(q, check=False)

    @classmethod
    def _sample(
        cls, key: PRNGKeyArray, batch_shape: tuple[int, ...], dtype: DTypeLike
    ) -> "SO3":
        # A normalized standard Gaussian in R^4 is uniform on S^3, which maps to the
        # Haar measure on SO(3).
        q = jax.random.normal(key, (*batch_shape, 4), dtype=dtype)
        return cls(q / jnp.linalg.norm(q, axis=-1, keepdims=True), check=False)

    # ------------------------------------------------------------- Lie algebra

    @classmethod
    def hat(cls, tangent: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        return skew(cls._as_tangent(tangent))

    @classmethod
    def vee(cls, matrix: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
        m = cls._as_matrices(matrix)
        return jnp.stack([m[..., 2, 1], m[..., 0, 2], m[..., 1, 0]], axis=-1)

    @classmethod
    def right_jacobian(
        cls, tangent: Float[ArrayLike, "*batch 3"]
    ) -> Float[Array, "*batch 3 3"]:
        # Jr(w) = I - A(theta) hat(w) + B(theta) hat(w)^2; see Sola, Deray and
        # Atchuthan, "A micro Lie theory for state estimation in robotics" (2018),
        # appendix on SO(3).
        eye, w, t = cls._jacobian_terms(tangent)
        return eye - coef_a(t) * w + coef_b(t) * mm(w, w)

    @classmethod
    def right_jacobian_inv(
        cls, tangent: Float[ArrayLike, "*batch 3"]
    ) -> Float[Array, "*batch 3 3"]:
        # Jr(w)^-1 = I + hat(w) / 2 + C(theta) hat(w)^2, C regular up to 2 pi.
        eye, w, t = cls._jacobian_terms(tangent)
        return eye + 0.5 * w + coef_c(t) * mm(w, w)

    @classmethod
    def _jacobian_terms(cls, tangent: ArrayLike) -> tuple[Array, Array, Array]:
        """What `Jr(w)` and `Jr(w)^-1` are series in: `I` and `hat(w)`, and
        `t = |w|^2` shaped `(*batch, 1, 1)` to scale matrices."""
        omega = cls._as_tangent(tangent)
        t = jnp.sum(jnp.square(omega), axis=-1)[..., None, None]
        return _eye_like(omega, 3), skew(omega), t

    # ---------------------------------------------------------------- operations

    def parameters(self) -> Float[Array, "*batch 4"]:
        return self.wxyz

    def log(self) -> Float[Array, "*batch 3"]:
        w = self.wxyz[..., 0]
        v = self.wxyz[..., 1:]
        scale = quat_log_scale(w, jnp.sum(jnp.square(v), axis=-1))
        return scale[..., None] * v

    def inverse(self) -> "SO3":
        q = self.wxyz
        return SO3(jnp.concatenate([q[..., :1], -q[..., 1:]], axis=-1), check=False)

    def compose(self, other: "SO3") -> "SO3":
        a, b = broadcast_batch(self.wxyz, other.wxyz)
        w1, v1 = a[..., 0], a[..., 1:]
        w2, v2 = b[..., 0], b[..., 1:]
        w = w1 * w2 - jnp.sum(v1 * v2, axis=-1)
        v = w1[..., None] * v2 + w2[..., None] * v1 + jnp.cross(v1, v2)
        return SO3(jnp.concatenate([w[..., None], v], axis=-1), check=False)

    def apply(self, points: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
        q, p = broadcast_batch(self.wxyz, self._as_points(points))
        w, v = q[..., :1], q[..., 1:]
        # p + (2 / |q|^2) (w (v x p) + v x (v x p)): exact for any nonzero scale.
        k = 2.0 / jnp.sum(jnp.square(q), axis=-1, keepdims=True)
        vxp = jnp.cross(v, p)
        return p + k * (w * vxp + jnp.cross(v, vxp))

    def adjoint(self) -> Float[Array, "*batch 3 3"]:
        return self.as_matrix()

    def as_matrix(self) -> Float[Array, "*batch 3 3"]:
        q = self.wxyz
        w, x, y, z = (q[..., i] for i in range(4))
        k = 2.0 / jnp.sum(jnp.square(q), axis=-1)
        xx, yy, zz = k * x * x, k * y * y, k * z * z
        xy, xz, yz = k * x * y, k * x * z, k * y * z
        wx, wy, wz = k * w * x, k * w * y, k * w * z
        return stack_matrix(
            [
                [1.0 - yy - zz, xy - wz, xz + wy],
                [xy + wz, 1.0 - xx - zz, yz - wx],
                [xz - wy, yz + wx, 1.0 - xx - yy],
            ]
        )

    def normalize(self) -> "SO3":
        q = self.wxyz
        return SO3(q / jnp.linalg.norm(q, axis=-1, keepdims=True))
