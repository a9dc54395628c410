"""Time to the first answer of a fresh process, and of a second one with a warm cache.

A new user meets compile time before anything else: every new graph
structure is traced, lowered to StableHLO and compiled by XLA before the
first answer. This script measures that as a user meets it, each case in a
fresh Python process (a subprocess of this script):

- `pose2`: GTSAM's Pose2SLAM example shape (5 SE(2) poses, a prior, 4
  odometry factors and a loop closure), solved by
  `eqs.least_squares(graph, values, LevenbergMarquardt())`;
- `chain1e4`, `chain1e5`: the SE(2) + velocity chain of
  `benchmarks/chain.py` (T = 1e4, 1e5), a whole `GaussNewton()` solve with
  the default linear solver (block-tridiagonal), at most 20 steps,
  `throw=False`;
- `train200`: the training step of `benchmarks/train_step.py` at T = 200,
  K = 3 (a batch of 32 disk graphs, `jax.value_and_grad` of the surrogate
  loss through `FixedStepGaussNewton` with the unrolled adjoint).

Each case runs in two processes in turn, both with JAX's persistent
compilation cache on (`jax_compilation_cache_dir` set to a fresh folder,
`jax_persistent_cache_min_compile_time_secs = 0`,
`jax_persistent_cache_min_entry_size_bytes = 0`): `cold` (the folder is
empty) and `warm` (the same folder, a second process).

By default the child times the call as a user makes it (the public
`eqs.least_squares` call for the solves, an `eqx.filter_jit` of the value
and gradient for the training step): `first_answer_s` (wall) and
`first_answer_cpu_s` (CPU seconds of the process, all threads: on a loaded
machine the honest figure) from the call to the answer, split by JAX's
monitoring events into `trace_s` (the outermost
`/jax/core/compile/jaxpr_trace_duration`, which includes nested jits),
`lower_s` (`.../jaxpr_to_mlir_module_duration`), `compile_s` (XLA,
`.../backend_compile_duration`) and `cache_read_s`. With `--staged` the
function is instead put under one outer `jax.jit` and taken through JAX's
stages, each timed (`.trace`, `.lower()`, `.compile()`, the first run), wall
and CPU. `build_s` (making the problem's arrays, including the small eager
computations that takes) and `import_s` (`import jax, eqsmooth`) are
reported beside it. `cache_hits` / `cache_misses` are JAX's events
`/jax/compilation_cache/cache_hits` and `.../cache_misses`;
`not_written_callbacks` counts JAX's log lines "Not writing persistent
cache entry ... because it uses host callbacks" (`jax_explain_cache_misses`
on): JAX neither writes such a program to the persistent cache nor finds it
there (jax `_src/compiler.py`, `_cache_write`), and `eqx.error_if` is a host
callback (a `jax.pure_callback` inside a `lax.cond`).

`--trees LABEL=PATH ...` runs every case with `PYTHONPATH=PATH` per label
(for example the main branch in a git worktree as `before`, this tree as
`after`), alternating labels, so that before and after are measured in the
same command. `--xla-flags LABEL=FLAGS ...` does the same for `XLA_FLAGS`
settings (an empty value: XLA's defaults), labelled in the `tree` column.

    python benchmarks/first_call.py                      # all cases, this tree
    python benchmarks/first_call.py --cases pose2        # one case
    python benchmarks/first_call.py --trees before=/tmp/main after=. \\
        --json benchmarks/results/first_call.json
    python benchmarks/first_call.py --cases pose2 --xla-flags default= \\
        fast=--xla_cpu_use_fusion_emitters=false
    python benchmarks/first_call.py --parts   # pieces of the pose2 solve
"""

import time


_T0 = time.perf_counter()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
from pathlib import Path  # noqa: E402


HERE = Path(__file__).resolve().parent
CASES = ("pose2", "chain1e4", "chain1e5", "train200")


# ----------------------------------------------------------------------------
# The child: one case in this (fresh) process.


def _pose2_case():
    import jax.numpy as jnp
    import numpy as np

    import eqsmooth as eqs

    def poses(xyt):
        xyt = np.asarray(xyt, np.float64)
        return eqs.SE2.from_xy_theta(
            jnp.asarray(xyt[:, 0]), jnp.asarray(xyt[:, 1]), jnp.asarray(xyt[:, 2])
        )

    odo = np.array(
        [
            [2.0, 0.0, 0.0],
            [2.1, 0.05, np.pi / 2],
            [1.9, -0.03, np.pi / 2 + 0.02],
            [2.05, 0.0, np.pi / 2 - 0.03],
            [2.1, 0.1, np.pi / 2 + 0.05],  # loop closure 4 -> 1
        ]
    )
    init = np.array(
        [
            [0.4, 0.1, 0.15],
            [2.3, 0.1, -0.2],
            [4.1, 0.2, np.pi / 2],
            [4.0, 2.1, np.pi],
            [2.1, 2.2, -np.pi / 2],
        ]
    )
    graph = eqs.FactorGraph(
        [
            eqs.PriorFactor(
                eqs.Var("x", [0]),
                poses([[0.0, 0.0, 0.0]]),
                eqs.DiagonalNoise.from_sigmas(jnp.array([0.3, 0.3, 0.1])),
            ),
            eqs.BetweenFactor(
                eqs.Var("x", [0, 1, 2, 3, 4]),
                eqs.Var("x", [1, 2, 3, 4, 1]),
                poses(odo),
                eqs.DiagonalNoise.from_sigmas(jnp.array([0.2, 0.2, 0.1])),
            ),
        ]
    )
    solver = eqs.LevenbergMarquardt()

    def fn(graph, values):
        return eqs.least_squares(graph, values, solver).value

    return fn, (graph, {"x": poses(init)})


def _chain_case(T: int):
    sys.path.insert(0, str(HERE))
    from chain import se2vel_problem

    import eqsmooth as eqs

    graph, values = se2vel_problem(T)
    solver = eqs.GaussNewton()

    def fn(graph, values):
        # 20 steps do not always reach the tolerances from these initial
        # values; the figure here is the time to the first answer.
        return eqs.least_squares(graph, values, solver, max_steps=20, throw=False).value

    return fn, (graph, values)


def _train_case(T: int, K: int = 3):
    sys.path.insert(0, str(HERE))
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    from train_step import BATCH, build_graph, MEAS_SIGMA, simulate

    import eqsmooth as eqs

    dtype = jnp.float64
    truths, meas = simulate(T, BATCH, dtype)
    graphs = eqx.filter_vmap(lambda m: build_graph(m, dtype))(meas)
    theta = jnp.full((2,), 1.0 / MEAS_SIGMA, dtype)
    solver = eqs.FixedStepGaussNewton(eqs.BlockTridiagonal(), num_steps=K)

    def one(theta, graph, truth):
        graph = eqx.tree_at(lambda g: g.factors[1].noise.sqrt_precision, graph, theta)
        x = eqs.least_squares(
            graph,
            {"x": truth},
            solver,
            adjoint=eqs.UnrolledAdjoint(),
            throw=False,
        ).value["x"]
        return jnp.mean((x - truth) ** 2)

    def loss(theta, graphs, truths):
        per = eqx.filter_vmap(one, in_axes=(None, 0, 0))(theta, graphs, truths)
        return jnp.mean(per)

    return jax.value_and_grad(loss), (theta, graphs, truths)


def child(case: str, cache_dir: str | None, staged: bool) -> dict:
    t_import = time.perf_counter()
    import logging

    import equinox as eqx
    import jax

    import eqsmooth  # noqa: F401

    import_s = time.perf_counter() - t_import
    jax.config.update("jax_enable_x64", True)
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
    events.clear()
    durations.clear()
    not_written.clear()

    rec = {"case": case, "import_s": import_s, "build_s": build_s}
    if staged:
        # Every stage timed apart, under one outer jax.jit of the arrays.
        dynamic, static = eqx.partition(args, eqx.is_array)

        def flat(dynamic):
            out = fn(*eqx.combine(dynamic, static))
            return jax.tree_util.tree_leaves(eqx.filter(out, eqx.is_array))

        stages = {}
        c0 = time.process_time()
        t0 = time.perf_counter()
        obj = jax.jit(flat)
        for stage, step in (
            ("trace", lambda o: o.trace(dynamic)),
            ("lower", lambda o: o.lower()),
            ("compile", lambda o: o.compile()),
            ("run", lambda o: jax.block_until_ready(o(dynamic))),
        ):
            t, c = time.perf_counter(), time.process_time()
            obj = step(obj) if stage != "run" else (obj, step(obj))[0]
            stages[stage] = (time.perf_counter() - t, time.process_time() - c)
        first = time.perf_counter() - t0
        first_cpu = time.process_time() - c0
        compiled = obj

        def call():
            return compiled(dynamic)

        for stage, (wall, cpu) in stages.items():
            rec[f"{stage}_s"] = wall
            rec[f"{stage}_cpu_s"] = cpu
    else:
        # As a user calls it: the public API (itself jitted) for a solve, an
        # eqx.filter_jit of value_and_grad for the training step. The split
        # comes from JAX's monitoring events.
        call_fn = eqx.filter_jit(fn) if case.startswith("train") else fn

        def call():
            return call_fn(*args)

        c0 = time.process_time()
        t0 = time.perf_counter()
        jax.block_until_ready(eqx.filter(call(), eqx.is_array))
        first = time.perf_counter() - t0
        first_cpu = time.process_time() - c0
        trace = durations.get("/jax/core/compile/jaxpr_trace_duration", [0.0])
        rec.update(
            # Nested jits are traced inside the outer one: the outermost trace
            # is the longest and includes them.
            trace_s=max(trace),
            lower_s=sum(
                durations.get("/jax/core/compile/jaxpr_to_mlir_module_duration", [])
            ),
            compile_s=sum(
                durations.get("/jax/core/compile/backend_compile_duration", [])
            ),
            cache_read_s=sum(
                durations.get("/jax/compilation_cache/cache_retrieval_time_sec", [])
            ),
            programs_traced=len(trace),
        )
    times = []
    for _ in range(5 if case != "chain1e5" else 3):
        t = time.perf_counter()
        jax.block_until_ready(eqx.filter(call(), eqx.is_array))
        times.append(time.perf_counter() - t)
    rec.update(
        first_answer_s=first,
        first_answer_cpu_s=first_cpu,
        steady_s=statistics.median(times),
        cache_hits=events.get("/jax/compilation_cache/cache_hits", 0),
        cache_misses=events.get("/jax/compilation_cache/cache_misses", 0),
        not_written_callbacks=sum("host callbacks" in m for m in not_written),
        not_written=not_written[:5],
        process_s=time.perf_counter() - _T0,
    )
    return rec


def parts() -> list[dict]:
    """Trace / lower / compile CPU seconds of pieces of the `pose2` solve, one
    process: how much of the whole program the linearisation is."""
    import equinox as eqx
    import jax

    import eqsmooth as eqs
    from eqsmooth.solve._linearization import linearize

    jax.config.update("jax_enable_x64", True)
    _, (graph, values) = _pose2_case()
    lin = jax.jit(linearize)(graph, values)
    gn = eqs.GaussNewton()
    pieces = {
        "linearize alone": (linearize, (graph, values)),
        "one dense normal solve alone": (
            lambda lin: eqs.solve.solve_normal(eqs.DenseCholesky(), lin),
            (lin,),
        ),
        "GaussNewton solve, throw=False": (
            lambda g, v: eqs.least_squares(g, v, gn, throw=False).value,
            (graph, values),
        ),
        "GaussNewton solve, throw=True (error_if under jit)": (
            lambda g, v: eqs.least_squares(g, v, gn).value,
            (graph, values),
        ),
    }
    out = []
    for name, (fn, args) in pieces.items():
        dynamic, static = eqx.partition(args, eqx.is_array)

        def flat(dynamic, fn=fn, static=static):
            res = fn(*eqx.combine(dynamic, static))
            return jax.tree_util.tree_leaves(eqx.filter(res, eqx.is_array))

        c = time.process_time()
        traced = jax.jit(flat).trace(dynamic)
        trace = time.process_time() - c
        c = time.process_time()
        lowered = traced.lower()
        lower = time.process_time() - c
        c = time.process_time()
        lowered.compile()
        compile_ = time.process_time() - c
        rec = {
            "benchmark": "first_call_parts",
            "config": {"case": "pose2", "piece": name},
            "piece": name,
            "trace_cpu_s": trace,
            "lower_cpu_s": lower,
            "compile_cpu_s": compile_,
            "hlo_lines": lowered.as_text().count("\n"),
            "median_s": float("nan"),
        }
        out.append(rec)
        print(
            f"{name:52s} trace {trace:5.2f}  lower {lower:5.2f}  compile "
            f"{compile_:5.2f} CPU s  {rec['hlo_lines']} HLO lines",
            flush=True,
        )
    return out


# ----------------------------------------------------------------------------
# The parent: subprocesses per case, tree and cache state.


def run_child(
    case: str, cache_dir: str | None, tree: str, env_extra: dict, staged: bool
) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(Path(tree).resolve()), str(HERE)])
    env.update(env_extra)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", case]
    if cache_dir:
        cmd += ["--cache-dir", cache_dir]
    if staged:
        cmd += ["--staged"]
    t = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if proc.returncode != 0:
        raise RuntimeError(f"{case} in {tree} failed:\n{proc.stderr[-4000:]}")
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    rec["wall_s"] = wall
    return rec


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--cache-dir", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument(
        "--trees",
        nargs="*",
        default=None,
        help="LABEL=PATH: the source tree each label imports eqsmooth from "
        "(default: this tree, label 'this')",
    )
    parser.add_argument(
        "--env",
        nargs="*",
        default=[],
        help="NAME=VALUE environment settings for the children, e.g. "
        "EQX_ON_ERROR=nan (no host callbacks)",
    )
    parser.add_argument(
        "--xla-flags",
        nargs="*",
        default=None,
        help="LABEL=FLAGS: XLA_FLAGS for the children, one setting per label "
        "(e.g. default= fast=--xla_cpu_use_fusion_emitters=false), each run "
        "with every tree in turn",
    )
    parser.add_argument("--repeats", type=int, default=1, help="cold/warm pairs")
    parser.add_argument(
        "--staged",
        action="store_true",
        help="time trace / lower / compile / run apart under one outer jax.jit "
        "(the default times the public call and splits it by JAX's events)",
    )
    parser.add_argument(
        "--parts",
        action="store_true",
        help="instead: trace/lower/compile CPU seconds of pieces of the pose2 "
        "solve (linearisation, normal solve, whole solve), in this process",
    )
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.parts:
        sys.path.insert(0, str(HERE))
        from _common import write_json

        records = parts()
        if args.json:
            write_json(args.json, records)
        return
    if args.child:
        print(json.dumps(child(args.child, args.cache_dir, args.staged)))
        return
    sys.path.insert(0, str(HERE))
    from _common import machine, markdown_table, write_json

    trees = dict(t.split("=", 1) for t in (args.trees or [f"this={HERE.parent}"]))
    env_extra = dict(e.split("=", 1) for e in args.env)
    flag_sets = dict(f.split("=", 1) for f in (args.xla_flags or []))
    # (label, tree, environment) per variant: every tree with every flag set.
    variants = []
    for tree_label, tree in trees.items():
        if not flag_sets:
            variants.append((tree_label, tree, env_extra))
        for flag_label, flags in flag_sets.items():
            env = {**env_extra, "XLA_FLAGS": flags}
            label = flag_label if len(trees) == 1 else f"{tree_label}/{flag_label}"
            variants.append((label, tree, env))
    records = []
    for case in args.cases:
        for rep in range(args.repeats):
            for label, tree, env in variants:
                with tempfile.TemporaryDirectory(prefix="eqs_jax_cache_") as cache:
                    for state in ("cold", "warm"):
                        rec = run_child(case, cache, tree, env, args.staged)
                        rec.update(
                            benchmark="first_call",
                            config={
                                "case": case,
                                "tree": label,
                                "process": state,
                                "env": env,
                                "staged": args.staged,
                            },
                            tree=label,
                            process=state,
                            repeat=rep,
                            load_average=os.getloadavg(),
                            median_s=rec["steady_s"],
                        )
                        records.append(rec)
                        print(
                            f"{case:9s} {label:7s} {state:5s} first answer "
                            f"{rec['first_answer_s']:6.2f} s, CPU "
                            f"{rec['first_answer_cpu_s']:6.2f} s (trace "
                            f"{rec['trace_s']:5.2f}, lower {rec['lower_s']:5.2f}, "
                            f"XLA compile {rec['compile_s']:5.2f} s wall); steady "
                            f"{rec['steady_s'] * 1e3:8.2f} ms; cache hits/misses "
                            f"{rec['cache_hits']}/{rec['cache_misses']}, not "
                            f"written (callbacks) {rec['not_written_callbacks']}; "
                            f"import {rec['import_s']:.2f} s, build "
                            f"{rec['build_s']:.2f} s",
                            flush=True,
                        )
    print()
    print(
        markdown_table(
            records,
            [
                "case",
                "tree",
                "process",
                "first_answer_s",
                "first_answer_cpu_s",
                "trace_s",
                "lower_s",
                "compile_s",
                "steady_s",
                "cache_hits",
                "cache_misses",
                "not_written_callbacks",
            ],
        )
    )
    if args.json:
        write_json(args.json, records, {"machine_at_start": machine()})


if __name__ == "__main__":
    main()
