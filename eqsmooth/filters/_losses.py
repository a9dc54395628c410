"""Training losses for the EKF baseline (Yi et al. 2021, Sec. V)."""

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..manifold import local
from ._ekf import EKFSolution
from ._rts import RTSSolution


def _errors(mean: PyTree, truth: PyTree, at_mean: bool) -> Float[Array, "T d"]:
    # Manifold error per time step: truth ⊖ mean in the tangent at the mean
    # (where the covariance lives), or mean ⊖ truth at the truth.
    if at_mean:
        return jax.vmap(local)(mean, truth)
    return jax.vmap(local)(truth, mean)


def _check_truth(belief, truth, where: str) -> None:
    T = belief.covariance.shape[0]
    for leaf in jax.tree_util.tree_leaves(truth):
        if jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != T:
            raise ValueError(
                f"{where}: truth must be the state pytree with a leading time axis "
                f"of length {T}; got a leaf of shape {jnp.shape(leaf)}"
            )


def ekf_mse_loss(
    belief: EKFSolution | RTSSolution,
    truth: PyTree,
    weights: Float[Array, " d"] | None = None,
) -> Float[Array, ""]:
    """End-to-end MSE of the estimated means against ground truth.

    `mean_t Σ_j w_j e_{t,j}²` with `e_t = mean_t ⊖ truth_t` (manifold
    [`eqsmooth.manifold.local`][], so Lie-group states are compared in their
    tangent space). This is the paper's "E2E MSE" EKF baseline loss when
    `belief` is an [`eqsmooth.filters.EKFSolution`][]; it applies equally to
    an [`eqsmooth.filters.RTSSolution`][].

    **Arguments:**

    - `belief`: the filter (or RTS smoother) output.
    - `truth`: ground-truth states, the state pytree with a leading axis `T`.
    - `weights`: per tangent component weights `(d,)` (default: all ones),
        e.g. to balance metres against radians.

    **Returns:** a scalar.
    """
    _check_truth(belief, truth, "ekf_mse_loss")
    e = _errors(belief.mean, truth, at_mean=False)
    d = e.shape[-1]
    if weights is None:
        weights = jnp.ones((d,), dtype=e.dtype)
    elif weights.shape != (d,):
        raise ValueError(
            f"ekf_mse_loss: weights must have shape ({d},), got {weights.shape}"
        )
    return jnp.mean(jnp.sum(weights.astype(e.dtype)[None] * e * e, axis=-1))


def ekf_marginal_nll(
    belief: EKFSolution | RTSSolution, truth: PyTree
) -> Float[Array, ""]:
    """Negative log-likelihood of the ground truth under the Gaussian beliefs.

    The paper's EKF "marginal NLL" loss: the mean over time steps of
    `−log N(e_t; 0, P_t) = ½ e_tᵀ P_t⁻¹ e_t + ½ log det P_t + (d/2) log 2π` with
    `e_t = truth_t ⊖ mean_t` (tangent at the mean, where `P_t` lives). It
    trains the filter's uncertainty as well as its means. Not to be confused
    with the *innovation* log-likelihood of the measurements
    ([`eqsmooth.filters.EKFSolution`][]`.log_likelihood`, see
    [`eqsmooth.filters.ekf_innovation_nll`][]), which needs no ground truth.

    **Arguments:**

    - `belief`: the filter (or RTS smoother) output.
    - `truth`: ground-truth states, leading axis `T`.

    **Returns:** a scalar.
    """
    _check_truth(belief, truth, "ekf_marginal_nll")
    e = _errors(belief.mean, truth, at_mean=True)
    P = belief.covariance
    d = e.shape[-1]
    chol = jnp.linalg.cholesky(P)
    alpha = jax.scipy.linalg.solve_triangular(chol, e[..., None], lower=True)[..., 0]
    logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1)), axis=-1)
    nll = 0.5 * jnp.sum(alpha * alpha, axis=-1) + 0.5 * logdet
    return jnp.mean(nll) + 0.5 * d * math.log(2 * math.pi)


def ekf_innovation_nll(solution: EKFSolution) -> Float[Array, ""]:
    """Negative marginal log-likelihood of the measurements, `−log p(z_{0:T−1})`.

    The prediction-error decomposition accumulated by the filter
    (`−solution.log_likelihood`): unsupervised (no ground truth), the classic
    way to fit noise parameters of a Kalman filter by maximum likelihood.

    **Arguments:**

    - `solution`: an [`eqsmooth.filters.EKFSolution`][].

    **Returns:** a scalar (a sum over the sequence, not a mean).
    """
    return -solution.log_likelihood
