from collections.abc import Callable
from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Real

from .._precision import matmul as mm
from ._base import AbstractRigidMotion
from ._so3 import skew, SO3
from ._utils import (
    broadcast_batch,
    coef_a,
    coef_b,
    coef_c,
    se3_a2,
    se3_a3,
)


def _q_matrix(rho: Array, omega: Array) -> Array:
    """Off-diagonal block of the left Jacobian of SE(3) at `(rho, omega)`.

    Barfoot, "State Estimation for Robotics" (2017), section 7.1.5.
    """
    t = jnp.sum(jnp.square(omega), axis=-1)[..., None, None]
    p = skew(rho)
    w = skew(omega)
    wp = mm(w, p)
    pw = mm(p, w)
    wpw = mm(wp, w)
    ww = mm(w, w)
    return (
        0.5 * p
        + coef_b(t) * (wp + pw + wpw)
        + se3_a2(t) * (mm(ww, p) + mm(pw, w) - 3.0 * wpw)
        + se3_a3(t) * (mm(wpw, w) + mm(w, wpw))
    )


def _block(top_left: Array, top_right: Array, bottom_right: Array) -> Array:
    zero = jnp.zeros_like(top_left)
    return jnp.concatenate(
        [
            jnp.concatenate([top_left, top_right], axis=-1),
            jnp.concatenate([zero, bottom_right], axis=-1),
        ],
        axis=-2,
    )


class SE3(AbstractRigidMotion):
    """Rigid motions of space.

    Parameters are `(qw, qx, qy, qz, x, y, z)`: a quaternion for the rotation (see
    [`eqsmooth.lie.SO3`][]) and the translation. Tangent vectors are
    `(vx, vy, vz, wx, wy, wz)`, translation part first.
    """

    wxyz_xyz: Float[Array, "*batch 7"]
    """`(qw, qx, qy, qz, x, y, z)`, shape `(*batch, 7)`."""

    tangent_dim: ClassVar[int] = 6
    parameters_dim: ClassVar[int] = 7
    matrix_dim: ClassVar[int] = 4
    rotation_group: ClassVar[type[SO3]] = SO3
    space_dim: ClassVar[int] = 3

    def __init__(self, wxyz_xyz: Float[ArrayLike, "*batch 7"], check: bool = True):
        """**Arguments:**

        - `wxyz_xyz`: `(qw, qx, qy, qz, x, y, z)`, shape `(*batch, 7)`.
        - `check`: check concrete parameters (see
            [`eqsmooth.lie.AbstractLieGroup`][]).
        """
        self.wxyz_xyz = self._checked_parameters("wxyz_xyz", wxyz_xyz, 4, check)

    # ---------------------------------------------------------------- constructors

    @classmethod
    def from_rotation_and_translation(
        cls, rotation: SO3, translation: Real[ArrayLike, "*#batch 3"]
    ) -> "SE3":
        """The rigid motion `p -> rotation @ p + translation`, from an
        [`eqsmooth.lie.SO3`][] and a translation `(*batch, 3)` (their batch
        axes broadcast)."""
        return cls._from_rotation_parameters(rotation.parameters(), translation)

    @classmethod
    def exp(cls, tangent: Float[ArrayLike, "*batch 6"]) -> "SE3":
        tangent = cls._as_tangent(tangent)
        rho, omega = tangent[..., :3], tangent[..., 3:]
        t = jnp.sum(jnp.square(omega), axis=-1, keepdims=True)
        # translation = Jl(omega) @ rho, written with cross products.
        w_rho = jnp.cross(omega, rho)
        translation = rho + coef_a(t) * w_rho + coef_b(t) * jnp.cross(omega, w_rho)
        return cls(
            jnp.concatenate([SO3.exp(omega).wxyz, translation], axis=-1), check=False
        )

    # ------------------------------------------------------------- Lie algebra

    @classmethod
    def hat(cls, tangent: Float[ArrayLike, "*batch 6"]) -> Float[Array, "*batch 4 4"]:
        tangent = cls._as_tangent(tangent)
        top = jnp.concatenate([skew(tangent[..., 3:]), tangent[..., :3, None]], axis=-1)
        bottom = jnp.zeros_like(top[..., :1, :])
        return jnp.concatenate([top, bottom], axis=-2)

    @classmethod
    def vee(cls, matrix: Float[ArrayLike, "*batch 4 4"]) -> Float[Array, "*batch 6"]:
        m = cls._as_matrices(matrix)
        return jnp.concatenate([m[..., :3, 3], SO3.vee(m[..., :3, :3])], axis=-1)

    @classmethod
    def right_jacobian(
        cls, tangent: Float[ArrayLike, "*batch 6"]
    ) -> Float[Array, "*batch 6 6"]:
        # Jr(xi) = Jl(-xi) = [[Jr(omega), Q(-rho, -omega)], [0, Jr(omega)]].
        jr, q = cls._jacobian_blocks(tangent, SO3.right_jacobian)
        return _block(jr, q, jr)

    @classmethod
    def right_jacobian_inv(
        cls, tangent: Float[ArrayLike, "*batch 6"]
    ) -> Float[Array, "*batch 6 6"]:
        # Block inverse: [[A, Q], [0, A]]^-1 = [[A^-1, -A^-1 Q A^-1], [0, A^-1]].
        jr_inv, q = cls._jacobian_blocks(tangent, SO3.right_jacobian_inv)
        return _block(jr_inv, -mm(mm(jr_inv, q), jr_inv), jr_inv)

    @classmethod
    def _jacobian_blocks(
        cls, tangent: ArrayLike, rotation_block: Callable[[Array], Array]
    ) -> tuple[Array, Array]:
        """`rotation_block(omega)` and `Q(-rho, -omega)` at `tangent = (rho,
        omega)`: the blocks of `right_jacobian` (with `SO3.right_jacobian`) or of
        its inverse (with `SO3.right_jacobian_inv`)."""
        tangent = cls._as_tangent(tangent)
        rho, omega = tangent[..., :3], tangent[..., 3:]
        return rotation_block(omega), _q_matrix(-rho, -omega)

    # ---------------------------------------------------------------- operations

    def parameters(self) -> Float[Array, "*batch 7"]:
        return self.wxyz_xyz

    def rotation(self) -> SO3:
        """The rotation part, an [`eqsmooth.lie.SO3`][]."""
        return SO3(self.wxyz_xyz[..., :4], check=False)

    def translation(self) -> Float[Array, "*batch 3"]:
        """The translation part, shape `(*batch, 3)`."""
        return self.wxyz_xyz[..., 4:]

    def log(self) -> Float[Array, "*batch 6"]:
        omega = self.rotation().log()
        translation = self.translation()
        t = jnp.sum(jnp.square(omega), axis=-1, keepdims=True)
        # rho = Jl(omega)^-1 @ translation, written with cross products.
        w_t = jnp.cross(omega, translation)
        rho = translation - 0.5 * w_t + coef_c(t) * jnp.cross(omega, w_t)
        return jnp.concatenate([rho, omega], axis=-1)

    def inverse(self) -> "SE3":
        rotation_inv = self.rotation().inverse()
        return SE3(
            jnp.concatenate(
                [rotation_inv.wxyz, -rotation_inv.apply(self.translation())], axis=-1
            ),
            check=False,
        )

    def compose(self, other: "SE3") -> "SE3":
        a, b = broadcast_batch(self.wxyz_xyz, other.wxyz_xyz)
        rotation = SO3(a[..., :4], check=False)
        q = rotation.compose(SO3(b[..., :4], check=False)).wxyz
        t = rotation.apply(b[..., 4:]) + a[..., 4:]
        return SE3(jnp.concatenate([q, t], axis=-1), check=False)

    def apply(self, points: Float[ArrayLike, "... 3"]) -> Float[Array, "... 3"]:
        return self._apply_rigid(points)

    def adjoint(self) -> Float[Array, "*batch 6 6"]:
        r = self.rotation().as_matrix()
        return _block(r, mm(skew(self.translation()), r), r)

    def as_matrix(self) -> Float[Array, "*batch 4 4"]:
        r = self.rotation().as_matrix()
        top = jnp.concatenate([r, self.translation()[..., None]], axis=-1)
        bottom = jnp.zeros_like(top[..., :1, :])
        bottom = bottom.at[..., 0, 3].set(1.0)
        return jnp.concatenate([top, bottom], axis=-2)
