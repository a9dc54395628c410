"""Time of one `find` → `name` → `add` call of the discrepancy workflow.

Each case runs in a fresh process: its first call includes every compilation,
later calls (each on new data) reuse them. Cases (B = 24 × T = 40, 10
candidates, viscous damping): `oscillator` (`experiments/discovery_validation/
oscillator.py`, SNR 0.4) and `pendulum` (`continuous.py` there, SNR 1). Per
case: the first call, its XLA compilations (count, time, the five longest
programs) and tracing and lowering time, and the median later call.
`--flags fast`: `eqsmooth.set_xla_cpu_flags(fast_compile=True)` first.
`--cache DIR`: each case twice with `eqsmooth.enable_compilation_cache(DIR)`
(compiled and, since 2026-11-29, traced programs; fast flags only with `--flags
fast`), DIR emptied first ("cold cache"), then in a new process reading it
("warm cache"). `--eqsmooth PATH`: another checkout (before/after in one command).

    python -m benchmarks.discover_speed --cases oscillator --flags default \\
        --repeats 3 --cache /tmp/dc_cache --json benchmarks/results/discover_speed.json
"""

import argparse
import json
import shutil
import statistics
import time
from pathlib import Path


CASES = ("oscillator", "pendulum")


def child(case: str, repeats: int, flags: str, cache: str | None) -> dict:
    import eqsmooth  # the flags and the cache are set before JAX starts

    if cache:
        eqsmooth.enable_compilation_cache(cache, fast_compile=flags == "fast")
    elif flags == "fast":
        eqsmooth.set_xla_cpu_flags(fast_compile=True)
    import jax

    jax.config.update("jax_enable_x64", True)
    events = []  # (event, program, seconds): tracing, lowering, compiling
    jax.monitoring.register_event_duration_secs_listener(
        lambda e, s, **kw: events.append((e.split("/")[-1], kw.get("fun_name"), s))
    )
    import numpy as np

    import eqsmooth.discover as dc

    from ._common import git

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

    times, names, rec = [], [], {"case": case, "flags": flags, "cache": cache}
    for seed in range(repeats + 1):
        d = data(seed)
        t0 = time.perf_counter()
        found = dc.find(model, d)
        named = dc.name(found, d)
        dc.add(found, named, d)
        times.append(time.perf_counter() - t0)
        names.append(list(named["named"]))
        if seed == 0:  # the first call: where its time went
            total = {e: sum(s for e2, _, s in events if e2 == e) for e, _, _ in events}
            compiles = [(n, s) for e, n, s in events if e == "backend_compile_duration"]
            programs = {}
            for n, s in compiles:
                programs[n] = programs.get(n, 0.0) + s
            rec["first_call_compiles"] = len(compiles)
            rec["first_call_compile_s"] = total.get("backend_compile_duration", 0.0)
            rec["first_call_trace_s"] = total.get("jaxpr_trace_duration", 0.0)
            rec["first_call_lower_s"] = total.get("jaxpr_to_mlir_module_duration", 0.0)
            rec["first_call_cache_read_s"] = total.get("cache_retrieval_time_sec", 0.0)
            top = sorted(programs.items(), key=lambda kv: -kv[1])[:5]
            rec["first_call_top_programs"] = {k: round(v, 2) for k, v in top}
    where = Path(eqsmooth.__file__).resolve().parent
    status = git("status", "--porcelain", "--untracked-files=no", where=where)
    rec |= {"eqsmooth": str(where), "eqsmooth_dirty": bool(status)}
    rec["eqsmooth_git"] = git("rev-parse", "--short", "HEAD", where=where)
    rec |= {"first_call_s": times[0], "later_calls_s": times[1:]}
    return rec | {"later_median_s": statistics.median(times[1:]), "named": names}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES))
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument(
        "--flags", choices=("default", "fast"), nargs="+", default=["default", "fast"]
    )
    parser.add_argument("--eqsmooth", default=None, help="checkout to time")
    parser.add_argument("--label", default="this checkout")
    parser.add_argument("--cache", default=None, help="cold, then warm, cache here")
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
    runs = ["cold cache", "warm cache"] if args.cache else [None]
    for case in args.cases:
        for flags in args.flags:
            for run in runs:
                child_args = [
                    "--child",
                    f"{case}:{flags}",
                    "--repeats",
                    str(args.repeats),
                ]
                if run:
                    if run == "cold cache":
                        shutil.rmtree(args.cache, ignore_errors=True)
                    child_args += ["--cache", args.cache]
                rec = run_child("discover_speed", child_args, args.eqsmooth)
                label = f"{args.label}, {run}" if run else args.label
                rec |= {"label": label, "command": cli_command()}
                rec["load_average"] = machine()["load_average"]
                records.append(rec)
                keys = ("first_call_s", "first_call_trace_s", "later_median_s")
                print(label, case, flags, {k: rec[k] for k in keys}, flush=True)
                if path:  # saved after every case: a stopped run keeps its cases
                    write_json(path, records, {"info": {"machine": machine()}})


if __name__ == "__main__":
    main()
