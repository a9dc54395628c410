"""Monte Carlo of the discrepancy workflow (find, name, add) on hidden effects.

Data: a 1-D oscillator, state (p, v), p' = p + v, v' = v − k p + effect +
noise (k = 0.05, process noise std (0.05, 0.5), position measured with std
1, first state from the model's prior N(0, diag(20², 4²))), B = 24 sequences
× T = 40 steps per data set. The nominal model knows the spring and the
noise levels (the workflow refits three noise scales) but not the effect.
The candidate library is the one-axis `mechanical_library` with sensor
terms (10 candidates, each a distractor for the others).

Hidden effects: viscous damping, quadratic drag, Coulomb friction, constant
force, sensor bias, and `sine` (a sinusoidal force outside the library: the
right outcome is no confident name), each at per-step signal-to-noise ratios
(the RMS of the effect's velocity increment over nominal trajectories over
the velocity noise std 0.5; a sensor bias b counts as the constant force k·b
it mimics), calibrated once from simulated nominal trajectories.
`--measurement-dof NU` makes the nominal measurement noise Student-t(NU).

Null data: no effect, with measurement noise of the assumed std, twice it,
or Student-t(3) (`--noises`); every alarm gets its own false-alarm rate.
Outcomes per data set: the truth named alone, inside a reported set, with
an extra term, a wrong name only, or nothing named (Wilson 95% intervals).

    python -m experiments.discovery_validation.oscillator --quick
    python -m experiments.discovery_validation.oscillator --seeds 50 --null 200 \\
        --json results/discovery_validation/oscillator.json \\
        --markdown results/discovery_validation/oscillator.md
    python -m experiments.discovery_validation.oscillator --seeds 10 --levels 0.4 \\
        --null 60 --noises gauss student3 --measurement-dof 4 \\
        --json results/discovery_validation/oscillator_robust.json \\
        --markdown results/discovery_validation/oscillator_robust.md
    python -m experiments.discovery_validation.oscillator \\
        --render results/discovery_validation/oscillator.json \\
        --markdown results/discovery_validation/oscillator.md  # report text only
"""

import argparse
import json
import math
import statistics
import time
from collections import Counter
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from benchmarks._common import cli_command, dirty, git, machine, write_json, write_text  # noqa: E402
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


# Per-step velocity increment of a unit coefficient (dynamics effects).
_TERMS = {
    "viscous": lambda v: -v,
    "drag": lambda v: -v * np.abs(v),
    "coulomb": lambda v: -np.tanh(v / COULOMB_EPS),
    "force": np.ones_like,
}


def _effect_term(effect: str, v: np.ndarray) -> np.ndarray:
    return _TERMS[effect](v)


NOISES = {
    "gauss": "Gaussian measurement noise of the assumed std",
    "gauss2x": "Gaussian measurement noise of twice the assumed std",
    "student3": "Student-t(3) measurement noise scaled to the assumed std",
}


def _measurement_noise(rng, shape, noise: str) -> np.ndarray:
    if noise == "student3":
        return R * rng.standard_t(3, size=shape) / np.sqrt(3.0)
    return {"gauss": 1.0, "gauss2x": 2.0}[noise] * R * rng.normal(size=shape)


def simulate(rng, effect: str, coef: float, num: int = B, noise: str = "gauss"):
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
        if effect in _TERMS or effect == "sine":
            d = coef * (
                _effect_term(effect, v)
                if effect in _TERMS
                else np.sin(2 * np.pi * t / period + phase)
            )
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


def _dyn(x, u, spring):
    return jnp.stack([x[0] + x[1], x[1] - spring * x[0]])


def _meas(x, spring):
    return x[:1]


_LIBRARY = dc.mechanical_library(
    [0], [1], 2, measured_positions=[0], coulomb_eps=COULOMB_EPS
)


def make_model(measurement_dof: float | None = None) -> dc.ChainModel:
    """The nominal model: Gaussian measurement noise, or Student-t(ν)."""
    nominal = (_dyn, _meas, jnp.asarray(SPRING), Q, np.array([R]), PRIOR)
    return dc.ChainModel(*nominal, _LIBRARY, measurement_dof=measurement_dof)


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
    st = found.state
    # The same score test with the outer-product covariance (what "auto"
    # picks with >= 10 sequences per parameter): reported, not used.
    if found["status"] == "ok":
        ident = np.flatnonzero(st.identifiable)
        opg = score_test(st.evaluation, ident, st.nuisance, "opg")
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
        # The data size each reported set's verdict says would separate it
        # (None where the information gives none).
        "sequences_to_separate": [
            max(
                (r["sequences_to_separate"] or math.inf)
                for r in step.get("rivals", [])
                if not r["separable"]
            )
            for step in named["steps"][: len(named["named"])]
            if any(not r["separable"] for r in step.get("rivals", []))
        ],
        "shape_unchecked": bool(
            named.get("shape_check") and not named["shape_check"]["checked"]
        ),
        "partial": bool(named["alarms"].get("partial", False)),
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


def naming_rates(c: Counter, n: int, alone: str, correct: str) -> dict:
    """Rates of the truth named alone (key `alone`), in a set, either (`correct`),
    with extras, of a wrong name and of none, from `classify`'s counts `c`."""
    out = {alone: rate(c["exact"], n), "truth_in_set": rate(c["set"], n)}
    out[correct] = rate(c["exact"] + c["set"], n)
    pairs = (
        ("truth_plus_extra", "extra"),
        ("wrong_name", "wrong"),
        ("nothing_named", "none"),
    )
    return out | {key: rate(c[k], n) for key, k in pairs}


def _head(config: dict, n: int, c: Counter, sequences_per_set: int) -> dict:
    """The fields every record of this benchmark starts with."""
    head = {"benchmark": "discover", "config": config | _data_config(sequences_per_set)}
    head |= {"n": n, "failures": c["failures"], "crashes": c["failures"]}
    return head | {k: c[k] for k in ("flagged", "status_failed")}


def fmt_rate(r: dict) -> str:
    if not r["n"]:
        return "–"
    lo, hi = r["ci95"]
    return f"{r['rate']:.2f} [{lo:.2f}, {hi:.2f}]"


def _q(values, q):
    return float(np.quantile(values, q)) if len(values) else float("nan")


def _model_config(model: dc.ChainModel) -> str:
    nu = model.measurement_dof
    return "gaussian" if nu is None else f"student-t({nu:g})"


def _data_config(sequences_per_set: int) -> dict:
    return {
        "B": sequences_per_set,
        "T": T,
        "spring": SPRING,
        "process_sigma": Q.tolist(),
        "measurement_sigma": R,
        "prior_sigma": PRIOR.tolist(),
        "library": list(MODEL.names),
        "alpha": 0.05,
    }


def _runs(cells, model, log, label):
    """Run the workflow on `(seed, data)` pairs; yields `(seed, out)` for runs
    that did not crash, and counts crashes, flags and failed statuses."""
    tally = Counter()
    outs = []
    for s, data in cells:
        out = guarded_run(data, model, log, f"{label} seed {s}")
        if out is None:
            tally["failures"] += 1
            continue
        tally["flagged"] += bool(out["flags"])
        tally["status_failed"] += out["status"] != "ok"
        if out["flags"]:
            log(f"  {label} seed {s}: flags {out['flags']}")
        outs.append((s, out))
    return outs, tally


def effect_cell(
    effect, level, coef, seeds, log, model=MODEL, sequences_per_set=B
) -> dict:
    truth = EFFECTS[effect]
    tag = list(EFFECTS).index(effect) + 1
    data = [
        simulate(rng_for(tag, level, s), effect, coef, sequences_per_set)
        for s in range(seeds)
    ]
    cells = [(s, sequences(y)) for s, (_, y, _) in enumerate(data)]
    outs, c = _runs(cells, model, log, f"{effect} level {level}")
    rel, covered, times, wrong_names = [], 0, [], Counter()
    for _, out in outs:
        times.append(out["seconds"])
        c["detected"] += out["detected"]
        c["unnamed"] += out["unnamed"]
        c["tentative"] += out["tentative"]
        c["confident"] += bool(out["named"]) and not (
            out["tentative"] or out["partial"]
        )
        cls = classify(out, truth)
        c[cls] += 1
        if cls == "exact":
            # The truth named alone: nothing is left, so the leftover-
            # structure alarm is a false alarm here.
            c["leftover_after_truth"] += out["alarms"]["leftover_structure"]
        if cls in ("wrong", "extra"):
            wrong_names.update(nm for nm in out["named"] if nm != truth)
        if truth in out["coefficients"]:
            value, (lo, hi) = out["coefficients"][truth]
            rel.append((value - coef) / coef)
            covered += lo <= coef <= hi
    n = len(outs)
    abs_rel = np.abs(rel)
    config = {
        "effect": effect,
        "truth": truth,
        "measurement_model": _model_config(model),
    }
    config |= {"snr_target": level, "coefficient": coef}
    return _head(config, n, c, sequences_per_set) | {
        "tentative": rate(c["tentative"], n),
        # A name marked neither tentative nor partial (for an effect outside
        # the library every such name is a wrong, confident one).
        "named_confidently": rate(c["confident"], n),
        "leftover_after_truth_alone": rate(c["leftover_after_truth"], c["exact"]),
        "snr_realised_median": float(np.median([snr for _, _, snr in data])),
        "median_s": statistics.median(times) if times else float("nan"),
        "p90_s": _q(times, 0.9),
        "detection": rate(c["detected"], n),
        **naming_rates(c, n, "named_truth_alone", "correct_naming"),
        "unnamed_structure": rate(c["unnamed"], n),
        "other_names": dict(wrong_names),
        "coef_n": len(rel),
        "coef_rel_error_median_abs": float(np.median(abs_rel)) if rel else None,
        "coef_rel_error_p90_abs": _q(abs_rel, 0.9) if rel else None,
        "coef_rel_error_median_signed": float(np.median(rel)) if rel else None,
        "coef_ci95_coverage": rate(covered, len(rel)),
        "coef_rel_errors": [float(r) for r in rel],
    }


ALARMS = (
    "detected",
    "unnamed_structure",
    "ambiguous",
    "leftover_structure",
    "partial",
)


def null_cell(num, log, noise="gauss", model=MODEL, sequences_per_set=B) -> dict:
    tag = list(NOISES).index(noise)
    cells = []
    for s in range(num):
        # Gaussian null data keep their historical stream (tag 0).
        rng = rng_for(0, 0, s) if tag == 0 else rng_for(100 + tag, 0, s)
        _, y, _ = simulate(rng, "none", 0.0, sequences_per_set, noise=noise)
        cells.append((s, sequences(y)))
    outs, c = _runs(cells, model, log, f"null ({noise})")
    alarm_counts, names, dfs = Counter(), Counter(), Counter()
    pvals, opg_p, times = [], [], []
    for s, out in outs:
        times.append(out["seconds"])
        if np.isfinite(out["p_value"]):
            pvals.append(out["p_value"])
        if np.isfinite(out["opg_p_value"]):
            opg_p.append(out["opg_p_value"])
            c["opg_rej"] += out["opg_p_value"] < 0.05
        dfs[out["df"]] += 1
        for key in ("detected", "heavy_tails", "scale_off_by_2", "unnamed"):
            c[key] += out[key]
        c["named_any"] += bool(out["named"])
        c["named_confident"] += bool(out["named"]) and not (
            out["tentative"] or out["partial"]
        )
        c["alarm"] += any(out["alarms"].values())
        alarm_counts.update(k for k, v in out["alarms"].items() if v)
        names.update(out["named"])
        if out["named"] or out["detected"] or any(out["alarms"].values()):
            log(
                f"  null ({noise}) seed {s}: p={out['p_value']:.3g} verdict: "
                f"{out['verdict']}"
            )
    n = len(outs)
    config = {"effect": "none", "noise": noise, "noise_description": NOISES[noise]}
    config |= {"measurement_model": _model_config(model), "truth": None}
    return _head(config, n, c, sequences_per_set) | {
        "median_s": statistics.median(times) if times else float("nan"),
        "p90_s": _q(times, 0.9),
        "false_discovery": rate(c["named_any"], n),
        "confident_false_discovery": rate(c["named_confident"], n),
        "score_test_rejects": rate(c["detected"], n),
        "unnamed_structure": rate(c["unnamed"], n),
        "alarm_rates": {k: rate(alarm_counts[k], n) for k in ALARMS},
        "any_alarm": rate(c["alarm"], n),
        "noise_check_heavy_tails": rate(c["heavy_tails"], n),
        "noise_check_scale_off_by_2": rate(c["scale_off_by_2"], n),
        "opg_score_test_rejects": rate(c["opg_rej"], len(opg_p)),
        "score_test_df_counts": {str(k): v for k, v in sorted(dfs.items())},
        "p_value_quantiles": {
            str(q): _q(pvals, q) for q in (0.01, 0.05, 0.1, 0.25, 0.5)
        },
        "named_counts": dict(names),
        "p_values": pvals,
        "opg_p_values": opg_p,
    }


def _table(columns: dict, rows) -> str:
    """A markdown table: header -> function of a record giving the cell."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    for r in rows:
        lines.append("| " + " | ".join(f(r) for f in columns.values()) + " |")
    return "\n".join(lines)


def _rate_of(key, sub=None):
    def cell(r):
        v = r.get(sub, {}).get(key) if sub else r.get(key)
        return fmt_rate(v) if v else "–"

    return cell


def _coef(key, fmt):
    return lambda r: format(r[key], fmt) if r["coef_n"] else "–"


EFFECT_COLUMNS = {
    "effect": lambda r: _row_label(r["config"], "truth"),
    "SNR (target / realised)": lambda r: (
        f"{r['config']['snr_target']:.2f} / {r['snr_realised_median']:.3f}"
    ),
    "coef": lambda r: f"{r['config']['coefficient']:.4g}",
    "n": lambda r: str(r["n"]),
    "detected": _rate_of("detection"),
    "correct (alone + set)": _rate_of("correct_naming"),
    "truth alone": _rate_of("named_truth_alone"),
    "truth in set": _rate_of("truth_in_set"),
    "truth + extra": _rate_of("truth_plus_extra"),
    "wrong name": _rate_of("wrong_name"),
    "named confidently": _rate_of("named_confidently"),
    "unnamed structure": _rate_of("unnamed_structure"),
    "abs. rel. err. median": _coef("coef_rel_error_median_abs", ".3f"),
    "abs. rel. err. p90": _coef("coef_rel_error_p90_abs", ".3f"),
    "signed rel. err. median": _coef("coef_rel_error_median_signed", "+.3f"),
    "CI coverage": lambda r: (
        f"{r['coef_ci95_coverage']['rate']:.2f} ({r['coef_n']})" if r["coef_n"] else "–"
    ),
    "leftover alarm after truth alone": _rate_of("leftover_after_truth_alone"),
    "crashes / flagged": lambda r: (
        f"{r.get('crashes', r['failures'])} / {r.get('flagged', '–')}"
    ),
    "median s": lambda r: f"{r['median_s']:.2f}",
}

NULL_COLUMNS = {
    "noise": lambda r: _row_label(r["config"], "noise"),
    "n": lambda r: str(r["n"]),
    "crashes": lambda r: str(r.get("crashes", r["failures"])),
    "flagged": lambda r: str(r.get("flagged", "–")),
    "detected (score test)": _rate_of("score_test_rejects"),
    "unnamed structure": lambda r: fmt_rate(
        r.get("alarm_rates", {}).get("unnamed_structure") or r["unnamed_structure"]
    ),
    "ambiguous": _rate_of("ambiguous", "alarm_rates"),
    "leftover structure": _rate_of("leftover_structure", "alarm_rates"),
    "any alarm": _rate_of("any_alarm"),
    "anything named": _rate_of("false_discovery"),
    "named confidently": _rate_of("confident_false_discovery"),
    "OPG score test rejects": _rate_of("opg_score_test_rejects"),
    "noise check: heavy tails": _rate_of("noise_check_heavy_tails"),
    "noise check: scale off ×2": _rate_of("noise_check_scale_off_by_2"),
    "median s": lambda r: f"{r['median_s']:.2f}",
}


def _row_label(config: dict, key: str) -> str:
    model = config.get("measurement_model", "gaussian")
    if key == "truth" and config.get("truth") is None:
        label = f"{config['effect']} (out of library)"
    else:
        label = str(config.get(key) or "gauss")
    return label if model == "gaussian" else f"{label} ({model} model)"


def _counts(d: dict) -> str:
    return ", ".join(f"{k} ×{v}" for k, v in sorted(d.items()))


def null_lines(null) -> str:
    fd = null["false_discovery"]
    alarms = null.get("alarm_rates", {})
    worst = max([a["rate"] for a in alarms.values()] + [fd["rate"]], default=0.0)
    text = (
        f"- {_row_label(null['config'], 'noise')}: anything named "
        f"{fd['rate']:.3f} (95% CI {fd['ci95'][0]:.3f} – {fd['ci95'][1]:.3f}, n = "
        f"{fd['n']}); largest single alarm rate {worst:.3f}: target ≤ 0.05 "
        + ("met" if worst <= 0.05 else "MISSED")
        + ". Score-test p-value quantiles (uniform would give q): "
        + ", ".join(f"q{k}: {v:.3f}" for k, v in null["p_value_quantiles"].items())
        + "; degrees of freedom: "
        + ", ".join(f"{k}: {v}" for k, v in null["score_test_df_counts"].items())
    )
    if null["named_counts"]:
        text += "; named: " + ", ".join(
            f"{k} ×{v}" for k, v in null["named_counts"].items()
        )
    return text + "."


EFFECTS_TEXT = (
    "SNR: per-step RMS of the effect over the velocity noise std (target: "
    "calibrated; realised: under the effect). `correct` = the truth named alone or "
    "inside a reported ambiguous / equivalence set; `(out of library)`: every name "
    "is wrong. Rates with Wilson 95% intervals; coefficient errors and coverage "
    "over the data sets in which the truth's coefficient was fitted (in brackets)."
)
NULL_TEXT = (
    "Each alarm's rate on null data (target ≤ α = 5% each); `anything named`: a "
    "name, tentative or not; `crashes` must be 0; `OPG`: the score test with the "
    "outer-product covariance, for comparison only; `noise check`: how often the "
    "report said heavy tails, or a refitted noise scale off by more than 2."
)


def report(records, nulls, info, quick) -> str:
    m = info["machine"]
    lines = ["# discover benchmark: Monte Carlo of find / name / add", ""]
    if quick:
        lines += ["**QUICK RUN (a small subset; not the committed figures).**", ""]
    changed = ", ".join(info["dirty"]) or "none under eqsmooth/ or in these studies"
    lines += [
        f"- command: `{info['command']}`",
        f"- machine: {m['cores']} cores, {m['memory']}, {m['cpu']}; "
        f"JAX {m['jax']} ({m['backend']}), Python {m['python']}",
        f"- git: {info['git']} (at start); uncommitted changes: {changed}",
        f"- data: B = {info['B']} sequences × T = {T} steps per data set; "
        f"oscillator k = {SPRING}, process noise std {Q.tolist()}, measurement "
        f"std {R}, first-state prior std {PRIOR.tolist()}",
        f"- library ({len(MODEL.names)} candidates): " + ", ".join(MODEL.names),
        '- decision: score test at α = 0.05 (`covariance="auto"`); naming: '
        "forward selection with the Bonferroni-gated likelihood-ratio test",
        f"- wall time: {info['total_s'] / 60:.1f} min in all; compile (first run "
        f"minus a repeat): {info['compile_s']:.1f} s; `median s` = median wall "
        "time of one find + name + add run",
        "",
        "## Hidden effects",
        "",
        EFFECTS_TEXT,
        "",
        _table(EFFECT_COLUMNS, records),
        "",
    ]
    other = [r for r in records if r["other_names"]]
    if other:
        lines += ["Other names given (in `wrong name` or `truth + extra`):", ""]
        for r in other:
            c = r["config"]
            lines.append(
                f"- {c['truth']} at SNR {c['snr_target']}: {_counts(r['other_names'])}"
            )
        lines.append("")
    if nulls:
        lines += ["## Null data (no missing effect): every alarm's false-alarm rate"]
        lines += ["", NULL_TEXT, "", _table(NULL_COLUMNS, nulls), ""]
        lines += [null_lines(null) for null in nulls] + [""]
    return "\n".join(lines)


def _git():
    """HEAD, and the paths under eqsmooth/ or in these studies with changes."""
    head = git("rev-parse", "--short", "HEAD") or "unknown"
    return head, dirty("eqsmooth", "experiments/discovery_validation")


def render(path, markdown=None) -> None:
    """Re-render the markdown report of a saved run from its JSON."""
    payload = json.loads(Path(path).read_text())
    recs = payload["records"]
    info = {k: payload[k] for k in ("machine", "command", "compile_s", "total_s")}
    info |= {"git": payload["machine"]["git"], "dirty": payload.get("git_dirty", [])}
    info["B"] = recs[0]["config"]["B"] if recs else B
    nulls = [r for r in recs if r["config"]["effect"] == "none"]
    effects = [r for r in recs if r["config"]["effect"] != "none"]
    text = report(effects, nulls, info, payload.get("quick", False))
    write_text(markdown, text) if markdown else print(text)


def parse(argv):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="small subset (CI)")
    parser.add_argument("--seeds", type=int, default=None, help="data sets per cell")
    parser.add_argument("--null", type=int, default=None, help="null data sets")
    parser.add_argument("--effects", nargs="*", default=None, choices=list(EFFECTS))
    parser.add_argument(
        "--null-other", type=int, default=None, help="null sets per other noise"
    )
    parser.add_argument("--noises", nargs="*", default=None, choices=list(NOISES))
    parser.add_argument("--levels", type=float, nargs="*", default=None)
    parser.add_argument("--sequences", type=int, default=B, metavar="B")
    parser.add_argument("--measurement-dof", type=float, default=None, metavar="NU")
    parser.add_argument("--json", default=None, help="write the records here")
    parser.add_argument("--markdown", default=None, help="write the report here")
    parser.add_argument("--render", default=None, metavar="JSON", help="report only")
    args = parser.parse_args(argv)
    if args.sequences < 2:
        parser.error(f"--sequences must be at least 2, got {args.sequences}")
    return args


def main(argv=None):
    args = parse(argv)
    if args.render:
        render(args.render, args.markdown)
        return
    head, changed = _git()  # captured at start
    m = machine()
    m["git"] = head
    command = cli_command()
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

    log(f"git {head}{' (dirty)' if changed else ''}; {m['cores']} cores, {m['cpu']}")
    rounded = {e: {lv: round(c, 6) for lv, c in d.items()} for e, d in coefs.items()}
    log(f"coefficients per SNR level: {rounded}")
    # Compile once (strong drag, a seed outside the Monte Carlo), then repeat
    # the same data set for the steady-state time.
    drag = coefs["drag"][max(levels)]
    warm = sequences(simulate(rng_for(99, 0, 0), "drag", drag, args.sequences)[1])
    first = run_workflow(warm, model)
    again = run_workflow(warm, model)
    compile_s = first["seconds"] - again["seconds"]
    log(
        f"warm-up: first run {first['seconds']:.1f} s, repeat {again['seconds']:.2f} s "
        f"(verdict {again['verdict']!r})"
    )
    records, nulls = [], []

    def save():
        total_s = time.perf_counter() - start
        for r in records + nulls:
            r["compile_s"] = compile_s
        if args.json:
            extra = {"machine": m, "command": command, "git_dirty": changed}
            extra |= {"quick": args.quick, "total_s": total_s, "compile_s": compile_s}
            extra["warmup"] = {k: first[k] for k in ("seconds", "verdict")}
            write_json(args.json, records + nulls, extra=extra)
        info = {"machine": m, "command": command, "git": head, "dirty": changed}
        info |= {"compile_s": compile_s, "total_s": total_s, "B": args.sequences}
        text = report(records, nulls, info, args.quick)
        if args.markdown:
            write_text(args.markdown, text)
        return text

    for noise in noises if num_null else ():
        t0 = time.perf_counter()
        count = num_null
        if noise != "gauss" and args.null_other is not None:
            count = args.null_other
        null = null_cell(count, log, noise, model, args.sequences)
        nulls.append(null)
        alarms = ", ".join(f"{k} {fmt_rate(v)}" for k, v in null["alarm_rates"].items())
        log(
            f"null ({noise}): n={null['n']} crashes {null['crashes']} named "
            f"{fmt_rate(null['false_discovery'])}, alarms {alarms} "
            f"({time.perf_counter() - t0:.0f} s)"
        )
        save()
    for effect in effects if seeds else ():
        for level in levels:
            t0 = time.perf_counter()
            coef = coefs[effect][level]
            rec = effect_cell(effect, level, coef, seeds, log, model, args.sequences)
            records.append(rec)
            log(
                f"{EFFECTS[effect] or effect + ' (out)':17s} SNR {level:<5} "
                f"n={rec['n']} detected {fmt_rate(rec['detection'])} correct "
                f"{fmt_rate(rec['correct_naming'])} wrong {fmt_rate(rec['wrong_name'])}"
                f" ({time.perf_counter() - t0:.0f} s)"
            )
            save()
    print()
    print(save())


if __name__ == "__main__":
    main()
