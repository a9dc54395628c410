"""Dense Cholesky: the reference solver for small graphs."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Bool, Float, PyTree

from ...factors import GroupLayout
from .._linearization import (
    flatten_layout,
    unflatten_layout,
)
from ._linear_solver import (
    AbstractFactorization,
    AbstractNormalSolver,
    diagonal_blocks,
    NormalOperator,
    pivot_tolerance,
    symmetric_psd_operator,
)


def dense_cholesky_ok(
    H: Float[Array, "N N"], upper_factor: Float[Array, "N N"]
) -> Bool[Array, ""]:
    """Whether a Cholesky factor of `H` has finite pivots above rounding level."""
    piv = jnp.diagonal(upper_factor)
    tol = pivot_tolerance(H.dtype, H.shape[0], jnp.asarray(1.0, H.dtype))
    return jnp.all(jnp.isfinite(upper_factor)) & jnp.all(
        piv * piv > tol * jnp.diagonal(H)
    )


class DenseFactorization(AbstractFactorization):
    """The state of [`eqsmooth.solve.DenseCholesky`][]: a dense Cholesky factor.

    `layout` is the tangent layout of the `NormalOperator` it factorises, or
    `None` for any other lineax operator (whose marginals are not defined).
    """

    lower: Float[Array, "N N"]
    ok: Bool[Array, ""]
    layout: tuple[GroupLayout, ...] | None = eqx.field(static=True)

    def log_det(self) -> Float[Array, ""]:
        return 2.0 * jnp.sum(jnp.log(jnp.diagonal(self.lower)))

    def solve(self, b: Float[Array, "N ..."]) -> Float[Array, "N ..."]:
        return jax.scipy.linalg.cho_solve((self.lower, True), b)

    def inverse_block_diagonal(self) -> dict[str, Float[Array, "_N _d _d"]]:
        if self.layout is None:
            raise ValueError(
                "DenseFactorization.inverse_block_diagonal needs the factorisation "
                "of an eqsmooth.solve.NormalOperator (its tangent layout names the "
                "blocks); this one factorises a general lineax operator"
            )
        eye = jnp.eye(self.lower.shape[0], dtype=self.lower.dtype)
        return diagonal_blocks(self.solve(eye), self.layout)


def _ravel(vector: PyTree[Array]) -> Float[Array, " N"]:
    """The leaves of `vector`, each flattened, concatenated in `tree_leaves`
    order: the row and column order of lineax's `as_matrix`."""
    leaves = jax.tree_util.tree_leaves(vector)
    dtype = jnp.result_type(*leaves)
    return jnp.concatenate([leaf.reshape(-1).astype(dtype) for leaf in leaves])


def _unravel(flat: Float[Array, " N"], like: PyTree[Array]) -> PyTree[Array]:
    """The inverse of `_ravel`, in the structure, shapes and dtypes of `like`."""
    leaves, treedef = jax.tree_util.tree_flatten(like)
    out, start = [], 0
    for leaf in leaves:
        part = flat[start : start + leaf.size]
        out.append(part.reshape(leaf.shape).astype(leaf.dtype))
        start += leaf.size
    return jax.tree_util.tree_unflatten(treedef, out)


class DenseCholesky(AbstractNormalSolver):
    """Dense Cholesky factorisation of a symmetric positive definite operator.

    Materialises the matrix (`N × N` for `N` unknowns) and factorises it:
    `O(N³)`. For the normal matrix `JᵀJ + diag(damping)` of a
    [`eqsmooth.solve.NormalOperator`][] it is the reference solver, for small
    graphs and tests; it accepts any graph structure, and its state is a
    [`eqsmooth.solve.DenseFactorization`][] (log-determinant, marginals).

    It also solves any real lineax operator tagged positive semidefinite
    (`lineax.positive_semidefinite_tag`): `lx.MatrixLinearOperator`,
    `lx.FunctionLinearOperator`, `lx.PyTreeLinearOperator`, vectors being any
    pytree of arrays. The matrix is `operator.as_matrix()` (which lineax
    computes by materialising a function operator), rows and columns in
    `jax.tree_util.tree_leaves` order. An operator without the tag raises a
    `ValueError` naming it. A matrix that is singular or not positive
    definite to working precision gives `RESULTS.singular` and a zero
    solution.
    """

    def init(
        self, operator: lx.AbstractLinearOperator, options: dict[str, Any]
    ) -> DenseFactorization:
        del options
        symmetric_psd_operator(operator, "DenseCholesky")
        # A NormalOperator materialises itself from its Jacobian blocks and
        # keeps its layout (for marginals); any other operator through lineax.
        layout = operator.lin.layout if isinstance(operator, NormalOperator) else None
        H = operator.as_matrix()
        lower = jnp.linalg.cholesky(0.5 * (H + H.T))
        ok = dense_cholesky_ok(H, lower.T)
        return DenseFactorization(lower, ok, layout)

    def compute(self, state: DenseFactorization, vector, options: dict[str, Any]):
        del options
        if state.layout is None:
            b = _ravel(vector)
        else:
            b = flatten_layout(state.layout, vector)
        x = state.solve(b.astype(state.lower.dtype))
        x = jnp.where(state.ok, x, jnp.zeros_like(x))
        result = lx.RESULTS.where(state.ok, lx.RESULTS.successful, lx.RESULTS.singular)
        # The operator is symmetric: the solution has the structure of `vector`.
        if state.layout is None:
            solution = _unravel(x, vector)
        else:
            solution = unflatten_layout(state.layout, x)
        return solution, result, {}
