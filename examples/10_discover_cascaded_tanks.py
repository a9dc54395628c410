"""Find where a two-tank model fails on real data, and name the overflow.

What it shows: the model-discrepancy workflow of `eqsmooth.discover` on the
Cascaded Tanks benchmark (Schoukens, Mattsson, Wigren, Noël 2016; real
measurements, see `../shared/data/README.md`). A pump (input u, volts)
fills an upper tank that drains into a lower tank; the lower tank's level
y (volts) is measured every 4 s. The nominal model is Torricelli's law,

    ẋ1 = −k1 √x1 + k4 u,    ẋ2 = k1 √x1 − k3 √x2,    y = x2,

integrated with RK4 over the sample time, its parameters and initial state
fitted by simulation error on the estimation record. What it lacks is the
overflow: at large inputs the upper tank fills up and spills.

The workflow then (1) localises where the nominal model fails (by time,
state and pump input: the whitened smoother residuals per bin), (2) tests it
against a library of user-defined candidates written with
`Candidate.from_function` (overflow of either tank, a saturating level
sensor, a leak, a pump that also feeds the lower tank, a sensor bias) and
names what it can by Laplace evidence, and (3) the named effects are added
to the model, whose parameters are refitted by simulation error on the
estimation record; the upper tank's overflow is then characterised (its
level and whether the spill reaches the lower tank) by the estimation-record
fit of a few overflow candidates. After each stage the validation record is
simulated and its RMSE reported. `--quick` (CI) puts one overflow level into
the workflow's library, the full run three. Writes `report.json`; the story
is in docs/tutorial/cascaded-tanks.md.

    python examples/10_discover_cascaded_tanks.py --quick --out results/tanks

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
SUBSTEPS = 1  # RK4 steps per 4 s sample (time constants are ~100 s)
SENSOR_LIMIT = 10.0  # V, the level sensor's (and lower tank's) upper limit
WINDOW = 128  # samples per sequence given to the workflow


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


def _rates(x, u, k):
    s1 = _root(x[0])
    return jnp.stack([-k[0] * s1 + k[2] * u, k[0] * s1 - k[1] * _root(x[1])])


def tank_step(x, u, params):
    """Nominal model: one sample time of Torricelli's law (RK4 sub-steps)."""
    k, h = params["k"], params["ts"] / SUBSTEPS
    for _ in range(SUBSTEPS):
        a = _rates(x, u[0], k)
        b = _rates(x + 0.5 * h * a, u[0], k)
        c = _rates(x + 0.5 * h * b, u[0], k)
        d = _rates(x + h * c, u[0], k)
        x = x + h / 6 * (a + 2 * b + 2 * c + d)
    return x


def measure_level(x, params):
    return x[1:]


def _simulate(theta, u, ts, extras):
    """Levels `y` and states of a simulation with parameters `theta` (log k1,
    log k3, log k4, x1(0), x2(0)) plus, for each candidate in `extras`, its
    coefficient (`theta[5:]`)."""
    params = {"k": jnp.exp(theta[:3]), "ts": ts}

    def step(x, ut):
        y = x[1]
        xn = tank_step(x, ut[None], params)
        for i, c in enumerate(extras):
            if c.target == "dynamics":
                xn = xn + theta[5 + i] * c.feature(x, ut[None])
            else:
                y = y + theta[5 + i] * c.feature(x, ut[None])[0]
        return xn, (y, x)

    _, (ys, xs) = jax.lax.scan(step, theta[3:5], u)
    return ys, xs


_sim = jax.jit(_simulate, static_argnums=(3,))
_sim_jac = jax.jit(
    jax.jacfwd(lambda th, u, ts, ex: _simulate(th, u, ts, ex)[0]), static_argnums=(3,)
)


def fit_output_error(u, y, ts, theta0, extras=()) -> dict:
    """Simulation-error least squares (Levenberg-Marquardt, exact Jacobian)."""
    from scipy.optimize import least_squares

    u, y, extras = jnp.asarray(u), np.asarray(y), tuple(extras)
    res = least_squares(
        lambda th: np.asarray(_sim(jnp.asarray(th), u, ts, extras)[0]) - y,
        np.asarray(theta0, float),
        jac=lambda th: np.asarray(_sim_jac(jnp.asarray(th), u, ts, extras)),
        method="lm",
    )
    return {"theta": res.x, "rmse": float(np.sqrt(np.mean(res.fun**2)))}


def validation_rmse(theta, u, y, ts, extras=()) -> dict:
    """Simulation RMSE on a record. The initial state is unknown: its two
    levels are fitted (everything else held), as is usual on this benchmark."""
    from scipy.optimize import least_squares

    theta = np.asarray(theta, float)

    def resid(x0):
        th = theta.copy()
        th[3:5] = x0
        return (
            np.asarray(_sim(jnp.asarray(th), jnp.asarray(u), ts, tuple(extras))[0]) - y
        )

    res = least_squares(resid, theta[3:5], method="lm")
    return {"rmse": float(np.sqrt(np.mean(res.fun**2))), "x0": res.x.tolist()}


# ---------------------------------------------------------------------------
# User-defined candidate effects (module-level functions + constants)
# ---------------------------------------------------------------------------


def overflow_lost(x, u, level, ts):
    """The upper tank spills above `level`; the water leaves the system."""
    e = jax.nn.relu(x[0] - level)
    return jnp.stack([-ts * e, 0.0 * e])


def overflow_to_lower(x, u, level, ts):
    """The upper tank spills above `level` into the lower tank."""
    e = jax.nn.relu(x[0] - level)
    return jnp.stack([-ts * e, ts * e])


def lower_overflow(x, u, level, ts):
    """The lower tank spills above `level`."""
    e = jax.nn.relu(x[1] - level)
    return jnp.stack([0.0 * e, -ts * e])


def sensor_saturation(x, u, limit):
    """The level reading stops at `limit` (coefficient 1 = a hard clip)."""
    return -jax.nn.relu(x[1:] - limit)


def pump_to_lower(x, u, ts):
    return jnp.stack([0.0 * u[0], ts * u[0]])


def linear_leak(x, u, tank, ts):
    e = jnp.zeros(2).at[tank].set(1.0)
    return -ts * x[tank] * e


def sensor_bias(x, u):
    return jnp.ones(1)


def tank_library(ts: float, x1_levels, x2_levels) -> tuple[dc.Candidate, ...]:
    """Overflow of either tank at a few levels, a saturating sensor and
    three distractors, all written with `Candidate.from_function`."""
    C = dc.Candidate.from_function

    def overflow(fn, tank: int, lv, suffix="", also=""):
        """Overflow of tank `tank` (1 upper, 2 lower) above level `lv`."""
        lv = round(float(lv), 2)
        where = "upper" if tank == 1 else "lower"
        return C(
            f"{where} overflow > {lv}{suffix}",
            fn,
            level=lv,
            ts=ts,
            sign=1,
            unit="1/s",
            description=f"ẋ{tank} -= c·max(x{tank} − {lv}, 0){also}",
        )

    out = []
    for lv in x1_levels:
        out.append(overflow(overflow_lost, 1, lv, " (lost)"))
        out.append(overflow(overflow_to_lower, 1, lv, " (to lower)", ", ẋ2 += same"))
    for lv in x2_levels:
        out.append(overflow(lower_overflow, 2, lv))
    out += [
        C(
            "sensor saturation",
            sensor_saturation,
            target="measurement",
            limit=SENSOR_LIMIT,
            sign=1,
            description=f"y -= c·max(x2 − {SENSOR_LIMIT}, 0)",
        ),
        C(
            "pump feeds lower tank",
            pump_to_lower,
            ts=ts,
            unit="1/s",
            description="ẋ2 += c·u",
        ),
        C(
            "upper tank leak",
            linear_leak,
            tank=0,
            ts=ts,
            sign=1,
            unit="1/s",
            description="ẋ1 -= c·x1",
        ),
        C(
            "lower tank leak",
            linear_leak,
            tank=1,
            ts=ts,
            sign=1,
            unit="1/s",
            description="ẋ2 -= c·x2",
        ),
        C(
            "sensor bias",
            sensor_bias,
            target="measurement",
            unit="V",
            description="y += c",
        ),
    ]
    return tuple(out)


def build_model(
    theta, ts, library, q, r, prior, noise_prior: float | None = None
) -> dc.ChainModel:
    params = {"k": jnp.exp(jnp.asarray(theta[:3])), "ts": jnp.asarray(ts)}
    return dc.ChainModel(
        tank_step,
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
    theta, u, y, ts, quick: bool, noise_prior: float | None = None
) -> dict:
    """Steps 2-3: the workflow on 128-sample windows of the estimation record."""
    _, xs = _sim(jnp.asarray(theta), jnp.asarray(u), ts, ())
    xs = np.asarray(xs)
    q_levels = (0.9,) if quick else (0.6, 0.75, 0.9)
    x1_levels = np.quantile(xs[:, 0], q_levels)
    x2_levels = (9.0,) if quick else (8.5, 9.5)
    library = tank_library(ts, x1_levels, x2_levels)
    model = build_model(
        theta,
        ts,
        library,
        q=np.array([0.05, 0.05]),
        r=np.array([0.05]),
        prior=np.array([1.0, 0.2]),
        noise_prior=noise_prior,
    )
    data = windows(u, y, xs, WINDOW)
    found = dc.find(model, data)
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
    named = dc.name(found, data, max_terms=2)
    added = dc.add(found, named, data)
    print(f"verdict: {named['verdict']}")
    for c in added["coefficients"]:
        print(
            f"  {c['name']}: {c['value']:.4g} ± {c['std_error']:.2g} "
            f"(sign ok: {c['sign_ok']})"
        )
    for flag in added["flags"]:
        print(f"  flag: {flag}")
    named_candidates = tuple(library[model.index(nm)] for nm in named["named"])
    return {
        "xs": xs,
        "x1_levels": x1_levels.tolist(),
        "x2_levels": list(x2_levels),
        "named_candidates": named_candidates,
        "report": dc.to_json({"find": found, "name": named, "add": added}),
    }


def add_and_show(theta, d, xs, named_candidates) -> dict:
    """Step 4: add the named effects, then characterise the upper tank's
    overflow (its level, and whether the spill reaches the lower tank) by the
    estimation-record fit of a few overflow candidates; the validation
    record is simulated after each stage but never used to choose."""
    u, y, ts = d["u_est"], d["y_est"], d["ts"]

    def stage(label, cands, theta_start, named_by_workflow):
        refit = fit_output_error(u, y, ts, theta_start, cands)
        val = validation_rmse(refit["theta"], d["u_val"], d["y_val"], ts, cands)
        row = {
            "added": label,
            "named_by_workflow": named_by_workflow,
            "coefficients": refit["theta"][5:].tolist(),
            "k": np.exp(refit["theta"][:3]).tolist(),
            "estimation_rmse": refit["rmse"],
            "validation_rmse": val["rmse"],
        }
        return row, refit["theta"]

    stages, extras = [], ()
    for cand in named_candidates:
        start = 1.0 if cand.target == "measurement" else 0.01
        extras = extras + (cand,)
        row, theta = stage(cand.name, extras, np.r_[theta, start], True)
        stages.append(row)
    overflow_fits = []
    for q in (0.6, 0.75, 0.9):
        lv = round(float(np.quantile(xs[:, 0], q)), 2)
        for fn, where in ((overflow_lost, "lost"), (overflow_to_lower, "to lower")):
            cand = dc.Candidate.from_function(
                f"upper overflow > {lv} ({where})", fn, level=lv, ts=ts
            )
            row, _ = stage(cand.name, extras + (cand,), np.r_[theta, 0.01], False)
            overflow_fits.append(row)
    stages.append(min(overflow_fits, key=lambda r: r["estimation_rmse"]))
    return {
        "stages": stages,
        "overflow_candidates": [
            {k: r[k] for k in ("added", "estimation_rmse", "validation_rmse")}
            for r in overflow_fits
        ],
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--out", type=Path, default=REPO / "results/tanks")
    parser.add_argument("--quick", action="store_true", help="smaller library (CI)")
    parser.add_argument(
        "--noise-prior",
        type=float,
        default=None,
        help="standard deviation of a normal prior on the log noise multipliers "
        "(ChainModel.noise_scale_prior); default: none",
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

    # 1. The nominal model, fitted by simulation error on the estimation record.
    theta0 = np.array([np.log(0.05), np.log(0.05), np.log(0.05), y[0], y[0]])
    nominal = fit_output_error(u, y, ts, theta0)
    theta = nominal["theta"]
    val_before = validation_rmse(theta, d["u_val"], d["y_val"], ts)
    print(
        f"nominal: k1 k3 k4 = {np.exp(theta[:3]).round(4).tolist()}, "
        f"estimation RMSE {nominal['rmse']:.3f} V, validation RMSE "
        f"{val_before['rmse']:.3f} V"
    )
    # 2-3. Find and name; 4. add and show.
    wf = find_and_name(theta, u, y, ts, args.quick, args.noise_prior)
    after = add_and_show(theta, d, wf["xs"], wf["named_candidates"])
    for row in after["stages"]:
        print(
            f"+ {row['added']}: estimation RMSE {row['estimation_rmse']:.3f} V, "
            f"validation RMSE {row['validation_rmse']:.3f} V "
            f"(nominal {val_before['rmse']:.3f} V)"
        )
    summary = {
        "seconds": time.perf_counter() - t_start,
        "quick": args.quick,
        "noise_prior": args.noise_prior,
        "nominal": {
            "k": np.exp(theta[:3]).tolist(),
            "estimation_rmse": nominal["rmse"],
            "validation_rmse": val_before["rmse"],
        },
        "x1_levels": wf["x1_levels"],
        "x2_levels": wf["x2_levels"],
        "workflow": wf["report"],
        "after": after,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "report.json").write_text(json.dumps(summary, indent=1, default=str))
    print(f"{summary['seconds']:.0f} s; wrote {args.out / 'report.json'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
