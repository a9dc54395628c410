"""Per-iteration CPU time of the se2vel chain, for before/after runs on a
loaded machine.

On an oversubscribed machine a niced process gets a small, varying share of
the cores, so wall-clock medians of two runs minutes apart differ by 2x
without any change in the code. The CPU time the process itself used
(`time.process_time()`, all its threads) for the same work is much less
sensitive to that share. This script times `chain.py`'s jitted iteration and
its `FixedStepGaussNewton` solve by both clocks; `--chain-dir` picks the
`chain.py` (the one of the checkout being measured), PYTHONPATH the library.

    PYTHONPATH=/path/to/checkout python benchmarks/cpu_time_ab.py \\
        --chain-dir /path/to/checkout/benchmarks --json results/x.json
"""

import argparse
import statistics
import sys
import time
from pathlib import Path

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
    parser.add_argument("--T", type=int, default=10_000)
    parser.add_argument("--solve-steps", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    sys.path.insert(0, str(args.chain_dir.resolve()))
    import chain  # the measured checkout's chain.py (its solver call differs)
    from _common import write_json

    import eqsmooth as eqs

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


if __name__ == "__main__":
    main()
