from typing import ClassVar

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, DTypeLike, Float, PRNGKeyArray, Real

from ._base import AbstractLieGroup
from ._utils import as_float_array, broadcast_batch, rotate_pairs, stack_matrix


class SO2(AbstractLieGroup):
    """Rotations of the plane.

    Parameters are a unit complex number `(cos, sin)`; the tangent space is the
    rotation angle (dimension 1). `log` uses `atan2` and so ignores the norm of the
    parameters; the other operations assume unit norm.
    """

    unit_complex: Float[Array, "*batch 2"]
    """`(cos, sin)` of the rotation angle, shape `(*batch, 2)`."""

    tangent_dim: ClassVar[int] = 1
    parameters_dim: ClassVar[int] = 2
    matrix_dim: ClassVar[int] = 2
    space_dim: ClassVar[int] = 2

    def __init__(self, unit_complex: Float[ArrayLike, "*batch 2"], check: bool = True):
        """**Arguments:**

        - `unit_complex`: `(cos, sin)` of the rotation angle, shape `(*batch, 2)`.
        - `check`: check concrete parameters (see
            [`eqsmooth.lie.AbstractLieGroup`][]).
        """
        self.unit_complex = self._checked_parameters(
            "unit_complex", unit_complex, 2, check
        )

    # ---------------------------------------------------------------- constructors

    @classmethod
    def from_radians(cls, theta: Real[ArrayLike, "*batch"]) -> "SO2":
        """Rotation by `theta` radians (counter-clockwise).

        **Arguments:**

        - `theta`: angles of shape `(*batch,)`.

        **Returns:**

        The rotations.
        """
        theta = as_float_array(theta)
        return cls(jnp.stack([jnp.cos(theta), jnp.sin(theta)], axis=-1), check=False)

    @classmethod
    def exp(cls, tangent: Float[ArrayLike, "*batch 1"]) -> "SO2":
        tangent = cls._as_tangent(tangent)
        return cls.from_radians(tangent[..., 0])

    @classmethod
    def _from_group_matrix(cls, matrix: Float[Array, "*batch n n"]) -> "SO2":
        # Average the two copies of cos and sin: this gives the closest rotation
        # (in Frobenius norm) to a slightly perturbed matrix.
        cos = matrix[..., 0, 0] + matrix[..., 1, 1]
        sin = matrix[..., 1, 0] - matrix[..., 0, 1]
        z = jnp.stack([cos, sin], axis=-1)
        return cls(z / jnp.linalg.norm(z, axis=-1, keepdims=True), check=False)

    @classmethod
    def _sample(
        cls, key: PRNGKeyArray, batch_shape: tuple[int, ...], dtype: DTypeLike
    ) -> "SO2":
        theta = jax.random.uniform(
            key, batch_shape, dtype=dtype, minval=-jnp.pi, maxval=jnp.pi
        )
        return cls.from_radians(theta)

    # ------------------------------------------------------------- Lie algebra

    @classmethod
    def hat(cls, tangent: Float[ArrayLike, "*batch 1"]) -> Float[Array, "*batch 2 2"]:
        tangent = cls._as_tangent(tangent)
        theta = tangent[..., 0]
        zero = jnp.zeros_like(theta)
        return stack_matrix([[zero, -theta], [theta, zero]])

    @classmethod
    def vee(cls, matrix: Float[ArrayLike, "*batch 2 2"]) -> Float[Array, "*batch 1"]:
        return cls._as_matrices(matrix)[..., 1, 0:1]

    @classmethod
    def right_jacobian(
        cls, tangent: Float[ArrayLike, "*batch 1"]
    ) -> Float[Array, "*batch 1 1"]:
        tangent = cls._as_tangent(tangent)
        return jnp.ones_like(tangent)[..., None]

    @classmethod
    def right_jacobian_inv(
        cls, tangent: Float[ArrayLike, "*batch 1"]
    ) -> Float[Array, "*batch 1 1"]:
        # SO(2) is abelian: Jr = 1 is its own inverse.
        return cls.right_jacobian(tangent)

    # ---------------------------------------------------------------- operations

    def parameters(self) -> Float[Array, "*batch 2"]:
        return self.unit_complex

    def as_radians(self) -> Float[Array, "*batch"]:
        """The rotation angle in `(-pi, pi]`."""
        return jnp.arctan2(self.unit_complex[..., 1], self.unit_complex[..., 0])

    def log(self) -> Float[Array, "*batch 1"]:
        return self.as_radians()[..., None]

    def inverse(self) -> "SO2":
        z = self.unit_complex
        return SO2(jnp.stack([z[..., 0], -z[..., 1]], axis=-1), check=False)

    def compose(self, other: "SO2") -> "SO2":
        a, b = broadcast_batch(self.unit_complex, other.unit_complex)
        # (c₁ + i s₁)(c₂ + i s₂) = c₁ b + s₁ (b turned by 90°), on whole vectors.
        return SO2(a[..., 0:1] * b + a[..., 1:2] * rotate_pairs(b), check=False)

    def apply(self, points: Float[ArrayLike, "... 2"]) -> Float[Array, "... 2"]:
        z, p = broadcast_batch(self.unit_complex, self._as_points(points))
        c, s = z[..., 0], z[..., 1]
        x, y = p[..., 0], p[..., 1]
        return jnp.stack([c * x - s * y, s * x + c * y], axis=-1)

    def adjoint(self) -> Float[Array, "*batch 1 1"]:
        return jnp.ones_like(self.unit_complex[..., :1])[..., None]

    def as_matrix(self) -> Float[Array, "*batch 2 2"]:
        c, s = self.unit_complex[..., 0], self.unit_complex[..., 1]
        return stack_matrix([[c, -s], [s, c]])

    def normalize(self) -> "SO2":
        z = self.unit_complex
        return SO2(z / jnp.linalg.norm(z, axis=-1, keepdims=True))
