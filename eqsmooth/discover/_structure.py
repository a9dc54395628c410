"""Structural equivalence: candidates whose effects on the measurements are
the same up to the initial state, decided from the model and the inputs."""

import numpy as np

from ._fit import fitted_model
from ._model import ChainModel, Sequences, trajectory_checks


# `1 − ρ²` below this is an exact equivalence up to rounding (linear models
# give about 1e-13); an approximate likeness is the evidence's business.
STRUCTURAL_TOL = 1e-8


def _blocks(model: ChainModel, z: np.ndarray, data: Sequences, xhat, scales):
    """Jacobians of every step's transition and observation about `xhat`, by
    central differences: `A = ∂f/∂x` `(B, T, n, n)`, `C = ∂f/∂c` `(B, T, n,
    K)`, `H = ∂h/∂x` `(B, T, m, n)`, `D = ∂h/∂c` `(B, T, m, K)`.

    Differences of `trajectory_checks`, the program `find` has already
    compiled for this model (2 (n + K) calls of a few milliseconds), rather
    than a program of their own: forward-mode Jacobians compiled one more
    program, 2.8 s of a first call on a busy 2-core machine. The steps are
    1e-5 of each state's RMS size, and for a coefficient the value that
    moves its feature by that much (`scales`, the features' RMS sizes);
    candidate terms and linear models are exact under central differences
    up to rounding (about 1e-11 relative), far below `STRUCTURAL_TOL`.
    """
    K = len(model.candidates)
    x = np.asarray(xhat, dtype=float)
    n = x.shape[-1]
    size = np.sqrt(np.mean(x * x, axis=(0, 1))) + 1e-3
    steps_x = 1e-5 * size
    steps_c = 1e-5 * float(np.sqrt(np.mean(size**2))) / np.asarray(scales, float)

    def one(zz, xx):
        _, f, h = trajectory_checks(fitted_model(model, zz), xx, data.inputs)
        return np.asarray(f), np.asarray(h)

    A, H = [], []
    for i in range(n):
        e = np.zeros(n)
        e[i] = steps_x[i]
        (fp, hp), (fm, hm) = one(z, x + e), one(z, x - e)
        A.append((fp - fm) / (2 * steps_x[i]))
        H.append((hp - hm) / (2 * steps_x[i]))
    C, D = [], []
    for k in range(K):
        e = np.zeros_like(z)
        e[k] = steps_c[k]
        (fp, hp), (fm, hm) = one(z + e, x), one(z - e, x)
        C.append((fp - fm) / (2 * steps_c[k]))
        D.append((hp - hm) / (2 * steps_c[k]))
    return (np.stack(A, -1), np.stack(C, -1)), (np.stack(H, -1), np.stack(D, -1))


def mean_path_gram(
    model: ChainModel,
    z: np.ndarray,
    data: Sequences,
    xhat: np.ndarray,
    scales: np.ndarray,
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
    (A, C), (H, D) = _blocks(model, z, data, xhat, scales)
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


def structure(
    model: ChainModel, z, data: Sequences, xhat, scales: np.ndarray
) -> np.ndarray:
    """Which candidate pairs are structurally equivalent on `data`'s inputs,
    about the MAP `xhat` (see `mean_path_gram`; `scales` are the features'
    RMS sizes, `FindState.scales`)."""
    return structural_equivalents(*mean_path_gram(model, z, data, xhat, scales))
