"""Time per solve of a 5-pose SE(2) graph after compilation, beside GTSAM.

The graph is `_common.pose2_problem` (a prior, 4 odometry factors and a loop
closure), solved again and again from the same initial values by `api`
(`eqs.least_squares(graph, values, LevenbergMarquardt())` from Python, as a
user calls it), `jit` (the same solve inside one `jax.jit` of the arrays,
`throw=False`) and `gtsam` (`LevenbergMarquardtOptimizer` on the same
factors, relative error tolerance 1e-8), when gtsam is importable;
`median_ms` / `min_ms` over `--repeats` calls after warm-up.

`--batch N`: N copies with perturbed odometry and initial values, solved by
one `eqs.least_squares_batch` call (its first call reported apart) against a
Python loop of GTSAM's optimizer; the largest difference of the solutions is
printed. Each timing is the median of `--repeats` batches. `--mixed`: the N
graphs are SE(2) loops of 5 to 8 poses with 1 to 3 closures (other sizes
and connectivity), padded to one bucket (`_mixed_bucket`: 12 poses and 12
rows per stack, the prior's one row kept) so that one call solves them all.

`--other-graphs K`: after the 5-pose loop, K more SE(2) loops of 5 to 8 poses
with 1 to 3 loop closures each (one factor stack per type, so the factor
types are the same; sizes and connectivity differ), each solved once as a
user would: `static` (`eqs.least_squares(..., pad_to=None)`, the graph as
built) and `default` (`eqs.least_squares`, which pads to power-of-two buckets),
in one process; per graph, the time to the answer and the XLA programs
compiled (JAX's compile events), and the largest pose difference between the
two answers. Then the later-solve medians of the 5-pose loop: `static`,
`default` (padding, solve and unpad each time) and `padded_solve_only`
(`pad_graph` once), beside GTSAM's.

    python -m benchmarks.small_graph --json benchmarks/results/small_graph.json
    python -m benchmarks.small_graph --batch 1000 --repeats 5 \\
        --json benchmarks/results/small_graph_batch.json
    python -m benchmarks.small_graph --batch 1000 --mixed --repeats 5 \\
        --json benchmarks/results/small_graph_batch_mixed.json
    python -m benchmarks.small_graph --other-graphs 12 \\
        --json benchmarks/results/small_graph_structure.json

`--floor` adds a row `floor`: `_floor_lm`, a Levenberg-Marquardt loop
written here with as few operations as it can have (the same closed-form
linearisation, then a dense `J`, `JᵀJ`, one Cholesky and one trial
linearisation per iteration; no result codes, no derivative rules, no
checks). It is not a solver of the library: it measures how close to
GTSAM XLA:CPU gets on this problem with the library's linearisation, so
that the gap of `jit` to GTSAM splits into what the solver adds and what
the runtime costs. `--sync-dispatch` sets JAX's
`jax_cpu_enable_async_dispatch` to False before the first computation
(JAX reads it once, so the comparison is two processes):

    for d in "" --sync-dispatch; do python -m benchmarks.small_graph --floor \\
        --repeats 300 $d --json benchmarks/results/small_graph_floor${d:+_sync}.json
    done
    python -m benchmarks.small_graph --floor --batch 1000 --repeats 5 \\
        --json benchmarks/results/small_graph_batch_floor.json

`--decompose` splits one solve's time into a fixed part and a part per
step, for the library's LM inside `jax.jit`, the `floor` and GTSAM, in one
process: each is timed with its iteration cap at 1, 2, 3 and 4 steps (none
converges before 5 on this graph), and a straight line through the medians
gives `fixed_us` (its intercept) and `per_step_us` (its slope). Beside them,
`round_trip`: a `jax.jit` with the same arguments and outputs as the `jit`
row that computes nothing (what passing the graph in and the values out
costs), and `flatten`: `jax.tree_util.tree_flatten` of those arguments
alone (JAX does it on every call):

    python -m benchmarks.small_graph --decompose --repeats 1000 \\
        --json benchmarks/results/small_graph_decompose.json
"""

import statistics
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs

from ._common import (
    cli,
    compile_log,
    machine,
    markdown_table,
    optional,
    pose2_problem,
    se2,
    time_host,
    write_json,
)


jax.config.update("jax_enable_x64", True)
GRAPH = "pose2 (5 SE(2) poses)"


def gtsam_case(gtsam, graph, values):
    """A GTSAM solve of the same factors: `(solve, cost_of_result)`."""
    g, init = gtsam_problem(gtsam, graph, values)
    return _gtsam_lm(gtsam, g, init, gtsam_params(gtsam)), g.error


def _gtsam_lm(gtsam, g, init, params):
    return lambda: gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()


def gtsam_problem(gtsam, graph, values):
    """The same factors and initial values in GTSAM: `(graph, values)`."""
    g, init = gtsam.NonlinearFactorGraph(), gtsam.Values()
    prior, between = graph.factors

    def sigmas(f):
        return gtsam.noiseModel.Diagonal.Sigmas(
            1.0 / np.asarray(f.noise.sqrt_precision)
        )

    def pose(p, i):
        return gtsam.Pose2(float(p.x()[i]), float(p.y()[i]), float(p.theta()[i]))

    g.add(gtsam.PriorFactorPose2(0, pose(prior.value, 0), sigmas(prior)))
    a, b = (np.asarray(v.ids) for v in between.variables)
    for i, (ia, ib) in enumerate(zip(a, b)):
        m = pose(between.measurement, i)
        g.add(gtsam.BetweenFactorPose2(int(ia), int(ib), m, sigmas(between)))
    for i in range(len(values["x"].x())):
        init.insert(i, pose(values["x"], i))
    return g, init


def gtsam_params(gtsam, max_iterations: int | None = None):
    """GTSAM's LM settings of every comparison here (relative tolerance 1e-8),
    optionally with an iteration cap."""
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-8)
    if max_iterations is not None:
        params.setMaxIterations(max_iterations)
    return params


def _times(fn, repeats: int, warm_up: bool = True) -> tuple[float, float]:
    """(median_s, min_s) of `fn()` over `repeats` calls (after one more)."""
    first, times, _ = time_host(fn, repeats if warm_up else repeats - 1)
    times = times if warm_up else [first, *times]
    return statistics.median(times), min(times)


def _floor_lm(graph, values, max_steps: int = 100):
    """The fewest-operations LM of `--floor`: `(values, cost, steps)`."""
    lin_mod = eqs.solve._linearization

    def linearise(v):
        lin = lin_mod.linearize_graph(graph, v)
        J, r = lin_mod.dense_jacobian(lin)
        return lin.layout, J, r, lin.cost

    layout, J, r, cost = linearise(values)
    eps = jnp.finfo(cost.dtype).eps

    def body(s):
        v, J, r, cost, lam, nu, k, _ = s
        H, g = J.T @ J, J.T @ r
        D = jnp.clip(jnp.diagonal(H), 1e-6, 1e32)
        L = jnp.linalg.cholesky(H + jnp.diag(lam * D))
        delta = jax.scipy.linalg.cho_solve((L, True), -g)
        nv = lin_mod.retract_values(v, lin_mod.unflatten_layout(layout, delta))
        _, nJ, nr, ncost = linearise(nv)
        Jd = J @ delta
        predicted = -g @ delta - 0.5 * Jd @ Jd
        gain = (cost - ncost) / jnp.where(predicted > 0, predicted, 1.0)
        accept = (predicted > 0) & (gain > 1e-3) & jnp.isfinite(ncost)
        converged = accept & (cost - ncost <= 1e-8 * cost)
        stalled = predicted <= 16 * eps * jnp.maximum(cost, 1.0)
        shrink = jnp.maximum(1 / 3, 1 - (2 * gain - 1) ** 3)
        lam = jnp.where(accept, lam * shrink, lam * nu)
        nu = jnp.where(accept, 2.0, 2 * nu)
        kept = jax.tree_util.tree_map(
            lambda a, b: jnp.where(accept, a, b), (nv, nJ, nr, ncost), (v, J, r, cost)
        )
        return (*kept, lam, nu, k + 1, converged | stalled)

    start = (values, J, r, cost, jnp.asarray(1e-8), jnp.asarray(2.0), 0, False)
    out = jax.lax.while_loop(lambda s: ~s[-1] & (s[-2] < max_steps), body, start)
    return out[0], out[3], out[6]


def _records(benchmark: str, key: str, rows: list[dict], seconds) -> list[dict]:
    config = {"graph": GRAPH, "dispatch": _dispatch()}
    print("load average", machine()["load_average"])
    return [
        {"benchmark": benchmark, "config": config | {key: r["method"]}}
        | {"median_s": seconds(r), "compile_s": 0.0, **r}
        for r in rows
    ]


def single(gtsam, repeats: int, floor: bool = False) -> list[dict]:
    graph, values = pose2_problem()
    solver = eqs.LevenbergMarquardt()
    dynamic, static = eqx.partition((graph, values), eqx.is_array)

    @jax.jit
    def compiled(dynamic):
        g, v = eqx.combine(dynamic, static)
        sol = eqs.least_squares(g, v, solver, throw=False)
        return eqx.filter(sol.value, eqx.is_array), sol.stats["final_cost"]

    @jax.jit
    def floor_compiled(dynamic):
        return _floor_lm(*eqx.combine(dynamic, static))[:2]

    def api():
        return jax.block_until_ready(eqs.least_squares(graph, values, solver).value)

    def jitted():
        return jax.block_until_ready(compiled(dynamic))

    cost = float(jitted()[1])
    calls = {"api": (api, lambda: cost), "jit": (jitted, lambda: cost)}
    if floor:
        floor_call = lambda: jax.block_until_ready(floor_compiled(dynamic))
        calls["floor"] = (floor_call, lambda: float(floor_call()[1]))
    if gtsam is not None:
        solve, error = gtsam_case(gtsam, graph, values)
        calls["gtsam"] = (solve, lambda: float(error(solve())))
    rows = []
    for name, (fn, final_cost) in calls.items():
        med, best = _times(fn, repeats)
        row = {"method": name, "median_ms": med * 1e3, "min_ms": best * 1e3}
        rows.append(row | {"final_cost": final_cost()})
    ref = calls.get("gtsam") and rows[-1]["median_ms"]
    for r in rows:
        r["ratio_to_gtsam"] = r["median_ms"] / ref if ref else float("nan")
    columns = ["method", "median_ms", "min_ms", "ratio_to_gtsam", "final_cost"]
    print(markdown_table(rows, columns))
    return _records("small_graph", "method", rows, lambda r: r["median_ms"] / 1e3)


def _line(points: list[tuple[int, float]]) -> tuple[float, float]:
    """Least-squares `(intercept, slope)` through `(steps, seconds)` points."""
    k, t = (np.array(c, dtype=float) for c in zip(*points))
    slope, intercept = np.polyfit(k, t, 1)
    return float(intercept), float(slope)


def decompose(gtsam, repeats: int) -> list[dict]:
    """`--decompose`: fixed and per-step time of one 5-pose solve."""
    graph, values = pose2_problem()
    solver = eqs.LevenbergMarquardt()
    dynamic, static = eqx.partition((graph, values), eqx.is_array)

    # Per method and iteration cap k (100: uncapped): (call, its step count).
    def library(k):
        @jax.jit
        def run(dynamic):
            g, v = eqx.combine(dynamic, static)
            sol = eqs.least_squares(g, v, solver, max_steps=k, throw=False)
            value = eqx.filter(sol.value, eqx.is_array)
            return value, sol.stats["final_cost"], sol.stats["num_steps"]

        return lambda: jax.block_until_ready(run(dynamic)), lambda: int(run(dynamic)[2])

    def floor(k):
        @jax.jit
        def run(dynamic):
            out, cost, steps = _floor_lm(*eqx.combine(dynamic, static), max_steps=k)
            return eqx.filter(out, eqx.is_array), cost, steps

        return lambda: jax.block_until_ready(run(dynamic)), lambda: int(run(dynamic)[2])

    def gtsam_lm(k):
        g, init = gtsam_problem(gtsam, graph, values)
        params = gtsam_params(gtsam, k if k < 100 else None)

        def steps():
            opt = gtsam.LevenbergMarquardtOptimizer(g, init, params)
            opt.optimize()
            return opt.iterations()

        return _gtsam_lm(gtsam, g, init, params), steps

    @jax.jit
    def round_trip(dynamic):
        g, v = eqx.combine(dynamic, static)
        return eqx.filter(v, eqx.is_array), jnp.zeros(()), jnp.zeros((), int)

    makers = {"jit": library, "floor": floor} | ({"gtsam": gtsam_lm} if gtsam else {})
    rows = []
    for name, make in makers.items():
        points = []
        for k in (1, 2, 3, 4):
            call, steps = make(k)
            points.append((steps(), _times(call, repeats)[0]))
        call, steps = make(100)
        fixed, per_step = _line(points)
        rows.append(
            {"method": name, "fixed_us": fixed * 1e6, "per_step_us": per_step * 1e6}
            | {"solve_us": _times(call, repeats)[0] * 1e6, "steps": steps()}
            | {"capped": [{"steps": s, "median_us": t * 1e6} for s, t in points]}
        )
    trip = _times(lambda: jax.block_until_ready(round_trip(dynamic)), repeats)[0]
    flat = _times(lambda: jax.tree_util.tree_flatten(dynamic), repeats)[0]
    rows.append({"method": "round_trip", "solve_us": trip * 1e6})
    rows.append({"method": "flatten", "solve_us": flat * 1e6})
    columns = ["method", "fixed_us", "per_step_us", "solve_us", "steps"]
    print(markdown_table(rows, columns))
    seconds = lambda r: r["solve_us"] / 1e6
    return _records("small_graph_decompose", "part", rows, seconds)


def _perturbed(graph, values, rng):
    """The 5-pose loop with its odometry and initial values perturbed."""
    prior, between = graph.factors

    def jitter(p, s_xy, s_theta):
        noise = [rng.normal(0, s, 5) for s in (s_xy, s_xy, s_theta)]
        parts = (p.x(), p.y(), p.theta())
        return eqs.SE2.from_xy_theta(
            *(c + jnp.asarray(n) for c, n in zip(parts, noise))
        )

    noisy = jitter(between.measurement, 0.05, 0.02)
    init = jitter(values["x"], 0.1, 0.05)
    between = eqs.BetweenFactor(*between.variables, noisy, between.noise)
    return eqs.FactorGraph([prior, between]), {"x": init}


def _mixed_bucket(n: int) -> int:
    """One bucket for every `--mixed` graph: the one-row prior stays one row;
    up to 8 poses and up to 10 odometry and closure rows pad to 12."""
    return 1 if n == 1 else 12


def _dispatch() -> str:
    return "async" if jax.config.values["jax_cpu_enable_async_dispatch"] else "sync"


def _row(method: str, num_graphs: int, median_s: float, **extra) -> dict:
    per_graph_us = median_s / num_graphs * 1e6
    row = {"method": method, "num_graphs": num_graphs, "median_s": median_s}
    return row | {"per_graph_us": per_graph_us, **extra}


def _first_and_median(run, repeats: int):
    """(result, first call s, median s of `repeats` more calls) of `run()`."""
    t0 = time.perf_counter()
    out = run()
    return out, time.perf_counter() - t0, _times(run, repeats, warm_up=False)[0]


def batch(
    gtsam, num_graphs: int, repeats: int, mixed: bool = False, floor: bool = False
) -> list[dict]:
    graph, values = pose2_problem()
    rng = np.random.default_rng(0)
    if mixed:  # other sizes and connectivity, padded to one bucket
        cases = [
            random_loop(rng, int(rng.integers(5, 9)), int(rng.integers(1, 4)))
            for _ in range(num_graphs)
        ]
        padded = [eqs.solve.pad_graph(g, v, bucket=_mixed_bucket) for g, v in cases]
        problems = [(p.graph, p.values) for p in padded]
    else:
        # Built on the host CPU: on a GPU each of these small eager
        # operations is a device round trip (10,000 graphs did not finish
        # their set-up in 190 s on an H200); `stack_trees` moves them once.
        with jax.default_device(jax.devices("cpu")[0]):
            cases = [_perturbed(graph, values, rng) for _ in range(num_graphs)]
        problems = cases
    graphs = eqs.learn.stack_trees([g for g, _ in problems])
    inits = eqs.learn.stack_trees([v for _, v in problems])
    solver = eqs.LevenbergMarquardt()

    def run():
        sol = eqs.least_squares_batch(graphs, inits, solver)
        return jax.block_until_ready(sol)

    sol, first_s, batch_s = _first_and_median(run, repeats)
    ours = np.asarray(sol.value["x"].x())
    steps = np.bincount(np.asarray(sol.stats["num_steps"])).tolist()
    method = "eqsmooth least_squares_batch"
    method += " (padded, mixed structures)" if mixed else ""
    rows = [_row(method, num_graphs, batch_s, first_call_s=first_s)]
    rows[0] |= {"graphs_by_num_steps": steps, "dispatch": _dispatch()}
    if floor:
        floor_batch = jax.jit(jax.vmap(_floor_lm))
        run = lambda: jax.block_until_ready(floor_batch(graphs, inits))
        (floor_values, _, floor_steps), first_s, floor_s = _first_and_median(
            run, repeats
        )
        diff = np.abs(np.asarray(floor_values["x"].x()) - ours).max()
        rows.append(
            _row("floor (fewest-operations LM, vmapped)", num_graphs, floor_s)
            | {"first_call_s": first_s}
            | {"graphs_by_num_steps": np.bincount(np.asarray(floor_steps)).tolist()}
            | {"max_abs_x_difference_to_eqsmooth": float(diff)}
            | {"dispatch": _dispatch()}
        )
    if gtsam is not None:
        solves = [gtsam_case(gtsam, g, v)[0] for g, v in cases]
        results = []

        def loop():
            results[:] = [s() for s in solves]

        gtsam_s = _times(loop, repeats, warm_up=False)[0]
        diff = max(
            abs(float(r.atPose2(i).x()) - float(ours[k, i]))
            for k, (r, (_, v)) in enumerate(zip(results, cases))
            for i in range(len(v["x"].x()))
        )
        rows.append(_row("gtsam loop", num_graphs, gtsam_s, max_abs_x_difference=diff))
        for row in rows[:-1]:
            row["speedup_over_gtsam"] = gtsam_s / row["median_s"]
    columns = ["method", "num_graphs", "median_s", "per_graph_us", "first_call_s"]
    columns += ["speedup_over_gtsam", "max_abs_x_difference"]
    print(markdown_table(rows, columns))
    return rows


def random_loop(rng, n: int, closures: int):
    """`n` SE(2) poses on a noisy walk, a prior on pose 0, odometry and
    `closures` loop closures to earlier poses (one BetweenFactor stack)."""
    steps = rng.normal(0, [1.0, 0.3, 0.4], (n, 3))
    truth = np.cumsum(steps, axis=0)
    pairs = [(i, i + 1) for i in range(n - 1)]
    pairs += [(n - 1 - k, int(rng.integers(0, n - 2 - k))) for k in range(closures)]
    a, b = (np.array(c) for c in zip(*pairs))

    true = se2(truth)
    noise = eqs.SE2.exp(jnp.asarray(rng.normal(0, 0.02, (len(a), 3))))
    meas = true[a].inverse() @ true[b] @ noise
    diag = eqs.DiagonalNoise.from_sigmas(jnp.array([0.2, 0.2, 0.1]))
    prior = eqs.PriorFactor(eqs.Var("x", [0]), true[np.array([0])], diag)
    loop = eqs.BetweenFactor(eqs.Var("x", a), eqs.Var("x", b), meas, diag)
    init = se2(truth + rng.normal(0, 0.1, truth.shape))
    return eqs.FactorGraph([prior, loop]), {"x": init}


def other_graphs(gtsam, count: int, repeats: int) -> list[dict]:
    compiled = compile_log()
    solver = eqs.LevenbergMarquardt()

    def static(graph, values):
        sol = eqs.least_squares(graph, values, solver, pad_to=None)
        return jax.block_until_ready(sol.value)

    def default(graph, values):  # pads to power-of-two buckets by itself
        return jax.block_until_ready(eqs.least_squares(graph, values, solver).value)

    rng = np.random.default_rng(0)
    problems = [pose2_problem()]
    problems += [
        random_loop(rng, int(rng.integers(5, 9)), int(rng.integers(1, 4)))
        for _ in range(count)
    ]
    rows = []
    for k, (graph, values) in enumerate(problems):
        row = {"graph": k, "poses": len(values["x"].x())}
        row["factors"] = sum(f.num_rows for f in graph.factors)
        answers = {}
        for name, fn in (("static", static), ("default", default)):
            start = len(compiled)
            t0 = time.perf_counter()
            answers[name] = fn(graph, values)["x"]
            row[f"{name}_s"] = time.perf_counter() - t0
            row[f"{name}_programs"] = len(compiled) - start
        diff = (answers["static"].inverse() @ answers["default"]).log()
        row["max_difference"] = float(jnp.max(jnp.abs(diff)))
        rows.append(row)
    print(markdown_table(rows, list(rows[0])))
    later = rows[1:]
    summary = {
        name: {
            "median_s_after_first": statistics.median(r[f"{name}_s"] for r in later),
            "max_s_after_first": max(r[f"{name}_s"] for r in later),
            "programs_after_first": sum(r[f"{name}_programs"] for r in later),
        }
        for name in ("static", "default")
    }
    graph, values = problems[0]
    once = eqs.solve.pad_graph(graph, values)
    calls = {
        "static": lambda: static(graph, values),
        "default": lambda: default(graph, values),
        "padded_solve_only": lambda: static(once.graph, once.values),
    }
    steady = {name: _times(call, repeats)[0] for name, call in calls.items()}
    if gtsam is not None:
        steady["gtsam"] = _times(gtsam_case(gtsam, graph, values)[0], repeats)[0]
    print("after the first graph:", summary)
    print("later solves of the 5-pose loop (median s):", steady)
    print("load average", machine()["load_average"])
    return [
        {
            "benchmark": "small_graph_structure",
            "config": {"graphs": count + 1, "solver": "LevenbergMarquardt"},
            "median_s": steady["default"],
            "compile_s": rows[0]["default_s"] - steady["default"],
            "graphs": rows,
            "after_first": summary,
            "later_solve_median_s": steady,
        }
    ]


def main(argv=None):
    parser = cli(__doc__)
    parser.add_argument("--repeats", type=int, default=None, help="200; 5 batches")
    parser.add_argument("--batch", type=int, default=0, metavar="N", help="N graphs")
    parser.add_argument("--mixed", action="store_true", help="other structures")
    parser.add_argument("--other-graphs", type=int, default=0, metavar="K")
    parser.add_argument("--floor", action="store_true", help="the fewest-op. LM")
    parser.add_argument("--decompose", action="store_true", help="fixed, per step")
    parser.add_argument("--sync-dispatch", action="store_true", help="before any run")
    parser.add_argument("--quick", action="store_true", help="20 repeats; N <= 20")
    args = parser.parse_args(argv)
    if args.sync_dispatch:
        jax.config.update("jax_cpu_enable_async_dispatch", False)
    gtsam = optional("gtsam")
    repeats = args.repeats or (5 if args.batch else 200)
    if args.quick:
        repeats, args.batch = min(repeats, 20), min(args.batch, 20)
    if args.other_graphs:
        count = min(args.other_graphs, 3 if args.quick else 10**6)
        records = other_graphs(gtsam, count, repeats)
    elif args.decompose:
        records = decompose(gtsam, repeats)
    elif args.batch:
        records = batch(gtsam, args.batch, repeats, args.mixed, args.floor)
    else:
        records = single(gtsam, repeats, args.floor)
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
