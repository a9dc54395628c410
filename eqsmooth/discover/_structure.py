"""Structural equivalence: candidates whose effects on the measurements are
the same up to the initial state, decided from the model and the inputs."""

import jax
import jax.numpy as jnp
import numpy as np

from ._model import _compiled, apply_z, ChainModel, Sequences


# `1 − ρ²` below this is an exact equivalence up to rounding (linear models
# give about 1e-13); an approximate likeness is the evidence's business.
STRUCTURAL_TOL = 1e-8


def _blocks_one(model: ChainModel, x, u):
    """Jacobians of one step's transition and observation with respect to
    the state and the candidate coefficients."""

    def f(x, c):
        return model.with_coefficients(c).transition(x, u)

    def h(x, c):
        return model.with_coefficients(c).observe(x, u)

    c = model.coefficients
    return jax.jacfwd(f, argnums=(0, 1))(x, c), jax.jacfwd(h, argnums=(0, 1))(x, c)


@_compiled
def _blocks(model: ChainModel, z, data: Sequences, xhat):
    m = apply_z(model, z)
    per_step = jax.vmap(_blocks_one, in_axes=(None, 0, 0))
    return jax.vmap(per_step, in_axes=(None, 0, 0))(m, xhat, data.inputs)


def mean_path_gram(
    model: ChainModel, z: np.ndarray, data: Sequences, xhat: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The `(K, K)` Gram matrix of the candidates' effects on the mean
    measurement path with each sequence's initial state profiled out, and
    the `(K,)` sizes (squared norms) of those effects before the projection.

    About the MAP `xhat` (coefficients and noise scales `z`) the model is
    linearised: a coefficient `c_k` moves the states by `δx_{t+1} = A_t δx_t
    + ∂f/∂c_k` from `δx_0 = 0` and the measurements by `δy_t = H_t δx_t +
    ∂h/∂c_k`, whitened by the measurement noise. For a linear-Gaussian model
    this is all that `c_k` does to the distribution of the data (the noise
    enters the same way whatever `c_k` is). The coefficients are shared by
    all sequences and the initial states are free (one per sequence), so
    each sequence's columns are projected off the span of its initial-state
    responses before the Gram matrix is summed over sequences. Two
    candidates whose projected columns are parallel change the data in the
    same way: only the prior on the first state can tell them apart.
    """
    z = np.asarray(z, dtype=float)
    (A, C), (H, D) = _blocks(model, jnp.asarray(z), data, jnp.asarray(xhat))
    A, C, H, D = (np.asarray(a) for a in (A, C, H, D))
    B, T, n, K = C.shape
    # The measurement noise of `apply_z(model, z)` (z[K + 1] its log scale).
    r = np.asarray(model.measurement_std) * np.exp(z[K + 1])
    # Columns: the K coefficients, then the n initial-state directions.
    dx = np.zeros((B, n, K + n))
    dx[:, :, K:] = np.eye(n)
    ys = []
    for t in range(T):
        dy = np.einsum("bmn,bnc->bmc", H[:, t], dx)
        dy[:, :, :K] += D[:, t]
        ys.append(dy / r[None, :, None])
        dx = np.einsum("bij,bjc->bic", A[:, t], dx)
        dx[:, :, :K] += C[:, t]
    S = np.concatenate(ys, axis=1)  # (B, T m, K + n)
    gram = np.zeros((K, K))
    for b in range(B):
        X, Sc = S[b, :, K:], S[b, :, :K]
        u, s, _ = np.linalg.svd(X, full_matrices=False)
        Q = u[:, s > 1e-10 * max(float(s.max(initial=0.0)), 1e-300)]
        P = Sc - Q @ (Q.T @ Sc)
        gram += P.T @ P
    return gram, np.sum(S[:, :, :K] ** 2, axis=(0, 1))


def structural_equivalents(gram: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """`(K, K)` booleans: the pairs whose projected effects are parallel
    (`1 − ρ² ≤ STRUCTURAL_TOL`), among candidates that keep an effect once the
    initial state is profiled (more than `1e-8` of their unprojected `sizes`).
    The diagonal is False."""
    d = np.diag(gram)
    alive = d > 1e-8 * np.maximum(sizes, 1e-300)
    rho = gram / np.sqrt(np.maximum(np.outer(d, d), 1e-300))
    same = (1.0 - rho * rho <= STRUCTURAL_TOL) & np.outer(alive, alive)
    np.fill_diagonal(same, False)
    return same


def structure(model: ChainModel, z, data: Sequences, xhat) -> np.ndarray:
    """Which candidate pairs are structurally equivalent on `data`'s inputs,
    about the MAP `xhat` (see `mean_path_gram`)."""
    return structural_equivalents(*mean_path_gram(model, z, data, xhat))
