"""Many small pose graphs: one batched eqsmooth call against GTSAM's loop.

`N` copies of `first_call.py`'s 5-pose SE(2) loop (a prior, 4 odometry
factors and a loop closure), each with its own odometry noise and initial
values, solved by

- `batch`: `eqs.least_squares_batch(graphs, values, LevenbergMarquardt())`,
  one call and one compiled, vmapped program for all `N` (timed after its
  compilation, which is reported apart);
- `gtsam`: a Python loop of `gtsam.LevenbergMarquardtOptimizer(graph,
  initial, params).optimize()` over the same `N` graphs (relative error
  tolerance 1e-8, as eqsmooth's `ftol`), when gtsam is importable.

Both reach the same solutions (the largest difference is printed). Each
timing is the median of `--repeats` runs of the whole batch; compare rows of
one run (the machines are noisy).

    python benchmarks/small_graph_batch.py --num-graphs 1000 \\
        --json benchmarks/results/small_graph_batch.json
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np


jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import write_json  # noqa: E402
from first_call import _pose2_case  # noqa: E402
from small_graph import gtsam_case  # noqa: E402

import eqsmooth as eqs  # noqa: E402


def _perturbed(graph, values, rng):
    """The 5-pose loop with its odometry and initial values perturbed."""
    prior, between = graph.factors
    m = between.measurement
    noisy = eqs.SE2.from_xy_theta(
        m.x() + jnp.asarray(rng.normal(0, 0.05, 5)),
        m.y() + jnp.asarray(rng.normal(0, 0.05, 5)),
        m.theta() + jnp.asarray(rng.normal(0, 0.02, 5)),
    )
    v = values["x"]
    init = eqs.SE2.from_xy_theta(
        v.x() + jnp.asarray(rng.normal(0, 0.1, 5)),
        v.y() + jnp.asarray(rng.normal(0, 0.1, 5)),
        v.theta() + jnp.asarray(rng.normal(0, 0.05, 5)),
    )
    between = eqs.BetweenFactor(*between.variables, noisy, between.noise)
    return eqs.FactorGraph([prior, between]), {"x": init}


def _median(fn, repeats):
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--num-graphs", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    _, (graph, values) = _pose2_case()
    rng = np.random.default_rng(0)
    cases = [_perturbed(graph, values, rng) for _ in range(a.num_graphs)]
    graphs = eqs.learn.stack_trees([g for g, _ in cases])
    inits = eqs.learn.stack_trees([v for _, v in cases])
    solver = eqs.LevenbergMarquardt()

    def batch():
        sol = eqs.least_squares_batch(graphs, inits, solver)
        return jax.block_until_ready(sol.value)

    t0 = time.perf_counter()
    ours = batch()
    first_s = time.perf_counter() - t0
    batch_s = _median(batch, a.repeats)
    rows = [
        {
            "method": "eqsmooth least_squares_batch",
            "num_graphs": a.num_graphs,
            "median_s": batch_s,
            "per_graph_us": batch_s / a.num_graphs * 1e6,
            "first_call_s": first_s,
        }
    ]
    try:
        solves = [gtsam_case(g, v)[0] for g, v in cases]
    except ImportError:
        print("note: gtsam not importable: not timed")
        solves = None
    if solves is not None:
        results = []

        def loop():
            results[:] = [s() for s in solves]

        gtsam_s = _median(loop, a.repeats)
        diff = max(
            max(
                abs(float(r.atPose2(i).x()) - float(ours["x"].x()[k, i]))
                for i in range(5)
            )
            for k, r in enumerate(results)
        )
        rows.append(
            {
                "method": "gtsam loop",
                "num_graphs": a.num_graphs,
                "median_s": gtsam_s,
                "per_graph_us": gtsam_s / a.num_graphs * 1e6,
                "max_abs_x_difference": diff,
            }
        )
        rows[0]["speedup_over_gtsam"] = gtsam_s / batch_s
    for r in rows:
        extra = ""
        if "first_call_s" in r:
            extra += f", first call {r['first_call_s']:.2f} s"
        if "speedup_over_gtsam" in r:
            extra += f", speed-up {r['speedup_over_gtsam']:.1f}x"
        if "max_abs_x_difference" in r:
            extra += f", max |dx| {r['max_abs_x_difference']:.1e}"
        print(
            f"{r['method']:30s} {r['num_graphs']} graphs: "
            f"{r['median_s'] * 1e3:8.1f} ms ({r['per_graph_us']:.1f} us per graph)"
            + extra
        )
    if a.json:
        write_json(a.json, rows)


if __name__ == "__main__":
    main()
