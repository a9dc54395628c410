"""Physical parameters before and after a named effect.

Does adding the effect the workflow names put the physics back, and does a
flexible residual model do as well? The system is the driven oscillator of
`systems.py` with viscous damping,

    p' = p + v,   v' = v − k p − c v + g u + a·e(v) + w,   y = p + r,

truth k = 0.05, c = 0.05, g = 1, process noise std (0.05, 0.5), sensor std
1, B = 24 sequences × T = 40 steps per data set. The nominal model has the
spring 0.04 (20 % low), no damping and unit gain; the physical parameters
are fitted as the corrections the mechanical library already holds:
k̂ = 0.04 + "spring error", ĉ = "viscous damping", ĝ = 1 + "actuator gain".
The hidden effect e is Coulomb friction or quadratic drag at the
per-step signal-to-noise ratio `--level`.

Per data set, three fits by `eqsmooth.discover.add` (Laplace evidence,
intervals from its curvature, noise scales fitted):

- `physics`: the three physical parameters alone (`named=None`), the model
  before any effect is added;
- `physics + named`: with the effects the workflow names (`find`, `name`
  on the mechanical library);
- `residual`: the physical parameters with an unconstrained residual in
  the velocity instead (`--basis` Gaussian bumps of v on [−6, 6], every
  coefficient free): the usual grey-box baseline.

Per model and parameter: the mean estimate, its bias, RMSE, mean interval
width and the coverage of the nominal 95 % interval (with a binomial
interval on the coverage).

    python -m experiments.discovery_validation.physics --seeds 20 \\
        --json results/discover_physics/summary.json \\
        --markdown results/discover_physics/summary.md
"""

import argparse
import json
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402
from benchmarks._common import cli_command, write_json, write_text  # noqa: E402

from .oscillator import _effect_term, _git, wilson  # noqa: E402
from .systems import _dyn1, _meas1, _trajectories1, COULOMB_EPS, PRIOR1, Q1, R1  # noqa: E402


B, T = 24, 40
TRUTH = {"spring": 0.05, "damping": 0.05, "gain": 1.0}
NOMINAL_SPRING = 0.04
PHYSICS = ("spring error", "viscous damping", "actuator gain")
EFFECTS = {"coulomb": "Coulomb friction", "drag": "quadratic drag"}


def _estimate(name: str, value: float) -> float:
    """The physical parameter from its correction's coefficient."""
    return {
        "spring error": NOMINAL_SPRING + value,
        "viscous damping": value,
        "actuator gain": 1.0 + value,
    }[name]


PARAMETER = dict(zip(PHYSICS, ("spring", "damping", "gain")))


def bump(x, u, centre, width):
    """A Gaussian bump of the velocity, as a velocity kick."""
    return jnp.stack([0.0 * x[1], jnp.exp(-0.5 * ((x[1] - centre) / width) ** 2)])


def trajectories(rng, effect: str, coef: float, num: int = B):
    return _trajectories1(
        rng,
        effect,
        coef,
        num,
        spring=TRUTH["spring"],
        damping=TRUTH["damping"],
        gain=TRUTH["gain"],
    )


def simulate(rng, effect: str, coef: float) -> dc.Sequences:
    xs, u = trajectories(rng, effect, coef)
    y = xs[..., :1] + R1 * rng.normal(size=(B, T, 1))
    init = np.concatenate([y, np.zeros_like(y)], -1)
    return dc.Sequences(y, np.zeros((B, 2)), inputs=u, initial_states=init)


def calibrate(level: float) -> dict:
    """The coefficient of each effect at a per-step SNR `level`."""
    xs, _ = trajectories(np.random.default_rng(12345), "coulomb", 0.0, 2000)
    v = xs[:, :-1, 1]
    return {
        e: level * Q1[1] / float(np.sqrt(np.mean(_effect_term(e, v) ** 2)))
        for e in EFFECTS
    }


def models(basis: int) -> tuple[dc.ChainModel, dc.ChainModel]:
    """The workflow's model (mechanical library) and the residual model's."""
    library = dc.mechanical_library(
        [0], [1], 2, measured_positions=[0], coulomb_eps=COULOMB_EPS, num_inputs=1
    )
    nominal = (_dyn1, _meas1, jnp.asarray(NOMINAL_SPRING), Q1, np.array([R1]), PRIOR1)
    physics = tuple(c for c in library if c.name in PHYSICS)
    width = 12.0 / (basis - 1)
    bumps = tuple(
        dc.Candidate.from_function(
            f"bump {i}", bump, centre=float(-6.0 + i * width), width=float(width)
        )
        for i in range(basis)
    )
    return dc.ChainModel(*nominal, library), dc.ChainModel(*nominal, physics + bumps)


def physical(added: dict) -> dict:
    """`{parameter: (estimate, std error)}` of an `add` result."""
    out = {}
    for c in added["coefficients"]:
        if c["name"] in PHYSICS:
            out[PARAMETER[c["name"]]] = (
                _estimate(c["name"], c["value"]),
                c["std_error"],
            )
    return out


def one(data, workflow_model, residual_model, basis: int) -> dict:
    found = dc.find(workflow_model, data)
    named = dc.name(found, data)
    fits = {
        "physics": dc.add(found, None, data, also=PHYSICS),
        "physics + named": dc.add(found, named, data, also=PHYSICS),
    }
    found_r = dc.find(residual_model, data)
    bumps = tuple(f"bump {i}" for i in range(basis))
    fits["residual"] = dc.add(found_r, None, data, also=PHYSICS + bumps)
    return {
        "named": list(named["named"]),
        "fits": {k: physical(v) for k, v in fits.items()},
        "flags": {k: list(v["flags"]) for k, v in fits.items()},
    }


def summarise(runs: list[dict]) -> dict:
    out = {}
    for model in ("physics", "physics + named", "residual"):
        rows = {}
        for par, truth in TRUTH.items():
            est = np.array([r["fits"][model][par][0] for r in runs])
            se = np.array([r["fits"][model][par][1] for r in runs])
            ok = np.isfinite(se)
            covered = int(np.sum(np.abs(est[ok] - truth) <= 1.96 * se[ok]))
            rows[par] = {
                "truth": truth,
                "mean": float(est.mean()),
                "bias": float(est.mean() - truth),
                "rmse": float(np.sqrt(np.mean((est - truth) ** 2))),
                "mean_interval_width": float(np.mean(2 * 1.96 * se[ok])),
                "coverage_95": covered / max(int(ok.sum()), 1),
                "coverage_interval": list(wilson(covered, int(ok.sum()))),
                "n": int(ok.sum()),
            }
        out[model] = rows
    return out


def report(records: dict, info: dict) -> str:
    lines = [
        "# Physical parameters before and after the named effect",
        "",
        f"- command: `{info['command']}`",
        f"- git {info['git'][0]} (changed: {info['git'][1] or 'none'}); "
        f"{info['seconds']:.0f} s",
        "",
        "Truth: " + ", ".join(f"{k} {v}" for k, v in TRUTH.items()),
        "",
    ]
    for effect, rec in records.items():
        lines += [
            f"## Hidden effect: {EFFECTS[effect]} (coefficient "
            f"{rec['coefficient']:.3g}, {rec['n']} data sets)",
            "",
            f"Named the true effect in {rec['named_truth']} of {rec['n']}.",
            "",
            "| model | parameter | mean | bias | RMSE | 95% width | coverage |",
            "|---|---|---|---|---|---|---|",
        ]
        for model, rows in rec["summary"].items():
            for par, r in rows.items():
                lo, hi = r["coverage_interval"]
                lines.append(
                    f"| {model} | {par} | {r['mean']:.4f} | {r['bias']:+.4f} | "
                    f"{r['rmse']:.4f} | {r['mean_interval_width']:.4f} | "
                    f"{r['coverage_95']:.2f} [{lo:.2f}, {hi:.2f}] |"
                )
        lines.append("")
    return "\n".join(lines)


def rerender(path: str, markdown: str | None = None) -> None:
    """Recompute the summaries and the report of a saved run from its runs."""
    payload = json.loads(Path(path).read_text())
    for rec in payload["records"].values():
        rec["summary"] = summarise(rec["runs"])
    Path(path).write_text(json.dumps(payload, indent=1))
    if markdown:
        write_text(markdown, report(payload["records"], payload["info"]))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=20)
    parser.add_argument("--level", type=float, default=1.0)
    parser.add_argument("--basis", type=int, default=7)
    parser.add_argument("--effects", nargs="+", default=list(EFFECTS))
    parser.add_argument("--quick", action="store_true", help="2 seeds, one effect")
    parser.add_argument("--json", default=None)
    parser.add_argument("--markdown", default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.seeds, args.effects = 2, args.effects[:1]
    t0 = time.perf_counter()
    coefs = calibrate(args.level)
    workflow_model, residual_model = models(args.basis)
    records = {}
    info = {
        "command": cli_command(),
        "git": _git(),
        "truth": TRUTH,
        "nominal_spring": NOMINAL_SPRING,
        "level": args.level,
        "basis": args.basis,
    }

    def save() -> str:
        info["seconds"] = time.perf_counter() - t0
        if args.json:
            write_json(args.json, records, {"info": info})
        text = report(records, info)
        if args.markdown:
            write_text(args.markdown, text)
        return text

    for e_i, effect in enumerate(args.effects):
        runs = []
        for s in range(args.seeds):
            rng = np.random.default_rng(np.random.SeedSequence([2026, 1129, e_i, s]))
            data = simulate(rng, effect, coefs[effect])
            run = one(data, workflow_model, residual_model, args.basis)
            runs.append(run)
            print(
                f"{effect} seed {s}: named {run['named']}; "
                + "; ".join(
                    f"{m}: c {f['damping'][0]:.3f}±{f['damping'][1]:.3f}"
                    for m, f in run["fits"].items()
                ),
                flush=True,
            )
        records[effect] = {
            "coefficient": coefs[effect],
            "n": len(runs),
            "named_truth": sum(EFFECTS[effect] in r["named"] for r in runs),
            "summary": summarise(runs),
            "runs": runs,
        }
        save()  # after each effect, so an interrupted run keeps what it did
    text = save()
    print(text)


if __name__ == "__main__":
    main()
