"""Time per Gauss-Newton iteration on smoothing chains, per linear solver.

Two problems (see /work/shared/DESIGN.md "Benchmarks convention"):

- `disk`: the paper's disk dynamics with drag, 4-D Euclidean state
  (p, v), position measurements;
- `se2vel`: a planar car, state (SE(2) pose, 2-D body velocity) as two
  variable groups, constant-velocity dynamics, velocity and GPS-like
  position measurements, a prior on the first pose (block size 5).

One "iteration" = linearise every factor + solve the normal equations +
retract, jitted. `median_s` is the median over repeats after warm-up;
`compile_s` is first call minus median; `temp_bytes` is XLA's temporary
buffer estimate for the compiled iteration.

Each jitted call pays for its scratch buffer: XLA:CPU allocates it per call,
and for long chains (222 MiB at T = 1e5) the kernel zero-fills every fresh
page, which is system time that grows with T but is not the solver's work.
A user's solve runs all its iterations inside one call, so the script also
times `least_squares(..., FixedStepGaussNewton(solver, num_steps=N))` (the
public API, N = `--solve-steps`, default 10; N + 1 linearisations, N
solves and retractions, cost history) and reports `solve_ms_per_step` =
its median / N, with `solve_compile_s` its compile time. Both figures are
kept; neither replaces the other.

    python benchmarks/chain.py                 # T = 1e2 .. 1e5
    python benchmarks/chain.py --quick         # T = 1e2, 1e3 (CI)
    python benchmarks/chain.py --json benchmarks/results/chain.json
    python benchmarks/chain.py --stages --sizes 10000 100000 --json ...

`--stages` times the parts of one BlockTridiagonal iteration separately
(linearise, assemble the blocks, factorise, solve, retract), each jitted on
its own, to show which part grows faster than T.
"""

import argparse
import resource

import jax
import jax.numpy as jnp
import numpy as np
from _common import markdown_table, time_fn, write_json

import eqsmooth as eqs
from eqsmooth.solve._linear._block_tridiagonal import (
    assemble_chain,
    chain_plan,
    cyclic_reduction_factor,
    cyclic_reduction_solve,
)
from eqsmooth.solve._linearization import linearize, retract_values, zeros_tangent


jax.config.update("jax_enable_x64", True)


def _disk_dyn(a, b, data, params):
    p, v = a[:2], a[2:]
    return b - jnp.concatenate([p + v, v - 0.05 * p - 0.0075 * jnp.sign(v) * v * v])


def _disk_meas(x, data, params):
    return x[:2] - data


def disk_problem(T: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    meas = jnp.asarray(rng.normal(scale=20.0, size=(T, 2)))
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _disk_dyn,
                (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])),
                eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 2.0, 2.0])),
            ),
            eqs.FunctionFactor(
                _disk_meas,
                (eqs.Var("x", t),),
                eqs.IsotropicNoise.from_sigma(5.0),
                data=meas,
            ),
        ]
    )
    values = {"x": jnp.concatenate([meas, jnp.zeros((T, 2))], axis=1)}
    return graph, values


DT = 0.1


def _car_dyn(pose_a, vel_a, pose_b, vel_b, data, params):
    twist = jnp.stack([vel_a[0] * DT, jnp.zeros_like(vel_a[0]), vel_a[1] * DT])
    pred = pose_a @ eqs.SE2.exp(twist)
    return jnp.concatenate([(pred.inverse() @ pose_b).log(), vel_b - vel_a])


def _car_vel(vel, data, params):
    return vel - data


def _car_gps(pose, data, params):
    return pose.translation() - data


def se2vel_problem(T: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    vel = jnp.asarray(np.stack([5 + rng.normal(size=T), 0.3 * np.sin(t / 50)], 1))
    gps = (
        jnp.asarray(rng.normal(scale=1.0, size=(T, 2))) + jnp.cumsum(vel[:, :1], 0) * DT
    )
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(
                _car_dyn,
                (
                    eqs.Var("pose", t[:-1]),
                    eqs.Var("vel", t[:-1]),
                    eqs.Var("pose", t[1:]),
                    eqs.Var("vel", t[1:]),
                ),
                eqs.DiagonalNoise.from_sigmas(jnp.array([0.05, 0.05, 0.01, 0.5, 0.1])),
            ),
            eqs.FunctionFactor(
                _car_vel,
                (eqs.Var("vel", t),),
                eqs.IsotropicNoise.from_sigma(0.5),
                data=vel,
            ),
            eqs.FunctionFactor(
                _car_gps,
                (eqs.Var("pose", t),),
                eqs.IsotropicNoise.from_sigma(2.0),
                data=gps,
            ),
            eqs.PriorFactor(
                eqs.Var("pose", [0]),
                eqs.SE2.identity((1,)),
                eqs.IsotropicNoise(sqrt_precision=100.0),
            ),
        ]
    )
    values = {
        "pose": eqs.SE2.exp(jnp.asarray(rng.normal(scale=0.1, size=(T, 3)))),
        "vel": vel,
    }
    return graph, values


def make_iteration(linear_solver):
    @jax.jit
    def iteration(graph, values):
        lin = linearize(graph, values)
        delta, result = eqs.solve.solve_normal(linear_solver, lin)
        return retract_values(values, delta), lin.cost

    return iteration


def make_solve(linear_solver, num_steps: int):
    solver = eqs.FixedStepGaussNewton(linear_solver, num_steps=num_steps)

    @jax.jit
    def solve(graph, values):
        sol = eqs.least_squares(graph, values, solver, throw=False)
        return sol.value, sol.stats["final_cost"]

    return solve


def _faults_per_call(fn, *args, calls: int = 5) -> tuple[float, float]:
    """Minor page faults and system CPU seconds per call, after warm-up.

    XLA:CPU allocates a program's scratch buffer on every call; when malloc
    hands out fresh pages the kernel zero-fills each one (see
    docs/getting-started.md), which shows up here.
    """
    jax.block_until_ready(fn(*args))
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    for _ in range(calls):
        jax.block_until_ready(fn(*args))
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return (r1.ru_minflt - r0.ru_minflt) / calls, (r1.ru_stime - r0.ru_stime) / calls


def stage_records(problem: str, build, T: int) -> list[dict]:
    """Median time of each part of one BlockTridiagonal iteration, jitted apart."""
    graph, values = build(T)
    lin_fn = jax.jit(linearize)
    lin = lin_fn(graph, values)
    plan = chain_plan(lin)
    assemble = jax.jit(lambda lin: assemble_chain(lin, plan, None))
    diag, upper, grad = assemble(lin)
    factor = jax.jit(cyclic_reduction_factor)
    state = factor(diag, upper)
    stages = {
        "linearize": (lin_fn, (graph, values)),
        "assemble": (assemble, (lin,)),
        "factor": (factor, (diag, upper)),
        "solve": (jax.jit(cyclic_reduction_solve), (state, grad)),
        "retract": (jax.jit(retract_values), (values, zeros_tangent(lin))),
    }
    records = []
    for stage, (fn, args) in stages.items():
        first, median, _ = time_fn(fn, *args, repeats=7)
        records.append(
            {
                "benchmark": "chain_stages",
                "config": {"problem": problem, "T": T, "stage": stage},
                "problem": problem,
                "T": T,
                "stage": stage,
                "median_s": median,
                "median_ms": median * 1e3,
                "compile_s": first - median,
            }
        )
        print(f"{problem:7s} T={T:<7d} {stage:10s} {median * 1e3:9.2f} ms", flush=True)
    return records


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--json", default=None)
    parser.add_argument("--sizes", type=int, nargs="*", default=None)
    parser.add_argument("--problems", nargs="*", default=["disk", "se2vel"])
    parser.add_argument(
        "--solvers",
        nargs="*",
        default=["BlockTridiagonal", "PCG", "DenseCholesky", "SparseLU"],
    )
    parser.add_argument(
        "--stages", action="store_true", help="time the parts of an iteration"
    )
    parser.add_argument(
        "--solve-steps",
        type=int,
        default=10,
        help="N of the FixedStepGaussNewton solve timed per configuration "
        "(0: skip that measurement)",
    )
    parser.add_argument(
        "--tail-size",
        type=int,
        default=None,
        help="BlockTridiagonal(tail_size=...) (1 = cyclic reduction all the way "
        "down, the behaviour before the sequential tail; default 32)",
    )
    args = parser.parse_args(argv)
    sizes = args.sizes or ([100, 1000] if args.quick else [100, 1000, 10_000, 100_000])
    builders = {"disk": disk_problem, "se2vel": se2vel_problem}
    if args.stages:
        records = []
        for problem in args.problems:
            for T in sizes:
                records += stage_records(problem, builders[problem], T)
        print()
        print(markdown_table(records, ["problem", "T", "stage", "median_ms"]))
        if args.json:
            write_json(args.json, records)
        return
    solvers = {
        "BlockTridiagonal": (
            eqs.BlockTridiagonal()
            if args.tail_size is None
            else eqs.BlockTridiagonal(tail_size=args.tail_size)
        ),
        "PCG": eqs.PCG(),
        "DenseCholesky": eqs.DenseCholesky(),
        "SparseLU": eqs.solve.SparseLU(),
    }
    solvers = {k: v for k, v in solvers.items() if k in args.solvers}
    records = []
    for problem in args.problems:
        build = builders[problem]
        for T in sizes:
            graph, values = build(T)
            for name, ls in solvers.items():
                if name == "DenseCholesky" and T > 1000:
                    continue
                if name in ("PCG", "SparseLU") and T > 10_000:
                    continue
                it = make_iteration(ls)
                first, median, _ = time_fn(
                    it, graph, values, repeats=7 if T < 1e5 else 5
                )
                faults, sys_s = _faults_per_call(it, graph, values)
                mem = it.lower(graph, values).compile().memory_analysis()
                solve_rec = {}
                if args.solve_steps > 0 and name != "DenseCholesky":
                    s_first, s_median, _ = time_fn(
                        make_solve(ls, args.solve_steps),
                        graph,
                        values,
                        repeats=5 if T < 1e5 else 3,
                    )
                    solve_rec = {
                        "solve_steps": args.solve_steps,
                        "solve_ms_per_step": s_median / args.solve_steps * 1e3,
                        "solve_compile_s": s_first - s_median,
                    }
                rec = {
                    "benchmark": "chain",
                    "config": {
                        "problem": problem,
                        "T": T,
                        "solver": name,
                        "dtype": "float64",
                    },
                    "problem": problem,
                    "T": T,
                    "solver": name,
                    "median_s": median,
                    "median_ms": median * 1e3,
                    "compile_s": first - median,
                    "temp_MiB": getattr(mem, "temp_size_in_bytes", 0) / 2**20,
                    "page_faults": faults,
                    "sys_ms": sys_s * 1e3,
                    **solve_rec,
                }
                records.append(rec)
                print(
                    f"{problem:7s} T={T:<7d} {name:17s} {median * 1e3:9.2f} ms/iter "
                    f"compile {first - median:6.2f} s  {faults:8.0f} page faults "
                    f"{sys_s * 1e3:6.1f} ms sys"
                    + (
                        f"; in a {args.solve_steps}-step solve "
                        f"{solve_rec['solve_ms_per_step']:8.2f} ms/step, compile "
                        f"{solve_rec['solve_compile_s']:5.2f} s"
                        if solve_rec
                        else ""
                    ),
                    flush=True,
                )
    # linear-scaling ratio of the structured solver
    for problem in ("disk", "se2vel"):
        bt = {
            r["T"]: r
            for r in records
            if r["problem"] == problem and r["solver"] == "BlockTridiagonal"
        }
        if 10_000 in bt and 100_000 in bt:
            ratio = bt[100_000]["median_s"] / bt[10_000]["median_s"]
            bt[100_000]["ratio_1e5_over_1e4"] = ratio
            line = f"{problem}: t(1e5)/t(1e4) = {ratio:.2f} per jitted iteration"
            if "solve_ms_per_step" in bt[10_000] and "solve_ms_per_step" in bt[100_000]:
                solve_ratio = (
                    bt[100_000]["solve_ms_per_step"] / bt[10_000]["solve_ms_per_step"]
                )
                bt[100_000]["solve_ratio_1e5_over_1e4"] = solve_ratio
                line += f", {solve_ratio:.2f} per step inside a solve"
            print(line + " (BlockTridiagonal)")
    print()
    print(
        markdown_table(
            records,
            [
                "problem",
                "T",
                "solver",
                "median_ms",
                "compile_s",
                "temp_MiB",
                "page_faults",
                "sys_ms",
                "solve_ms_per_step",
                "solve_compile_s",
            ],
        )
    )
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
