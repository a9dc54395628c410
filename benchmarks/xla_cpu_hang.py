"""Does XLA:CPU still hang on eqsmooth's block-tridiagonal solve? A/B trial.

Each trial is a fresh process that factors a random `T x D` block-tridiagonal
system and calls the jitted `cyclic_reduction_solve` `--calls` times. A
process whose CPU time (all its threads, from /proc) has not advanced for
`--stall` seconds while it is still running counts as hung (all threads
asleep in `block_until_ready`, see `eqsmooth/_xla_flags.py`); one still
advancing at `--timeout` seconds counts as slow, not hung. On a shared,
oversubscribed machine a niced process can take minutes of wall time for
seconds of CPU, so wall time alone cannot tell a hang from starvation.
Trials alternate between JAX's default XLA flags and the flag set by
`eqsmooth.set_xla_cpu_flags()` (opt-in), so machine load affects both arms
alike.

    python benchmarks/xla_cpu_hang.py --trials 6 --json results/xla_cpu_hang.json
"""

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _common import write_json


CHILD = """
import sys, time
import os
import eqsmooth
if os.environ.get("HANG_TRIAL_FLAGS") == "1":
    eqsmooth.set_xla_cpu_flags()
import jax, jax.numpy as jnp
from eqsmooth.solve._linear._block_tridiagonal import (
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


def _cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process (all threads), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def trial(keep_default: bool, args) -> dict:
    env = dict(os.environ)
    env.pop("XLA_FLAGS", None)
    env["HANG_TRIAL_FLAGS"] = "0" if keep_default else "1"
    cmd = [sys.executable, "-c", CHILD, str(args.T), str(args.D), str(args.calls)]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile("w+") as log:
        proc = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)
        cpu, last_progress, outcome = 0.0, t0, "finished"
        while proc.poll() is None:
            time.sleep(1.0)
            now = time.perf_counter()
            try:
                c = _cpu_seconds(proc.pid)
            except (OSError, IndexError):  # exited between poll and read
                continue
            if c > cpu:
                cpu, last_progress = c, now
            if now - last_progress > args.stall:
                outcome = "hung"
            elif now - t0 > args.timeout:
                outcome = "slow"
            else:
                continue
            proc.kill()
            proc.wait()
            break
        log.seek(0)
        out = log.read()
    return {
        "arm": "jax default" if keep_default else "eqsmooth flags",
        "hung": outcome == "hung",
        "outcome": outcome,
        "returncode": proc.returncode,
        "calls_done": out.count("call "),
        "wall_s": time.perf_counter() - t0,
        "cpu_s": cpu,
        "load_average": os.getloadavg(),
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--trials", type=int, default=6, help="pairs of processes")
    parser.add_argument("--T", type=int, default=100_000)
    parser.add_argument("--D", type=int, default=5)
    parser.add_argument("--calls", type=int, default=20)
    parser.add_argument(
        "--stall",
        type=float,
        default=30.0,
        help="seconds without CPU progress that count as a hang",
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=900.0,
        help="seconds after which a still-progressing process is stopped as slow",
    )
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    records = []
    for i in range(args.trials):
        for keep_default in (True, False):
            rec = trial(keep_default, args) | {"trial": i}
            records.append(rec)
            print(
                f"trial {i} {rec['arm']:15s} {rec['outcome']:8s} "
                f"calls {rec['calls_done']}/{args.calls} wall {rec['wall_s']:.0f} s "
                f"cpu {rec['cpu_s']:.1f} s load {rec['load_average'][0]:.1f}",
                flush=True,
            )
            if args.json:  # after every trial: a run stopped part-way keeps them
                write_json(args.json, records, {"config": vars(args)})
    for arm in ("jax default", "eqsmooth flags"):
        rs = [r for r in records if r["arm"] == arm]
        hung = sum(r["hung"] for r in rs)
        slow = sum(r["outcome"] == "slow" for r in rs)
        print(f"{arm}: {hung}/{len(rs)} processes hung, {slow} stopped as slow")
    if args.json:
        write_json(args.json, records, {"config": vars(args)})


if __name__ == "__main__":
    main()
