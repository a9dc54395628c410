"""Monte Carlo of the naming safeguards: effects outside the library must not
get a confident name, effects inside it must keep theirs.

Three systems (B = 24 sequences × T = 40 steps per data set, the nominal
models and libraries of `oscillator.py` and `systems.py`):

- `driven`: the oscillator driven by a known input force u (sinusoid plus
  random telegraph, |u| ≤ 1); 11 candidates.
- `oscillator`: the undriven oscillator of `oscillator.py`; 10 candidates.
- `two_axis`: two coupled axes with two sensors; 14 candidates.

Hidden effects outside every library (nonsmooth): on the driven system's
actuator an input `saturation` at ±L, a `dead zone` of half-width w and a
`backlash` (play) g, each in full (the force applied is `shape(u)` instead
of `u`); on the velocity of the other two a `stiction` (Stribeck) friction
`−c · sign(v) · exp(−(v/0.5)²)`, strong only near rest. Each is set by its
shape parameter (`--shapes`), and reported with two per-step SNRs: the RMS
of its velocity increments over the velocity noise std, and the same for
what remains after a least-squares fit of the library's dynamics candidates
at the true states (the part no candidate can mimic; on this input a
saturation or dead zone never leaves more than 0.19). Hidden effects inside
the library (set by their SNR, `--in-library-level`): actuator gain,
quadratic drag, Coulomb friction and a constant force (driven); viscous
damping, quadratic drag and Coulomb friction (oscillator); isotropic
quadratic drag (two axes). Null data: no effect, measurement noise of the
assumed std and of twice it.

A name is *confident* when the verdict marks it neither tentative (the named
model fails its innovation diagnostics) nor partial (it fails the adequacy
test of `eqsmooth.discover.name`). For an out-of-library effect every
confident name is wrong. Rates with Wilson 95% intervals.

    python -m experiments.discovery_validation.nonsmooth --quick
    python -m experiments.discovery_validation.nonsmooth --seeds 20 --null 200 \\
        --json results/discovery_validation/nonsmooth.json \\
        --markdown results/discovery_validation/nonsmooth.md

The run saves after every cell and, given the same `--json`, skips the cells
already there (it can be stopped and resumed).
"""

import argparse
import math
import time
from collections import Counter

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402

from . import oscillator as d1, systems as d2  # noqa: E402
from ._run import cell_key, cell_runs, log, resume, run_info, run_lines, saver, stream  # noqa: E402
from .oscillator import classify, fmt_rate, rate  # noqa: E402


B, T = 24, 40
STICTION_SPEED = 0.5


def _backlash(u: np.ndarray, gap: float) -> np.ndarray:
    out, y = np.zeros_like(u), u[:, 0].copy()
    for t in range(u.shape[1]):
        y = np.clip(y, u[:, t] - gap, u[:, t] + gap)
        out[:, t] = y
    return out


# Input effects: (input u, shape parameter w) -> the increment
# `shape(u, w) − u` (the full nonlinearity: the force applied is shape(u, w));
# the gain error is c·u.
_INPUT = {
    "saturation": lambda u, w: np.clip(u, -w, w) - u,
    "dead zone": lambda u, w: np.sign(u) * np.maximum(np.abs(u) - w, 0.0) - u,
    "backlash": lambda u, w: _backlash(u, w) - u,
    "actuator gain": lambda u, c: c * u,
    # Regional (`localise.py`): the actuator loses force
    # above u = 0.3.
    "weak above 0.3": lambda u, c: -c * np.maximum(u - 0.3, 0.0),
}
# Position effects on the first axis only (`localise.py`):
# a contact spring beyond p = 10.
CONTACT_AT = 10.0
_POSITION = {"contact": lambda p, c: -c * np.maximum(p - CONTACT_AT, 0.0)}
# Velocity effects: coefficient times a unit shape.
_VELOCITY = {
    "stiction": lambda v: -np.sign(v) * np.exp(-((v / STICTION_SPEED) ** 2)),
    "viscous damping": lambda v: -v,
    "quadratic drag": lambda v: -v * np.abs(v),
    "Coulomb friction": lambda v: -np.tanh(v / d1.COULOMB_EPS),
    "constant force": np.ones_like,
}
OUT_OF_LIBRARY = ("saturation", "dead zone", "backlash", "stiction")
# Stable stream tags (str hashes change between processes).
_TAGS = {
    name: i + 1
    for i, name in enumerate(
        ["saturation", "dead zone", "backlash", "actuator gain", *_VELOCITY]
        + ["weak above 0.3", *_POSITION]
    )
}


class Plant:
    """One system's nominal dynamics, noise and candidate library."""

    def __init__(self, name, model, axes, q, r, prior, driven, effects, tag):
        self.name, self.model, self.axes = name, model, axes
        self.q, self.r, self.prior = np.asarray(q), float(r), np.asarray(prior)
        self.driven, self.effects, self.tag = driven, effects, tag

    def acceleration(self, p: np.ndarray) -> np.ndarray:
        a = -d2.SPRING * p
        if self.axes == 2:
            a = a - d2.COUPLING * (p - p[:, ::-1])
        return a

    def trajectories(self, rng, effect: str | None, coef: float, num: int):
        """States `(num, T, 2·axes)`, inputs `(num, T, 1)` and the effect's
        increments (for the realised SNR)."""
        n = 2 * self.axes
        u = d2._inputs(rng, num) if self.driven else np.zeros((num, T, 1))
        extra = None
        if effect in _INPUT:
            extra = _INPUT[effect](u[..., 0], coef)
        x = rng.normal(size=(num, n)) * self.prior
        xs, incs = [], []
        for t in range(T):
            xs.append(x)
            p, v = x[:, : self.axes], x[:, self.axes :]
            a = self.acceleration(p)
            if self.driven:
                a = a + u[:, t]
            inc = np.zeros_like(v)
            if extra is not None:
                inc = np.broadcast_to(extra[:, t, None], v.shape)
            elif effect in _VELOCITY:
                inc = coef * _VELOCITY[effect](v)
            elif effect in _POSITION:
                inc = np.zeros_like(v)
                inc[:, 0] = _POSITION[effect](p[:, 0], coef)
            incs.append(inc)
            x = np.concatenate([p + v, v + a + inc], 1)
            x = x + rng.normal(size=(num, n)) * self.q
        return np.stack(xs, 1), u, np.stack(incs[:-1], 1)

    def simulate(self, rng, effect, coef, noise: float = 1.0, num: int = B):
        xs, u, incs = self.trajectories(rng, effect, coef, num)
        y = xs[..., : self.axes]
        y = y + noise * self.r * rng.normal(size=y.shape)
        init = np.concatenate([y, np.zeros_like(y)], -1)
        data = dc.Sequences(
            y, np.zeros((num, 2 * self.axes)), inputs=u, initial_states=init
        )
        snr = float(np.sqrt(np.mean(np.square(incs)))) / self.q[self.axes]
        return data, snr

    def beyond_library(self, effect: str, coef: float) -> tuple[float, float]:
        """Per-step SNR of the effect (RMS of its velocity increments over the
        velocity noise std) and of what remains of it after a least-squares
        fit of the library's dynamics candidates at the true states (the
        part no candidate can mimic; measurement candidates left out)."""
        xs, u, incs = self.trajectories(np.random.default_rng(54321), effect, coef, 400)
        x = xs[:, :-1].reshape(-1, xs.shape[-1])
        uu = u[:, :-1].reshape(-1, u.shape[-1])
        cols = []
        for c in self.model.candidates:
            if c.target == "dynamics":
                f = np.asarray(jax.vmap(c.feature)(x, uu))[:, self.axes :]
                cols.append(f.reshape(-1))
        y = incs.reshape(-1)
        A = np.stack(cols, 1)
        rest = y - A @ np.linalg.lstsq(A, y, rcond=None)[0]
        q = self.q[self.axes]
        return float(np.sqrt(np.mean(y * y))) / q, float(np.sqrt(np.mean(rest**2))) / q

    def coefficient(self, effect: str, level: float) -> float:
        """Coefficient of an in-library effect (a velocity effect or the
        actuator gain) giving the per-step SNR `level` on nominal
        trajectories."""
        xs, u, _ = self.trajectories(np.random.default_rng(12345), None, 0.0, 2000)
        if effect in _VELOCITY:
            unit = _VELOCITY[effect](xs[:, :-1, self.axes :])
        else:
            unit = _INPUT[effect](u[..., 0], 1.0)[:, :-1]
        return level / (float(np.sqrt(np.mean(np.square(unit)))) / self.q[self.axes])


def plants() -> dict[str, Plant]:
    r1 = d2.R1
    return {
        "driven": Plant(
            "driven",
            d2.driven().model,
            1,
            d2.Q1,
            r1,
            d2.PRIOR1,
            True,
            ("saturation", "dead zone", "backlash")
            + ("actuator gain", "quadratic drag", "Coulomb friction", "constant force"),
            1,
        ),
        "oscillator": Plant(
            "oscillator",
            d1.MODEL,
            1,
            d1.Q,
            d1.R,
            d1.PRIOR,
            False,
            ("stiction", "viscous damping", "quadratic drag", "Coulomb friction"),
            2,
        ),
        "two_axis": Plant(
            "two_axis",
            d2.two_axis().model,
            2,
            d2.Q2,
            d2.R2[0],
            d2.PRIOR2,
            False,
            ("stiction", "quadratic drag"),
            3,
        ),
    }


def cell(plant: Plant, effect, level, seeds, log, noise=1.0, num=B) -> dict:
    """`seeds` data sets of `num` sequences of one (system, effect, level)
    or null cell."""
    out_of_library = effect in OUT_OF_LIBRARY
    # Out-of-library effects are set by their shape parameter (`level` is
    # it); in-library ones by their per-step SNR.
    coef = (
        level if out_of_library else plant.coefficient(effect, level) if effect else 0.0
    )
    snr_total, snr_beyond = plant.beyond_library(effect, coef) if effect else (0, 0)
    truth = None if (effect is None or out_of_library) else effect
    c, names, alarms, times, snrs = Counter(), Counter(), Counter(), [], []
    separate: list[float] = []
    for s, out, snr in cell_runs(
        stream(plant.tag, _TAGS.get(effect, 0), level, noise, num),
        range(seeds),
        lambda rng: plant.simulate(rng, effect, coef, noise, num),
        plant.model,
        log,
        f"{plant.name} {effect}",
        c,
    ):
        snrs.append(snr)
        times.append(out["seconds"])
        kind = tally(out, truth, c, names, alarms)
        if kind == "set":
            separate += out.get("sequences_to_separate", [])
        if effect is None or out_of_library:
            if out["named"]:
                log(f"  {plant.name} {effect} seed {s}: {out['verdict']}")
    n = seeds - c["crashes"]
    rec = {
        "system": plant.name,
        "effect": effect or "none",
        "out_of_library": out_of_library,
        "truth": truth,
        "snr_target": None if out_of_library else level,
        "parameter": level if out_of_library else None,
        "snr_total": snr_total,
        "snr_beyond_library": snr_beyond,
        "snr_realised_median": float(np.median(snrs)) if snrs else None,
        "measurement_noise_factor": noise,
        "sequences": num,
        "coefficient": coef,
        "n": n,
        "crashes": c["crashes"],
        "flagged": c["flagged"],
        **outcome_rates(c, n, names, alarms, truth),
        "median_s": float(np.median(times)) if times else None,
        # Where the truth was reported in a set: the sequences (of this
        # length) its verdict said would separate the set (inf: none given).
        "sets_sequences_to_separate": [v if np.isfinite(v) else None for v in separate],
    }
    return rec


def tally(out: dict, truth: str | None, c: Counter, names, alarms) -> str | None:
    """Count one workflow run (`guarded_run`'s dict) into the counters `c`,
    the names given (`names`) and the alarms raised (`alarms`); returns its
    `classify` kind against `truth` (None without one)."""
    c["flagged"] += bool(out["flags"])
    c["detected"] += out["detected"]
    c["named"] += bool(out["named"])
    c["partial"] += out["partial"]
    c["tentative"] += out["tentative"]
    c["shape_unchecked"] += out.get("shape_unchecked", False)
    confident = bool(out["named"]) and not (out["tentative"] or out["partial"])
    c["confident"] += confident
    c["alarm"] += any(out["alarms"].values())
    alarms.update(k for k, v in out["alarms"].items() if v)
    names.update(nm for group in (out["sets"] or [out["named"]]) for nm in group)
    if truth is None:
        return None
    kind = classify(out, truth)
    c[kind] += 1
    c["alone_confident"] += kind == "exact" and confident
    return kind


def outcome_rates(c: Counter, n: int, names, alarms, truth: str | None) -> dict:
    """The rates of a cell from `tally`'s counts over its `n` runs."""
    out = {
        "detected": rate(c["detected"], n),
        "anything_named": rate(c["named"], n),
        "named_confidently": rate(c["confident"], n),
        "partial": rate(c["partial"], n),
        "tentative": rate(c["tentative"], n),
        "shape_unchecked": rate(c["shape_unchecked"], n),
        "any_alarm": rate(c["alarm"], n),
        "alarms": {k: rate(alarms[k], n) for k in sorted(alarms)},
        "names": dict(names),
    }
    if truth is not None:
        out |= {
            "truth_alone": rate(c["exact"], n),
            "truth_alone_confident": rate(c["alone_confident"], n),
            "truth_in_set": rate(c["set"], n),
            "truth_plus_extra": rate(c["extra"], n),
            "wrong_name": rate(c["wrong"], n),
        }
    return out


def report(records: list[dict], info: dict) -> str:
    lines = [
        "# discover benchmark: out-of-library nonsmooth effects, in-library "
        "effects and null data on three systems",
        "",
        *run_lines(info),
        "- `confident` = a name the verdict marks neither tentative nor partial; "
        "for an out-of-library effect every such name is wrong. `shape unchecked` "
        "= tentative because the named term is too weak for the adequacy test to "
        "see a 20% departure from its shape (`name`'s shape check).",
        "",
        "## Out-of-library effects (the right answer: no confident name)",
        "",
        "| system | effect | parameter | SNR total / beyond the library | "
        "sequences | n | "
        "detected | anything named "
        "| named confidently | partial | tentative | of which shape unchecked "
        "| names given (alone or in sets) | median s |",
        "|" + "---|" * 14,
    ]
    for r in records:
        if r["out_of_library"]:
            lines.append(
                f"| {r['system']} | {r['effect']} | {r['parameter']:g} | "
                f"{r['snr_total']:.2f} / {r['snr_beyond_library']:.2f} | "
                f"{r.get('sequences', B)} | {r['n']} | "
                + rate_cells(
                    r,
                    (
                        "detected",
                        "anything_named",
                        "named_confidently",
                        "partial",
                        "tentative",
                    ),
                )
                + " | "
                + (fmt_rate(r["shape_unchecked"]) if "shape_unchecked" in r else "–")
                + f" | {r['names'] or '–'} | {r['median_s']:.2f} |"
            )
    lines += [
        "",
        "## In-library effects (the right answer: the truth alone, confidently)",
        "",
        "| system | effect | SNR | sequences | n | detected | truth alone | truth "
        "alone, confident | shape unchecked | truth in a set | truth + extra | "
        "wrong name | partial (false) | sets: sequences to separate | median s |",
        "|" + "---|" * 15,
    ]
    for r in records:
        if r["truth"] is not None:
            lines.append(
                f"| {r['system']} | {r['effect']} | {r['snr_target']} | "
                f"{r.get('sequences', B)} | {r['n']} | "
                + rate_cells(
                    r,
                    (
                        "detected",
                        "truth_alone",
                        "truth_alone_confident",
                        "shape_unchecked",
                        "truth_in_set",
                        "truth_plus_extra",
                        "wrong_name",
                        "partial",
                    ),
                )
                + f" | {_separate(r)} | {r['median_s']:.2f} |"
            )
    lines += [
        "",
        "## Null data (no missing effect): every alarm (target ≤ 5% each, and "
        "for their union)",
        "",
        *null_table(records, "system"),
    ]
    return "\n".join(lines) + "\n"


def _separate(r: dict) -> str:
    """The data sizes the verdicts of the runs with the truth in a set gave
    for separating it (`none` where the information gave none)."""
    sizes = r.get("sets_sequences_to_separate")
    if not sizes:
        return "–"
    given = sorted(math.ceil(v) for v in sizes if v is not None)
    none = sum(v is None for v in sizes)
    return ", ".join([str(v) for v in given] + ([f"none ×{none}"] if none else []))


def rate_cells(r: dict, keys) -> str:
    """The markdown cells of the rates `keys` of record `r`."""
    return " | ".join(fmt_rate(r[k]) for k in keys)


def null_table(records: list[dict], key: str, median_s: bool = False) -> list[str]:
    """Markdown rows of the null cells: every alarm's rate and their union;
    the first column is `record[key]`."""
    extra = " median s |" if median_s else ""
    lines = [
        f"| {key} | measurement noise | n | any alarm | "
        + " | ".join(d1.ALARMS)
        + " | named confidently | crashes |"
        + extra,
        "|" + "---|" * (6 + len(d1.ALARMS) + median_s),
    ]
    for r in records:
        if r["effect"] == "none":
            zero = {"k": 0, "n": r["n"], "rate": 0.0, "ci95": [0.0, 0.0]}
            lines.append(
                f"| {r[key]} | ×{r['measurement_noise_factor']:g} | {r['n']} | "
                f"{fmt_rate(r['any_alarm'])} | "
                + " | ".join(fmt_rate(r["alarms"].get(a, zero)) for a in d1.ALARMS)
                + f" | {fmt_rate(r['named_confidently'])} | {r['crashes']} |"
                + (f" {r['median_s']:.1f} |" if median_s else "")
            )
    return lines


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--systems", nargs="+", default=list(plants()))
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument(
        "--shapes",
        default="saturation=0.4,dead zone=0.4,backlash=0.3:0.6,stiction=1:2",
        help="shape parameters of the out-of-library effects (level, "
        "half-width, play, stiction coefficient)",
    )
    parser.add_argument("--in-library-level", type=float, default=1.0)
    parser.add_argument("--null", type=int, default=200)
    parser.add_argument("--null-noises", type=float, nargs="+", default=[1.0, 2.0])
    parser.add_argument(
        "--sequences", type=int, default=B, help="sequences per data set"
    )
    parser.add_argument(
        "--effects", nargs="+", default=None, help="only these effects (and null)"
    )
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.systems, args.seeds = ["driven"], 1
        args.shapes = "saturation=0.4,dead zone=0.4,backlash=0.6"
        args.null, args.null_noises = 1, [1.0]
    t0 = time.perf_counter()
    records, commands, done = resume(
        args.json,
        lambda r: cell_key(
            r, "system", r["parameter"] if r["out_of_library"] else r["snr_target"]
        ),
    )
    info = run_info(commands)
    save = saver(args, records, info, report, t0)

    shapes = {}
    for item in args.shapes.split(","):
        effect, values = item.split("=")
        shapes[effect.strip()] = [float(v) for v in values.split(":")]
    all_plants = plants()
    for name in args.systems:
        plant = all_plants[name]
        jobs = []
        for effect in plant.effects:
            if args.effects is not None and effect not in args.effects:
                continue
            if effect in OUT_OF_LIBRARY:
                jobs += [(effect, w, args.seeds, 1.0) for w in shapes.get(effect, [])]
            else:
                jobs.append((effect, args.in_library_level, args.seeds, 1.0))
        jobs += [(None, 0.0, args.null, nz) for nz in args.null_noises]
        for effect, level, seeds, noise in jobs:
            if (name, effect or "none", level, noise, args.sequences) in done:
                continue
            if seeds < 1:
                continue
            log(f"{name}: {effect or 'null'} level {level} noise ×{noise}")
            rec = cell(plant, effect, level, seeds, log, noise, args.sequences)
            records.append(rec)
            log(
                f"  -> named confidently {rec['named_confidently']['k']}/{rec['n']}, "
                f"partial {rec['partial']['k']}, any alarm {rec['any_alarm']['k']}"
            )
            save()
    save()
    print(report(records, info))


if __name__ == "__main__":
    main()
