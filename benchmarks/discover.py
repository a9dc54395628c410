"""Monte Carlo of the discrepancy workflow (find, name, add) on hidden effects.

Data: a 1-D oscillator, state (p, v), p' = p + v, v' = v − k p + effect +
noise (k = 0.05, process noise std (0.05, 0.5), position measured with std
1, first state drawn from the model's prior N(0, diag(20², 4²))), B = 24
sequences × T = 40 steps per data set (one shape for everything, so the
jitted code compiles once). The nominal model knows the spring and the noise
levels (the workflow refits three noise scales) but not the effect. The
candidate library is the full `mechanical_library` of one axis with sensor
terms: constant force, viscous damping, quadratic drag, Coulomb friction
(tanh(v/1)), cubic damping, spring error, cubic stiffness, sensor bias,
sensor scale, sensor delay. Every candidate is a distractor for every other:
drag vs damping vs v³ vs Coulomb, constant force vs sensor bias.

Hidden effects: viscous damping, quadratic drag, Coulomb friction, constant
force and sensor bias, each at several strengths given as a per-step
signal-to-noise ratio: the RMS of the effect's per-step contribution over
nominal trajectories divided by the noise std of the component it enters
(the process velocity noise 0.5). A sensor bias b is scaled as the constant
force it mimics: with the spring, the states can absorb the bias except for
the force k·b the spring would need, so its ratio is k·b / 0.5 (per
measurement, b / 1 is 10 times larger; at b / 1 = 0.4 the bias is not
detectable with this prior). The coefficient of each level is calibrated once from
simulated nominal trajectories; the realised ratio under the effect (lower
for dissipative effects, which slow the system down) is reported too.

With `--measurement-dof NU` the nominal model's measurement noise is
Student-t(NU) instead of Gaussian (the robust evidence), so that the rows
show what the robust model does to detection and naming.

Null data: the same simulation with no effect; the false-discovery rate is
the fraction of null data sets in which anything is named, and every alarm
the workflow can raise ("detected", "unnamed structure", "ambiguous",
"leftover structure") gets its own false-alarm rate. Null data also come
with measurement noise twice the assumed std and with Student-t(3) noise
(`--noises`). The leftover-structure alarm is also counted where the truth
was named alone (nothing is left there). Exceptions out of find / name /
add are counted as crashes (the target is 0); runs that end with a result
flag (a fit that did not converge) are counted as flagged.

Per data set the outcome is one of: the truth named alone; the truth inside
a reported ambiguous or equivalence set ("correct, as a set" — e.g.
{constant force ≡ sensor bias}, which the data cannot tell apart when the
spring shifts the equilibrium); the truth named unambiguously plus an extra
term; a wrong name only; nothing named. Rates carry Wilson 95% intervals.

    python benchmarks/discover.py --quick
    python benchmarks/discover.py --seeds 50 --null 200 \
        --json benchmarks/results/discover.json \
        --markdown benchmarks/results/discover.md
    python benchmarks/discover.py --seeds 10 --levels 0.4 --null 200 \
        --null-other 60 --json benchmarks/results/discover_alarms.json \
        --markdown benchmarks/results/discover_alarms.md  # alarms, noise
    python benchmarks/discover.py --seeds 10 --levels 0.4 --null 60 \
        --noises gauss student3 --measurement-dof 4 \
        --json benchmarks/results/discover_robust.json \
        --markdown benchmarks/results/discover_robust.md  # robust evidence
    python benchmarks/discover.py --render benchmarks/results/discover.json \
        --markdown benchmarks/results/discover.md  # report text only
"""

import argparse
import json
import math
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, write_json  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from eqsmooth.discover import score_test  # noqa: E402


B, T = 24, 40
SPRING = 0.05
Q = np.array([0.05, 0.5])  # process noise std (position, velocity)
R = 1.0  # measurement noise std
PRIOR = np.array([20.0, 4.0])
COULOMB_EPS = 1.0

# Hidden effect -> the candidate that is the truth.
EFFECTS = {
    "viscous": "viscous damping",
    "drag": "quadratic drag",
    "coulomb": "Coulomb friction",
    "force": "constant force",
    "bias": "sensor bias",
    # Out of the library: a sinusoidal force whose period (8-20 steps) and
    # phase differ per sequence. The right outcome is no confident name.
    "sine": None,
}
LEVELS = (0.05, 0.15, 0.4)


# ---------------------------------------------------------------------------
# Data
# ---------------------------------------------------------------------------


def _effect_term(effect: str, v: np.ndarray) -> np.ndarray:
    """Per-step velocity increment of a unit coefficient (dynamics effects)."""
    if effect == "viscous":
        return -v
    if effect == "drag":
        return -v * np.abs(v)
    if effect == "coulomb":
        return -np.tanh(v / COULOMB_EPS)
    if effect == "force":
        return np.ones_like(v)
    raise ValueError(effect)


NOISES = {
    "gauss": "Gaussian measurement noise of the assumed std",
    "gauss2x": "Gaussian measurement noise of twice the assumed std",
    "student3": "Student-t(3) measurement noise scaled to the assumed std",
}


def _measurement_noise(rng, shape, noise: str) -> np.ndarray:
    if noise == "gauss":
        return R * rng.normal(size=shape)
    if noise == "gauss2x":
        return 2.0 * R * rng.normal(size=shape)
    if noise == "student3":
        return R * rng.standard_t(3, size=shape) / np.sqrt(3.0)
    raise ValueError(noise)


def simulate(
    rng: np.random.Generator,
    effect: str,
    coef: float,
    num: int = B,
    noise: str = "gauss",
):
    """States `(num, T, 2)` and measurements `(num, T, 1)`; effect RMS per step."""
    x = np.stack([rng.normal(0, PRIOR[0], num), rng.normal(0, PRIOR[1], num)], 1)
    if effect == "sine":  # drawn first: the other effects' streams are unchanged
        period = rng.uniform(8.0, 20.0, num)
        phase = rng.uniform(0.0, 2 * np.pi, num)
    xs, contrib = [], []
    for t in range(T):
        xs.append(x.copy())
        p, v = x[:, 0], x[:, 1]
        a = -SPRING * p
        if effect in ("viscous", "drag", "coulomb", "force"):
            d = coef * _effect_term(effect, v)
            contrib.append(d)
            a = a + d
        elif effect == "sine":
            d = coef * np.sin(2 * np.pi * t / period + phase)
            contrib.append(d)
            a = a + d
        x = np.stack([p + v, v + a], 1) + rng.normal(size=(num, 2)) * Q
    xs = np.stack(xs, 1)
    y = xs[..., :1] + _measurement_noise(rng, (num, T, 1), noise)
    if effect == "bias":
        y = y + coef
        snr = SPRING * abs(coef) / Q[1]  # as the equivalent constant force
    elif contrib:
        snr = float(np.sqrt(np.mean(np.square(contrib[:-1])))) / Q[1]
    else:
        snr = 0.0
    return xs, y, snr


def sequences(y: np.ndarray) -> dc.Sequences:
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((y.shape[0], 2)), initial_states=init)


def calibrate(levels) -> dict:
    """Coefficient per (effect, level) from nominal trajectories (fixed seed)."""
    xs, _, _ = simulate(np.random.default_rng(12345), "none", 0.0, num=4000)
    v = xs[:, :-1, 1]
    out = {}
    for effect in EFFECTS:
        if effect == "bias":
            unit = SPRING / Q[1]
        elif effect == "sine":
            unit = math.sqrt(0.5) / Q[1]
        else:
            unit = float(np.sqrt(np.mean(np.square(_effect_term(effect, v))))) / Q[1]
        out[effect] = {lv: lv / unit for lv in levels}
    return out


def rng_for(tag: int, level: float, seed: int) -> np.random.Generator:
    """Independent streams per (effect, level, seed), stable across runs."""
    key = [2026, tag, int(round(level * 10_000)), seed]
    return np.random.default_rng(np.random.SeedSequence(key))


# ---------------------------------------------------------------------------
# Model and one workflow run
# ---------------------------------------------------------------------------


def _dyn(x, u, spring):
    return jnp.stack([x[0] + x[1], x[1] - spring * x[0]])


def _meas(x, spring):
    return x[:1]


_LIBRARY = dc.mechanical_library(
    [0], [1], 2, measured_positions=[0], coulomb_eps=COULOMB_EPS
)


def make_model(measurement_dof: float | None = None) -> dc.ChainModel:
    """The nominal model: Gaussian measurement noise, or Student-t(ν)."""
    return dc.ChainModel(
        _dyn,
        _meas,
        jnp.asarray(SPRING),
        Q,
        np.array([R]),
        PRIOR,
        _LIBRARY,
        measurement_dof=measurement_dof,
    )


# Built once: the library is static structure of the model, so one model
# object (and one set of compiled callables) serves every data set.
MODEL = make_model()


def run_workflow(data: dc.Sequences, model: dc.ChainModel = MODEL) -> dict:
    t0 = time.perf_counter()
    found = dc.find(model, data)
    t1 = time.perf_counter()
    named = dc.name(found, data)
    t2 = time.perf_counter()
    added = dc.add(found, named, data)
    t3 = time.perf_counter()
    st = found["_state"]
    # The same score test with the outer-product covariance (what "auto"
    # picks with >= 10 sequences per parameter): reported, not used.
    if found["status"] == "ok":
        ident = np.flatnonzero(st["identifiable"])
        opg = score_test(st["evaluation"], ident, st["nuisance"], "opg")
    else:
        opg = {"p_value": float("nan")}
    check = found.get("noise_check") or {}
    return {
        "status": found["status"],
        "heavy_tails": bool(check.get("heavy_tails", False)),
        "scale_off_by_2": bool(check.get("scale_off_by_2", False)),
        "flags": list(found["flags"]) + list(named["flags"]) + list(added["flags"]),
        "alarms": dict(named["alarms"]),
        "tentative": bool(named["tentative"]),
        "detected": bool(found["detected"]),
        "p_value": float(found["score_test"]["p_value"]),
        "df": int(found["score_test"]["df"]),
        "covariance": found["score_test"]["covariance"],
        "opg_p_value": float(opg["p_value"]),
        "named": list(named["named"]),
        "sets": [list(s) for s in named["equivalence_sets"] + named["ambiguous"]],
        "equivalence_sets": [list(s) for s in named["equivalence_sets"]],
        "unnamed": bool(named["unnamed_residual_structure"]),
        "verdict": named["verdict"],
        "coefficients": {
            c["name"]: (c["value"], c["interval"]) for c in added["coefficients"]
        },
        "seconds": t3 - t0,
        "find_s": t1 - t0,
        "name_s": t2 - t1,
        "add_s": t3 - t2,
    }


def guarded_run(data: dc.Sequences, model: dc.ChainModel, log, label: str):
    """`run_workflow`, or None after logging its exception as a crash."""
    try:
        return run_workflow(data, model)
    except Exception as e:  # reported, never hidden
        log(f"  {label}: CRASH {type(e).__name__}: {e}")
        return None


def classify(out: dict, truth: str) -> str:
    named = out["named"]
    if not named:
        return "none"
    in_set = any(truth in s for s in out["sets"])
    if in_set:
        return "set"
    if named == [truth]:
        return "exact"
    if truth in named:
        return "extra"
    return "wrong"


# ---------------------------------------------------------------------------
# Statistics
# ---------------------------------------------------------------------------


def wilson(k: int, n: int, z: float = 1.959964) -> tuple[float, float]:
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    den = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, centre - half), min(1.0, centre + half))


def rate(k: int, n: int) -> dict:
    lo, hi = wilson(k, n)
    return {"k": k, "n": n, "rate": k / n if n else float("nan"), "ci95": [lo, hi]}


def fmt_rate(r: dict) -> str:
    if not r["n"]:
        return "–"
    lo, hi = r["ci95"]
    return f"{r['rate']:.2f} [{lo:.2f}, {hi:.2f}]"


def _q(values, q):
    return float(np.quantile(values, q)) if len(values) else float("nan")


# ---------------------------------------------------------------------------
# Runs
# ---------------------------------------------------------------------------


def _model_config(model: dc.ChainModel) -> str:
    nu = model.measurement_dof
    return "gaussian" if nu is None else f"student-t({nu:g})"


def effect_cell(
    effect, level, coef, seeds, log, model=MODEL, sequences_per_set=B
) -> dict:
    truth = EFFECTS[effect]
    tag = list(EFFECTS).index(effect) + 1
    outcomes = {k: 0 for k in ("exact", "set", "extra", "wrong", "none")}
    detected = unnamed = failures = flagged = failed_status = confident = 0
    truth_named = leftover_after_truth = tentative = 0
    rel, covered, snrs, times, wrong_names = [], 0, [], [], {}
    for s in range(seeds):
        _, y, snr = simulate(rng_for(tag, level, s), effect, coef, sequences_per_set)
        snrs.append(snr)
        out = guarded_run(sequences(y), model, log, f"{effect} level {level} seed {s}")
        if out is None:
            failures += 1
            continue
        times.append(out["seconds"])
        flagged += bool(out["flags"])
        failed_status += out["status"] != "ok"
        if out["flags"]:
            log(f"  {effect} level {level} seed {s}: flags {out['flags']}")
        detected += out["detected"]
        unnamed += out["unnamed"]
        tentative += out["tentative"]
        confident += bool(out["named"]) and not out["tentative"]
        cls = classify(out, truth)
        outcomes[cls] += 1
        if cls == "exact":
            # The truth named alone: nothing is left, so the leftover-
            # structure alarm is a false alarm here.
            truth_named += 1
            leftover_after_truth += out["alarms"]["leftover_structure"]
        if cls in ("wrong", "extra"):
            for nm in out["named"]:
                if nm != truth:
                    wrong_names[nm] = wrong_names.get(nm, 0) + 1
        if truth in out["coefficients"]:
            value, (lo, hi) = out["coefficients"][truth]
            rel.append((value - coef) / coef)
            covered += lo <= coef <= hi
    n = seeds - failures
    abs_rel = np.abs(rel)
    rec = {
        "benchmark": "discover",
        "config": {
            "effect": effect,
            "truth": truth,
            "measurement_model": _model_config(model),
            "snr_target": level,
            "coefficient": coef,
            "B": sequences_per_set,
            "T": T,
            "spring": SPRING,
            "process_sigma": Q.tolist(),
            "measurement_sigma": R,
            "prior_sigma": PRIOR.tolist(),
            "library": list(MODEL.names),
            "alpha": 0.05,
        },
        "n": n,
        "failures": failures,
        "crashes": failures,
        "flagged": flagged,
        "status_failed": failed_status,
        "tentative": rate(tentative, n),
        # A name that is not marked tentative (for an effect outside the
        # library every such name is a wrong, confident one).
        "named_confidently": rate(confident, n),
        "leftover_after_truth_alone": rate(leftover_after_truth, truth_named),
        "snr_realised_median": float(np.median(snrs)),
        "median_s": statistics.median(times) if times else float("nan"),
        "p90_s": _q(times, 0.9),
        "detection": rate(detected, n),
        "named_truth_alone": rate(outcomes["exact"], n),
        "truth_in_set": rate(outcomes["set"], n),
        "correct_naming": rate(outcomes["exact"] + outcomes["set"], n),
        "truth_plus_extra": rate(outcomes["extra"], n),
        "wrong_name": rate(outcomes["wrong"], n),
        "nothing_named": rate(outcomes["none"], n),
        "unnamed_structure": rate(unnamed, n),
        "other_names": wrong_names,
        "coef_n": len(rel),
        "coef_rel_error_median_abs": float(np.median(abs_rel)) if rel else None,
        "coef_rel_error_p90_abs": _q(abs_rel, 0.9) if rel else None,
        "coef_rel_error_median_signed": float(np.median(rel)) if rel else None,
        "coef_ci95_coverage": rate(covered, len(rel)),
        "coef_rel_errors": [float(r) for r in rel],
    }
    return rec


def null_cell(num, log, noise="gauss", model=MODEL, sequences_per_set=B) -> dict:
    counts = dict.fromkeys(
        (
            "rejected",
            "named_any",
            "named_confident",
            "unnamed",
            "alarm",
            "opg_rej",
            "failures",
            "flagged",
            "status_failed",
            "heavy_tails",
            "scale_off_by_2",
        ),
        0,
    )
    alarm_counts = {}
    names, pvals, opg_p, times, dfs = {}, [], [], [], {}
    tag = list(NOISES).index(noise)
    for s in range(num):
        # Gaussian null data keep their historical stream (tag 0).
        rng = rng_for(0, 0, s) if tag == 0 else rng_for(100 + tag, 0, s)
        _, y, _ = simulate(rng, "none", 0.0, sequences_per_set, noise=noise)
        out = guarded_run(sequences(y), model, log, f"null ({noise}) seed {s}")
        if out is None:
            counts["failures"] += 1
            continue
        times.append(out["seconds"])
        counts["flagged"] += bool(out["flags"])
        counts["status_failed"] += out["status"] != "ok"
        if out["flags"]:
            log(f"  null ({noise}) seed {s}: flags {out['flags']}")
        if np.isfinite(out["p_value"]):
            pvals.append(out["p_value"])
        if np.isfinite(out["opg_p_value"]):
            opg_p.append(out["opg_p_value"])
            counts["opg_rej"] += out["opg_p_value"] < 0.05
        dfs[out["df"]] = dfs.get(out["df"], 0) + 1
        counts["rejected"] += out["detected"]
        counts["heavy_tails"] += out["heavy_tails"]
        counts["scale_off_by_2"] += out["scale_off_by_2"]
        counts["unnamed"] += out["unnamed"]
        counts["named_any"] += bool(out["named"])
        counts["named_confident"] += bool(out["named"]) and not out["tentative"]
        counts["alarm"] += any(out["alarms"].values())
        for k, v in out["alarms"].items():
            alarm_counts[k] = alarm_counts.get(k, 0) + bool(v)
        for nm in out["named"]:
            names[nm] = names.get(nm, 0) + 1
        if out["named"] or out["detected"] or any(out["alarms"].values()):
            log(
                f"  null ({noise}) seed {s}: p={out['p_value']:.3g} verdict: "
                f"{out['verdict']}"
            )
    n = num - counts["failures"]
    return {
        "benchmark": "discover",
        "config": {
            "effect": "none",
            "noise": noise,
            "noise_description": NOISES[noise],
            "measurement_model": _model_config(model),
            "truth": None,
            "B": sequences_per_set,
            "T": T,
            "spring": SPRING,
            "process_sigma": Q.tolist(),
            "measurement_sigma": R,
            "prior_sigma": PRIOR.tolist(),
            "library": list(MODEL.names),
            "alpha": 0.05,
        },
        "n": n,
        "failures": counts["failures"],
        "crashes": counts["failures"],
        "flagged": counts["flagged"],
        "status_failed": counts["status_failed"],
        "median_s": statistics.median(times) if times else float("nan"),
        "p90_s": _q(times, 0.9),
        "false_discovery": rate(counts["named_any"], n),
        "confident_false_discovery": rate(counts["named_confident"], n),
        "score_test_rejects": rate(counts["rejected"], n),
        "unnamed_structure": rate(counts["unnamed"], n),
        "alarm_rates": {
            k: rate(alarm_counts.get(k, 0), n)
            for k in (
                "detected",
                "unnamed_structure",
                "ambiguous",
                "leftover_structure",
            )
        },
        "any_alarm": rate(counts["alarm"], n),
        "noise_check_heavy_tails": rate(counts["heavy_tails"], n),
        "noise_check_scale_off_by_2": rate(counts["scale_off_by_2"], n),
        "opg_score_test_rejects": rate(counts["opg_rej"], len(opg_p)),
        "score_test_df_counts": {str(k): v for k, v in sorted(dfs.items())},
        "p_value_quantiles": {
            str(q): _q(pvals, q) for q in (0.01, 0.05, 0.1, 0.25, 0.5)
        },
        "named_counts": names,
        "p_values": pvals,
        "opg_p_values": opg_p,
    }


# ---------------------------------------------------------------------------
# Output
# ---------------------------------------------------------------------------


def effect_table(records) -> str:
    cols = [
        "effect",
        "SNR (target / realised)",
        "coef",
        "n",
        "detected",
        "correct (alone + set)",
        "truth alone",
        "truth in set",
        "truth + extra",
        "wrong name",
        "named confidently",
        "unnamed structure",
        "abs. rel. err. median",
        "abs. rel. err. p90",
        "signed rel. err. median",
        "CI coverage",
        "leftover alarm after truth alone",
        "crashes / flagged",
        "median s",
    ]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in records:
        c = r["config"]
        cells = [
            _row_label(c, "truth"),
            f"{c['snr_target']:.2f} / {r['snr_realised_median']:.3f}",
            f"{c['coefficient']:.4g}",
            str(r["n"]),
            fmt_rate(r["detection"]),
            fmt_rate(r["correct_naming"]),
            fmt_rate(r["named_truth_alone"]),
            fmt_rate(r["truth_in_set"]),
            fmt_rate(r["truth_plus_extra"]),
            fmt_rate(r["wrong_name"]),
            fmt_rate(r["named_confidently"]) if "named_confidently" in r else "–",
            fmt_rate(r["unnamed_structure"]),
        ]
        if r["coef_n"]:
            cells += [
                f"{r['coef_rel_error_median_abs']:.3f}",
                f"{r['coef_rel_error_p90_abs']:.3f}",
                f"{r['coef_rel_error_median_signed']:+.3f}",
                f"{r['coef_ci95_coverage']['rate']:.2f} ({r['coef_n']})",
            ]
        else:
            cells += ["–", "–", "–", "–"]
        left = r.get("leftover_after_truth_alone")
        cells.append(fmt_rate(left) if left else "–")
        cells.append(f"{r.get('crashes', r['failures'])} / {r.get('flagged', '–')}")
        cells.append(f"{r['median_s']:.2f}")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _row_label(config: dict, key: str) -> str:
    model = config.get("measurement_model", "gaussian")
    if key == "truth" and config.get("truth") is None:
        label = f"{config['effect']} (out of library)"
    else:
        label = str(config.get(key) or "gauss")
    return label if model == "gaussian" else f"{label} ({model} model)"


def null_table(nulls) -> str:
    cols = [
        "noise",
        "n",
        "crashes",
        "flagged",
        "detected (score test)",
        "unnamed structure",
        "ambiguous",
        "leftover structure",
        "any alarm",
        "anything named",
        "named confidently",
        "OPG score test rejects",
        "noise check: heavy tails",
        "noise check: scale off ×2",
        "median s",
    ]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for r in nulls:
        a = r.get("alarm_rates", {})
        cells = [
            _row_label(r["config"], "noise"),
            str(r["n"]),
            str(r.get("crashes", r["failures"])),
            str(r.get("flagged", "–")),
            fmt_rate(r["score_test_rejects"]),
            fmt_rate(a["unnamed_structure"]) if a else fmt_rate(r["unnamed_structure"]),
            fmt_rate(a["ambiguous"]) if a else "–",
            fmt_rate(a["leftover_structure"]) if a else "–",
            fmt_rate(r["any_alarm"]),
            fmt_rate(r["false_discovery"]),
            fmt_rate(r["confident_false_discovery"])
            if "confident_false_discovery" in r
            else "–",
            fmt_rate(r["opg_score_test_rejects"]),
            fmt_rate(r["noise_check_heavy_tails"])
            if "noise_check_heavy_tails" in r
            else "–",
            fmt_rate(r["noise_check_scale_off_by_2"])
            if "noise_check_scale_off_by_2" in r
            else "–",
            f"{r['median_s']:.2f}",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def other_names_lines(records) -> list[str]:
    out = []
    for r in records:
        if r["other_names"]:
            items = ", ".join(f"{k} ×{v}" for k, v in sorted(r["other_names"].items()))
            out.append(
                f"- {r['config']['truth']} at SNR {r['config']['snr_target']}: {items}"
            )
    return out


def report(records, nulls, info, quick) -> str:
    m = info["machine"]
    lines = ["# discover benchmark: Monte Carlo of find / name / add", ""]
    if quick:
        lines += ["**QUICK RUN (a small subset; not the committed figures).**", ""]
    lines += [
        f"- command: `{info['command']}`",
        f"- machine: {m['cores']} cores, {m['memory']}, {m['cpu']}; "
        f"JAX {m['jax']} ({m['backend']}), Python {m['python']}",
        f"- git: {info['git']} (at start)"
        + (
            "; uncommitted changes then in: " + ", ".join(info["dirty"])
            if info["dirty"]
            else "; no uncommitted changes under eqsmooth/ or in this script"
        ),
        f"- data: B = {info['B']} sequences × T = {T} steps per data set; oscillator "
        f"k = {SPRING}, process noise std {Q.tolist()}, measurement std {R}, "
        f"first-state prior std {PRIOR.tolist()}",
        f"- library ({len(MODEL.names)} candidates, all distractors): "
        + ", ".join(MODEL.names),
        '- decision: score test at α = 0.05 (`covariance="auto"`, which with '
        f"{info['B']} sequences is the conservative observed-information form); "
        "naming: forward selection with the Bonferroni-gated likelihood-ratio test",
        f"- wall time: {info['total_s'] / 60:.1f} min in all; compile (first "
        f"workflow run minus a repeat on the same data): {info['compile_s']:.1f} s; "
        "`median s` = median wall time of one find + name + add run",
        "",
        "## Hidden effects",
        "",
        "SNR: per-step RMS of the effect over the velocity process-noise std "
        "(target: calibrated on nominal trajectories; realised: under the "
        "effect); a sensor bias b counts as the constant force k·b it mimics "
        "(its per-measurement ratio b / r is q_v / (k r) = 10 times larger). "
        "`correct` = the truth named alone, or the truth inside a "
        "reported ambiguous / equivalence set (e.g. {constant force ≡ sensor "
        "bias}: an equivalence-set answer containing the truth counts as correct "
        "naming). `truth + extra` = the truth named unambiguously with a further "
        "term; `wrong name` = only other names; `named confidently` = a name "
        "not marked tentative. A row marked `(out of library)` hides an effect "
        "no candidate describes (`sine`: a sinusoidal force of period 8-20 "
        "steps and random phase per sequence); every name there is wrong, and "
        "the workflow should give none confidently. Rates over all n data sets with "
        "Wilson 95% intervals. Coefficient errors and the coverage of the 95% "
        "coefficient interval are over the data sets in which the truth's own "
        "coefficient was fitted (count in brackets); at low SNR these few are "
        "selected for large estimates (only those pass the gates), so their "
        "errors are biased upwards.",
        "",
        effect_table(records),
        "",
    ]
    other = other_names_lines(records)
    if other:
        lines += [
            "Other names given (in `wrong name` or `truth + extra` outcomes):",
            "",
        ]
        lines += other + [""]
    if nulls:
        lines += [
            "## Null data (no missing effect): every alarm's false-alarm rate",
            "",
            "Each alarm a run can raise, as the fraction of null data sets that "
            "raised it (target ≤ α = 5% each): `detected` = the score test "
            'rejects; `unnamed structure` = the verdict says "unnamed residual '
            'structure" with no name (the residual diagnostics significant, '
            "whether or not the score test rejects); `ambiguous` = a name "
            "given with a runner-up within ln 20; `leftover structure` = names "
            "given but the named model's diagnostics still significant (the names "
            "are then reported as tentative); `any alarm` = any of these. "
            "`anything named`: a name, tentative or not; `named confidently`: a "
            "name that is not tentative. `crashes`: exceptions out of find / name "
            "/ add (must be 0); `flagged`: runs that finished with a result flag "
            "(a fit that did not converge, a failed evaluation). Rows: Gaussian "
            "measurement noise of the assumed std; twice that std (the workflow "
            "refits the noise scales); Student-t(3) noise of the assumed std "
            "(heavy tails). A row marked `(student-t(ν) model)` ran the workflow "
            "with Student-t(ν) measurement noise in the nominal model "
            "(`--measurement-dof`, the robust evidence); the others with the "
            "Gaussian model. `OPG`: the score test with the "
            "outer-product-of-gradients covariance, for comparison only. "
            "`noise check`: how often the report's noise check (not an alarm) "
            "said the innovations are heavy-tailed, or that a refitted noise "
            "scale is off by more than a factor 2.",
            "",
            null_table(nulls),
            "",
        ]
        for null in nulls:
            fd = null["false_discovery"]
            noise = _row_label(null["config"], "noise")
            alarms = null.get("alarm_rates", {})
            worst = max(
                [a["rate"] for a in alarms.values()] + [fd["rate"]], default=0.0
            )
            lines += [
                f"- {noise}: anything named {fd['rate']:.3f} (95% CI "
                f"{fd['ci95'][0]:.3f} – {fd['ci95'][1]:.3f}, n = {fd['n']}); "
                f"largest single alarm rate {worst:.3f}: target ≤ 0.05 "
                + ("met" if worst <= 0.05 else "MISSED")
                + ". Score-test p-value quantiles (uniform would give q): "
                + ", ".join(
                    f"q{k}: {v:.3f}" for k, v in null["p_value_quantiles"].items()
                )
                + "; degrees of freedom: "
                + ", ".join(
                    f"{k}: {v}" for k, v in null["score_test_df_counts"].items()
                )
                + (
                    "; named: "
                    + ", ".join(f"{k} ×{v}" for k, v in null["named_counts"].items())
                    if null["named_counts"]
                    else ""
                )
                + "."
            ]
        lines.append("")
    return "\n".join(lines)


def _git():
    here = Path(__file__).resolve().parent
    head = subprocess.run(
        ["git", "rev-parse", "--short", "HEAD"],
        capture_output=True,
        text=True,
        cwd=here,
    ).stdout.strip()
    dirty = subprocess.run(
        ["git", "status", "--porcelain", "--", "../eqsmooth", "discover.py"],
        capture_output=True,
        text=True,
        cwd=here,
    ).stdout
    # Paths (relative to the repository root) with uncommitted changes.
    dirty = [ln[3:] for ln in dirty.splitlines() if ln.strip()]
    return head or "unknown", dirty


def render(path, markdown=None) -> None:
    """Re-render the markdown report of a saved run from its JSON."""
    payload = json.loads(Path(path).read_text())
    recs = payload["records"]
    info = {
        "machine": payload["machine"],
        "command": payload["command"],
        "git": payload["machine"]["git"],
        "dirty": payload.get("git_dirty", []),
        "compile_s": payload["compile_s"],
        "total_s": payload["total_s"],
        "B": recs[0]["config"]["B"] if recs else B,
    }
    nulls = [r for r in recs if r["config"]["effect"] == "none"]
    effects = [r for r in recs if r["config"]["effect"] != "none"]
    text = report(effects, nulls, info, payload.get("quick", False))
    if markdown:
        Path(markdown).write_text(text + "\n")
    else:
        print(text)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small subset (CI)")
    parser.add_argument("--seeds", type=int, default=None, help="data sets per cell")
    parser.add_argument("--null", type=int, default=None, help="null data sets")
    parser.add_argument("--effects", nargs="*", default=None, choices=list(EFFECTS))
    parser.add_argument(
        "--null-other",
        type=int,
        default=None,
        help="null data sets per non-Gaussian noise (default: --null)",
    )
    parser.add_argument(
        "--noises",
        nargs="*",
        default=None,
        choices=list(NOISES),
        help="measurement noise of the null data sets",
    )
    parser.add_argument("--levels", type=float, nargs="*", default=None)
    parser.add_argument(
        "--sequences",
        type=int,
        default=B,
        metavar="B",
        help=f"sequences per data set (default {B}; a data-size sweep reruns "
        "with larger B)",
    )
    parser.add_argument(
        "--measurement-dof",
        type=float,
        default=None,
        metavar="NU",
        help="the nominal model's measurement noise is Student-t(NU) (robust "
        "evidence) instead of Gaussian",
    )
    parser.add_argument("--json", default=None, help="write the records here")
    parser.add_argument("--markdown", default=None, help="write the report here")
    parser.add_argument(
        "--render",
        default=None,
        metavar="JSON",
        help="only re-render the report of a saved run (to --markdown or stdout)",
    )
    args = parser.parse_args(argv)
    if args.sequences < 2:
        parser.error(f"--sequences must be at least 2, got {args.sequences}")
    if args.render:
        render(args.render, args.markdown)
        return

    head, dirty = _git()  # captured at start
    m = machine()
    m["git"] = head
    command = " ".join([Path(sys.executable).name] + sys.argv)
    seeds = args.seeds if args.seeds is not None else (2 if args.quick else 50)
    num_null = args.null if args.null is not None else (10 if args.quick else 200)
    effects = args.effects or (["drag", "force"] if args.quick else list(EFFECTS))
    levels = tuple(args.levels or ((0.4,) if args.quick else LEVELS))
    noises = args.noises or (["gauss"] if args.quick else list(NOISES))
    coefs = calibrate(levels)
    model = make_model(args.measurement_dof)
    start = time.perf_counter()

    def log(msg):
        print(msg, flush=True)

    log(f"git {head}{' (dirty)' if dirty else ''}; {m['cores']} cores, {m['cpu']}")
    log(
        "coefficients per SNR level: "
        + str({e: {lv: round(c, 6) for lv, c in d.items()} for e, d in coefs.items()})
    )

    # Compile once (strong drag, a seed outside the Monte Carlo), then repeat
    # the same data set for the steady-state time.
    _, y, _ = simulate(
        rng_for(99, 0, 0), "drag", coefs["drag"][max(levels)], args.sequences
    )
    warm = sequences(y)
    first = run_workflow(warm, model)
    again = run_workflow(warm, model)
    compile_s = first["seconds"] - again["seconds"]
    log(
        f"warm-up: first run {first['seconds']:.1f} s, repeat {again['seconds']:.2f} s "
        f"(verdict {again['verdict']!r})"
    )

    records, nulls = [], []

    def save():
        info = {
            "machine": m,
            "command": command,
            "git": head,
            "dirty": dirty,
            "compile_s": compile_s,
            "total_s": time.perf_counter() - start,
            "B": args.sequences,
        }
        for r in records + nulls:
            r["compile_s"] = compile_s
        recs = records + nulls
        if args.json:
            write_json(
                args.json,
                recs,
                extra={
                    "machine": m,
                    "command": command,
                    "git_dirty": dirty,
                    "quick": args.quick,
                    "total_s": info["total_s"],
                    "compile_s": compile_s,
                    "warmup": {k: first[k] for k in ("seconds", "verdict")},
                },
            )
        text = report(records, nulls, info, args.quick)
        if args.markdown:
            Path(args.markdown).parent.mkdir(parents=True, exist_ok=True)
            Path(args.markdown).write_text(text + "\n")
        return text

    for noise in noises if num_null else ():
        t0 = time.perf_counter()
        count = num_null
        if noise != "gauss" and args.null_other is not None:
            count = args.null_other
        null = null_cell(count, log, noise, model, args.sequences)
        nulls.append(null)
        fd = null["false_discovery"]
        log(
            f"null ({noise}): n={null['n']} crashes {null['crashes']} named "
            f"{fmt_rate(fd)}, alarms "
            + ", ".join(f"{k} {fmt_rate(v)}" for k, v in null["alarm_rates"].items())
            + f" ({time.perf_counter() - t0:.0f} s)"
        )
        save()
    for effect in effects if seeds else ():
        for level in levels:
            t0 = time.perf_counter()
            rec = effect_cell(
                effect, level, coefs[effect][level], seeds, log, model, args.sequences
            )
            records.append(rec)
            log(
                f"{EFFECTS[effect] or effect + ' (out)':17s} SNR {level:<5} "
                f"n={rec['n']} detected "
                f"{fmt_rate(rec['detection'])} "
                f"correct {fmt_rate(rec['correct_naming'])}"
                f" wrong {fmt_rate(rec['wrong_name'])} "
                f"({time.perf_counter() - t0:.0f} s)"
            )
            save()
    text = save()
    print()
    print(text)


if __name__ == "__main__":
    main()
