"""Joint marginal covariances of chosen variables, cross-covariances included."""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float

from ...factors import Var
from .._linear._default_solver import linear_solver_for
from .._linear._linear_solver import solve_normal
from .._linearization import Linearization
from .._solution import RESULTS, Solution
from ._posterior import (
    as_linearization,
    raise_unless_ok,
    real_counts,
    singular_message,
)


def _selection(
    lin: Linearization, variables, real: dict[str, int] | None = None
) -> list[tuple[str, int]]:
    out = []
    for v in variables:
        if isinstance(v, Var):
            out.extend((v.group, int(i)) for i in v.ids)
        else:
            group, index = v
            out.append((str(group), int(index)))
    counts = real or {g.name: g.count for g in lin.layout}
    for group, index in out:
        if group not in counts:
            raise ValueError(
                f"joint_marginal_covariance: unknown group {group!r}; the graph has "
                f"{sorted(counts)}"
            )
        if not 0 <= index < counts[group]:
            raise ValueError(
                f"joint_marginal_covariance: index {index} out of range for group "
                f"{group!r} with {counts[group]} variables"
            )
    if not out:
        raise ValueError("joint_marginal_covariance: no variables selected")
    return out


def joint_marginal_covariance(
    lin: Linearization | Solution,
    variables: Sequence[tuple[str, int] | Var],
    solver: lx.AbstractLinearSolver | None = None,
) -> Float[Array, "k k"]:
    """Joint covariance of a few variables, cross-covariances included.

    The block of `(JᵀJ)⁻¹` (the Laplace approximation at the linearisation
    point, in right-perturbation tangent coordinates) on the rows and columns
    of the chosen variables. It is computed column by column, `k` solves with
    the graph's own linear solver (one factorisation for the direct ones), so
    no dense inverse of the whole normal matrix is ever formed: the cost is
    that of `k` solves, with `k` the summed tangent dimension of the chosen
    variables.

    **Arguments:**

    - `lin`: a [`eqsmooth.solve.Linearization`][], or the
        [`eqsmooth.solve.Solution`][] of a solve by `GaussNewton`,
        `LevenbergMarquardt` or `FixedStepGaussNewton`, whose final state
        keeps the linearisation at the solution (no new linearisation).
    - `variables`: `(group, index)` pairs and/or
        [`eqsmooth.factors.Var`][]s, in the order of the result.
    - `solver`: the linear solver; `None` picks the graph's default
        (`BlockTridiagonal()` for chains, else `DenseCholesky()` or
        `SparseLU()` by size).

    **Returns:**

    A `(k, k)` symmetric matrix: variable `j`'s tangent occupies
    `d_j` consecutive rows and columns, in the order given. A normal
    matrix that cannot be factorised or solved (singular, or too
    ill-conditioned in float32) raises an `EquinoxRuntimeError` that says
    which.
    """
    real = real_counts(lin)
    lin = as_linearization(lin, "joint_marginal_covariance")
    chosen = _selection(lin, variables, real)
    cov, ok = _joint(lin, tuple(chosen), solver)
    return raise_unless_ok(
        ok, cov, singular_message("joint_marginal_covariance", lin.dtype)
    )


@eqx.filter_jit
def _joint(lin: Linearization, chosen, solver):
    dims = {g.name: g.dim for g in lin.layout}
    solver = linear_solver_for(solver, lin)
    # One unit right-hand side per selected tangent coordinate.
    cols = [(g, i, c) for g, i in chosen for c in range(dims[g])]
    k = len(cols)
    rhs = {
        g.name: np.zeros((k, g.count, g.dim), dtype=np.dtype(lin.dtype))
        for g in lin.layout
    }
    for j, (g, i, c) in enumerate(cols):
        rhs[g][j, i, c] = 1.0
    rhs = {name: jnp.asarray(v) for name, v in rhs.items()}

    def column(b):
        x, result = solve_normal(solver, lin, rhs=b)
        return x, result == RESULTS.successful

    x, solved = jax.vmap(column)(rhs)
    rows = jnp.stack([x[g][:, i, c] for g, i, c in cols], axis=0)
    cov = 0.5 * (rows + rows.T)
    # An iterative solve of a singular system may stop with finite garbage in
    # some columns: any failed column or non-finite entry fails the whole.
    return cov, jnp.all(solved) & jnp.all(jnp.isfinite(cov))
