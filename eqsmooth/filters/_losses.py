"""Training losses for the EKF baseline (Yi et al. 2021, Sec. V)."""

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PyTree

from ..manifold import local, manifold_mse
from ._ekf import EKFSolution
from ._rts import RTSSolution


def _errors_at_mean(mean: PyTree, truth: PyTree) -> Float[Array, "T d"]:
    # truth ⊖ mean in the tangent at the mean, where the covariance lives.
    return jax.vmap(local)(mean, truth)


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
    weights: PyTree | None = None,
) -> Float[Array, ""]:
    """End-to-end MSE of the estimated means against ground truth.

    [`eqsmooth.manifold.manifold_mse`][] of the means against the truth: the
    error of every time step is `mean_t ⊖ truth_t` (manifold
    [`eqsmooth.manifold.local`][], so Lie-group states are compared in their
    tangent space), and the loss is `Σ w e² / (number of error entries)`,
    the same normalisation as the smoother's
    [`eqsmooth.learn.surrogate_loss`][], so the two are comparable. This is
    the paper's "E2E MSE" EKF baseline loss when `belief` is an
    [`eqsmooth.filters.EKFSolution`][]; it applies equally to an
    [`eqsmooth.filters.RTSSolution`][].

    **Arguments:**

    - `belief`: the filter (or RTS smoother) output.
    - `truth`: ground-truth states, the state pytree with a leading axis `T`.
    - `weights`: `None` or per-component weights with the structure of the
        state (or a prefix of it), e.g. `jnp.array([1.0, 1.0, 10.0])` for an
        SE(2) state or `{"pose": ..., "vel": ...}` for a dict state; see
        [`eqsmooth.manifold.manifold_mse`][].

    **Returns:** a scalar.
    """
    _check_truth(belief, truth, "ekf_mse_loss")
    return manifold_mse(truth, belief.mean, weights)


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
    e = _errors_at_mean(belief.mean, truth)
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
