"""Per-iteration CPU time of the se2vel chain, for before/after runs on a
loaded machine.

On an oversubscribed machine a niced process gets a small, varying share of
the cores, so wall-clock medians of two runs minutes apart differ by 2x
without any change in the code. The CPU time the process itself used
(`time.process_time()`, all its threads) for the same work is much less
sensitive to that share. This script times `chain.py`'s jitted iteration and
its `FixedStepGaussNewton` solve by both clocks (`--case train`: the
surrogate training step of `train_step.py` instead); `--chain-dir` picks
the benchmark folder (the one of the checkout being measured), PYTHONPATH
the library.

    PYTHONPATH=/path/to/checkout python benchmarks/cpu_time_ab.py \\
        --chain-dir /path/to/checkout/benchmarks --json results/x.json
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

import equinox as eqx
import jax


def _clocks(fn, *args, repeats: int):
    jax.block_until_ready(fn(*args))  # compile
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        jax.block_until_ready(fn(*args))
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--chain-dir", type=Path, required=True)
    parser.add_argument(
        "--case",
        choices=["chain", "train"],
        default="chain",
        help="chain: chain.py's iteration and solve; train: train_step.py's "
        "surrogate training step (value and gradient, BlockTridiagonal, "
        "FixedStepGaussNewton, --K steps)",
    )
    parser.add_argument("--K", type=int, default=3)
    parser.add_argument(
        "--adjoint", choices=["unrolled", "truncated"], default="unrolled"
    )
    parser.add_argument("--T", type=int, default=10_000)
    parser.add_argument("--solve-steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(args.chain_dir.resolve()))
    from _common import write_json

    import eqsmooth as eqs

    if args.case == "train":
        records = [_train_case(args)]
        if args.json:
            write_json(args.json, records)
        return
    import chain  # the measured checkout's chain.py (its solver call differs)

    graph, values = chain.se2vel_problem(args.T)[:2]
    records = []
    for name, fn in (
        ("iteration", chain.make_iteration(eqs.BlockTridiagonal())),
        (
            f"solve/{args.solve_steps}",
            chain.make_solve(eqs.BlockTridiagonal(), args.solve_steps),
        ),
    ):
        wall, cpu = _clocks(fn, graph, values, repeats=args.repeats)
        per = args.solve_steps if name.startswith("solve") else 1
        rec = {
            "benchmark": "cpu_time_ab",
            "config": {"problem": "se2vel", "T": args.T, "what": name},
            "median_s": wall / per,
            "cpu_median_s": cpu / per,
            "cpu_share": cpu / wall,
        }
        records.append(rec)
        print(
            f"{name:10s} wall {wall / per * 1e3:9.2f} ms  "
            f"cpu {cpu / per * 1e3:9.2f} ms (cpu/wall {cpu / wall:.2f}) per iteration",
            flush=True,
        )
    if args.json:
        write_json(args.json, records)


def _train_case(args) -> dict:
    import jax.numpy as jnp
    import train_step  # the measured checkout's train_step.py

    import eqsmooth as eqs

    jax.config.update("jax_enable_x64", True)
    dtype = jnp.float64
    truths, meas = train_step.simulate(args.T, train_step.BATCH, dtype)
    graphs = eqx.filter_vmap(lambda m: train_step.build_graph(m, dtype))(meas)
    theta = jnp.full((2,), 1.0 / train_step.MEAS_SIGMA, dtype)
    adjoint = (
        eqs.UnrolledAdjoint() if args.adjoint == "unrolled" else eqs.TruncatedAdjoint(1)
    )
    fn = train_step.eqsmooth_step(eqs.BlockTridiagonal(), args.K, adjoint)
    wall, cpu = _clocks(fn, theta, graphs, truths, repeats=args.repeats)
    print(
        f"train step T={args.T} K={args.K} {args.adjoint}: wall {wall * 1e3:9.2f} ms  "
        f"cpu {cpu * 1e3:9.2f} ms (cpu/wall {cpu / wall:.2f})",
        flush=True,
    )
    return {
        "benchmark": "cpu_time_ab",
        "config": {
            "problem": "train_step",
            "T": args.T,
            "K": args.K,
            "adjoint": args.adjoint,
            "batch": train_step.BATCH,
        },
        "median_s": wall,
        "cpu_median_s": cpu,
        "cpu_share": cpu / wall,
    }


if __name__ == "__main__":
    main()
