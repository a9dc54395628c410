"""Residual diagnostics shared by find, name and show: innovation tests
(and whether they raise an alarm), the localisation table, residual
summaries and open-loop errors."""

import numpy as np

from .._stats import (
    chi2_two_sided,
    ljung_box,
    normal_two_sided,
)
from ._fit import describe_error, EVALUATION_ERRORS
from ._model import (
    ChainModel,
    diagnostic_innovations,
    Sequences,
    trajectory_checks,
)


# ---------------------------------------------------------------------------
# Diagnostics shared by Find and Show
# ---------------------------------------------------------------------------


# Fixed-point steps of the Student-t diagnostic filter's noise scale (the
# mean NIS reaches m to about 1e-3 in 5 on the benchmark's data).
_CALIBRATION_STEPS = 5


def _whitened_innovations(model: ChainModel, data: Sequences, xhat) -> tuple:
    nu, S, _ = diagnostic_innovations(model, data, np.asarray(xhat))
    nu, S = np.asarray(nu), np.asarray(S)
    L = np.linalg.cholesky(S)
    e = np.linalg.solve(L, nu[..., None])[..., 0]
    return e, float(np.sum(e * e))


def innovation_tests(
    model: ChainModel, data: Sequences, xhat: np.ndarray, lags: int = 10
) -> dict:
    """NIS, bias and whiteness (Ljung-Box) tests of the filter innovations.

    The filter is the Kalman filter of the model linearised about the
    smoothed states `xhat` (see `diagnostic_innovations`).

    With Student-t measurement noise (`model.measurement_dof`) no Gaussian
    filter is exact, and the size of the innovations depends on the tails
    the model assumes as much as on missing structure. The NIS test then
    reports the moment-matched filter's innovation size but raises no alarm
    (`nis_alarm` False). The bias and whiteness tests use the Gaussian
    filter whose measurement standard deviation, `measurement_std` times
    `diagnostic_scale`, makes the mean NIS equal to `m` on the data: a filter
    with too much or too little measurement noise has autocorrelated
    innovations, which the whiteness test would read as structure (on null
    data, the moment-matched filter raised "unnamed structure" in 20% of
    Gaussian and 8% of Student-t(3) data sets).
    """
    e, total = _whitened_innovations(model, data, xhat)
    B, T, m = e.shape
    dof = B * T * m
    gaussian = model.measurement_dof is None
    out = {
        "nis_mean": total / (B * T),
        "nis_expected": float(m),
        "nis_p_value": chi2_two_sided(total, dof),
        "nis_alarm": gaussian,
        "bias": [],
        "whiteness": [],
    }
    if not gaussian:
        scale = 1.0
        for _ in range(_CALIBRATION_STEPS):
            scale *= float(np.sqrt(total / dof))
            e, total = _whitened_innovations(model.moment_matched(scale), data, xhat)
        out["diagnostic_scale"] = scale
        out["diagnostic_nis_mean"] = total / (B * T)
    for j in range(m):
        ej = e[..., j]
        mean = float(np.mean(ej))
        z = mean * np.sqrt(ej.size)
        out["bias"].append(
            {"channel": j, "mean_whitened": mean, "p_value": normal_two_sided(z)}
        )
        q, p = ljung_box(ej, lags)
        out["whiteness"].append(
            {"channel": j, "ljung_box_q": q, "lags": lags, "p_value": p}
        )
        # Excess kurtosis of the whitened innovations: 0 for Gaussian noise,
        # standard error √(24/N) (a check for heavy tails, not an alarm).
        c = ej - mean
        kurt = float(np.mean(c**4) / max(np.mean(c**2) ** 2, 1e-300) - 3.0)
        out.setdefault("kurtosis", []).append(
            {
                "channel": j,
                "excess_kurtosis": kurt,
                "p_value": normal_two_sided(kurt / np.sqrt(24.0 / ej.size)),
            }
        )
    out["whitened_innovations"] = e
    return out


def safe_innovation_tests(model, data, xhat, flags: list[str]) -> dict:
    """`innovation_tests`, or NaN p-values and a line in `flags` if the
    diagnostic filter fails or gives non-finite innovations."""
    try:
        out = innovation_tests(model, data, xhat)
        if np.all(np.isfinite(out["whitened_innovations"])):
            return out
        flags.append("diagnostic filter: non-finite innovations")
    except EVALUATION_ERRORS as e:
        flags.append(f"diagnostic filter: {describe_error(e)}")
    m = np.asarray(data.measurements).shape[-1]
    nan = float("nan")
    return {
        "nis_mean": nan,
        "nis_expected": float(m),
        "nis_p_value": nan,
        "nis_alarm": model.measurement_dof is None,
        "bias": [
            {"channel": j, "mean_whitened": nan, "p_value": nan} for j in range(m)
        ],
        "whiteness": [
            {"channel": j, "ljung_box_q": nan, "lags": 0, "p_value": nan}
            for j in range(m)
        ],
    }


def innovations_significant(innov: dict, alpha: float) -> bool:
    """Whether the innovation tests raise an alarm at level `alpha`: the
    smallest finite p-value of the NIS (when it may alarm), bias and
    whiteness tests below `alpha` over their number (Bonferroni)."""
    pvals = [innov["nis_p_value"]] if innov.get("nis_alarm", True) else []
    pvals += [w["p_value"] for w in innov["whiteness"]]
    pvals += [b["p_value"] for b in innov["bias"]]
    pvals = [p for p in pvals if np.isfinite(p)]
    return bool(pvals) and min(pvals) < alpha / len(pvals)


def _residuals(model: ChainModel, data: Sequences, xhat: np.ndarray):
    """Whitened smoother residuals: transitions `(B, T-1, n)`, measurements."""
    x, y = xhat, np.asarray(data.measurements)
    _, trans, obs = trajectory_checks(model, x, data.inputs)
    rt = (x[:, 1:] - np.asarray(trans)[:, :-1]) / np.asarray(model.process_sigma)
    rm = (y - np.asarray(obs)) / np.asarray(model.measurement_std)
    return rt, rm


def _bin_rows(label, values, resid, bins):
    rows = []
    edges = np.quantile(values, np.linspace(0, 1, bins + 1))
    for b in range(bins):
        lo, hi = edges[b], edges[b + 1]
        sel = (values >= lo) & (values <= hi if b == bins - 1 else values < hi)
        r = resid[sel]
        if r.size < 5:
            continue
        mean = float(np.mean(r))
        z = mean / (np.std(r) / np.sqrt(r.size) + 1e-300)
        rows.append(
            {
                "where": label,
                "bin": [float(lo), float(hi)],
                "count": int(r.size),
                "mean_whitened": mean,
                "z": float(z),
            }
        )
    return rows


def _binned(label: str, comp, states, inputs, bins: int) -> list:
    """Rows of one residual component `comp` (sequences × times) binned by
    each state coordinate, by time (quarters) and by each varying input."""
    rows = []
    for s in range(states.shape[-1]):
        rows += _bin_rows(
            f"{label} by state[{s}]", states[..., s].ravel(), comp.ravel(), bins
        )
    times = np.broadcast_to(np.arange(comp.shape[1]), comp.shape).ravel()
    rows += _bin_rows(f"{label} by time", times, comp.ravel(), 4)
    for k in range(inputs.shape[-1]):
        if np.ptp(inputs[..., k]) > 0:
            rows += _bin_rows(
                f"{label} by input[{k}]", inputs[..., k].ravel(), comp.ravel(), bins
            )
    return rows


def localisation_table(
    model: ChainModel,
    data: Sequences,
    xhat: np.ndarray,
    bins: int = 5,
    top: int = 8,
) -> list[dict]:
    """Where the whitened smoother residuals are biased.

    Rows by factor type and component, binned by each state coordinate and
    each (non-constant) input (quantile bins), by time (quarters of the
    sequence) and by sequence; sorted by `|z|`, the mean over its standard
    error.
    """
    rt, rm = _residuals(model, data, xhat)
    n, m = rt.shape[-1], rm.shape[-1]
    u = np.asarray(data.inputs)
    rows = []
    for i in range(n):
        comp = rt[..., i]
        if np.std(comp) == 0:
            continue
        rows += _binned(f"transition[{i}]", comp, xhat[:, :-1], u[:, :-1], bins)
    for j in range(m):
        comp = rm[..., j]
        rows += _binned(f"measurement[{j}]", comp, xhat, u, bins)
        seq_means = comp.mean(axis=1)
        worst = int(np.argmax(np.abs(seq_means)))
        r = comp[worst]
        rows.append(
            {
                "where": f"measurement[{j}] by sequence",
                "bin": [worst, worst],
                "count": int(r.size),
                "mean_whitened": float(seq_means[worst]),
                "z": float(seq_means[worst] / (np.std(r) / np.sqrt(r.size) + 1e-300)),
            }
        )
    rows.sort(key=lambda r: -abs(r["z"]))
    return rows[:top]


def residual_summary(model, data, xhat) -> list[dict]:
    rt, rm = _residuals(model, data, xhat)
    out = []
    for kind, r in (("transition", rt), ("measurement", rm)):
        for i in range(r.shape[-1]):
            c = r[..., i]
            out.append(
                {
                    "factor": kind,
                    "component": i,
                    "mean_whitened": float(np.mean(c)),
                    "rms_whitened": float(np.sqrt(np.mean(c * c))),
                }
            )
    return out


def open_loop(model: ChainModel, data: Sequences, xhat: np.ndarray) -> dict:
    """Noise-free simulation from the smoothed first states versus the data."""
    ys, _, _ = trajectory_checks(model, xhat, data.inputs)
    err = np.asarray(data.measurements) - np.asarray(ys)
    rms_t = np.sqrt(np.mean(err * err, axis=(0, 2)))
    T = rms_t.shape[0]
    marks = sorted({0, T // 4, T // 2, 3 * T // 4, T - 1})
    return {
        "rms_error": float(np.sqrt(np.mean(err * err))),
        "rms_error_by_time": {int(t): float(rms_t[t]) for t in marks},
        "measurement_std": np.asarray(model.measurement_std).tolist(),
    }
