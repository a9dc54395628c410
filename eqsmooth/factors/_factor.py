import abc
import dataclasses
import functools
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PyTree

from ..manifold import retract, tangent_dim
from ._noise import AbstractNoiseModel
from ._variables import Var


_SHARED = "eqsmooth_shared"


def shared_field(**kwargs: Any) -> Any:
    """An `eqx.field` whose value is shared by every row of a stacked factor.

    Array leaves of a stacked factor normally carry a leading axis with one
    entry per row. Leaves under a field declared with `shared_field()` are
    instead used as they are by every row: learnable physical coefficients,
    neural network weights, and so on.
    """
    metadata = dict(kwargs.pop("metadata", {}))
    metadata[_SHARED] = True
    return eqx.field(metadata=metadata, **kwargs)


class AbstractFactor(eqx.Module):
    """A stack of `n` factors of one type, evaluated row by row with `vmap`.

    Subclasses declare their data as fields: array leaves have a leading axis
    of length `n` (one entry per row) unless the field is declared with
    [`eqsmooth.factors.shared_field`][]. They implement `residual`, which
    receives ONE row's states (unbatched) for the variables listed in
    `variables`, in that order, and returns the unwhitened residual of that
    row as a 1-D array.

    **Fields every factor has:**

    - `variables`: a tuple of [`eqsmooth.factors.Var`][], one per touched
        variable, each with `n` indices.
    - `noise`: an [`eqsmooth.factors.AbstractNoiseModel`][] for the stack.
    """

    variables: eqx.AbstractVar[tuple[Var, ...]]
    noise: eqx.AbstractVar[AbstractNoiseModel]
    # A likely cause, in words, when a row's residual or Jacobian is not
    # finite at the initial values: added to the solve's error, which names
    # the rows. The landmark factors name a point at its observer.
    nonfinite_hint: ClassVar[str] = ""

    @abc.abstractmethod
    def residual(self, *states: PyTree) -> Float[Array, " m"]:
        """Unwhitened residual of one row, given that row's states."""

    def __check_init__(self):
        name = type(self).__name__
        if not isinstance(self.variables, tuple) or not all(
            isinstance(v, Var) for v in self.variables
        ):
            raise TypeError(f"{name}.variables must be a tuple of Var")
        if len(self.variables) == 0:
            raise ValueError(f"{name}.variables must not be empty")
        n = len(self.variables[0])
        for v in self.variables:
            if len(v) != n:
                raise ValueError(
                    f"{name}: all variables must have the same number of rows; "
                    f"got {[len(u) for u in self.variables]}"
                )
        if not isinstance(self.noise, AbstractNoiseModel):
            raise TypeError(
                f"{name}.noise must be an AbstractNoiseModel, got "
                f"{type(self.noise).__name__}"
            )
        check_array_leaves(self)

    @property
    def num_rows(self) -> int:
        """Number of stacked rows `n`."""
        return len(self.variables[0])


class AbstractAnalyticFactor(AbstractFactor):
    """A factor that also gives its Jacobians in closed form.

    The linearisation of an [`eqsmooth.factors.AbstractFactor`][] pushes the
    tangent directions of its variables through `residual` with forward-mode
    autodiff. A factor whose Jacobians have a cheap closed form (a pose-graph
    edge: `Jr⁻¹(e)` and `−Jr⁻¹(e) Ad(X⁻¹)`) implements
    `residual_and_jacobians` too, and the linearisation calls it instead:
    less work per row and a smaller program to trace and compile. `residual`
    is still used wherever only the cost is needed.
    """

    @abc.abstractmethod
    def residual_and_jacobians(
        self, *states: PyTree
    ) -> tuple[Float[Array, " m"], tuple[Float[Array, "m _d"], ...]]:
        """One row's unwhitened residual `r` (as `residual` gives it) and, per
        variable `k`, the Jacobian `∂ r(…, x_k ⊕ δ, …) / ∂ δ` at `δ = 0`, of
        shape `(m, tangent_dim(x_k))` (right perturbations, as
        [`eqsmooth.manifold.retract`][] applies them)."""


def _is_per_row(f: dataclasses.Field) -> bool:
    """Whether a field's array leaves carry one entry per factor row: the one
    rule, used by the smoother's vmap, the shape check and the filters."""
    return not (
        f.metadata.get("static", False)
        or f.name in ("variables", "noise")
        or f.metadata.get(_SHARED, False)
    )


def per_row_fields(factor: AbstractFactor) -> dict[str, PyTree]:
    """The fields of a factor stack whose array leaves have one entry per row.

    Every field except `variables`, `noise`, static fields and fields
    declared with [`eqsmooth.factors.shared_field`][].

    **Arguments:**

    - `factor`: a factor stack.

    **Returns:** a dict `{field name: value}`.
    """
    return {
        f.name: getattr(factor, f.name)
        for f in dataclasses.fields(factor)
        if _is_per_row(f)
    }


def with_rows(factor: AbstractFactor, rows: dict[str, PyTree]) -> AbstractFactor:
    """A copy of `factor` whose per-row fields are replaced by `rows`.

    Built without `__init__` (like the smoother's vmap prefix), so a one-row
    copy inside a `lax.scan` skips the stack's shape checks.

    **Arguments:**

    - `factor`: a factor stack.
    - `rows`: a dict `{field name: value}`, e.g. one row of
        [`eqsmooth.factors.per_row_fields`][].

    **Returns:** the new factor.
    """
    unknown = set(rows) - {f.name for f in dataclasses.fields(factor) if _is_per_row(f)}
    if unknown:
        raise ValueError(
            f"with_rows: {type(factor).__name__} has no per-row fields "
            f"{sorted(unknown)}"
        )
    new = object.__new__(type(factor))
    for f in dataclasses.fields(factor):
        value = rows[f.name] if f.name in rows else getattr(factor, f.name)
        object.__setattr__(new, f.name, value)
    return new


def _row_axes(factor: AbstractFactor) -> AbstractFactor:
    """A prefix of `factor` for `filter_vmap`: 0 for per-row fields, None else."""
    axes = object.__new__(type(factor))
    for f in dataclasses.fields(factor):
        if f.metadata.get("static", False):
            object.__setattr__(axes, f.name, getattr(factor, f.name))
            continue
        object.__setattr__(axes, f.name, 0 if _is_per_row(f) else None)
    return axes


def check_array_leaves(factor: AbstractFactor) -> None:
    """Raise if a data field of `factor` holds something that is not an array
    (e.g. a `gtsam.Pose2`, a list of objects), which would otherwise fail
    later inside JAX without naming the factor or the field."""
    name = type(factor).__name__
    for field_name, value in per_row_fields(factor).items():
        for leaf in jax.tree_util.tree_leaves(value):
            if not (eqx.is_array(leaf) or isinstance(leaf, (int, float, np.generic))):
                raise TypeError(
                    f"{name}.{field_name} holds a {type(leaf).__module__}."
                    f"{type(leaf).__qualname__}, not an array: factor data must be "
                    "JAX or NumPy arrays or eqsmooth Lie groups (for a GTSAM pose, "
                    "e.g. eqsmooth.SE2.from_xy_theta(p.x(), p.y(), p.theta()))"
                )


def check_row_leaves(factor: AbstractFactor) -> None:
    """Raise if a per-row leaf of `factor` lacks the leading axis of length n."""
    name = type(factor).__name__
    n = factor.num_rows
    for field_name, value in per_row_fields(factor).items():
        for leaf in jax.tree_util.tree_leaves(value):
            if eqx.is_array(leaf) and (leaf.ndim == 0 or leaf.shape[0] != n):
                raise ValueError(
                    f"{name}.{field_name}: per-row leaf of shape {leaf.shape} must "
                    f"have a leading axis of length {n} (the number of factor rows): "
                    "give one entry per row (for a single row, add a leading axis "
                    "of length 1, e.g. x[None], or build a group element from "
                    "arrays of shape (1,)); only for a parameter that every row of "
                    "your own factor shares, declare the field with "
                    "eqsmooth.factors.shared_field()"
                )


def _row_call(factor, *states):
    return factor.residual(*states)


def _inert_inactive_rows(factor: AbstractFactor) -> AbstractFactor:
    """`factor` with each inactive row's per-row data (rows its noise model
    switches off) replaced by the first active row's.

    An inactive row's residual is zeroed after it is computed, but autodiff
    still multiplies the derivative of what it read by that zero: NaN data
    there (a missing measurement) would make the gradients of the shared
    parameters NaN (0 · NaN). Reading an active row's data instead, the row
    computes something finite and, being zeroed, contributes nothing; its
    own data gets a zero derivative."""
    active = factor.noise.active_rows()
    n = factor.num_rows
    if active is None or active.shape != (n,):  # a wrong shape: check_shapes says
        return factor
    source = jnp.where(active, jnp.arange(n), jnp.argmax(active))
    take = lambda leaf: leaf[source] if eqx.is_inexact_array(leaf) else leaf
    rows = {
        name: jax.tree_util.tree_map(take, value)
        for name, value in per_row_fields(factor).items()
    }
    return with_rows(factor, rows)


def evaluate_rows(
    factor: AbstractFactor, states: tuple[PyTree, ...]
) -> Float[Array, "n m"]:
    """Residuals of all rows, `(n, m)`, given per-row stacked states."""
    axes = _row_axes(factor)
    fn = eqx.filter_vmap(_row_call, in_axes=(axes,) + (0,) * len(states))
    r = fn(_inert_inactive_rows(factor), *states)
    if r.ndim != 2:  # (rows, m): each row's residual must be 1-D
        raise ValueError(
            f"{type(factor).__name__}.residual must return a 1-D array, got "
            f"shape {r.shape[1:]}"
        )
    return r


def linearize_rows(
    factor: AbstractFactor, states: tuple[PyTree, ...]
) -> tuple[Float[Array, "n m"], tuple[Float[Array, "n m _d"], ...]]:
    """Residuals `(n, m)` and Jacobians `(n, m, d_k)` w.r.t. right perturbations.

    The Jacobian block k is `∂ r(x_1, ..., x_k ⊕ δ, ...) / ∂ δ` at `δ = 0`,
    computed with forward-mode autodiff, one `jacfwd` per touched variable and
    row, vmapped over rows.
    """
    name = type(factor).__name__
    dims = [tangent_dim(s, batch_ndim=1) for s in states]
    axes = _row_axes(factor)
    factor = _inert_inactive_rows(factor)
    if isinstance(factor, AbstractAnalyticFactor):
        r, jacs = eqx.filter_vmap(
            _closed_form_row, in_axes=(axes,) + (0,) * len(states)
        )(factor, *states)
        if r.ndim != 2:
            raise ValueError(
                f"{name}.residual_and_jacobians must return a 1-D residual, got "
                f"shape {r.shape[1:]}"
            )
        want = [(r.shape[1], d) for d in dims]
        got = [j.shape[1:] for j in jacs]
        if len(jacs) != len(dims) or any(g != w for g, w in zip(got, want)):
            raise ValueError(
                f"{name}.residual_and_jacobians must return one Jacobian per "
                f"variable, of shapes {want}; got {got}"
            )
        return r, tuple(jacs)

    def one_row(f, *xs):
        dtype = jnp.result_type(*jax.tree_util.tree_leaves(xs))
        zeros = [jnp.zeros(d, dtype=dtype) for d in dims]

        def r_of(k, delta):
            # Only variable k moves; the others are retracted by a constant
            # zero, so that every k evaluates the same primal (XLA merges
            # the copies) and carries no tangent through it.
            pieces = [delta if i == k else z for i, z in enumerate(zeros)]
            moved = [retract(x, d) if dd else x for x, d, dd in zip(xs, pieces, dims)]
            r = f.residual(*moved)
            if r.ndim != 1:
                raise ValueError(
                    f"{name}.residual must return a 1-D array, got shape {r.shape}"
                )
            return r

        # One Jacobian per variable rather than one over the concatenated
        # tangent: each pushes only its own directions through the residual,
        # as forward mode skips the other variables' zero tangents, which the
        # concatenated form carried through every operation (a chain of
        # SE(2) poses and velocities linearises about 1.5x faster:
        # benchmarks/results/chain_linearize.md).
        moving = [k for k, d in enumerate(dims) if d]
        r = r_of(0, zeros[0]) if not moving else None
        blocks = {}
        for k in moving:
            r, blocks[k] = _value_and_jacfwd(functools.partial(r_of, k), zeros[k])
        empty = jnp.zeros((r.shape[0], 0), dtype=r.dtype)
        return r, tuple(blocks.get(k, empty) for k in range(len(dims)))

    fn = eqx.filter_vmap(one_row, in_axes=(axes,) + (0,) * len(states))
    return fn(factor, *states)


def _closed_form_row(factor, *states):
    r, jacs = factor.residual_and_jacobians(*states)
    return r, tuple(jacs)


def _value_and_jacfwd(fn, x):
    # One linearisation, then push the identity through the JVP with vmap.
    r, jvp = jax.linearize(fn, x)
    eye = jnp.eye(x.shape[0], dtype=x.dtype)
    jac = jax.vmap(jvp, in_axes=1, out_axes=1)(eye)
    return r, jac
