"""The normal operator of a linearisation and the base of eqsmooth's linear solvers.

The Gauss-Newton / Levenberg-Marquardt step solves `(JᵀJ + diag(λ)) δ = −Jᵀr`
for a tangent dict `δ = {group: (N_g, d_g)}`. [`eqsmooth.solve.NormalOperator`][]
is that matrix as a `lineax.AbstractLinearOperator` over tangent dicts, so any
lineax solver (`lx.CG`, `lx.Cholesky`, `lx.AutoLinearSolver`) can solve the
step, and eqsmooth's structured solvers are `lineax.AbstractLinearSolver`s
that read the block structure of the operator.
"""

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Bool, Float

from .._linearization import (
    block_diagonal,
    dense_normal_matrix,
    flatten_tangent,
    gradient,
    Linearization,
    normal_matvec,
    Tangent,
    zeros_tangent,
)
from .._misc import nan_derivative_if
from .._solution import promote_result, RESULTS


class NormalOperator(lx.AbstractLinearOperator):
    """The normal matrix `JᵀJ + diag(damping)` of a linearisation, matrix-free.

    Acts on tangent dicts `{group: (N_g, d_g)}` (in and out structure alike).
    It is symmetric and positive semidefinite, and lineax knows it
    (`lx.is_symmetric` and `lx.is_positive_semidefinite` are true, every other
    structure predicate false), so `lx.Cholesky()`, `lx.CG(...)` and
    `lx.AutoLinearSolver(well_posed=None)` accept it without extra tags.
    `mv` applies `J` and `Jᵀ` block by block (never forming the matrix);
    `as_matrix` materialises the dense `N × N` matrix (group-major, the order
    of `jax.flatten_util.ravel_pytree` of a tangent dict).

    **Arguments:**

    - `lin`: the [`eqsmooth.solve.Linearization`][].
    - `damping`: a tangent dict of non-negative values added to the diagonal
        (Levenberg-Marquardt), or `None`.
    """

    lin: Linearization
    damping: Tangent | None = None

    def __check_init__(self):
        if self.damping is not None:
            names = sorted(g.name for g in self.lin.layout)
            if sorted(self.damping) != names:
                raise ValueError(
                    f"NormalOperator: damping has groups {sorted(self.damping)}, the "
                    f"linearisation has {names}"
                )

    def damping_of(self, name: str) -> Array | None:
        if self.damping is None:
            return None
        return self.damping[name].astype(self.lin.dtype)

    def mv(self, vector: Tangent) -> Tangent:
        vector = {
            g.name: vector[g.name].astype(self.lin.dtype) for g in self.lin.layout
        }
        out = normal_matvec(self.lin, vector)
        if self.damping is not None:
            out = {k: out[k] + self.damping_of(k) * vector[k] for k in out}
        return out

    def as_matrix(self) -> Float[Array, "N N"]:
        return dense_normal_matrix(self.lin, self.damping)

    def transpose(self) -> "NormalOperator":
        return self

    def in_structure(self) -> dict[str, jax.ShapeDtypeStruct]:
        dtype = self.lin.dtype
        return {
            g.name: jax.ShapeDtypeStruct((g.count, g.dim), dtype)
            for g in self.lin.layout
        }

    def out_structure(self) -> dict[str, jax.ShapeDtypeStruct]:
        return self.in_structure()

    def block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        """The diagonal blocks with damping: `{group: (N_g, d_g, d_g)}`."""
        blocks = block_diagonal(self.lin)
        if self.damping is None:
            return blocks
        out = {}
        for g in self.lin.layout:
            eye = jnp.eye(g.dim, dtype=self.lin.dtype)
            out[g.name] = (
                blocks[g.name] + self.damping_of(g.name)[:, :, None] * eye[None]
            )
        return out


def register_symmetric_psd(
    cls: type,
    diagonal: Callable,
    is_diagonal: Callable = lambda operator: False,
    is_tridiagonal: Callable = lambda operator: False,
) -> None:
    """Register lineax's rules for a symmetric positive semidefinite operator class.

    `linearise`, `materialise` and `conj` return the operator itself (it is
    linear, structured and real); it is symmetric and positive semidefinite,
    neither negative semidefinite nor triangular; `diagonal`, `is_diagonal`
    and `is_tridiagonal` are given.
    """
    for rule in (lx.linearise, lx.materialise, lx.conj):
        rule.register(cls)(lambda operator: operator)
    for rule in (lx.is_symmetric, lx.is_positive_semidefinite):
        rule.register(cls)(lambda operator: True)
    for rule in (
        lx.is_negative_semidefinite,
        lx.is_lower_triangular,
        lx.is_upper_triangular,
        lx.has_unit_diagonal,
    ):
        rule.register(cls)(lambda operator: False)
    lx.diagonal.register(cls)(diagonal)
    lx.is_diagonal.register(cls)(is_diagonal)
    lx.is_tridiagonal.register(cls)(is_tridiagonal)


def _normal_diagonal(operator: NormalOperator) -> Array:
    blocks = operator.block_diagonal()
    return jnp.concatenate(
        [
            jnp.diagonal(blocks[g.name], axis1=1, axis2=2).reshape(-1)
            for g in operator.lin.layout
        ]
    )


register_symmetric_psd(NormalOperator, _normal_diagonal)


class AbstractNormalSolver(lx.AbstractLinearSolver):
    """Base of eqsmooth's structured solvers of a [`eqsmooth.solve.NormalOperator`][].

    They are `lineax.AbstractLinearSolver`s: `lx.linear_solve(NormalOperator(lin),
    b, solver)` works, and so does passing any lineax solver where eqsmooth
    asks for a linear solver. The normal matrix is symmetric, so a solver's
    state is its own transpose and conjugate. Failures (a singular or
    indefinite system) give a non-successful result and a finite solution.
    """

    def transpose(self, state, options: dict[str, Any]):
        return state, options

    def conj(self, state, options: dict[str, Any]):
        return state, options

    def assume_full_rank(self) -> bool:
        return True


class AbstractFactorization(eqx.Module):
    """A factorisation of a normal matrix, as kept in a direct solver's state.

    Answers what the Laplace approximation needs without knowing which solver
    made it: [`eqsmooth.solve.marginal_covariances`][] and
    [`eqsmooth.solve.normal_log_det`][] call these methods.
    """

    ok: eqx.AbstractVar[Bool[Array, ""]]

    @abc.abstractmethod
    def log_det(self) -> Float[Array, ""]:
        """`log det` of the factorised matrix (NaN if it is not positive definite)."""

    @abc.abstractmethod
    def inverse_block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        """The diagonal blocks of the inverse, `{group: (N_g, d_g, d_g)}`."""


def _linear_solve(operator, b, linear_solver, options):
    """`lx.linear_solve(..., throw=False)` whose derivatives never throw.

    lineax differentiates and transposes a solve by solving again with
    `throw=True`, so the gradient of a failed solve (a singular or indefinite
    normal matrix in float32, say) stops the program with an error inside
    lineax. Here `jax.lax.custom_linear_solve` differentiates it implicitly
    (through `operator.mv`) and every solve, primal, tangent or transposed,
    keeps `throw=False`: the derivative of a failed solve is NaN, which a
    caller (e.g. [`eqsmooth.learn.train`][] with `on_nonfinite="skip"`) can
    detect. Returns the solution and lineax's result (an `lx.RESULTS` item,
    carried as the solve's non-differentiable auxiliary output).
    """

    def solve(_, rhs):
        sol = lx.linear_solve(
            operator, rhs, linear_solver, options=options, throw=False
        )
        return sol.value, sol.result

    return jax.lax.custom_linear_solve(
        operator.mv, b, solve, symmetric=True, has_aux=True
    )


def solve_normal(
    linear_solver: lx.AbstractLinearSolver,
    lin: Linearization,
    damping: Tangent | None = None,
    rhs: Tangent | None = None,
    options: dict[str, Any] | None = None,
) -> tuple[Tangent, RESULTS]:
    """Solve `(JᵀJ + diag(damping)) δ = −Jᵀr` (or `= rhs`) with any lineax solver.

    **Arguments:**

    - `linear_solver`: an eqsmooth solver (`BlockTridiagonal()`, `PCG()`,
        `SparseLU()`, `SparseCholesky()`, `DenseCholesky()`) or a lineax one
        (`lx.CG(rtol, atol)`, `lx.Cholesky()`, `lx.AutoLinearSolver(...)`).
    - `lin`: the [`eqsmooth.solve.Linearization`][].
    - `damping`: a tangent dict added to the diagonal, or `None`.
    - `rhs`: a tangent dict to use as right-hand side instead of `−Jᵀr`.
    - `options`: passed to `lineax.linear_solve` (e.g. `{"preconditioner": M}`).

    **Returns:**

    The step `δ` as a tangent dict and a [`eqsmooth.solve.RESULTS`][] code.
    When the solution is not finite, `δ` is zero and the code is
    `linear_solve_failed`; the derivatives of `δ` (forward or reverse) are
    then NaN, never zero or an exception, so that training notices.
    """
    if not isinstance(linear_solver, lx.AbstractLinearSolver):
        raise TypeError(
            "linear_solver must be a lineax.AbstractLinearSolver (e.g. "
            f"BlockTridiagonal(), lx.Cholesky()), got {type(linear_solver).__name__}"
        )
    operator = NormalOperator(lin, damping)
    if rhs is None:
        b = {k: -v for k, v in gradient(lin).items()}
    else:
        b = {g.name: rhs[g.name].astype(lin.dtype) for g in lin.layout}
    solution, lx_result = _linear_solve(operator, b, linear_solver, options)
    value = {g.name: solution[g.name] for g in lin.layout}
    finite = all_finite(jax.tree_util.tree_leaves(value))
    failed = jnp.logical_not(finite)
    value = {
        k: nan_derivative_if(failed, jnp.where(finite, v, jnp.zeros_like(v)), lin.cost)
        for k, v in value.items()
    }
    result = lx.RESULTS.where(finite, lx_result, lx.RESULTS.singular)
    return value, promote_result(result)


class UnsupportedOperatorError(TypeError, ValueError):
    """A linear solver was given a lineax operator it cannot solve.

    A `TypeError` (the operator has the wrong type); also a `ValueError`,
    which these checks raised before, so that older `except ValueError`
    clauses still catch it.
    """


def normal_operator_of(operator: lx.AbstractLinearOperator, who: str) -> NormalOperator:
    """`operator` if it is a `NormalOperator`, else a `TypeError` naming `who`.

    For the solvers that read the block structure of a linearisation (chains,
    sparse patterns) and cannot solve a general lineax operator.
    """
    if not isinstance(operator, NormalOperator):
        raise UnsupportedOperatorError(
            f"{who} solves the normal equations of a linearisation: it needs an "
            f"eqsmooth.solve.NormalOperator, got {type(operator).__name__} (for a "
            "general symmetric positive semidefinite lineax operator use "
            "eqsmooth.PCG() or eqsmooth.DenseCholesky())"
        )
    return operator


def symmetric_psd_operator(
    operator: lx.AbstractLinearOperator, who: str
) -> lx.AbstractLinearOperator:
    """`operator` if lineax knows it is positive semidefinite (hence symmetric
    and square) and real; else an error naming `who` and the tag."""
    if not isinstance(operator, lx.AbstractLinearOperator):
        raise UnsupportedOperatorError(
            f"{who} needs a lineax.AbstractLinearOperator, got "
            f"{type(operator).__name__}"
        )
    if not lx.is_positive_semidefinite(operator):
        raise ValueError(
            f"{who} needs a symmetric positive semidefinite operator: tag it with "
            "lineax.positive_semidefinite_tag (e.g. lx.MatrixLinearOperator(A, "
            f"lx.positive_semidefinite_tag)); got a {type(operator).__name__} "
            "without that tag"
        )
    # lineax itself checks that a tagged operator's input and output
    # structures agree (square), so only the entry type is left.
    in_leaves = jax.tree_util.tree_leaves(operator.in_structure())
    if any(jnp.issubdtype(a.dtype, jnp.complexfloating) for a in in_leaves):
        raise ValueError(f"{who} solves real systems; the operator is complex")
    return operator


def diagonal_blocks(
    inverse: Float[Array, "N N"], layout: tuple
) -> dict[str, Float[Array, "_n _d _d"]]:
    """The `(d, d)` diagonal blocks of a dense inverse of the normal matrix,
    per variable group of the tangent `layout` (group-major, as flattened)."""
    out, start = {}, 0
    for g in layout:
        size = g.count * g.dim
        block = inverse[start : start + size, start : start + size]
        block = block.reshape(g.count, g.dim, g.count, g.dim)
        i = np.arange(g.count)
        out[g.name] = block[i, :, i, :]
        start += size
    return out


def pivot_tolerance(dtype, size: int, scale: Float[Array, ""]) -> Float[Array, ""]:
    """Smallest acceptable squared Cholesky pivot.

    A pivot whose square is below `size · eps · scale` (with `scale` the largest
    diagonal entry of the matrix) is rounding noise: the matrix is singular to
    working precision. Pivots of a genuinely singular system (an unfixed gauge
    freedom) come out at about `eps · scale`, or negative, or NaN.
    """
    eps = float(np.finfo(dtype).eps)
    return jnp.asarray(size * eps, dtype) * scale


def all_finite(tree_leaves: list[Array]) -> Bool[Array, ""]:
    out = jnp.asarray(True)
    for leaf in tree_leaves:
        out = out & jnp.all(jnp.isfinite(leaf))
    return out


def flat_damping(lin: Linearization, damping: Tangent | None) -> Array | None:
    if damping is None:
        return None
    return flatten_tangent(lin, {k: v.astype(lin.dtype) for k, v in damping.items()})


def solve_unless(
    skip: Bool[Array, ""],
    linear_solver: lx.AbstractLinearSolver,
    lin: Linearization,
    damping: Tangent | None,
    options: dict[str, Any],
) -> tuple[Tangent, Bool[Array, ""]]:
    """[`eqsmooth.solve.solve_normal`][] for a nonlinear solver's next step,
    unless `skip` (the solver has stopped): `(δ, solved)`, where a skipped
    solve gives zeros and `True`. A `lax.cond`, so a stopped solve costs
    nothing (under `vmap` with a batched `skip` both branches run).
    `options` are the solver's optimistix options (`"linear_options"` is
    passed on)."""
    linear_options = options.get("linear_options")

    def solve(lin, damping):
        delta, res = solve_normal(linear_solver, lin, damping, options=linear_options)
        return delta, res == RESULTS.successful

    def skipped(lin, damping):
        del damping
        return zeros_tangent(lin), jnp.array(True)

    return jax.lax.cond(skip, skipped, solve, lin, damping)
