"""An eager `eqs.linearize` call, and the `pose2` solve program, per source tree.

Each measurement runs in a fresh Python process (so every compilation is a
first one), alternating between the trees given, for `--rounds` rounds:

- `eager`: `eqs.linearize(graph, values)` on the 5-pose SE(2) graph of
  `first_call.py`'s `pose2` case, called outside `jit`: the first call
  (seconds, and how many XLA programs it compiled) and the second (ms);
- `cost`: `graph.cost(values)` then `graph.negative_log_likelihood(values)`
  on that graph, outside `jit`: first calls (seconds, XLA programs) and
  second calls (ms);
- `solve`: that graph's `LevenbergMarquardt` solve staged with
  `jax.jit(...).trace / .lower() / .compile()` (seconds each), the median of
  300 runs of the compiled program, and its HLO size.

```bash
git worktree add /tmp/before <commit>
python benchmarks/eager_linearize.py --trees before=/tmp/before after=. \\
    --json benchmarks/results/eager_linearize.json
python benchmarks/eager_linearize.py --trees before=/tmp/before after=. \\
    --what cost --json benchmarks/results/eager_cost.json
```
"""

import argparse
import json
import pathlib
import subprocess
import sys
import time


HERE = pathlib.Path(__file__).resolve().parent


def child(root: str, what: str) -> dict:
    sys.path[:0] = [root, str(pathlib.Path(root) / "benchmarks")]
    import eqsmooth as eqs

    if not eqs.__file__.startswith(str(pathlib.Path(root).resolve())):
        raise SystemExit(f"imported {eqs.__file__}, not the tree at {root}")
    eqs.set_xla_cpu_flags(fast_compile=True)
    import jax
    from jax import monitoring

    jax.config.update("jax_enable_x64", True)
    programs = [0]

    def on_duration(event, secs, **kwargs):
        if event.endswith("backend_compile_duration"):
            programs[0] += 1

    monitoring.register_event_duration_secs_listener(on_duration)
    import first_call

    fn, (graph, values) = first_call._pose2_case()
    if what == "eager":
        t = time.perf_counter()
        jax.block_until_ready(eqs.linearize(graph, values).cost)
        first = time.perf_counter() - t
        t = time.perf_counter()
        jax.block_until_ready(eqs.linearize(graph, values).cost)
        return {
            "first_s": first,
            "first_programs": programs[0],
            "second_ms": (time.perf_counter() - t) * 1e3,
        }
    if what == "cost":
        t = time.perf_counter()
        jax.block_until_ready(graph.cost(values))
        jax.block_until_ready(graph.negative_log_likelihood(values))
        first = time.perf_counter() - t
        t = time.perf_counter()
        jax.block_until_ready(graph.cost(values))
        jax.block_until_ready(graph.negative_log_likelihood(values))
        return {
            "first_s": first,
            "first_programs": programs[0],
            "second_ms": (time.perf_counter() - t) * 1e3,
        }
    t0 = time.perf_counter()
    traced = jax.jit(fn).trace(graph, values)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    jax.block_until_ready(compiled(graph, values))
    runs = []
    for _ in range(300):
        t = time.perf_counter()
        jax.block_until_ready(compiled(graph, values))
        runs.append(time.perf_counter() - t)
    runs.sort()
    return {
        "trace_s": t1 - t0,
        "lower_s": t2 - t1,
        "compile_s": t3 - t2,
        "run_median_ms": runs[len(runs) // 2] * 1e3,
        "hlo_lines": len(lowered.as_text().splitlines()),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trees", nargs="+", default=[f"this={HERE.parent}"])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument(
        "--what",
        nargs="+",
        default=["eager", "solve"],
        choices=["eager", "cost", "solve"],
    )
    parser.add_argument("--json")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(*args.child)))
        return
    trees = dict(t.split("=", 1) for t in args.trees)
    results = []
    for r in range(args.rounds):
        for label, root in trees.items():
            for what in args.what:
                out = subprocess.run(
                    [sys.executable, __file__, "--child", root, what],
                    capture_output=True,
                    text=True,
                    check=True,
                )
                rec = {"round": r, "tree": label, "what": what}
                rec |= json.loads(out.stdout.strip().splitlines()[-1])
                print(rec, flush=True)
                results.append(rec)
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(results, indent=1) + "\n")


if __name__ == "__main__":
    main()
