"""Time to the first answer of a fresh process, and of a second one with a warm cache.

Cases, each in a fresh Python process: `pose2` (`_common.pose2_problem`,
`eqs.least_squares(graph, values, LevenbergMarquardt())`), `chain1e4`,
`chain1e5` (`chain.py`'s SE(2) + velocity chain, a `GaussNewton()` solve of
at most 20 steps, `throw=False`) and `train200` (`train_step.py`'s training
step at T = 200, K = 3, unrolled). Each runs in two processes in turn with
JAX's persistent compilation cache on (a fresh folder, no minimum compile
time or size): `cold` (empty folder) and `warm` (the same folder).

The child times the call as a user makes it: `first_answer_s` (wall) and
`first_answer_cpu_s` (CPU seconds, all threads), split by JAX's monitoring
events into `trace_s` (the outermost trace), `lower_s`, `compile_s` (XLA)
and `cache_read_s`; `--staged` instead times `.trace`, `.lower()`,
`.compile()` and the first run of one outer `jax.jit` apart. `cache_hits` /
`cache_misses` are JAX's events; `not_written_callbacks` counts programs JAX
would not cache because they use host callbacks (as `eqx.error_if` does).
`--trees LABEL=PATH ...` runs every case with eqsmooth imported from the
checkout PATH per label, alternating (before and after in one command);
`--xla-flags LABEL=FLAGS` likewise for `XLA_FLAGS`; `--parts` compiles
pieces of the pose2 solve.

    python -m benchmarks.first_call --json benchmarks/results/first_call.json
    python -m benchmarks.first_call --cases pose2 --trees before=/tmp/main after=.
    python -m benchmarks.first_call --cases pose2 --xla-flags default= \\
        fast=--xla_cpu_use_fusion_emitters=false
    python -m benchmarks.first_call --parts \\
        --json benchmarks/results/first_call_parts.json
"""

import time


_T0 = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402


CASES = ("pose2", "chain1e4", "chain1e5", "train200")


# ----------------------------------------------------------------------------
# The child: one case in this (fresh) process.


def _pose2_case():
    import eqsmooth as eqs

    from ._common import pose2_problem

    solver = eqs.LevenbergMarquardt()

    def fn(graph, values):
        return eqs.least_squares(graph, values, solver).value

    return fn, pose2_problem()


def _chain_case(T: int):
    import eqsmooth as eqs

    from .chain import se2vel_problem

    graph, values = se2vel_problem(T)
    solver = eqs.GaussNewton()

    def fn(graph, values):
        # 20 steps do not always reach the tolerances from these initial
        # values; the figure here is the time to the first answer.
        return eqs.least_squares(graph, values, solver, max_steps=20, throw=False).value

    return fn, (graph, values)


def _train_case(T: int, K: int = 3):
    import equinox as eqx
    import jax.numpy as jnp

    import eqsmooth as eqs

    from .train_step import BATCH, build_graph, eqsmooth_step, MEAS_SIGMA, simulate

    truths, meas = simulate(T, BATCH, jnp.float64)
    graphs = eqx.filter_vmap(lambda m: build_graph(m, jnp.float64))(meas)
    theta = jnp.full((2,), 1.0 / MEAS_SIGMA, jnp.float64)
    # eqx.filter_jit of jax.value_and_grad, as a user's training step.
    step = eqsmooth_step(eqs.BlockTridiagonal(), K, eqs.UnrolledAdjoint())
    return step, (theta, graphs, truths)


def _monitor(cache_dir: str | None):
    """Turn the persistent cache on and collect JAX's compile events."""
    import logging

    import jax

    if cache_dir:
        jax.config.update("jax_compilation_cache_dir", cache_dir)
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
        # Makes JAX log (at WARNING) why it does not write a cache entry.
        jax.config.update("jax_explain_cache_misses", True)
    events: dict[str, int] = {}
    durations: dict[str, list[float]] = {}
    not_written: list[str] = []

    def on_event(name, **kwargs):
        events[name] = events.get(name, 0) + 1

    def on_duration(name, secs, **kwargs):
        durations.setdefault(name, []).append(secs)

    class _Capture(logging.Handler):
        def emit(self, record):
            msg = record.getMessage()
            if msg.startswith("Not writing persistent cache entry"):
                not_written.append(msg)

    logging.getLogger("jax._src.compiler").addHandler(_Capture())
    jax.monitoring.register_event_listener(on_event)
    jax.monitoring.register_event_duration_secs_listener(on_duration)
    return events, durations, not_written


def _staged(fn, args, rec, run=True):
    """Trace, lower, compile (and run) `fn(*args)` under one outer `jax.jit`,
    each stage timed apart into `rec` (wall and CPU seconds). Returns the
    compiled call and the lowered program."""
    import equinox as eqx
    import jax

    dynamic, static = eqx.partition(args, eqx.is_array)

    def flat(dynamic):
        out = fn(*eqx.combine(dynamic, static))
        return jax.tree_util.tree_leaves(eqx.filter(out, eqx.is_array))

    obj, lowered = jax.jit(flat), None
    stages = [("trace", lambda o: o.trace(dynamic)), ("lower", lambda o: o.lower())]
    stages += [("compile", lambda o: o.compile())]
    stages += [("run", lambda o: (jax.block_until_ready(o(dynamic)), o)[1])] * run
    for stage, step in stages:
        t, c = time.perf_counter(), time.process_time()
        obj = step(obj)
        rec[f"{stage}_s"] = time.perf_counter() - t
        rec[f"{stage}_cpu_s"] = time.process_time() - c
        lowered = obj if stage == "lower" else lowered
    return lambda: obj(dynamic), lowered


def _eager(fn, args, rec, durations):
    """The call as a user makes it, split by JAX's monitoring events."""
    import equinox as eqx
    import jax

    jax.block_until_ready(eqx.filter(fn(*args), eqx.is_array))
    get = lambda name: durations.get(name, [])
    trace = get("/jax/core/compile/jaxpr_trace_duration") or [0.0]
    # Nested jits are traced inside the outer one: the outermost trace is the
    # longest and includes them.
    rec |= {"trace_s": max(trace), "programs_traced": len(trace)}
    rec["lower_s"] = sum(get("/jax/core/compile/jaxpr_to_mlir_module_duration"))
    rec["compile_s"] = sum(get("/jax/core/compile/backend_compile_duration"))
    rec["cache_read_s"] = sum(get("/jax/compilation_cache/cache_retrieval_time_sec"))
    return lambda: fn(*args)


def child(case: str, cache_dir: str | None, staged: bool) -> dict:
    t_import = time.perf_counter()
    import equinox as eqx
    import jax

    import eqsmooth  # noqa: F401

    import_s = time.perf_counter() - t_import
    jax.config.update("jax_enable_x64", True)
    events, durations, not_written = _monitor(cache_dir)
    t = time.perf_counter()
    if case == "pose2":
        fn, args = _pose2_case()
    elif case.startswith("chain"):
        fn, args = _chain_case(int(float(case[len("chain") :])))
    elif case.startswith("train"):
        fn, args = _train_case(int(case[len("train") :]))
    else:
        raise ValueError(f"unknown case {case!r}; known: {CASES}")
    jax.block_until_ready(eqx.filter(args, eqx.is_array))
    build_s = time.perf_counter() - t
    for collected in (events, durations, not_written):
        collected.clear()
    rec = {"case": case, "import_s": import_s, "build_s": build_s}
    c0, t0 = time.process_time(), time.perf_counter()
    if staged:
        call = _staged(fn, args, rec)[0]
    else:
        call = _eager(fn, args, rec, durations)
    first, first_cpu = time.perf_counter() - t0, time.process_time() - c0
    times = []
    for _ in range(5 if case != "chain1e5" else 3):
        t = time.perf_counter()
        jax.block_until_ready(eqx.filter(call(), eqx.is_array))
        times.append(time.perf_counter() - t)
    rec |= dict(first_answer_s=first, first_answer_cpu_s=first_cpu)
    rec["steady_s"] = statistics.median(times)
    rec["cache_hits"] = events.get("/jax/compilation_cache/cache_hits", 0)
    rec["cache_misses"] = events.get("/jax/compilation_cache/cache_misses", 0)
    rec["not_written_callbacks"] = sum("host callbacks" in m for m in not_written)
    rec["not_written"] = not_written[:5]
    return rec | {"process_s": time.perf_counter() - _T0}


def parts() -> list[dict]:
    """Trace / lower / compile CPU seconds of pieces of the `pose2` solve, one
    process: how much of the whole program the linearisation is."""
    import jax

    import eqsmooth as eqs

    jax.config.update("jax_enable_x64", True)
    _, (graph, values) = _pose2_case()
    lin, gn, gv = eqs.linearize(graph, values), eqs.GaussNewton(), (graph, values)
    dense = lambda lin: eqs.solve.solve_normal(eqs.DenseCholesky(), lin)
    pieces = {
        "linearize alone": (eqs.linearize, gv),
        "one dense normal solve alone": (dense, (lin,)),
        "GaussNewton solve, throw=False": (
            lambda g, v: eqs.least_squares(g, v, gn, throw=False).value,
            gv,
        ),
        "GaussNewton solve, throw=True (error_if under jit)": (
            lambda g, v: eqs.least_squares(g, v, gn).value,
            gv,
        ),
    }
    out = []
    for name, (fn, args) in pieces.items():
        t = {}
        _, lowered = _staged(fn, args, t, run=False)
        rec = {"benchmark": "first_call_parts"}
        rec |= {"config": {"case": "pose2", "piece": name}, "piece": name}
        rec |= {k: t[k] for k in ("trace_cpu_s", "lower_cpu_s", "compile_cpu_s")}
        rec |= {"hlo_lines": lowered.as_text().count("\n"), "median_s": float("nan")}
        out.append(rec)
        print(
            f"{name:52s} trace {t['trace_cpu_s']:5.2f}  lower {t['lower_cpu_s']:5.2f}"
            f"  compile {t['compile_cpu_s']:5.2f} CPU s  {rec['hlo_lines']} HLO lines",
            flush=True,
        )
    return out


# ----------------------------------------------------------------------------
# The parent: subprocesses per case, tree and cache state.


def run_case(case: str, cache_dir: str, tree: str, env: dict, staged: bool) -> dict:
    """One case in a fresh process, eqsmooth imported from `tree`."""
    from ._common import run_child

    args = ["--child", case, "--cache-dir", cache_dir] + ["--staged"] * staged
    t = time.perf_counter()
    rec = run_child("first_call", args, tree, env)
    return rec | {"wall_s": time.perf_counter() - t}


def cold_warm(case, rep, label, tree, env, staged) -> list[dict]:
    """A cold and a warm process of one case, sharing a fresh cache folder."""
    out = []
    with tempfile.TemporaryDirectory(prefix="eqs_jax_cache_") as cache:
        for state in ("cold", "warm"):
            rec = run_case(case, cache, tree, env, staged)
            config = {"case": case, "tree": label, "process": state}
            config |= {"env": env, "staged": staged}
            rec |= dict(benchmark="first_call", config=config, tree=label)
            rec |= dict(process=state, repeat=rep, load_average=os.getloadavg())
            rec["median_s"] = rec["steady_s"]
            out.append(rec)
            print(
                f"{case:9s} {label:7s} {state:5s} first answer "
                f"{rec['first_answer_s']:6.2f} s, CPU {rec['first_answer_cpu_s']:6.2f}"
                f" s (trace {rec['trace_s']:5.2f}, lower {rec['lower_s']:5.2f}, XLA "
                f"compile {rec['compile_s']:5.2f} s wall); steady "
                f"{rec['steady_s'] * 1e3:8.2f} ms; cache hits/misses "
                f"{rec['cache_hits']}/{rec['cache_misses']}, not written "
                f"(callbacks) {rec['not_written_callbacks']}",
                flush=True,
            )
    return out


COLUMNS = ["case", "tree", "process", "first_answer_s", "first_answer_cpu_s"]
COLUMNS += ["trace_s", "lower_s", "compile_s", "steady_s", "cache_hits"]
COLUMNS += ["cache_misses", "not_written_callbacks"]


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--cache-dir", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--trees", nargs="*", default=None, help="LABEL=PATH ...")
    parser.add_argument("--env", nargs="*", default=[], help="NAME=VALUE ...")
    parser.add_argument("--xla-flags", nargs="*", default=None, help="LABEL=FLAGS")
    parser.add_argument("--repeats", type=int, default=1, help="cold/warm pairs")
    parser.add_argument("--staged", action="store_true", help="time JAX's stages")
    parser.add_argument("--parts", action="store_true", help="pieces of pose2")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.child, args.cache_dir, args.staged)))
        return
    # Not at the top: a child times its own imports (of JAX among them).
    from ._common import machine, print_and_save, ROOT, write_json

    if args.parts:
        records = parts()
        if args.json:
            write_json(args.json, records)
        return
    trees = dict(t.split("=", 1) for t in (args.trees or [f"this={ROOT}"]))
    env_extra = dict(e.split("=", 1) for e in args.env)
    flag_sets = dict(f.split("=", 1) for f in (args.xla_flags or []))
    # (label, tree, environment) per variant: every tree with every flag set.
    variants = []
    for tree_label, tree in trees.items():
        if not flag_sets:
            variants.append((tree_label, tree, env_extra))
        for flag_label, flags in flag_sets.items():
            label = flag_label if len(trees) == 1 else f"{tree_label}/{flag_label}"
            variants.append((label, tree, {**env_extra, "XLA_FLAGS": flags}))
    records = []
    for case in args.cases:
        for rep in range(args.repeats):
            for variant in variants:
                records += cold_warm(case, rep, *variant, args.staged)
    print_and_save(records, COLUMNS, args.json, {"machine_at_start": machine()})


if __name__ == "__main__":
    main()
