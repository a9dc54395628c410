"""What asking for full float32 precision costs on this machine (A/B, one process).

Off the CPU, eqsmooth's own matrix products ask for `Precision.HIGHEST`
(`eqsmooth/_precision.py`): on GPUs with tensor cores JAX's default would
round float32 operands to TF32. XLA:CPU computes float32 products in
float32 either way, but keeps a product that names a precision as a `dot`
instead of rewriting a small one as fused arithmetic. This script measures
what naming it would cost on this backend, alternating the two programs in
one process (`highest`: traced under `jax.default_matmul_precision("highest")`,
which names it on every product as eqsmooth does off the CPU: the lowered
programs of these solves are the same text; `default`: as traced here), with
fresh compilations for each, in float32 and float64:

- `se2vel` and `vehicle` chains of T states (benchmarks/chain.py's
  problems), a `FixedStepGaussNewton` solve of `--steps` steps with the
  default block-tridiagonal solver;
- `pose2`: the 5-pose SE(2) loop of GTSAM's example, a Levenberg-Marquardt
  solve in `jax.jit`.

Records: `median_s` per configuration, and `ratio` (highest / default) per
problem and dtype. On a GPU both rows are HIGHEST (the library's choice
there): run it on a CPU.

    python -m benchmarks.precision_ab --json benchmarks/results/precision_ab.json
    python -m benchmarks.precision_ab --quick
"""

import contextlib
import statistics

import jax
import jax.numpy as jnp

import eqsmooth as eqs

from ._common import cli, pose2_problem, print_and_save, record, time_fn
from .chain import se2vel_problem, vehicle_problem


jax.config.update("jax_enable_x64", True)


SETTINGS = {
    "highest": lambda: jax.default_matmul_precision("highest"),
    "default": contextlib.nullcontext,
}


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
    p = cli(__doc__)
    p.add_argument("--size", type=int, default=2000, help="chain length T")
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--repeats", type=int, default=9)
    p.add_argument("--quick", action="store_true")
    a = p.parse_args(argv)
    if a.quick:
        a.size, a.rounds, a.repeats = 200, 1, 3
    records = []
    for name, graph, values, solver in _problems(a.size, a.steps):
        for dtype in (jnp.float32, jnp.float64):
            g, v = _cast(graph, dtype), _cast(values, dtype)
            times = {"highest": [], "default": []}
            for _ in range(a.rounds):
                for setting in times:
                    jax.clear_caches()
                    with SETTINGS[setting]():
                        times[setting].append(_timed(g, v, solver, a.repeats))
            med = {s: statistics.median(m for _, m in t) for s, t in times.items()}
            for setting, t in times.items():
                config = {"problem": name, "T": a.size if name != "pose2" else 5}
                config |= {"dtype": jnp.dtype(dtype).name, "precision": setting}
                config["backend"] = jax.default_backend()
                rec = record("precision_ab", config, median_s=med[setting])
                rec["compile_s"] = statistics.median(f - m for f, m in t)
                rec["ratio"] = med["highest"] / med["default"]
                records.append(rec | {"median_ms": 1e3 * med[setting]})
    columns = ["problem", "T", "dtype", "precision", "median_ms", "ratio"]
    print_and_save(records, columns, a.json)
    return records


if __name__ == "__main__":
    main()
