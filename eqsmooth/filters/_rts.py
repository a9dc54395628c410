"""Extended Rauch-Tung-Striebel smoothing of an EKF run."""

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from .._precision import matmul as mm
from ..manifold import local, retract
from ._ekf import EKFSolution


class RTSSolution(eqx.Module):
    """What [`eqsmooth.filters.rts_smoother`][] returns.

    **Fields:**

    - `mean`: smoothed means `x_{t|T−1}`, leading axis `T`.
    - `covariance`: smoothed covariances `(T, d, d)`, read in the tangent
        coordinates of the smoothed mean (first order; see the smoother's notes).
    """

    mean: PyTree
    covariance: Float[Array, "T d d"]


def _index(tree, i):
    return jax.tree_util.tree_map(lambda a: a[i], tree)


@eqx.filter_jit
def rts_smoother(solution: EKFSolution) -> RTSSolution:
    """Extended Rauch-Tung-Striebel smoother on the output of an EKF.

    A backward pass over the filter's own linearisation: with the gain
    `G_t = P_{t|t} F_tᵀ P_{t+1|t}⁻¹`,

    - `x_{t|T} = x_{t|t} ⊕ G_t (x_{t+1|T} ⊖ x_{t+1|t})`,
    - `P_{t|T} = P_{t|t} + G_t (P_{t+1|T} − P_{t+1|t}) G_tᵀ`.

    On a linear-Gaussian chain this is exact and equals the factor-graph MAP
    and its marginal covariances (tested). On a manifold it is the usual
    first-order approximation: the transition Jacobians are those of the
    filter (not re-linearised at the smoothed means, unlike the smoother of
    [`eqsmooth.solve.least_squares`][]), and covariances are not transported between
    the tangent spaces at `x_{t|t}` and `x_{t|T}`.

    **Arguments:**

    - `solution`: an [`eqsmooth.filters.EKFSolution`][].

    **Returns:** an [`eqsmooth.filters.RTSSolution`][].
    """
    T = solution.covariance.shape[0]
    last_mean = _index(solution.mean, T - 1)
    last_cov = solution.covariance[T - 1]
    xs = (
        _index(solution.mean, slice(0, T - 1)),
        solution.covariance[: T - 1],
        _index(solution.predicted_mean, slice(1, T)),
        solution.predicted_covariance[1:],
        solution.transition_jacobian,
    )

    def body(carry, x):
        next_mean, next_cov = carry
        mean, cov, pred_mean, pred_cov, F = x
        # G = P Fᵀ Pp⁻¹, with Pp symmetric positive definite.
        chol = jnp.linalg.cholesky(pred_cov)
        G = jax.scipy.linalg.cho_solve((chol, True), mm(F, cov)).T
        smoothed = retract(mean, mm(G, local(pred_mean, next_mean)))
        P = cov + mm(mm(G, next_cov - pred_cov), G.T)
        P = 0.5 * (P + P.T)
        return (smoothed, P), (smoothed, P)

    _, (means, covs) = lax.scan(body, (last_mean, last_cov), xs, reverse=True)
    mean = jax.tree_util.tree_map(
        lambda a, b: jnp.concatenate([a, b[None]], axis=0), means, last_mean
    )
    cov = jnp.concatenate([covs, last_cov[None]], axis=0)
    return RTSSolution(mean=mean, covariance=cov)
