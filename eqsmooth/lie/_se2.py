from typing import ClassVar

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, Real

from ._base import AbstractRigidMotion
from ._so2 import SO2
from ._utils import (
    as_float_array,
    broadcast_batch,
    coef_a,
    coef_b,
    coef_c,
    rotate_pairs,
    signs,
    sinc,
    stack_matrix,
)


def _affine(row0: list[Array], row1: list[Array]) -> Float[Array, "*batch 3 3"]:
    """The 3x3 matrices with top rows `row0` and `row1` (lists of `(*batch,)`
    arrays) and bottom row `(0, 0, 1)`."""
    zero = jnp.zeros_like(row0[0])
    one = jnp.ones_like(row0[0])
    return stack_matrix([row0, row1, [zero, zero, one]])


def _jacobian_column(
    vx: Array, vy: Array, theta: Array, t: Array, coef_1mcos: Array
) -> tuple[Array, Array]:
    """The last entries `(m0, m1)` of the top rows of the right Jacobian at
    `(vx, vy, theta)`, given `t = theta^2` and `coef_1mcos = (1 - cos) / theta^2`."""
    p = theta * coef_b(t)  # (theta - sin) / theta^2
    return vx * p - vy * coef_1mcos, vx * coef_1mcos + vy * p


class SE2(AbstractRigidMotion):
    """Rigid motions of the plane.

    Parameters are `(cos, sin, x, y)`: a unit complex number for the rotation and the
    translation. Tangent vectors are `(vx, vy, omega)`, translation part first.
    `log` ignores the norm of `(cos, sin)`; the other operations assume unit norm.
    """

    unit_complex_xy: Float[Array, "*batch 4"]
    """`(cos, sin, x, y)`, shape `(*batch, 4)`."""

    tangent_dim: ClassVar[int] = 3
    parameters_dim: ClassVar[int] = 4
    matrix_dim: ClassVar[int] = 3
    rotation_group: ClassVar[type[SO2]] = SO2
    space_dim: ClassVar[int] = 2

    def __init__(
        self, unit_complex_xy: Float[ArrayLike, "*batch 4"], check: bool = True
    ):
        """**Arguments:**

        - `unit_complex_xy`: `(cos, sin, x, y)`, shape `(*batch, 4)`.
        - `check`: check concrete parameters (see
            [`eqsmooth.lie.AbstractLieGroup`][]).
        """
        self.unit_complex_xy = self._checked_parameters(
            "unit_complex_xy", unit_complex_xy, 2, check
        )

    # ---------------------------------------------------------------- constructors

    @classmethod
    def from_rotation_and_translation(
        cls, rotation: SO2, translation: Real[ArrayLike, "*#batch 2"]
    ) -> "SE2":
        """The rigid motion `p -> rotation @ p + translation`, from an
        [`eqsmooth.lie.SO2`][] and a translation `(*batch, 2)` (their batch
        axes broadcast)."""
        return cls._from_rotation_parameters(rotation.parameters(), translation)

    @classmethod
    def from_xy_theta(
        cls,
        x: Real[ArrayLike, "*#batch"],
        y: Real[ArrayLike, "*#batch"],
        theta: Real[ArrayLike, "*#batch"],
    ) -> "SE2":
        """Build a pose from its position and heading.

        This is not `exp` of `(x, y, theta)`: the translation is `(x, y)` exactly.

        **Arguments:**

        - `x`, `y`: position, arrays broadcasting to `(*batch,)`.
        - `theta`: heading in radians, broadcasting to `(*batch,)`.

        **Returns:**

        The pose.
        """
        x, y, theta = jnp.broadcast_arrays(
            as_float_array(x), as_float_array(y), as_float_array(theta)
        )
        return cls(
            jnp.stack([jnp.cos(theta), jnp.sin(theta), x, y], axis=-1), check=False
        )

    @classmethod
    def exp(cls, tangent: Float[ArrayLike, "*batch 3"]) -> "SE2":
        vx, vy, theta, t = cls._tangent_parts(tangent)
        a = sinc(t)
        b = theta * coef_a(t)
        x = a * vx - b * vy
        y = b * vx + a * vy
        return cls(
            jnp.stack([jnp.cos(theta), jnp.sin(theta), x, y], axis=-1), check=False
        )

    # ------------------------------------------------------------- Lie algebra

    @classmethod
    def hat(cls, tangent: Float[ArrayLike, "*batch 3"]) -> Float[Array, "*batch 3 3"]:
        tangent = cls._as_tangent(tangent)
        vx, vy, theta = tangent[..., 0], tangent[..., 1], tangent[..., 2]
        zero = jnp.zeros_like(theta)
        return stack_matrix([[zero, -theta, vx], [theta, zero, vy], [zero, zero, zero]])

    @classmethod
    def vee(cls, matrix: Float[ArrayLike, "*batch 3 3"]) -> Float[Array, "*batch 3"]:
        matrix = cls._as_matrices(matrix)
        return jnp.stack(
            [matrix[..., 0, 2], matrix[..., 1, 2], matrix[..., 1, 0]], axis=-1
        )

    @classmethod
    def right_jacobian(
        cls, tangent: Float[ArrayLike, "*batch 3"]
    ) -> Float[Array, "*batch 3 3"]:
        # Sola, Deray and Atchuthan, "A micro Lie theory for state estimation in
        # robotics" (2018), appendix on SE(2).
        vx, vy, theta, t = cls._tangent_parts(tangent)
        a = sinc(t)
        coef_1mcos = coef_a(t)  # (1 - cos) / theta^2
        b = theta * coef_1mcos  # (1 - cos) / theta
        m0, m1 = _jacobian_column(vx, vy, theta, t, coef_1mcos)
        return _affine([a, b, m0], [-b, a, m1])

    @classmethod
    def right_jacobian_inv(
        cls, tangent: Float[ArrayLike, "*batch 3"]
    ) -> Float[Array, "*batch 3 3"]:
        # Block inverse of right_jacobian: the 2x2 block [[a, b], [-b, a]] has inverse
        # [[h, -theta/2], [theta/2, h]] with h = (theta/2) cot(theta/2) = 1 - t C(t).
        vx, vy, theta, t = cls._tangent_parts(tangent)
        h = 1.0 - t * coef_c(t)
        half = 0.5 * theta
        m0, m1 = _jacobian_column(vx, vy, theta, t, coef_a(t))
        return _affine(
            [h, -half, -(h * m0 - half * m1)], [half, h, -(half * m0 + h * m1)]
        )

    @classmethod
    def _tangent_parts(cls, tangent: ArrayLike) -> tuple[Array, Array, Array, Array]:
        """`vx`, `vy`, `theta` and `t = theta^2` of tangent vectors
        `(vx, vy, theta)`."""
        tangent = cls._as_tangent(tangent)
        vx, vy, theta = tangent[..., 0], tangent[..., 1], tangent[..., 2]
        return vx, vy, theta, jnp.square(theta)

    # ---------------------------------------------------------------- operations

    def parameters(self) -> Float[Array, "*batch 4"]:
        return self.unit_complex_xy

    def rotation(self) -> SO2:
        """The rotation part, an [`eqsmooth.lie.SO2`][]."""
        return SO2(self.unit_complex_xy[..., :2], check=False)

    def translation(self) -> Float[Array, "*batch 2"]:
        """The translation part, shape `(*batch, 2)`."""
        return self.unit_complex_xy[..., 2:]

    def x(self) -> Float[Array, "*batch"]:
        """The `x` coordinate of the translation, shape `(*batch,)`."""
        return self.unit_complex_xy[..., 2]

    def y(self) -> Float[Array, "*batch"]:
        """The `y` coordinate of the translation, shape `(*batch,)`."""
        return self.unit_complex_xy[..., 3]

    def theta(self) -> Float[Array, "*batch"]:
        """The heading angle in `(-π, π]`, shape `(*batch,)`."""
        return jnp.arctan2(self.unit_complex_xy[..., 1], self.unit_complex_xy[..., 0])

    def log(self) -> Float[Array, "*batch 3"]:
        c, s, x, y = (self.unit_complex_xy[..., i] for i in range(4))
        theta = jnp.arctan2(s, c)
        t = jnp.square(theta)
        # Inverse of the V matrix of exp: [[h, theta/2], [-theta/2, h]] with
        # h = (theta/2) cot(theta/2), finite up to and including theta = pi.
        h = 1.0 - t * coef_c(t)
        half = 0.5 * theta
        return jnp.stack([h * x + half * y, -half * x + h * y, theta], axis=-1)

    # inverse and compose are written on whole parameter vectors (no per-
    # component slices and stacks): the same arithmetic in a quarter of the
    # operations, which matters once they are differentiated twice inside an
    # unrolled solver.
    def inverse(self) -> "SE2":
        a = self.unit_complex_xy
        c, s, t = a[..., 0:1], a[..., 1:2], a[..., 2:]
        z = a[..., :2] * signs([1.0, -1.0], a)
        # -R(θ)ᵀ t = (-c x - s y, s x - c y)
        return SE2(
            jnp.concatenate([z, s * rotate_pairs(t) - c * t], axis=-1), check=False
        )

    def compose(self, other: "SE2") -> "SE2":
        a, b = broadcast_batch(self.unit_complex_xy, other.unit_complex_xy)
        # (c₁ + i s₁)(c₂ + i s₂) and R₁ t₂, both as c₁ b + s₁ (b turned by 90°).
        out = a[..., 0:1] * b + a[..., 1:2] * rotate_pairs(b)
        return SE2(
            jnp.concatenate([out[..., :2], out[..., 2:] + a[..., 2:]], axis=-1),
            check=False,
        )

    def apply(self, points: Float[ArrayLike, "... 2"]) -> Float[Array, "... 2"]:
        return self._apply_rigid(points)

    def adjoint(self) -> Float[Array, "*batch 3 3"]:
        c, s, x, y = (self.unit_complex_xy[..., i] for i in range(4))
        return _affine([c, -s, y], [s, c, -x])

    def as_matrix(self) -> Float[Array, "*batch 3 3"]:
        c, s, x, y = (self.unit_complex_xy[..., i] for i in range(4))
        return _affine([c, -s, x], [s, c, y])
