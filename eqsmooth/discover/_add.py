"""Add: fit the named candidates' coefficients, with standard errors and intervals."""

from collections.abc import Sequence

import numpy as np

from .._stats import (
    normal_quantile,
)
from ._fit import (
    fit,
    fitted_model,
    null_z,
)
from ._model import (
    Sequences,
)
from ._report import FindState, NameState, StepReport
from ._validate import fingerprint


def add(
    found: StepReport,
    named: StepReport | None,
    data: Sequences,
    *,
    level: float = 0.95,
    also: Sequence[str] = (),
) -> dict:
    """Fit the named candidates' coefficients (and noise scales) and give
    confidence intervals.

    The coefficients maximise the Laplace marginal likelihood (not a plug-in
    regression on smoothed states, which is biased); the intervals come from
    the curvature of the log marginal likelihood (observed information,
    noise scales profiled out).

    **Arguments:**

    - `found`, `named`: the reports of [`eqsmooth.discover.find`][] and
        [`eqsmooth.discover.name`][] on `data`. `named=None` fits the
        candidates of `also` alone (e.g. a model's physical parameters
        before any effect is added).
    - `data`: the sequences `find` analysed.
    - `level`: the confidence level of the intervals.
    - `also`: names of further candidates of the library to fit with the
        named ones, e.g. the corrections of physical parameters
        (`"spring error"`, `"viscous damping"`, `"actuator gain"` in
        [`eqsmooth.discover.mechanical_library`][]), whose estimates and
        intervals then say how the physics moves when an effect is added.

    **Returns:** a dict with `model` (the fitted
    [`eqsmooth.discover.ChainModel`][]), `coefficients` (name, value,
    standard error, interval, sign check; the named candidates first, then
    those of `also` not named), `noise_scales` and `flags` (a fit that did
    not converge, an information matrix that is not positive definite, a
    coefficient without a standard error).
    """
    st = found.state if isinstance(found, StepReport) else None
    named_state = NameState(None, ()) if named is None else named.state
    if not (isinstance(st, FindState) and isinstance(named_state, NameState)):
        raise TypeError(
            "add: found and named must be the reports of eqsmooth.discover.find "
            "and eqsmooth.discover.name (or None), in that order"
        )
    if isinstance(also, str) or not all(isinstance(a, str) for a in also):
        raise TypeError(
            f"add: also must be a sequence of candidate names, got {also!r}"
        )
    if st.fingerprint != fingerprint(data):
        raise ValueError(
            "add: data are not the sequences find analysed (their contents differ); "
            "fit the named effects on the data find and name were given"
        )
    if st.failed:
        model = st.model
        return {
            "model": fitted_model(model, null_z(model)),
            "log_marginal": float("nan"),
            "coefficients": [],
            "noise_scales": {},
            "flags": ["no fit: find failed"],
        }
    model, scales, nuis = st.model, st.scales, st.nuisance
    active = list(named_state.active)
    unknown = [a for a in also if a not in model.names]
    if unknown:
        raise ValueError(
            f"add: also names {unknown[0]!r}, which is not a candidate of the "
            f"model's library (candidates: {list(model.names)})"
        )
    active += [k for k in dict.fromkeys(map(model.index, also)) if k not in active]
    start = st.evaluation if named_state.evaluation is None else named_state.evaluation
    free = np.concatenate([np.asarray(active, int), nuis])
    ev = fit(model, data, free, start.z, start.xhat, scales) if len(free) else start
    flags = [] if ev.converged else ["fit did not converge"]
    K = len(model.candidates)
    coefs = []
    if active:
        info = -ev.hessian[np.ix_(free, free)]
        try:
            cov = np.linalg.pinv(info)
        except np.linalg.LinAlgError:
            cov = np.full(info.shape, np.nan)
            flags.append("information matrix could not be inverted")
        sym = 0.5 * (info + info.T)
        if np.all(np.isfinite(sym)):
            smallest = float(np.linalg.eigvalsh(sym).min())
            if smallest <= 0:
                flags.append(
                    "information matrix is not positive definite (smallest "
                    f"eigenvalue {smallest:.3g}): the fit is not a strict maximum "
                    "of the evidence, so standard errors are unreliable"
                )
        zq = normal_quantile(0.5 + level / 2)
        for i, k in enumerate(active):
            c = model.candidates[k]
            value = float(ev.z[k])
            se = float(np.sqrt(cov[i, i])) if cov[i, i] >= 0 else float("nan")
            if not np.isfinite(se):
                flags.append(
                    f"no standard error for {c.name!r}: its variance from the "
                    f"(pseudo-)inverse information is {float(cov[i, i]):.3g}"
                )
            coefs.append(
                {
                    "name": c.name,
                    "value": value,
                    "std_error": se,
                    "interval": [value - zq * se, value + zq * se],
                    "level": level,
                    "sign_ok": bool(c.sign == 0 or np.sign(value) in (0, c.sign)),
                }
            )
    return {
        "model": fitted_model(model, ev.z),
        "log_marginal": ev.log_marginal,
        "coefficients": coefs,
        "noise_scales": {
            "process": float(np.exp(ev.z[K])),
            "measurement": float(np.exp(ev.z[K + 1])),
            "prior": float(np.exp(ev.z[K + 2])),
        },
        "flags": flags,
    }
