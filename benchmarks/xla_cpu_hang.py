"""Does XLA:CPU still hang on eqsmooth's block-tridiagonal solve? A/B trial.

Each trial is a fresh process that factors a random `T x D` block-tridiagonal
system and calls the jitted `cyclic_reduction_solve` `--calls` times; a
process that has not finished after `--timeout` seconds (all threads asleep
in `block_until_ready`, see `eqsmooth/_xla_flags.py`) counts as hung. Trials
alternate between JAX's default XLA flags and the flag set by
`eqsmooth.set_xla_cpu_flags()` (opt-in), so machine load affects both arms
alike.

    python benchmarks/xla_cpu_hang.py --trials 6 --json results/xla_cpu_hang.json
"""

import argparse
import os
import subprocess
import sys
import time

from _common import write_json


CHILD = """
import sys, time
import os
import eqsmooth
if os.environ.get("HANG_TRIAL_FLAGS") == "1":
    eqsmooth.set_xla_cpu_flags()
import jax, jax.numpy as jnp
from eqsmooth.solve._block_tridiagonal import (
    cyclic_reduction_factor, cyclic_reduction_solve)
jax.config.update("jax_enable_x64", True)
T, D, calls = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3])
k = jax.random.split(jax.random.key(0), 3)
A = jax.random.normal(k[0], (T, D, D))
A = A @ jnp.swapaxes(A, 1, 2) + 10 * jnp.eye(D)
B = 0.1 * jax.random.normal(k[1], (T - 1, D, D))
b = jax.random.normal(k[2], (T, D))
state = jax.block_until_ready(jax.jit(cyclic_reduction_factor)(A, B))
solve = jax.jit(cyclic_reduction_solve)
for i in range(calls):
    jax.block_until_ready(solve(state, b))
    print("call", i, flush=True)
"""


def trial(keep_default: bool, args) -> dict:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env["HANG_TRIAL_FLAGS"] = "0" if keep_default else "1"
    cmd = [sys.executable, "-c", CHILD, str(args.T), str(args.D), str(args.calls)]
    t0 = time.perf_counter()
    try:
        out = subprocess.run(
            cmd, env=env, capture_output=True, text=True, timeout=args.timeout
        ).stdout
        hung = False
    except subprocess.TimeoutExpired as e:
        out = e.stdout.decode() if isinstance(e.stdout, bytes) else (e.stdout or "")
        hung = True
    return {
        "arm": "jax default" if keep_default else "eqsmooth flags",
        "hung": hung,
        "calls_done": out.count("call "),
        "wall_s": time.perf_counter() - t0,
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=6, help="pairs of processes")
    parser.add_argument("--T", type=int, default=100_000)
    parser.add_argument("--D", type=int, default=5)
    parser.add_argument("--calls", type=int, default=20)
    parser.add_argument("--timeout", type=float, default=60.0)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    records = []
    for i in range(args.trials):
        for keep_default in (True, False):
            rec = trial(keep_default, args) | {"trial": i}
            records.append(rec)
            print(
                f"trial {i} {rec['arm']:15s} hung={rec['hung']!s:5s} "
                f"calls {rec['calls_done']}/{args.calls} {rec['wall_s']:.0f} s",
                flush=True,
            )
    for arm in ("jax default", "eqsmooth flags"):
        rs = [r for r in records if r["arm"] == arm]
        print(f"{arm}: {sum(r['hung'] for r in rs)}/{len(rs)} processes hung")
    if args.json:
        write_json(args.json, records, {"config": vars(args)})


if __name__ == "__main__":
    main()
