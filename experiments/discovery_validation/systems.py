"""Monte Carlo of the discrepancy workflow on other systems than the 1-D oscillator.

`--system two_axis`: two axes joined by a coupling spring, state
(p_x, p_y, v_x, v_y), v' = v − k p − k_c (p − p_swapped) + effect + noise
(k = 0.05, k_c = 0.02, process noise std (0.05, 0.05, 0.5, 0.5)), each
position measured by its own sensor (std 1); the two-axis
`mechanical_library` with two sensors (14 candidates). Hidden effects:
isotropic quadratic drag, and a constant force on the y axis only (which the
springs make equivalent to a bias of the y sensor: that set counts as
correct, a name on the x axis as wrong).

`--system driven`: the oscillator of `oscillator.py` driven by a known input
force u (a sinusoid of amplitude 0.6, period 6-20 steps, plus a ±0.4 random
telegraph switching with probability 0.15 per step); the one-axis library
with one input (an actuator-gain candidate added). Hidden effects: an
actuator gain error, quadratic drag, Coulomb friction, a constant force.

Both: B = 24 sequences × T = 40 steps per data set, each effect at the
per-step signal-to-noise ratio `--level`; null data: no effect. Outcomes and
rates as in `oscillator.py`.

    python -m experiments.discovery_validation.systems --system two_axis \\
        --seeds 10 --null 40 \\
        --json results/discovery_validation/systems_two_axis.json \\
        --markdown results/discovery_validation/systems_two_axis.md
    python -m experiments.discovery_validation.systems --system driven \\
        --seeds 10 --null 200 \\
        --json results/discovery_validation/systems_driven.json \\
        --markdown results/discovery_validation/systems_driven.md
"""

import argparse
import dataclasses
import time
from collections import Counter
from collections.abc import Callable

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from benchmarks._common import cli_command, machine, write_json, write_text  # noqa: E402

from .oscillator import (  # noqa: E402
    _effect_term,
    _git,
    classify,
    fmt_rate,
    guarded_run,
    naming_rates,
    rate,
    run_workflow,
)


B, T = 24, 40


@dataclasses.dataclass(frozen=True)
class System:
    """One benchmark system: its nominal model, hidden effects and data."""

    name: str
    title: str
    model: dc.ChainModel
    effects: dict[str, str]  # hidden effect -> the candidate that is the truth
    simulate: Callable[..., dc.Sequences]  # (rng, effect, coef) -> data
    calibrate: Callable[[float], dict]  # SNR level -> coefficient per effect
    stream: int  # offsets the random streams, so systems never share data


SPRING, COUPLING = 0.05, 0.02
Q2 = np.array([0.05, 0.05, 0.5, 0.5])
R2 = np.array([1.0, 1.0])
PRIOR2 = np.array([20.0, 20.0, 4.0, 4.0])


def _dyn2(x, u, params):
    k, kc = params
    p, v = x[:2], x[2:]
    return jnp.concatenate([p + v, v - k * p - kc * (p - p[::-1])])


def _meas2(x, params):
    return x[:2]


def _increment2(effect: str, v: np.ndarray) -> np.ndarray:
    """Velocity increment `(…, 2)` of a unit coefficient."""
    if effect == "force_y":
        return np.broadcast_to(np.array([0.0, 1.0]), v.shape)
    return -v * np.abs(v) if effect == "drag" else np.zeros_like(v)


def _simulate2(rng, effect: str, coef: float, num: int = B):
    x = rng.normal(size=(num, 4)) * PRIOR2
    xs = []
    for _ in range(T):
        xs.append(x)
        p, v = x[:, :2], x[:, 2:]
        a = -SPRING * p - COUPLING * (p - p[:, ::-1]) + coef * _increment2(effect, v)
        x = np.concatenate([p + v, v + a], 1) + rng.normal(size=(num, 4)) * Q2
    xs = np.stack(xs, 1)
    y = xs[..., :2] + R2 * rng.normal(size=(num, T, 2))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((num, 4)), initial_states=init)


def _calibrate2(level: float) -> dict:
    """Coefficient per effect for a per-step SNR `level` (nominal states)."""
    rng = np.random.default_rng(12345)
    x = rng.normal(size=(2000, 4)) * PRIOR2
    vs = []
    for _ in range(T):
        p, v = x[:, :2], x[:, 2:]
        vs.append(v)
        a = -SPRING * p - COUPLING * (p - p[:, ::-1])
        x = np.concatenate([p + v, v + a], 1) + rng.normal(size=(2000, 4)) * Q2
    v = np.stack(vs, 1)[:, :-1]
    drag = float(np.sqrt(np.mean(np.square(_increment2("drag", v))))) / Q2[2]
    return {"drag": level / drag, "force_y": level * Q2[3]}


def two_axis() -> System:
    sensors = {"measured_positions": [0, 1], "axis_names": ["x", "y"]}
    library = dc.mechanical_library([0, 1], [2, 3], 4, **sensors, coulomb_eps=1.0)
    params = (jnp.asarray(SPRING), jnp.asarray(COUPLING))
    model = dc.ChainModel(_dyn2, _meas2, params, Q2, R2, PRIOR2, library)
    effects = {"drag": "quadratic drag", "force_y": "constant force [y]"}
    title = "two coupled axes, two sensors"
    return System("two_axis", title, model, effects, _simulate2, _calibrate2, 0)


Q1 = np.array([0.05, 0.5])
R1 = 1.0
PRIOR1 = np.array([20.0, 4.0])
COULOMB_EPS = 1.0  # as in oscillator.py, whose effect terms are used


def _dyn1(x, u, spring):
    return jnp.stack([x[0] + x[1], x[1] - spring * x[0] + u[0]])


def _meas1(x, spring):
    return x[:1]


def _inputs(rng, num: int, amplitude: float = 1.0) -> np.ndarray:
    """Known input force `(num, T, 1)`: a sinusoid plus a random telegraph,
    both scaled by `amplitude` (`design.py`'s input designs)."""
    t = np.arange(T)[None]
    period = rng.uniform(6.0, 20.0, (num, 1))
    phase = rng.uniform(0.0, 2 * np.pi, (num, 1))
    sine = 0.6 * np.sin(2 * np.pi * t / period + phase)
    flips = rng.random((num, T)) < 0.15
    sign = np.where(rng.random((num, 1)) < 0.5, -1.0, 1.0)
    tele = 0.4 * sign * np.cumprod(np.where(flips, -1.0, 1.0), axis=1)
    return (amplitude * (sine + tele))[..., None]


def _increment1(effect: str, v: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Velocity increment of a unit coefficient (others as in `oscillator.py`)."""
    if effect in ("gain", "none"):
        return u if effect == "gain" else np.zeros_like(v)
    return _effect_term(effect, v)


def _trajectories1(
    rng,
    effect: str,
    coef: float,
    num: int,
    spring=SPRING,
    damping=0.0,
    gain=1.0,
    amplitude=1.0,
    actuator=None,
    extra=None,
):
    """States `(num, T, 2)` and inputs `(num, T, 1)`; `physics.py` sets the
    spring, a viscous damping and the actuator gain; `design.py` the input's
    `amplitude`, an `actuator` (the force applied for an input `(num,)`,
    e.g. a saturation; default the input itself) and an `extra` velocity
    increment `(num,)` at step t for velocities v, `extra(t, v)`."""
    u = _inputs(rng, num, amplitude)
    x = np.stack([rng.normal(0, PRIOR1[0], num), rng.normal(0, PRIOR1[1], num)], 1)
    xs = []
    for t in range(T):
        xs.append(x)
        p, v = x[:, 0], x[:, 1]
        force = u[:, t, 0] if actuator is None else actuator(u[:, t, 0])
        a = -spring * p - damping * v + gain * force
        a = a + coef * _increment1(effect, v, u[:, t, 0])
        if extra is not None:
            a = a + extra(t, v)
        x = np.stack([p + v, v + a], 1) + rng.normal(size=(num, 2)) * Q1
    return np.stack(xs, 1), u


def _simulate1(rng, effect: str, coef: float, num: int = B, **options):
    """Data of `num` sequences; `options` go to `_trajectories1`."""
    xs, u = _trajectories1(rng, effect, coef, num, **options)
    y = xs[..., :1] + R1 * rng.normal(size=(num, T, 1))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((num, 2)), inputs=u, initial_states=init)


def _calibrate1(level: float) -> dict:
    xs, u = _trajectories1(np.random.default_rng(12345), "none", 0.0, 2000)
    v, u = xs[:, :-1, 1], u[:, :-1, 0]
    out = {}
    for effect in ("gain", "drag", "coulomb", "force"):
        unit = float(np.sqrt(np.mean(np.square(_increment1(effect, v, u))))) / Q1[1]
        out[effect] = level / unit
    return out


def driven() -> System:
    library = dc.mechanical_library(
        [0], [1], 2, measured_positions=[0], coulomb_eps=COULOMB_EPS, num_inputs=1
    )
    nominal = (_dyn1, _meas1, jnp.asarray(SPRING), Q1, np.array([R1]), PRIOR1)
    model = dc.ChainModel(*nominal, library)
    effects = {"gain": "actuator gain", "drag": "quadratic drag"}
    effects |= {"coulomb": "Coulomb friction", "force": "constant force"}
    title = "a driven oscillator (one axis, a known input force)"
    return System("driven", title, model, effects, _simulate1, _calibrate1, 100)


SYSTEMS = {"two_axis": two_axis, "driven": driven}


def cell(
    system: System, effect: str | None, coef: float, seeds: int, tag: int, log
) -> dict:
    truth = system.effects.get(effect) if effect is not None else None
    c, coefs, times = Counter(), [], []
    names, per_alarm = Counter(), Counter()
    for s in range(seeds):
        rng = np.random.default_rng(np.random.SeedSequence([2026, 77, tag, s]))
        data = system.simulate(rng, effect or "none", coef)
        out = guarded_run(data, system.model, log, f"{effect} seed {s}")
        if out is None:
            c["crashes"] += 1
            continue
        times.append(out["seconds"])
        for key in ("detected", "unnamed"):
            c[key] += out[key]
        c["flagged"] += bool(out["flags"])
        c["alarm"] += any(out["alarms"].values())
        c["named_any"] += bool(out["named"])
        per_alarm.update({kind: bool(raised) for kind, raised in out["alarms"].items()})
        names.update(out["named"])
        if truth is not None:
            c[classify(out, truth)] += 1
            if truth in out["coefficients"]:
                coefs.append(out["coefficients"][truth][0])
        elif out["named"] or any(out["alarms"].values()):
            log(f"  null seed {s}: verdict {out['verdict']}")
    n = seeds - c["crashes"]
    rec = {"effect": effect or "none", "truth": truth, "coefficient": coef, "n": n}
    rec |= {"crashes": c["crashes"], "flagged": c["flagged"]}
    rec |= {
        "detected": rate(c["detected"], n),
        "unnamed_structure": rate(c["unnamed"], n),
        "any_alarm": rate(c["alarm"], n),
        "alarms": {kind: rate(k, n) for kind, k in per_alarm.items()},
        "named_counts": dict(names),
        "median_s": float(np.median(times)) if times else float("nan"),
    }
    if truth is None:
        return rec | {"anything_named": rate(c["named_any"], n)}
    err = np.median(np.abs(np.asarray(coefs) - coef) / coef) if coefs else None
    rec |= naming_rates(c, n, "truth_alone", "correct")
    return rec | {"coefficient_median_rel_error": None if err is None else float(err)}


def _effect_row(r) -> str:
    err = r["coefficient_median_rel_error"]
    cells = [r["truth"], f"{r['coefficient']:.4g}", str(r["n"])]
    cells += [fmt_rate(r[k]) for k in ("detected", "correct", "truth_alone")]
    cells += [fmt_rate(r[k]) for k in ("truth_in_set", "truth_plus_extra")]
    cells += [fmt_rate(r["wrong_name"]), "–" if err is None else f"{err:.3f}"]
    cells += [fmt_rate(r["any_alarm"]), f"{r['crashes']} / {r['flagged']}"]
    return "| " + " | ".join(cells + [f"{r['median_s']:.2f}"]) + " |"


def _null_lines(r) -> list[str]:
    lines = [
        "",
        f"Null data (n = {r['n']}): detected {fmt_rate(r['detected'])}, unnamed "
        f"structure {fmt_rate(r['unnamed_structure'])}, any alarm "
        f"{fmt_rate(r['any_alarm'])}, anything named {fmt_rate(r['anything_named'])};"
        f" crashes {r['crashes']}, flagged {r['flagged']}; names given: "
        f"{r['named_counts'] or 'none'}.",
    ]
    if r.get("alarms"):
        worst = max(a["rate"] for a in r["alarms"].values())
        each = ", ".join(
            f"{kind.replace('_', ' ')} {fmt_rate(a)}" for kind, a in r["alarms"].items()
        )
        lines.append(
            f"- every alarm on null data (target ≤ α = 0.05 each): {each}; largest "
            f"{worst:.3f}: " + ("met." if worst <= 0.05 else "MISSED.")
        )
    return lines


def report(system: System, records, info) -> str:
    m = info["machine"]
    lines = [
        f"# discover benchmark: {system.title}",
        "",
        f"- command: `{info['command']}`",
        f"- machine: {m['cores']} cores, {m['cpu']}; JAX {m['jax']}",
        f"- git: {info['git']}"
        + (f"; uncommitted: {', '.join(info['dirty'])}" if info["dirty"] else ""),
        f"- library ({len(system.model.names)} candidates): "
        + ", ".join(system.model.names),
        f"- wall time {info['total_s'] / 60:.1f} min; first run (compile) "
        f"{info['first_s']:.0f} s",
        "",
        "| data | coef | n | detected | correct (alone + set) | truth alone | "
        "truth in set | truth + extra | wrong name | median abs. rel. coef. error "
        "| any alarm | crashes / flagged | median s |",
        "|" + "---|" * 13,
    ]
    lines += [_effect_row(r) for r in records if r["truth"] is not None]
    for r in records:
        if r["truth"] is None:
            lines += _null_lines(r)
    for r in records:
        if r["truth"] is not None and r["named_counts"]:
            lines.append(f"- names given with {r['truth']}: {r['named_counts']}")
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--system", choices=list(SYSTEMS), default="two_axis")
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--null", type=int, default=40)
    parser.add_argument("--level", type=float, default=0.4)
    parser.add_argument("--quick", action="store_true", help="2 seeds, 2 null sets")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.null = min(args.seeds, 2), min(args.null, 2)
    system = SYSTEMS[args.system]()
    head, changed = _git()
    m = machine()
    start = time.perf_counter()
    coefs = system.calibrate(args.level)
    print(f"git {head}; coefficients at SNR {args.level}: {coefs}", flush=True)
    t0 = time.perf_counter()
    warm = system.simulate(np.random.default_rng(99), "drag", coefs["drag"])
    run_workflow(warm, system.model)
    first_s = time.perf_counter() - t0
    command = cli_command()
    records = []

    def save():
        info = {"command": command, "machine": m, "git": head, "dirty": changed}
        info |= {"system": system.name, "total_s": time.perf_counter() - start}
        info["first_s"] = first_s
        if args.json:
            write_json(args.json, records, extra=info)
        text = report(system, records, info)
        if args.markdown:
            write_text(args.markdown, text)
        return text

    cells = [(None, args.null)] + [(e, args.seeds) for e in system.effects]
    for index, (effect, count) in enumerate(cells):
        t0 = time.perf_counter()
        coef = 0.0 if effect is None else coefs[effect]
        rec = cell(system, effect, coef, count, system.stream + index, print)
        records.append(rec)
        print(f"{rec['effect']}: done in {time.perf_counter() - t0:.0f} s", flush=True)
        save()
    print(save())


if __name__ == "__main__":
    main()
