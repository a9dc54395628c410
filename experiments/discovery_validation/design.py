"""Following `propose`: sequences to a confident correct name, proposed design
against the default excitation.

The 1-D oscillator of `oscillator.py` (its model and library) with a hidden
effect at the per-step signal-to-noise ratio `--level`, where 24 sequences
released from the prior give a tentative name. The experiments the user
allows (`DESIGNS`): release from the prior (the default, as the data were
measured) or release at 2 or 3 times the prior's velocity spread (signs
alternating, positions from the prior).

Per seed: 24 default sequences go through `find` and `name`; if the verdict
is open, `propose` picks a design from the current fit. Then, for the
default and for the proposed design, fresh sequences of that design are
simulated from the truth at each size of `GRID` and named; the size where
the verdict first is the true effect alone (confident: no set, not
tentative) is the sequences needed (`None` past the grid). A confident name
that is not the truth is counted as a wrong name (at any size). `sine`, a
periodic force, is outside the library: every confident name is wrong.

    python -m experiments.discovery_validation.design --effects drag \\
        --seeds 10 --json results/discover_design/summary.json \\
        --markdown results/discover_design/summary.md
"""

import argparse
import time

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from benchmarks._common import cli_command, write_json, write_text  # noqa: E402

from .oscillator import (  # noqa: E402
    _effect_term,
    _git,
    calibrate,
    EFFECTS,
    MODEL,
    PRIOR,
    Q,
    R,
    SPRING,
    T,
)


DESIGNS = {"default": 1.0, "velocity x2": 2.0, "velocity x3": 3.0}
GRID = (24, 48, 96, 192)


def release(design: str, num: int) -> np.ndarray:
    """First-state means `(num, 2)` of a design: position 0, velocity
    `±factor · PRIOR[1]` (alternating), or 0 for the default."""
    x0 = np.zeros((num, 2))
    factor = DESIGNS[design]
    if factor != 1.0:
        x0[:, 1] = factor * PRIOR[1] * np.where(np.arange(num) % 2, 1.0, -1.0)
    return x0


def measure(rng, effect: str, coef: float, design: str, num: int) -> dc.Sequences:
    """`num` sequences of `design` from the truth (first states drawn from
    the prior about the design's means)."""
    x0 = release(design, num)
    x = x0 + PRIOR * rng.normal(size=(num, 2))
    if effect == "sine":  # outside the library: a periodic force, as oscillator.py
        period = rng.uniform(8.0, 20.0, num)
        phase = rng.uniform(0.0, 2 * np.pi, num)
    xs = []
    for t in range(T):
        xs.append(x.copy())
        p, v = x[:, 0], x[:, 1]
        a = -SPRING * p
        if effect == "sine":
            a = a + coef * np.sin(2 * np.pi * t / period + phase)
        elif effect != "none":
            a = a + coef * _effect_term(effect, v)
        x = np.stack([p + v, v + a], 1) + rng.normal(size=(num, 2)) * Q
    y = np.stack(xs, 1)[..., :1] + R * rng.normal(size=(num, T, 1))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, x0, initial_states=init)


def verdict(data: dc.Sequences) -> tuple:
    found = dc.find(MODEL, data)
    named = dc.name(found, data)
    open_ = bool(named["tentative"] or named["equivalence_sets"] or named["ambiguous"])
    return found, named, open_


def needed(rng, effect, coef, truth, design, grid) -> dict:
    """The first size of `grid` at which `design` gives the truth alone."""
    wrong = 0
    for n in grid:
        _, named, open_ = verdict(measure(rng, effect, coef, design, n))
        if not open_ and named["named"] == [truth]:
            return {"sequences": n, "wrong": wrong}
        if not open_ and named["named"] and truth not in named["named"]:
            wrong += 1
    return {"sequences": None, "wrong": wrong}


def one_seed(effect, coef, seed, grid=GRID) -> dict:
    truth = EFFECTS[effect]
    rng = np.random.default_rng(np.random.SeedSequence([2026, 1130, seed]))
    data = measure(rng, effect, coef, "default", grid[0])
    found, named, open_ = verdict(data)
    rec = {"seed": seed, "first_verdict": named["verdict"], "open": open_}
    if not open_:
        return rec
    templates = {d: dc.Sequences(np.zeros((24, T, 1)), release(d, 24)) for d in DESIGNS}
    prop = dc.propose(found, named, data, templates, seed=seed)
    rec["proposal"] = prop["proposal"]
    rec["predicted"] = prop["sequences"]
    rec["figures"] = {k: v["sequences_needed"] for k, v in prop["designs"].items()}
    rec["default"] = needed(rng, effect, coef, truth, "default", grid)
    if prop["proposal"] is not None:
        rec["proposed"] = needed(rng, effect, coef, truth, prop["proposal"], grid)
    return rec


def summarise(runs: list[dict], grid=GRID) -> dict:
    opened = [r for r in runs if r["open"] and r.get("proposed")]

    def sizes(key):
        return [r[key]["sequences"] or 2 * grid[-1] for r in opened]

    out = {"seeds": len(runs), "open": len(opened)}
    if opened:
        d, p = np.median(sizes("default")), np.median(sizes("proposed"))
        out |= {
            "median_default": float(d),
            "median_proposed": float(p),
            "ratio": float(d / p),
            "censored_default": sum(r["default"]["sequences"] is None for r in opened),
            "censored_proposed": sum(
                r["proposed"]["sequences"] is None for r in opened
            ),
            "wrong_default": sum(r["default"]["wrong"] for r in opened),
            "wrong_proposed": sum(r["proposed"]["wrong"] for r in opened),
            "proposals": {k: sum(r["proposal"] == k for r in opened) for k in DESIGNS},
        }
    return out


def report(records: dict, info: dict) -> str:
    lines = [
        "# Following `propose`: sequences to a confident correct name",
        "",
        f"- command: `{info['command']}`",
        f"- git {info['git'][0]}; level {info['level']}; grid {info['grid']}; "
        f"{info['seconds']:.0f} s",
        "",
        "| effect | seeds | open at 24 | median default | median proposed | ratio "
        "| past the grid (default / proposed) | wrong names (default / proposed) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for effect, rec in records.items():
        s = rec["summary"]
        if "ratio" not in s:
            lines.append(f"| {effect} | {s['seeds']} | {s['open']} | | | | | |")
            continue
        lines.append(
            f"| {effect} | {s['seeds']} | {s['open']} | {s['median_default']:.0f} | "
            f"{s['median_proposed']:.0f} | {s['ratio']:.2f} | "
            f"{s['censored_default']} / {s['censored_proposed']} | "
            f"{s['wrong_default']} / {s['wrong_proposed']} |"
        )
    lines += [
        "",
        f"Sizes past the grid count as {2 * info['grid'][-1]} in the medians.",
    ]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--effects", nargs="+", default=["drag", "coulomb"])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--level", type=float, default=0.15)
    parser.add_argument("--grid", type=int, nargs="+", default=list(GRID))
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    grid = tuple(args.grid)
    t0 = time.perf_counter()
    coefs = calibrate([args.level])
    records: dict = {}
    info = {"command": cli_command(), "git": _git(), "level": args.level}
    info["grid"] = list(grid)

    def save() -> str:
        info["seconds"] = time.perf_counter() - t0
        if args.json:
            write_json(args.json, records, {"info": info})
        text = report(records, info)
        if args.markdown:
            write_text(args.markdown, text)
        return text

    for effect in args.effects:
        coef = coefs[effect][args.level]
        runs = []
        records[effect] = {"coefficient": coef, "runs": runs}
        for seed in range(args.seeds):
            runs.append(one_seed(effect, coef, seed, grid))
            print(effect, runs[-1], flush=True)
            records[effect]["summary"] = summarise(runs, grid)
            save()
    print(save())


if __name__ == "__main__":
    main()
