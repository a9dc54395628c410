"""Following `propose`: sequences to a confident correct name, proposed design
against the default excitation.

`--system oscillator` (the default): the 1-D oscillator of `oscillator.py`
(its model and library) with a hidden effect at the per-step signal-to-noise
ratio `--level`, where 24 sequences released from the prior give a
tentative name. The experiments the user allows (`DESIGNS`): release from
the prior (the default, as the data were measured) or release at 2 or 3
times the prior's velocity spread (signs alternating, positions from the
prior).

`--system driven`: the driven oscillator of `systems.py` (its model, with
the actuator-gain candidate, and its known input force: a sinusoid plus a
random telegraph, `systems._inputs`), the first state from the prior. The
experiments the user allows (`AMPLITUDES`) are the input force they
command: the default excitation, or the same kind of signal scaled by 0.5,
2 or 3. The amplitude is the experimenter's choice (the actuator takes the
command; the first state is not theirs to set here), and it moves the
velocities the friction terms are seen at: RMS velocity 7.9, 8.7, 11.4 and
14.8 for the four. Hidden effects: actuator gain, quadratic drag, Coulomb
friction and a constant force (coefficients from `systems._calibrate1` at
`--level`), and outside the library: an input `saturation` at ±`--shape` or a
`dead zone` of half-width `--shape` (`nonsmooth.py`'s: the force applied is
shape(u), so a larger command amplitude shows more of it; their stand-ins,
actuator gain and sensor scale, are structurally equivalent, which no
design settles), `stiction` of coefficient `--shape` and a periodic force
`sine` of amplitude `--shape` (neither gave a name at 24 sequences in a
first look), and `drag 1.5`, a drag `c · sign(v) |v|^1.5` at the SNR
`--level` (its stand-ins, viscous damping or quadratic drag, have shapes
that a larger data set can check).

Per seed: 24 default sequences go through `find` and `name`; if the verdict
is open, `propose` picks a design from the current fit. Then, for the
default and for the proposed design, fresh sequences of that design are
simulated from the truth at each size of `GRID` and named; the size where
the verdict first is the true effect alone (confident: no set, not
tentative, and on `driven` not partial) is the sequences needed (`None`
past the grid). A confident name that is not the truth is counted as a wrong
name (at any size). `sine` (oscillator), and `saturation`, `dead zone`,
`stiction`, `sine` and `drag 1.5` (driven) are outside the library: every
confident name is wrong. (The oscillator runs of 2026-11-29 counted a
partial verdict as confident; the driven study follows `nonsmooth.py`,
where it is not.)

    python -m experiments.discovery_validation.design --effects drag \\
        --seeds 10 --json results/discover_design/summary.json \\
        --markdown results/discover_design/summary.md
    python -m experiments.discovery_validation.design --system driven \\
        --effects drag coulomb --level 1.0 --seeds 10 \\
        --json results/discover_design/driven.json \\
        --markdown results/discover_design/driven.md
"""

import argparse
import dataclasses
import json
import shlex
import sys
import time
from collections.abc import Callable
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from benchmarks._common import write_json, write_text  # noqa: E402

from . import systems as d2  # noqa: E402
from .nonsmooth import _INPUT, _VELOCITY  # noqa: E402
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


@dataclasses.dataclass(frozen=True)
class Study:
    """One system of the study: its model, hidden effects and designs."""

    name: str
    model: dc.ChainModel
    effects: dict[str, str | None]  # hidden effect -> the truth (None: outside)
    designs: tuple[str, ...]  # the first is the default excitation
    measure: Callable[..., dc.Sequences]  # (rng, effect, coef, design, num)
    template: Callable[..., dc.Sequences]  # (design, num, seed) -> for propose
    coefficients: Callable[[float], dict]  # level -> coefficient per effect
    stream: tuple[int, ...]  # random stream key before the seed
    partial_is_open: bool  # whether a partial verdict is not confident


def _release_template(design: str, num: int, seed: int) -> dc.Sequences:
    return dc.Sequences(np.zeros((num, T, 1)), release(design, num))


def oscillator(shape: float = 0.4) -> Study:
    def coefficients(level):
        return {e: c[level] for e, c in calibrate([level]).items()}

    return Study(
        "oscillator",
        MODEL,
        EFFECTS,
        tuple(DESIGNS),
        measure,
        _release_template,
        coefficients,
        (2026, 1130),
        False,
    )


# The input force the experimenter commands: `systems._inputs` scaled.
AMPLITUDES = {
    "default": 1.0,
    "amplitude x0.5": 0.5,
    "amplitude x2": 2.0,
    "amplitude x3": 3.0,
}
DRIVEN_EFFECTS: dict[str, str | None] = {
    "gain": "actuator gain",
    "drag": "quadratic drag",
    "coulomb": "Coulomb friction",
    "force": "constant force",
    "saturation": None,
    "dead zone": None,
    "stiction": None,
    "sine": None,
    "drag 1.5": None,
}
# Velocity effects outside the library (unit coefficient): `nonsmooth.py`'s
# stiction, and a drag growing as |v|^1.5 (between viscous damping and
# quadratic drag, both candidates: its stand-ins have shapes to check).
_OUTSIDE = {
    "stiction": _VELOCITY["stiction"],
    "drag 1.5": lambda v: -np.sign(v) * np.abs(v) ** 1.5,
}


def measure_driven(rng, effect: str, coef: float, design: str, num: int):
    """`num` sequences of the driven oscillator under input `design`; an
    input `saturation` or `dead zone` of parameter `coef` makes the force
    applied `shape(u)` (`nonsmooth.py`'s shapes); `stiction` of coefficient
    `coef` is `nonsmooth.py`'s, `drag 1.5` is `coef · sign(v) |v|^1.5`,
    `sine` a periodic force of amplitude `coef` (period 8-20 steps and phase
    per sequence, as `oscillator.py`'s)."""
    amplitude = AMPLITUDES[design]
    if effect in _OUTSIDE:

        def extra(t, v):
            return coef * _OUTSIDE[effect](v)

    elif effect == "sine":
        period = rng.uniform(8.0, 20.0, num)
        phase = rng.uniform(0.0, 2 * np.pi, num)

        def extra(t, v):
            return coef * np.sin(2 * np.pi * t / period + phase)

    if effect in _OUTSIDE or effect == "sine":
        options = {"amplitude": amplitude, "extra": extra}
        return d2._simulate1(rng, "none", 0.0, num, **options)
    if DRIVEN_EFFECTS[effect] is None:
        shape = _INPUT[effect]

        def actuator(u):
            return u + shape(u, coef)

        options = {"amplitude": amplitude, "actuator": actuator}
        return d2._simulate1(rng, "none", 0.0, num, **options)
    return d2._simulate1(rng, effect, coef, num, amplitude=amplitude)


def _input_template(design: str, num: int, seed: int) -> dc.Sequences:
    """The design's input force for `propose`: one draw per seed, the same
    signal for every design (only the amplitude differs)."""
    rng = np.random.default_rng(np.random.SeedSequence([2026, 1130, 100, seed, 1]))
    u = d2._inputs(rng, num, AMPLITUDES[design])
    return dc.Sequences(np.zeros((num, T, 1)), np.zeros((num, 2)), inputs=u)


def driven(shape: float = 0.4) -> Study:
    def coefficients(level):
        out = dict(d2._calibrate1(level))
        out |= {e: shape for e, t in DRIVEN_EFFECTS.items() if t is None}
        # `drag 1.5` by its per-step SNR, as `systems._calibrate1` does.
        xs, _ = d2._trajectories1(np.random.default_rng(12345), "none", 0.0, 2000)
        unit = np.sqrt(np.mean(np.square(_OUTSIDE["drag 1.5"](xs[:, :-1, 1]))))
        return out | {"drag 1.5": level * d2.Q1[1] / float(unit)}

    return Study(
        "driven",
        d2.driven().model,
        DRIVEN_EFFECTS,
        tuple(AMPLITUDES),
        measure_driven,
        _input_template,
        coefficients,
        (2026, 1130, 100),
        True,
    )


STUDIES = {"oscillator": oscillator, "driven": driven}


def verdict(data: dc.Sequences, study: Study | None = None) -> tuple:
    model = MODEL if study is None else study.model
    found = dc.find(model, data)
    named = dc.name(found, data)
    open_ = bool(named["tentative"] or named["equivalence_sets"] or named["ambiguous"])
    if study is not None and study.partial_is_open:
        open_ = open_ or bool(named["alarms"].get("partial", False))
    return found, named, open_


def needed(rng, study: Study, effect, coef, design, grid) -> dict:
    """The first size of `grid` at which `design` gives the truth alone
    (every size for an effect outside the library), and the verdicts."""
    truth = study.effects[effect]
    wrong, seen = 0, []
    for n in grid:
        _, named, open_ = verdict(study.measure(rng, effect, coef, design, n), study)
        seen.append({"sequences": n, "named": list(named["named"]), "open": open_})
        if not open_ and named["named"] == [truth]:
            return {"sequences": n, "wrong": wrong, "verdicts": seen}
        if not open_ and named["named"] and truth not in named["named"]:
            wrong += 1
    return {"sequences": None, "wrong": wrong, "verdicts": seen}


def one_seed(study: Study, effect, coef, seed, grid=GRID) -> dict:
    truth = study.effects[effect]
    rng = np.random.default_rng(np.random.SeedSequence([*study.stream, seed]))
    data = study.measure(rng, effect, coef, study.designs[0], grid[0])
    found, named, open_ = verdict(data, study)
    rec = {"seed": seed, "first_verdict": named["verdict"], "open": open_}
    rec["first_named"] = list(named["named"])
    rec["first_wrong"] = bool(
        not open_ and named["named"] and truth not in named["named"]
    )
    if not open_:
        return rec
    templates = {d: study.template(d, 24, seed) for d in study.designs}
    prop = dc.propose(found, named, data, templates, seed=seed)
    rec["proposal"] = prop["proposal"]
    rec["predicted"] = prop["sequences"]
    rec["figures"] = {k: v["sequences_needed"] for k, v in prop["designs"].items()}
    rec["default"] = needed(rng, study, effect, coef, study.designs[0], grid)
    if prop["proposal"] is not None:
        rec["proposed"] = needed(rng, study, effect, coef, prop["proposal"], grid)
    return rec


def summarise(runs: list[dict], grid=GRID, designs=tuple(DESIGNS)) -> dict:
    opened = [r for r in runs if r["open"] and r.get("proposed")]

    def sizes(key):
        return [r[key]["sequences"] or 2 * grid[-1] for r in opened]

    out = {"seeds": len(runs), "open": len(opened)}
    # Every open data set, whether or not a design was proposed; data sets
    # (not sizes) with a confident wrong name.
    asked = [r for r in runs if r["open"]]
    out |= {
        "open_any": len(asked),
        "no_proposal": sum(r.get("proposal") is None for r in asked),
        "first_wrong": sum(r.get("first_wrong", False) for r in runs),
        "sets_wrong_default": sum(r["default"]["wrong"] > 0 for r in asked),
        "sets_wrong_proposed": sum(r["proposed"]["wrong"] > 0 for r in opened),
    }
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
            "proposals": {k: sum(r["proposal"] == k for r in opened) for k in designs},
        }
    return out


def report(records: dict, info: dict) -> str:
    lines = [
        "# Following `propose`: sequences to a confident correct name",
        "",
        f"- command: `{info['command']}`",
        f"- git {info['git'][0]}; level {info['level']}; grid {info['grid']}; "
        f"{info['seconds']:.0f} s",
    ]
    if info.get("system", "oscillator") != "oscillator":
        lines.append(
            f"- system {info['system']}; designs {', '.join(info['designs'])}; "
            f"out-of-library shape parameter {info['shape']}"
        )
    lines += [
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
    if info.get("system", "oscillator") != "oscillator":
        lines += [
            "`open at 24` counts the data sets with a proposal (the table's "
            "rows); below, every open data set. A data set counts once for wrong "
            "names if any size gave one.",
            "",
            "| effect | open at 24 | no design proposed | confident wrong at 24 "
            "(of all seeds) | data sets with a confident wrong name (default / "
            "proposed) | proposals |",
            "|---|---|---|---|---|---|",
        ]
        for effect, rec in records.items():
            s = rec["summary"]
            props = ", ".join(f"{k} ×{v}" for k, v in s.get("proposals", {}).items())
            lines.append(
                f"| {effect} | {s['open_any']} | {s['no_proposal']} | "
                f"{s['first_wrong']} / {s['seeds']} | {s['sets_wrong_default']} / "
                f"{s['sets_wrong_proposed']} | {props} |"
            )
    return "\n".join(lines)


def render(paths, json_path=None, markdown=None) -> str:
    """One report of several saved runs (their effects side by side, each
    run's command listed; runs of one grid and level)."""
    records: dict = {}
    infos = []
    for path in paths:
        payload = json.loads(Path(path).read_text())
        infos.append(payload["info"])
        for effect, rec in payload["records"].items():
            # Runs of one effect over several seed ranges are joined.
            records.setdefault(effect, {"coefficient": rec["coefficient"], "runs": []})
            records[effect]["runs"] += rec["runs"]
    info = dict(infos[0])
    designs = tuple(info.get("designs", DESIGNS))
    for rec in records.values():
        rec["runs"].sort(key=lambda r: r["seed"])
        rec["summary"] = summarise(rec["runs"], tuple(info["grid"]), designs)
    info["command"] = "`; `".join(i["command"] for i in infos)
    info["seconds"] = sum(i["seconds"] for i in infos)
    if json_path:
        write_json(json_path, records, {"info": info, "runs": infos})
    text = report(records, info)
    if markdown:
        write_text(markdown, text)
    return text


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--system", choices=list(STUDIES), default="oscillator")
    parser.add_argument("--effects", nargs="+", default=["drag", "coulomb"])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--level", type=float, default=0.15)
    parser.add_argument("--shape", type=float, default=0.4, help="saturation etc.")
    parser.add_argument("--grid", type=int, nargs="+", default=list(GRID))
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    parser.add_argument(
        "--render", nargs="+", default=None, metavar="JSON", help="merge saved runs"
    )
    args = parser.parse_args(argv)
    if args.render:
        print(render(args.render, args.json, args.markdown))
        return
    study = STUDIES[args.system](args.shape)
    for effect in args.effects:
        if effect not in study.effects:
            parser.error(f"--effects: {effect!r} is not one of {list(study.effects)}")
    grid = tuple(args.grid)
    t0 = time.perf_counter()
    coefs = study.coefficients(args.level)
    records: dict = {}
    # Quoted, so that effect names with spaces (`drag 1.5`) survive a shell.
    command = "python -m experiments.discovery_validation.design "
    command += shlex.join(sys.argv[1:] if argv is None else argv)
    info = {"command": command, "git": _git(), "level": args.level}
    info["grid"] = list(grid)
    if study.name != "oscillator":
        info |= {"system": study.name, "designs": list(study.designs)}
        info["shape"] = args.shape

    def save() -> str:
        info["seconds"] = time.perf_counter() - t0
        if args.json:
            write_json(args.json, records, {"info": info})
        text = report(records, info)
        if args.markdown:
            write_text(args.markdown, text)
        return text

    seeds = range(args.first_seed, args.first_seed + args.seeds)
    for effect in args.effects:
        coef = coefs[effect]
        runs = []
        records[effect] = {"coefficient": coef, "runs": runs}
        for seed in seeds:
            runs.append(one_seed(study, effect, coef, seed, grid))
            print(effect, runs[-1], flush=True)
            records[effect]["summary"] = summarise(runs, grid, study.designs)
            save()
    print(save())


if __name__ == "__main__":
    main()
