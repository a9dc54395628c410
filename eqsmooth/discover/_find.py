"""Find: is something missing from the model, and how large would each
candidate need to be to be seen?"""

import jax
import numpy as np

from .._stats import (
    efficient_information,
    normal_quantile,
    normal_two_sided,
)
from ._adequacy import adequacy_test
from ._candidates import check_features
from ._diagnostics import (
    innovations_significant,
    localisation_table,
    open_loop,
    residual_summary,
    safe_innovation_tests,
)
from ._fit import (
    describe_error,
    evaluate,
    EVALUATION_ERRORS,
    feature_scales,
    fit,
    fitted_model,
    null_z,
)
from ._model import (
    ChainModel,
    NUM_SCALES,
    Sequences,
)
from ._report import FindState, StepReport
from ._score import score_test
from ._validate import check_informative, check_inputs, check_level, fingerprint


# ---------------------------------------------------------------------------
# The workflow
# ---------------------------------------------------------------------------


def _candidate_indices(model: ChainModel) -> np.ndarray:
    return np.arange(len(model.candidates))


def _nuisance(model: ChainModel, fit_noise: bool) -> np.ndarray:
    K = len(model.candidates)
    return K + np.arange(NUM_SCALES) if fit_noise else np.array([], dtype=int)


def find(
    model: ChainModel,
    data: Sequences,
    *,
    alpha: float = 0.05,
    fit_noise: bool = True,
    covariance: str = "auto",
    localise: bool = False,
) -> StepReport:
    """Find where the nominal model and the data disagree.

    Fits the noise scales of the nominal model (all candidate coefficients
    zero) by Laplace marginal likelihood, then reports: open-loop simulation
    error from the smoothed first states; whitened smoother residuals per
    factor type; NIS, bias and Ljung-Box whiteness tests of the innovations;
    the score test against the whole candidate library (the decision test);
    per-candidate score statistics and smallest detectable effects; and a
    localisation table.

    **Arguments:**

    - `model`: the nominal [`eqsmooth.discover.ChainModel`][] with its
        candidate library (coefficients are reset to zero).
    - `data`: the measured [`eqsmooth.discover.Sequences`][].
    - `alpha`: the level of the workflow's alarms together: on data with no
        missing effect, the probability that any alarm is raised (the
        decision test and the innovation diagnostics run at `alpha / 2`
        each; every later alarm needs one of them).
    - `fit_noise`: refit the process/measurement noise scales first (they
        are then nuisance parameters of the score test).
    - `covariance`: `"auto"`, `"opg"` or `"hessian"` (see `score_test`).
    - `localise`: when the decision test detects a missing effect, also say
        where in the states and inputs it acts: the adequacy test of
        [`eqsmooth.discover.name`][] run on the nominal model, with hats on
        every equation a candidate of the library acts on. The report's
        `where` then holds the block (variable and equation) with the
        smallest p-value, its `region` (intervals of the variable where
        single hats score beyond a Bonferroni bound over all hats), and
        every block. It is computed only after a detection, so it raises no
        alarm of its own. One more compiled program per model structure.

    **Returns:** a [`eqsmooth.discover.StepReport`][]: the report (a
    read-only mapping of JSON-serialisable values), with what later steps
    reuse as its `state`, a [`eqsmooth.discover.FindState`][].
    """
    check_inputs("find", model, data)
    check_level("find", alpha)
    check_informative("find", data)
    K = len(model.candidates)
    if K == 0:
        raise ValueError("find: the model has no candidate effects to test")
    # Sliced in NumPy: an eager JAX slice compiles a program on a first call.
    x0 = jax.device_put(np.asarray(data.x0_mean)[0])
    u0 = jax.device_put(np.asarray(data.inputs)[0, 0])
    check_features(model.candidates, x0, u0, data.measurements.shape[-1])
    model = model.with_coefficients(np.zeros(K))
    nuis = _nuisance(model, fit_noise)
    # What a failed find hands on (the settings and the nominal model).
    failed = FindState(
        fingerprint(data), model, alpha, fit_noise, covariance, failed=True
    )
    flags: list[str] = []
    z0 = null_z(model)
    try:
        ev0 = evaluate(model, data, z0, np.asarray(data.initial_states), np.ones(K))
    except EVALUATION_ERRORS as e:
        return _failed_find(failed, f"nominal evidence: {describe_error(e)}")
    scales = feature_scales(model, data, ev0.xhat)
    if fit_noise:
        ev = fit(model, data, nuis, z0, ev0.xhat, scales)
        if not ev.converged:
            flags.append("noise-scale fit did not converge")
    else:
        ev = ev0
    everything = np.concatenate([_candidate_indices(model), nuis])
    try:
        ev = evaluate(model, data, ev.z, ev.xhat, scales, everything)
    except EVALUATION_ERRORS as e:
        return _failed_find(failed, f"information matrix: {describe_error(e)}")
    if not (np.all(np.isfinite(ev.hessian)) and np.all(np.isfinite(ev.scores))):
        return _failed_find(failed, "information matrix or scores are not finite")
    nominal = fitted_model(model, ev.z)
    test = _candidate_indices(model)
    I_eff = efficient_information(-ev.hessian, test, nuis)
    g = np.sum(ev.scores, axis=0)[test]
    raw = np.diag(-ev.hessian)[test]
    # A candidate whose information is (almost) all explained by the nuisance
    # parameters (e.g. a sensor scale of a linear model against the noise
    # scales and the prior) cannot be identified: it is reported, not tested.
    ident = np.array(
        [abs(I_eff[k, k]) > 1e-3 * max(abs(raw[k]), 1e-300) for k in range(len(test))]
    )
    decision = score_test(ev, test[ident], nuis, covariance)
    # The decision test and the diagnostics share alpha (Bonferroni): on data
    # with no missing effect every alarm of the workflow needs one of the two,
    # so their union stays within alpha (each at alpha made it about 2 alpha:
    # 7% on 200 null sets of the driven oscillator).
    level = alpha / 2
    per_candidate = _candidate_table(model, I_eff, g, raw, ident, scales, level)
    innov = safe_innovation_tests(nominal, data, ev.xhat, flags)
    report = _report(
        model, data, nominal, ev, innov, flags, decision, per_candidate, ident, level
    )
    if localise and report["detected"]:
        everything_acting = list(range(K))
        report["where"] = adequacy_test(
            model, data, ev.z, ev.xhat, nuis, alpha, everything_acting
        )
    state = FindState(
        failed.fingerprint,
        model,
        alpha,
        fit_noise,
        covariance,
        evaluation=ev,
        scales=scales,
        nuisance=nuis,
        efficient_information=I_eff,
        identifiable=ident,
        diagnostics_significant=innovations_significant(innov, level),
    )
    return StepReport(report, state)


def _report(
    model, data, nominal, ev, innov, flags, decision, per_candidate, ident, alpha
) -> dict:
    """The JSON-serialisable report of a successful `find`."""
    K = len(model.candidates)
    return {
        "status": "ok",
        "flags": flags,
        "log_marginal": ev.log_marginal,
        "noise_scales": {
            "process": float(np.exp(ev.z[K])),
            "measurement": float(np.exp(ev.z[K + 1])),
            "prior": float(np.exp(ev.z[K + 2])),
        },
        "open_loop": open_loop(nominal, data, ev.xhat),
        "residuals": residual_summary(nominal, data, ev.xhat),
        "nis": {
            "mean": innov["nis_mean"],
            "expected": innov["nis_expected"],
            "p_value": innov["nis_p_value"],
            "alarm": innov.get("nis_alarm", True),
        },
        "bias": innov["bias"],
        "whiteness": innov["whiteness"],
        "noise_check": _noise_check(innov, ev.z[K : K + NUM_SCALES], alpha),
        "score_test": decision,
        "detected": bool(decision["p_value"] < alpha),
        "decision_level": alpha,
        "candidates": per_candidate,
        "not_identifiable": [
            c.name for c, ok in zip(model.candidates, ident) if not ok
        ],
        "localisation": localisation_table(nominal, data, ev.xhat),
    }


def _candidate_table(model, I_eff, g, raw, ident, scales, alpha) -> list[dict]:
    """Per candidate: its score `z` and p-value after the nuisance parameters,
    its smallest detectable coefficient (power 0.8 at level `alpha`), and the
    candidate whose information it is most correlated with."""
    K = len(model.candidates)
    z_power = normal_quantile(1 - alpha / 2) + normal_quantile(0.8)
    per_candidate = []
    # Correlation of the candidates' information (after the noise scales):
    # near ±1, the data cannot tell the two effects apart.
    dd = np.sqrt(np.maximum(np.abs(np.diag(I_eff)), 1e-300))
    corr = I_eff / np.outer(dd, dd)
    np.fill_diagonal(corr, 0.0)
    for k, c in enumerate(model.candidates):
        info = I_eff[k, k] if I_eff[k, k] > 0 else raw[k]
        identifiable = bool(ident[k]) and info > 0
        zk = g[k] / np.sqrt(info) if identifiable else float("nan")
        j = int(np.argmax(np.abs(corr[k]))) if K > 1 else k
        per_candidate.append(
            {
                "name": c.name,
                "target": c.target,
                "identifiable": identifiable,
                "most_correlated_with": model.candidates[j].name if K > 1 else None,
                "information_correlation": float(corr[k, j]) if K > 1 else 0.0,
                "score_z": float(zk),
                "score_p_value": normal_two_sided(zk) if identifiable else 1.0,
                "smallest_detectable": float(z_power / np.sqrt(info))
                if identifiable
                else float("inf"),
                "feature_scale": float(scales[k]),
            }
        )
    return per_candidate


def _noise_check(innov: dict, log_scales: np.ndarray, alpha: float) -> dict:
    """Is the measurement noise heavy-tailed, or far from its assumed size?

    Heavy tails: the excess kurtosis of any channel's whitened innovations
    is significant (Bonferroni over channels). Size: the refitted noise
    multipliers (1 = as assumed); a factor beyond 2 either way is reported.
    Both are reported with the verdict, not used to name effects.
    """
    kurt = innov.get("kurtosis", [])
    pvals = [k["p_value"] for k in kurt if np.isfinite(k["p_value"])]
    heavy = bool(pvals) and min(pvals) < alpha / len(pvals)
    scales = np.exp(np.asarray(log_scales, float))
    return {
        "heavy_tails": heavy,
        "excess_kurtosis": [k["excess_kurtosis"] for k in kurt],
        "process_scale": float(scales[0]),
        "measurement_scale": float(scales[1]),
        "scale_off_by_2": bool(np.any((scales[:2] > 2.0) | (scales[:2] < 0.5))),
    }


def _failed_find(state: FindState, why: str) -> StepReport:
    """The report of a find whose evidence could not be evaluated (no raise)."""
    report = {
        "status": "failed",
        "flags": [why],
        "detected": False,
        "score_test": {
            "statistic": float("nan"),
            "df": 0,
            "p_value": float("nan"),
            "covariance": state.covariance,
        },
        "candidates": [],
        "not_identifiable": [],
    }
    return StepReport(report, state)
