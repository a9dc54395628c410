"""Matrix-free preconditioned conjugate gradients for general sparse graphs."""

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
from jaxtyping import Array, Float

from ._linear_solver import AbstractLinearSolver, all_finite
from ._linearization import (
    block_diagonal,
    gradient,
    Linearization,
    normal_matvec as _normal_matvec,
    Tangent,
)
from ._solution import RESULTS


def _structure(lin: Linearization):
    return {
        g.name: jax.ShapeDtypeStruct((g.count, g.dim), lin.dtype) for g in lin.layout
    }


def _damped(lin: Linearization, damping: Tangent | None) -> Tangent | None:
    if damping is None:
        return None
    return {g.name: damping[g.name].astype(lin.dtype) for g in lin.layout}


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
        chol = jnp.linalg.cholesky(b + jitter * eye[None])
        inv = jax.scipy.linalg.cho_solve((chol, True), jnp.broadcast_to(eye, b.shape))
        good = jnp.all(jnp.isfinite(inv), axis=(1, 2)) & (scale[:, 0, 0] > 0)
        out[g.name] = jnp.where(good[:, None, None], inv, eye[None])
    return out


class PCG(AbstractLinearSolver):
    """Block-Jacobi preconditioned conjugate gradients, matrix-free.

    Applies `JᵀJ + diag(damping)` through the Jacobian blocks (never forming
    it) and preconditions with the inverse of its per-variable diagonal
    blocks. For any graph structure, in particular graphs with loop closures;
    `O(nnz(J))` per iteration. Runs `lineax.CG` with `options={"preconditioner":
    ...}`; running out of steps returns `RESULTS.max_steps_reached` with the
    last iterate rather than raising.

    **Arguments:**

    - `rtol`, `atol`: stop when every component of the residual `b − H δ` is
        within `atol + rtol·|b|` (and likewise the last update against `δ`),
        lineax's criterion.
    - `max_steps`: the iteration limit.
    """

    rtol: float = eqx.field(static=True, default=1e-6)
    atol: float = eqx.field(static=True, default=1e-9)
    max_steps: int = eqx.field(static=True, default=500)

    def __check_init__(self):
        if self.rtol < 0 or self.atol < 0 or (self.rtol == 0 and self.atol == 0):
            raise ValueError(
                f"PCG needs rtol >= 0, atol >= 0, not both zero; got rtol={self.rtol}, "
                f"atol={self.atol}"
            )
        if self.max_steps < 1:
            raise ValueError(f"PCG needs max_steps >= 1, got {self.max_steps}")

    def solve(
        self,
        lin: Linearization,
        damping: Tangent | None,
        rhs: Tangent | None = None,
    ) -> tuple[Tangent, RESULTS]:
        damping = _damped(lin, damping)
        structure = _structure(lin)

        def matvec(delta):
            out = _normal_matvec(lin, delta)
            if damping is not None:
                out = {k: out[k] + damping[k] * delta[k] for k in out}
            return out

        inverse = block_jacobi_inverse(lin, damping)

        def precondition(v):
            return {k: jnp.einsum("nde,ne->nd", inverse[k], v[k]) for k in v}

        psd = lx.positive_semidefinite_tag
        operator = lx.FunctionLinearOperator(matvec, structure, psd)
        preconditioner = lx.FunctionLinearOperator(precondition, structure, psd)
        if rhs is None:
            rhs = {k: -v for k, v in gradient(lin).items()}
        else:
            rhs = {g.name: rhs[g.name].astype(lin.dtype) for g in lin.layout}
        solver = lx.CG(rtol=self.rtol, atol=self.atol, max_steps=self.max_steps)
        sol = lx.linear_solve(
            operator,
            rhs,
            solver,
            options={"preconditioner": preconditioner},
            throw=False,
        )
        finite = all_finite(list(sol.value.values()))
        delta = {
            k: jnp.where(finite, v, jnp.zeros_like(v)) for k, v in sol.value.items()
        }
        result = lx.RESULTS.where(finite, sol.result, lx.RESULTS.singular)
        return delta, RESULTS.promote(result)
