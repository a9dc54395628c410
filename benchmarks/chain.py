"""Time per Gauss-Newton iteration on smoothing chains, per linear solver.

Problems: `disk` (the paper's disk dynamics with drag, 4-D Euclidean state,
position measurements), `se2vel` (SE(2) pose and 2-D body velocity as two
groups, constant-velocity dynamics as a `FunctionFactor`, velocity and
GPS-like measurements, a prior; block size 5), `vehicle` (`VehicleState` with
the closed-form `VehicleDynamicsFactor`, same measurements; block size 5) and
`vehicle_autodiff` (its residual as a `FunctionFactor`). Default: `disk`, `se2vel`.

One iteration = linearise + solve the normal equations + retract, jitted:
`median_s` over repeats, `compile_s` = first call minus median, `temp_MiB`
XLA's scratch estimate, `page_faults` / `sys_ms` per call (XLA:CPU allocates
its scratch per call and the kernel zero-fills the pages). `solve_ms_per_step`
times `least_squares(..., FixedStepGaussNewton(solver, num_steps=N))` / N
(`--solve-steps`), as a user's solve runs, with `solve_compile_s`.

    python -m benchmarks.chain                 # T = 1e2 .. 1e5
    python -m benchmarks.chain --quick         # T = 1e2, 1e3
    python -m benchmarks.chain --json benchmarks/results/chain.json

`--stages` splits a BlockTridiagonal iteration into `linearize`, `factorize`
(assembly + factorisation), `solve` (back substitution), `retract` and `cost`,
each jitted through the public API: median time, XLA's flop and byte counts
and the rates they imply, beside this core's `peak_gflops` (a large matrix
product) and `read_GBps` (summing 128 MiB), measured in the same process.

    python -m benchmarks.chain --stages --problems se2vel --sizes 10000 100000 \\
        --json benchmarks/results/chain_stages.json
"""

import resource

import jax
import jax.numpy as jnp
import numpy as np

import eqsmooth as eqs

from ._common import (
    cli,
    disk_dynamics,
    disk_position,
    print_and_save,
    record,
    time_fn,
    xla_cost,
)


jax.config.update("jax_enable_x64", True)


def disk_problem(T: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    meas = jnp.asarray(rng.normal(scale=20.0, size=(T, 2)))
    steps = (eqs.Var("x", t[:-1]), eqs.Var("x", t[1:]))
    dyn_noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.1, 0.1, 2.0, 2.0]))
    meas_noise = eqs.IsotropicNoise.from_sigma(5.0)
    dyn = eqs.FunctionFactor(disk_dynamics, steps, dyn_noise)
    fix = eqs.FunctionFactor(disk_position, (eqs.Var("x", t),), meas_noise, data=meas)
    init = jnp.concatenate([meas, jnp.zeros((T, 2))], axis=1)
    return eqs.FactorGraph([dyn, fix]), {"x": init}


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
    gps = jnp.asarray(rng.normal(scale=1.0, size=(T, 2)))
    gps = gps + jnp.cumsum(vel[:, :1], 0) * DT
    pose, v = (eqs.Var("pose", t), eqs.Var("vel", t))
    steps = (eqs.Var("pose", t[:-1]), eqs.Var("vel", t[:-1]))
    steps += (eqs.Var("pose", t[1:]), eqs.Var("vel", t[1:]))
    dyn_noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.05, 0.05, 0.01, 0.5, 0.1]))
    iso = eqs.IsotropicNoise.from_sigma
    prior_noise = eqs.IsotropicNoise(sqrt_precision=100.0)
    graph = eqs.FactorGraph(
        [
            eqs.FunctionFactor(_car_dyn, steps, dyn_noise),
            eqs.FunctionFactor(_car_vel, (v,), iso(0.5), data=vel),
            eqs.FunctionFactor(_car_gps, (pose,), iso(2.0), data=gps),
            eqs.PriorFactor(eqs.Var("pose", [0]), eqs.SE2.identity((1,)), prior_noise),
        ]
    )
    poses = eqs.SE2.exp(jnp.asarray(rng.normal(scale=0.1, size=(T, 3))))
    return graph, {"pose": poses, "vel": vel}


def _vehicle_motion_residual(prev, next, data, params):
    return eqs.local(eqs.factors.vehicle_motion(prev, DT), next)


def _vehicle_gps(x, data, params):
    return x.pose.translation() - data


def vehicle_problem(T: int, seed: int = 0, closed_form: bool = True):
    """The library's planar vehicle (`VehicleState`: SE(2) pose and `(v, ω)`
    in one variable, block size 5): `VehicleDynamicsFactor` (closed-form
    Jacobians; with `closed_form=False` the same residual as a
    `FunctionFactor`, linearised by forward-mode autodiff),
    `VelocityMeasurementFactor`, GPS-like positions, a prior on the first
    state."""
    rng = np.random.default_rng(seed)
    t = np.arange(T)
    vel = np.stack([5 + rng.normal(size=T), 0.3 * np.sin(t / 50)], 1)
    gps = rng.normal(scale=1.0, size=(T, 2)) + np.cumsum(vel[:, :1], 0) * DT
    x = eqs.Var("x", t)
    prev, next = eqs.Var("x", t[:-1]), eqs.Var("x", t[1:])
    dyn_noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.05, 0.05, 0.01, 0.5, 0.1]))
    if closed_form:
        dyn = eqs.factors.VehicleDynamicsFactor(prev, next, dyn_noise, dt=DT)
    else:
        dyn = eqs.FunctionFactor(_vehicle_motion_residual, (prev, next), dyn_noise)
    iso = eqs.IsotropicNoise.from_sigma
    first = eqs.factors.VehicleState(eqs.SE2.identity((1,)), jnp.asarray(vel[:1]))
    prior_noise = eqs.IsotropicNoise(sqrt_precision=100.0)
    graph = eqs.FactorGraph(
        [
            dyn,
            eqs.factors.VelocityMeasurementFactor(x, vel, iso(0.5)),
            eqs.FunctionFactor(_vehicle_gps, (x,), iso(2.0), data=jnp.asarray(gps)),
            eqs.PriorFactor(eqs.Var("x", [0]), first, prior_noise),
        ]
    )
    poses = eqs.SE2.exp(jnp.asarray(rng.normal(scale=0.1, size=(T, 3))))
    return graph, {"x": eqs.factors.VehicleState(poses, jnp.asarray(vel))}


def make_iteration(linear_solver):
    @jax.jit
    def iteration(graph, values):
        lin = eqs.linearize(graph, values)
        delta, result = eqs.solve.solve_normal(linear_solver, lin)
        return {k: eqs.retract(v, delta[k]) for k, v in values.items()}, lin.cost

    return iteration


def make_solve(linear_solver, num_steps: int):
    solver = eqs.FixedStepGaussNewton(linear_solver, num_steps=num_steps)

    @jax.jit
    def solve(graph, values):
        sol = eqs.least_squares(graph, values, solver, throw=False)
        return sol.value, sol.stats["final_cost"]

    return solve


def _faults_per_call(fn, *args, calls: int = 5) -> tuple[float, float]:
    """Minor page faults and system CPU seconds per call, after warm-up."""
    jax.block_until_ready(fn(*args))
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    for _ in range(calls):
        jax.block_until_ready(fn(*args))
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return (r1.ru_minflt - r0.ru_minflt) / calls, (r1.ru_stime - r0.ru_stime) / calls


def measure(problem, T, graph, values, name, ls, solve_steps) -> dict:
    it = make_iteration(ls)
    first, median, _ = time_fn(it, graph, values, repeats=7 if T < 1e5 else 5)
    faults, sys_s = _faults_per_call(it, graph, values)
    mem = it.lower(graph, values).compile().memory_analysis()
    config = {"problem": problem, "T": T, "solver": name, "dtype": "float64"}
    rec = record("chain", config, median_s=median, median_ms=median * 1e3)
    rec |= {"compile_s": first - median, "page_faults": faults, "sys_ms": sys_s * 1e3}
    rec["temp_MiB"] = getattr(mem, "temp_size_in_bytes", 0) / 2**20
    text = ""
    if solve_steps > 0 and name != "DenseCholesky":
        solve = make_solve(ls, solve_steps)
        s_first, s_med, _ = time_fn(solve, graph, values, repeats=5 if T < 1e5 else 3)
        rec["solve_steps"] = solve_steps
        rec["solve_ms_per_step"] = s_med / solve_steps * 1e3
        rec["solve_compile_s"] = s_first - s_med
        text = (
            f"; in a {solve_steps}-step solve {rec['solve_ms_per_step']:8.2f} "
            f"ms/step, compile {rec['solve_compile_s']:5.2f} s"
        )
    print(
        f"{problem:7s} T={T:<7d} {name:17s} {median * 1e3:9.2f} ms/iter compile "
        f"{first - median:6.2f} s {faults:8.0f} page faults {sys_s * 1e3:6.1f} "
        f"ms sys{text}",
        flush=True,
    )
    return rec


def scaling(records) -> None:
    """t(1e5) / t(1e4) of BlockTridiagonal, added to the T = 1e5 record."""
    for problem in ("disk", "se2vel", "vehicle", "vehicle_autodiff"):
        bt = {r["T"]: r for r in records if r["problem"] == problem}
        bt = {T: r for T, r in bt.items() if r["solver"] == "BlockTridiagonal"}
        if 10_000 not in bt or 100_000 not in bt:
            continue
        small, large = bt[10_000], bt[100_000]
        large["ratio_1e5_over_1e4"] = large["median_s"] / small["median_s"]
        ratio = large["ratio_1e5_over_1e4"]
        line = f"{problem}: t(1e5)/t(1e4) = {ratio:.2f} per jitted iteration"
        if "solve_ms_per_step" in small and "solve_ms_per_step" in large:
            ratio = large["solve_ms_per_step"] / small["solve_ms_per_step"]
            large["solve_ratio_1e5_over_1e4"] = ratio
            line += f", {ratio:.2f} per step inside a solve"
        print(line + " (BlockTridiagonal)")


def machine_limits() -> dict:
    """The compute and memory rates one core reaches on easy work."""
    a = jnp.ones((1024, 1024))
    mm = jax.jit(lambda x: x @ x)
    _, t_mm, _ = time_fn(mm, a)
    big = jnp.ones((2**24,))  # 128 MiB, read once per call
    read = jax.jit(jnp.sum)
    _, t_read, _ = time_fn(read, big)
    return {
        "peak_gflops": 2 * 1024**3 / t_mm / 1e9,
        "read_GBps": big.nbytes / t_read / 1e9,
    }


def stages(problem, T, graph, values, limits) -> list[dict]:
    ls = eqs.BlockTridiagonal()
    lin = eqs.linearize(graph, values)
    factorize = jax.jit(lambda lin: eqs.solve.factorize(lin, ls))
    fac = factorize(lin)
    rhs = jax.tree_util.tree_map(
        jnp.ones_like,
        eqs.solve.NormalOperator(lin).mv(
            {g.name: jnp.zeros((g.count, g.dim)) for g in lin.layout}
        ),
    )
    back = jax.jit(lambda fac, b: ls.compute(fac, b, {})[0])
    delta = back(fac, rhs)
    retract = jax.jit(lambda v, d: {k: eqs.retract(v[k], 1e-3 * d[k]) for k in v})
    cost = jax.jit(lambda g, v: g.cost(v))
    parts = {
        "linearize": (jax.jit(eqs.solve.linearize), graph, values),
        "factorize": (factorize, lin),
        "solve": (back, fac, rhs),
        "retract": (retract, values, delta),
        "cost": (cost, graph, values),
        "iteration": (make_iteration(ls), graph, values),
    }
    records = []
    for stage, (fn, *args) in parts.items():
        _, median, _ = time_fn(fn, *args, repeats=7 if T < 1e5 else 5)
        flops, nbytes = xla_cost(fn.lower(*args).compile()).values()
        config = {"problem": problem, "T": T, "stage": stage}
        rec = record("chain_stages", config, median_s=median, median_ms=median * 1e3)
        rec |= {"us_per_step": median / T * 1e6, "mflops": flops / 1e6}
        rec |= {"MiB_accessed": nbytes / 2**20, "gflops": flops / median / 1e9}
        rec |= {"GBps": nbytes / median / 1e9} | limits
        print(
            f"{problem} T={T} {stage:10s} {median * 1e3:8.2f} ms "
            f"{rec['us_per_step']:6.3f} us/step {rec['mflops']:8.1f} MFLOP "
            f"{rec['MiB_accessed']:8.1f} MiB {rec['gflops']:6.2f} GFLOP/s "
            f"{rec['GBps']:6.2f} GB/s",
            flush=True,
        )
        records.append(rec)
    return records


STAGE_COLUMNS = ["problem", "T", "stage", "median_ms", "us_per_step", "mflops"]
STAGE_COLUMNS += ["MiB_accessed", "gflops", "GBps"]


# The largest T each linear solver is timed at.
LARGEST = {"BlockTridiagonal": 10**9, "PCG": 10_000, "DenseCholesky": 1000}
LARGEST["SparseLU"] = 10_000
COLUMNS = ["problem", "T", "solver", "median_ms", "compile_s", "temp_MiB"]
COLUMNS += ["page_faults", "sys_ms", "solve_ms_per_step", "solve_compile_s"]


def main(argv=None):
    parser = cli(__doc__)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--sizes", type=int, nargs="*", default=None)
    parser.add_argument("--problems", nargs="*", default=["disk", "se2vel"])
    parser.add_argument("--solvers", nargs="*", default=list(LARGEST))
    parser.add_argument("--solve-steps", type=int, default=10, help="0: no solve")
    parser.add_argument("--tail-size", type=int, help="BlockTridiagonal(tail_size=)")
    parser.add_argument("--stages", action="store_true", help="the parts of a step")
    args = parser.parse_args(argv)
    sizes = args.sizes or ([100, 1000] if args.quick else [100, 1000, 10_000, 100_000])
    builders = {
        "disk": disk_problem,
        "se2vel": se2vel_problem,
        "vehicle": vehicle_problem,
        "vehicle_autodiff": lambda T: vehicle_problem(T, closed_form=False),
    }
    if args.stages:
        limits = machine_limits()
        print(limits)
        records = []
        for problem in args.problems:
            for T in sizes:
                records += stages(problem, T, *builders[problem](T), limits)
        return print_and_save(records, STAGE_COLUMNS, args.json)
    tail = {} if args.tail_size is None else {"tail_size": args.tail_size}
    solvers = {
        "BlockTridiagonal": eqs.BlockTridiagonal(**tail),
        "PCG": eqs.PCG(),
        "DenseCholesky": eqs.DenseCholesky(),
        "SparseLU": eqs.solve.SparseLU(),
    }
    records = []
    for problem in args.problems:
        for T in sizes:
            graph, values = builders[problem](T)
            for name in args.solvers:
                if T <= LARGEST[name]:
                    ls, steps = solvers[name], args.solve_steps
                    records.append(measure(problem, T, graph, values, name, ls, steps))
    scaling(records)
    print_and_save(records, COLUMNS, args.json)


if __name__ == "__main__":
    main()
