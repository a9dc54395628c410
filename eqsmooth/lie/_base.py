import abc
from typing import Any, overload, TypeVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, DTypeLike, Float, PRNGKeyArray, Real

from ._utils import (
    as_float_array,
    as_matrices,
    as_vectors,
    broadcast_batch,
    check_on_group,
    check_unit_norm,
    default_float_dtype,
)


# Stands for "the concrete group of `self`" (beartype rejects `typing.Self` on
# individually decorated methods, which is how the jaxtyping import hook checks).
_G = TypeVar("_G", bound="AbstractLieGroup")
_R = TypeVar("_R", bound="AbstractRigidMotion")


class AbstractLieGroup(eqx.Module):
    """Base class of the matrix Lie groups [`eqsmooth.lie.SO2`][],
    [`eqsmooth.lie.SE2`][], [`eqsmooth.lie.SO3`][] and [`eqsmooth.lie.SE3`][].

    A group element stores one array of parameters whose last axis has size
    `parameters_dim`; any leading axes are batch axes, and every operation broadcasts
    over them. Tangent vectors have shape `(*batch, tangent_dim)`.

    Constructors take `check=True` by default: concrete parameters whose
    rotation part is not finite with unit norm (within `max(1e-3, 10 eps)`)
    raise `ValueError`. Traced values (under `jit` or `vmap`) are not
    checked. `check=False` accepts any parameters, e.g. to call
    `normalize()` on them.
    """

    tangent_dim: eqx.AbstractClassVar[int]
    """Dimension of the tangent space (the Lie algebra)."""
    parameters_dim: eqx.AbstractClassVar[int]
    """Size of the last axis of the parameter array."""
    matrix_dim: eqx.AbstractClassVar[int]
    """Size of the square matrix returned by `as_matrix`."""
    space_dim: eqx.AbstractClassVar[int]
    """Dimension of the points the group acts on."""

    # ---------------------------------------------------------------- abstract API

    @abc.abstractmethod
    def parameters(self) -> Float[Array, "*batch p"]:
        """The underlying parameter array, of shape `(*batch, parameters_dim)`."""

    @classmethod
    def identity(
        cls: type[_G], batch_shape: tuple[int, ...] = (), dtype: DTypeLike | None = None
    ) -> _G:
        """The identity element.

        **Arguments:**

        - `batch_shape`: leading batch axes of the result.
        - `dtype`: floating dtype of the parameters (default: JAX's default float).

        **Returns:**

        The identity, with parameters of shape `(*batch_shape, parameters_dim)`.
        """
        dtype = default_float_dtype() if dtype is None else dtype
        # Every group's parameters are (1, 0, ..., 0) at the identity: cos = 1
        # or qw = 1, then zeros.
        params = jnp.zeros((cls.parameters_dim,), dtype).at[0].set(1.0)
        shape = (*batch_shape, cls.parameters_dim)
        return cls(jnp.broadcast_to(params, shape), check=False)

    @classmethod
    def _checked_parameters(
        cls, field: str, value: ArrayLike, rotation_dim: int, check: bool
    ) -> Array:
        """`value` as the parameter array `field` of a new element: shape
        checked, and with `check` its first `rotation_dim` entries of unit
        norm (when concrete)."""
        value = as_vectors(value, cls.parameters_dim, cls.__name__, field)
        if check:
            check_unit_norm(cls.__name__, field, value, rotation_dim)
        return value

    @classmethod
    def _as_tangent(cls, tangent: ArrayLike) -> Array:
        """`tangent` as a float array of tangent vectors; a last axis other than
        `tangent_dim` raises `ValueError` naming the group."""
        return as_vectors(tangent, cls.tangent_dim, cls.__name__)

    @classmethod
    def _as_points(cls, points: ArrayLike) -> Array:
        """`points` as a float array of points; a last axis other than
        `space_dim` raises `ValueError` naming the group."""
        return as_vectors(points, cls.space_dim, cls.__name__, "points")

    @classmethod
    def _as_matrices(cls, matrix: ArrayLike) -> Array:
        """`matrix` as a float array of `(matrix_dim, matrix_dim)` matrices;
        another shape raises `ValueError` naming the group."""
        return as_matrices(matrix, cls.matrix_dim, cls.__name__)

    @classmethod
    @abc.abstractmethod
    def exp(cls: type[_G], tangent: Float[ArrayLike, "*batch d"]) -> _G:
        """Exponential map from tangent vectors to group elements.

        **Arguments:**

        - `tangent`: array of shape `(*batch, tangent_dim)`.

        **Returns:**

        The group element `exp(hat(tangent))`.
        """

    @classmethod
    def from_matrix(
        cls: type[_G], matrix: Float[ArrayLike, "*batch n n"], check: bool = True
    ) -> _G:
        """Build an element from its (homogeneous) matrix.

        **Arguments:**

        - `matrix`: array of shape `(*batch, matrix_dim, matrix_dim)`; any other
            shape raises `ValueError`.
        - `check`: if `True` (the default) the matrix must be in the group up to
            a tolerance of `max(1e-3, 10 eps)`: rotation block orthonormal with
            determinant +1, bottom row `(0, ..., 0, 1)` for SE(2)/SE(3), every
            entry finite. A concrete matrix that fails raises `ValueError`
            naming the batch index and the fault (a reflection, not
            orthonormal, a bad bottom row, non-finite entries); under `jax.jit`
            the check is an `eqx.error_if`. With `check=False` nothing is
            checked: the rotation block is projected onto the rotations (the
            closest rotation for a slightly perturbed one, an arbitrary one for
            a reflection or a singular matrix) and the bottom row is ignored.

        **Returns:**

        The group element.
        """
        matrix = cls._as_matrices(matrix)
        if check:
            homogeneous = cls.matrix_dim > cls.space_dim
            matrix = check_on_group(cls.__name__, matrix, cls.space_dim, homogeneous)
        return cls._from_group_matrix(matrix)

    @classmethod
    @abc.abstractmethod
    def _from_group_matrix(cls: type[_G], matrix: Float[Array, "*batch n n"]) -> _G:
        """The element of a matrix of the right shape, projected onto the group
        (unchecked; see `from_matrix`)."""

    def __check_init__(self):
        check_parameters(type(self).__name__, self.parameters(), self.parameters_dim)

    @classmethod
    def sample_uniform(
        cls: type[_G],
        key: PRNGKeyArray,
        batch_shape: tuple[int, ...] = (),
        dtype: DTypeLike | None = None,
    ) -> _G:
        """Draw random elements: rotations uniformly (Haar measure), translations
        uniformly in `[-1, 1]` per coordinate.

        **Arguments:**

        - `key`: a JAX PRNG key.
        - `batch_shape`: leading batch axes of the result.
        - `dtype`: floating dtype of the parameters (default: JAX's default float).

        **Returns:**

        A batch of random group elements.
        """
        dtype = default_float_dtype() if dtype is None else dtype
        return cls._sample(key, batch_shape, dtype)

    @classmethod
    @abc.abstractmethod
    def _sample(
        cls: type[_G], key: PRNGKeyArray, batch_shape: tuple[int, ...], dtype: DTypeLike
    ) -> _G:
        """`sample_uniform` with the dtype given."""

    @classmethod
    @abc.abstractmethod
    def hat(cls, tangent: Float[ArrayLike, "*batch d"]) -> Float[Array, "*batch n n"]:
        """Map a tangent vector to the corresponding Lie algebra matrix.

        **Arguments:**

        - `tangent`: array of shape `(*batch, tangent_dim)`.

        **Returns:**

        Matrices of shape `(*batch, matrix_dim, matrix_dim)`.
        """

    @classmethod
    @abc.abstractmethod
    def vee(cls, matrix: Float[ArrayLike, "*batch n n"]) -> Float[Array, "*batch d"]:
        """Inverse of [`hat`][eqsmooth.lie.AbstractLieGroup.hat].

        **Arguments:**

        - `matrix`: Lie algebra matrices of shape `(*batch, matrix_dim, matrix_dim)`.

        **Returns:**

        Tangent vectors of shape `(*batch, tangent_dim)`.
        """

    @classmethod
    @abc.abstractmethod
    def right_jacobian(
        cls, tangent: Float[ArrayLike, "*batch d"]
    ) -> Float[Array, "*batch d d"]:
        """Right Jacobian `Jr` of the exponential map.

        It satisfies `exp(xi + delta) ~= exp(xi) @ exp(Jr(xi) @ delta)` for small
        `delta`.

        **Arguments:**

        - `tangent`: the point `xi`, of shape `(*batch, tangent_dim)`.

        **Returns:**

        Matrices of shape `(*batch, tangent_dim, tangent_dim)`.
        """

    @classmethod
    @abc.abstractmethod
    def right_jacobian_inv(
        cls, tangent: Float[ArrayLike, "*batch d"]
    ) -> Float[Array, "*batch d d"]:
        """Inverse of the right Jacobian, computed in closed form.

        **Arguments:**

        - `tangent`: the point `xi`, of shape `(*batch, tangent_dim)`. For rotations
            the inverse exists for angles below `2 pi`.

        **Returns:**

        Matrices of shape `(*batch, tangent_dim, tangent_dim)`.
        """

    @abc.abstractmethod
    def log(self) -> Float[Array, "*batch d"]:
        """Logarithm map, the inverse of [`exp`][eqsmooth.lie.AbstractLieGroup.exp].

        Rotation angles are returned in `[0, pi]` (SO(3), SE(3)) or `(-pi, pi]`
        (SO(2), SE(2)). The result does not depend on the norm of the
        rotation parameters, so slightly unnormalized elements give sensible results.

        **Returns:**

        Tangent vectors of shape `(*batch, tangent_dim)`.
        """

    @abc.abstractmethod
    def inverse(self: _G) -> _G:
        """The group inverse."""

    @abc.abstractmethod
    def compose(self: _G, other: _G) -> _G:
        """Group product `self @ other` (batch axes broadcast).

        **Arguments:**

        - `other`: an element of the same group.

        **Returns:**

        The composition, applying `other` first and then `self` to points.
        """

    @abc.abstractmethod
    def apply(self, points: Float[ArrayLike, "... s"]) -> Float[Array, "... s"]:
        """Act on points (batch axes broadcast).

        **Arguments:**

        - `points`: array of shape `(*batch, space_dim)`.

        **Returns:**

        Transformed points, same shape as the broadcast input.
        """

    @abc.abstractmethod
    def adjoint(self) -> Float[Array, "*batch d d"]:
        """Adjoint matrix `Ad(g)`, such that `exp(Ad(g) @ xi) = g @ exp(xi) @ g^-1`.

        **Returns:**

        Matrices of shape `(*batch, tangent_dim, tangent_dim)`.
        """

    @abc.abstractmethod
    def as_matrix(self) -> Float[Array, "*batch n n"]:
        """Homogeneous matrix of shape `(*batch, matrix_dim, matrix_dim)`."""

    @abc.abstractmethod
    def normalize(self: _G) -> _G:
        """Project the rotation parameters back to unit norm (use after long
        chains of compositions, which slowly accumulate rounding drift)."""

    # ---------------------------------------------------------- shared behaviour

    @classmethod
    def left_jacobian(
        cls, tangent: Float[ArrayLike, "*batch d"]
    ) -> Float[Array, "*batch d d"]:
        """Left Jacobian `Jl(xi) = Jr(-xi)` of the exponential map.

        It satisfies `exp(xi + delta) ~= exp(Jl(xi) @ delta) @ exp(xi)`.

        **Arguments:**

        - `tangent`: the point `xi`, of shape `(*batch, tangent_dim)`.

        **Returns:**

        Matrices of shape `(*batch, tangent_dim, tangent_dim)`.
        """
        return cls.right_jacobian(-as_float_array(tangent))

    @classmethod
    def left_jacobian_inv(
        cls, tangent: Float[ArrayLike, "*batch d"]
    ) -> Float[Array, "*batch d d"]:
        """Inverse of the left Jacobian, `Jl(xi)^-1 = Jr(-xi)^-1`.

        **Arguments:**

        - `tangent`: the point `xi`, of shape `(*batch, tangent_dim)`.

        **Returns:**

        Matrices of shape `(*batch, tangent_dim, tangent_dim)`.
        """
        return cls.right_jacobian_inv(-as_float_array(tangent))

    def jlog(self) -> Float[Array, "*batch d d"]:
        """Jacobian of the logarithm under a right perturbation.

        This is `d log(self @ exp(delta)) / d delta` at `delta = 0`, which equals
        `right_jacobian_inv(self.log())`.

        **Returns:**

        Matrices of shape `(*batch, tangent_dim, tangent_dim)`.
        """
        return self.right_jacobian_inv(self.log())

    def interpolate(self: _G, other: _G, alpha: Real[ArrayLike, "*#batch"]) -> _G:
        """Geodesic interpolation `self @ exp(alpha * log(self^-1 @ other))`.

        **Arguments:**

        - `other`: the end point (an element of the same group).
        - `alpha`: interpolation parameter; `0` gives `self`, `1` gives `other`.
            A scalar or an array broadcasting against the batch axes.

        **Returns:**

        The interpolated element.
        """
        delta = self.inverse().compose(other).log()
        alpha = as_float_array(alpha, dtype=delta.dtype)
        alpha, delta = broadcast_batch(alpha[..., None], delta)
        return self.compose(self.exp(alpha * delta))

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading batch axes of the parameters."""
        return self.parameters().shape[:-1]

    @property
    def dtype(self) -> Any:
        """Floating dtype of the parameters."""
        return self.parameters().dtype

    def __getitem__(self: _G, index: Any) -> _G:
        """Index the batch axes (the parameter axis is never indexed)."""
        if not isinstance(index, tuple):
            index = (index,)
        params = self.parameters()[(*index, slice(None))]
        return type(self)(params)

    @overload
    def __matmul__(self: _G, other: _G) -> _G: ...

    @overload
    def __matmul__(self, other: Float[ArrayLike, "... s"]) -> Float[Array, "... s"]: ...

    def __matmul__(self, other):
        """`g @ h` composes two elements; `g @ points` applies `g` to points."""
        if isinstance(other, AbstractLieGroup):
            if type(other) is not type(self):
                raise TypeError(
                    f"Cannot compose {type(self).__name__} with {type(other).__name__}."
                )
            return self.compose(other)
        return self.apply(other)


class AbstractRigidMotion(AbstractLieGroup):
    """Base class of [`eqsmooth.lie.SE2`][] and [`eqsmooth.lie.SE3`][]: the
    parameters of a rotation group's element, then a translation."""

    rotation_group: eqx.AbstractClassVar[type[AbstractLieGroup]]
    """The rotation group (`SO2` or `SO3`)."""

    @classmethod
    def _from_rotation_parameters(
        cls: type[_R], rotation: Array, translation: ArrayLike
    ) -> _R:
        """A rigid motion from its rotation's parameters and a translation."""
        who = f"{cls.__name__}.from_rotation_and_translation"
        t = as_vectors(translation, cls.space_dim, who, "translation", like=rotation)
        r, t = broadcast_batch(rotation, t)
        return cls(jnp.concatenate([r, t], axis=-1), check=False)

    def _apply_rigid(self, points: ArrayLike) -> Array:
        """`apply` of every rigid motion: rotate the points by the rotation
        part of the parameters, then add the translation part."""
        params, p = broadcast_batch(self.parameters(), self._as_points(points))
        rotation, translation = self._split_parameters(params)
        return rotation.apply(p) + translation

    @classmethod
    def _split_parameters(cls, params: Array) -> tuple[AbstractLieGroup, Array]:
        """The rotation part of parameters `params` (unchecked, an element of
        `rotation_group`) and their translation part."""
        k = cls.rotation_group.parameters_dim
        return cls.rotation_group(params[..., :k], check=False), params[..., k:]

    def normalize(self: _R) -> _R:
        rotation, translation = self._split_parameters(self.parameters())
        return self._from_rotation_parameters(
            rotation.normalize().parameters(), translation
        )

    @classmethod
    def _from_group_matrix(cls: type[_R], matrix: Float[Array, "*batch n n"]) -> _R:
        n = cls.space_dim
        rotation = cls.rotation_group.from_matrix(matrix[..., :n, :n], check=False)
        return cls._from_rotation_parameters(rotation.parameters(), matrix[..., :n, n])

    @classmethod
    def _sample(
        cls: type[_R], key: PRNGKeyArray, batch_shape: tuple[int, ...], dtype: DTypeLike
    ) -> _R:
        key_rot, key_trans = jax.random.split(key)
        translation = jax.random.uniform(
            key_trans,
            (*batch_shape, cls.space_dim),
            dtype=dtype,
            minval=-1.0,
            maxval=1.0,
        )
        rotation = cls.rotation_group.sample_uniform(key_rot, batch_shape, dtype)
        return cls._from_rotation_parameters(rotation.parameters(), translation)


def check_parameters(name: str, params: Array, size: int) -> None:
    """Shared `__check_init__` body: trace-time checks of the parameter array."""
    if params.ndim < 1 or params.shape[-1] != size:
        raise ValueError(
            f"{name} parameters must have shape (*batch, {size}), got {params.shape}."
        )
    if not jnp.issubdtype(params.dtype, jnp.floating):
        raise TypeError(
            f"{name} parameters must have a floating dtype, got {params.dtype}."
        )
