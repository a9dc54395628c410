"""Time of one `find` → `name` → `add` call of the discrepancy workflow.

Each case runs in a fresh process (`--child`), so the first call includes
every compilation; the later calls reuse them. Cases:

- `oscillator`: the 1-D oscillator of
  `experiments/discovery_validation/oscillator.py` (10 candidates) with
  viscous damping at SNR 0.4, B = 24 × T = 40.
- `pendulum`: the continuous-time pendulum of `continuous.py` there (an
  `Integrator` model, 10 candidates inside the vector field) with
  viscous damping at SNR 1, B = 24 × T = 40.

Reported per case: the first call (with compilation), the median of the
later calls (each on a new data set), the number of XLA compilations and
their total time in the first call. `--flags fast` starts each child with
`eqsmooth.set_xla_cpu_flags(fast_compile=True)`, the documented set-up.
`--cache DIR` turns on JAX's persistent compilation cache in DIR
(`eqsmooth.enable_compilation_cache`): run twice, the second run's first
call reads what the first run compiled. `--eqsmooth PATH` times another
checkout (e.g. a worktree of an earlier commit, for a before/after run in
one command).

    python -m benchmarks.discover_speed \\
        --json benchmarks/results/discover_speed.json
    rm -rf /tmp/dc_cache; for run in cold warm; do \\
        python -m benchmarks.discover_speed --cases oscillator --flags fast \\
        --repeats 1 --cache /tmp/dc_cache --label "cache $run" \\
        --json benchmarks/results/discover_speed.json; done
    # the same with EQX_ON_ERROR=nan set, to a new folder (no host callbacks)
"""

import argparse
import json
import statistics
import time
from pathlib import Path


CASES = ("oscillator", "pendulum")


def child(case: str, repeats: int, flags: str, cache: str | None) -> dict:
    # Before JAX starts: the flags and the cache are set up first.
    import eqsmooth

    if cache:
        eqsmooth.enable_compilation_cache(cache, fast_compile=flags == "fast")
    elif flags == "fast":
        eqsmooth.set_xla_cpu_flags(fast_compile=True)
    import jax

    jax.config.update("jax_enable_x64", True)
    from ._common import compile_log, git

    compiles = compile_log()
    import numpy as np

    import eqsmooth.discover as dc

    if case == "oscillator":
        from experiments.discovery_validation import oscillator as d1

        coef = d1.calibrate([0.4])["viscous"][0.4]
        model = d1.MODEL

        def data(seed):
            _, y, _ = d1.simulate(d1.rng_for(1, 0.4, seed), "viscous", coef)
            return d1.sequences(y)
    else:
        from experiments.discovery_validation import continuous as d3

        coef = d3.coefficient("viscous damping", 1.0)
        model = d3.MODELS["rate"]

        def data(seed):
            rng = np.random.default_rng([2026, 37, 99, seed])
            return d3.simulate(rng, "viscous damping", coef)[0]

    times, names, first = [], [], None
    for seed in range(repeats + 1):
        d = data(seed)
        t0 = time.perf_counter()
        found = dc.find(model, d)
        named = dc.name(found, d)
        dc.add(found, named, d)
        dt = time.perf_counter() - t0
        names.append(list(named["named"]))
        if first is None:
            first = {"s": dt, "n": len(compiles), "c": sum(c[1] for c in compiles)}
        else:
            times.append(dt)
    where = Path(eqsmooth.__file__).resolve().parent
    status = git("status", "--porcelain", "--untracked-files=no", where=where)
    rec = {"case": case, "flags": flags, "cache": cache, "eqsmooth": str(where)}
    rec["eqsmooth_git"] = git("rev-parse", "--short", "HEAD", where=where)
    rec |= {"eqsmooth_dirty": bool(status), "first_call_s": first["s"]}
    rec |= {"first_call_compiles": first["n"], "first_call_compile_s": first["c"]}
    rec |= {"later_calls_s": times, "later_median_s": statistics.median(times)}
    return rec | {"named": names}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--flags", choices=("default", "fast"), nargs="+", default=["default", "fast"]
    )
    parser.add_argument("--eqsmooth", default=None, help="checkout to time")
    parser.add_argument("--label", default="this checkout")
    parser.add_argument(
        "--cache",
        default=None,
        help="run each child with eqsmooth.enable_compilation_cache(CACHE); "
        "an empty folder measures a cold cache, a second run the warm one",
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.child:
        case, flags = args.child.split(":")
        print(json.dumps(child(case, args.repeats, flags, args.cache)))
        return
    from ._common import cli_command, machine, run_child, write_json

    path = Path(args.json) if args.json else None
    records = json.loads(path.read_text())["records"] if path and path.exists() else []
    for case in args.cases:
        for flags in args.flags:
            child_args = ["--child", f"{case}:{flags}", "--repeats", str(args.repeats)]
            child_args += ["--cache", args.cache] if args.cache else []
            rec = run_child("discover_speed", child_args, args.eqsmooth)
            rec |= {"label": args.label, "command": cli_command()}
            records.append(rec)
            print(
                f"{args.label} {case} {flags}: first {rec['first_call_s']:.1f} s "
                f"({rec['first_call_compiles']} compiles, "
                f"{rec['first_call_compile_s']:.1f} s), later median "
                f"{rec['later_median_s']:.2f} s",
                flush=True,
            )
            if path:  # saved after every case: a stopped run keeps its cases
                write_json(path, records, {"info": {"machine": machine()}})


if __name__ == "__main__":
    main()
