"""Fitting by Laplace marginal likelihood, score tests, derivatives."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._model import (
    batch_log_marginal,
    batch_scores,
    ChainModel,
    map_states,
    NUM_SCALES,
    Sequences,
    z_of,
)


class Evaluation(eqx.Module):
    """Laplace evidence of a model at `z`, with its MAP states and derivatives."""

    z: np.ndarray
    log_marginal: float
    per_sequence: np.ndarray
    scores: np.ndarray  # (B, P)
    hessian: np.ndarray  # (P, P), total
    xhat: np.ndarray
    # False when the fit that produced it stopped early: a non-finite
    # gradient or curvature, an evidence that could not be evaluated, or the
    # iteration limit. Its numbers are then the best point reached, not an
    # optimum.
    converged: bool = True
    # The indices of `z` whose block of `hessian` was computed (None: none).
    hessian_of: np.ndarray | None = None


def feature_scales(model: ChainModel, data: Sequences, xhat: np.ndarray) -> np.ndarray:
    """RMS size of every candidate feature over the given states (for steps).

    A feature that is not finite at some of these states (e.g. `√x` where
    `x < 0`) raises a `ValueError` naming the candidate and the first such
    state: its score would be NaN, and the test of every candidate with it.
    """
    # NumPy reshapes: eager ones on JAX arrays compile a program each.
    x = np.asarray(xhat).reshape(-1, xhat.shape[-1])
    u = np.asarray(data.inputs).reshape(-1, data.inputs.shape[-1])
    out = []
    for c, f in zip(model.candidates, feature_values(model, x, u)):
        bad = ~np.isfinite(f.reshape(f.shape[0], -1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            b, t = np.unravel_index(i, xhat.shape[:-1])
            raise ValueError(
                f"Candidate {c.name!r}: its feature is not finite at {int(bad.sum())} "
                f"of {bad.size} estimated states (first: sequence {b}, step {t}, "
                f"state {np.asarray(x[i]).tolist()}, input {np.asarray(u[i]).tolist()}"
                "); give it a value everywhere (e.g. √|x| instead of √x) or drop it "
                "from the library"
            )
        out.append(float(np.sqrt(np.mean(np.sum(f * f, axis=-1)))))
    scales = np.asarray(out)
    return np.where(scales > 0, scales, 1.0)


def feature_values(model: ChainModel, x, u) -> list[np.ndarray]:
    """Every candidate's feature at the states `x` `(N, n)` and inputs `u`
    `(N, k)`: one compiled program for the whole library (a program per
    feature cost about 0.15 s of compilation each on a first call)."""
    features = tuple(c.feature for c in model.candidates)
    return [np.asarray(f) for f in _eval_features(features, x, u)]


@eqx.filter_jit
def _eval_features(features, x, u):
    import jax

    return [jax.vmap(feature)(x, u) for feature in features]


def _step_sizes(model: ChainModel, scales: np.ndarray) -> np.ndarray:
    # A perturbation of 1e-4 state units per step for coefficients and 1e-4
    # in the log noise scales: far above rounding, far below curvature scale.
    return np.concatenate([1e-4 / scales, [1e-4] * NUM_SCALES])


def evaluate(
    model: ChainModel,
    data: Sequences,
    z: np.ndarray,
    init: np.ndarray,
    scales: np.ndarray,
    hessian_of: np.ndarray | None = None,
    *,
    at_map: bool = False,
) -> Evaluation:
    """MAP, Laplace evidence, per-sequence scores and (optionally) the Hessian.

    Scores are exact (reverse-mode autodiff through the Laplace approximation
    at the MAP). The Hessian block over the indices `hessian_of` is a central
    difference of those exact gradients at the fixed MAP (the Laplace
    objective's one-step correction makes this the Hessian of the profiled
    evidence); it is used for Newton steps, information matrices and
    confidence intervals, never for scores.

    `at_map=True` takes `init` as the MAP at `z` (no solve: e.g. a model
    extended by terms whose coefficients are zero at `z`).
    """
    zj = jnp.asarray(z)
    xh = jnp.asarray(init) if at_map else map_states(model, zj, data, jnp.asarray(init))
    vals, scores, _ = batch_scores(model, zj, data, xh)
    P = z.shape[0]
    H = np.zeros((P, P))
    if hessian_of is not None and len(hessian_of):
        h = _step_sizes(model, scales)
        cols = {}
        for i in hessian_of:
            e = np.zeros(P)
            e[i] = h[i]
            _, gp, _ = batch_scores(model, jnp.asarray(z + e), data, xh)
            _, gm, _ = batch_scores(model, jnp.asarray(z - e), data, xh)
            cols[i] = (np.sum(np.asarray(gp), 0) - np.sum(np.asarray(gm), 0)) / (
                2 * h[i]
            )
        idx = np.asarray(hessian_of)
        for i in hessian_of:
            H[idx, i] = cols[i][idx]
        sub = H[np.ix_(idx, idx)]
        H[np.ix_(idx, idx)] = 0.5 * (sub + sub.T)
    vals = np.asarray(vals)
    return Evaluation(
        z=np.asarray(z, dtype=float),
        log_marginal=float(np.sum(vals)),
        per_sequence=vals,
        scores=np.asarray(scores),
        hessian=H,
        xhat=np.asarray(xh).copy(),
        hessian_of=(
            None
            if hessian_of is None or not len(hessian_of)
            else np.asarray(hessian_of, int)
        ),
    )


def covers(ev: Evaluation, indices) -> bool:
    """Whether `ev`'s Hessian block holds every index of `indices`."""
    return ev.hessian_of is not None and set(np.asarray(indices, int).tolist()) <= set(
        ev.hessian_of.tolist()
    )


def restricted(ev: Evaluation, free) -> Evaluation:
    """`ev` with its Hessian kept on the block `free` only (zero elsewhere),
    as `evaluate(..., hessian_of=free)` gives it."""
    free = np.asarray(free, int)
    if not covers(ev, free):
        raise ValueError("restricted: the evaluation's Hessian does not cover `free`")
    H = np.zeros_like(ev.hessian)
    H[np.ix_(free, free)] = ev.hessian[np.ix_(free, free)]
    return eqx.tree_at(
        lambda e: (e.hessian, e.hessian_of), ev, (H, free), is_leaf=lambda x: x is None
    )


def with_hessian(model, data, ev: Evaluation, scales, free) -> Evaluation:
    """`ev` (at its MAP) with the Hessian block over `free` computed, unless
    it already has it; keeps `converged`."""
    if covers(ev, free):
        return restricted(ev, free)
    new = evaluate(model, data, ev.z, ev.xhat, scales, free, at_map=True)
    return eqx.tree_at(lambda e: e.converged, new, ev.converged)


def _trial(model, data, z, init, scales) -> Evaluation:
    # A trial point of the Newton iterations: its MAP (solved from `init`),
    # evidence and scores, from the one score program (an evidence-only
    # program would be a second compilation per model structure, and an
    # accepted trial needs the scores anyway).
    return evaluate(model, data, z, init, scales)


def log_marginal_at(model, data, z, init) -> tuple[float, np.ndarray]:
    zj = jnp.asarray(z)
    xh = map_states(model, zj, data, jnp.asarray(init))
    return float(jnp.sum(batch_log_marginal(model, zj, data, xh))), np.asarray(xh)


# Largest change of a log noise scale in one Newton step (a factor of e), and
# the initial / largest trust radius in curvature-scaled coordinates. Noise
# scales that the data cannot identify have almost no curvature, so an
# unbounded Newton step sends them to exp(±hundreds), where the MAP solve
# breaks down.
_MAX_LOG_SCALE_STEP = 1.0
_TRUST_RADIUS = (1.0, 10.0)
# Errors that mean "this point cannot be evaluated" (a failed linear solve,
# non-finite numbers), not a bug: caught and turned into result flags.
EVALUATION_ERRORS = (
    eqx.EquinoxRuntimeError,
    np.linalg.LinAlgError,
    FloatingPointError,
)


def describe_error(e: BaseException) -> str:
    """One line for a report's flags: the error's type and first line."""
    text = str(e).strip().splitlines()
    return f"{type(e).__name__}: {text[0] if text else ''}"


def _bounded_step(step, d, free, num_coefficients, radius):
    """Shrink a Newton step into the trust region and the log-scale bound."""
    size = float(np.linalg.norm(step * d))
    if size > radius:
        step = step * (radius / size)
    is_scale = free >= num_coefficients
    return np.where(
        is_scale,
        np.clip(step, -_MAX_LOG_SCALE_STEP, _MAX_LOG_SCALE_STEP),
        step,
    )


def _scale_prior(model: ChainModel, free: np.ndarray):
    """Log density (up to a constant), gradient and negative Hessian over
    `free` of the optional normal prior on the log noise multipliers."""
    sd = model.noise_scale_prior
    is_scale = (free >= len(model.candidates)).astype(float)
    if sd is None:
        is_scale = 0.0 * is_scale
        sd = 1.0

    def log_prior(z):
        return -0.5 * float(np.sum(is_scale * (z[free] / sd) ** 2))

    def grad(z):
        return -is_scale * z[free] / sd**2

    return log_prior, grad, np.diag(is_scale / sd**2)


def fit(
    model: ChainModel,
    data: Sequences,
    free: np.ndarray,
    z0: np.ndarray,
    init: np.ndarray,
    scales: np.ndarray,
    *,
    max_iter: int = 25,
    tol: float = 1e-7,
    start: Evaluation | None = None,
    final_hessian: bool = True,
) -> Evaluation:
    """Maximise the Laplace evidence over the parameters `free` (indices of z).

    Damped Newton (Levenberg) steps on the exact gradient and the
    difference-of-gradients Hessian, inside a trust region (in coordinates
    scaled by the curvature) and with every log noise scale moving by at most
    1 per step; each trial point gets a fresh MAP (warm-started). A trial
    whose evidence cannot be evaluated (a failed solve, non-finite numbers)
    is rejected like a worse one. Never raises on finite data: if the fit
    cannot go on, it returns the best point reached with `converged=False`.
    With `model.noise_scale_prior` set, the objective adds that prior on the
    log noise multipliers (the returned `log_marginal` is still the data's
    evidence). Returns the evaluation at the optimum, with the Hessian over
    `free` (for confidence intervals).

    `start`: an evaluation at `z0` (its MAP solved) whose Hessian covers
    `free`, used instead of a new one: fits of several candidates from one
    point share its Hessian columns. `final_hessian=False` skips the
    Hessian at the optimum (the returned evaluation then may lack it; see
    `with_hessian`), for fits of which only the evidence is kept.
    """
    free = np.asarray(free, dtype=int)
    log_prior, prior_grad, prior_negH = _scale_prior(model, free)
    objective = (log_prior, prior_grad, prior_negH)
    if start is None:
        ev = evaluate(
            model, data, np.asarray(z0, dtype=float).copy(), init, scales, free
        )
    else:
        ev = restricted(start, free)
    ev, converged, fresh = _newton(
        model, data, free, ev, scales, objective, max_iter, tol
    )
    if not (converged or fresh):
        # Stopped short (the iteration limit, or no better point along a
        # step of the updated curvature): restart once from the best point
        # with a new difference-of-gradients Hessian and a reset trust region.
        # On a pendulum with a constant torque, a fit that crept along the
        # ridge between the torque and the process-noise scale for 25 steps
        # gained 7 more nats this way.
        try:
            restart = evaluate(model, data, ev.z, ev.xhat, scales, free, at_map=True)
        except EVALUATION_ERRORS:
            restart = None
        if restart is not None:
            ev, converged, fresh = _newton(
                model, data, free, restart, scales, objective, max_iter, tol
            )
    if not fresh and final_hessian:
        try:
            ev = evaluate(model, data, ev.z, ev.xhat, scales, free, at_map=True)
        except EVALUATION_ERRORS:
            converged = False
    return eqx.tree_at(lambda e: e.converged, ev, converged)


def _newton(model, data, free, ev, scales, objective_terms, max_iter, tol):
    """Damped Newton iterations of `fit` from `ev` (whose Hessian over `free`
    is fresh). Returns `(evaluation, converged, fresh)`; `fresh` is False when
    the evaluation returned holds no Hessian of its own."""
    log_prior, prior_grad, prior_negH = objective_terms
    num_coefficients = len(model.candidates)
    z = ev.z.copy()
    # The difference-of-gradients Hessian costs two score evaluations per
    # free parameter; it is computed where the iterations start and where
    # the fit ends (for intervals), and updated by BFGS in between.
    negH = -ev.hessian[np.ix_(free, free)] + prior_negH
    fresh = True
    lam, radius = 1e-3, _TRUST_RADIUS[0]
    converged = False
    for _ in range(max_iter):
        g = np.sum(ev.scores, axis=0)[free] + prior_grad(z)
        objective = ev.log_marginal + log_prior(z)
        if not (np.all(np.isfinite(g)) and np.all(np.isfinite(negH))):
            break
        # Newton in coordinates scaled by the curvature diagonal.
        d = np.sqrt(np.maximum(np.abs(np.diag(negH)), 1e-12))
        A = negH / np.outer(d, d)
        try:
            w, V = np.linalg.eigh(A)
        except np.linalg.LinAlgError:
            break
        accepted = False
        for _ in range(8):
            wl = np.maximum(w, 1e-6) + lam
            step = (V @ ((V.T @ (g / d)) / wl)) / d
            step = _bounded_step(step, d, free, num_coefficients, radius)
            z_new = z.copy()
            z_new[free] += step
            try:
                trial = _trial(model, data, z_new, ev.xhat, scales)
                ll_new = trial.log_marginal + log_prior(z_new)
            except EVALUATION_ERRORS:
                ll_new = -np.inf
            if np.isfinite(ll_new) and ll_new >= objective - 1e-9:
                accepted = True
                break
            lam = max(lam * 10.0, 1e-3)
            radius = radius / 4.0
        if not accepted:
            # No better point nearby: a (local) optimum when the gradient is
            # small, otherwise a stop.
            converged = bool(np.max(np.abs(g / d)) < 1e-6)
            break
        lam = max(lam / 10.0, 1e-9)
        radius = min(2.0 * radius, _TRUST_RADIUS[1])
        gain = ll_new - objective
        new_ev = trial
        g_new = np.sum(new_ev.scores, axis=0)[free] + prior_grad(z_new)
        negH = _bfgs(negH, step, g - g_new)
        z, ev, fresh = z_new, new_ev, False
        if (
            gain < tol * max(1.0, abs(ev.log_marginal + log_prior(z)))
            and np.max(np.abs(step * d)) < 1e-3
        ):
            converged = True
            break
    return ev, converged, fresh


def _bfgs(B: np.ndarray, s: np.ndarray, y: np.ndarray) -> np.ndarray:
    """BFGS update of the curvature `B` (of the negative objective) after the
    step `s` changed the negative gradient by `y`; kept as is when the pair
    has no positive curvature (`sᵀy ≤ 0`)."""
    sy = float(s @ y)
    Bs = B @ s
    sBs = float(s @ Bs)
    if not (np.isfinite(sy) and sy > 1e-12 * max(1.0, sBs)) or sBs <= 0:
        return B
    return B + np.outer(y, y) / sy - np.outer(Bs, Bs) / sBs


def null_z(model: ChainModel) -> np.ndarray:
    z = z_of(model)
    z[: len(model.candidates)] = 0.0
    return z


def fitted_model(model: ChainModel, z: np.ndarray) -> ChainModel:
    """The model with coefficients and noise scales of `z` applied.

    `apply_z` in NumPy: applied eagerly to JAX arrays, its operations
    compiled a program each on a first call."""
    z, K = np.asarray(z, dtype=float), len(model.candidates)
    sigmas = (model.process_sigma, model.measurement_sigma, model.prior_sigma)
    scaled = [np.asarray(s) * np.exp(z[K + i]) for i, s in enumerate(sigmas)]
    return eqx.tree_at(
        lambda m: (m.coefficients, m.process_sigma, m.measurement_sigma, m.prior_sigma),
        model,
        tuple(jax.device_put(a) for a in [z[:K], *scaled]),
    )
