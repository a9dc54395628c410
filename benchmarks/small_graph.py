"""Time per solve of a 5-pose SE(2) graph after compilation, beside GTSAM.

The graph is GTSAM's Pose2SLAM example shape (`first_call.py`'s `pose2`: a
prior, 4 odometry factors and a loop closure), solved from the same initial
values by

- `api`: `eqs.least_squares(graph, values, LevenbergMarquardt())` called
  from Python as a user would (eqx.filter_jit dispatch, argument flattening,
  the host-side result check of `throw=True`);
- `jit`: the same solve inside one `jax.jit`-compiled function of the
  arrays (`throw=False`), called with the same arrays: the cost of the
  compiled program plus JAX's dispatch;
- `gtsam`: `gtsam.LevenbergMarquardtOptimizer(graph, initial,
  params).optimize()` on the same factors (default parameters, relative
  error tolerance 1e-8 as eqsmooth's `ftol`), when gtsam is importable.

`median_s` is the median over `--repeats` calls after warm-up; both
solvers converge to the same cost (printed). Timings on a shared machine
are noisy: compare the rows of one run.

    python benchmarks/small_graph.py
    python benchmarks/small_graph.py --json benchmarks/results/small_graph.json
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import equinox as eqx
import jax
import numpy as np


jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import machine, markdown_table, write_json  # noqa: E402
from first_call import _pose2_case  # noqa: E402

import eqsmooth as eqs  # noqa: E402


def _median(fn, repeats):
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), min(times)


def gtsam_case(graph, values):
    import gtsam

    g = gtsam.NonlinearFactorGraph()
    prior, between = graph.factors
    sig = lambda f: 1.0 / np.asarray(f.noise.sqrt_precision)  # noqa: E731
    p = lambda pose, i: gtsam.Pose2(  # noqa: E731
        float(pose.x()[i]), float(pose.y()[i]), float(pose.theta()[i])
    )
    g.add(
        gtsam.PriorFactorPose2(
            0, p(prior.value, 0), gtsam.noiseModel.Diagonal.Sigmas(sig(prior))
        )
    )
    a, b = between.variables
    for i, (ia, ib) in enumerate(zip(np.asarray(a.ids), np.asarray(b.ids))):
        g.add(
            gtsam.BetweenFactorPose2(
                int(ia),
                int(ib),
                p(between.measurement, i),
                gtsam.noiseModel.Diagonal.Sigmas(sig(between)),
            )
        )
    init = gtsam.Values()
    for i in range(5):
        init.insert(i, p(values["x"], i))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-8)

    def solve():
        return gtsam.LevenbergMarquardtOptimizer(g, init, params).optimize()

    return solve, lambda result: g.error(result)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=200)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    fn, (graph, values) = _pose2_case()
    solver = eqs.LevenbergMarquardt()

    def api():
        return jax.block_until_ready(eqs.least_squares(graph, values, solver).value)

    dynamic, static = eqx.partition((graph, values), eqx.is_array)

    @jax.jit
    def compiled(dynamic):
        g, v = eqx.combine(dynamic, static)
        sol = eqs.least_squares(g, v, solver, throw=False)
        return eqx.filter(sol.value, eqx.is_array), sol.stats["final_cost"]

    def jitted():
        return jax.block_until_ready(compiled(dynamic))

    rows = []
    ours_cost = float(jitted()[1])
    for name, f in (("api", api), ("jit", jitted)):
        med, best = _median(f, args.repeats)
        rows.append({"method": name, "median_ms": med * 1e3, "min_ms": best * 1e3})
        rows[-1]["final_cost"] = ours_cost
    try:
        g_solve, g_cost = gtsam_case(graph, values)
    except ImportError:
        print("note: gtsam not importable: not timed")
    else:
        med, best = _median(g_solve, args.repeats)
        rows.append(
            {
                "method": "gtsam",
                "median_ms": med * 1e3,
                "min_ms": best * 1e3,
                "final_cost": float(g_cost(g_solve())),
            }
        )
    ref = next((r["median_ms"] for r in rows if r["method"] == "gtsam"), None)
    records = []
    for r in rows:
        r["ratio_to_gtsam"] = r["median_ms"] / ref if ref else float("nan")
        records.append(
            {
                "benchmark": "small_graph",
                "config": {"graph": "pose2 (5 SE(2) poses)", "method": r["method"]},
                "median_s": r["median_ms"] / 1e3,
                "compile_s": 0.0,
                **r,
            }
        )
    print(
        markdown_table(
            rows, ["method", "median_ms", "min_ms", "ratio_to_gtsam", "final_cost"]
        )
    )
    print("load average", machine()["load_average"])
    if args.json:
        write_json(args.json, records)


if __name__ == "__main__":
    main()
