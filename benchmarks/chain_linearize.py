"""Before/after of the per-variable autodiff Jacobians, in one process.

`before` is `linearize_rows` of git `ac3878c` (one forward-mode Jacobian over
the concatenated tangent of a factor's variables, split afterwards), read
from git and run with this checkout's helpers; `after` is the library's. Each
variant is traced and compiled ahead of time (jax caches are cleared between
them so that no nested program is reused), then the calls alternate (the
first variant changes each round): `linearize` alone and a 10-step
`FixedStepGaussNewton(BlockTridiagonal())` solve (ms per step), per problem
and T. Wall time (median, min) and the process's CPU time (median; all of
XLA's threads, so less disturbed by other processes on a loaded machine).

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.chain_linearize \\
        --json benchmarks/results/chain_linearize.json
"""

import statistics
import subprocess
import time

import jax
import jax.numpy as jnp

import eqsmooth as eqs
import eqsmooth.factors._factor as factor_module
import eqsmooth.solve._linearization as lin_module

from ._common import cli, print_and_save, record, ROOT
from .chain import make_solve, se2vel_problem, vehicle_problem


BASE = "ac3878c"
NAMES = ("linearize_rows", "_cumsum", "_value_and_jacfwd")


def before_linearize_rows():
    """The base commit's `linearize_rows`, executed in this `_factor` module's
    namespace (same classes, so analytic factors still take their branch)."""
    src = subprocess.run(
        ["git", "show", f"{BASE}:eqsmooth/factors/_factor.py"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    ).stdout
    blocks = src.split("\n\n\n")
    wanted = [b for b in blocks if any(b.startswith(f"def {n}(") for n in NAMES)]
    namespace = dict(vars(factor_module))
    exec(compile("\n\n\n".join(wanted), f"{BASE}:_factor.py", "exec"), namespace)
    return namespace["linearize_rows"]


def compiled(variant, graph, values, steps):
    lin_module.linearize_rows = variant
    jax.clear_caches()
    lin = jax.jit(lin_module.linearize_graph).lower(graph, values).compile()
    solve = make_solve(eqs.BlockTridiagonal(), steps)
    t0 = time.perf_counter()
    solve = solve.lower(graph, values).compile()
    return lin, solve, time.perf_counter() - t0


def main(argv=None):
    parser = cli(__doc__)
    parser.add_argument("--sizes", type=int, nargs="*", default=[10_000, 100_000])
    parser.add_argument("--problems", nargs="*", default=["se2vel", "vehicle"])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=15)
    args = parser.parse_args(argv)
    after = lin_module.linearize_rows
    variants = {"before": before_linearize_rows(), "after": after}
    builders = {"se2vel": se2vel_problem, "vehicle": vehicle_problem}
    records = []
    for problem in args.problems:
        for T in args.sizes:
            graph, values = builders[problem](T)
            progs = {
                k: compiled(v, graph, values, args.steps) for k, v in variants.items()
            }
            lin_module.linearize_rows = after
            outs = [jax.block_until_ready(p[0](graph, values)) for p in progs.values()]
            leaves = [jax.tree_util.tree_leaves(o) for o in outs]
            diff = max(float(jnp.max(jnp.abs(a - b))) for a, b in zip(*leaves))
            times = {k: {p: [] for p in PARTS} for k in progs}
            repeats = args.repeats if T < 100_000 else max(3, args.repeats // 3)
            for i in range(repeats):
                order = list(progs) if i % 2 else list(progs)[::-1]
                for k in order:
                    lin, solve, _ = progs[k]
                    for part, fn in (("lin", lin), ("solve", solve)):
                        t0, c0 = time.perf_counter(), time.process_time()
                        jax.block_until_ready(fn(graph, values))
                        times[k][part].append(time.perf_counter() - t0)
                        times[k][part + "_cpu"].append(time.process_time() - c0)
            for k, (_, _, compile_s) in progs.items():
                t = times[k]
                config = {"problem": problem, "T": T, "variant": k}
                rec = record("chain_linearize", config)
                rec["linearize_ms"] = statistics.median(t["lin"]) * 1e3
                rec["linearize_min_ms"] = min(t["lin"]) * 1e3
                rec["linearize_cpu_ms"] = statistics.median(t["lin_cpu"]) * 1e3
                step = 1e3 / args.steps
                rec["solve_ms_per_step"] = statistics.median(t["solve"]) * step
                rec["solve_min_ms_per_step"] = min(t["solve"]) * step
                rec["solve_cpu_ms_per_step"] = statistics.median(t["solve_cpu"]) * step
                rec["solve_compile_s"] = compile_s
                rec["max_abs_diff"] = diff
                rec["repeats"] = repeats
                records.append(rec)
                print({c: rec[c] for c in COLUMNS}, flush=True)
    print_and_save(records, COLUMNS, args.json, extra={"base": BASE})


PARTS = ("lin", "lin_cpu", "solve", "solve_cpu")
COLUMNS = ["problem", "T", "variant", "linearize_ms", "linearize_min_ms"]
COLUMNS += ["linearize_cpu_ms", "solve_ms_per_step", "solve_min_ms_per_step"]
COLUMNS += ["solve_cpu_ms_per_step", "solve_compile_s"]
COLUMNS += ["max_abs_diff"]


if __name__ == "__main__":
    main()
