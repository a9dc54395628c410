"""Matrix-free preconditioned conjugate gradients for general sparse graphs.

The iteration (`_misc.preconditioned_cg`, shared with the implicit adjoint)
is our own, not `lineax.CG`'s, because lineax stops CG per component
(`|r_i| ≤ atol + rtol·|b_i|`): on pose graphs the smallest entries of `b`
then decide, and CG runs thousands of iterations past the point where
the Gauss-Newton step is accurate. Here CG stops on the Euclidean norm,
`‖b − Hδ‖ ≤ max(rtol·‖b‖, atol)`, the usual inexact-Newton criterion. It
is a lineax solver of the [`eqsmooth.solve.NormalOperator`][], so forward and
reverse mode and `vmap` come from lineax's rules. `lx.CG` works on the same
operator too, with a preconditioner from
[`eqsmooth.solve.AbstractPreconditioner.as_operator`][] passed as
`options={"preconditioner": ...}`.
"""

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
from jaxtyping import Array, Float

from ..._precision import einsum
from ...factors import Var
from .._linearization import (
    block_diagonal,
    FactorLinearization,
    Linearization,
    Tangent,
)
from .._misc import preconditioned_cg
from ._block_tridiagonal import (
    assemble_chain,
    chain_plan,
    cyclic_reduction_factor,
    cyclic_reduction_solve,
)
from ._linear_solver import (
    AbstractNormalSolver,
    all_finite,
    NormalOperator,
    symmetric_psd_operator,
)
from ._small_blocks import block_cho_solve, block_cholesky


# ---------------------------------------------------------------------------
# Preconditioners
# ---------------------------------------------------------------------------


class AbstractPreconditioner(eqx.Module):
    """How [`eqsmooth.solve.PCG`][] preconditions `JᵀJ + diag(damping)`.

    A preconditioner builds, once per linear solve, a symmetric positive
    definite approximation `M` of the normal matrix and returns the map
    `v ↦ M⁻¹ v` on tangent dicts. It never changes the solution, only how
    fast CG reaches it, and it is not differentiated.
    """

    @abc.abstractmethod
    def build(
        self, lin: Linearization, damping: Tangent | None
    ) -> Callable[[Tangent], Tangent]:
        """Return `v ↦ M⁻¹ v` as a pytree-compatible callable (`eqx.Partial`).

        **Arguments:**

        - `lin`: the Gauss-Newton model.
        - `damping`: the diagonal added to `JᵀJ`, or `None`.
        """

    def as_operator(self, operator: NormalOperator) -> lx.AbstractLinearOperator:
        """`M⁻¹` as a lineax operator tagged positive semidefinite.

        What lineax's `options={"preconditioner": ...}` convention takes, for
        `lx.CG` or [`eqsmooth.solve.PCG`][] solving `operator`. Built from
        the stopped operator: preconditioners are not differentiated.
        """
        op = jax.lax.stop_gradient(operator)
        apply = self.build(op.lin, op.damping)
        return lx.FunctionLinearOperator(
            apply, operator.in_structure(), lx.positive_semidefinite_tag
        )


def block_jacobi_inverse(
    lin: Linearization, damping: Tangent | None
) -> dict[str, Float[Array, "_N _d _d"]]:
    """Inverses of the diagonal blocks of `JᵀJ + diag(damping)`, per variable.

    A block that cannot be factorised (a variable no factor constrains in
    some direction) gets a small jitter and, failing that, the identity: the
    preconditioner only needs to be positive definite, not exact.
    """
    blocks = block_diagonal(lin)
    out = {}
    for g in lin.layout:
        b = blocks[g.name]
        eye = jnp.eye(g.dim, dtype=lin.dtype)
        if damping is not None:
            b = b + damping[g.name][:, :, None] * eye[None]
        diag = jnp.diagonal(b, axis1=1, axis2=2)
        scale = jnp.max(diag, axis=1, keepdims=True)[:, :, None]
        jitter = jnp.asarray(jnp.finfo(lin.dtype).eps, lin.dtype) * scale
        chol = block_cholesky(b + jitter * eye[None])
        inv = block_cho_solve(chol, jnp.broadcast_to(eye, b.shape))
        good = jnp.all(jnp.isfinite(inv), axis=(1, 2)) & (scale[:, 0, 0] > 0)
        out[g.name] = jnp.where(good[:, None, None], inv, eye[None])
    return out


def _apply_block_jacobi(inverse, v: Tangent) -> Tangent:
    return {k: einsum("nde,ne->nd", inverse[k], v[k]) for k in v}


class BlockJacobi(AbstractPreconditioner):
    """Block-Jacobi: the inverses of the per-variable diagonal blocks of `JᵀJ`.

    Cheap (`O(N d³)` to build, `O(N d²)` to apply) and works for any graph,
    but it sees no coupling between variables: on long odometry chains CG
    then needs many iterations (the condition number grows with the chain
    length). The default of [`eqsmooth.solve.PCG`][].
    """

    def build(self, lin, damping):
        return eqx.Partial(_apply_block_jacobi, block_jacobi_inverse(lin, damping))


def _chain_part(lin: Linearization) -> Linearization:
    """The chain-shaped part of `lin`, for a block-tridiagonal preconditioner.

    Rows touching time steps `t, t+1` only are kept whole. A longer-range row
    (a loop closure) with Jacobian blocks `J_1, …, J_k` is replaced by `k`
    unary rows `J_i`: its normal-matrix contribution `JᵀJ` becomes the block
    diagonal `diag(J_iᵀJ_i)`, which is positive semidefinite and satisfies
    `JᵀJ ⪯ k·diag(J_iᵀJ_i)`, so the result stays a positive definite
    preconditioner within a constant factor of those rows' contribution.
    This is a subgraph preconditioner in the sense of Dellaert et al.,
    "Subgraph-preconditioned conjugate gradients for large scale SLAM"
    (IROS 2010), with the odometry chain as the subgraph.
    """
    out = []
    for fl in lin.factors:
        ids = np.stack([np.asarray(v.ids) for v in fl.variables])  # (k, n)
        if ids.shape[1] == 0:
            continue
        span = ids.max(axis=0) - ids.min(axis=0)
        near = span <= 1
        if near.all():
            out.append(fl)
            continue
        if near.any():
            rows = np.nonzero(near)[0]
            out.append(
                FactorLinearization(
                    fl.residual[rows],
                    tuple(j[rows] for j in fl.jacobians),
                    tuple(Var(v.group, np.asarray(v.ids)[rows]) for v in fl.variables),
                    fl.name,
                )
            )
        rows = np.nonzero(~near)[0]
        for j, v in zip(fl.jacobians, fl.variables):
            out.append(
                FactorLinearization(
                    fl.residual[rows],
                    (j[rows],),
                    (Var(v.group, np.asarray(v.ids)[rows]),),
                    f"{fl.name} (loop closures)",
                )
            )
    return Linearization(tuple(out), lin.layout, lin.cost)


class ChainPreconditioner(AbstractPreconditioner):
    """Block-tridiagonal preconditioner from the graph's chain (odometry) part.

    For graphs that are a chain plus long-range factors (pose graphs: an
    odometry chain with loop closures; smoothing problems with a few
    long-range constraints): every variable group has one variable per time
    step, and the preconditioner keeps every factor row touching steps `t` and
    `t + 1` only, plus the diagonal blocks `J_iᵀJ_i` of the longer-range rows.
    `M` is block tridiagonal and solved exactly by block cyclic reduction
    (`O(T D³)` to build and apply), so CG only has to resolve what the loop
    closures add. On a pure chain `M` is the whole matrix and CG converges in
    one iteration.

    Requires every group to have the same number of variables (raises a
    `ValueError` otherwise, like [`eqsmooth.solve.BlockTridiagonal`][]);
    the variables should be numbered along the trajectory (g2o files are).
    If `M` turns out singular, block-Jacobi is used instead.
    """

    def build(self, lin, damping):
        part = _chain_part(lin)
        plan = chain_plan(part)
        diag, upper, _ = assemble_chain(part, plan, damping)
        # A relative jitter keeps unconstrained directions (an unfixed gauge
        # freedom) from making M singular.
        dvals = jnp.diagonal(diag, axis1=1, axis2=2)
        scale = jnp.max(dvals)
        eps = jnp.asarray(jnp.finfo(lin.dtype).eps, lin.dtype)
        eye = jnp.eye(plan.block_size, dtype=lin.dtype)
        diag = diag + (16 * eps * scale) * eye[None]
        factor = cyclic_reduction_factor(diag, upper)
        jacobi = block_jacobi_inverse(lin, damping)
        layout = lin.layout

        # `plan` is static (numpy); a closure keeps it out of the pytree.
        def apply(factor, jacobi, v: Tangent) -> Tangent:
            b = plan.from_tangent(v, layout, factor.tail.chol_inv.dtype)
            x = plan.to_tangent(cyclic_reduction_solve(factor, b), layout)
            fallback = _apply_block_jacobi(jacobi, v)
            return {k: jnp.where(factor.ok, x[k], fallback[k]) for k in x}

        return eqx.Partial(apply, factor, jacobi)


# ---------------------------------------------------------------------------
# The solver
# ---------------------------------------------------------------------------


class _PCGState(eqx.Module):
    operator: lx.AbstractLinearOperator
    precondition: Callable


class PCG(AbstractNormalSolver):
    """Preconditioned conjugate gradients on `JᵀJ + diag(damping)`, matrix-free.

    A lineax solver of the [`eqsmooth.solve.NormalOperator`][]: applies the
    normal matrix through the Jacobian blocks (never forming it),
    `O(nnz(J))` per iteration, for any graph structure, in particular graphs
    with loop closures. Through `lineax.linear_solve` it `vmap`s and its
    solution can be differentiated (forward and reverse mode; the derivative
    is that of the exact solve, computed by more CG solves).

    CG stops when the residual norm `‖b − Hδ‖₂ ≤ max(rtol·‖b‖₂, atol)` (an
    inexact Newton step). If it runs out of `max_steps`, the last iterate is
    returned as `successful` by default (`accept_inexact=True`): CG's
    iterates decrease the Gauss-Newton model monotonically, so
    [`eqsmooth.solve.LevenbergMarquardt`][]'s gain ratio can judge the step.
    A breakdown (non-positive curvature: the system is singular or
    indefinite along a search direction) returns a non-successful code with
    the last finite iterate.

    The preconditioner is the `preconditioner` field, applied to the
    operator being solved; lineax's convention
    `options={"preconditioner": M}` (a positive semidefinite lineax
    operator approximating the inverse) overrides it.

    Any real lineax operator tagged positive semidefinite
    (`lineax.positive_semidefinite_tag`, which lineax reads as symmetric too)
    can be solved: `lx.MatrixLinearOperator`, `lx.FunctionLinearOperator`,
    `lx.PyTreeLinearOperator`, vectors being any pytree of arrays (CG's
    vector operations are tree-mapped and only `operator.mv` is called).
    One that is not a `NormalOperator` is preconditioned only through
    `options` (the identity otherwise). An operator without the tag raises a
    `ValueError` naming it.

    **Arguments:**

    - `rtol`: relative tolerance on the residual norm.
    - `atol`: absolute tolerance on the residual norm.
    - `max_steps`: the CG iteration limit.
    - `preconditioner`: [`eqsmooth.solve.BlockJacobi`][] (default, any
        graph) or [`eqsmooth.solve.ChainPreconditioner`][] (a chain plus
        loop closures, e.g. pose graphs: far fewer iterations).
    - `accept_inexact`: whether an iterate left by `max_steps` counts as
        success; `False` reports `RESULTS.max_steps_reached` instead.
    """

    rtol: float = eqx.field(static=True, default=1e-6)
    atol: float = eqx.field(static=True, default=0.0)
    max_steps: int = eqx.field(static=True, default=500)
    preconditioner: AbstractPreconditioner = eqx.field(default_factory=BlockJacobi)
    accept_inexact: bool = eqx.field(static=True, default=True)

    def __check_init__(self):
        if self.rtol < 0 or self.atol < 0 or (self.rtol == 0 and self.atol == 0):
            raise ValueError(
                f"PCG needs rtol >= 0, atol >= 0, not both zero; got rtol={self.rtol}, "
                f"atol={self.atol}"
            )
        if self.max_steps < 1:
            raise ValueError(f"PCG needs max_steps >= 1, got {self.max_steps}")
        if not isinstance(self.preconditioner, AbstractPreconditioner):
            raise TypeError(
                "PCG preconditioner must be an AbstractPreconditioner (e.g. "
                f"BlockJacobi()), got {type(self.preconditioner).__name__}"
            )

    def init(self, operator: lx.AbstractLinearOperator, options: dict[str, Any]):
        symmetric_psd_operator(operator, "PCG")
        M = options.get("preconditioner")
        if M is None:
            if isinstance(operator, NormalOperator):
                M = self.preconditioner.as_operator(operator)
            else:
                M = lx.IdentityLinearOperator(operator.in_structure())
        elif not lx.is_positive_semidefinite(M):
            raise ValueError(
                "PCG: options['preconditioner'] must be tagged positive semidefinite"
            )
        return _PCGState(operator, M.mv)

    def compute(self, state: _PCGState, vector, options: dict[str, Any]):
        del options
        x, converged, breakdown, k = preconditioned_cg(
            state.operator.mv,
            state.precondition,
            vector,
            self.rtol,
            self.atol,
            self.max_steps,
        )
        finite = all_finite(jax.tree_util.tree_leaves(x))
        x = jax.tree_util.tree_map(lambda v: jnp.where(finite, v, jnp.zeros_like(v)), x)
        out_of_steps = (
            lx.RESULTS.successful
            if self.accept_inexact
            else lx.RESULTS.max_steps_reached
        )
        result = lx.RESULTS.where(
            converged,
            lx.RESULTS.successful,
            lx.RESULTS.where(breakdown, lx.RESULTS.singular, out_of_steps),
        )
        result = lx.RESULTS.where(finite, result, lx.RESULTS.singular)
        return x, result, {"num_steps": k, "converged": converged}
