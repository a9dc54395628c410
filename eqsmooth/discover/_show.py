"""Show: the held-out gap before and after, and the whole workflow in one call."""

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from ._add import add
from ._diagnostics import safe_innovation_tests
from ._find import find
from ._fit import (
    describe_error,
    evaluate,
    EVALUATION_ERRORS,
    fitted_model,
)
from ._model import (
    ChainModel,
    k_step_errors,
    NUM_SCALES,
    Sequences,
)
from ._name import bootstrap, name
from ._report import StepReport


def _model_metrics(
    model: ChainModel, data: Sequences, horizon: int, burn_in: int
) -> dict:
    K = len(model.candidates)
    z = np.concatenate([np.asarray(model.coefficients), np.zeros(NUM_SCALES)])
    B, T = data.num_sequences, data.length
    flags: list[str] = []
    try:
        ev = evaluate(
            model, data, z, np.asarray(data.initial_states), np.ones(max(K, 1))
        )
        errs = np.asarray(k_step_errors(model, data, ev.xhat, horizon, burn_in))
    except EVALUATION_ERRORS as e:
        nan = float("nan")
        return {
            "log_marginal_per_step": nan,
            "nis_mean": nan,
            "nis_p_value": nan,
            "whiteness_p_values": [],
            "k_step_rmse": [nan] * horizon,
            "flags": [f"held-out evaluation: {describe_error(e)}"],
        }
    innov = safe_innovation_tests(model, data, ev.xhat, flags)
    return {
        "flags": flags,
        "log_marginal_per_step": ev.log_marginal / (B * T),
        "nis_mean": innov["nis_mean"],
        "nis_p_value": innov["nis_p_value"],
        "whiteness_p_values": [w["p_value"] for w in innov["whiteness"]],
        "k_step_rmse": np.sqrt(errs.mean(axis=1)).tolist(),
    }


def show(
    before: ChainModel,
    after: ChainModel,
    heldout: Sequences,
    *,
    horizon: int = 10,
    burn_in: int = 0,
) -> dict:
    """Held-out before/after comparison of two fitted models.

    Log marginal likelihood per time step (Laplace), NIS with its two-sided
    p-value, Ljung-Box p-values and the k-step open-loop prediction RMSE for
    `k = 1..horizon` (predictions start from the filtered state at `t` and
    run the model's mean dynamics, so they are genuine forecasts). Start
    times `t < burn_in` are left out of the k-step errors: their filtered
    states rest on few measurements and a diffuse prior.
    """
    if burn_in < 0 or heldout.length <= horizon + burn_in + 1:
        raise ValueError(
            f"show: held-out sequences of length {heldout.length} are too short for "
            f"horizon {horizon} after a burn-in of {burn_in} (or burn_in < 0)"
        )
    b = _model_metrics(before, heldout, horizon, burn_in)
    a = _model_metrics(after, heldout, horizon, burn_in)
    return {
        "before": b,
        "after": a,
        "log_marginal_gain_per_step": a["log_marginal_per_step"]
        - b["log_marginal_per_step"],
        "k_step_rmse_ratio": (
            np.asarray(a["k_step_rmse"]) / np.asarray(b["k_step_rmse"])
        ).tolist(),
    }


def discover(
    model: ChainModel,
    data: Sequences,
    heldout: Sequences | None = None,
    *,
    alpha: float = 0.05,
    fit_noise: bool = True,
    covariance: str = "auto",
    max_terms: int = 3,
    shape_tolerance: float = 0.2,
    shape_power: float = 0.9,
    horizon: int = 10,
    burn_in: int = 0,
    bootstrap_resamples: int = 0,
    physics: Sequence[str] = (),
) -> dict:
    """Run find, name, add and (with held-out data) show; return one report.

    **Arguments:**

    - `model`: the nominal [`eqsmooth.discover.ChainModel`][] with its library.
    - `data`: identification sequences.
    - `heldout`: validation sequences for the before/after comparison, or
        `None`.
    - `alpha`, `fit_noise`, `covariance`: see [`eqsmooth.discover.find`][].
    - `max_terms`, `shape_tolerance`, `shape_power`: see
        [`eqsmooth.discover.name`][].
    - `horizon`, `burn_in`: see [`eqsmooth.discover.show`][].
    - `bootstrap_resamples`: if positive, also run
        [`eqsmooth.discover.bootstrap`][] with this many resamples (each
        costs one find + name).
    - `physics`: names of library candidates that correct the model's
        physical parameters (e.g. `"spring error"`, `"viscous damping"`,
        `"actuator gain"` of [`eqsmooth.discover.mechanical_library`][]).
        They are fitted before any effect is added and again with the named
        effects (`add(..., also=physics)`, whose fit is then the final
        model), and the report's `physics` entry says, per parameter,
        whether it moved: whether the refit value lies outside the 95%
        interval of the fit without the named effects.

    **Returns:** a JSON-serialisable dict with `verdict`, `find`, `name`,
    `add`, `show` (with held-out data), `bootstrap` (when asked) and
    `physics` (when asked), plus
    the fitted model under the key `"model"` (remove it before serialising,
    or use [`eqsmooth.discover.to_json`][]).
    """
    found = find(model, data, alpha=alpha, fit_noise=fit_noise, covariance=covariance)
    named = name(
        found,
        data,
        max_terms=max_terms,
        shape_tolerance=shape_tolerance,
        shape_power=shape_power,
    )
    added = add(found, named, data, also=physics)
    report = {
        "verdict": named["verdict"],
        "find": found,
        "name": named,
        "add": {k: v for k, v in added.items() if k != "model"},
        "model": added["model"],
    }
    if bootstrap_resamples > 0:
        report["bootstrap"] = bootstrap(
            found,
            data,
            named=named,
            num_resamples=bootstrap_resamples,
            max_terms=max_terms,
        )
    if physics:
        report["physics"] = physics_moved(
            add(found, None, data, also=physics), added, physics
        )
    if heldout is not None and not found.state.failed:
        before = fitted_model(found.state.model, found.state.evaluation.z)
        report["show"] = show(
            before, added["model"], heldout, horizon=horizon, burn_in=burn_in
        )
    return report


def physics_moved(before: dict, after: dict, names: Sequence[str]) -> dict:
    """Per physical-parameter correction: its fit without and with the named
    effects (two [`eqsmooth.discover.add`][] results) and whether it moved
    (the value with them outside the 95% interval without them)."""
    out = {}
    for nm in names:
        b = next((c for c in before["coefficients"] if c["name"] == nm), None)
        a = next((c for c in after["coefficients"] if c["name"] == nm), None)
        if a is None or b is None:
            out[nm] = {"moved": None, "statement": f"{nm}: no fit"}
            continue
        lo, hi = b["interval"]
        finite = bool(np.isfinite(lo) and np.isfinite(hi))
        moved = bool(not lo <= a["value"] <= hi) if finite else None
        verdict = {True: "moved", False: "held", None: "unknown (no interval)"}
        out[nm] = {
            "before": {k: b[k] for k in ("value", "std_error", "interval")},
            "after": {k: a[k] for k in ("value", "std_error", "interval")},
            "moved": moved,
            "statement": (
                f"{nm}: {b['value']:.4g} [{lo:.4g}, {hi:.4g}] without the named "
                f"effects, {a['value']:.4g} with them: {verdict[moved]}"
            ),
        }
    return out


def to_json(report: Mapping[str, Any]) -> dict:
    """A copy of a report (a [`eqsmooth.discover.StepReport`][] or a dict that
    holds them) without internal state, models or arrays."""

    def clean(x):
        if isinstance(x, StepReport):
            return clean(x.report)
        if isinstance(x, dict):
            return {
                str(k): clean(v)
                for k, v in x.items()
                if not str(k).startswith("_")
                and k not in ("model", "whitened_innovations")
            }
        if isinstance(x, list | tuple):
            return [clean(v) for v in x]
        if isinstance(x, np.ndarray):
            return x.tolist()
        if isinstance(x, np.floating | np.integer | np.bool_):
            return x.item()
        return x

    return clean(report)
