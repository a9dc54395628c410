"""Monte Carlo of the discrepancy workflow on effects inside a continuous-time model.

System: a pendulum `φ̈ = −ω₀² sin φ + c · a(φ, φ̇)` (ω₀² = 4 s⁻²), sampled
every dt = 0.25 s (ω₀ dt = 0.5: a coarse sample time, where a step's
discretisation matters). Data: integrated with 25 RK4 steps per sample
(the effect inside the ODE), discrete process noise of std (0.005 rad,
0.05 rad/s) added per sample, the angle measured with std 0.05 rad, first
state from N(0, diag(1 rad, 2 rad/s)²); B = 24 sequences × T = 40 samples
per data set. The nominal model is an `eqsmooth.discover.Integrator` of
the nominal vector field (RK4, two substeps per sample) with the noise
levels known (the workflow refits three noise scales).

Libraries compared on the same data sets:

- `rate`: `mechanical_library(..., dynamics=integrator)`, the default for a
  continuous-time model: every acceleration candidate is a term of the
  vector field, integrated by the model's own scheme.
- `kick`: the discrete-time library (`dt=0.25`, a velocity kick
  `dt · a(x_t)` at the start of each step), the default before.

Hidden effects inside the ODE (the library's candidates, coefficient set by
the per-step SNR `--level`: RMS of `c · a · dt` over nominal trajectories,
over the velocity noise std): viscous damping, Coulomb friction
(`tanh(φ̇/0.1)`), quadratic drag, a constant torque. The interval is the
95% interval `add` reports for the true candidate's coefficient (coverage
of the true continuous-time coefficient). Null data: no effect, measurement
noise of the assumed std and of twice it.

    python -m experiments.discovery_validation.continuous --quick
    python -m experiments.discovery_validation.continuous --seeds 20 --kick-seeds 10 \\
        --null 60 --json results/discovery_validation/continuous.json \\
        --markdown results/discovery_validation/continuous.md

The run saves after every cell and, given the same `--json`, skips the cells
already there (it can be stopped and resumed).
"""

import argparse
import functools
import time
from collections import Counter

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402

from ._run import cell_key, cell_runs, log, resume, run_info, run_lines, saver, stream  # noqa: E402
from .nonsmooth import null_table, outcome_rates, rate_cells, tally  # noqa: E402
from .oscillator import fmt_rate, rate  # noqa: E402


B, T = 24, 40
W2, DT, SUBSTEPS = 4.0, 0.25, 25
Q = np.array([0.005, 0.05])
R = 0.05
PRIOR = np.array([1.0, 2.0])
COULOMB_EPS = 0.1

# Hidden effect (= the true candidate's name) -> unit acceleration a(φ̇).
EFFECTS = {
    "viscous damping": lambda v: -v,
    "Coulomb friction": lambda v: -np.tanh(v / COULOMB_EPS),
    "quadratic drag": lambda v: -v * np.abs(v),
    "constant force": np.ones_like,
}
_TAGS = {name: i + 1 for i, name in enumerate(EFFECTS)}  # stable stream tags


def _field(x, u, w2):
    return jnp.stack([x[1], -w2 * jnp.sin(x[0])])


def _measure(x, w2):
    return x[:1]


INTEGRATOR = dc.Integrator(_field, DT, "rk4", 2)
LIBRARIES = {
    "rate": dc.mechanical_library(
        [0],
        [1],
        2,
        measured_positions=[0],
        coulomb_eps=COULOMB_EPS,
        dynamics=INTEGRATOR,
    ),
    "kick": dc.mechanical_library(
        [0], [1], 2, dt=DT, measured_positions=[0], coulomb_eps=COULOMB_EPS
    ),
}
MODELS = {
    key: dc.ChainModel(
        INTEGRATOR, _measure, jnp.asarray(W2), Q, np.array([R]), PRIOR, lib
    )
    for key, lib in LIBRARIES.items()
}


def _states(rng, effect, coef, num):
    """True states `(num, T, 2)`: 25 RK4 steps per sample of the pendulum
    with the effect inside, plus discrete process noise per sample."""
    x = np.stack([rng.normal(0, PRIOR[0], num), rng.normal(0, PRIOR[1], num)], 1)
    term = EFFECTS[effect] if effect else None

    def field(x):
        a = -W2 * np.sin(x[:, 0])
        if term is not None:
            a = a + coef * term(x[:, 1])
        return np.stack([x[:, 1], a], 1)

    h, xs = DT / SUBSTEPS, []
    for _ in range(T):
        xs.append(x.copy())
        for _ in range(SUBSTEPS):
            k1 = field(x)
            k2 = field(x + h / 2 * k1)
            k3 = field(x + h / 2 * k2)
            k4 = field(x + h * k3)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        x = x + rng.normal(size=(num, 2)) * Q
    return np.stack(xs, 1)


def _snr(effect, coef, xs) -> float:
    """RMS of the effect's velocity change per step, over the velocity noise."""
    term = EFFECTS[effect](xs[:, :-1, 1])
    return float(np.sqrt(np.mean(np.square(coef * term)))) * DT / Q[1]


def simulate(rng, effect, coef, noise=1.0, num=B):
    """Data set of `num` sequences; returns (Sequences, realised SNR)."""
    xs = _states(rng, effect, coef, num)
    y = xs[..., :1] + noise * R * rng.normal(size=(num, T, 1))
    snr = _snr(effect, coef, xs) if effect else 0.0
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((num, 2)), initial_states=init), snr


@functools.cache
def coefficient(effect: str, level: float) -> float:
    """The coefficient whose per-step SNR is `level` on nominal trajectories."""
    xs = _states(np.random.default_rng(12345), None, 0.0, 2000)
    return level / _snr(effect, 1.0, xs)


def cell(library, effect, level, seeds, log, noise=1.0, num=B, first_seed=0) -> dict:
    """`seeds` data sets (streams `first_seed`, ...) of `num` sequences of one
    (library, effect, level) or null cell. Both libraries see the same data
    sets (the streams do not depend on it)."""
    model = MODELS[library]
    coef = coefficient(effect, level) if effect else 0.0
    truth = effect
    c, names, alarms, times, snrs, rel = Counter(), Counter(), Counter(), [], [], []
    for s, out, snr in cell_runs(
        stream(3, _TAGS.get(effect, 0), level, noise, num),
        range(first_seed, first_seed + seeds),
        lambda rng: simulate(rng, effect, coef, noise, num),
        model,
        log,
        f"{library} {effect}",
        c,
    ):
        snrs.append(snr)
        times.append(out["seconds"])
        kind = tally(out, truth, c, names, alarms)
        if truth is not None:
            if truth in out["coefficients"]:
                value, (lo, hi) = out["coefficients"][truth]
                rel.append((value - coef) / coef)
                c["covered"] += lo <= coef <= hi
            if kind != "exact":
                log(f"  {library} {effect} seed {s}: {out['verdict']}")
        elif out["named"] or any(out["alarms"].values()):
            log(f"  {library} null seed {s}: {out['verdict']}")
    n = seeds - c["crashes"]
    rec = {
        "library": library,
        "effect": effect or "none",
        "snr_target": level if effect else None,
        "snr_realised_median": float(np.median(snrs)) if snrs else None,
        "measurement_noise_factor": noise,
        "sequences": num,
        "first_seed": first_seed,
        "coefficient": coef,
        "n": n,
        "crashes": c["crashes"],
        **outcome_rates(c, n, names, alarms, truth),
        "median_s": float(np.median(times)) if times else None,
        "max_s": float(np.max(times)) if times else None,
    }
    if truth is not None:
        rec |= {
            "coef_ci95_coverage": rate(c["covered"], len(rel)),
            "coef_rel_error_median_abs": (
                float(np.median(np.abs(rel))) if rel else None
            ),
            "coef_rel_errors": [float(r) for r in rel],
        }
    return rec


def report(records: list[dict], info: dict) -> str:
    lines = [
        "# discover benchmark: effects inside a continuous-time model (pendulum, "
        f"dt = {DT} s, ω₀ dt = {DT * W2**0.5:g})",
        "",
        *run_lines(info),
        "- sequences per data set: "
        + ", ".join(str(v) for v in sorted({r.get("sequences", B) for r in records}))
        + f" (× {T} samples)",
        "- `rate`: candidates inside the integrator (the default for an "
        "`Integrator` model); `kick`: the discrete-time library.",
        "- coverage: the true coefficient inside `add`'s 95% interval, over the "
        "runs that fitted the true candidate.",
        "",
        "## Effects inside the ODE (the right answer: the truth alone)",
        "",
        "| library | effect | SNR | n | detected | truth alone | truth alone, "
        "confident | truth in a set | truth + extra | wrong name | interval "
        "coverage | median abs rel error | median s | max s |",
        "|" + "---|" * 14,
    ]
    for r in records:
        if r["effect"] != "none":
            err = r["coef_rel_error_median_abs"]
            lines.append(
                f"| {r['library']} | {r['effect']} | {r['snr_target']:g} | {r['n']} | "
                + rate_cells(
                    r,
                    (
                        "detected",
                        "truth_alone",
                        "truth_alone_confident",
                        "truth_in_set",
                        "truth_plus_extra",
                        "wrong_name",
                        "coef_ci95_coverage",
                    ),
                )
                + f" | {'–' if err is None else f'{err:.3f}'}"
                + f" | {r['median_s']:.1f} | {r['max_s']:.1f} |"
            )
    lines += [
        "",
        "## Null data (no missing effect; target ≤ 5% for each alarm and for "
        "their union)",
        "",
        *null_table(records, "library", median_s=True),
    ]
    return "\n".join(lines) + "\n"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=20, help="data sets, rate")
    parser.add_argument("--kick-seeds", type=int, default=10, help="data sets, kick")
    parser.add_argument("--level", type=float, default=1.0)
    parser.add_argument("--effects", nargs="+", default=list(EFFECTS))
    parser.add_argument("--null", type=int, default=60)
    parser.add_argument("--null-noises", type=float, nargs="+", default=[1.0, 2.0])
    parser.add_argument(
        "--sequences", type=int, default=B, help="sequences per data set"
    )
    parser.add_argument(
        "--first-seed", type=int, default=0, help="first data set's stream"
    )
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.kick_seeds, args.null = 1, 1, 1
        args.effects, args.null_noises = ["viscous damping"], [1.0]
    t0 = time.perf_counter()
    records, commands, done = resume(
        args.json,
        lambda r: cell_key(r, "library", r["snr_target"]) + (r.get("first_seed", 0),),
    )
    info = run_info(commands)
    save = saver(args, records, info, report, t0)
    plan = [("rate", e, args.level, args.seeds, 1.0) for e in args.effects]
    plan += [("rate", None, None, args.null, nz) for nz in args.null_noises]
    plan += [("kick", e, args.level, args.kick_seeds, 1.0) for e in args.effects]
    for library, effect, level, seeds, noise in plan:
        key = (library, effect or "none", level, noise, args.sequences, args.first_seed)
        if key in done or seeds <= 0:
            continue
        t = time.perf_counter()
        rec = cell(
            library,
            effect,
            level or 0.0,
            seeds,
            log,
            noise,
            args.sequences,
            args.first_seed,
        )
        records.append(rec)
        save()
        head = f"{library} {effect or 'null'} ×{noise:g}: n={rec['n']}"
        if effect:
            head += (
                f" alone {fmt_rate(rec['truth_alone'])}"
                f" coverage {fmt_rate(rec['coef_ci95_coverage'])}"
            )
        else:
            head += f" any alarm {fmt_rate(rec['any_alarm'])}"
        log(f"{head} ({time.perf_counter() - t:.0f} s)")
    save()
    if not args.json:
        print(report(records, info))


if __name__ == "__main__":
    main()
