"""The interface every linear solver of the Gauss-Newton model implements."""

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._linearization import Linearization, Tangent
from ._solution import RESULTS


class AbstractLinearSolver(eqx.Module):
    """Solves the (damped) normal equations of a [`eqsmooth.solve.Linearization`][].

    Linear solvers are chosen by passing an instance to a nonlinear solver,
    e.g. `GaussNewton(linear_solver=BlockTridiagonal())`.
    """

    @abc.abstractmethod
    def solve(
        self,
        lin: Linearization,
        damping: Tangent | None,
        rhs: Tangent | None = None,
    ) -> tuple[Tangent, RESULTS]:
        """Solve `(JᵀJ + diag(damping)) δ = −Jᵀr` (or `= rhs`).

        **Arguments:**

        - `lin`: the whitened Gauss-Newton model.
        - `damping`: a tangent dict `{group: (N_g, d_g)}` of non-negative values
            added to the diagonal (Levenberg-Marquardt), or `None` (Gauss-Newton).
        - `rhs`: a tangent dict to use as right-hand side instead of `−Jᵀr`
            (the implicit adjoint and preconditioners use this), or `None`.

        **Returns:**

        The step `δ` as a tangent dict and a [`eqsmooth.solve.RESULTS`][] code.
        When the code is not `successful` (singular or indefinite system, or an
        iterative solver out of steps), `δ` is finite (zero for the direct
        solvers), never NaN.
        """


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
