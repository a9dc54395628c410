"""Monte Carlo of the discrepancy workflow on a two-axis, two-sensor system.

Data: two axes joined by a coupling spring, state (p_x, p_y, v_x, v_y),
p' = p + v, v' = v − k p − k_c (p − p_swapped) + effect + noise (k = 0.05,
k_c = 0.02, process noise std (0.05, 0.05, 0.5, 0.5)), each position
measured by its own sensor with std 1, first state from the model's prior
N(0, diag(20², 20², 4², 4²)); B = 24 sequences × T = 40 steps per data set.
The candidate library is the whole `mechanical_library` of two axes with
two sensors: constant force and sensor bias, scale and delay per axis or
channel, and isotropic damping, drag, Coulomb friction, cubic damping,
spring error and cubic stiffness (14 candidates, every one a distractor).

Hidden effects, each at a per-step signal-to-noise ratio (the RMS of the
effect's velocity increment over nominal trajectories, over the velocity
noise 0.5; for the force on y, over that axis): isotropic quadratic drag,
and a constant force on the y axis only (which the springs make equivalent
to a bias of the y sensor; that set counts as correct, a name on the x axis
as wrong). Null data: no effect. Outcomes and rates as in
`benchmarks/discover.py` (Wilson 95% intervals).

    python benchmarks/discover_two_axis.py --seeds 10 --null 40 \
        --json benchmarks/results/discover_two_axis.json \
        --markdown benchmarks/results/discover_two_axis.md
"""

import argparse
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import machine, write_json  # noqa: E402
from discover import (  # noqa: E402
    _git,
    classify,
    fmt_rate,
    guarded_run,
    rate,
    run_workflow,
)

import eqsmooth.discover as dc  # noqa: E402


B, T = 24, 40
SPRING, COUPLING = 0.05, 0.02
Q = np.array([0.05, 0.05, 0.5, 0.5])
R = np.array([1.0, 1.0])
PRIOR = np.array([20.0, 20.0, 4.0, 4.0])
EFFECTS = {"drag": "quadratic drag", "force_y": "constant force [y]"}


def _dyn(x, u, params):
    k, kc = params
    p, v = x[:2], x[2:]
    return jnp.concatenate([p + v, v - k * p - kc * (p - p[::-1])])


def _meas(x, params):
    return x[:2]


MODEL = dc.ChainModel(
    _dyn,
    _meas,
    (jnp.asarray(SPRING), jnp.asarray(COUPLING)),
    Q,
    R,
    PRIOR,
    dc.mechanical_library(
        [0, 1],
        [2, 3],
        4,
        measured_positions=[0, 1],
        axis_names=["x", "y"],
        coulomb_eps=1.0,
    ),
)


def _increment(effect: str, v: np.ndarray) -> np.ndarray:
    """Velocity increment `(…, 2)` of a unit coefficient."""
    if effect == "drag":
        return -v * np.abs(v)
    if effect == "force_y":
        return np.broadcast_to(np.array([0.0, 1.0]), v.shape)
    return np.zeros_like(v)


def simulate(rng, effect: str, coef: float, num: int = B):
    x = rng.normal(size=(num, 4)) * PRIOR
    xs = []
    for _ in range(T):
        xs.append(x)
        p, v = x[:, :2], x[:, 2:]
        a = -SPRING * p - COUPLING * (p - p[:, ::-1]) + coef * _increment(effect, v)
        x = np.concatenate([p + v, v + a], 1) + rng.normal(size=(num, 4)) * Q
    xs = np.stack(xs, 1)
    y = xs[..., :2] + R * rng.normal(size=(num, T, 2))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((num, 4)), initial_states=init)


def calibrate(level: float) -> dict:
    """Coefficient per effect for a per-step SNR `level` (nominal states)."""
    rng = np.random.default_rng(12345)
    x = rng.normal(size=(2000, 4)) * PRIOR
    vs = []
    for _ in range(T):
        p, v = x[:, :2], x[:, 2:]
        vs.append(v)
        a = -SPRING * p - COUPLING * (p - p[:, ::-1])
        x = np.concatenate([p + v, v + a], 1) + rng.normal(size=(2000, 4)) * Q
    v = np.stack(vs, 1)[:, :-1]
    drag = float(np.sqrt(np.mean(np.square(_increment("drag", v))))) / Q[2]
    return {"drag": level / drag, "force_y": level * Q[3]}


def cell(effect: str | None, coef: float, seeds: int, tag: int, log) -> dict:
    truth = EFFECTS.get(effect)
    counts = {k: 0 for k in ("exact", "set", "extra", "wrong", "none")}
    detected = unnamed = flagged = crashes = alarm = named_any = 0
    coefs, times, names = [], [], {}
    for s in range(seeds):
        rng = np.random.default_rng(np.random.SeedSequence([2026, 77, tag, s]))
        data = simulate(rng, effect or "none", coef)
        out = guarded_run(data, MODEL, log, f"{effect} seed {s}")
        if out is None:
            crashes += 1
            continue
        times.append(out["seconds"])
        flagged += bool(out["flags"])
        detected += out["detected"]
        unnamed += out["unnamed"]
        alarm += any(out["alarms"].values())
        named_any += bool(out["named"])
        for nm in out["named"]:
            names[nm] = names.get(nm, 0) + 1
        if truth is not None:
            counts[classify(out, truth)] += 1
            if truth in out["coefficients"]:
                coefs.append(out["coefficients"][truth][0])
        elif out["named"] or any(out["alarms"].values()):
            log(f"  null seed {s}: verdict {out['verdict']}")
    n = seeds - crashes
    rec = {
        "effect": effect or "none",
        "truth": truth,
        "coefficient": coef,
        "n": n,
        "crashes": crashes,
        "flagged": flagged,
        "detected": rate(detected, n),
        "unnamed_structure": rate(unnamed, n),
        "any_alarm": rate(alarm, n),
        "named_counts": names,
        "median_s": float(np.median(times)) if times else float("nan"),
    }
    if truth is not None:
        rec.update(
            {
                "truth_alone": rate(counts["exact"], n),
                "truth_in_set": rate(counts["set"], n),
                "correct": rate(counts["exact"] + counts["set"], n),
                "truth_plus_extra": rate(counts["extra"], n),
                "wrong_name": rate(counts["wrong"], n),
                "nothing_named": rate(counts["none"], n),
                "coefficient_median_rel_error": float(
                    np.median(np.abs(np.asarray(coefs) - coef) / coef)
                )
                if coefs
                else None,
            }
        )
    else:
        rec["anything_named"] = rate(named_any, n)
    return rec


def report(records, info) -> str:
    lines = [
        "# discover benchmark: two coupled axes, two sensors",
        "",
        f"- command: `{info['command']}`",
        f"- machine: {info['machine']['cores']} cores, {info['machine']['cpu']}; "
        f"JAX {info['machine']['jax']}",
        f"- git: {info['git']}"
        + (f"; uncommitted: {', '.join(info['dirty'])}" if info["dirty"] else ""),
        f"- library ({len(MODEL.names)} candidates): " + ", ".join(MODEL.names),
        f"- wall time {info['total_s'] / 60:.1f} min; first run (compile) "
        f"{info['first_s']:.0f} s",
        "",
        "| data | coef | n | detected | correct (alone + set) | truth alone | "
        "truth in set | truth + extra | wrong name | median abs. rel. coef. error "
        "| any alarm | crashes / flagged | median s |",
        "|" + "---|" * 13,
    ]
    for r in records:
        if r["truth"] is None:
            continue
        lines.append(
            f"| {r['truth']} | {r['coefficient']:.4g} | {r['n']} | "
            f"{fmt_rate(r['detected'])} | {fmt_rate(r['correct'])} | "
            f"{fmt_rate(r['truth_alone'])} | {fmt_rate(r['truth_in_set'])} | "
            f"{fmt_rate(r['truth_plus_extra'])} | {fmt_rate(r['wrong_name'])} | "
            + (
                f"{r['coefficient_median_rel_error']:.3f}"
                if r["coefficient_median_rel_error"] is not None
                else "–"
            )
            + f" | {fmt_rate(r['any_alarm'])} | {r['crashes']} / {r['flagged']} | "
            f"{r['median_s']:.2f} |"
        )
    for r in records:
        if r["truth"] is None:
            lines += [
                "",
                f"Null data (n = {r['n']}): detected {fmt_rate(r['detected'])}, "
                f"unnamed structure {fmt_rate(r['unnamed_structure'])}, any alarm "
                f"{fmt_rate(r['any_alarm'])}, anything named "
                f"{fmt_rate(r['anything_named'])}; crashes {r['crashes']}, flagged "
                f"{r['flagged']}; names given: {r['named_counts'] or 'none'}.",
            ]
    for r in records:
        if r["truth"] is not None and r["named_counts"]:
            lines.append(f"- names given with {r['truth']}: {r['named_counts']}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--null", type=int, default=40)
    parser.add_argument("--level", type=float, default=0.4)
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    head, dirty = _git()
    m = machine()
    start = time.perf_counter()
    coefs = calibrate(args.level)
    print(f"git {head}; coefficients at SNR {args.level}: {coefs}", flush=True)
    t0 = time.perf_counter()
    run_workflow(simulate(np.random.default_rng(99), "drag", coefs["drag"]), MODEL)
    first_s = time.perf_counter() - t0
    records = []

    def save():
        info = {
            "command": " ".join([Path(sys.executable).name] + sys.argv),
            "machine": m,
            "git": head,
            "dirty": dirty,
            "total_s": time.perf_counter() - start,
            "first_s": first_s,
        }
        if args.json:
            write_json(args.json, records, extra=info)
        text = report(records, info)
        if args.markdown:
            Path(args.markdown).write_text(text)
        return text

    for tag, (effect, count) in enumerate(
        [(None, args.null), ("drag", args.seeds), ("force_y", args.seeds)]
    ):
        t0 = time.perf_counter()
        coef = 0.0 if effect is None else coefs[effect]
        rec = cell(effect, coef, count, tag, print)
        records.append(rec)
        print(f"{rec['effect']}: done in {time.perf_counter() - t0:.0f} s", flush=True)
        save()
    print(save())


if __name__ == "__main__":
    main()
