"""A differentiable extended Kalman filter on manifolds, built from factors."""

import math
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.lax as lax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from .._precision import matmul as mm
from ..factors import AbstractFactor
from ..manifold import is_group, local, retract, tangent_dim
from ._chain import (
    chain_order,
    checked_covariance,
    checked_measurements,
    residual_dim,
    time_layers,
    value_and_jacobian,
)
from ._rows import (
    gather_rows,
    per_row_fields,
    row_whitening,
    with_rows,
)


class EKFSolution(eqx.Module):
    """What [`eqsmooth.filters.ekf`][] returns.

    Covariances are in the tangent coordinates of the corresponding mean
    (right perturbations, `x ⊕ δ` with `δ ~ N(0, P)`). Innovations are
    *whitened*: `y = −R r(x̂)` with `R` the measurement's square-root
    information, so for a Gaussian measurement `y ~ N(0, S)`.

    **Fields:**

    - `mean`: filtered means `x_{t|t}`, the state pytree with a leading axis `T`.
    - `covariance`: filtered covariances `P_{t|t}`, shape `(T, d, d)`.
    - `predicted_mean`: `x_{t|t−1}` (with `x_{0|−1}` the initial mean), leading
        axis `T`.
    - `predicted_covariance`: `P_{t|t−1}`, shape `(T, d, d)`.
    - `transition_jacobian`: `F_t`, shape `(T−1, d, d)`, mapping the tangent at
        `x_{t|t}` to the tangent at `x_{t+1|t}` (used by
        [`eqsmooth.filters.rts_smoother`][]).
    - `innovations`: one array `(n_j, m_j)` per measurement stack, aligned with
        that stack's rows.
    - `innovation_covariances`: one array `(n_j, m_j, m_j)` per measurement
        stack (`S = H P Hᵀ + I` in whitened units).
    - `step_log_likelihood`: `log p(z_t | z_{<t})` for every time step, `(T,)`;
        zero at steps without measurements.
    - `log_likelihood`: their sum, the marginal log-likelihood `log p(z_{0:T−1})`
        of the measurements under the linearised model.
    """

    mean: PyTree
    covariance: Float[Array, "T d d"]
    predicted_mean: PyTree
    predicted_covariance: Float[Array, "T d d"]
    transition_jacobian: Float[Array, "Tm1 d d"]
    innovations: tuple[Float[Array, "_n _m"], ...]
    innovation_covariances: tuple[Float[Array, "_n _m _m"], ...]
    step_log_likelihood: Float[Array, " T"]
    log_likelihood: Float[Array, ""]


def _sym(P):
    return 0.5 * (P + P.T)


def ekf(
    transition: AbstractFactor,
    measurements: Sequence[AbstractFactor],
    initial_mean: PyTree,
    initial_covariance: Float[ArrayLike, "d d"],
    *,
    prediction_steps: int = 1,
    reset_covariance: bool = False,
    throw: bool = True,
) -> EKFSolution:
    """Run an extended Kalman filter defined by the smoother's own factors.

    The same factor stacks that make up a smoothing graph define the filter:
    no second model description. Time runs over the rows of `transition`:
    `T = transition.num_rows + 1` states.

    *Prediction.* With the whitened transition residual `r_w(a, b) = W r(a, b)`
    (`r_w ~ N(0, I)`), the predicted mean `b̂` solves `r(x_{t|t}, b) = 0` by
    `prediction_steps` Newton steps in the tangent of `b`, started at
    `b = x_{t|t}`. One step is exact for residuals of the form `b ⊖ f(a)`,
    `f(a) ⊖ b` and the [`eqsmooth.factors.BetweenFactor`][] residual, on vector spaces
    and Lie groups alike. With `A = ∂r_w/∂δa` and `B = ∂r_w/∂δb` at
    `(x_{t|t}, b̂)` (forward-mode autodiff through
    [`eqsmooth.manifold.retract`][]), `F = −B⁻¹A`, `Q = B⁻¹B⁻ᵀ` and
    `P_{t+1|t} = F P Fᵀ + Q`.

    *Update.* For each measurement row at time `t` (stacks in the given order,
    rows of one stack at the same `t` in row order), with the whitened
    residual `r_w(x) = R r(x) ~ N(0, I)` and `H = ∂r_w/∂δ` at the prediction
    `x̂`: innovation `y = −r_w(x̂)`, `S = H P Hᵀ + I`, `K = P Hᵀ S⁻¹`,
    `x = x̂ ⊕ K y` and the Joseph form `P = (I − KH) P (I − KH)ᵀ + K Kᵀ`.
    The log-likelihood adds `log N(y; 0, S) + log|det R|`, which is the density
    of the measurement itself when `r = h(x) − z`.

    Everything is a `lax.scan`, so `jax.jit`, `jax.vmap` (batches of
    sequences) and `jax.grad` (with respect to any array leaf of the factors,
    including per-row noise parameters, and to the initial belief) apply.

    **Arguments:**

    - `transition`: a factor stack whose rows touch `(x_t, x_{t+1})` of one
        variable group, one row per `t = 0..T−2` (in any row order). Its
        residual dimension must equal the tangent dimension `d` of the state.
    - `measurements`: factor stacks whose rows each touch one `x_t` of the same
        group; they may cover any subset of time steps (missing measurements)
        and several rows may share a time step.
    - `initial_mean`: the prior mean of `x_0`, one state (pytree of arrays and
        Lie groups such as [`eqsmooth.lie.SE2`][], no leading time axis).
    - `initial_covariance`: its covariance `(d, d)` in tangent coordinates.
    - `prediction_steps`: Newton steps solving `r(a, b) = 0` for the predicted
        mean (at least 1).
    - `reset_covariance`: after each update, move the covariance from the
        tangent at `x̂` to the tangent at the updated mean `x = x̂ ⊕ v` by the
        Jacobian `J` of `δ ↦ (x̂ ⊕ (v + δ)) ⊖ x`, i.e. `P ← J P Jᵀ` (the
        "covariance reset" of multiplicative/invariant EKFs). It has no effect
        on vector-space states. Off by default: the textbook EKF.
    - `throw`: raise an `EquinoxRuntimeError` (through `eqx.error_if`) if a
        covariance or the log-likelihood is not finite, e.g. a singular
        transition Jacobian `B`, or if a traced initial belief is invalid;
        with `throw=False` non-finite values are returned as they are, and
        the compiled program holds no host callback (JAX's persistent cache
        stores only programs without one). A concrete invalid initial belief
        raises `ValueError` either way.

    **Returns:** an [`eqsmooth.filters.EKFSolution`][].

    Raises `ValueError`/`TypeError` naming the factor if the transition is not
    a chain `t → t+1`, a measurement touches another group or several
    variables, a time index is out of range, or a noise model is robust.
    """
    if not isinstance(transition, AbstractFactor):
        raise TypeError(
            f"ekf: transition must be an AbstractFactor, got "
            f"{type(transition).__name__}"
        )
    measurements = checked_measurements(transition, measurements)
    if not isinstance(prediction_steps, int) or prediction_steps < 1:
        raise ValueError(
            f"ekf: prediction_steps must be an int >= 1, got {prediction_steps!r}"
        )
    d = tangent_dim(initial_mean)
    initial_covariance = checked_covariance("ekf", initial_covariance, d)
    initial_mean, initial_covariance = _check_initial_belief(
        initial_mean, initial_covariance, throw
    )
    return _ekf(
        transition,
        measurements,
        initial_mean,
        initial_covariance,
        prediction_steps,
        reset_covariance,
        throw,
    )


def _check_initial_belief(
    mean: PyTree, cov: Array, throw: bool
) -> tuple[PyTree, Array]:
    """Validate the initial belief: a finite mean and a finite, symmetric,
    positive-definite covariance. Concrete values raise `ValueError` naming
    the fault; traced ones get an `eqx.error_if` when `throw` (a host
    callback, which also keeps JAX's persistent cache from storing the
    program: without `throw` they pass as they are)."""
    if not jnp.issubdtype(cov.dtype, jnp.floating):
        raise TypeError(
            f"ekf: initial_covariance must be a floating-point array, got {cov.dtype}"
        )
    leaves = [
        leaf.parameters() if is_group(leaf) else jnp.asarray(leaf)
        for leaf in jax.tree_util.tree_leaves(mean, is_leaf=is_group)
    ]
    concrete = not any(isinstance(x, jax.core.Tracer) for x in leaves + [cov])
    if concrete:
        for k, leaf in enumerate(leaves):
            if not np.all(np.isfinite(np.asarray(leaf))):
                raise ValueError(
                    f"ekf: initial_mean has non-finite entries (leaf {k}, shape "
                    f"{leaf.shape})"
                )
        c = np.asarray(cov, dtype=np.float64)
        if not np.all(np.isfinite(c)):
            raise ValueError("ekf: initial_covariance has non-finite entries")
        asym = np.max(np.abs(c - c.T), initial=0.0)
        if asym > 1e-8 * max(np.max(np.abs(c), initial=0.0), 1e-300):
            raise ValueError(
                f"ekf: initial_covariance is not symmetric (largest |P - Pᵀ| entry "
                f"{asym:.3g})"
            )
        eig = np.linalg.eigvalsh(c) if c.size else np.ones(1)
        if eig.min() <= 0:
            raise ValueError(
                "ekf: initial_covariance is not positive definite (smallest "
                f"eigenvalue {eig.min():.3g})"
            )
        return mean, cov
    if not throw:
        return mean, cov
    finite = jnp.all(jnp.isfinite(cov))
    for leaf in leaves:
        finite = finite & jnp.all(jnp.isfinite(leaf))
    chol = jnp.linalg.cholesky(cov)
    ok = finite & jnp.all(jnp.isfinite(chol)) & jnp.allclose(cov, cov.T)
    cov = eqx.error_if(
        cov,
        ~ok,
        "ekf: the initial belief is invalid: initial_mean or initial_covariance is "
        "not finite, or the covariance is not symmetric positive definite",
    )
    return mean, cov


@eqx.filter_jit
def _update(mean, cov, factor, R, logdet_R, present, reset_covariance: bool):
    """One measurement update (skipped where `present` is false): the new
    mean and covariance, and (whitened innovation, its covariance, log-lik)."""
    d, dtype = cov.shape[0], cov.dtype

    def r_w(delta):
        return mm(R, factor.residual(retract(mean, delta)))

    r, H = value_and_jacobian(r_w, d, dtype)
    m = r.shape[0]
    y = -r
    PHt = mm(cov, H.T)
    S = _sym(mm(H, PHt) + jnp.eye(m, dtype=dtype))
    L = jnp.linalg.cholesky(S)
    K = jax.scipy.linalg.cho_solve((L, True), PHt.T).T
    v = mm(K, y)
    new_mean = retract(mean, v)
    IKH = jnp.eye(d, dtype=dtype) - mm(K, H)
    new_cov = mm(mm(IKH, cov), IKH.T) + mm(K, K.T)
    if reset_covariance:

        def moved(delta):
            return local(new_mean, retract(mean, v + delta))

        _, J = value_and_jacobian(moved, d, dtype)
        new_cov = mm(mm(J, new_cov), J.T)
    new_cov = _sym(new_cov)
    alpha = jax.scipy.linalg.solve_triangular(L, y, lower=True)
    ll = (
        -0.5 * mm(alpha, alpha)
        - jnp.sum(jnp.log(jnp.diagonal(L)))
        - 0.5 * m * math.log(2 * math.pi)
        + logdet_R
    )
    mean = jax.tree_util.tree_map(lambda a, b: jnp.where(present, a, b), new_mean, mean)
    cov = jnp.where(present, new_cov, cov)
    y = jnp.where(present, y, jnp.zeros_like(y))
    S = jnp.where(present, S, jnp.eye(m, dtype=dtype))
    ll = jnp.where(present, ll, jnp.zeros_like(ll))
    return mean, cov, (y, S, ll)


def _predict(mean, cov, factor, W, prediction_steps: int):
    """The predicted mean and covariance of the next state, and `F`."""
    d, dtype = cov.shape[0], cov.dtype

    def r_w(a, b):
        return mm(W, factor.residual(a, b))

    b = mean
    for _ in range(prediction_steps):
        r, B = value_and_jacobian(lambda db: r_w(mean, retract(b, db)), d, dtype)
        b = retract(b, -jnp.linalg.solve(B, r))

    def joint(delta):
        return r_w(retract(mean, delta[:d]), retract(b, delta[d:]))

    _, J = value_and_jacobian(joint, 2 * d, dtype)
    A, B = J[:, :d], J[:, d:]
    Binv = jnp.linalg.solve(B, jnp.eye(d, dtype=dtype))
    F = -mm(Binv, A)
    P = _sym(mm(mm(F, cov), F.T) + mm(Binv, Binv.T))
    return b, P, F


def _transition_rows(transition, mean0, d: int, dtype):
    """The transition's rows in time order, padded with one dummy row so that
    every scan step is "update at t, then predict t+1" (the last prediction
    is discarded): (scanned arrays, static part)."""
    _, perm = chain_order(transition)
    trans_rows = per_row_fields(transition)
    m_trans = residual_dim(transition, trans_rows, mean0, mean0)
    if m_trans != d:
        raise ValueError(
            f"ekf: the transition factor {type(transition).__name__} has residual "
            f"dimension {m_trans} but the state has tangent dimension {d}; the "
            "residual must determine x_t+1 given x_t (a square Jacobian)"
        )
    W_all, _ = row_whitening(transition, d, dtype)
    order = np.concatenate([perm, perm[-1:]])
    dyn, static = eqx.partition(gather_rows(trans_rows, order), eqx.is_array)
    return (dyn, W_all[order]), static


def _measurement_layers(measurements, mean0, T: int, dtype):
    """Each measurement stack's rows as layers over time (a stack may have
    several rows per step): static parts, scanned arrays and the layout."""
    meas_static, meas_xs, meas_layout = [], [], []
    for f in measurements:
        rows = per_row_fields(f)
        m = residual_dim(f, rows, mean0)
        R_all, logdet_all = row_whitening(f, m, dtype)
        ids = f.variables[0].ids
        layer, table, mask = time_layers(ids, T)
        dyn, static = eqx.partition(gather_rows(rows, table), eqx.is_array)
        meas_static.append(static)
        meas_xs.append((dyn, R_all[table], logdet_all[table], jnp.asarray(mask)))
        meas_layout.append((ids, layer, m))
    return meas_static, meas_xs, meas_layout


def _innovations(records, meas_layout, layer_counts, T: int, dtype):
    """Per-stack innovations and covariances in row order, and the per-step
    log-likelihood, from the updates recorded stack by stack, layer by layer."""
    innovations, innovation_covs = [], []
    step_ll = jnp.zeros((T,), dtype=dtype)
    start = 0
    for j, (ids, layer, m) in enumerate(meas_layout):
        ys = jnp.stack([records[start + k][0] for k in range(layer_counts[j])], 1)
        Ss = jnp.stack([records[start + k][1] for k in range(layer_counts[j])], 1)
        for k in range(layer_counts[j]):
            step_ll = step_ll + records[start + k][2]
        start += layer_counts[j]
        innovations.append(ys[ids, layer])
        innovation_covs.append(Ss[ids, layer])
    return tuple(innovations), tuple(innovation_covs), step_ll


def _ekf(
    transition, measurements, mean0, cov0, prediction_steps, reset_covariance, throw
):
    dtype = cov0.dtype
    d = cov0.shape[0]
    T = transition.num_rows + 1
    trans_xs, trans_static = _transition_rows(transition, mean0, d, dtype)
    meas_static, meas_xs, meas_layout = _measurement_layers(
        measurements, mean0, T, dtype
    )
    layer_counts = [int(x[3].shape[1]) for x in meas_xs]

    def body(carry, xs):
        mean, cov = carry
        (t_dyn, W), m_xs = xs
        pred_mean, pred_cov = mean, cov
        records = []
        for j, (static, (dyn, R, logdet_R, mask)) in enumerate(zip(meas_static, m_xs)):
            for k in range(layer_counts[j]):
                rows_k = jax.tree_util.tree_map(lambda a: a[k], dyn)
                factor = with_rows(measurements[j], eqx.combine(rows_k, static))
                mean, cov, rec = _update(
                    mean, cov, factor, R[k], logdet_R[k], mask[k], reset_covariance
                )
                records.append(rec)
        tfactor = with_rows(transition, eqx.combine(t_dyn, trans_static))
        next_mean, next_cov, F = _predict(mean, cov, tfactor, W, prediction_steps)
        return (next_mean, next_cov), (pred_mean, pred_cov, mean, cov, F, records)

    _, outs = lax.scan(body, (mean0, cov0), (trans_xs, tuple(meas_xs)))
    pred_mean, pred_cov, mean, cov, F, records = outs
    innovations, innovation_covs, step_ll = _innovations(
        records, meas_layout, layer_counts, T, dtype
    )
    log_likelihood = jnp.sum(step_ll)
    if throw:
        finite = jnp.all(jnp.isfinite(cov)) & jnp.isfinite(log_likelihood)
        cov = eqx.error_if(
            cov,
            ~finite,
            "ekf: a covariance or the log-likelihood is not finite (a singular "
            "transition Jacobian, a non-positive-definite innovation covariance, "
            "or non-finite measurements?)",
        )
    return EKFSolution(
        mean=mean,
        covariance=cov,
        predicted_mean=pred_mean,
        predicted_covariance=pred_cov,
        transition_jacobian=F[:-1],
        innovations=innovations,
        innovation_covariances=innovation_covs,
        step_log_likelihood=step_ll,
        log_likelihood=log_likelihood,
    )
