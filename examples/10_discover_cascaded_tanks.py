"""Find where a two-tank model fails on real data, and name the overflow.

What it shows: the model-discrepancy workflow of `eqsmooth.discover` on the
Cascaded Tanks benchmark (Schoukens, Mattsson, Wigren, Noël 2016; real
measurements, see `../shared/data/README.md`). A pump (input u, volts)
fills an upper tank that drains into a lower tank; the lower tank's level
y (volts) is measured every 4 s. The nominal model is Torricelli's law,

    ẋ1 = −k1 √x1 + k4 u,    ẋ2 = k1 √x1 − k3 √x2,    y = x2,

an `eqsmooth.discover.Integrator` (RK4, two steps per sample), its
parameters and initial state fitted by simulation error on the estimation
record. What it lacks: the overflow of the upper tank at large inputs, the
lower tank's (and its sensor's) limit at 10 V, and an outflow law that is
not exactly Torricelli's.

The workflow (1) localises where the nominal model fails (by time, state
and pump input: the whitened smoother residuals per bin), (2) tests it
against a library of user-defined candidates written with
`Candidate.from_function` and `Candidate.family` (overflow of either tank,
the upper tank's level profiled over a grid; a saturating level sensor; the
outflow law's exponent or a laminar part; three distractors), all terms of
the vector field (`target="rate"`), and names what it can by Laplace
evidence; (3) the named effects are added one at a time, in the order
named, and every parameter (a profiled level included) is refitted by
simulation error on the estimation record. After each stage the validation
record is simulated and its RMSE reported; it is never used to choose.
`--quick` (CI) profiles the level over two grid values instead of three.
Writes `report.json`; the story is in docs/tutorial/cascaded-tanks.md.

    python examples/10_discover_cascaded_tanks.py --quick --out results/tanks

`--untouched` makes every choice on the estimation record alone: its first
768 samples are the workflow's data, its last 256 choose how many of the
named effects to keep, the chosen model is refitted on the whole record,
and the validation record is simulated once, at the end
(`untouched.json`):

    python examples/10_discover_cascaded_tanks.py --untouched \
        --out results/cascaded_tanks

Data: `dataBenchmark.csv` of the benchmark, expected at
`../shared/data/cascaded_tanks/` next to the repository (or pass `--data
PATH`); it is distributed with the benchmark (www.nonlinearbenchmark.org).
Without it the script says so and exits with status 0.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import eqsmooth.discover as dc  # noqa: E402


REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO.parent / "shared/data/cascaded_tanks/dataBenchmark.csv"
SUBSTEPS = 2  # RK4 steps per 4 s sample (time constants are ~100 s)
SENSOR_LIMIT = 10.0  # V, the level sensor's (and lower tank's) upper limit
WINDOW = 128  # samples per sequence given to the workflow
MAX_TERMS = 6  # at most this many named effects


# ---------------------------------------------------------------------------
# Data and the nominal model
# ---------------------------------------------------------------------------


def load(path: Path) -> dict:
    """Estimation and validation records (`u`, `y`: `(1024,)`) and `Ts`."""
    d = np.genfromtxt(path, delimiter=",", skip_header=1)
    return {
        "u_est": d[:, 0],
        "u_val": d[:, 1],
        "y_est": d[:, 2],
        "y_val": d[:, 3],
        "ts": float(d[0, 4]),
    }


def _root(x):
    # √max(x, 0), smoothed over 0.01 V so that derivatives stay finite.
    return jnp.sqrt(0.5 * (x + jnp.sqrt(x * x + 1e-4)))


def tank_field(x, u, params):
    """Nominal vector field: Torricelli's law for both tanks."""
    k = params["k"]
    s1 = _root(x[0])
    return jnp.stack([-k[0] * s1 + k[2] * u[0], k[0] * s1 - k[1] * _root(x[1])])


def tank_model(ts: float) -> dc.Integrator:
    """The nominal discrete model: RK4 over the sample time, `SUBSTEPS`
    steps per sample. Candidates with `target="rate"` act inside it."""
    return dc.Integrator(tank_field, dt=ts, method="rk4", substeps=SUBSTEPS)


def measure_level(x, params):
    return x[1:]


def _terms(theta, extras):
    """`(target, coefficient, feature)` of each added candidate. `theta[5:]`
    holds, per candidate in order, its coefficient and, for a member of a
    family, the value of its profiled parameter (fitted, not the grid's)."""
    pos, terms = 5, []
    for c in extras:
        coefficient, pos = theta[pos], pos + 1
        feature = c.feature
        if c.profiled is not None:
            feature, pos = c.feature_at(theta[pos]), pos + 1
        terms.append((c.target, coefficient, feature))
    return terms


def _simulate(theta, u, model, extras):
    """Levels `y` and states of a simulation of the `Integrator` `model` with
    parameters `theta` (log k1, log k3, log k4, x1(0), x2(0), then the added
    candidates' parameters, see `_terms`)."""
    params = {"k": jnp.exp(theta[:3])}
    terms = _terms(theta, extras)
    rates = [(c, f) for target, c, f in terms if target == "rate"]
    sensor = [(c, f) for target, c, f in terms if target == "measurement"]

    def extra(x, ut):
        return sum((c * f(x, ut) for c, f in rates), jnp.zeros_like(x))

    def step(x, ut):
        y = x[1] + sum((c * f(x, ut[None])[0] for c, f in sensor), 0.0)
        xn = model.step(x, ut[None], params, extra if rates else None)
        return xn, (y, x)

    _, (ys, xs) = jax.lax.scan(step, theta[3:5], u)
    return ys, xs


_sim = jax.jit(_simulate, static_argnums=(2, 3))
_sim_jac = jax.jit(
    jax.jacfwd(lambda th, u, m, ex: _simulate(th, u, m, ex)[0]), static_argnums=(2, 3)
)


class NonFiniteSimulation(Exception):
    """The simulation (or its Jacobian) at some parameters is not finite."""


def fit_output_error(u, y, model, theta0, extras=(), bounds=None) -> dict:
    """Simulation-error least squares with the exact Jacobian:
    Levenberg-Marquardt, or a trust-region method within `bounds` (a pair of
    arrays) when given.

    A fit whose simulation or Jacobian becomes non-finite on the way (a
    start, or a trial step, where a tank level runs negative or an exponent
    overflows) stops there: it is returned with `rmse = inf` and the reason
    in `failed`, so that a multi-start refit can drop it."""
    from scipy.optimize import least_squares

    u, y, extras = jnp.asarray(u), np.asarray(y), tuple(extras)
    theta0 = np.asarray(theta0, float)
    if bounds is not None:
        theta0 = np.clip(theta0, *bounds)

    def finite(what, value, th):
        if not np.all(np.isfinite(value)):
            raise NonFiniteSimulation(f"the {what} at {np.round(th, 4).tolist()}")
        return value

    def residual(th):
        out = np.asarray(_sim(jnp.asarray(th), u, model, extras)[0]) - y
        return finite("simulation", out, th)

    def jacobian(th):
        out = np.asarray(_sim_jac(jnp.asarray(th), u, model, extras))
        return finite("simulation's Jacobian", out, th)

    try:
        res = least_squares(
            residual,
            theta0,
            jac=jacobian,
            method="lm" if bounds is None else "trf",
            **({} if bounds is None else {"bounds": bounds}),
        )
    except NonFiniteSimulation as err:
        return {"theta": theta0, "rmse": np.inf, "failed": f"not finite: {err}"}
    return {"theta": res.x, "rmse": float(np.sqrt(np.mean(res.fun**2)))}


def refit_bounds(extras, grid) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of a refit with the added candidates `extras`: a coefficient
    has the sign physics gives it (`Candidate.sign`), a profiled level stays
    within half the smallest and twice the largest value of its grid; the
    nominal parameters are free."""
    lo, hi = [-np.inf] * 5, [np.inf] * 5
    for c in extras:
        lo.append(0.0 if c.sign > 0 else -np.inf)
        hi.append(0.0 if c.sign < 0 else np.inf)
        if c.profiled is not None:
            lo.append(0.5 * min(grid))
            hi.append(2.0 * max(grid))
    return np.asarray(lo), np.asarray(hi)


def validation_rmse(theta, u, y, model, extras=()) -> dict:
    """Simulation RMSE on a record. The initial state is unknown: its two
    levels are fitted (everything else held), as is usual on this benchmark."""
    from scipy.optimize import least_squares

    theta = np.asarray(theta, float)

    def resid(x0):
        th = theta.copy()
        th[3:5] = x0
        return (
            np.asarray(_sim(jnp.asarray(th), jnp.asarray(u), model, tuple(extras))[0])
            - y
        )

    res = least_squares(resid, theta[3:5], method="lm")
    return {"rmse": float(np.sqrt(np.mean(res.fun**2))), "x0": res.x.tolist()}


# ---------------------------------------------------------------------------
# User-defined candidate effects (module-level functions + constants)
# ---------------------------------------------------------------------------

EDGE = 0.05  # V: thresholds are softplus ramps this wide, so fits see a slope


def _ramp(x):
    """max(x, 0), rounded over `EDGE` (a smooth threshold)."""
    return EDGE * jax.nn.softplus(x / EDGE)


def overflow_lost(x, u, level):
    """The upper tank spills above `level`; the water leaves the system."""
    e = _ramp(x[0] - level)
    return jnp.stack([-e, 0.0 * e])


def overflow_to_lower(x, u, level):
    """The upper tank spills above `level` into the lower tank."""
    e = _ramp(x[0] - level)
    return jnp.stack([-e, e])


def lower_overflow(x, u, level):
    """The lower tank spills above `level`."""
    e = _ramp(x[1] - level)
    return jnp.stack([0.0 * e, -e])


def sensor_saturation(x, u, limit):
    """The level reading stops at `limit` (coefficient 1 = a clip)."""
    return -_ramp(x[1:] - limit)


def outflow_exponent(x, u, tank, k):
    """Torricelli's exponent ½ off by c: the derivative of the outflow
    `k x^a` in `a` at `a = ½`, out of `tank` (and into the lower tank when
    the upper one drains)."""
    h = _root(x[tank])
    q = k * h * jnp.log(h * h + 1e-6)
    return jnp.stack([-q, q]) if tank == 0 else jnp.stack([0.0 * q, -q])


def outflow_linear(x, u, tank):
    """A part of the outflow proportional to the level (a laminar part)."""
    q = x[tank]
    return jnp.stack([-q, q]) if tank == 0 else jnp.stack([0.0 * q, -q])


def pump_to_lower(x, u):
    return jnp.stack([0.0 * u[0], u[0]])


def linear_leak(x, u, tank):
    e = jnp.zeros(2).at[tank].set(1.0)
    return -x[tank] * e


def sensor_bias(x, u):
    return jnp.ones(1)


def tank_library(k, x1_levels) -> tuple[dc.Candidate, ...]:
    """What could be missing from a two-tank model, all written with
    `Candidate.from_function` and `Candidate.family`: overflow of either
    tank (the upper tank's level unknown: a family over `x1_levels`, whose
    level the workflow profiles), a saturating sensor, the outflow law off
    Torricelli's (an exponent other than ½, a laminar part), and three
    distractors. `k` are the nominal (k1, k3)."""
    C, F = dc.Candidate.from_function, dc.Candidate.family
    k1, k3 = (round(float(v), 4) for v in k)
    levels = tuple(round(float(v), 2) for v in x1_levels)
    return (
        C(
            "sensor saturation",
            sensor_saturation,
            target="measurement",
            limit=SENSOR_LIMIT,
            sign=1,
            description=f"y -= c·max(x2 − {SENSOR_LIMIT}, 0)",
        ),
        C(
            f"lower overflow > {SENSOR_LIMIT}",
            lower_overflow,
            target="rate",
            level=SENSOR_LIMIT,
            sign=1,
            unit="1/s",
            description=f"ẋ2 -= c·max(x2 − {SENSOR_LIMIT}, 0)",
        ),
        *(
            member
            for label, fn, also in (
                ("lost", overflow_lost, ""),
                ("to lower", overflow_to_lower, ", ẋ2 += same"),
            )
            for member in F(
                f"upper overflow ({label})",
                fn,
                target="rate",
                over="level",
                values=levels,
                sign=1,
                unit="1/s",
                description=f"ẋ1 -= c·max(x1 − level, 0){also}",
            )
        ),
        C(
            "lower outflow exponent",
            outflow_exponent,
            target="rate",
            tank=1,
            k=k3,
            description="k3·x2^(½ + c) in place of k3·√x2 (to first order)",
        ),
        C(
            "upper outflow exponent",
            outflow_exponent,
            target="rate",
            tank=0,
            k=k1,
            description="k1·x1^(½ + c) in place of k1·√x1 (to first order)",
        ),
        C(
            "lower outflow, linear part",
            outflow_linear,
            target="rate",
            tank=1,
            unit="1/s",
            description="ẋ2 -= c·x2",
        ),
        C(
            "pump feeds lower tank",
            pump_to_lower,
            target="rate",
            unit="1/s",
            description="ẋ2 += c·u",
        ),
        C(
            "upper tank leak",
            linear_leak,
            target="rate",
            tank=0,
            sign=1,
            unit="1/s",
            description="ẋ1 -= c·x1",
        ),
        C(
            "sensor bias",
            sensor_bias,
            target="measurement",
            unit="V",
            description="y += c",
        ),
    )


def build_model(
    theta, model, library, q, r, prior, noise_prior: float | None = None
) -> dc.ChainModel:
    params = {"k": jnp.exp(jnp.asarray(theta[:3]))}
    return dc.ChainModel(
        model,
        measure_level,
        params,
        q,
        r,
        prior,
        library,
        noise_scale_prior=noise_prior,
    )


def windows(u, y, xs, length: int) -> dc.Sequences:
    """Cut one record into sequences of `length` samples; each starts from the
    nominal simulation's state (the prior mean) and is initialised by it."""
    B = len(y) // length
    cut = slice(0, B * length)
    U = u[cut].reshape(B, length, 1)
    Y = y[cut].reshape(B, length, 1)
    X = xs[cut].reshape(B, length, 2)
    return dc.Sequences(Y, X[:, 0], inputs=U, initial_states=X)


# ---------------------------------------------------------------------------
# The run
# ---------------------------------------------------------------------------


def find_and_name(
    theta, u, y, model, quick: bool, noise_prior: float | None = None
) -> dict:
    """Steps 2-3: the workflow on 128-sample windows of the estimation record."""
    _, xs = _sim(jnp.asarray(theta), jnp.asarray(u), model, ())
    xs = np.asarray(xs)
    q_levels = (0.75, 0.9) if quick else (0.6, 0.75, 0.9)
    x1_levels = np.quantile(xs[:, 0], q_levels)
    library = tank_library(np.exp(theta[:2]), x1_levels)
    chain = build_model(
        theta,
        model,
        library,
        q=np.array([0.05, 0.05]),
        r=np.array([0.05]),
        prior=np.array([1.0, 0.2]),
        noise_prior=noise_prior,
    )
    data = windows(u, y, xs, WINDOW)
    found = dc.find(chain, data)
    print(f"find: {found['status']}, flags {found['flags']}")
    print(
        "noise multipliers: "
        + ", ".join(f"{k} {v:.3g}" for k, v in found["noise_scales"].items())
    )
    print(
        f"decision test p = {found['score_test']['p_value']:.2g} "
        f"(df {found['score_test']['df']}); detected: {found['detected']}"
    )
    print("where the nominal model fails (whitened smoother residuals):")
    for row in found["localisation"][:6]:
        lo, hi = row["bin"]
        print(
            f"  {row['where']:28s} [{lo:8.2f}, {hi:8.2f}] n={row['count']:4d} "
            f"mean {row['mean_whitened']:+.2f}  z {row['z']:+.1f}"
        )
    named = dc.name(found, data, max_terms=MAX_TERMS)
    for i, step in enumerate(named["steps"], 1):
        top = ", ".join(
            f"{c['name']} {c['log_marginal_gain']:.1f}" for c in step["candidates"][:3]
        )
        print(f"step {i}: p = {step['p_value']:.2g} (gate {step['gate']:.2g}); {top}")
        if "profile" in step:
            pr = step["profile"]
            print(
                f"  profile of {pr['family']} over {pr['parameter']}: "
                + ", ".join(
                    f"{v:g} {g:.1f}"
                    for v, g in zip(pr["values"], pr["log_marginal_gains"])
                )
            )
    added = dc.add(found, named, data)
    print(f"verdict: {named['verdict']}")
    for c in added["coefficients"]:
        print(
            f"  {c['name']}: {c['value']:.4g} ± {c['std_error']:.2g} "
            f"(sign ok: {c['sign_ok']})"
        )
    for flag in added["flags"]:
        print(f"  flag: {flag}")
    named_candidates = tuple(library[chain.index(nm)] for nm in named["named"])
    return {
        "xs": xs,
        "x1_levels": x1_levels.tolist(),
        "named_candidates": named_candidates,
        "library": library,
        "report": dc.to_json({"find": found, "name": named, "add": added}),
    }


def add_and_show(theta, u, y, model, named_candidates, grid, heldout=None) -> dict:
    """Step 4: add the named effects one at a time, in the order the workflow
    named them, and refit every parameter by simulation error on the record
    `(u, y)` (a profiled threshold becomes a fitted parameter, started at
    each grid value of the family; the best fit on `(u, y)` is kept). With
    `heldout = (u, y)` that record is simulated after each stage (and
    before the first) for the report; it is never used to choose here."""
    stages, extras = [], ()
    score = (
        (lambda th, ex: validation_rmse(th, *heldout, model, ex)["rmse"])
        if (heldout is not None)
        else (lambda th, ex: None)
    )
    before = score(theta, ())
    for cand in named_candidates:
        extras = extras + (cand,)
        starts = _starts(theta, cand, grid)
        bounds = refit_bounds(extras, grid)
        fits = [fit_output_error(u, y, model, th0, extras, bounds) for th0 in starts]
        failed = [f["failed"] for f in fits if "failed" in f]
        if len(failed) == len(fits):
            raise RuntimeError(
                f"refit after adding {cand.name!r}: every one of the {len(fits)} "
                f"starts failed; the first: {failed[0]}"
            )
        refit = min(fits, key=lambda f: f["rmse"])
        theta = refit["theta"]
        stages.append(
            {
                "added": cand.name,
                "parameters": _describe(theta, extras),
                "k": np.exp(theta[:3]).tolist(),
                "theta": np.asarray(theta).tolist(),
                "starts": len(starts),
                "failed_starts": failed,
                "estimation_rmse": refit["rmse"],
                "validation_rmse": score(theta, extras),
            }
        )
    return {"stages": stages, "theta": np.asarray(theta).tolist(), "before": before}


def _starts(theta, cand, grid) -> list[np.ndarray]:
    """Starting points for the refit after adding `cand`: the previous fit
    with the new coefficient at a few values (a clip at 1; a rate at a
    slow and a fast one, 1/s, or either sign) and, for a family member, its
    parameter at every value of `grid` (the family's)."""
    if cand.target == "measurement":
        coefficients = (1.0,) if cand.sign > 0 else (0.0,)
    elif cand.sign > 0:
        coefficients = (0.0, 0.05, 0.5)
    else:
        coefficients = (0.0, -0.05, 0.05)
    if cand.profiled is None:
        return [np.r_[theta, c] for c in coefficients]
    return [np.r_[theta, c, v] for c in coefficients for v in grid]


def _describe(theta, extras) -> list[dict]:
    """The added candidates' fitted parameters, for the report."""
    out, pos = [], 5
    for c in extras:
        row = {"name": c.name, "coefficient": float(theta[pos])}
        pos += 1
        if c.profiled is not None:
            row[c.profiled.parameter] = float(theta[pos])
            pos += 1
        out.append(row)
    return out


SELECTION_SAMPLES = 256  # the estimation record's last 1024 s: the held-out part


def untouched(d, model, quick: bool, noise_prior: float | None) -> dict:
    """Every choice on the estimation record alone; the validation record
    scored once, at the end.

    The estimation record is split in time: its first `1024 −
    SELECTION_SAMPLES` samples (six windows) are the workflow's data (the
    nominal fit, find, name, the refits and their starts); its last
    `SELECTION_SAMPLES` are held out to choose how many of the named
    effects to keep (the number, in the order named, whose refit simulates
    the held-out part best, scored as the validation record is: initial
    levels fitted, everything else held). The chosen model is then refitted
    on the whole estimation record, stage by stage as before, and only that
    model is simulated on the validation record."""
    u, y = d["u_est"], d["y_est"]
    cut = len(u) - SELECTION_SAMPLES
    fit_part, held = (u[:cut], y[:cut]), (u[cut:], y[cut:])
    theta0 = np.array([np.log(0.05), np.log(0.05), np.log(0.05), y[0], y[0]])
    nominal = fit_output_error(*fit_part, model, theta0)
    if "failed" in nominal:
        raise RuntimeError(f"the nominal fit failed: {nominal['failed']}")
    wf = find_and_name(nominal["theta"], *fit_part, model, quick, noise_prior)
    named = wf["named_candidates"]
    grid = sorted({c.profiled.value for c in wf["library"] if c.profiled is not None})
    first = add_and_show(nominal["theta"], *fit_part, model, named, grid, held)
    selection = [first["before"]] + [st["validation_rmse"] for st in first["stages"]]
    keep = int(np.argmin(selection))  # ties: the fewest effects
    for k, rmse in enumerate(selection):
        print(
            f"held-out part, {k} effects: RMSE {rmse:.3f} V"
            + ("  <- kept" if k == keep else "")
        )
    # The chosen model, refitted on the whole estimation record.
    full = fit_output_error(u, y, model, theta0)
    if "failed" in full:
        raise RuntimeError(f"the nominal refit failed: {full['failed']}")
    final = add_and_show(full["theta"], u, y, model, named[:keep], grid)
    theta = np.asarray(final["theta"])
    estimation_rmse = final["stages"][-1]["estimation_rmse"] if keep else full["rmse"]
    # The one look at the validation record.
    validation = validation_rmse(theta, d["u_val"], d["y_val"], model, named[:keep])
    print(
        f"untouched: {keep} effects ({', '.join(c.name for c in named[:keep])}); "
        f"estimation RMSE {estimation_rmse:.3f} V, validation RMSE "
        f"{validation['rmse']:.3f} V"
    )
    return {
        "selection": "estimation record only",
        "split": {
            "fit_samples": [0, cut],
            "selection_samples": [cut, len(u)],
            "validation": "scored once, after every choice",
        },
        "named": [c.name for c in named],
        "selection_rmse": {
            "by_number_of_effects": selection,
            "kept": keep,
        },
        "fit_part": {
            "nominal_rmse": nominal["rmse"],
            "stages": first["stages"],
            "workflow": wf["report"],
        },
        "final": {
            "effects": [c.name for c in named[:keep]],
            "parameters": _describe(theta, named[:keep]),
            "k": np.exp(theta[:3]).tolist(),
            "estimation_rmse": estimation_rmse,
            "failed_starts": [st["failed_starts"] for st in final["stages"]],
        },
        "validation_rmse": validation["rmse"],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=REPO / "results/tanks")
    parser.add_argument("--quick", action="store_true", help="smaller library (CI)")
    parser.add_argument(
        "--noise-prior",
        type=float,
        default=5.0,
        help="standard deviation of a normal prior on the log noise multipliers "
        "(ChainModel.noise_scale_prior); without one the measurement multiplier "
        "runs off towards 0 on these smooth readings. Pass 0 for none",
    )
    parser.add_argument(
        "--untouched",
        action="store_true",
        help="choose everything on the estimation record alone (its last "
        f"{SELECTION_SAMPLES} samples held out to choose the number of effects), "
        "score the validation record once; writes untouched.json",
    )
    args = parser.parse_args()
    if not args.data.exists():
        print(
            f"data not found: {args.data}\nGet dataBenchmark.csv of the Cascaded "
            "Tanks benchmark (www.nonlinearbenchmark.org) and put it there, or pass "
            "--data PATH."
        )
        return 0
    t_start = time.perf_counter()
    d = load(args.data)
    ts, u, y = d["ts"], d["u_est"], d["y_est"]

    model = tank_model(ts)
    noise_prior = args.noise_prior or None
    if args.untouched:
        record = untouched(d, model, args.quick, noise_prior)
        record = {
            "command": "python " + " ".join(sys.argv),
            "seconds": time.perf_counter() - t_start,
            "quick": args.quick,
            "noise_prior": noise_prior,
            **record,
        }
        args.out.mkdir(parents=True, exist_ok=True)
        path = args.out / "untouched.json"
        path.write_text(json.dumps(record, indent=1, default=str))
        print(f"{record['seconds']:.0f} s; wrote {path}")
        return 0

    # 1. The nominal model, fitted by simulation error on the estimation record.
    theta0 = np.array([np.log(0.05), np.log(0.05), np.log(0.05), y[0], y[0]])
    nominal = fit_output_error(u, y, model, theta0)
    if "failed" in nominal:
        raise RuntimeError(f"the nominal fit failed: {nominal['failed']}")
    theta = nominal["theta"]
    val_before = validation_rmse(theta, d["u_val"], d["y_val"], model)
    print(
        f"nominal: k1 k3 k4 = {np.exp(theta[:3]).round(4).tolist()}, "
        f"estimation RMSE {nominal['rmse']:.3f} V, validation RMSE "
        f"{val_before['rmse']:.3f} V"
    )
    # 2-3. Find and name; 4. add and show.
    wf = find_and_name(theta, u, y, model, args.quick, noise_prior)
    grid = [c.profiled.value for c in wf["library"] if c.profiled is not None]
    after = add_and_show(
        theta,
        u,
        y,
        model,
        wf["named_candidates"],
        sorted(set(grid)),
        heldout=(d["u_val"], d["y_val"]),
    )
    for row in after["stages"]:
        dropped = len(row["failed_starts"])
        print(
            f"+ {row['added']}: estimation RMSE {row['estimation_rmse']:.3f} V, "
            f"validation RMSE {row['validation_rmse']:.3f} V "
            f"(nominal {val_before['rmse']:.3f} V)"
            + (f"; {dropped} of {row['starts']} starts not finite" if dropped else "")
        )
    summary = {
        "command": "python " + " ".join(sys.argv),
        "seconds": time.perf_counter() - t_start,
        "quick": args.quick,
        "noise_prior": noise_prior,
        "nominal": {
            "k": np.exp(theta[:3]).tolist(),
            "estimation_rmse": nominal["rmse"],
            "validation_rmse": val_before["rmse"],
        },
        "x1_levels": wf["x1_levels"],
        "workflow": wf["report"],
        "after": after,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.json").write_text(json.dumps(summary, indent=1, default=str))
    print(f"{summary['seconds']:.0f} s; wrote {args.out / 'report.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
