"""Localisation as a measured output: where `find(..., localise=True)` says a
missing effect acts, against where it does.

Effects that act only in a region of one state or input, on the three
systems of `nonsmooth.py` (B = 24 sequences × T = 40 steps):

- `oscillator`, `contact`: a contact spring beyond p = 10,
  `v' += −k (p − 10)₊` (region: x0 ≥ 10, on the velocity equation x1').
- `two_axis`, `contact`: the same on the x axis only (region x0 ≥ 10, on
  x2').
- `driven`, `weak above 0.3`: the actuator loses force above u = 0.3,
  `v' += −c (u − 0.3)₊` (region u0 ≥ 0.3, on x1').

`find` reports the block (variable, equation) with the smallest p-value and
its region (the intervals nearest to the knots of the hats that score
beyond a Bonferroni bound). Scored over the true states (inputs) of each
data set: the right variable and equation, and the precision, recall and
F1 of the flagged region against the true one (0 when the variable is
wrong). Null data (no effect): how often a region is reported at all (only
after a detection, so at most the decision test's level, α/2).

    python -m experiments.discovery_validation.localise --seeds 20 --null 100 \\
        --json results/discovery_validation/localise.json \\
        --markdown results/discovery_validation/localise.md
"""

import argparse
import time

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402

from . import nonsmooth as dn  # noqa: E402
from ._run import log, resume, run_info, run_lines, saver  # noqa: E402
from .oscillator import fmt_rate, rate  # noqa: E402


# system -> (effect, coefficient, true variable, true equation, region start)
CELLS = {
    "oscillator": ("contact", 0.02, "x0", "x1'", dn.CONTACT_AT),
    "two_axis": ("contact", 0.02, "x0", "x2'", dn.CONTACT_AT),
    "driven": ("weak above 0.3", 0.6, "u0", "x1'", 0.3),
}


def _inside(values: np.ndarray, region) -> np.ndarray:
    mask = np.zeros(values.shape, bool)
    for lo, hi in region:
        lo = -np.inf if lo is None else lo
        hi = np.inf if hi is None else hi
        mask |= (values >= lo) & (values <= hi)
    return mask


def cell(plant, effect, coef, truth, seeds, log) -> dict:
    variable, equation, start = truth if effect else (None, None, None)
    key = [2026, 37, 5, plant.tag, dn._TAGS.get(effect, 0)]
    c = {"detected": 0, "located": 0, "variable": 0, "block": 0}
    f1s, precisions, recalls, times = [], [], [], []
    for s in range(seeds):
        rng = np.random.default_rng(np.random.SeedSequence(key + [s]))
        xs, u, _ = plant.trajectories(rng, effect, coef, dn.B)
        y = xs[..., : plant.axes] + plant.r * rng.normal(
            size=xs[..., : plant.axes].shape
        )
        init = np.concatenate([y, np.zeros_like(y)], -1)
        data = dc.Sequences(
            y, np.zeros((dn.B, 2 * plant.axes)), inputs=u, initial_states=init
        )
        t0 = time.perf_counter()
        found = dc.find(plant.model, data, localise=True)
        times.append(time.perf_counter() - t0)
        c["detected"] += bool(found["detected"])
        where = found.get("where") or {}
        if not where.get("tested"):
            continue
        c["located"] += 1
        best = where["where"]
        if effect is None:
            log(f"  null seed {s}: region {best['block']} {best['region']}")
            continue
        c["variable"] += best["variable"] == variable
        c["block"] += (best["variable"], best["equation"]) == (variable, equation)
        if best["variable"] == variable:
            src = xs[..., int(variable[1:])] if variable[0] == "x" else u[..., 0]
            flagged = _inside(src, best["region"])
            true = src >= start
            hit = float(np.sum(flagged & true))
            precision = hit / max(float(np.sum(flagged)), 1.0)
            recall = hit / max(float(np.sum(true)), 1.0)
        else:
            precision = recall = 0.0
        f1 = 2 * precision * recall / max(precision + recall, 1e-12)
        f1s.append(f1)
        precisions.append(precision)
        recalls.append(recall)
        log(
            f"  {effect} seed {s}: {best['block']} {best['region']} "
            f"F1 {f1:.2f} (P {precision:.2f}, R {recall:.2f})"
        )
    rec = {
        "system": plant.name,
        "effect": effect or "none",
        "coefficient": coef,
        "truth": None
        if effect is None
        else {"variable": variable, "equation": equation, "from": start},
        "n": seeds,
        "detected": rate(c["detected"], seeds),
        "region_reported": rate(c["located"], seeds),
        "median_s": float(np.median(times)),
    }
    if effect is not None:
        rec |= {
            "right_variable": rate(c["variable"], seeds),
            "right_variable_and_equation": rate(c["block"], seeds),
            "f1_median": float(np.median(f1s)) if f1s else None,
            "f1_mean": float(np.mean(f1s)) if f1s else None,
            "precision_median": float(np.median(precisions)) if f1s else None,
            "recall_median": float(np.median(recalls)) if f1s else None,
            "f1": f1s,
        }
    return rec


def report(records, info) -> str:
    lines = [
        "# discover benchmark: localisation of region-limited effects",
        "",
        *run_lines(info),
        "",
        "| system | effect | true region | n | detected | right variable and "
        "equation | F1 median (mean) | precision / recall median | median s |",
        "|" + "---|" * 9,
    ]
    for r in records:
        if r["truth"] is None:
            continue
        t = r["truth"]
        f1 = (
            "–"
            if r["f1_median"] is None
            else f"{r['f1_median']:.2f} ({r['f1_mean']:.2f})"
        )
        pr = (
            "–"
            if r["f1_median"] is None
            else f"{r['precision_median']:.2f} / {r['recall_median']:.2f}"
        )
        lines.append(
            f"| {r['system']} | {r['effect']} | {t['variable']} ≥ {t['from']:g} on "
            f"{t['equation']} | {r['n']} | {fmt_rate(r['detected'])} | "
            f"{fmt_rate(r['right_variable_and_equation'])} | {f1} | {pr} | "
            f"{r['median_s']:.2f} |"
        )
    lines += ["", "Null data (no effect): a region reported at all:", ""]
    for r in records:
        if r["truth"] is None:
            lines.append(
                f"- {r['system']}: {fmt_rate(r['region_reported'])} of {r['n']} "
                f"(detected {fmt_rate(r['detected'])})"
            )
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--systems", nargs="+", default=list(CELLS))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--null", type=int, default=100)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.systems, args.seeds, args.null = ["oscillator"], 1, 1
    t0 = time.perf_counter()
    records, _, done = resume(args.json, lambda r: (r["system"], r["effect"]))
    info = run_info()
    save = saver(args, records, info, report, t0)

    plants = dn.plants()
    for name in args.systems:
        effect, coef, variable, equation, start = CELLS[name]
        for eff, seeds in ((effect, args.seeds), (None, args.null)):
            if (name, eff or "none") in done or seeds < 1:
                continue
            log(f"{name}: {eff or 'null'}")
            truth = (variable, equation, start)
            records.append(cell(plants[name], eff, coef, truth, seeds, log))
            save()
    save()
    print(report(records, info))


if __name__ == "__main__":
    main()
