"""First answer of a Pose2 loop built one factor object per edge (a GTSAM
port's `graph.add` per edge), as given and after
`eqsmooth.factors.merge_stacks`: seconds of the first `least_squares` call
(tracing and compiling included), of a later call, and the peak resident
memory the first call added, per number of edges, in one process.

    OPENBLAS_NUM_THREADS=1 python -m benchmarks.unstacked_graph \\
        --json benchmarks/results/unstacked_graph.json
"""

import resource
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from . import _common as common


jax.config.update("jax_enable_x64", True)

import eqsmooth as eqs  # noqa: E402


def factors(poses: int) -> list:
    rng = np.random.default_rng(0)
    noise = eqs.DiagonalNoise.from_sigmas(jnp.array([0.2, 0.2, 0.1]))
    x = lambda i: eqs.Var("x", [i])
    se2 = lambda v: eqs.SE2.from_xy_theta(*(jnp.asarray([c]) for c in v))
    fs = [eqs.PriorFactor(x(0), se2([0.0, 0.0, 0.0]), noise)]
    for i in range(poses - 1):
        fs.append(
            eqs.BetweenFactor(
                x(i), x(i + 1), se2([1, 0, 0.2] + 0.05 * rng.normal(size=3)), noise
            )
        )
    for i in range(8, poses, 4):
        fs.append(eqs.BetweenFactor(x(i - 8), x(i), se2([0.5, 0.5, 0.1]), noise))
    return fs


def timed(graph, values):
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    jax.block_until_ready(eqs.least_squares(graph, values, eqs.LevenbergMarquardt()).value)
    first = time.perf_counter() - t0
    t0 = time.perf_counter()
    jax.block_until_ready(eqs.least_squares(graph, values, eqs.LevenbergMarquardt()).value)
    later = time.perf_counter() - t0
    grown = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak
    return first, later, grown / 1024


def main(argv=None):
    parser = common.cli(__doc__)
    parser.add_argument("--poses", type=int, nargs="*", default=[20, 40, 80])
    a = parser.parse_args(argv)
    records = []
    for poses in a.poses:
        fs = factors(poses)
        values = {
            "x": eqs.SE2.from_xy_theta(
                jnp.arange(poses) * 1.0, jnp.zeros(poses), jnp.zeros(poses)
            )
        }
        # merged first: the peak memory it reports is not hidden by the larger run
        for name, graph_factors in (
            ("merge_stacks", eqs.factors.merge_stacks(fs)),
            ("one stack per factor", fs),
        ):
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                graph = eqs.FactorGraph(graph_factors)
            first, later, mib = timed(graph, values)
            config = dict(poses=poses, edges=len(fs) - 1, graph=name)
            records.append(
                common.record(
                    "unstacked_graph",
                    config,
                    stacks=len(graph.factors),
                    first_s=first,
                    later_s=later,
                    peak_rss_growth_MiB=mib,
                )
            )
            print(records[-1], flush=True)
    common.print_and_save(
        records,
        [
            "poses",
            "edges",
            "graph",
            "stacks",
            "first_s",
            "later_s",
            "peak_rss_growth_MiB",
        ],
        a.json,
    )


if __name__ == "__main__":
    main()
