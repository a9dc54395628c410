"""What asking for full float32 precision costs on this machine (A/B, one process).

Off the CPU, eqsmooth's own matrix products ask for `Precision.HIGHEST`
(`eqsmooth/_precision.py`): on GPUs with tensor cores JAX's default would
round float32 operands to TF32. XLA:CPU computes float32 products in
float32 either way, but keeps a product that names a precision as a `dot`
instead of rewriting a small one as fused arithmetic. This script measures
what naming it would cost on this backend, alternating the two programs in
one process (`highest`: traced as for a GPU, by patching the backend that
`eqsmooth._precision` reads; `default`: as traced here), with fresh
compilations for each, in float32 and float64:

- `se2vel` and `vehicle` chains of T states (benchmarks/chain.py's
  problems), a `FixedStepGaussNewton` solve of `--steps` steps with the
  default block-tridiagonal solver;
- `pose2`: the 5-pose SE(2) loop of GTSAM's example, a Levenberg-Marquardt
  solve in `jax.jit`.

Records: `median_s` per configuration, and `ratio` (highest / default) per
problem and dtype. On a GPU both rows are HIGHEST (the library's choice
there): run it on a CPU.

    python benchmarks/precision_ab.py --json benchmarks/results/precision_ab.json
    python benchmarks/precision_ab.py --quick
"""

import argparse
import statistics

import jax
import jax.numpy as jnp
from _common import markdown_table, pose2_problem, time_fn, write_json
from chain import se2vel_problem, vehicle_problem

import eqsmooth as eqs
import eqsmooth._precision as precision


jax.config.update("jax_enable_x64", True)


def _cast(tree, dtype):
    return jax.tree_util.tree_map(
        lambda a: a.astype(dtype) if eqx_inexact(a) else a, tree
    )


def eqx_inexact(a) -> bool:
    return isinstance(a, jax.Array) and jnp.issubdtype(a.dtype, jnp.floating)


def _problems(T: int, steps: int):
    chain_solver = eqs.FixedStepGaussNewton(num_steps=steps)
    for name, build in (("se2vel", se2vel_problem), ("vehicle", vehicle_problem)):
        graph, values = build(T)
        yield name, graph, values, chain_solver
    graph, values = pose2_problem()
    yield "pose2", graph, values, eqs.LevenbergMarquardt()


def _timed(graph, values, solver, repeats: int) -> tuple[float, float]:
    @jax.jit
    def solve(graph, values):
        sol = eqs.least_squares(graph, values, solver, throw=False)
        return sol.value, sol.stats["final_cost"]

    first, median, _ = time_fn(solve, graph, values, repeats=repeats)
    return first, median


def main(argv=None) -> list[dict]:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--size", type=int, default=2000, help="chain length T")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--json")
    a = p.parse_args(argv)
    if a.quick:
        a.size, a.rounds, a.repeats = 200, 1, 3
    records = []
    for name, graph, values, solver in _problems(a.size, a.steps):
        for dtype in (jnp.float32, jnp.float64):
            g, v = _cast(graph, dtype), _cast(values, dtype)
            times = {"highest": [], "default": []}
            real = precision._backend
            for _ in range(a.rounds):
                for setting in times:
                    precision._backend = (
                        (lambda: "gpu") if setting == "highest" else real
                    )
                    jax.clear_caches()
                    times[setting].append(_timed(g, v, solver, a.repeats))
            precision._backend = real
            med = {s: statistics.median(m for _, m in t) for s, t in times.items()}
            for setting, t in times.items():
                records.append(
                    {
                        "benchmark": "precision_ab",
                        "config": {
                            "problem": name,
                            "T": a.size if name != "pose2" else 5,
                            "dtype": jnp.dtype(dtype).name,
                            "precision": setting,
                            "backend": jax.default_backend(),
                        },
                        "median_s": med[setting],
                        "compile_s": statistics.median(f - m for f, m in t),
                        "ratio": med["highest"] / med["default"],
                    }
                )
    rows = [
        {**r["config"], "median_ms": 1e3 * r["median_s"], "ratio": r["ratio"]}
        for r in records
    ]
    print(
        markdown_table(
            rows, ["problem", "T", "dtype", "precision", "median_ms", "ratio"]
        )
    )
    if a.json:
        write_json(a.json, records)
    return records


if __name__ == "__main__":
    main()
